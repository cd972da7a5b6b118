//! Validating a calibration on a standard star in frames, as the paper checks its V map with
//! an unpolarized star in the lower-right corner of FORS1 (section `sec:fors1`): the star is
//! measured by aperture photometry (`skyfield`), its chi corrected for the HWP zero angle of
//! the calibration's filter, and compared with what the calibration predicts at its position
//! ([`crate::standards::validate_star`]: the prediction, the comparison and the pass/fail
//! decision). `instpol validate` and `instpol demo` run this; so can any other front end.

use crate::correction::correct::{CorrectOptions, WithModelError};
use crate::standards::{validate_star as compare, Expected, MeasuredStar, Validation};
use crate::Calibration;
use instrument::Instrument;
use serde::Serialize;
use skyfield::photometry::{photometry, Aperture};
use skyfield::reduce::{read_frames_with, FrameSet};
use std::path::PathBuf;

/// The result of validating a calibration on a star: the comparison (the JSON contract first)
/// and where and what was measured.
#[derive(Debug, Clone, Serialize)]
pub struct ValidationReport {
    #[serde(flatten)]
    pub validation: Validation,
    pub star: String,
    pub band: String,
    pub x_px: f64,
    pub y_px: f64,
    pub x_arcmin: f64,
    pub y_arcmin: f64,
    #[serde(rename = "sigma_model")]
    pub model_error: f64,
    pub hwp_chi_offset_deg: f64,
    pub n_frames: usize,
    /// Things a person should know that do not stop the check (e.g. frames of another filter
    /// than the calibration's); not part of the JSON.
    #[serde(skip)]
    pub warnings: Vec<String>,
    /// What the star was measured in: the frames' instrument file, filter, plate and detector,
    /// the run's inputs (`None`: a measurement given as numbers, not frames).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub product: Option<skyfield::provenance::Product>,
}

/// How to measure and judge the star.
#[derive(Debug, Clone)]
pub struct ValidateOptions {
    pub aperture: Aperture,
    /// Pass threshold in units of the combined error.
    pub threshold: f64,
    /// Extra per-component calibration error (fraction); `None`: [`auto_model_error`].
    pub model_error: Option<f64>,
    pub allow_extrapolation: bool,
    /// Calibration frames (bias, flat) and HWP angles for reading the frames.
    pub read: skyfield::calib::ReadOptions,
}

impl Default for ValidateOptions {
    /// Aperture 10 px with a 14-24 px background annulus, threshold 3 sigma, automatic model
    /// error, no extrapolation.
    fn default() -> Self {
        Self {
            aperture: Aperture { radius_px: 10.0, annulus: Some((14.0, 24.0)) },
            threshold: 3.0,
            model_error: None,
            allow_extrapolation: false,
            read: Default::default(),
        }
    }
}

/// The model error "auto" means for a calibration: its own RMS residual for a radial model
/// (the paper's ~0.05%: a smooth fit predicts one new position no better than the scatter of
/// its data about it), 0 for models that already carry their interpolation error (a residual
/// map, a gridded map).
pub fn auto_model_error(cal: &Calibration) -> f64 {
    match cal.model {
        crate::Model::Radial(_) if cal.rms_residual.is_finite() => cal.rms_residual,
        _ => 0.0,
    }
}

/// Why a star could not be validated.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(
        "the calibration is for instrument {cal} but the frames are read as instrument {frames} (--instrument); use a calibration of {frames}"
    )]
    WrongInstrument { cal: String, frames: String },
    /// The frames' plate or detector is not the calibration's
    /// ([`crate::correction::setup::check_compatible`]).
    #[error("{0}: a calibration is validated on frames of its own plate and detector")]
    Mismatch(crate::correction::setup::Mismatch),
    #[error("{doing}")]
    Frames {
        doing: String,
        #[source]
        source: skyfield::Error,
    },
    #[error("validating {star} at ({x:.3}, {y:.3}) arcmin")]
    Compare {
        star: String,
        x: f64,
        y: f64,
        #[source]
        source: crate::standards::Error,
    },
}

