//! Speed of the joint Mueller-field fit (the target: three fields of 2700 bins in under a
//! second). Run: `cargo bench -p instpol-fit --features bench --bench mueller_field`. Side by side:
//! - `forward_pass`: one evaluation of the forward model (`LinearBlock::forward`) at every
//!   observation of the three fields, the bound: a Gauss-Newton iteration needs at least
//!   `1 + 2 n_free` such passes (value and central differences);
//! - `joint_deg4`, `joint_deg6`: the smooth fit (diattenuation + retardance vector, each a
//!   degree-4 / degree-6 polynomial: 60 / 112 coefficients);
//! - `per_bin`: 2700 independent 4-parameter fits (rayon);
//! - `radial_deg4_from_bins`, `interp_from_bins`: the radial and interpolant smooth forms
//!   built from those per-bin fits (`fit::mueller_field::smooth`), on top of `per_bin`.

use criterion::{criterion_group, criterion_main, Criterion};
use fit::mueller_field::{fit_mueller_field, fit_per_bin, CalField, Kind, MuellerFitOptions, Observation};
use mueller::linear::{physical_block, retardance_vector};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;
use std::hint::black_box;

fn truth(x: f64, y: f64) -> mueller::linear::LinearBlock {
    let (dx, dy) = (x - 0.8, y + 0.4);
    let delta = 18f64.to_radians() * (dx * dx + dy * dy) / (3.4 * 3.4);
    physical_block(2e-4 * (x * x - y * y), 4e-4 * x * y, retardance_vector(delta, dy.atan2(dx)), 0.0, 0.0)
}

fn fields() -> Vec<CalField> {
    let skies = [(0.0645, 68.4f64), (0.04, 10.0), (0.08, 130.0)];
    let n = Normal::new(0.0, 3e-4).unwrap();
    skies
        .iter()
        .enumerate()
        .map(|(k, &(p, chi))| {
            let mut rng = Xoshiro256PlusPlus::seed_from_u64(k as u64);
            let chi = chi.to_radians();
            let (q0, u0) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
            let mut obs = Vec::new();
            for j in 0..45 {
                for i in 0..60 {
                    let (x, y) = (-3.4 + 6.8 * (i as f64 + 0.5) / 60.0, -3.4 + 6.8 * (j as f64 + 0.5) / 45.0);
                    let (q, u) = truth(x, y).forward(q0, u0).unwrap();
                    obs.push(Observation::new(x, y, q + n.sample(&mut rng), u + n.sample(&mut rng), 9e-8, 9e-8, 0.0));
                }
            }
            CalField::from_p_chi(&format!("sky{k}"), p, chi, 0.0, obs)
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let f = fields();
    let mut g = c.benchmark_group("mueller_field");
    g.sample_size(10);
    g.bench_function("forward_pass", |b| {
        b.iter(|| {
            let mut s = 0.0;
            for fl in &f {
                for o in &fl.obs {
                    let (q, u) = truth(o.x_arcmin, o.y_arcmin).forward(fl.sky_q, fl.sky_u).unwrap();
                    s += q + u;
                }
            }
            black_box(s)
        })
    });
    let o = MuellerFitOptions { kind: Kind::diattenuation_retardance(), ..Default::default() };
    g.bench_function("joint_deg4", |b| {
        b.iter(|| black_box(fit_mueller_field(&f, &MuellerFitOptions { deg: 4, ..o }).unwrap()))
    });
    g.bench_function("joint_deg6", |b| {
        b.iter(|| black_box(fit_mueller_field(&f, &MuellerFitOptions { deg: 6, ..o }).unwrap()))
    });
    g.bench_function("per_bin", |b| b.iter(|| black_box(fit_per_bin(&f, &o).unwrap())));
    // The other smooth forms, from the per-bin fits (their cost on top of `per_bin`).
    let (bins, _) = fit_per_bin(&f, &o).unwrap();
    g.bench_function("radial_deg4_from_bins", |b| {
        b.iter(|| black_box(fit::mueller_field::smooth::radial_field(&bins, 4).unwrap()))
    });
    g.bench_function("interp_from_bins", |b| {
        b.iter(|| black_box(fit::mueller_field::smooth::interp_field(&bins).unwrap()))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
