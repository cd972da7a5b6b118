//! Polarization ray tracing of a lens collimator: from an optical prescription to the
//! instrumental polarization field `p(r)`, `phi(alpha)` and its wavelength law
//! (the mechanism of the paper's section `sec:cause`).
//!
//! # Model
//!
//! The telescope focal plane (the polarimetric mask) is at `z = 0`; light travels along `+z`.
//! A field point at `(x, y)` arcmin sits at `(x, y) * 60 / field_scale_arcsec_per_mm` mm and
//! sends a cone of the telescope focal ratio towards the collimator, its axis (the chief ray)
//! pointing away from the telescope exit pupil (`exit_pupil_distance_mm` before the focal
//! plane; telecentric if absent). Real rays are traced through the surfaces (conic sections,
//! Snell's law in 3-D). At each intersection the Fresnel / thin-film amplitude coefficients of
//! the surface's coating at the local angle of incidence act in the local s/p basis; they are
//! accumulated as Chipman's 3 x 3 polarization ray-tracing matrix
//! `P = t_s s s^T + t_p p' p^T + k' k^T` (flux-normalized `t`, so that `|t|^2` is the
//! transmittance). The product over the surfaces is projected on transverse bases of the
//! entering and leaving rays (the global x, y axes carried to each ray by the minimal
//! rotation of `z` onto the ray) into a Jones matrix, converted to a Mueller matrix, and the
//! Mueller matrices are summed incoherently over the pupil: Gauss-Legendre rings in
//! `rho^2` (equal area) and equally spaced spokes, uniform illumination, optional central
//! obstruction; rays outside a clear aperture or totally reflected are lost.
//!
//! For unpolarized input, the field point's instrumental polarization is the polarizance
//! `p = sqrt(M10^2 + M20^2) / M00` with angle `phi = atan2(M20, M10) / 2` in `[0, pi)`, the
//! paper's `M_I(p, phi)` of section `sec:instr`.
//!
//! # Field file (`instpol-field-v1`)
//!
//! [`FieldFile`] is written as JSON:
//!
//! ```text
//! {
//!   "format": "instpol-field-v1",
//!   "source": "ray trace of <prescription description>",
//!   "wavelength_nm": 554.0,
//!   "radius_arcmin": [0.0, 0.5, ...],      // increasing, from the optical axis
//!   "p": [0.0, 1.2e-4, ...],               // fraction, same length
//!   "phi_rel_deg": [0.0, 0.0, ...],        // phi - alpha (deg): 0 means radial
//!   "polynomial": { "powers": [1, 2, 3], "coefficients": [...] }  // p(r) = sum c_k r^k
//! }
//! ```
//!
//! The field is rotationally symmetric about the optical axis (at the detector centre): a
//! reader interpolates `p` linearly in `radius_arcmin` (or evaluates the polynomial) at
//! `r = hypot(x, y)` and takes the angle `phi = atan2(y, x) + phi_rel` (radial).

mod glass;
mod trace;

pub use glass::{catalog, Dispersion, CATALOG_NAMES};
pub use trace::{
    fit_radial, Compiled, FieldFile, FieldPoint, Intersection, Polynomial, Sampling, WavelengthLaw, PAPER_LAW_A,
    PAPER_LAW_B,
};

use crate::thinfilm::Layer;
use crate::Error;
use serde::{Deserialize, Serialize};

/// An optical prescription: the telescope beam and the collimator surfaces.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Prescription {
    /// What this is (and whether it is an approximation).
    #[serde(default)]
    pub description: String,
    /// Telescope focal ratio (f-number of the beam at the focal plane).
    pub focal_ratio: f64,
    /// Focal-plane scale (arcsec per mm).
    pub field_scale_arcsec_per_mm: f64,
    /// Radius of the field to trace (arcmin), e.g. the half-diagonal of the detector.
    pub field_radius_arcmin: f64,
    /// Distance of the telescope exit pupil before the focal plane (mm); absent: telecentric.
    #[serde(default)]
    pub exit_pupil_distance_mm: Option<f64>,
    /// Central obstruction as a fraction of the pupil diameter (0 = none).
    #[serde(default)]
    pub central_obstruction: f64,
    /// Distance from the focal plane to the first surface's vertex (mm).
    pub first_surface_distance_mm: f64,
    /// Coating of every air-glass surface that does not give its own.
    #[serde(default)]
    pub default_coating: Option<Coating>,
    /// Glasses defined here (looked up before the built-in catalog).
    #[serde(default)]
    pub glasses: Vec<GlassDef>,
    /// Surfaces in the order light meets them.
    pub surfaces: Vec<Surface>,
}

