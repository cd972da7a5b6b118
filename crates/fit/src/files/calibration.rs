//! Any calibration file, read once, and the corrections it defines: the top of the calibration
//! files' layers.
//!
//! A calibration file holds one of four things, told apart by its `HIERARCH IP MODEL`
//! keyword (`docs/calibration-file.md`): a field model of the partial polarizer `M_I(p, phi)`
//! (`eq:instpol`; [`crate::files::calfile`]), a telescope model (`TELESCOPE`, [`crate::telescope::cal`])
//! alone or beside a field model, a Mueller field (`MUELLER`, [`crate::mueller_field::cal`]), or an
//! instrument's constant response from standards (`RESPONSE`, [`crate::response::cal`]).
//! [`load`] is the one reader both faces call: it answers which kind the file is and returns
//! its models; [`crate::correction::request`] makes the correction they define.
//!
//! A field model or a Mueller field may stand among several field elements in order (a lens
//! measured on its own, then the partial polarizer: [`crate::files::elements`]), which the
//! correction inverts together.
//!
//! Layers: this module imports the three file formats; none of them imports it, and they share
//! their keywords through [`crate::files::keys`] only.

use crate::files::calfile::Calibration;
use crate::mueller_field::cal::MuellerCal;
use crate::response::cal::ResponseCal;
use crate::telescope::TelescopeFit;
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
    /// A constant response from standards: `(q0, u0)`, efficiency and angle offset
    /// (`instpol efficiency --output CAL.fits`).
    Response,
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
    pub response: Option<ResponseCal>,
    /// The file's field elements in the order light meets them when it holds several (its own
    /// model among them, [`crate::files::elements`]); empty when it holds its own model alone.
    pub elements: Vec<crate::files::elements::Element>,
    /// What the file is: the product keywords of its primary header (the instrument file's
    /// BLAKE3, the filter, the plate, the detector, the inputs' BLAKE3), `None` for a file
    /// that does not record them (written before products were, or by other software).
    pub product: Option<skyfield::provenance::Product>,
}

/// Read any calibration file: the format version is checked, the kind is read from
/// `HIERARCH IP MODEL`, and each model is read by its own format's reader (which names the
/// keyword, HDU or row at fault). A file with no model is refused.
pub fn load(path: &Path) -> Result<CalibrationFile> {
    let (model, instrument, product) = crate::files::keys::model_instrument_product(path)?;
    let path_buf = path.to_path_buf();
    if model == crate::files::keys::MUELLER_MODEL {
        let m = MuellerCal::load(path)?;
        return Ok(CalibrationFile {
            path: path_buf,
            instrument,
            field: None,
            // A telescope model beside the Mueller field acts before it (absent in the files
            // `calibrate-mueller` writes).
            telescope: crate::telescope::cal::read_hdu(path)?,
            mueller: Some(m),
            response: None,
            elements: crate::files::elements::read(path)?,
            product,
        });
    }
    if model == crate::response::cal::RESPONSE_MODEL {
        let r = ResponseCal::load(path)?;
        return Ok(CalibrationFile {
            path: path_buf,
            instrument,
            field: None,
            telescope: None,
            mueller: None,
            response: Some(r),
            elements: no_elements(path, "a constant response")?,
            product,
        });
    }
    let field = if model == crate::files::keys::TELESCOPE_MODEL { None } else { Some(Calibration::load(path)?) };
    let telescope = crate::telescope::cal::read_hdu(path)?;
    if field.is_none() && telescope.is_none() {
        return Err(Error::BadFile {
            path: path.into(),
            what: format!(
                "MODEL = '{}' but no {} HDU",
                crate::files::keys::TELESCOPE_MODEL,
                crate::telescope::cal::HDU
            ),
        });
    }
    let elements = match field {
        Some(_) => crate::files::elements::read(path)?,
        None => no_elements(path, "a telescope model alone")?,
    };
    Ok(CalibrationFile {
        path: path_buf,
        instrument,
        field,
        telescope,
        mueller: None,
        response: None,
        elements,
        product,
    })
}

/// No field elements besides a model that is not a field element (`what`): a file that
/// places one among several is refused by name.
fn no_elements(path: &Path, what: &str) -> Result<Vec<crate::files::elements::Element>> {
    if crate::files::elements::read(path)?.is_empty() {
        return Ok(vec![]);
    }
    Err(Error::BadFile {
        path: path.into(),
        what: format!("holds {what}, which is not a field element, yet names several field elements (IP NELEM)"),
    })
}

impl CalibrationFile {
    /// The setup of a calibration file: its model's instrument and filter (a telescope model
    /// alone: the file's instrument and no filter, its band checked apart) and what the file's
    /// product keywords record. The detector only where a model depends on the field position
    /// (a field or a Mueller field): a telescope model or a constant response is the same at
    /// every position, on any detector of the instrument.
    pub fn setup(&self) -> crate::correction::setup::Setup {
        let (inst, filter) = match (&self.field, &self.mueller, &self.response) {
            (Some(c), _, _) => (c.instrument.as_str(), c.filter.as_str()),
            (None, Some(m), _) => (m.instrument.as_str(), m.filter.as_str()),
            (None, None, Some(r)) => (r.instrument.as_str(), r.filter.as_str()),
            (None, None, None) => (self.instrument.as_str(), ""),
        };
        let s = crate::correction::setup::Setup::named(inst, filter).with_product(self.product.as_ref());
        if self.field.is_some() || self.mueller.is_some() {
            s
        } else {
            crate::correction::setup::Setup { detector_px: None, pixel_scale_arcsec: None, ..s }
        }
    }

    /// Which models the file holds.
    pub fn kind(&self) -> Kind {
        if self.response.is_some() {
            return Kind::Response;
        }
        match (&self.field, &self.telescope, &self.mueller) {
            (_, _, Some(_)) => Kind::Mueller,
            (Some(_), Some(_), None) => Kind::FieldAndTelescope,
            (None, Some(_), None) => Kind::Telescope,
            _ => Kind::Field,
        }
    }

    /// The field and telescope models, for a use that cannot take a Mueller field (the
    /// catalog's and the standard's corrections through the chain): a Mueller field is refused
    /// by name, and so is a constant response.
    pub fn p_phi_models(&self) -> Result<(Option<&Calibration>, Option<&TelescopeFit>)> {
        if self.response.is_some() {
            return Err(Error::BadFile {
                path: self.path.clone(),
                what: "holds an instrument's constant response from standards (instpol efficiency), not a partial polarizer p, phi or a telescope model: correct with it by instpol correct".into(),
            });
        }
        if self.mueller.is_some() {
            return Err(Error::BadFile {
                path: self.path.clone(),
                what: "holds a Mueller field (instpol calibrate-mueller), not a partial polarizer p, phi or a telescope model: correct with it by instpol correct".into(),
            });
        }
        Ok((self.field.as_ref(), self.telescope.as_ref()))
    }

    /// [`p_phi_models`](Self::p_phi_models) for a prediction through the field model as the
    /// one field element (`validate`): a file of several field elements is refused by name, as
    /// its field model alone is not the instrument's field.
    pub fn p_phi_models_alone(&self) -> Result<(Option<&Calibration>, Option<&TelescopeFit>)> {
        if !self.elements.is_empty() {
            return Err(Error::BadFile {
                path: self.path.clone(),
                what: format!(
                    "holds {} field elements in order (IP NELEM), and a prediction takes one field model: correct with it by instpol correct",
                    self.elements.len()
                ),
            });
        }
        self.p_phi_models()
    }
}
