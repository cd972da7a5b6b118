//! Sky fields seen through a given Mueller field, for the smooth-form tests: three skies of
//! different P and chi (the B sky of the paper's Table tab:empty and two others), measured on
//! an `n x n` grid of bins with Gaussian noise. Separate from `mueller_cal.rs`'s own fixture
//! (the two are not yet one); the truth is a closure here.

use fit::mueller_field::{CalField, Observation};
use mueller::linear::LinearBlock;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

/// The skies: (P fraction, chi deg).
pub const SKIES: [(f64, f64); 3] = [(0.0645, 68.4), (0.04, 10.0), (0.08, 130.0)];

/// Bin centres of an `n x n` grid over `[-half, half]^2` arcmin.
pub fn grid(n: usize, half: f64) -> Vec<(f64, f64)> {
    let step = 2.0 * half / (n - 1) as f64;
    (0..n * n).map(|i| ((i % n) as f64 * step - half, (i / n) as f64 * step - half)).collect()
}

/// The three sky fields through `truth` on `grid(n, half)`, noise `s` on each of q, u.
pub fn fields(truth: &dyn Fn(f64, f64) -> LinearBlock, n: usize, half: f64, s: f64, seed: u64) -> Vec<CalField> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let g = Normal::new(0.0, 1.0).unwrap();
    SKIES
        .iter()
        .enumerate()
        .map(|(k, &(p, chi))| {
            let c = 2.0 * chi.to_radians();
            let obs = grid(n, half)
                .into_iter()
                .map(|(x, y)| {
                    let (q, u) = truth(x, y).forward(p * c.cos(), p * c.sin()).unwrap();
                    Observation::new(x, y, q + s * g.sample(&mut rng), u + s * g.sample(&mut rng), s * s, s * s, 0.0)
                })
                .collect();
            CalField::from_p_chi(&format!("sky{k}.fits"), p, chi.to_radians(), 0.0, obs)
        })
        .collect()
}