/// Measure a star at 0-based ordinary-image pixel `(x_px, y_px)` in `frames` (all HWP angles
/// of one filter, read as instrument `inst`) and validate `cal` on it; `star` names the star
/// and its expected intrinsic polarization ([`Expected::ZERO`] for a null standard).
pub fn validate_frames(
    cal: &Calibration,
    inst: &Instrument,
    frames: &[PathBuf],
    x_px: f64,
    y_px: f64,
    star: (&str, Expected),
    opts: &ValidateOptions,
) -> Result<ValidationReport, Error> {
    // A calibration's positions and pattern mean nothing on another instrument's detector.
    if !inst.writes(&cal.instrument) {
        return Err(Error::WrongInstrument { cal: cal.instrument.clone(), frames: inst.name.clone() });
    }
    let cal_setup = crate::correction::setup::Setup::named(&cal.instrument, &cal.filter)
        .with_product(cal.provenance.product.as_ref());
    check_frames_against(inst, &cal_setup)?;
    let MeasuredFrames { star: measured, filter, .. } = measure_frames(inst, frames, x_px, y_px, opts)?;
    // Another filter's calibration is allowed (it is how a wrong calibration is shown to
    // fail), but said.
    let mut warnings = vec![];
    if !crate::correction::setup::same_filter(Some(inst), &filter, &cal.filter) {
        warnings.push(format!("the frames are in filter {filter} but the calibration is for filter {}", cal.filter));
    }
    let (x, y) = inst.pixel_to_arcmin(x_px, y_px);
    let mut r = validate_measured(cal, &measured, (x, y), star, opts)?;
    r.x_px = x_px;
    r.y_px = y_px;
    r.n_frames = frames.len();
    r.warnings = warnings;
    r.product = Some(skyfield::provenance::Product::of_instrument(inst, &filter, None).with_run_inputs());
    Ok(r)
}

/// Frames read as `inst` against a calibration of setup `cal`, by the one compatibility check
/// ([`crate::correction::setup::check_compatible`]): the plate and the detector where both
/// sides say. The filter is not compared here: a calibration of another filter is how a
/// wrong calibration is shown to fail, and the callers warn of it.
pub fn check_frames_against(inst: &Instrument, cal: &crate::correction::setup::Setup) -> Result<(), Error> {
    use crate::correction::setup::{check_same_instrument, Setup};
    check_same_instrument(&Setup::of_instrument(inst, ""), cal).map_err(Error::Mismatch)
}

/// A star measured from frames ([`measure_frames`]).
#[derive(Debug, Clone)]
pub struct MeasuredFrames {
    /// Normalized Stokes parameters in the plate frame (no zero angle applied).
    pub star: MeasuredStar,
    /// The frames' filter.
    pub filter: String,
    /// Each exposure's file and HWP angle (deg), angle by angle: what the telescope's
    /// exposure-by-exposure correction needs (`telescope_cal::exposure_tracks`).
    pub exposures: Vec<(PathBuf, f64)>,
}

/// Measure a star at 0-based ordinary-image pixel `(x_px, y_px)` in `frames` (all HWP angles
/// of one filter, read as instrument `inst`): aperture photometry of both beams with the
/// local background subtracted ([`skyfield::photometry::photometry`]).
pub fn measure_frames(
    inst: &Instrument,
    frames: &[PathBuf],
    x_px: f64,
    y_px: f64,
    opts: &ValidateOptions,
) -> Result<MeasuredFrames, Error> {
    let frames_err = |doing: &str| {
        let doing = doing.to_string();
        move |source| Error::Frames { doing, source }
    };
    let fr = read_frames_with(frames, inst, &opts.read, &|| {}).map_err(frames_err("reading the frames"))?;
    let set = FrameSet::from_frames(fr, inst, true).map_err(frames_err("grouping the frames by HWP angle"))?;
    let ph = photometry(&set, inst, x_px, y_px, &opts.aperture)
        .map_err(frames_err(&format!("photometry of the star at ({x_px}, {y_px}) px")))?;
    let qu = ph.reduction.qu;
    Ok(MeasuredFrames {
        star: MeasuredStar { q: qu.q, u: qu.u, var_q: qu.var_q, var_u: qu.var_u, cov_qu: qu.cov_qu },
        filter: set.filter.clone(),
        exposures: set.exposures(),
    })
}

/// Validate `cal` on a star already measured (`measured`, in the plate frame as the
/// reduction gives it) at field position `(x, y)` arcmin: the prediction, the comparison and
/// the pass/fail decision ([`crate::standards::validate_star`]) with the model error of
/// `opts`. The pixel position and frame count of the report are left 0 (set by the caller).
pub fn validate_measured(
    cal: &Calibration,
    measured: &MeasuredStar,
    (x, y): (f64, f64),
    star: (&str, Expected),
    opts: &ValidateOptions,
) -> Result<ValidationReport, Error> {
    let me = opts.model_error.unwrap_or_else(|| auto_model_error(cal));
    let model = WithModelError { model: cal, sigma: me };
    let copts =
        CorrectOptions { allow_extrapolation: opts.allow_extrapolation, ..CorrectOptions::for_calibration(cal) };
    let v = compare(&model, x, y, measured, &star.1, copts, opts.threshold).map_err(|source| Error::Compare {
        star: star.0.to_string(),
        x,
        y,
        source,
    })?;
    Ok(ValidationReport {
        validation: v,
        star: star.0.to_string(),
        band: cal.filter.clone(),
        x_px: 0.0,
        y_px: 0.0,
        x_arcmin: x,
        y_arcmin: y,
        model_error: me,
        hwp_chi_offset_deg: cal.hwp_chi_offset_deg,
        n_frames: 0,
        warnings: vec![],
        product: None,
    })
}