/// One refracting surface.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Surface {
    #[serde(default)]
    pub name: String,
    /// Vertex radius of curvature (mm), positive when the centre lies after the vertex
    /// (`+z`); absent: flat.
    #[serde(default)]
    pub radius_mm: Option<f64>,
    /// Conic constant (0 sphere, -1 paraboloid).
    #[serde(default)]
    pub conic: f64,
    /// Distance to the next surface's vertex (mm).
    pub thickness_mm: f64,
    /// Medium after the surface: "air", a catalog glass or a name from `glasses`.
    pub glass: String,
    /// Clear aperture (diameter, mm).
    pub clear_aperture_mm: f64,
    /// Coating; absent: the prescription's `default_coating` on air-glass surfaces, none
    /// elsewhere; `{ layers = [] }`: explicitly uncoated.
    #[serde(default)]
    pub coating: Option<Coating>,
}

/// A thin-film coating, layers listed from the air side (from the incident side for a
/// surface between two glasses).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Coating {
    pub layers: Vec<CoatingLayer>,
}

/// A coating layer: a material (catalog or `glasses` name) or a constant `index`, and a
/// physical `thickness_nm` or `quarter_wave_nm` (quarter-wave optical thickness at that
/// wavelength, normal incidence).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoatingLayer {
    #[serde(default)]
    pub material: Option<String>,
    #[serde(default)]
    pub index: Option<f64>,
    #[serde(default)]
    pub thickness_nm: Option<f64>,
    #[serde(default)]
    pub quarter_wave_nm: Option<f64>,
}

/// A user glass: exactly one of Sellmeier (`sellmeier_b` and `sellmeier_c`, um^2), Cauchy
/// (`cauchy = [A, B, C]`, um) or a constant `index`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GlassDef {
    pub name: String,
    #[serde(default)]
    pub sellmeier_b: Option<[f64; 3]>,
    #[serde(default)]
    pub sellmeier_c: Option<[f64; 3]>,
    #[serde(default)]
    pub cauchy: Option<[f64; 3]>,
    #[serde(default)]
    pub index: Option<f64>,
}

fn invalid(what: impl Into<String>, why: impl Into<String>) -> Error {
    Error::Invalid { what: what.into(), why: why.into() }
}

impl Prescription {
    /// The dispersion of a named medium.
    pub fn dispersion(&self, name: &str) -> Result<Dispersion, Error> {
        if let Some(g) = self.glasses.iter().find(|g| g.name.eq_ignore_ascii_case(name)) {
            return match (g.sellmeier_b, g.sellmeier_c, g.cauchy, g.index) {
                (Some(b), Some(c), None, None) => Ok(Dispersion::Sellmeier { b, c }),
                (None, None, Some([a, b, c]), None) => Ok(Dispersion::Cauchy { a, b, c }),
                (None, None, None, Some(n)) => Ok(Dispersion::Constant(n)),
                _ => Err(invalid(
                    format!("glasses.{}", g.name),
                    "give exactly one of sellmeier_b + sellmeier_c, cauchy, index",
                )),
            };
        }
        catalog(name).ok_or_else(|| {
            invalid(format!("glass '{name}'"), format!("unknown: not in [[glasses]] nor the catalog ({CATALOG_NAMES})"))
        })
    }

