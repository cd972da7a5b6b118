//! Instrument definitions: what a dual-beam imaging polarimeter looks like to the software.
//!
//! An instrument file (TOML, in `instruments/`) gives the detector, the field, the focal-plane
//! mask strips and the Wollaston throw (which fix where the ordinary and extraordinary images
//! of each strip fall on the detector), the FITS header keywords that carry the HWP angle and
//! the filter, and the filters with their effective wavelengths and HWP chromatic zero angles.
//! Files are validated on load: unknown keys and impossible values are errors that name the
//! file and the key. This crate holds data and geometry only; no optics, no reduction.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

mod format;
pub use format::{Chip, FrameFormat, NumberOrKeyword};

/// Errors while loading an instrument definition.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot read instrument file {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("instrument file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("instrument file {path}: {key} = {value}: {why}")]
    Invalid { path: PathBuf, key: String, value: String, why: String },
    #[error("unknown instrument '{name}': not a file, and not one of the built-in instruments ({known})")]
    Unknown { name: String, known: String },
    #[error("instrument {instrument} has no filter '{filter}' (known: {known})")]
    UnknownFilter { instrument: String, filter: String, known: String },
}

/// Detector geometry and electronics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Detector {
    pub nx: usize,
    pub ny: usize,
    pub pixel_scale_arcsec: f64,
    pub gain_e_per_adu: f64,
    pub read_noise_e: f64,
    pub saturation_adu: f64,
    #[serde(default)]
    pub bias_adu: f64,
}

/// The field of view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Field {
    pub width_arcmin: f64,
    pub height_arcmin: f64,
}

/// Polarimetric optics as the detector sees them: mask strips, throw, header keywords.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Polarimetry {
    pub throw_arcsec: f64,
    /// Detector axis along which the Wollaston separates the beams: "x" or "y".
    pub strip_axis: String,
    pub strip_count: usize,
    /// Lower edge (0-based pixel along the strip axis) of the first strip's ordinary image.
    pub first_strip_y_px: usize,
    /// +1: the extraordinary image lies at +throw from the ordinary one; -1: at -throw.
    pub extraordinary_offset_sign: i32,
    pub hwp_angle_keyword: String,
    pub filter_keyword: String,
    #[serde(default = "default_exptime_keyword")]
    pub exptime_keyword: String,
}

fn default_exptime_keyword() -> String {
    "EXPTIME".into()
}

/// A filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Filter {
    pub name: String,
    #[serde(default)]
    pub aliases: Vec<String>,
    pub lambda_eff_nm: f64,
    /// HWP chromatic zero angle: degrees to add to a measured chi (section `sec:HWP`).
    #[serde(default)]
    pub hwp_chi_offset_deg: f64,
}

/// A whole instrument definition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Instrument {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub detector: Detector,
    pub field: Field,
    pub polarimetry: Polarimetry,
    pub filters: Vec<Filter>,
    /// Optical prescription of the collimator for polarization ray tracing (optional).
    #[serde(default)]
    pub optics: Option<mueller::raytrace::Prescription>,
    /// How raw frames are laid out (HDUs, chips, overscan, binning); see [`FrameFormat`].
    #[serde(default)]
    pub format: FrameFormat,
}

/// One mask strip on the detector: rows `[o_start, o_start + height)` hold its ordinary image
/// and rows `[e_start, e_start + height)` its extraordinary image (along the strip axis).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Strip {
    pub index: usize,
    pub o_start: usize,
    pub e_start: usize,
    pub height: usize,
}

const BUILTIN: &[(&str, &str)] = &[
    ("fors1", include_str!("../../../instruments/fors1.toml")),
    ("fors2", include_str!("../../../instruments/fors2.toml")),
    ("efosc2", include_str!("../../../instruments/efosc2.toml")),
];

