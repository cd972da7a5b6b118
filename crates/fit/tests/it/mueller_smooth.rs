//! The smooth forms of the Mueller field built from the per-bin fits (`fit::mueller_field::smooth`):
//! a radially symmetric diattenuation + retardance (a partial polarizer with a radial axis and
//! a stressed-lens retardance with a radial axis, written here in closed form) recovered by the
//! radial form within its errors; a field that is not radial flagged by the radial form's
//! chi2_dof; the interpolant passing through the per-bin values and continuous; polarized stars
//! corrected with every form coming back within their errors; each form written to a
//! calibration file and read back.

#[path = "../smooth_fixture/mod.rs"]
mod smooth_fixture;

use fit::correction::correct::{CorrectOptions, Measurement};
use fit::mueller_field::cal::{MuellerCal, SkyField};
use fit::mueller_field::smooth::{interp_field, radial_field};
use fit::mueller_field::{fit_mueller_field, fit_per_bin, BinFit, Kind, MuellerField, MuellerFitOptions, Smooth};
use mueller::linear::{physical_block, retardance_vector, LinearBlock};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal, Uniform};
use rand_xoshiro::Xoshiro256PlusPlus;
use smooth_fixture::fields;

/// Diattenuation p(r) = A r^2 with a radial axis (p = 0.3 % at 3.4'), B band-like.
const A: f64 = 0.003 / (3.4 * 3.4);
/// Retardance with a radial axis, (1 - cos delta) / 2 = B r^4 (delta = 18 deg at 3.4').
const B: f64 = 0.024471741852423214 / (3.4 * 3.4 * 3.4 * 3.4);

/// The radially symmetric truth: `p(r)` along the radius, a retardance `delta(r)` whose axis
/// is the radius (`retardance_vector` of delta and the polar angle).
fn radial_truth(x: f64, y: f64) -> LinearBlock {
    let (r, a) = (x.hypot(y), y.atan2(x));
    let p = A * r * r;
    let delta = (1.0 - 2.0 * B * r.powi(4)).acos();
    physical_block(p * (2.0 * a).cos(), p * (2.0 * a).sin(), retardance_vector(delta, a), 0.0, 0.0)
}

/// A field that is not radial: a constant diattenuation and a retardance growing along x.
fn tilted_truth(x: f64, y: f64) -> LinearBlock {
    let g = [0.01 + 0.004 * x, -0.006 + 0.003 * y];
    physical_block(0.002 + 3e-4 * x, -0.001, g, 0.0, 0.0)
}

fn opts(deg: usize) -> MuellerFitOptions {
    MuellerFitOptions { kind: Kind::diattenuation_retardance(), deg, scale_arcmin: 3.0, ..Default::default() }
}

fn per_bin(truth: &dyn Fn(f64, f64) -> LinearBlock, s: f64, seed: u64) -> Vec<BinFit> {
    let f = fields(truth, 11, 3.0, s, seed);
    let (bins, skipped) = fit_per_bin(&f, &opts(0)).unwrap();
    assert_eq!(skipped, 0);
    bins
}

