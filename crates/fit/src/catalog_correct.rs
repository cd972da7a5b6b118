//! A catalog of stars (`skyfield::catalog`) corrected with a calibration in the same run
//! (issue 13, `instpol catalog --cal`): each measured star's `(q, u)` goes through the one
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
    let dchi = cal.hwp_chi_offset_deg - cat.chi_offset_deg;
    opts.chi_offset = dchi.to_radians();
    let cor = Corrector::new(cal, opts);
    let mut n_extrapolated = 0;
    let rows = cat
        .rows
        .iter()
        .map(|r| {
            let Some(m) = measurement(r) else { return Ok(None) };
            let c = cor.correct(&m).map_err(|source| Error::Star { id: r.id, x: r.x_arcmin, y: r.y_arcmin, source })?;
            n_extrapolated += c.extrapolated as usize;
            Ok(Some(c))
        })
        .collect::<Result<Vec<_>, Error>>()?;
    Ok(CorrectedCatalog { rows, n_extrapolated, chi_offset_applied_deg: dchi })
}

/// The measurement of a catalog row (`None` for a star not measured).
fn measurement(r: &skyfield::catalog::Row) -> Option<Measurement> {
    (r.q.is_finite() && r.u.is_finite()).then_some(Measurement {
        x: r.x_arcmin,
        y: r.y_arcmin,
        q: r.q,
        u: r.u,
        sigma_q: r.sigma_q,
        sigma_u: r.sigma_u,
        cov_qu: r.cov_qu,
    })
}

/// Correct every measured star of `cat` (taken with `instrument`) through the chain of the
/// field calibration `field` (when given; `opts` as for [`Corrector`], its zero angle left 0)
/// and the telescope model `tel` in `band` (module docs): over each exposure's own track when
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
    let ex = crate::telescope_cal::telescope_exposures(exposures, track.rotator);
    let prepared =
        if ex.is_empty() { None } else { Some(tel.prepare_exposures(band, track, &ex).map_err(Error::Exposures)?) };
    let seen = prepared.as_ref().map_or(Seen::Track(track), Seen::Prepared);
    let mut n_extrapolated = 0;
    let rows = cat
        .rows
        .iter()
        .map(|r| {
            let Some(m) = measurement(r) else { return Ok(None) };
            let c = crate::telescope_cal::correct_chain_seen(cor.as_ref(), tel, band, &m, seen)
                .map_err(|source| Error::Chain { id: r.id, x: r.x_arcmin, y: r.y_arcmin, source })?
                .with_telescope_in_inst();
            n_extrapolated += c.extrapolated as usize;
            Ok(Some(c))
        })
        .collect::<Result<Vec<_>, Error>>()?;
    Ok(CorrectedCatalog { rows, n_extrapolated, chi_offset_applied_deg: 0.0 })
}
