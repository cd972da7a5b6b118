//! A calibration a test states as true: its model given (no bins, no fit statistics), over a
//! square region. Shared by the fit and the simulator tests (the latter include this file by
//! its path).

/// The calibration of `instrument` in `filter` (`lambda_nm`) with HWP zero angle `zero_deg`
/// and field `model`, valid over `|x|, |y| <= half_width_arcmin`.
pub fn given_calibration(
    instrument: &str,
    filter: &str,
    lambda_nm: f64,
    zero_deg: f64,
    model: fit::Model,
    half_width_arcmin: f64,
) -> fit::Calibration {
    let h = half_width_arcmin;
    fit::Calibration {
        format_version: fit::files::calfile::FORMAT_VERSION,
        instrument: instrument.into(),
        filter: filter.into(),
        lambda_nm,
        hwp_chi_offset_deg: zero_deg,
        model,
        region: fit::FieldRegion { x_min: -h, x_max: h, y_min: -h, y_max: h },
        rms_residual: f64::NAN,
        n_bins_used: 0,
        polar_angle: None,
        exclusions: vec![],
        robust: "none".into(),
        pixel: None,
        provenance: fit::files::calfile::Provenance::now("test", vec![]),
        bins: vec![],
        grid: None,
    }
}
