//! Synthetic binned fields for the tests: the bins of a FORS1-like 2048 x 2048 px detector
//! (0.2"/px) in 30 x 30 px bins (section `sec:fors1`), with Gaussian noise per bin.
#![allow(dead_code)]

pub mod given;
pub mod mueller_fields;
pub mod shared_data;

use fit::Bin;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

/// Per-bin noise of the paper's data: SNR >= 200 per pixel gives ~0.3% per pixel in p
/// (section `sec:fors1`), i.e. ~0.3% / 30 = 0.01% for the mean of a 30 x 30 px bin.
pub const SIGMA_BIN: f64 = 1e-4;

/// Bin centres (arcmin from the detector centre) of `bin_px` bins on FORS1's detector.
pub fn fors1_bin_centres(bin_px: usize) -> Vec<(f64, f64)> {
    let n = 2048 / bin_px;
    let s = 0.2 / 60.0;
    let mut v = vec![];
    for j in 0..n {
        for i in 0..n {
            let (px, py) =
                ((i * bin_px) as f64 + 0.5 * bin_px as f64 - 0.5, (j * bin_px) as f64 + 0.5 * bin_px as f64 - 0.5);
            v.push(((px - 1023.5) * s, (py - 1023.5) * s));
        }
    }
    v
}

/// Bins of the field `truth(x, y) -> (q, u)` with Gaussian noise `sigma` per component.
pub fn noisy_bins(centres: &[(f64, f64)], truth: impl Fn(f64, f64) -> (f64, f64), sigma: f64, seed: u64) -> Vec<Bin> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let n = Normal::new(0.0, sigma).unwrap();
    centres
        .iter()
        .map(|&(x, y)| {
            let (q, u) = truth(x, y);
            Bin::new(x, y, q + n.sample(&mut rng), u + n.sample(&mut rng), sigma, sigma)
        })
        .collect()
}

/// The paper's V-band pattern (section `sec:fors1`), coefficients as fractions (the paper's
/// polynomial gives percent: 1.4% at the corner).
pub const V_COEFFS: [f64; 3] = [0.012e-2, 0.046e-2, 0.002e-2];
/// The paper's I-band pattern.
pub const I_COEFFS: [f64; 3] = [-0.017e-2, 0.105e-2, -0.006e-2];

/// Radial field `p(r) (cos 2 alpha, sin 2 alpha)` about `centre`.
pub fn radial_field(coeffs: &[f64], centre: (f64, f64)) -> impl Fn(f64, f64) -> (f64, f64) + '_ {
    move |x, y| {
        let (dx, dy) = (x - centre.0, y - centre.1);
        let r = dx.hypot(dy);
        let p: f64 = coeffs.iter().enumerate().map(|(i, c)| c * r.powi(i as i32 + 1)).sum();
        let a = dy.atan2(dx);
        (p * (2.0 * a).cos(), p * (2.0 * a).sin())
    }
}

/// A Jones calculus written for the tests, independent of `mueller`: 2x2 complex matrices
/// acting on the field components `(Ex, Ey)`.
pub mod jones {
    pub use num_complex::Complex64 as C;
    pub type J = [[C; 2]; 2];

    pub fn mul(a: &J, b: &J) -> J {
        let mut o = [[C::new(0.0, 0.0); 2]; 2];
        for i in 0..2 {
            for j in 0..2 {
                o[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j];
            }
        }
        o
    }

    /// Field components in axes turned by t.
    pub fn rot(t: f64) -> J {
        let (s, c) = t.sin_cos();
        [[C::new(c, 0.0), C::new(s, 0.0)], [C::new(-s, 0.0), C::new(c, 0.0)]]
    }
}
