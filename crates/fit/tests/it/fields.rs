//! Field models on simulated fields (section `sec:fors1`): recovery of the paper's V and I
//! patterns, the free optical-axis centre, the B-band residual interpolant, and bad input.

use crate::common;

use common::*;
use fit::models::polar::polar_angle_test;
use fit::{fit_radial, Error, FieldModel, RadialFitOptions};

fn check_recovery(coeffs: &[f64; 3], seed: u64) {
    let bins = noisy_bins(&fors1_bin_centres(30), radial_field(coeffs, (0.0, 0.0)), SIGMA_BIN, seed);
    let fit = fit_radial(&bins, &RadialFitOptions::default()).unwrap();
    let errs = fit.model.coefficient_errors();
    for k in 0..3 {
        let z = (fit.model.coeffs[k] - coeffs[k]) / errs[k];
        assert!(
            z.abs() < 4.0,
            "c{} = {} +- {} vs input {} ({z} sigma)",
            k + 1,
            fit.model.coeffs[k],
            errs[k],
            coeffs[k]
        );
    }
    // Residual RMS: the paper reaches ~0.05%; with 0.01% bins the fit sits at the noise.
    assert!(fit.rms_residual < 5e-4 && (fit.rms_residual / SIGMA_BIN - 1.0).abs() < 0.1, "{}", fit.rms_residual);
    assert!((fit.chi2_reduced - 1.0).abs() < 0.1, "chi2 {}", fit.chi2_reduced);
    let mut used = bins.clone();
    for (b, u) in used.iter_mut().zip(&fit.used) {
        b.used = *u;
    }
    let t = polar_angle_test(&used, fit.model.centre, 0.5).unwrap();
    assert!(
        ((t.slope - 1.0) / t.slope_err).abs() < 4.0 && (t.slope - 1.0).abs() < 0.01,
        "slope {} +- {}",
        t.slope,
        t.slope_err
    );
    assert!(t.intercept_deg.abs() < 4.0 * t.intercept_err_deg + 0.05, "{}", t.intercept_deg);
}

#[test]
fn recovers_paper_v_band_polynomial_sec_fors1() {
    check_recovery(&V_COEFFS, 1);
}

#[test]
fn recovers_paper_i_band_polynomial_sec_fors1() {
    check_recovery(&I_COEFFS, 2);
}

#[test]
fn free_centre_finds_a_decentred_axis_and_fixed_centre_fails() {
    // Axis decentred by (0.35, -0.25) arcmin (105 and 75 px, several 30 px bins).
    let c = (0.35, -0.25);
    let bins = noisy_bins(&fors1_bin_centres(30), radial_field(&V_COEFFS, c), SIGMA_BIN, 3);
    let fixed = fit_radial(&bins, &RadialFitOptions::default()).unwrap();
    let free = fit_radial(&bins, &RadialFitOptions { free_centre: true, ..Default::default() }).unwrap();
    let bin_arcmin = 30.0 * 0.2 / 60.0;
    let (dx, dy) = (free.model.centre[0] - c.0, free.model.centre[1] - c.1);
    assert!(dx.hypot(dy) < 0.1 * bin_arcmin, "free centre {:?}", free.model.centre);
    let ce = free.model.centre_errors();
    assert!((dx / ce[0]).abs() < 4.0 && (dy / ce[1]).abs() < 4.0, "{dx} +- {} {dy} +- {}", ce[0], ce[1]);
    // The fixed-centre fit visibly fails: residuals far above the noise, chi2 >> 1.
    assert!(
        fixed.rms_residual > 5.0 * SIGMA_BIN && fixed.chi2_reduced > 20.0,
        "fixed: rms {} chi2 {}",
        fixed.rms_residual,
        fixed.chi2_reduced
    );
    assert!((free.rms_residual / SIGMA_BIN - 1.0).abs() < 0.1 && (free.chi2_reduced - 1.0).abs() < 0.1);
    let errs = free.model.coefficient_errors();
    for k in 0..3 {
        assert!(((free.model.coeffs[k] - V_COEFFS[k]) / errs[k]).abs() < 4.0);
    }
}

