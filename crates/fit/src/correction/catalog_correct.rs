//! A catalog of stars (`skyfield::catalog`) corrected with a calibration in the same run
//! (`instpol catalog --cal`): each measured star's `(q, u)` goes through the calibration's
//! chain ([`crate::correction::chain::Chain::invert`]), at its field position.
//!
//! The zero angle: the catalog's `q, u` are already in the sky's frame (the filter's HWP zero
//! angle of the instrument file applied), while the chain undoes the calibration's zero angle
//! itself, so only the difference `calibration - catalog` is applied; the same angle in both
//! is applied once, not twice.
//!
//! A calibration with a telescope model undoes the field and the telescope as the catalog's
//! exposures saw it: each exposure over its own parallactic track from its header,
//! demodulated together (every star of a catalog was measured in the same exposures, so
//! their demodulations are built once). The rules are [`crate::correction::request`]'s, as for
//! `instpol correct`: the catalog is a table of rows that carry the zero angle of the
//! catalog's instrument file and recorded their exposures.

use crate::correction::correct::Measurement;
use crate::correction::correct::{CorrectOptions, Corrected};
use skyfield::catalog::Catalog;

/// Why a catalog cannot be corrected with a calibration.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Frames of another instrument, filter or plate than the calibration's
    /// ([`crate::correction::setup::check_compatible`]).
    #[error("{0}: a calibration corrects data of its own instrument and filter only")]
    Mismatch(crate::correction::setup::Mismatch),
    #[error("star {id} at ({x:.2}, {y:.2}) arcmin: {source}")]
    Star { id: usize, x: f64, y: f64, source: crate::correction::correct::Error },
    #[error("star {id} at ({x:.2}, {y:.2}) arcmin: {source}")]
    Chain { id: usize, x: f64, y: f64, source: crate::Error },
    #[error("the catalog's exposures: {0}")]
    Exposures(String),
    #[error("no field model to correct with")]
    NoModel,
    #[error("{0}")]
    Calibration(crate::Error),
    #[error(
        "the calibration holds a telescope model, which needs the frames' parallactic angles, but instrument {0} names no header keyword for them ([telescope] parang_start_keyword): correct a written catalog with the set's parallactic track instead (instpol correct --parang)"
    )]
    NoParallacticKeyword(String),
    #[error("the parallactic angle of the frames (the telescope model needs it): {0}")]
    Headers(crate::Error),
    #[error(
        "the telescope model has bands {bands}{}: it cannot tell which to use (correct a written catalog with instpol correct --band)",
        frames.as_deref().map_or(String::new(), |f| format!(" and the frames' filter is {f}"))
    )]
    Band { bands: String, frames: Option<String> },
    #[error(
        "the telescope model was fitted with rotator angles, but instrument {0} names no rotator keyword ([telescope] rotator_keyword): correct a written catalog with instpol correct --rotator"
    )]
    NoRotator(String),
}

/// The telescope model a catalog was corrected with: its name, the band used, and how many
/// exposures were undone one by one.
#[derive(Debug, Clone, PartialEq)]
pub struct TelescopeUsed {
    pub model: &'static str,
    pub band: String,
    pub exposures: usize,
}

