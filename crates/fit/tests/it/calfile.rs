//! The calibration file: a round trip keeps the model and the bins, a newer format version is
//! refused by name, and a failed write leaves nothing behind.

use crate::common;

use common::*;
use fit::files::calfile::{Calibration, Model, PixelGrid, Provenance, FORMAT_VERSION};
use fit::{fit_radial, Error, FieldModel, FieldRegion, RadialFitOptions};

fn sample(residual: bool) -> Calibration {
    let bins = noisy_bins(&fors1_bin_centres(64), radial_field(&V_COEFFS, (0.1, -0.05)), SIGMA_BIN, 11);
    let opts =
        RadialFitOptions { free_centre: true, exclusions: vec!["sector:10:80".parse().unwrap()], ..Default::default() };
    let fit = fit_radial(&bins, &opts).unwrap();
    let mut bins = bins;
    for (b, u) in bins.iter_mut().zip(&fit.used) {
        b.used = *u;
    }
    let model = if residual {
        let r = fit::files::calfile::residual_from_bins(&fit.model, &bins).unwrap();
        Model::RadialResidual { radial: fit.model.clone(), residual: r }
    } else {
        Model::Radial(fit.model.clone())
    };
    // 24 characters (8 mod 16): the width at which fitsio's string-column reader overflowed.
    let mut prov = Provenance::now("test", vec!["a.fits".into(), "frames/b_24_chars_x.fits".into()]);
    prov.sky_p = Some(0.0174);
    prov.sky_chi_deg = Some(126.2);
    Calibration {
        format_version: FORMAT_VERSION,
        instrument: "FORS1".into(),
        filter: "V".into(),
        lambda_nm: 554.0,
        hwp_chi_offset_deg: -1.5,
        model,
        region: FieldRegion::bounding(bins.iter().map(|b| (b.x, b.y)), 0.05).unwrap(),
        rms_residual: fit.rms_residual,
        n_bins_used: fit.n_used,
        polar_angle: None,
        exclusions: opts.exclusions.clone(),
        robust: opts.robust.name(),
        pixel: Some(PixelGrid { scale_arcsec: 0.2, origin_px: [1023.5, 1023.5] }),
        provenance: prov,
        bins,
        grid: None,
    }
}

#[test]
fn round_trip_keeps_model_bins_and_provenance() {
    let dir = tempfile::tempdir().unwrap();
    for residual in [false, true] {
        let cal = sample(residual);
        let path = dir.path().join(format!("cal_{residual}.fits"));
        cal.save(&path).unwrap();
        let back = Calibration::load(&path).unwrap();
        // The one loader says what the file is and holds the same field model.
        let any = fit::files::calibration::load(&path).unwrap();
        assert_eq!(any.kind(), fit::files::calibration::Kind::Field);
        assert!(any.telescope.is_none() && any.mueller.is_none());
        assert_eq!(any.field.as_ref().unwrap().model.radial().unwrap().coeffs, back.model.radial().unwrap().coeffs);
        let (a, b) = (cal.model.radial().unwrap(), back.model.radial().unwrap());
        for (x, y) in a.coeffs.iter().zip(&b.coeffs) {
            assert!((x - y).abs() <= 1e-13 * x.abs(), "{x} {y}");
        }
        for (x, y) in a.cov.iter().zip(&b.cov) {
            assert!((x - y).abs() <= 1e-13 * x.abs() + 1e-300, "{x} {y}");
        }
        assert_eq!(back.model.kind(), cal.model.kind());
        assert_eq!(back.bins.len(), cal.bins.len());
        assert_eq!(back.bins.iter().filter(|b| b.used).count(), cal.n_bins_used);
        assert_eq!(back.exclusions, cal.exclusions);
        assert_eq!(back.provenance.inputs, cal.provenance.inputs);
        assert_eq!(back.provenance.sky_p, Some(0.0174));
        assert_eq!((back.filter.as_str(), back.instrument.as_str(), back.lambda_nm), ("V", "FORS1", 554.0));
        assert_eq!(back.hwp_chi_offset_deg, -1.5);
        // The model evaluates the same after the round trip (the residual interpolant is
        // rebuilt from the BINS table).
        for &(x, y) in &[(1.0, 1.0), (-2.5, 0.3), (3.0, -3.0)] {
            let (u, v) = (cal.eval(x, y), back.eval(x, y));
            assert!((u.q - v.q).abs() < 1e-13 && (u.u - v.u).abs() < 1e-13, "{u:?} {v:?}");
            assert_eq!(cal.contains(x, y), back.contains(x, y));
        }
        let c = back.centre_px().unwrap();
        assert!((c[0] - (1023.5 + a.centre[0] * 300.0)).abs() < 1e-9);
        // The images are the model on the grid.
        let g = back.grid.as_ref().unwrap();
        let k = (g.ny / 2) * g.nx + g.nx / 3;
        let (x, y) = g.pixel_centre(g.nx / 3, g.ny / 2);
        assert!((g.q[k] - back.eval(x, y).q).abs() < 1e-15);
    }
}