#[test]
fn v_band_sector_exclusion_drops_a_disturbed_region() {
    // A disturbance in the 10-80 deg sector (the paper's V band) biases the plain fit; the
    // exclusion removes it.
    let truth = radial_field(&V_COEFFS, (0.0, 0.0));
    let disturbed = |x: f64, y: f64| {
        let (q, u) = truth(x, y);
        let a = y.atan2(x).to_degrees();
        if (10.0..=80.0).contains(&a) {
            (q + 0.003, u)
        } else {
            (q, u)
        }
    };
    let bins = noisy_bins(&fors1_bin_centres(30), disturbed, SIGMA_BIN, 4);
    let opts = RadialFitOptions { exclusions: vec!["sector:10:80".parse().unwrap()], ..Default::default() };
    let fit = fit_radial(&bins, &opts).unwrap();
    let errs = fit.model.coefficient_errors();
    for k in 0..3 {
        assert!(((fit.model.coeffs[k] - V_COEFFS[k]) / errs[k]).abs() < 4.0);
    }
    assert!(fit.n_used < bins.len() * 82 / 100);
}

#[test]
fn b_band_residual_interpolant_reproduces_injected_asymmetry_at_held_out_points() {
    // A B-like field: a radial pattern plus an asymmetric blob of up to 0.5% (fig:residB).
    let radial = radial_field(&V_COEFFS, (0.0, 0.0));
    let asym = |x: f64, y: f64| {
        let g = 0.005 * (-((x - 1.5).powi(2) + (y + 1.0).powi(2)) / (2.0 * 1.2f64.powi(2))).exp();
        (g * 0.5, g * 0.866)
    };
    let truth = |x: f64, y: f64| {
        let (a, b) = radial(x, y);
        let (c, d) = asym(x, y);
        (a + c, b + d)
    };
    let centres = fors1_bin_centres(30);
    // Hold out every 7th bin.
    let (train, held): (Vec<_>, Vec<_>) = centres.iter().enumerate().partition(|(k, _)| k % 7 != 3);
    let train: Vec<(f64, f64)> = train.into_iter().map(|(_, c)| *c).collect();
    let held: Vec<(f64, f64)> = held.into_iter().map(|(_, c)| *c).collect();
    let bins = noisy_bins(&train, truth, SIGMA_BIN, 5);
    let fit = fit_radial(&bins, &RadialFitOptions::default()).unwrap();
    assert!(fit.rms_residual > 5.0 * SIGMA_BIN, "the radial fit alone cannot describe the B field");
    let residual = fit::files::calfile::residual_from_bins(&fit.model, &bins).unwrap();
    let mut ss = 0.0;
    let mut n = 0;
    for &(x, y) in &held {
        let Some((dq, du)) = residual.eval(x, y) else { continue };
        let m = fit.model.eval(x, y);
        let (tq, tu) = truth(x, y);
        ss += (m.q + dq - tq).powi(2) + (m.u + du - tu).powi(2);
        n += 2;
    }
    let rms = (ss / n as f64).sqrt();
    // Natural-neighbour interpolation averages a few noisy neighbours: error at about the map
    // noise, far below the 0.5% asymmetry.
    assert!(rms < 1.5 * SIGMA_BIN, "held-out error {rms} vs noise {SIGMA_BIN}");
    // Leave-one-out estimate of the interpolation error: noise of the point plus that of the
    // interpolant, so between 1 and 2 x the noise.
    assert!(residual.loo_rms_q > SIGMA_BIN && residual.loo_rms_q < 2.0 * SIGMA_BIN, "{}", residual.loo_rms_q);
}

#[test]
fn too_few_bins_and_degenerate_fits_are_clear_errors() {
    let bins = noisy_bins(&[(1.0, 0.0), (0.0, 1.0), (-1.0, 0.5)], radial_field(&V_COEFFS, (0.0, 0.0)), SIGMA_BIN, 6);
    let e = fit_radial(&bins, &RadialFitOptions::default()).unwrap_err();
    assert!(matches!(e, Error::TooFewBins { .. }), "{e}");
    assert!(e.to_string().contains("too few"), "{e}");
    // All bins at one radius: the powers of r cannot be told apart.
    let ring: Vec<(f64, f64)> =
        (0..100).map(|k| (2.0 * (k as f64 * 0.0628).cos(), 2.0 * (k as f64 * 0.0628).sin())).collect();
    let bins = noisy_bins(&ring, radial_field(&V_COEFFS, (0.0, 0.0)), SIGMA_BIN, 7);
    let e = fit_radial(&bins, &RadialFitOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Undetermined(_)), "{e}");
    assert!(e.to_string().contains("radii span only 2.0000..2.0000"), "{e}");
    assert!(e.to_string().contains("coefficient"), "{e}");
}