/// Correct a catalog made by `skyfield::catalog::catalog_files` from `frames` (as given) with
/// a calibration file's models ([`crate::files::calibration::load`]): the field model alone, or the
/// chain with its telescope model ([`crate::correction::request::plan_rows`]) over each exposure's own track from the frames' headers (the instrument's `[telescope]`
/// keywords; the rotator angle only for a model fitted with it), in the band the field model's
/// filter, else the frames' filter, else the model's only band, names. The one rule of
/// `instpol catalog --cal` and the Python package's `catalog(cal=...)`.
pub fn correct_catalog_loaded(
    cat: &Catalog,
    inst: &instrument::Instrument,
    frames: &[std::path::PathBuf],
    loaded: &crate::files::calibration::CalibrationFile,
    opts: CorrectOptions,
) -> Result<(CorrectedCatalog, Option<TelescopeUsed>), Error> {
    // What the frames are, checked against the calibration by the one rule (the plate first:
    // a quarter-wave plate's V/I is refused before the models are asked for).
    let data = crate::correction::setup::Setup::of_instrument(inst, &cat.filter);
    crate::correction::setup::check_compatible(&data, None).map_err(Error::Mismatch)?;
    let (field, tel) = loaded.p_phi_models().map_err(Error::Calibration)?;
    // The exposures' angles from the frames' headers, for a telescope model.
    let (recorded, band) = match tel {
        None => {
            field.ok_or(Error::NoModel)?;
            (None, None)
        }
        Some(tel) => {
            let t = inst
                .telescope
                .as_ref()
                .filter(|t| !t.parang_start_keyword.is_empty())
                .ok_or_else(|| Error::NoParallacticKeyword(inst.name.clone()))?;
            let (track, each) =
                crate::telescope::cal::exposure_tracks(&cat.frames, frames, t).map_err(Error::Headers)?;
            // The band of the field model's filter, else of the frames' filter.
            let band =
                tel.choose_band(None, field.map(|c| c.filter.as_str()), Some(&cat.filter)).map_err(|e| match e {
                    crate::telescope::BandChoiceError::Missing { bands, .. }
                    | crate::telescope::BandChoiceError::Ambiguous { bands } => {
                        Error::Band { bands: bands.join(", "), frames: Some(cat.filter.clone()) }
                    }
                })?;
            let rotator_rad = (!t.rotator_keyword.is_empty()).then_some(track.rotator);
            let r = skyfield::RecordedAngles {
                parallactic_rad: Some((track.start, track.end)),
                rotator_rad,
                exposure_tracks: each,
            };
            (Some(r), Some(band))
        }
    };
    // The catalog's rows are in the sky frame of the zero angle it was made with (celestial on
    // a rotator: its product says so).
    let frame = cat
        .product
        .as_ref()
        .and_then(|p| p.frame())
        .unwrap_or(mueller::Frame::Sky { zero_angle_deg: cat.chi_offset_deg });
    let request = crate::correction::request::Request {
        band: band.as_deref(),
        frame,
        recorded: recorded.as_ref(),
        data: Some(&data),
        ..crate::correction::request::Request::new(opts.method, opts.allow_extrapolation, opts.extrapolation_rel_error)
    };
    let plan = crate::correction::request::plan_rows(loaded, &request, cat.rows.len()).map_err(|e| match e {
        crate::correction::request::Refusal::NoRotator { .. } => Error::NoRotator(inst.name.clone()),
        crate::correction::request::Refusal::Exposures(e) => Error::Exposures(e),
        crate::correction::request::Refusal::Mismatch { mismatch, .. } => Error::Mismatch(mismatch),
        e => Error::Calibration(crate::Error::Input(e.to_string())),
    })?;
    let mut rows = Vec::with_capacity(cat.rows.len());
    for (i, r) in cat.rows.iter().enumerate() {
        let Some(m) = measurement(r, frame) else {
            rows.push(None);
            continue;
        };
        let c = plan.correct(i, &m).map_err(|e| match e {
            crate::correction::request::RowError::Field(source) => {
                Error::Star { id: r.id, x: r.x_arcmin, y: r.y_arcmin, source }
            }
            crate::correction::request::RowError::Chain(source) => {
                Error::Chain { id: r.id, x: r.x_arcmin, y: r.y_arcmin, source }
            }
        })?;
        rows.push(Some(c));
    }
    let n_extrapolated = rows.iter().flatten().filter(|c| c.extrapolated).count();
    let corrected = CorrectedCatalog { rows, n_extrapolated, chi_offset_applied_deg: plan.to_sky_deg };
    let used =
        plan.telescope.map(|t| TelescopeUsed { model: t.fit.model.name(), band: t.band, exposures: t.exposures });
    Ok((corrected, used))
}

/// The corrections of a catalog's rows (in row order; `None` for a star not measured).
#[derive(Debug, Clone)]
pub struct CorrectedCatalog {
    pub rows: Vec<Option<Corrected>>,
    /// Stars outside the calibrated field, corrected by extrapolation (flagged in their row).
    pub n_extrapolated: usize,
    /// The zero angle applied here (deg): the calibration's minus the catalog's.
    pub chi_offset_applied_deg: f64,
}

/// The measurement of a catalog row (`None` for a star not measured).
fn measurement(r: &skyfield::catalog::Row, frame: mueller::Frame) -> Option<Measurement> {
    let qu = mueller::Qu::from_sigmas(r.q, r.u, r.sigma_q, r.sigma_u, r.cov_qu);
    (r.q.is_finite() && r.u.is_finite()).then_some(Measurement::at(r.x_arcmin, r.y_arcmin, qu, frame))
}
