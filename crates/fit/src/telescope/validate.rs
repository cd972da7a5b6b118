//! Validating a telescope calibration on a standard star (`instpol validate` with a calibration
//! holding a telescope model): the star measured in the frames at the plate, corrected through
//! the calibration's chain ([`crate::correction::chain::Chain`], as `instpol correct` corrects), and judged
//! against its expected intrinsic polarization. [`validate_telescope`] is the workflow from
//! frames: where the parallactic angles come from (given, or the frames' headers each exposure
//! its own track), the band, the frames' zero angle; [`validate_chain`] the judgement of one
//! measured star.

use crate::correction::chain::{Chain, FieldStep, RecordedExposures, RowError, TelescopeStep, Tracks};
use crate::correction::correct::{CorrectOptions, Corrector, WithModelError};
use crate::files::calfile::Calibration;
use crate::models::model::FieldModel;
use crate::telescope::{BandChoiceError, TelescopeFit, Track};
use crate::{Error, Result};

/// Validating a telescope calibration (with or without a field model) on a standard star:
/// the star as measured, what the telescope alone makes of an unpolarized star over the
/// exposure's track, the star corrected through the chain ([`Chain::invert_parts`]) and its
/// distance from its expected intrinsic polarization (Mahalanobis, in sigma). Polarization as
/// fractions, angles in degrees.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ChainValidation {
    pub star: String,
    pub band: String,
    pub telescope_model: &'static str,
    /// A field model was applied too (first, then the telescope).
    pub field_model: bool,
    pub x_arcmin: f64,
    pub y_arcmin: f64,
    pub parallactic_start_deg: f64,
    pub parallactic_end_deg: f64,
    /// The rotator angle applied (0 when the model was fitted without rotator angles).
    pub rotator_deg: f64,
    /// The HWP zero angle (deg) the star, measured at the plate, was turned by into the sky
    /// frame (module docs).
    pub hwp_chi_offset_deg: f64,
    /// Exposures whose telescope was undone one by one, each over its own parallactic track
    /// and demodulated together; 0 when the set's one track was used.
    pub exposures: usize,
    pub measured_q: f64,
    pub measured_u: f64,
    pub sigma_q: f64,
    pub sigma_u: f64,
    pub telescope_q: f64,
    pub telescope_u: f64,
    pub corrected_q: f64,
    pub corrected_u: f64,
    pub sigma_corrected_q: f64,
    pub sigma_corrected_u: f64,
    pub corrected_p: f64,
    pub sigma_corrected_p: f64,
    pub corrected_chi_deg: f64,
    pub sigma_corrected_chi_deg: f64,
    pub expected_q: f64,
    pub expected_u: f64,
    /// The corrected star against its expected polarization (sigma).
    #[serde(rename = "corrected_pull")]
    pub corrected_residual_sigma: f64,
    /// The measured star, uncorrected, against its expected polarization (sigma): how much
    /// the correction mattered.
    #[serde(rename = "uncorrected_pull")]
    pub uncorrected_residual_sigma: f64,
    pub threshold: f64,
    pub pass: bool,
    pub extrapolated: bool,
    /// Things a person should know (not in the JSON).
    #[serde(skip)]
    pub warnings: Vec<String>,
    /// What the star was measured in: the frames' instrument file, filter, plate and
    /// detector, the run's inputs (`None`: a measurement given as numbers, not frames).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub product: Option<skyfield::provenance::Product>,
}

