//! Any calibration file, read once, and the corrections it defines: the top of the calibration
//! files' layers.
//!
//! A calibration file holds one of three things, told apart by its `HIERARCH IP MODEL`
//! keyword (`docs/calibration-file.md`): a field model of the partial polarizer `M_I(p, phi)`
//! (`eq:instpol`; [`crate::calfile`]), a telescope model (`TELESCOPE`, [`crate::telescope_cal`])
//! alone or beside a field model, or a Mueller field (`MUELLER`, [`crate::mueller_cal`]).
//! [`load`] is the one reader both faces call: it answers which kind the file is and returns
//! its models. The map correction each kind makes is [`correct_stokes_map`].
//!
//! Layers: this module imports the three file formats; none of them imports it, and they share
//! their keywords through [`crate::keys`] only.

use crate::calfile::Calibration;
use crate::correct::{correct_map, correct_map_with, CorrectOptions, CorrectedMap, Corrector, MapError, Method};
use crate::mueller_cal::MuellerCal;
use crate::telescope::{TelescopeFit, Track};
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// Which models a calibration file holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// A field model of `M_I(p, phi)` (`instpol calibrate`, `import-map`, `fit`).
    Field,
    /// A telescope model alone (`instpol fit-standards --output`).
    Telescope,
    /// A field model with a telescope model beside it (`fit-standards --output --field-cal`).
    FieldAndTelescope,
    /// A Mueller field (`instpol calibrate-mueller --out CAL.fits`).
    Mueller,
}

/// A calibration file as read by [`load`]: its instrument and the models it holds (a field
/// and/or a telescope model, or a Mueller field alone; [`CalibrationFile::kind`]).
#[derive(Debug, Clone)]
pub struct CalibrationFile {
    pub path: PathBuf,
    /// `HIERARCH IP INSTRUMENT`.
    pub instrument: String,
    pub field: Option<Calibration>,
    pub telescope: Option<TelescopeFit>,
    pub mueller: Option<MuellerCal>,
}

/// Read any calibration file: the format version is checked, the kind is read from
/// `HIERARCH IP MODEL`, and each model is read by its own format's reader (which names the
/// keyword, HDU or row at fault). A file with no model is refused.
pub fn load(path: &Path) -> Result<CalibrationFile> {
    let (model, instrument) = crate::keys::model_and_instrument(path)?;
    let path_buf = path.to_path_buf();
    if model == crate::keys::MUELLER_MODEL {
        let m = MuellerCal::load(path)?;
        return Ok(CalibrationFile { path: path_buf, instrument, field: None, telescope: None, mueller: Some(m) });
    }
    let field = if model == crate::keys::TELESCOPE_MODEL { None } else { Some(Calibration::load(path)?) };
    let telescope = crate::telescope_cal::read_hdu(path)?;
    if field.is_none() && telescope.is_none() {
        return Err(Error::BadFile {
            path: path.into(),
            what: format!("MODEL = '{}' but no {} HDU", crate::keys::TELESCOPE_MODEL, crate::telescope_cal::HDU),
        });
    }
    Ok(CalibrationFile { path: path_buf, instrument, field, telescope, mueller: None })
}

impl CalibrationFile {
    /// Which models the file holds.
    pub fn kind(&self) -> Kind {
        match (&self.field, &self.telescope, &self.mueller) {
            (_, _, Some(_)) => Kind::Mueller,
            (Some(_), Some(_), None) => Kind::FieldAndTelescope,
            (None, Some(_), None) => Kind::Telescope,
            _ => Kind::Field,
        }
    }

    /// The field and telescope models, for a use that cannot take a Mueller field (the
    /// catalog's and the standard's corrections through the chain): a Mueller field is refused
    /// by name.
    pub fn p_phi_models(&self) -> Result<(Option<&Calibration>, Option<&TelescopeFit>)> {
        if self.mueller.is_some() {
            return Err(Error::BadFile {
                path: self.path.clone(),
                what: "holds a Mueller field (instpol calibrate-mueller), not a partial polarizer p, phi or a telescope model: correct with it by instpol correct".into(),
            });
        }
        Ok((self.field.as_ref(), self.telescope.as_ref()))
    }
}