impl Instrument {
    /// Load a built-in instrument by name (case-insensitive) or an instrument file by path.
    pub fn load(name_or_path: &str) -> Result<Self, Error> {
        let p = Path::new(name_or_path);
        if p.is_file() {
            return Self::from_file(p);
        }
        let lower = name_or_path.to_ascii_lowercase();
        match BUILTIN.iter().find(|(n, _)| *n == lower) {
            Some((n, text)) => Self::from_toml_str(text, Path::new(&format!("<built-in {n}>"))),
            None => Err(Error::Unknown {
                name: name_or_path.into(),
                known: BUILTIN.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", "),
            }),
        }
    }

    /// Read and validate an instrument file.
    pub fn from_file(path: &Path) -> Result<Self, Error> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io { path: path.into(), source })?;
        Self::from_toml_str(&text, path)
    }

    /// Parse and validate instrument TOML; `path` only labels errors.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Self, Error> {
        let inst: Instrument =
            toml::from_str(text).map_err(|e| Error::Parse { path: path.into(), message: e.to_string() })?;
        inst.validate(path)?;
        Ok(inst)
    }

    fn validate(&self, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| {
            Err(Error::Invalid { path: path.into(), key: key.into(), value, why: why.into() })
        };
        let d = &self.detector;
        if d.nx == 0 || d.ny == 0 {
            return bad("detector.nx/ny", format!("{} x {}", d.nx, d.ny), "the detector must have pixels");
        }
        for (k, v) in
            [("detector.pixel_scale_arcsec", d.pixel_scale_arcsec), ("detector.gain_e_per_adu", d.gain_e_per_adu)]
        {
            if !(v.is_finite() && v > 0.0) {
                return bad(k, v.to_string(), "must be a positive number");
            }
        }
        if !(d.read_noise_e.is_finite() && d.read_noise_e >= 0.0) {
            return bad("detector.read_noise_e", d.read_noise_e.to_string(), "must be >= 0");
        }
        let p = &self.polarimetry;
        if p.strip_axis != "x" && p.strip_axis != "y" {
            return bad("polarimetry.strip_axis", p.strip_axis.clone(), "must be \"x\" or \"y\"");
        }
        if p.extraordinary_offset_sign != 1 && p.extraordinary_offset_sign != -1 {
            return bad(
                "polarimetry.extraordinary_offset_sign",
                p.extraordinary_offset_sign.to_string(),
                "must be 1 or -1",
            );
        }
        if !(p.throw_arcsec.is_finite() && p.throw_arcsec > 0.0) {
            return bad("polarimetry.throw_arcsec", p.throw_arcsec.to_string(), "must be positive");
        }
        if p.strip_count == 0 {
            return bad("polarimetry.strip_count", "0".into(), "need at least one strip");
        }
        if !(d.saturation_adu.is_finite() && d.saturation_adu > 0.0) {
            return bad("detector.saturation_adu", d.saturation_adu.to_string(), "must be a positive number");
        }
        // The strip layout, in floating point first so that absurd values (a throw of 1e308",
        // 2^62 strips) are refused by name instead of overflowing the pixel arithmetic.
        let extent = if p.strip_axis == "y" { d.ny } else { d.nx } as f64;
        let h = (p.throw_arcsec / d.pixel_scale_arcsec).round();
        if !(h >= 1.0 && h <= extent) {
            return bad(
                "polarimetry.throw_arcsec",
                p.throw_arcsec.to_string(),
                &format!(
                    "the throw is {h} px at {} arcsec/px (detector.pixel_scale_arcsec): it must be 1 to {extent} px",
                    d.pixel_scale_arcsec
                ),
            );
        }
        let below = if p.extraordinary_offset_sign < 0 { h } else { 0.0 };
        let lo = p.first_strip_y_px as f64 - below;
        let hi = p.first_strip_y_px as f64 + 2.0 * p.strip_count as f64 * h - below;
        if lo < 0.0 || hi > extent {
            let key = if p.first_strip_y_px as f64 >= extent {
                "polarimetry.first_strip_y_px"
            } else {
                "polarimetry.strip_count"
            };
            let value = if key.ends_with("count") { p.strip_count.to_string() } else { p.first_strip_y_px.to_string() };
            return bad(
                key,
                value,
                &format!(
                    "{} strips of {h} px (the throw) from pixel {} span pixels {lo}..{hi}, outside the detector (0..{extent})",
                    p.strip_count, p.first_strip_y_px
                ),
            );
        }
        if let Err((key, value, why)) = self.format.check(d.nx, d.ny) {
            return bad(&key, value, &why);
        }
        if self.filters.is_empty() {
            return bad("filters", "[]".into(), "need at least one filter");
        }
        for f in &self.filters {
            if !(f.lambda_eff_nm.is_finite() && f.lambda_eff_nm > 100.0 && f.lambda_eff_nm < 30000.0) {
                return bad(
                    &format!("filters.{}.lambda_eff_nm", f.name),
                    f.lambda_eff_nm.to_string(),
                    "must be a wavelength in nm",
                );
            }
        }
        Ok(())
    }

    /// The Wollaston throw in pixels (rounded): also the height of each mask strip.
    pub fn throw_px(&self) -> usize {
        (self.polarimetry.throw_arcsec / self.detector.pixel_scale_arcsec).round() as usize
    }

    /// The mask strips with the rows (along the strip axis) of their o and e images.
    pub fn strips(&self) -> Vec<Strip> {
        let h = self.throw_px();
        let p = &self.polarimetry;
        (0..p.strip_count)
            .map(|k| {
                let o = p.first_strip_y_px + 2 * k * h + if p.extraordinary_offset_sign < 0 { h } else { 0 };
                let e = if p.extraordinary_offset_sign > 0 { o + h } else { o - h };
                Strip { index: k, o_start: o, e_start: e, height: h }
            })
            .collect()
    }

    /// Find a filter by name or alias (case-insensitive).
    pub fn filter(&self, name: &str) -> Result<&Filter, Error> {
        self.filters
            .iter()
            .find(|f| f.name.eq_ignore_ascii_case(name) || f.aliases.iter().any(|a| a.eq_ignore_ascii_case(name)))
            .ok_or_else(|| Error::UnknownFilter {
                instrument: self.name.clone(),
                filter: name.into(),
                known: self.filters.iter().map(|f| f.name.as_str()).collect::<Vec<_>>().join(", "),
            })
    }

    /// Field coordinates (arcmin from the detector centre) of 0-based pixel `(x, y)`.
    pub fn pixel_to_arcmin(&self, x: f64, y: f64) -> (f64, f64) {
        let s = self.detector.pixel_scale_arcsec / 60.0;
        ((x - 0.5 * (self.detector.nx as f64 - 1.0)) * s, (y - 0.5 * (self.detector.ny as f64 - 1.0)) * s)
    }

    /// 0-based pixel of field position `(x, y)` in arcmin from the detector centre.
    pub fn arcmin_to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        let s = 60.0 / self.detector.pixel_scale_arcsec;
        (x * s + 0.5 * (self.detector.nx as f64 - 1.0), y * s + 0.5 * (self.detector.ny as f64 - 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fors1_loads_with_paper_facts() {
        let f = Instrument::load("fors1").unwrap();
        assert_eq!(f.detector.pixel_scale_arcsec, 0.2);
        assert_eq!(f.polarimetry.throw_arcsec, 22.0);
        assert_eq!(f.throw_px(), 110);
        // 2048 px * 0.2" = 6.83': the paper's 6.8' field.
        assert!((f.detector.nx as f64 * 0.2 / 60.0 - f.field.width_arcmin).abs() < 0.05);
        for b in ["B", "V", "R", "I", "v_bess"] {
            f.filter(b).unwrap();
        }
        assert!(f.filter("Z").is_err());
        let strips = f.strips();
        assert_eq!(strips.len(), 9);
        for w in strips.windows(2) {
            assert_eq!(w[1].o_start - w[0].o_start, 220);
        }
        assert!(strips.last().unwrap().e_start + 110 <= f.detector.ny);
    }

    #[test]
    fn unknown_key_is_named() {
        let text = include_str!("../../../instruments/fors1.toml").replace("throw_arcsec", "throw_arcsek");
        let e = Instrument::from_toml_str(&text, Path::new("x.toml")).unwrap_err().to_string();
        assert!(e.contains("throw_arcsek") && e.contains("x.toml"), "{e}");
    }

    #[test]
    fn strips_outside_detector_rejected() {
        let text = include_str!("../../../instruments/fors1.toml").replace("strip_count = 9", "strip_count = 10");
        let e = Instrument::from_toml_str(&text, Path::new("x.toml")).unwrap_err().to_string();
        assert!(e.contains("strip_count"), "{e}");
    }

    #[test]
    fn pixel_arcmin_round_trip() {
        let f = Instrument::load("fors1").unwrap();
        let (x, y) = f.pixel_to_arcmin(1023.5, 1023.5);
        assert!(x.abs() < 1e-12 && y.abs() < 1e-12);
        let (px, py) = f.arcmin_to_pixel(-3.1, 2.2);
        let (ax, ay) = f.pixel_to_arcmin(px, py);
        assert!((ax + 3.1).abs() < 1e-12 && (ay - 2.2).abs() < 1e-12);
    }
}