/// Validate the telescope model `tel` (band `band`) and, when given, the field calibration
/// `field` on a star measured at the plate (`measured`, as the reduction sees it; brought into
/// the sky frame by the field calibration's HWP zero angle, or without one by `zero_angle_deg`,
/// the instrument's for the frames' filter: module docs) at field position `(x, y)` arcmin as
/// its exposures saw the telescope: each
/// over its own track when `exposures` lists them ([`crate::telescope::cal::exposure_tracks`]), else over the set's
/// `track` (which also gives the rotator angle and the reported angles). The field
/// model's error at a position is its coefficient covariance plus `model_error` (default
/// [`crate::validate::auto_model_error`]). Passes when the corrected star is within
/// `threshold` sigma of `star`'s expected polarization. A model fitted without rotator angles
/// ([`TelescopeFit::with_rotator`]) holds the standards' rotator angle in its offset: the
/// track's rotator angle is then not applied (said in the warnings when it is not 0).
#[allow(clippy::too_many_arguments)]
pub fn validate_chain(
    field: Option<&Calibration>,
    tel: &TelescopeFit,
    band: &str,
    measured: &crate::standards::MeasuredStar,
    (x, y): (f64, f64),
    mut track: Track,
    exposures: &[skyfield::ExposureTrack],
    star: (&str, crate::standards::Expected),
    opts: &crate::validate::ValidateOptions,
    zero_angle_deg: f64,
) -> Result<ChainValidation> {
    let mut warnings = vec![];
    let zero_angle = field.map_or(zero_angle_deg, |c| c.hwp_chi_offset_deg);
    if zero_angle != zero_angle_deg {
        warnings.push(format!(
            "the field calibration's HWP zero angle {zero_angle} deg is applied; the instrument's for this filter is {zero_angle_deg} deg"
        ));
    }
    if !tel.with_rotator && track.rotator != 0.0 {
        warnings.push(format!(
            "the telescope model was fitted without rotator angles (its offset holds the standards' rotator angle): the frames' rotator angle {:.2} deg is not applied",
            track.rotator.to_degrees()
        ));
        track.rotator = 0.0;
    }
    let me = field.map(|c| opts.model_error.unwrap_or_else(|| crate::validate::auto_model_error(c)));
    let wm = field.zip(me).map(|(c, me)| WithModelError { model: c, sigma: me });
    let field_step = match (&wm, field) {
        (Some(m), Some(c)) => FieldStep::PartialPolarizer {
            corrector: Corrector::new(
                m as &dyn FieldModel,
                CorrectOptions {
                    zero_angle_deg: zero_angle,
                    allow_extrapolation: opts.allow_extrapolation,
                    ..CorrectOptions::for_calibration(c)
                },
            ),
            calibration: c,
        },
        _ => FieldStep::None,
    };
    let recorded = RecordedExposures::new(tel, band, track, exposures, zero_angle.to_radians())?;
    let n_exposures = recorded.as_ref().map_or(0, |r| r.list.len());
    let tracks = match recorded {
        Some(r) => Tracks::Exposures(Box::new(r)),
        None => Tracks::Shared(track),
    };
    let chain =
        Chain::new(Some(zero_angle), field_step, Some(TelescopeStep { fit: tel, band: band.to_string(), tracks }));
    let m = crate::correction::correct::Measurement::at(x, y, *measured, mueller::Frame::Plate);
    let r = chain.invert_parts(0, &m).map_err(|e| match e {
        RowError::Chain(e) => e,
        RowError::Field(e) => Error::Input(e.to_string()),
    })?;
    let c = r.corrected;
    let e = star.1;
    let dist = |got: &mueller::Qu| {
        crate::standards::sigma_from(&e, got).map_err(|err| Error::Input(format!("validating {}: {err}", star.0)))
    };
    let corrected = dist(&mueller::Qu::new(c.q0, c.u0, c.var_q0, c.var_u0, c.cov_qu0))?;
    let uncorrected = dist(measured)?;
    Ok(ChainValidation {
        star: star.0.to_string(),
        band: band.to_string(),
        telescope_model: tel.model.name(),
        field_model: field.is_some(),
        x_arcmin: x,
        y_arcmin: y,
        parallactic_start_deg: track.start.to_degrees(),
        parallactic_end_deg: track.end.to_degrees(),
        rotator_deg: track.rotator.to_degrees(),
        hwp_chi_offset_deg: zero_angle,
        exposures: n_exposures,
        measured_q: measured.q,
        measured_u: measured.u,
        sigma_q: m.qu.sigma_q(),
        sigma_u: m.qu.sigma_u(),
        telescope_q: r.q_tel,
        telescope_u: r.u_tel,
        corrected_q: c.q0,
        corrected_u: c.u0,
        sigma_corrected_q: c.var_q0.max(0.0).sqrt(),
        sigma_corrected_u: c.var_u0.max(0.0).sqrt(),
        corrected_p: c.p0,
        sigma_corrected_p: c.sigma_p0,
        corrected_chi_deg: c.chi0.to_degrees(),
        sigma_corrected_chi_deg: c.sigma_chi0.to_degrees(),
        expected_q: e.q,
        expected_u: e.u,
        corrected_residual_sigma: corrected,
        uncorrected_residual_sigma: uncorrected,
        threshold: opts.threshold,
        pass: corrected <= opts.threshold,
        extrapolated: c.extrapolated,
        warnings,
        product: None,
    })
}

