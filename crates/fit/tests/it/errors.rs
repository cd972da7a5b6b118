//! How honest the radial fit's error bars are: the covariance against closed forms for a
//! linear model, the three chi^2 scalings (conservative = max(1, chi2_red), scaled = chi2_red,
//! absolute = none) against known true errors, Monte Carlo coverage of the fitted centre, the
//! correlated-errors inflation against a map smoothed with a known kernel, and sector
//! exclusions measured about a fitted, decentred axis.

use crate::common;

use common::*;
use fit::models::radial::Robust;
use fit::{fit_radial, Bin, ErrorScaling, RadialFitOptions};
use nalgebra::{DMatrix, DVector};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

/// Bins on a square grid of `n x n` with step `h` arcmin, centred on the detector centre.
fn grid(n: usize, h: f64) -> Vec<(f64, f64)> {
    let c = 0.5 * (n as f64 - 1.0);
    (0..n * n).map(|k| (((k % n) as f64 - c) * h, ((k / n) as f64 - c) * h)).collect()
}

/// The linear least-squares problem of a fixed-centre radial fit, written out independently:
/// rows `r^k cos 2a`, `r^k sin 2a` (k = 1..3) about the detector centre, weights `1/sigma^2`.
fn design(bins: &[Bin], sigma_q: &[f64], sigma_u: &[f64]) -> (DMatrix<f64>, DVector<f64>) {
    let n = bins.len();
    let mut a = DMatrix::zeros(2 * n, 3);
    let mut y = DVector::zeros(2 * n);
    for (i, b) in bins.iter().enumerate() {
        let r2 = b.x * b.x + b.y * b.y;
        let r = r2.sqrt();
        let (c2, s2) = ((b.x * b.x - b.y * b.y) / r2, 2.0 * b.x * b.y / r2);
        for k in 0..3 {
            let rk = r.powi(k as i32 + 1);
            a[(2 * i, k)] = rk * c2 / sigma_q[i];
            a[(2 * i + 1, k)] = rk * s2 / sigma_u[i];
        }
        y[2 * i] = b.qu.q / sigma_q[i];
        y[2 * i + 1] = b.qu.u / sigma_u[i];
    }
    (a, y)
}

fn linear_opts(mode: ErrorScaling) -> RadialFitOptions {
    RadialFitOptions { robust: Robust::None, error_scaling: mode, ..Default::default() }
}

fn cov_block(m: &fit::RadialModel, n: usize) -> DMatrix<f64> {
    DMatrix::from_fn(n, n, |i, j| m.cov_at(i, j))
}

fn max_rel(a: &DMatrix<f64>, b: &DMatrix<f64>) -> f64 {
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    a.iter().zip(b.iter()).fold(0.0f64, |m, (x, y)| m.max((x - y).abs() / scale))
}

