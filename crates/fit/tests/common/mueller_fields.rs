//! Simulated Mueller-field calibration fields: sky fields of known `(p, chi)` seen
//! through a known block at bin centres, with Gaussian noise per bin. One copy for fit's tests
//! (`common::mueller_fields`: not `mueller`, which would shadow the crate under
//! `use common::*`) and sim's (`#[path = "../../fit/tests/common/mueller_fields.rs"]`), so it
//! uses nothing from `super`.
#![allow(dead_code)]

use fit::mueller_field::{CalField, Observation};
use mueller::linear::{physical_block, retardance_vector, LinearBlock};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

/// The paper's B sky (tab:empty) and two other sky fields at other helio-ecliptic positions:
/// `(p, chi_deg)`.
pub const SKIES: [(f64, f64); 3] = [(0.0645, 68.4), (0.040, 10.0), (0.080, 130.0)];
/// Noise per bin and Stokes component.
pub const SIGMA: f64 = 3e-4;

/// The FORS1 B stressed lens: 18 deg at the edge, 3.4' radius, centre off axis (about 0.3 % on
/// the B sky).
pub const LENS_EDGE_DEG: f64 = 18.0;
pub const LENS_RADIUS_ARCMIN: f64 = 3.4;
pub const LENS_CENTRE_ARCMIN: [f64; 2] = [0.8, -0.4];

/// Centres of `nx` x `ny` bins over the FORS1 6.8' x 6.8' field (arcmin from its centre).
pub fn fors1_grid(nx: usize, ny: usize) -> Vec<(f64, f64)> {
    let mut v = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            v.push((-3.4 + 6.8 * (i as f64 + 0.5) / nx as f64, -3.4 + 6.8 * (j as f64 + 0.5) / ny as f64));
        }
    }
    v
}

/// Diattenuation of the paper's radial form: p = 2e-4 r^2, phi = polar angle.
pub fn diat(x: f64, y: f64) -> (f64, f64) {
    (2e-4 * (x * x - y * y), 2e-4 * 2.0 * x * y)
}

/// The paper's diattenuation then a stressed lens of `edge_deg` at `LENS_RADIUS_ARCMIN` about
/// `centre` with its axis turned by `axis_deg` (the order of mueller::linear's physical form).
pub fn diat_and_lens(x: f64, y: f64, edge_deg: f64, centre: [f64; 2], axis_deg: f64) -> LinearBlock {
    let (qd, ud) = diat(x, y);
    let (d, ax) =
        mueller::causes::stressed_lens(x, y, edge_deg.to_radians(), LENS_RADIUS_ARCMIN, centre, axis_deg.to_radians());
    physical_block(qd, ud, retardance_vector(d, ax), 0.0, 0.0)
}

/// The FORS1 B truth: the paper's diattenuation and the B stressed lens, axis unturned.
pub fn b_truth(x: f64, y: f64) -> LinearBlock {
    diat_and_lens(x, y, LENS_EDGE_DEG, LENS_CENTRE_ARCMIN, 0.0)
}

/// One calibration field named `name` of sky `(p, chi_deg)`: at each of `grid`, the measured
/// `(q, u)` are `meas(x, y, q_sky, u_sky)` plus Gaussian noise `sigma` drawn from `rng`
/// (q then u, bin after bin).
pub fn cal_field(
    name: &str,
    p: f64,
    chi_deg: f64,
    grid: &[(f64, f64)],
    meas: &dyn Fn(f64, f64, f64, f64) -> (f64, f64),
    sigma: f64,
    rng: &mut Xoshiro256PlusPlus,
) -> CalField {
    let chi = chi_deg.to_radians();
    let (q0, u0) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
    let n = Normal::new(0.0, sigma).unwrap();
    let obs = grid
        .iter()
        .map(|&(x, y)| {
            let (q, u) = meas(x, y, q0, u0);
            Observation::new(x, y, q + n.sample(rng), u + n.sample(rng), sigma * sigma, sigma * sigma, 0.0)
        })
        .collect();
    CalField::from_p_chi(name, p, chi, 0.0, obs)
}

/// Sky field `k` of `SKIES`, named `sky{k}`, noise `SIGMA` from the seed `seed + k`.
pub fn sky_field(
    k: usize,
    grid: &[(f64, f64)],
    meas: &dyn Fn(f64, f64, f64, f64) -> (f64, f64),
    seed: u64,
) -> CalField {
    let (p, chi_deg) = SKIES[k];
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed + k as u64);
    cal_field(&format!("sky{k}"), p, chi_deg, grid, meas, SIGMA, &mut rng)
}

/// The first `n` sky fields of `SKIES` (`sky_field` each).
pub fn sky_fields(
    n: usize,
    grid: &[(f64, f64)],
    meas: &dyn Fn(f64, f64, f64, f64) -> (f64, f64),
    seed: u64,
) -> Vec<CalField> {
    (0..n).map(|k| sky_field(k, grid, meas, seed)).collect()
}

/// `block(x, y)` as a measurement: the sky through the block's forward model.
pub fn through(block: impl Fn(f64, f64) -> LinearBlock) -> impl Fn(f64, f64, f64, f64) -> (f64, f64) {
    move |x, y, q, u| block(x, y).forward(q, u).unwrap()
}