/// What corrects a Stokes map ([`correct_stokes_map`]): the pieces of a calibration file, as
/// `instpol correct` and the Python package load them.
#[derive(Debug, Clone, Copy)]
pub enum MapCorrection<'a> {
    /// A partial-polarizer field (`eq:instpol` inverted, or `eq:approx`), with the HWP zero
    /// angle of the calibration.
    Field { cal: &'a Calibration, method: Method },
    /// A Mueller field (`instpol calibrate-mueller`), inverted exactly in the maps' frame.
    Mueller(&'a MuellerCal),
    /// A telescope model over the exposures' one track, after the field when there is one
    /// ([`crate::telescope_cal::correct_map_chain`]); the band and the track chosen by the
    /// caller ([`TelescopeFit::choose_band`],
    /// [`TelescopeFit::choose_track`]).
    Chain {
        field: Option<(&'a Calibration, Method)>,
        telescope: &'a TelescopeFit,
        band: &'a str,
        track: Track,
        /// Undo the telescope exposure by exposure where the map recorded each one's angles
        /// ([`skyfield::StokesMap::exposure_tracks`]): true when `track` is the map's own,
        /// false when the caller replaced it (the exposures' recorded angles would then
        /// contradict it).
        by_exposure: bool,
        /// The HWP zero angle (deg) of the map's instrument in its filter: what brings the map
        /// (at the plate) into the chain's sky frame when no field calibration gives its own
        /// ([`crate::telescope_cal`] module docs); 0 where the instrument gives none.
        zero_angle_deg: f64,
    },
}

/// Correct a whole Stokes map with a calibration's pieces, and the record the corrected map
/// carries ([`skyfield::StokesMap::write_corrected_fits`]; `calibration`: the file's name).
/// The one map correction of `instpol correct` and the Python package; the caller checks the
/// map's instrument and filter against the calibration's ([`crate::setup::matches_setup`]).
/// - A field: the calibration's HWP zero angle is added to chi (`CORRHWP`).
/// - A Mueller field: inverted exactly after the zero angle its maps were turned by (`CORRHWP`;
///   0 for maps that recorded none), (`eq:approx` is the p, phi model's first order: the front
///   ends refuse it for a Mueller field).
/// - A chain: the map is brought into the sky frame by the field calibration's HWP zero
///   angle, or without a field by its instrument's (`CORRHWP`), then corrected by both models
///   there (module docs of [`crate::telescope_cal`]); the corrected map records the track used
///   (its parallactic and rotator angles).
pub fn correct_stokes_map(
    map: &skyfield::StokesMap,
    with: MapCorrection<'_>,
    allow_extrapolation: bool,
    extrapolation_rel_error: f64,
    calibration: &str,
) -> std::result::Result<(CorrectedMap, skyfield::CorrectionStamp), MapError> {
    let opts = |method, chi_offset| CorrectOptions { method, allow_extrapolation, extrapolation_rel_error, chi_offset };
    let meth = |m: Method| match m {
        Method::Exact => "exact M_I inverse (eq:instpol)",
        Method::FirstOrder => "first order (eq:approx)",
    };
    let stamp = |method: String, hwp: f64, telescope| skyfield::CorrectionStamp {
        calibration: calibration.to_string(),
        method,
        hwp_chi_offset_deg: hwp,
        telescope,
    };
    let corrected = match with {
        MapCorrection::Field { cal, method } => {
            let c = correct_map(cal, map, opts(method, cal.hwp_chi_offset_deg.to_radians()))?;
            Ok((c, stamp(meth(method).into(), cal.hwp_chi_offset_deg, None)))
        }
        MapCorrection::Mueller(mc) => {
            let o = opts(Method::Exact, mc.hwp_chi_offset_deg.to_radians());
            let c = correct_map_with(map, |m| mc.correct(m, &o))?;
            Ok((c, stamp("exact inverse of the Mueller field (calibrate-mueller)".into(), mc.hwp_chi_offset_deg, None)))
        }
        MapCorrection::Chain { field, telescope, band, track, by_exposure, zero_angle_deg } => {
            let cor = field.map(|(cal, method)| Corrector::new(cal, opts(method, 0.0)));
            let z = field.map_or(zero_angle_deg, |(cal, _)| cal.hwp_chi_offset_deg);
            let exposures = if by_exposure { &map.exposure_tracks[..] } else { &[] };
            let mut c = crate::telescope_cal::correct_map_chain(
                cor.as_ref(),
                telescope,
                band,
                map,
                track,
                exposures,
                z.to_radians(),
            )?;
            if !by_exposure {
                c.map.exposure_tracks.clear();
            }
            c.map.parallactic_rad = Some((track.start, track.end));
            if telescope.with_rotator {
                c.map.rotator_rad = Some(track.rotator);
            }
            let mut method = match field {
                None => "telescope model only".to_string(),
                Some((_, m)) => format!("{}, then the telescope", meth(m)),
            };
            if !exposures.is_empty() {
                method += &format!(" (exposure by exposure, {})", exposures.len());
            }
            let t = skyfield::TelescopeStamp {
                model: telescope.model.name().to_string(),
                band: band.to_string(),
                rotator_deg: track.rotator.to_degrees(),
            };
            Ok((c, stamp(method, z, Some(t))))
        }
    };
    // The corrected map is in the sky frame, its zero angle applied (CORRHWP): it no longer
    // lacks one (HWPZERO).
    corrected.map(|(mut c, s)| {
        c.map.hwp_zero_angle_deg = None;
        (c, s)
    })
}