#[test]
fn linear_model_covariance_is_the_inverse_normal_matrix_exactly() {
    // Unequal errors per bin (0.5 to 2 x 1e-4), so that W is not a multiple of the identity.
    let centres: Vec<(f64, f64)> = grid(24, 0.25).into_iter().filter(|(x, y)| x.hypot(*y) > 1e-9).collect();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(21);
    let unit = Normal::new(0.0, 1.0).unwrap();
    let truth = radial_field(&V_COEFFS, (0.0, 0.0));
    let (mut sq, mut su, mut bins) = (vec![], vec![], vec![]);
    for (k, &(x, y)) in centres.iter().enumerate() {
        let (a, b) =
            (1e-4 * (0.5 + 1.5 * ((k * 7) % 11) as f64 / 10.0), 1e-4 * (0.5 + 1.5 * ((k * 3) % 13) as f64 / 12.0));
        let (q, u) = truth(x, y);
        bins.push(Bin::new(x, y, q + a * unit.sample(&mut rng), u + b * unit.sample(&mut rng), a, b));
        sq.push(a);
        su.push(b);
    }
    let (a, y) = design(&bins, &sq, &su);
    let normal_inv = (a.transpose() * &a).try_inverse().unwrap();
    let c_hat = &normal_inv * a.transpose() * &y;
    let resid = &y - &a * &c_hat;
    let chi2_red = resid.norm_squared() / (y.len() - 3) as f64;

    let abs = fit_radial(&bins, &linear_opts(ErrorScaling::Absolute)).unwrap();
    for k in 0..3 {
        assert!(
            (abs.model.coeffs[k] - c_hat[k]).abs() < 1e-9 * c_hat[k].abs(),
            "c{} {} vs {}",
            k + 1,
            abs.model.coeffs[k],
            c_hat[k]
        );
    }
    assert!((abs.chi2_reduced / chi2_red - 1.0).abs() < 1e-9, "{} vs {chi2_red}", abs.chi2_reduced);
    // absolute: (J^T W J)^-1 exactly.
    assert!(max_rel(&cov_block(&abs.model, 3), &normal_inv) < 1e-9);
    // scaled: chi2_red (J^T W J)^-1; conservative: max(1, chi2_red) (J^T W J)^-1.
    let sc = fit_radial(&bins, &linear_opts(ErrorScaling::Scaled)).unwrap();
    assert!(max_rel(&cov_block(&sc.model, 3), &(&normal_inv * chi2_red)) < 1e-9);
    let cons = fit_radial(&bins, &linear_opts(ErrorScaling::Conservative)).unwrap();
    assert!(max_rel(&cov_block(&cons.model, 3), &(&normal_inv * chi2_red.max(1.0))) < 1e-9);
    let s = cons.model.scaling.unwrap();
    assert_eq!(s.mode, ErrorScaling::Conservative);
    assert!((s.chi2_factor - chi2_red.max(1.0)).abs() < 1e-9 && s.correlation_inflation.is_none());
}

#[test]
fn overstated_errors_scaled_recovers_the_truth_absolute_and_conservative_do_not_shrink() {
    // True noise 1e-4, stated 2e-4 (errors overstated by 2): the true covariance of the linear
    // estimate is (A^T W_true A)^-1 with the true errors.
    let centres: Vec<(f64, f64)> = grid(30, 0.2).into_iter().filter(|(x, y)| x.hypot(*y) > 1e-9).collect();
    let n = centres.len();
    let truth_bins = noisy_bins(&centres, radial_field(&I_COEFFS, (0.0, 0.0)), SIGMA_BIN, 22);
    let stated: Vec<Bin> =
        truth_bins.iter().map(|b| Bin::new(b.x, b.y, b.qu.q, b.qu.u, 2.0 * SIGMA_BIN, 2.0 * SIGMA_BIN)).collect();
    let (a, _) = design(&truth_bins, &vec![SIGMA_BIN; n], &vec![SIGMA_BIN; n]);
    let truth = (a.transpose() * &a).try_inverse().unwrap();
    let dof = (2 * n - 3) as f64;
    let ratio = |m: ErrorScaling| {
        let f = fit_radial(&stated, &linear_opts(m)).unwrap();
        (0..3).map(|k| f.model.cov_at(k, k) / truth[(k, k)]).collect::<Vec<f64>>()
    };
    // chi2_red ~ 1/4 +- sqrt(2/dof)/4: scaled recovers the truth within that noise.
    for r in ratio(ErrorScaling::Scaled) {
        assert!((r - 1.0).abs() < 4.0 * (2.0 / dof).sqrt(), "scaled/truth = {r}");
    }
    // absolute keeps the stated errors: 4x the true variance, exactly.
    for r in ratio(ErrorScaling::Absolute) {
        assert!((r - 4.0).abs() < 1e-9, "absolute/truth = {r}");
    }
    // conservative does not shrink below the stated errors either (the price of never
    // claiming more precision than the stated errors allow).
    for r in ratio(ErrorScaling::Conservative) {
        assert!((r - 4.0).abs() < 1e-9, "conservative/truth = {r}");
    }
    // Understated errors (stated 1e-4, true 2e-4): conservative and scaled both recover the
    // truth (chi2_red ~ 4), absolute is 4x too small.
    let loud = noisy_bins(&centres, radial_field(&I_COEFFS, (0.0, 0.0)), 2.0 * SIGMA_BIN, 23);
    let understated: Vec<Bin> = loud.iter().map(|b| Bin::new(b.x, b.y, b.qu.q, b.qu.u, SIGMA_BIN, SIGMA_BIN)).collect();
    let truth4 = &truth * 4.0;
    for (m, want) in [(ErrorScaling::Conservative, 1.0), (ErrorScaling::Scaled, 1.0), (ErrorScaling::Absolute, 0.25)] {
        let f = fit_radial(&understated, &linear_opts(m)).unwrap();
        for k in 0..3 {
            let r = f.model.cov_at(k, k) / truth4[(k, k)];
            assert!((r - want).abs() < 4.0 * want * (2.0 / dof).sqrt(), "{m:?}: {r} vs {want}");
        }
    }
}

