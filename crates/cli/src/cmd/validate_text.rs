//! `instpol validate`'s text reports, as printed without --json: a field calibration's check
//! on a star, and a telescope chain's.

use fit::telescope::validate::ChainValidation;
use fit::validate::ValidationReport;
use std::path::Path;

/// A star validated through a telescope chain (`name` in `band` at `(x_px, y_px)`, measured in
/// `n_frames` frames, calibration file `cal`).
pub fn print_chain(r: &ChainValidation, name: &str, band: &str, (x_px, y_px): (f64, f64), n_frames: usize, cal: &Path) {
    outln!(
        "star {name} in {band} at ({x_px:.1}, {y_px:.1}) px, {} frames; parallactic angle {:.2} to {:.2} deg, rotator {:.2} deg",
        n_frames,
        r.parallactic_start_deg,
        r.parallactic_end_deg,
        r.rotator_deg
    );
    outln!(
        "calibration {} ({} telescope model{}, HWP zero angle {:+.2} deg)",
        cal.display(),
        r.telescope_model,
        if r.field_model { " after the field model" } else { "" },
        r.hwp_chi_offset_deg
    );
    outln!(
        "  measured   q = {:.3} +- {:.3} %   u = {:.3} +- {:.3} %  (telescope alone: q = {:.3} %, u = {:.3} %)",
        100.0 * r.measured_q,
        100.0 * r.sigma_q,
        100.0 * r.measured_u,
        100.0 * r.sigma_u,
        100.0 * r.telescope_q,
        100.0 * r.telescope_u
    );
    outln!(
        "  corrected  P0 = {:.3} +- {:.3} %  chi0 = {:.1} deg  (expected q = {:.3} %, u = {:.3} %): {:.2} sigma (uncorrected {:.2} sigma)",
        100.0 * r.corrected_p,
        100.0 * r.sigma_corrected_p,
        r.corrected_chi_deg,
        100.0 * r.expected_q,
        100.0 * r.expected_u,
        r.corrected_residual_sigma,
        r.uncorrected_residual_sigma
    );
    outln!("{} (threshold {} sigma)", if r.pass { "PASS" } else { "FAIL" }, r.threshold);
}

/// A star validated with a field calibration `cal`.
pub fn print_report(r: &ValidationReport, cal: &Path) {
    let v = &r.validation;
    outln!(
        "star {} in {} at ({:.1}, {:.1}) px = ({:.3}, {:.3}) arcmin, {} frames",
        r.star,
        r.band,
        r.x_px,
        r.y_px,
        r.x_arcmin,
        r.y_arcmin,
        r.n_frames
    );
    outln!(
        "calibration {} (HWP zero angle {:+.2} deg, model error {:.3} %)",
        cal.display(),
        r.hwp_chi_offset_deg,
        100.0 * r.model_error
    );
    outln!(
        "  measured   P = {:.3} +- {:.3} %   chi = {:.1} +- {:.1} deg",
        100.0 * v.measured_p,
        100.0 * v.sigma_p,
        v.measured_chi_deg,
        v.sigma_chi_deg
    );
    outln!(
        "  predicted  P = {:.3} +- {:.3} %   chi = {:.1} deg",
        100.0 * v.predicted_p,
        100.0 * v.sigma_predicted_p,
        v.predicted_chi_deg
    );
    outln!("  difference {:.2} sigma", v.residual_sigma);
    outln!(
        "  corrected  P0 = {:.3} +- {:.3} % (expected {:.3} %): {:.2} sigma",
        100.0 * v.corrected_p,
        100.0 * v.sigma_corrected_p,
        100.0 * v.expected_p,
        v.corrected_residual_sigma
    );
    outln!("{} (threshold {} sigma)", if v.pass { "PASS" } else { "FAIL" }, v.threshold);
}