    /// Check every number and name (surfaces are named `surfaces[i]` in errors).
    pub fn validate(&self) -> Result<(), Error> {
        let pos = |v: f64, what: &str| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(invalid(what.to_string(), format!("{v} must be a positive number")))
            }
        };
        pos(self.focal_ratio, "optics.focal_ratio")?;
        pos(self.field_scale_arcsec_per_mm, "optics.field_scale_arcsec_per_mm")?;
        pos(self.field_radius_arcmin, "optics.field_radius_arcmin")?;
        pos(self.first_surface_distance_mm, "optics.first_surface_distance_mm")?;
        if let Some(l) = self.exit_pupil_distance_mm {
            pos(l, "optics.exit_pupil_distance_mm")?;
        }
        if !(0.0..0.95).contains(&self.central_obstruction) {
            return Err(invalid(
                "optics.central_obstruction",
                format!("{} must be in [0, 0.95)", self.central_obstruction),
            ));
        }
        if self.surfaces.is_empty() {
            return Err(invalid("optics.surfaces", "need at least one surface"));
        }
        for (i, s) in self.surfaces.iter().enumerate() {
            let w = format!(
                "optics.surfaces[{i}]{}",
                if s.name.is_empty() { String::new() } else { format!(" ({})", s.name) }
            );
            if let Some(r) = s.radius_mm {
                if !(r.is_finite() && r != 0.0) {
                    return Err(invalid(format!("{w}.radius_mm"), format!("{r}: omit the key for a flat surface")));
                }
            }
            if !s.conic.is_finite() {
                return Err(invalid(format!("{w}.conic"), "must be finite"));
            }
            if !(s.thickness_mm.is_finite() && s.thickness_mm >= 0.0) {
                return Err(invalid(format!("{w}.thickness_mm"), format!("{} must be >= 0", s.thickness_mm)));
            }
            pos(s.clear_aperture_mm, &format!("{w}.clear_aperture_mm"))?;
            let d = self.dispersion(&s.glass).map_err(|e| invalid(format!("{w}.glass"), e.to_string()))?;
            for lam in [350.0, 550.0, 1000.0] {
                let n = d.index(lam);
                if !(n.is_finite() && n >= 1.0) {
                    return Err(invalid(format!("{w}.glass"), format!("index {n} at {lam} nm is not >= 1")));
                }
            }
            if let Some(c) = &s.coating {
                self.layers(c, 550.0).map_err(|e| invalid(format!("{w}.coating"), e.to_string()))?;
            }
        }
        if let Some(c) = &self.default_coating {
            self.layers(c, 550.0).map_err(|e| invalid("optics.default_coating", e.to_string()))?;
        }
        Ok(())
    }

    /// The coating's layers at `wavelength_nm`, listed from the air (or incident) side.
    pub fn layers(&self, c: &Coating, wavelength_nm: f64) -> Result<Vec<Layer>, Error> {
        c.layers
            .iter()
            .enumerate()
            .map(|(k, l)| {
                let what = format!("layers[{k}]");
                let disp = match (&l.material, l.index) {
                    (Some(m), None) => self.dispersion(m)?,
                    (None, Some(n)) if n.is_finite() && n >= 1.0 => Dispersion::Constant(n),
                    _ => return Err(invalid(what, "give either material or index (>= 1)")),
                };
                let d = match (l.thickness_nm, l.quarter_wave_nm) {
                    (Some(d), None) if d.is_finite() && d >= 0.0 => d,
                    (None, Some(l0)) if l0.is_finite() && l0 > 0.0 => l0 / (4.0 * disp.index(l0)),
                    _ => return Err(invalid(what, "give either thickness_nm (>= 0) or quarter_wave_nm (> 0)")),
                };
                Ok(Layer::new(disp.index(wavelength_nm), d))
            })
            .collect()
    }

    /// The prescription with every index and coating evaluated at `wavelength_nm`.
    pub fn compile(&self, wavelength_nm: f64) -> Result<Compiled, Error> {
        self.validate()?;
        if !(wavelength_nm.is_finite() && wavelength_nm > 100.0 && wavelength_nm < 30000.0) {
            return Err(Error::OutOfRange { name: "wavelength (nm)", value: wavelength_nm, range: "(100, 30000)" });
        }
        Compiled::new(self, wavelength_nm)
    }
}

#[cfg(test)]
mod tests;