/// The radial form's coefficients are the truth's (powers 1..3 of r: p = A r^2, m = B r^4 is
/// outside degree 3 — so degree 4 here) within 4 sigma, and its chi2_dof is 1 within 5 sigma
/// of chi^2's scatter, no warning.
#[test]
fn radial_form_recovers_a_radial_field_within_errors() {
    let bins = per_bin(&radial_truth, 1e-4, 3);
    let mf = radial_field(&bins, 4).unwrap();
    let Smooth::Radial(form) = &mf.smooth else { panic!("not radial") };
    assert_eq!(form.pairs.len(), 2);
    // Parameter-major coefficients of r^1..r^4: diattenuation (0, A, 0, 0), retardance (0, 0, 0, B).
    let want = [0.0, A, 0.0, 0.0, 0.0, 0.0, 0.0, B];
    let n = mf.coeffs.len();
    assert_eq!(n, 8);
    for k in 0..n {
        let z = (mf.coeffs[k] - want[k]) / mf.cov[k * n + k].sqrt();
        assert!(z.abs() < 4.0, "coefficient {k}: {} vs {} (z = {z:.2})", mf.coeffs[k], want[k]);
    }
    // The pattern really is measured (not within errors because the errors are huge): at
    // (3', 0) the diattenuation q_d = p(3') and the retardance g_1 = m(3') over their errors.
    let (v, c) = mf.params_at(3.0, 0.0);
    assert!(v[0] / c[0].sqrt() > 20.0 && v[2] / c[10].sqrt() > 20.0, "{v:?} {c:?}");
    let dof = (bins.len() * 4 - 8) as f64;
    assert!((mf.chi2_dof - 1.0).abs() < 5.0 * (2.0 / dof).sqrt(), "chi2_dof {}", mf.chi2_dof);
    assert!(mf.warnings.is_empty(), "{:?}", mf.warnings);
    // The diattenuation the form gives at a position is the truth's there, within its errors.
    for &(x, y) in &[(1.3, -2.2), (-2.5, 0.4), (0.7, 0.9)] {
        let (v, c) = mf.params_at(x, y);
        let want = A * (x * x + y * y);
        let a2 = 2.0 * y.atan2(x);
        let zq = (v[0] - want * a2.cos()) / c[0].sqrt();
        let zu = (v[1] - want * a2.sin()) / c[5].sqrt();
        assert!(zq.abs() < 4.0 && zu.abs() < 4.0, "({x}, {y}): {v:?} vs p = {want}");
    }
}

/// A field that is not radial gives the radial form a reduced chi^2 far above 1 and the
/// warning saying so; the poly form of the same data does not.
#[test]
fn radial_form_flags_a_field_that_is_not_radial() {
    let bins = per_bin(&tilted_truth, 1e-4, 4);
    let mf = radial_field(&bins, 3).unwrap();
    let dof = (bins.len() * 4 - 6) as f64;
    assert!(mf.chi2_dof > 1.0 + 5.0 * (2.0 / dof).sqrt(), "chi2_dof {}", mf.chi2_dof);
    assert!(mf.warnings.iter().any(|w| w.contains("not radial")), "{:?}", mf.warnings);
    let poly = fit_mueller_field(&fields(&tilted_truth, 11, 3.0, 1e-4, 4), &opts(2)).unwrap();
    assert!(poly.chi2_dof < 1.5, "{}", poly.chi2_dof);
    // Rotation and depolarization have no radial pattern: refused by name.
    let f = fields(&tilted_truth, 5, 2.0, 1e-4, 5);
    let k = Kind::parse_free("retardance,rotation").unwrap();
    let (b, _) = fit_per_bin(&f, &MuellerFitOptions { kind: k, ..opts(0) }).unwrap();
    let e = radial_field(&b, 3).unwrap_err().to_string();
    assert!(e.contains("radial") && e.contains("rotation"), "{e}");
}

/// The interpolant passes through every per-bin value at its bin centre (with the bin's
/// covariance), is continuous (steps of 1e-4' along a line across the field change it by no
/// more than a bounded slope times the step; nearest-bin values would jump by the bins' noise),
/// and has no value outside the bins' hull.
#[test]
fn interpolant_passes_through_the_bins_and_is_continuous() {
    let bins = per_bin(&radial_truth, 3e-4, 6);
    let mf = interp_field(&bins).unwrap();
    for b in &bins {
        let (v, c) = mf.params_at(b.x_arcmin, b.y_arcmin);
        for k in 0..4 {
            assert!((v[k] - b.field.coeffs[k]).abs() < 1e-12, "{v:?} vs {:?}", b.field.coeffs);
        }
        for (a, w) in c.iter().zip(&b.field.cov) {
            assert!((a - w).abs() <= 1e-12 * w.abs().max(1e-12), "{c:?} vs {:?}", b.field.cov);
        }
    }
    // Largest secant slope between grid neighbours (0.6' apart), per parameter.
    let spacing = 0.6;
    let mut slope = [0.0f64; 4];
    for a in &bins {
        for b in &bins {
            let d = (a.x_arcmin - b.x_arcmin).hypot(a.y_arcmin - b.y_arcmin);
            if d > 0.0 && d < 1.01 * spacing {
                for k in 0..4 {
                    slope[k] = slope[k].max((a.field.coeffs[k] - b.field.coeffs[k]).abs() / d);
                }
            }
        }
    }
    let h = 1e-4;
    let mut prev = mf.params_at(-2.95, -1.234).0;
    let mut t = -2.95 + h;
    let mut worst = 0.0f64;
    while t < 2.95 {
        let v = mf.params_at(t, -1.234 + 0.37 * (t + 2.95)).0;
        for k in 0..4 {
            worst = worst.max((v[k] - prev[k]).abs() / (slope[k] * h * 1.07));
        }
        prev = v;
        t += h;
    }
    assert!(worst < 10.0, "largest step {worst} times the secant slope");
    assert!(worst > 0.0);
    assert!(!fit::FieldModel::contains(&mf, 3.2, 0.0) && mf.params_at(3.2, 0.0).0[0].is_nan());
    assert!(fit::FieldModel::contains(&mf, 2.9, -2.9));
    // The JSON form rebuilds the interpolant from its points.
    let back = MuellerField::from_json(&mf.to_json(), "t.json").unwrap();
    let (a, b) = (back.params_at(0.31, -1.7).0, mf.params_at(0.31, -1.7).0);
    for k in 0..4 {
        assert!((a[k] - b[k]).abs() <= 1e-12 * b[k].abs().max(1e-9), "{a:?} {b:?}");
    }
}

