//! Which linear Mueller block a Mueller field fits ([`Kind`]): the physical form
//! `B · M_I(p, phi)` with the parts asked for (diattenuation always; retardance, rotation,
//! depolarization) or the general 3 x 3 block, with the names of their parameters. The bottom
//! of the Mueller-field modules: the forms ([`crate::mueller_field::forms`]), the fit
//! ([`crate::mueller_field`]) and the smooth forms' builders ([`crate::mueller_field::smooth`]) use it.

use mueller::linear::{self, LinearBlock};
use nalgebra::Matrix3;

/// Which linear block is fitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Kind {
    /// `B · M_I(p, phi)` (see [`mueller::linear`]): the diattenuation always, the others
    /// when asked for.
    Physical { retardance: bool, rotation: bool, depolarization: bool },
    /// The general 3 x 3 block with `m00 = 1`.
    General,
}

/// Names of the full parameter vectors of each kind.
const PHYSICAL_NAMES: [&str; 6] = ["q_diat", "u_diat", "g1_ret", "g2_ret", "rotation", "depolarization"];
const GENERAL_NAMES: [&str; 8] = ["m01", "m02", "m10", "m11", "m12", "m20", "m21", "m22"];

impl Kind {
    /// Diattenuation and retardance: the stressed-lens hypothesis (a lens under stress adds a
    /// retardance field to the partial polarizer, `mueller::causes`).
    pub fn diattenuation_retardance() -> Self {
        Kind::Physical { retardance: true, rotation: false, depolarization: false }
    }

    /// The physical form with the effects named in `s` (comma-separated: retardance,
    /// rotation, depolarization, or none) free besides the diattenuation.
    pub fn parse_free(s: &str) -> std::result::Result<Self, String> {
        let (mut retardance, mut rotation, mut depolarization) = (false, false, false);
        for w in s.split(',').map(str::trim).filter(|w| !w.is_empty()) {
            match w {
                "retardance" => retardance = true,
                "rotation" => rotation = true,
                "depolarization" => depolarization = true,
                "none" => {}
                _ => return Err(format!("unknown effect '{w}' (retardance, rotation, depolarization or none)")),
            }
        }
        Ok(Kind::Physical { retardance, rotation, depolarization })
    }

    /// The model as a vocabulary word: `physical` or `general` (JSON `model`, the
    /// calibration file's `MU MODEL`).
    pub fn model_name(&self) -> &'static str {
        match self {
            Kind::Physical { .. } => "physical",
            Kind::General => "general",
        }
    }

    /// The effects fitted, as vocabulary words (JSON `free`, the calibration file's `MU FREE`):
    /// `diattenuation` always for the physical form, then `retardance`, `rotation`,
    /// `depolarization` when free; the general block names all eight elements' effect as
    /// `general` (it has no physical split).
    pub fn free_words(&self) -> Vec<&'static str> {
        match *self {
            Kind::Physical { retardance, rotation, depolarization } => {
                let mut v = vec!["diattenuation"];
                for (on, w) in [(retardance, "retardance"), (rotation, "rotation"), (depolarization, "depolarization")]
                {
                    if on {
                        v.push(w);
                    }
                }
                v
            }
            Kind::General => vec!["general"],
        }
    }

    /// The kind of a model word and its effect words ([`model_name`](Self::model_name),
    /// [`free_words`](Self::free_words)); an error naming the unknown word.
    pub fn from_words(model: &str, free: &[&str]) -> std::result::Result<Self, String> {
        match model {
            "general" => Ok(Kind::General),
            "physical" => {
                let rest: Vec<&str> = free.iter().copied().filter(|w| *w != "diattenuation").collect();
                if rest.is_empty() {
                    Self::parse_free("none")
                } else {
                    Self::parse_free(&rest.join(","))
                }
            }
            other => Err(format!("unknown Mueller model '{other}' (physical or general)")),
        }
    }

    /// Indices of the free parameters in the full vector of this kind.
    pub fn free(&self) -> Vec<usize> {
        match *self {
            Kind::Physical { retardance, rotation, depolarization } => {
                let mut v = vec![0, 1];
                if retardance {
                    v.extend([2, 3]);
                }
                if rotation {
                    v.push(4);
                }
                if depolarization {
                    v.push(5);
                }
                v
            }
            Kind::General => (0..8).collect(),
        }
    }

    /// The full parameter vector of no instrumental effect.
    pub fn identity(&self) -> Vec<f64> {
        match self {
            Kind::Physical { .. } => vec![0.0; 6],
            Kind::General => vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        }
    }

    /// Name of full parameter `i`.
    pub fn name(&self, i: usize) -> &'static str {
        match self {
            Kind::Physical { .. } => PHYSICAL_NAMES[i],
            Kind::General => GENERAL_NAMES[i],
        }
    }

    /// The physical quantity full parameter `i` belongs to (for messages).
    pub(crate) fn group(&self, i: usize) -> &'static str {
        match self {
            Kind::Physical { .. } => {
                ["diattenuation", "diattenuation", "retardance", "retardance", "rotation", "depolarization"][i]
            }
            Kind::General => GENERAL_NAMES[i],
        }
    }

    /// The linear block of a full parameter vector.
    pub fn block(&self, full: &[f64]) -> LinearBlock {
        match self {
            Kind::Physical { .. } => linear::physical_block(full[0], full[1], [full[2], full[3]], full[4], full[5]),
            Kind::General => {
                #[rustfmt::skip]
                let m = Matrix3::new(
                    1.0,     full[0], full[1],
                    full[2], full[3], full[4],
                    full[5], full[6], full[7],
                );
                LinearBlock(m)
            }
        }
    }
}
