//! Regression tests for defects found by the cargo-fuzz targets (fuzz/FINDINGS.md).

use fit::models::residual::{ResidualMap, ResidualPoint};

/// fuzz/FINDINGS.md, calibration_file 1: `ResidualMap::eval` (and so `FieldModel::eval` and
/// `contains` of a RADIAL+RESIDUAL calibration) panicked inside spade at a NaN position
/// ("assertion failed: !f64::is_nan(pos.x)") and at |x| > 2^201 ("Failed to locate
/// position"). Such positions are outside the hull of the bins: `None`. Inside, the
/// natural-neighbour interpolant still passes through its data points.
#[test]
fn residual_map_at_unrepresentable_positions_is_none() {
    let pts: Vec<ResidualPoint> = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (0.4, 0.6)]
        .iter()
        .enumerate()
        .map(|(k, &(x, y))| ResidualPoint { x, y, dq: 1e-3 * k as f64, du: -2e-3 * k as f64 })
        .collect();
    let m = ResidualMap::new(pts.clone()).unwrap();
    for (x, y) in
        [(f64::NAN, 0.5), (0.5, f64::NAN), (f64::INFINITY, 0.5), (0.5, f64::NEG_INFINITY), (1e300, -1e300), (0.5, 1e61)]
    {
        assert_eq!(m.eval(x, y), None, "({x}, {y})");
    }
    // Subnormal offsets from a vertex: the vertex's value (spade flushes them to 0).
    let (dq, du) = m.eval(1e-310, 0.0).unwrap();
    assert!((dq - pts[0].dq).abs() < 1e-15 && (du - pts[0].du).abs() < 1e-15);
    for p in &pts {
        let (dq, du) = m.eval(p.x, p.y).unwrap();
        assert!((dq - p.dq).abs() < 1e-12 && (du - p.du).abs() < 1e-12, "through ({}, {})", p.x, p.y);
    }
}

use crate::common;

/// A radial calibration with two input names, saved to `dir/cal.fits`.
fn saved_calibration(dir: &std::path::Path) -> std::path::PathBuf {
    use common::*;
    use fit::files::calfile::{Calibration, Model, Provenance, FORMAT_VERSION};
    let bins = noisy_bins(&fors1_bin_centres(16), radial_field(&V_COEFFS, (0.0, 0.0)), SIGMA_BIN, 3);
    let fit = fit::fit_radial(&bins, &fit::RadialFitOptions::default()).unwrap();
    let cal = Calibration {
        format_version: FORMAT_VERSION,
        instrument: "FORS1".into(),
        filter: "V".into(),
        lambda_nm: 554.0,
        hwp_chi_offset_deg: 0.0,
        model: Model::Radial(fit.model.clone()),
        region: fit::FieldRegion::bounding(bins.iter().map(|b| (b.x, b.y)), 0.05).unwrap(),
        rms_residual: fit.rms_residual,
        n_bins_used: fit.n_used,
        polar_angle: None,
        exclusions: vec![],
        robust: "none".into(),
        pixel: None,
        provenance: Provenance::now("test", vec!["a.fits".into(), "b.fits".into()]),
        bins,
        grid: None,
    };
    let p = dir.join("cal.fits");
    cal.save(&p).unwrap();
    p
}

/// fuzz/FINDINGS.md, calibration_file 2: a calibration whose header says NINPUT = 2 but whose
/// INPUTS table has no rows (NAXIS2 = 0, or a card CFITSIO reads as 0) panicked in `load`
/// ("chunk size must be non-zero": zero bytes divide into any number of names). Now an error
/// naming the file and the table; the unpatched file loads with its two names.
#[test]
fn calibration_with_empty_inputs_table_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let p = saved_calibration(dir.path());
    assert_eq!(fit::Calibration::load(&p).unwrap().provenance.inputs, vec!["a.fits", "b.fits"]);
    let mut b = std::fs::read(&p).unwrap();
    let ext = b.windows(17).position(|w| w == b"EXTNAME = 'INPUTS").expect("INPUTS table");
    let start = b[..ext].windows(8).rposition(|w| w == b"XTENSION").unwrap();
    let card = start + b[start..ext].windows(9).position(|w| w == b"NAXIS2  =").unwrap();
    b[card + 10..card + 30].copy_from_slice(format!("{:>20}", 0).as_bytes());
    std::fs::write(&p, b).unwrap();
    let e = fit::Calibration::load(&p).expect_err("empty INPUTS refused").to_string();
    assert!(e.contains("cal.fits") && e.contains("INPUTS"), "{e}");
}
