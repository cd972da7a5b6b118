//! A catalog of stars (`skyfield::catalog`) corrected with a calibration in the same run
//! (`instpol catalog --cal`): each measured star's `(q, u)` goes through the one
//! [`Corrector`], at its field position.
//!
//! The zero angle: the catalog's `q, u` are already in the sky's frame (the filter's HWP zero
//! angle of the instrument file applied), while [`Corrector`] undoes the calibration's zero
//! angle itself, so only the difference `calibration - catalog` is applied here; the same
//! angle in both is applied once, not twice.
//!
//! A calibration with a telescope model ([`correct_catalog_chain`]) undoes the field first and
//! then the telescope as the catalog's exposures saw it: each exposure over its own
//! parallactic track from its header, demodulated together (every star of a catalog was
//! measured in the same exposures, so their demodulations are built once). The chain takes
//! the models' angles as fitted (`telescope_cal` module docs): no zero angle is applied.

use crate::correct::Measurement;
use crate::correct::{CorrectOptions, Corrected, Corrector};
use crate::telescope::{Seen, TelescopeFit, Track};
use crate::Calibration;
use skyfield::catalog::Catalog;

/// Why a catalog cannot be corrected with a calibration.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(
        "the calibration is of filter {cal} but the frames are {frames}: a calibration corrects its own filter only"
    )]
    Filter { cal: String, frames: String },
    #[error("the calibration is of instrument {cal} but the frames were reduced as {frames}")]
    Instrument { cal: String, frames: String },
    #[error("star {id} at ({x:.2}, {y:.2}) arcmin: {source}")]
    Star { id: usize, x: f64, y: f64, source: crate::correct::Error },
    #[error("star {id} at ({x:.2}, {y:.2}) arcmin: {source}")]
    Chain { id: usize, x: f64, y: f64, source: crate::Error },
    #[error("the catalog's exposures: {0}")]
    Exposures(crate::Error),
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
/// a calibration file's models ([`crate::calibration::load`]): the field model alone
/// ([`correct_catalog`]), or the chain with its telescope model ([`correct_catalog_chain`])
/// over each exposure's own track from the frames' headers (the instrument's `[telescope]`
/// keywords; the rotator angle only for a model fitted with it), in the band the field model's
/// filter, else the frames' filter, else the model's only band, names. The one rule of
/// `instpol catalog --cal` and the Python package's `catalog(cal=...)`.
pub fn correct_catalog_loaded(
    cat: &Catalog,
    inst: &instrument::Instrument,
    frames: &[std::path::PathBuf],
    loaded: &crate::calibration::CalibrationFile,
    opts: CorrectOptions,
) -> Result<(CorrectedCatalog, Option<TelescopeUsed>), Error> {
    let (field, tel) = loaded.p_phi_models().map_err(Error::Calibration)?;
    let Some(tel) = tel else {
        let cal = field.ok_or(Error::NoModel)?;
        return Ok((correct_catalog(cat, &inst.name, cal, opts)?, None));
    };
    let t = inst
        .telescope
        .as_ref()
        .filter(|t| !t.parang_start_keyword.is_empty())
        .ok_or_else(|| Error::NoParallacticKeyword(inst.name.clone()))?;
    let (recorded, each) = crate::telescope_cal::exposure_tracks(&cat.frames, frames, t).map_err(Error::Headers)?;
    let band = tel.choose_band(None, field.map(|c| c.filter.as_str()), Some(&cat.filter)).map_err(|e| match e {
        crate::telescope::BandChoiceError::Missing { bands, .. }
        | crate::telescope::BandChoiceError::Ambiguous { bands } => {
            Error::Band { bands: bands.join(", "), frames: Some(cat.filter.clone()) }
        }
    })?;
    let rot = (!t.rotator_keyword.is_empty()).then_some(recorded.rotator);
    // The parallactic angles are recorded, so only a missing rotator angle can stop the choice.
    let choice = tel
        .choose_track(None, Some((recorded.start, recorded.end)), None, rot)
        .map_err(|_| Error::NoRotator(inst.name.clone()))?;
    let c = correct_catalog_chain(cat, &inst.name, field, opts, tel, &band, choice.track, &each)?;
    let used = TelescopeUsed { model: tel.model.name(), band, exposures: each.len() };
    Ok((c, Some(used)))
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

/// Correct every measured star of `cat` (taken with `instrument`) with `cal`; `opts` as for
/// [`Corrector`], except its zero angle, which is set from the two files (module docs).
pub fn correct_catalog(
    cat: &Catalog,
    instrument: &str,
    cal: &Calibration,
    mut opts: CorrectOptions,
) -> Result<CorrectedCatalog, Error> {
    if !cal.filter.eq_ignore_ascii_case(&cat.filter) {
        return Err(Error::Filter { cal: cal.filter.clone(), frames: cat.filter.clone() });
    }
    if !cal.instrument.eq_ignore_ascii_case(instrument) {
        return Err(Error::Instrument { cal: cal.instrument.clone(), frames: instrument.to_string() });
    }
    let (dchi, _) = crate::correct::row_zero_angles(Some(cal.hwp_chi_offset_deg), Some(cat.chi_offset_deg));
    opts.chi_offset = dchi.to_radians();
    let cor = Corrector::new(cal, opts);
    let (rows, n_extrapolated) = correct_rows(cat, |r, m| {
        cor.correct(m).map_err(|source| Error::Star { id: r.id, x: r.x_arcmin, y: r.y_arcmin, source })
    })?;
    Ok(CorrectedCatalog { rows, n_extrapolated, chi_offset_applied_deg: dchi })
}

/// Every row of `cat` through `correct` (`None` for a star not measured), and how many of the
/// corrections extrapolated.
fn correct_rows(
    cat: &Catalog,
    mut correct: impl FnMut(&skyfield::catalog::Row, &Measurement) -> Result<Corrected, Error>,
) -> Result<(Vec<Option<Corrected>>, usize), Error> {
    let rows = cat
        .rows
        .iter()
        .map(|r| measurement(r).map(|m| correct(r, &m)).transpose())
        .collect::<Result<Vec<_>, Error>>()?;
    let n = rows.iter().flatten().filter(|c| c.extrapolated).count();
    Ok((rows, n))
}

/// The measurement of a catalog row (`None` for a star not measured).
fn measurement(r: &skyfield::catalog::Row) -> Option<Measurement> {
    (r.q.is_finite() && r.u.is_finite())
        .then_some(Measurement::new(r.x_arcmin, r.y_arcmin, r.q, r.u, r.sigma_q, r.sigma_u, r.cov_qu))
}

/// Correct every measured star of `cat` (taken with `instrument`) through the chain of the
/// field calibration `field` (when given; `opts` as for [`Corrector`], except its zero angle)
/// and the telescope model `tel` in `band` (module docs), in the sky frame
/// (`telescope_cal` module docs: the catalog's q, u carry its zero angle already, so only a
/// field calibration's different one is applied, as [`correct_catalog`] does): over each exposure's own track when
/// `exposures` lists them (`telescope_cal::exposure_tracks` of [`Catalog::frames`], their
/// rotator `track`'s), else over `track`. Each row's `inst` is the field's and the
/// telescope's polarization together.
#[allow(clippy::too_many_arguments)]
pub fn correct_catalog_chain(
    cat: &Catalog,
    instrument: &str,
    field: Option<&Calibration>,
    opts: CorrectOptions,
    tel: &TelescopeFit,
    band: &str,
    track: Track,
    exposures: &[skyfield::ExposureTrack],
) -> Result<CorrectedCatalog, Error> {
    if let Some(cal) = field {
        if !cal.filter.eq_ignore_ascii_case(&cat.filter) {
            return Err(Error::Filter { cal: cal.filter.clone(), frames: cat.filter.clone() });
        }
        if !cal.instrument.eq_ignore_ascii_case(instrument) {
            return Err(Error::Instrument { cal: cal.instrument.clone(), frames: instrument.to_string() });
        }
    }
    let cor = field.map(|c| Corrector::new(c, CorrectOptions { chi_offset: 0.0, ..opts }));
    let (dchi, plate) = crate::correct::row_zero_angles(field.map(|c| c.hwp_chi_offset_deg), Some(cat.chi_offset_deg));
    let prepared = crate::telescope_cal::prepare_recorded(tel, band, track, exposures, plate.to_radians())
        .map_err(Error::Exposures)?;
    let seen = prepared.as_ref().map_or(Seen::Track(track), Seen::Prepared);
    let (rows, n_extrapolated) = correct_rows(cat, |r, m| {
        crate::telescope_cal::correct_chain_seen(cor.as_ref(), tel, band, m, seen, dchi.to_radians())
            .map(|c| c.with_telescope_in_inst())
            .map_err(|source| Error::Chain { id: r.id, x: r.x_arcmin, y: r.y_arcmin, source })
    })?;
    Ok(CorrectedCatalog { rows, n_extrapolated, chi_offset_applied_deg: dchi })
}
