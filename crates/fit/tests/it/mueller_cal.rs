//! The Mueller field in a calibration file (`fit::mueller_field::cal`): written and read back exactly,
//! malformed files refused by name, today's p, phi reader refusing it by name; the exact
//! correction's propagated errors against a Monte Carlo written here (coefficients drawn from
//! their covariance, measurements from theirs, each inverted with nalgebra's own 3 x 3
//! inverse); positions outside the fitted field refused as on the p, phi path.

use fit::correction::correct::{CorrectOptions, Error as CorrError, Measurement};
use fit::mueller_field::cal::{MuellerCal, SkyField};
use fit::mueller_field::{fit_mueller_field, fit_per_bin, CalField, Kind, MuellerField, MuellerFitOptions};
use mueller::Qu;
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

use crate::common;

/// Truth: a diattenuation and a retardance varying over a 5 x 5 arcmin field.
fn truth(x: f64, y: f64) -> mueller::linear::LinearBlock {
    let g = [0.01 + 0.004 * x, -0.006 + 0.003 * y * x];
    mueller::linear::physical_block(0.002 + 3e-4 * x, -0.001 + 2e-4 * y, g, 0.0, 0.0)
}

/// Three sky fields seen through the truth on a 9 x 9 grid, with noise of `s`.
fn fields(s: f64, seed: u64) -> Vec<CalField> {
    fields_n(s, seed, 3)
}

/// The first `n` of four sky fields (the general block's 8 parameters need four), all noise
/// from one generator.
fn fields_n(s: f64, seed: u64, nf: usize) -> Vec<CalField> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let grid: Vec<(f64, f64)> = (0..81).map(|i| ((i % 9) as f64 * 0.6 - 2.4, (i / 9) as f64 * 0.6 - 2.4)).collect();
    let meas = common::mueller_fields::through(truth);
    common::mueller_fields::SKIES
        .iter()
        .chain(&[(0.05, 40.0)])
        .take(nf)
        .enumerate()
        .map(|(k, &(p, chi))| {
            common::mueller_fields::cal_field(&format!("sky{k}.fits"), p, chi, &grid, &meas, s, &mut rng)
        })
        .collect()
}

fn calibration(mf: MuellerField, per_bin: Vec<fit::mueller_field::BinFit>) -> MuellerCal {
    MuellerCal {
        instrument: "fors1".into(),
        filter: "B".into(),
        field: mf,
        coords: Some(field::FieldCoords::centred(2048, 2048, 0.2)),
        skies: vec![
            SkyField { name: "sky0.fits".into(), p: 0.0645, chi_deg: 68.4, sigma: 0.0 },
            SkyField { name: "sky1.fits".into(), p: 0.04, chi_deg: 10.0, sigma: 1e-4 },
        ],
        per_bin,
        provenance: fit::files::calfile::Provenance::now("instpol calibrate-mueller", vec!["sky0.fits".into()]),
        // FORS2 b_HIGH's (instruments/fors2.toml), so that the keyword is written and read.
        hwp_chi_offset_deg: -1.54,
    }
}

/// Everything written comes back bit for bit (FITS doubles), the per-bin table included; the
/// p, phi reader refuses the file by name instead of reading something else from it.
#[test]
fn save_and_load_give_back_the_same_calibration() {
    let f = fields(3e-4, 1);
    let opts = MuellerFitOptions { deg: 2, scale_arcmin: 2.4, ..Default::default() };
    let mf = fit_mueller_field(&f, &opts).unwrap();
    let (bins, _) = fit_per_bin(&f, &opts).unwrap();
    let cal = calibration(mf, bins);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cal.fits");
    cal.save(&path).unwrap();
    assert_eq!(fit::files::calibration::load(&path).unwrap().kind(), fit::files::calibration::Kind::Mueller);
    let back = MuellerCal::load(&path).unwrap();
    assert_eq!(back.field.kind, cal.field.kind);
    assert_eq!(back.field.free, cal.field.free);
    assert_eq!(back.field.coeffs, cal.field.coeffs);
    assert_eq!(back.field.cov, cal.field.cov);
    // Keywords keep about 16 significant digits: the box and the statistics to 1e-14.
    for (a, b) in back.field.bounds.iter().zip(&cal.field.bounds) {
        assert!((a - b).abs() < 1e-14, "{a} {b}");
    }
    assert!((back.field.chi2_dof / cal.field.chi2_dof - 1.0).abs() < 1e-14);
    // The box's edges stay inside after the round trip.
    let b = cal.field.bounds;
    assert!(fit::models::model::FieldModel::contains(&back.field, b[1], b[3]));
    assert_eq!((back.instrument.as_str(), back.filter.as_str()), ("fors1", "B"));
    assert_eq!(back.coords, cal.coords);
    assert_eq!(back.skies, cal.skies);
    assert_eq!(back.per_bin.len(), 81);
    for (a, b) in back.per_bin.iter().zip(&cal.per_bin) {
        assert_eq!((a.x_arcmin, a.y_arcmin), (b.x_arcmin, b.y_arcmin));
        assert_eq!(a.field.coeffs, b.field.coeffs);
        // The diagonal goes through SIGMA (a square root), the fit's covariance is symmetric
        // to rounding and the file keeps one triangle: within 1e-14 of the correlation scale.
        let nf = a.field.free.len();
        for k in 0..nf {
            for l in 0..nf {
                let (u, v) = (a.field.cov[k * nf + l], b.field.cov[k * nf + l]);
                let scale = (b.field.cov[k * nf + k] * b.field.cov[l * nf + l]).sqrt();
                assert!((u - v).abs() <= 1e-14 * scale, "({k}, {l}): {u} {v}");
            }
        }
    }
    // The pixel grid converts like the field coordinates.
    let g = back.pixel().unwrap();
    let (x, y) = g.to_arcmin(0.0, 2047.0);
    assert!((x + 3.411_666_666_666_667).abs() < 1e-12 && (y - 3.411_666_666_666_667).abs() < 1e-12);

    let err = fit::Calibration::load(&path).unwrap_err().to_string();
    assert!(err.contains("Mueller field") && err.contains("cal.fits"), "{err}");
    let err = fit::files::calibration::load(&path).unwrap().p_phi_models().unwrap_err().to_string();
    assert!(err.contains("Mueller field"), "{err}");
}