#[test]
fn monte_carlo_pulls_of_the_free_centre_have_unit_rms_in_the_default_mode() {
    // 200 independent-noise fields, free centre, default options (Huber, conservative): the
    // pulls (fitted - true) / error of x0 and y0 have unit RMS within its noise
    // (400 pulls: sigma(RMS) ~ 1/sqrt(800) = 0.035).
    let centres = fors1_bin_centres(64);
    let c = (0.15, -0.1);
    let mut pulls = vec![];
    let mut coeff_pulls = vec![];
    for seed in 0..200u64 {
        let bins = noisy_bins(&centres, radial_field(&V_COEFFS, c), SIGMA_BIN, 1000 + seed);
        let f = fit_radial(&bins, &RadialFitOptions { free_centre: true, ..Default::default() }).unwrap();
        assert_eq!(f.model.scaling.unwrap().mode, ErrorScaling::Conservative);
        let e = f.model.centre_errors();
        pulls.push((f.model.centre[0] - c.0) / e[0]);
        pulls.push((f.model.centre[1] - c.1) / e[1]);
        let ce = f.model.coefficient_errors();
        coeff_pulls.extend((0..3).map(|k| (f.model.coeffs[k] - V_COEFFS[k]) / ce[k]));
    }
    let rms = |v: &[f64]| (v.iter().map(|p| p * p).sum::<f64>() / v.len() as f64).sqrt();
    let (r, rc) = (rms(&pulls), rms(&coeff_pulls));
    eprintln!("centre pull RMS {r:.3} over {}, coefficient pull RMS {rc:.3} over {}", pulls.len(), coeff_pulls.len());
    assert!((r - 1.0).abs() < 3.0 / (2.0 * pulls.len() as f64).sqrt(), "centre pull RMS {r}");
    assert!((rc - 1.0).abs() < 3.0 / (2.0 * coeff_pulls.len() as f64).sqrt(), "coefficient pull RMS {rc}");
    let mean = pulls.iter().sum::<f64>() / pulls.len() as f64;
    assert!(mean.abs() < 3.0 / (pulls.len() as f64).sqrt(), "centre pulls biased: mean {mean}");
}

/// White noise smoothed with a normalized Gaussian kernel of `s` bins on an `n x n` grid:
/// returns the noise for q and u and `sum k^2`. The noise is drawn on a padded grid so that every
/// kept bin has its whole kernel (stationary noise, no edge effects).
fn smoothed_noise(n: usize, s: f64, sigma0: f64, seed: u64) -> (Vec<f64>, Vec<f64>, f64) {
    let rad = (4.0 * s).ceil() as isize;
    let mut k = vec![];
    for dj in -rad..=rad {
        for di in -rad..=rad {
            k.push((di, dj, (-((di * di + dj * dj) as f64) / (2.0 * s * s)).exp()));
        }
    }
    let sum: f64 = k.iter().map(|t| t.2).sum();
    k.iter_mut().for_each(|t| t.2 /= sum);
    let k2: f64 = k.iter().map(|t| t.2 * t.2).sum();
    let m = n + 2 * rad as usize;
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let g = Normal::new(0.0, sigma0).unwrap();
    let mut out = vec![];
    for _ in 0..2 {
        let white: Vec<f64> = (0..m * m).map(|_| g.sample(&mut rng)).collect();
        let mut sm = vec![0.0; n * n];
        for j in 0..n {
            for i in 0..n {
                let (ci, cj) = (i as isize + rad, j as isize + rad);
                sm[j * n + i] =
                    k.iter().map(|&(di, dj, w)| w * white[((cj + dj) as usize) * m + (ci + di) as usize]).sum();
            }
        }
        out.push(sm);
    }
    let u = out.pop().unwrap();
    (out.pop().unwrap(), u, k2)
}

