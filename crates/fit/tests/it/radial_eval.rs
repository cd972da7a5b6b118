//! The allocation-free `RadialModel::eval` (Horner in r, the coefficient block of the
//! covariance as the variance of p(r), the centre terms only for a fitted centre) against a
//! straightforward reference written here: the gradient of `q = p(r) cos 2 alpha`,
//! `u = p(r) sin 2 alpha` with respect to `(c..., x0, y0)` in full vectors with `powi`, and the
//! full `g^T C g` double loop over all parameters.
//!
//! "Identical" means equal to rounding: the difference is at most 1e-14 of the size of the
//! terms that are summed (`sum |c_k| r^k` for q and u, `sum |h_i h_j C_ij|` with
//! `h_i = |(dq, du)/dparam_i|` for the covariance), which is what two orders of the same sum,
//! and the angle computed two ways (`atan2` here, `dx^2 - dy^2` over `r^2` there), can differ
//! by; the plain relative difference is printed too (large only where q or u, or their
//! variance, pass through zero with the angle).

use fit::models::pipeline::{calibrate_bins, CalibrateOptions, CalibrationMeta};
use fit::{FieldModel, InstPol, RadialModel};
use rand::{RngExt, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;

/// The reference: `(InstPol, scale of q/u, scale of var_q, var_u, cov_qu)`.
fn reference(m: &RadialModel, x: f64, y: f64) -> (InstPol, f64, [f64; 3]) {
    let nc = m.coeffs.len();
    let n = nc + 2;
    let (mut gq, mut gu) = (vec![0.0; n], vec![0.0; n]);
    let (dx, dy) = (x - m.centre[0], y - m.centre[1]);
    let r = dx.hypot(dy);
    let (q, u, pabs);
    if r < 1e-12 {
        if m.first_power == 0 {
            gq[0] = 1.0;
            (q, u, pabs) = (m.coeffs[0], 0.0, m.coeffs[0].abs());
        } else {
            (q, u, pabs) = (0.0, 0.0, 0.0);
        }
    } else {
        let alpha = dy.atan2(dx);
        let (c2, s2) = ((2.0 * alpha).cos(), (2.0 * alpha).sin());
        let (mut p, mut dp, mut pa) = (0.0, 0.0, 0.0);
        for (i, c) in m.coeffs.iter().enumerate() {
            let k = (m.first_power + i) as i32;
            p += c * r.powi(k);
            pa += (c * r.powi(k)).abs();
            if k > 0 {
                dp += c * k as f64 * r.powi(k - 1);
            }
            gq[i] = r.powi(k) * c2;
            gu[i] = r.powi(k) * s2;
        }
        // d alpha / d dx = -dy / r^2, d alpha / d dy = dx / r^2; d/dx0 = -d/ddx.
        let (ax, ay) = (-dy / (r * r), dx / (r * r));
        gq[nc] = -(dp * dx / r * c2 - 2.0 * p * s2 * ax);
        gq[nc + 1] = -(dp * dy / r * c2 - 2.0 * p * s2 * ay);
        gu[nc] = -(dp * dx / r * s2 + 2.0 * p * c2 * ax);
        gu[nc + 1] = -(dp * dy / r * s2 + 2.0 * p * c2 * ay);
        (q, u, pabs) = (p * c2, p * s2, pa);
    }
    let (mut vq, mut vu, mut cqu, mut scale) = (0.0, 0.0, 0.0, 0.0);
    for i in 0..n {
        for j in 0..n {
            let c = m.cov[i * n + j];
            vq += gq[i] * gq[j] * c;
            vu += gu[i] * gu[j] * c;
            cqu += gq[i] * gu[j] * c;
            // The size of the terms whatever the direction: near cos 2 alpha = 0 the variance of
            // q is tiny and carries the rounding of the angle times the full amplitude.
            scale += (gq[i].hypot(gu[i]) * gq[j].hypot(gu[j]) * c).abs();
        }
    }
    (InstPol { q, u, var_q: vq.max(0.0), var_u: vu.max(0.0), cov_qu: cqu }, pabs, [scale; 3])
}

/// Largest difference in units of the term scale, and largest plain relative difference.
#[derive(Default, Debug)]
struct Worst {
    scaled: f64,
    relative: f64,
    n: usize,
}

fn compare(m: &RadialModel, x: f64, y: f64, w: &mut Worst, label: &str) {
    let got = m.eval(x, y);
    let (want, pabs, sc) = reference(m, x, y);
    for (what, a, b, s) in [
        ("q", got.q, want.q, pabs),
        ("u", got.u, want.u, pabs),
        ("var_q", got.var_q, want.var_q, sc[0]),
        ("var_u", got.var_u, want.var_u, sc[1]),
        ("cov_qu", got.cov_qu, want.cov_qu, sc[2]),
    ] {
        let d = (a - b).abs();
        let scaled = if s > 0.0 { d / s } else { d };
        assert!(
            scaled <= 1e-14,
            "{label}: {what} at ({x}, {y}): eval {a:e}, reference {b:e}, difference {d:e} = {scaled:e} of the terms' size {s:e}"
        );
        w.scaled = w.scaled.max(scaled);
        // Plain relative difference where the value is not itself a cancellation (>= 1e-3 of
        // the terms' size).
        if b.abs() >= 1e-3 * s && b != 0.0 {
            w.relative = w.relative.max(d / b.abs());
        }
        w.n += 1;
    }
    // And qu() agrees with eval().
    let (q, u) = m.qu(x, y);
    assert!(
        (q - got.q).abs() <= 1e-15 * pabs && (u - got.u).abs() <= 1e-15 * pabs,
        "{label}: qu() differs from eval()"
    );
}

/// Random positions over the FORS1 field (+-3.5'), plus the centre itself and points next to it.
fn positions(m: &RadialModel, rng: &mut Xoshiro256PlusPlus) -> Vec<(f64, f64)> {
    let mut v: Vec<(f64, f64)> =
        (0..2000).map(|_| (rng.random_range(-3.5..3.5), rng.random_range(-3.5..3.5))).collect();
    let [cx, cy] = m.centre;
    v.extend([(cx, cy), (cx + 1e-9, cy), (cx, cy - 1e-6), (cx + 0.3, cy), (cx, cy + 0.3), (cx + 0.2, cy + 0.2)]);
    v
}

/// A radial3 calibration fitted to the V pattern of section `sec:fors1` (a real, correlated
/// coefficient covariance), decentred by (0.12, -0.08)', centre fixed or fitted.
fn fitted(free_centre: bool) -> RadialModel {
    let truth = RadialModel::new(1, vec![0.012e-2, 0.046e-2, 0.002e-2], [0.12, -0.08]);
    let centres = fit::models::synth::bin_centres(2048, 2048, 0.2, 128);
    let bins: Vec<fit::Bin> = fit::models::synth::sky_field(&centres, &truth, 0.0, 0.0, 2e-5, 11)
        .iter()
        .map(|b| fit::Bin::new(b.x, b.y, b.qu.q, b.qu.u, b.qu.sigma_q(), b.qu.sigma_u()))
        .collect();
    let meta = CalibrationMeta {
        instrument: "FORS1".into(),
        filter: "V".into(),
        lambda_nm: 554.0,
        hwp_chi_offset_deg: 0.0,
        pixel: None,
        provenance: fit::files::calfile::Provenance::now("test", vec![]),
    };
    let mut opts = CalibrateOptions::default();
    opts.fit.free_centre = free_centre;
    let run = calibrate_bins(bins, meta, &opts).unwrap();
    // Through the calibration file's model, as `instpol correct` evaluates it.
    match run.calibration.model {
        fit::Model::Radial(m) => m,
        other => panic!("expected a radial model, got {}", other.kind()),
    }
}

/// A random symmetric positive-definite covariance `A A^T` (the centre block zero when fixed).
fn random_model(rng: &mut Xoshiro256PlusPlus, first_power: usize, nc: usize, free: bool) -> RadialModel {
    let coeffs: Vec<f64> = (0..nc).map(|_| rng.random_range(-0.02..0.02)).collect();
    let mut m = RadialModel::new(first_power, coeffs, [rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3)]);
    m.centre_free = free;
    let n = m.n_params();
    let k = if free { n } else { nc };
    let a: Vec<f64> = (0..k * k).map(|_| rng.random_range(-1e-3..1e-3)).collect();
    for i in 0..k {
        for j in 0..k {
            m.cov[i * n + j] = (0..k).map(|l| a[i * k + l] * a[j * k + l]).sum();
        }
    }
    m
}