/// Why a telescope calibration cannot be validated on frames; each face words it with its
/// own option names.
#[derive(Debug, thiserror::Error)]
pub enum ValidateError {
    /// The calibration is of another instrument than the frames are read as.
    #[error("the calibration is for instrument {calibration} but the frames are read as instrument {frames}")]
    Instrument { calibration: String, frames: String },
    /// No track was given and the instrument names no header keywords for the angles.
    #[error("instrument {0} has no [telescope] section naming the header keywords of the parallactic angle")]
    NoAngleKeywords(String),
    /// The frames' headers do not give the angles.
    #[error("the parallactic angle of the frames (the telescope model needs it): {0}")]
    Headers(Error),
    /// The band cannot be chosen.
    #[error("{0:?}")]
    Band(BandChoiceError, String),
    #[error("{0}")]
    Other(#[from] Error),
    /// The star could not be measured in the frames.
    #[error("{0}")]
    Measure(#[from] crate::validate::Error),
}

/// A telescope calibration validated on frames ([`validate_telescope`]).
#[derive(Debug, Clone)]
pub struct TelescopeValidation {
    pub result: ChainValidation,
    /// The frames' filter.
    pub filter: String,
    /// Whether the band used is the frames' filter ([`crate::correction::setup::same_filter`]).
    pub band_is_filter: bool,
}

/// Validate the telescope calibration `loaded` (with its field model, when it has one) on the
/// star at `(x_px, y_px)` of `frames` (as `inst` reads them): the star measured
/// ([`crate::validate::measure_frames`]); its exposures over `parang` when given (one track
/// for all), else each over its own track from the headers (the instrument's `[telescope]`
/// keywords); the band asked for, else the field model's filter, else the frames' filter
/// ([`TelescopeFit::choose_band`]); the frames brought into the sky frame by their filter's
/// zero angle; `expected`: the star's name and expected polarization in the band chosen.
pub fn validate_telescope(
    loaded: &crate::files::calibration::CalibrationFile,
    inst: &instrument::Instrument,
    frames: &[std::path::PathBuf],
    (x_px, y_px): (f64, f64),
    parang: Option<Track>,
    band: Option<&str>,
    expected: impl FnOnce(&str) -> Result<(String, crate::standards::Expected)>,
    opts: &crate::validate::ValidateOptions,
) -> std::result::Result<TelescopeValidation, ValidateError> {
    let (field, tel) = loaded.p_phi_models_alone()?;
    let tel = tel.ok_or_else(|| Error::Input("the calibration holds no telescope model".into()))?;
    if crate::correction::setup::is_known(&loaded.instrument) && !inst.writes(&loaded.instrument) {
        return Err(ValidateError::Instrument { calibration: loaded.instrument.clone(), frames: inst.name.clone() });
    }
    crate::validate::check_frames_against(inst, &loaded.setup())?;
    let headers = match (parang, inst.telescope.as_ref()) {
        (Some(_), _) => None,
        (None, Some(t)) => Some(t),
        (None, None) => return Err(ValidateError::NoAngleKeywords(inst.name.clone())),
    };
    let crate::validate::MeasuredFrames { star: measured, filter, exposures } =
        crate::validate::measure_frames(inst, frames, x_px, y_px, opts)?;
    let (track, each) = match (parang, headers) {
        (Some(t), _) => (t, vec![]),
        (None, Some(t)) => {
            crate::telescope::cal::exposure_tracks(&exposures, frames, t).map_err(ValidateError::Headers)?
        }
        (None, None) => unreachable!("refused above"),
    };
    let band = tel
        .choose_band(band, field.map(|c| c.filter.as_str()), Some(&filter))
        .map_err(|e| ValidateError::Band(e, filter.clone()))?;
    let band_is_filter = crate::correction::setup::same_filter(Some(inst), &filter, &band);
    let (name, exp) = expected(&band)?;
    let pos = inst.pixel_to_arcmin(x_px, y_px);
    // The frames are at the plate: their filter's zero angle brings them into the sky frame
    // of the models (crate::telescope::cal module docs).
    let zero_angle_deg = inst.filter(&filter).map_or(0.0, |f| f.chi_offset_deg());
    let mut result =
        validate_chain(field, tel, &band, &measured, pos, track, &each, (&name, exp), opts, zero_angle_deg)?;
    result.product = Some(skyfield::provenance::Product::of_instrument(inst, &filter, None).with_run_inputs());
    Ok(TelescopeValidation { result, filter, band_is_filter })
}