#[test]
fn correlated_errors_inflation_recovers_a_known_smoothing_kernel() {
    // A map smoothed with a Gaussian of s = 1.5 bins: neighbouring bins share their noise and
    // the true inflation is tau = 1 / sum k^2 (~ 4 pi s^2 = 28). The stated per-bin errors are
    // the right marginal ones, so chi2_red ~ 1 and only the correlation makes the
    // independent-bin covariance too small.
    let (n, h, s) = (64, 0.1, 1.5);
    let centres = grid(n, h);
    let c = (0.2, -0.1);
    let truth = radial_field(&V_COEFFS, c);
    let mut taus = vec![];
    let (mut pulls, mut naive_pulls) = (vec![], vec![]);
    let mut tau_true = 0.0;
    for seed in 0..24u64 {
        let (nq, nu, k2) = smoothed_noise(n, s, 1.0, 500 + seed);
        tau_true = 1.0 / k2;
        // Marginal sigma of the smoothed noise: sigma0 sqrt(sum k^2); scale it to 1e-4.
        let sigma0 = SIGMA_BIN / k2.sqrt();
        let bins: Vec<Bin> = centres
            .iter()
            .enumerate()
            .map(|(i, &(x, y))| {
                let (q, u) = truth(x, y);
                Bin::new(x, y, q + sigma0 * nq[i], u + sigma0 * nu[i], SIGMA_BIN, SIGMA_BIN)
            })
            .collect();
        let opts = RadialFitOptions { free_centre: true, correlated_errors: true, ..Default::default() };
        let f = fit_radial(&bins, &opts).unwrap();
        let corr = f.correlation.unwrap();
        assert!(corr.resolved, "{corr:?}");
        taus.push(corr.factor);
        let sc = f.model.scaling.unwrap();
        assert_eq!(sc.correlation_inflation, Some(corr.factor));
        let e = f.model.centre_errors();
        let naive = (sc.chi2_factor * (e[0] * e[0] / sc.total())).sqrt().max(1e-300);
        let naive_y = (sc.chi2_factor * (e[1] * e[1] / sc.total())).sqrt().max(1e-300);
        pulls.push((f.model.centre[0] - c.0) / e[0]);
        pulls.push((f.model.centre[1] - c.1) / e[1]);
        naive_pulls.push((f.model.centre[0] - c.0) / naive);
        naive_pulls.push((f.model.centre[1] - c.1) / naive_y);
    }
    let nt = taus.len() as f64;
    let mean = taus.iter().sum::<f64>() / nt;
    let sd = (taus.iter().map(|t| (t - mean).powi(2)).sum::<f64>() / (nt - 1.0)).sqrt();
    let rms = |v: &[f64]| (v.iter().map(|p| p * p).sum::<f64>() / v.len() as f64).sqrt();
    let (rp, rn) = (rms(&pulls), rms(&naive_pulls));
    eprintln!(
        "tau true {tau_true:.2} (4 pi s^2 = {:.2}); estimated {mean:.2} +- {sd:.2} per map; centre pull RMS {rp:.3} \
         inflated, {rn:.3} as if independent",
        4.0 * std::f64::consts::PI * s * s
    );
    // The estimate recovers the kernel's factor within its noise (3 standard errors of the
    // mean), and each map's estimate within 4 of its own standard deviations.
    assert!((mean - tau_true).abs() < 3.0 * sd / nt.sqrt(), "tau {mean} +- {} vs {tau_true}", sd / nt.sqrt());
    assert!(taus.iter().all(|t| (t - tau_true).abs() < 4.0 * sd), "{taus:?}");
    // With it, the centre's pulls have unit RMS (48 pulls: sigma(RMS) ~ 0.1); without it they
    // are about sqrt(tau) ~ 5 times too large.
    assert!((rp - 1.0).abs() < 0.3, "inflated centre pull RMS {rp}");
    assert!(rn > 3.0, "independent-bin centre pull RMS {rn}");
}