fn calibration(mf: MuellerField, per_bin: Vec<BinFit>) -> MuellerCal {
    MuellerCal {
        instrument: "fors1".into(),
        filter: "B".into(),
        field: mf,
        coords: Some(field::FieldCoords::centred(2048, 2048, 0.2)),
        skies: smooth_fixture::SKIES
            .iter()
            .map(|&(p, chi_deg)| SkyField { name: "sky".into(), p, chi_deg, sigma: 0.0 })
            .collect(),
        per_bin,
        provenance: fit::files::calfile::Provenance::now("instpol calibrate-mueller", vec!["sky0.fits".into()]),
        hwp_chi_offset_deg: 0.0,
    }
}

/// Polarized stars across the field (P up to 8 %, any angle) seen through the truth with
/// noise, corrected with each form: the pulls of q0, u0 against the true polarization have an
/// RMS of 1 within 0.15 and a mean within 0.2 (400 stars: 2 x 400 pulls). Each form written
/// to a calibration file and read back gives the same correction.
#[test]
fn stars_corrected_with_every_form_come_back_within_errors() {
    let f = fields(&radial_truth, 11, 3.0, 1e-4, 7);
    let (bins, _) = fit_per_bin(&f, &opts(0)).unwrap();
    let forms = [
        ("poly", fit_mueller_field(&f, &opts(4)).unwrap()),
        ("radial", radial_field(&bins, 4).unwrap()),
        ("interp", interp_field(&bins).unwrap()),
    ];
    let dir = std::env::temp_dir().join(format!("instpol_mueller_smooth_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (name, mf) in forms {
        assert_eq!(mf.smooth.name(), name);
        let cal = calibration(mf, bins.clone());
        let path = dir.join(format!("{name}.fits"));
        cal.save(&path).unwrap();
        let back = MuellerCal::load(&path).unwrap();
        assert_eq!(back.field.smooth.name(), name);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(11);
        let g = Normal::new(0.0, 1.0).unwrap();
        let (pos, unit) = (Uniform::new(-2.9, 2.9).unwrap(), Uniform::new(0.0, 1.0).unwrap());
        let s = 3e-4;
        let mut pulls = vec![];
        for _ in 0..400 {
            let (x, y) = (pos.sample(&mut rng), pos.sample(&mut rng));
            let (p, chi) = (0.08 * unit.sample(&mut rng), std::f64::consts::PI * unit.sample(&mut rng));
            let (qt, ut) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
            let (q, u) = radial_truth(x, y).forward(qt, ut).unwrap();
            let m = Measurement::at_plate(x, y, q + s * g.sample(&mut rng), u + s * g.sample(&mut rng), s, s, 0.0);
            let r = cal.correct(&m, &CorrectOptions::default()).unwrap();
            let rb = back.correct(&m, &CorrectOptions::default()).unwrap();
            assert!(
                (r.q0 - rb.q0).abs() < 1e-12 && (r.u0 - rb.u0).abs() < 1e-12,
                "{name}: file gives a different correction"
            );
            assert!((r.var_q0 / rb.var_q0 - 1.0).abs() < 1e-6, "{name}: {} vs {}", r.var_q0, rb.var_q0);
            pulls.push((r.q0 - qt) / r.var_q0.sqrt());
            pulls.push((r.u0 - ut) / r.var_u0.sqrt());
        }
        let n = pulls.len() as f64;
        let mean = pulls.iter().sum::<f64>() / n;
        let rms = (pulls.iter().map(|z| z * z).sum::<f64>() / n).sqrt();
        eprintln!("{name}: pulls mean {mean:.3} rms {rms:.3}");
        assert!((rms - 1.0).abs() < 0.15 && mean.abs() < 0.2, "{name}: pulls mean {mean} rms {rms}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// A file written before the smooth forms (no `MU SMOOTH` keyword, deleted here with
/// cfitsio's own `ffdkey`) is read as the polynomial it holds; an unknown form is refused by
/// name; an interpolant file whose per-bin table was dropped is refused naming MUELLER_BINS.
#[test]
fn older_files_read_as_poly_and_bad_forms_are_refused() {
    let f = fields(&tilted_truth, 5, 2.0, 1e-4, 8);
    let mf = fit_mueller_field(&f, &opts(1)).unwrap();
    let (bins, _) = fit_per_bin(&f, &opts(0)).unwrap();
    let dir = std::env::temp_dir().join(format!("instpol_mueller_smooth_old_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("poly.fits");
    calibration(mf.clone(), vec![]).save(&path).unwrap();
    let edit = |p: &std::path::Path, f: &dyn Fn(*mut fitsio::sys::fitsfile, &mut i32)| {
        let mut ff = fitsio::FitsFile::edit(p).unwrap();
        ff.hdu("MUELLER").unwrap();
        let mut status = 0;
        f(unsafe { ff.as_raw() }, &mut status);
        assert_eq!(status, 0, "cfitsio status");
    };
    let old = dir.join("old.fits");
    std::fs::copy(&path, &old).unwrap();
    edit(&old, &|ptr, st| unsafe {
        fitsio::sys::ffdkey(ptr, c"IP MU SMOOTH".as_ptr(), st);
    });
    let back = MuellerCal::load(&old).unwrap();
    assert_eq!(back.field.smooth, Smooth::Poly);
    assert_eq!(back.field.coeffs, mf.coeffs);

    let bad = dir.join("spline.fits");
    std::fs::copy(&path, &bad).unwrap();
    edit(&bad, &|ptr, st| unsafe {
        fitsio::sys::ffukys(ptr, c"HIERARCH IP MU SMOOTH".as_ptr(), c"SPLINE".as_ptr(), std::ptr::null(), st);
    });
    let e = MuellerCal::load(&bad).unwrap_err().to_string();
    assert!(e.contains("spline.fits") && e.contains("MU SMOOTH") && e.contains("spline"), "{e}");

    let ip = dir.join("interp.fits");
    calibration(interp_field(&bins).unwrap(), bins.clone()).save(&ip).unwrap();
    assert_eq!(MuellerCal::load(&ip).unwrap().field.smooth.name(), "interp");
    edit(&ip, &|ptr, st| unsafe {
        let mut ty = 0;
        fitsio::sys::ffmnhd(ptr, -1, c"MUELLER_BINS".as_ptr() as *mut _, 0, st);
        fitsio::sys::ffdhdu(ptr, &mut ty, st);
    });
    let e = MuellerCal::load(&ip).unwrap_err().to_string();
    assert!(e.contains("interp.fits") && e.contains("MUELLER_BINS"), "{e}");
    // Saving an interpolant without its per-bin fits is refused (it would not read back).
    let e = calibration(interp_field(&bins).unwrap(), vec![]).save(&dir.join("x.fits")).unwrap_err().to_string();
    assert!(e.contains("per-bin"), "{e}");
    assert!(!dir.join("x.fits").exists());
    std::fs::remove_dir_all(&dir).ok();
}