#[test]
fn fast_eval_equals_the_reference_for_fitted_models() {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(3);
    for free in [false, true] {
        let m = fitted(free);
        assert_eq!(m.centre_free, free);
        let n = m.n_params();
        let coeff_cov = (0..3).flat_map(|i| (0..3).map(move |j| (i, j))).filter(|(i, j)| i != j);
        assert!(coeff_cov.map(|(i, j)| m.cov[i * n + j].abs()).fold(0.0, f64::max) > 0.0, "no correlations");
        if free {
            assert!(m.cov[(n - 1) * n + n - 1] > 0.0, "free centre without a centre variance");
        }
        let mut w = Worst::default();
        for (x, y) in positions(&m, &mut rng) {
            compare(&m, x, y, &mut w, if free { "fitted, free centre" } else { "fitted, fixed centre" });
        }
        println!("fitted model, free centre {free}: {w:?}");
    }
}

#[test]
fn fast_eval_equals_the_reference_for_random_models() {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(17);
    let mut w = Worst::default();
    for first_power in [0, 1] {
        for nc in 1..=9 {
            for free in [false, true] {
                let m = random_model(&mut rng, first_power, nc, free);
                for (x, y) in positions(&m, &mut rng).into_iter().step_by(8) {
                    compare(&m, x, y, &mut w, &format!("random f={first_power} nc={nc} free={free}"));
                }
            }
        }
    }
    println!("random models: {w:?}");
    // A model without covariance (a simulation's truth) has zero variance everywhere.
    let m = RadialModel::new(1, vec![0.012e-2, 0.046e-2, 0.002e-2], [0.0, 0.0]);
    let a = m.eval(2.0, -1.0);
    assert_eq!((a.var_q, a.var_u, a.cov_qu), (0.0, 0.0, 0.0));
}