#[test]
fn sectors_are_measured_about_the_fitted_centre_of_a_decentred_axis() {
    // Axis at (0.30, -0.15) arcmin: 100 px in x from the detector centre (FORS1, 0.2"/px).
    // The bins at polar angle 10..80 deg about the true axis are disturbed (as the paper's
    // V-band sector); sector:10:80 must drop exactly those.
    let c = (100.0 * 0.2 / 60.0, -0.15);
    let truth = radial_field(&V_COEFFS, c);
    let in_sector = |x: f64, y: f64, cx: f64, cy: f64| {
        let a = (y - cy).atan2(x - cx).to_degrees();
        (10.0..=80.0).contains(&a)
    };
    let disturbed = |x: f64, y: f64| {
        let (q, u) = truth(x, y);
        if in_sector(x, y, c.0, c.1) {
            (q + 0.003, u)
        } else {
            (q, u)
        }
    };
    let centres = fors1_bin_centres(30);
    let bins = noisy_bins(&centres, disturbed, SIGMA_BIN, 31);
    let opts =
        RadialFitOptions { free_centre: true, exclusions: vec!["sector:10:80".parse().unwrap()], ..Default::default() };
    let f = fit_radial(&bins, &opts).unwrap();
    let bin_arcmin = 30.0 * 0.2 / 60.0;
    let (dx, dy) = (f.model.centre[0] - c.0, f.model.centre[1] - c.1);
    assert!(dx.hypot(dy) < 0.1 * bin_arcmin, "centre {:?} vs {c:?}", f.model.centre);
    let errs = f.model.coefficient_errors();
    for k in 0..3 {
        let z = (f.model.coeffs[k] - V_COEFFS[k]) / errs[k];
        assert!(z.abs() < 4.0, "c{} {z} sigma", k + 1);
    }
    assert!(f.chi2_reduced < 1.2, "chi2 {}", f.chi2_reduced);
    // The membership was recomputed about the fitted centre and settled there.
    assert!(f.passes >= 2, "passes {}", f.passes);
    assert!((f.exclusion_centre[0] - f.model.centre[0]).hypot(f.exclusion_centre[1] - f.model.centre[1]) < 0.01);
    let about = |cx: f64, cy: f64| centres.iter().map(|&(x, y)| !in_sector(x, y, cx, cy)).collect::<Vec<bool>>();
    assert_eq!(f.used, about(f.exclusion_centre[0], f.exclusion_centre[1]));
    // About the detector centre the sector would take other bins: many of them differ.
    let old = about(0.0, 0.0);
    let differ = old.iter().zip(&f.used).filter(|(a, b)| a != b).count();
    assert!(differ > 100, "only {differ} bins differ");
    // ... and that old membership keeps disturbed bins in the fit: a visibly bad fit.
    let old_bins: Vec<Bin> = bins
        .iter()
        .zip(&old)
        .map(|(b, keep)| {
            if *keep {
                *b
            } else {
                let mut bad = *b;
                bad.qu.var_q = f64::NAN;
                bad
            }
        })
        .collect();
    let g = fit_radial(&old_bins, &RadialFitOptions { free_centre: true, ..Default::default() }).unwrap();
    let ge = g.model.coefficient_errors();
    let worst = (0..3).map(|k| ((g.model.coeffs[k] - V_COEFFS[k]) / ge[k]).abs()).fold(0.0, f64::max);
    eprintln!(
        "sector about the detector centre: rms {:.2e}, chi2 {:.1}, worst coefficient {worst:.1} sigma",
        g.rms_residual, g.chi2_reduced
    );
    assert!(
        g.rms_residual > 2.0 * SIGMA_BIN && g.chi2_reduced > 4.0,
        "old-style rms {} chi2 {}",
        g.rms_residual,
        g.chi2_reduced
    );
    assert!(worst > 4.0, "old-style coefficients within {worst} sigma");
}