/// The general 3 x 3 block and the p, phi-only physical form are written and read as well.
#[test]
fn general_and_diattenuation_only_kinds_round_trip() {
    let f = fields_n(3e-4, 2, 4);
    for kind in [Kind::General, Kind::Physical { retardance: false, rotation: false, depolarization: false }] {
        let opts = MuellerFitOptions { kind, deg: 1, scale_arcmin: 2.4, ..Default::default() };
        let mf = fit_mueller_field(&f, &opts).unwrap();
        let cal = calibration(mf, vec![]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cal.fits");
        cal.save(&path).unwrap();
        let back = MuellerCal::load(&path).unwrap();
        assert_eq!(back.field.kind, kind);
        assert_eq!(back.field.coeffs, cal.field.coeffs);
        assert!(back.per_bin.is_empty());
    }
}

/// A tampered coefficient row and a covariance with a negative variance are refused, naming
/// the row or element and the file.
#[test]
fn malformed_files_are_refused_by_name() {
    let f = fields(3e-4, 3);
    let mf = fit_mueller_field(&f, &MuellerFitOptions { deg: 1, scale_arcmin: 2.4, ..Default::default() }).unwrap();
    let cal = calibration(mf, vec![]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cal.fits");
    cal.save(&path).unwrap();

    let bad = dir.path().join("px.fits");
    std::fs::copy(&path, &bad).unwrap();
    {
        let mut ff = fitsio::FitsFile::edit(&bad).unwrap();
        let h = ff.hdu("MUELLER").unwrap();
        let mut px: Vec<i32> = h.read_col(&mut ff, "PX").unwrap();
        px[1] = 7;
        h.write_col(&mut ff, "PX", &px).unwrap();
    }
    let err = MuellerCal::load(&bad).unwrap_err().to_string();
    assert!(err.contains("px.fits") && err.contains("MUELLER row 2"), "{err}");

    let bad = dir.path().join("cov.fits");
    std::fs::copy(&path, &bad).unwrap();
    {
        let mut ff = fitsio::FitsFile::edit(&bad).unwrap();
        let h = ff.hdu("MUELLER_COV").unwrap();
        let mut c: Vec<f64> = h.read_image(&mut ff).unwrap();
        c[0] = -1.0;
        h.write_image(&mut ff, &c).unwrap();
    }
    let err = MuellerCal::load(&bad).unwrap_err().to_string();
    assert!(err.contains("cov.fits") && err.contains("MUELLER_COV") && err.contains("variance"), "{err}");

    let err = MuellerCal::load(&dir.path().join("none.fits")).unwrap_err().to_string();
    assert!(err.contains("none.fits"), "{err}");
}

/// The exact inverse written separately: nalgebra's inverse of the 3 x 3 block applied to
/// `(1, q, u)`, normalized.
fn invert_by_hand(m: &Matrix3<f64>, q: f64, u: f64) -> (f64, f64) {
    let s = m.try_inverse().unwrap() * Vector3::new(1.0, q, u);
    (s[1] / s[0], s[2] / s[0])
}

/// The propagated covariance of the corrected (q, u) — the measurement's and the model's —
/// against a Monte Carlo: the coefficients drawn from their covariance (Cholesky), the
/// measurement from its own, each draw inverted by hand. Sample (co)variances of 40000 draws
/// agree within 4 % (their own scatter is ~1 %).
#[test]
fn propagated_errors_match_a_monte_carlo() {
    let f = fields(1e-3, 4);
    let mf = fit_mueller_field(&f, &MuellerFitOptions { deg: 2, scale_arcmin: 2.4, ..Default::default() }).unwrap();
    let cal = calibration(mf.clone(), vec![]);
    let (x, y) = (1.7, -0.9);
    let m = Measurement::at_plate(x, y, 0.031, -0.018, 2e-4, 3e-4, 2e-8);
    let r = cal.correct(&m, &CorrectOptions::default()).unwrap();
    // The central value is the hand inverse of the fitted block.
    let (qh, uh) = invert_by_hand(&mf.block_at(x, y).0, m.qu.q, m.qu.u);
    assert!((r.q0 - qh).abs() < 1e-13 && (r.u0 - uh).abs() < 1e-13);

    let n = mf.coeffs.len();
    let c = DMatrix::from_row_slice(n, n, &mf.cov);
    let l = c.cholesky().unwrap().l();
    let sm = nalgebra::Matrix2::new(m.qu.var_q, m.qu.cov_qu, m.qu.cov_qu, m.qu.var_u);
    let lm = sm.cholesky().unwrap().l();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(16);
    let g = Normal::new(0.0, 1.0).unwrap();
    let k = 40_000;
    let (mut sq, mut su, mut squ, mut mq, mut mu) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let mut draw = mf.clone();
    let mut samples = Vec::with_capacity(k);
    for _ in 0..k {
        let z = DVector::from_fn(n, |_, _| g.sample(&mut rng));
        let dc = &l * z;
        for i in 0..n {
            draw.coeffs[i] = mf.coeffs[i] + dc[i];
        }
        let zm = lm * nalgebra::Vector2::new(g.sample(&mut rng), g.sample(&mut rng));
        let (q0, u0) = invert_by_hand(&draw.block_at(x, y).0, m.qu.q + zm[0], m.qu.u + zm[1]);
        samples.push((q0, u0));
        mq += q0;
        mu += u0;
    }
    mq /= k as f64;
    mu /= k as f64;
    for (q0, u0) in &samples {
        sq += (q0 - mq).powi(2);
        su += (u0 - mu).powi(2);
        squ += (q0 - mq) * (u0 - mu);
    }
    let kk = (k - 1) as f64;
    let (vq, vu, cqu) = (sq / kk, su / kk, squ / kk);
    assert!((r.var_q0 / vq - 1.0).abs() < 0.04, "var q0: propagated {} MC {vq}", r.var_q0);
    assert!((r.var_u0 / vu - 1.0).abs() < 0.04, "var u0: propagated {} MC {vu}", r.var_u0);
    // The covariance against the MC's, on the scale of the standard deviations.
    assert!((r.cov_qu0 - cqu).abs() < 0.04 * (vq * vu).sqrt(), "cov: propagated {} MC {cqu}", r.cov_qu0);
    // The model's part matters here (it is not only the measurement's error).
    assert!(r.var_q0 > 1.2 * m.qu.var_q, "{} vs {}", r.var_q0, m.qu.var_q);
}

/// Outside the fitted box: refused as on the p, phi path; with extrapolation allowed, flagged,
/// the same central value as the model's own inverse and the variance grown by
/// `(f |correction|)^2`.
#[test]
fn outside_the_field_is_refused_unless_extrapolation_is_allowed() {
    let f = fields(3e-4, 5);
    let mf = fit_mueller_field(&f, &MuellerFitOptions { deg: 1, scale_arcmin: 2.4, ..Default::default() }).unwrap();
    let cal = calibration(mf.clone(), vec![]);
    let m = Measurement::at_plate(3.0, 0.0, 0.05, 0.01, 3e-4, 3e-4, 0.0);
    let e = cal.correct(&m, &CorrectOptions::default()).unwrap_err();
    assert!(matches!(e, CorrError::OutsideField { .. }), "{e}");
    let opts = CorrectOptions { allow_extrapolation: true, extrapolation_rel_error: 0.5, ..Default::default() };
    let r = cal.correct(&m, &opts).unwrap();
    assert!(r.extrapolated);
    let ((q0, u0), cov) = mf.correct(3.0, 0.0, m.qu.q, m.qu.u, [9e-8, 0.0, 9e-8]).unwrap();
    assert_eq!((r.q0, r.u0), (q0, u0));
    let add = 0.25 * ((q0 - m.qu.q).powi(2) + (u0 - m.qu.u).powi(2));
    assert!(add > 0.0);
    assert!((r.var_q0 - (cov[0] + add)).abs() < 1e-18 && (r.var_u0 - (cov[2] + add)).abs() < 1e-18);
    // Bad input names itself.
    let e = cal.correct(&Measurement { qu: Qu { var_q: f64::NAN, ..m.qu }, ..m }, &opts).unwrap_err();
    assert!(e.to_string().contains("sigma_q"), "{e}");
}