#[test]
fn newer_format_version_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("new.fits");
    sample(false).save(&path).unwrap();
    {
        let mut f = fitsio::FitsFile::edit(&path).unwrap();
        let h = f.primary_hdu().unwrap();
        h.write_key(&mut f, "HIERARCH IP FORMAT VERSION", fit::files::keys::NEWEST_FORMAT_VERSION + 1).unwrap();
    }
    let e = Calibration::load(&path).unwrap_err();
    assert!(
        matches!(e, Error::NewerFormat { found, .. } if found == fit::files::keys::NEWEST_FORMAT_VERSION + 1),
        "{e}"
    );
    let msg = e.to_string();
    assert!(msg.contains("new.fits") && msg.contains("newer"), "{msg}");
}

#[test]
fn not_a_calibration_file_and_unwritable_folder() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plain.fits");
    {
        let mut f = fitsio::FitsFile::create(&path).open().unwrap();
        let h = f.primary_hdu().unwrap();
        h.write_key(&mut f, "OBJECT", "nothing").unwrap();
    }
    let e = Calibration::load(&path).unwrap_err().to_string();
    assert!(e.contains("FORMAT VERSION") && e.contains("plain.fits"), "{e}");
    let e = Calibration::load(&dir.path().join("missing.fits")).unwrap_err().to_string();
    assert!(e.contains("missing.fits"), "{e}");
    // Writing into a folder that does not exist fails without leaving anything.
    let bad = dir.path().join("no/such/dir/cal.fits");
    assert!(sample(false).save(&bad).is_err());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn error_scaling_is_recorded_and_files_without_it_still_load() {
    let dir = tempfile::tempdir().unwrap();
    let mut cal = sample(false);
    let Model::Radial(r) = &mut cal.model else { unreachable!() };
    let sc = r.scaling.expect("a fitted model records its scaling");
    assert_eq!(sc.mode, fit::ErrorScaling::Conservative);
    assert_eq!(sc.chi2_factor, sc.chi2_reduced.max(1.0));
    // With a correlated-errors inflation too.
    r.scaling = Some(fit::CovarianceScaling { correlation_inflation: Some(12.5), ..sc });
    let path = dir.path().join("scaled.fits");
    cal.save(&path).unwrap();
    {
        let mut f = fitsio::FitsFile::open(&path).unwrap();
        let h = f.primary_hdu().unwrap();
        assert_eq!(h.read_key::<String>(&mut f, "HIERARCH IP ERR SCALING").unwrap(), "conservative");
        assert_eq!(h.read_key::<f64>(&mut f, "HIERARCH IP ERR CORR INFL").unwrap(), 12.5);
    }
    let back = Calibration::load(&path).unwrap();
    let b = back.model.radial().unwrap().scaling.unwrap();
    assert_eq!(b.mode, fit::ErrorScaling::Conservative);
    assert_eq!(b.correlation_inflation, Some(12.5));
    assert!((b.chi2_reduced - sc.chi2_reduced).abs() <= 1e-14 * sc.chi2_reduced);
    assert!((b.total() - 12.5 * sc.chi2_factor).abs() <= 1e-13 * b.total());

    // A file as written before the keywords existed: no ERR keywords, the covariance as stored.
    let Model::Radial(r) = &mut cal.model else { unreachable!() };
    r.scaling = None;
    let want = r.centre_errors()[0];
    let old = dir.path().join("old.fits");
    cal.save(&old).unwrap();
    let back = Calibration::load(&old).unwrap();
    let rb = back.model.radial().unwrap();
    assert!(rb.scaling.is_none());
    assert!((rb.centre_errors()[0] - want).abs() <= 1e-13 * want);

    // A value this build does not know is an error naming the keyword (added to the file that
    // has none: fitsio appends keywords rather than updating them).
    {
        let mut f = fitsio::FitsFile::edit(&old).unwrap();
        let h = f.primary_hdu().unwrap();
        h.write_key(&mut f, "HIERARCH IP ERR SCALING", "optimistic").unwrap();
    }
    let e = Calibration::load(&old).map(|_| ()).unwrap_err().to_string();
    assert!(e.contains("ERR SCALING") && e.contains("optimistic") && e.contains("old.fits"), "{e}");
}

/// A calibration whose binned measurements hold a negative error or P > 1 is refused naming
/// the file, the table and the row; the untouched sample loads.
#[test]
fn unphysical_bins_in_a_calibration_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    for (k, edit) in [
        &(|c: &mut Calibration| c.bins[3].qu.var_q = -1e-4 * 1e-4) as &dyn Fn(&mut Calibration),
        &|c: &mut Calibration| c.bins[5].qu.q = 1.2,
    ]
    .iter()
    .enumerate()
    {
        let mut cal = sample(false);
        edit(&mut cal);
        let path = dir.path().join(format!("bad{k}.fits"));
        cal.save(&path).unwrap();
        let e = Calibration::load(&path).unwrap_err().to_string();
        assert!(e.contains(&format!("bad{k}.fits")) && e.contains("BINS row"), "{e}");
    }
    let path = dir.path().join("good.fits");
    sample(false).save(&path).unwrap();
    Calibration::load(&path).unwrap();
}
