//! Half-wave-plate causes of a Mueller field as effects a scene can call for:
//! `[effects.tilted_hwp]` (a plate tilted in the collimated beam, `mueller::causes::
//! tilted_hwp`) and `[effects.wedged_hwp]` (a retardance error varying across the field,
//! `mueller::causes::wedged_hwp`). A polarizing plate is `[effects.pleochroism]` already.
//!
//! These plates differ from field point to field point, while the simulator's optics hold one
//! plate for the whole frame; so each is applied, like `[effects.stressed_lens]`, as the
//! linear block it is equivalent to after the demodulation at the scene's HWP angles
//! (`stokes::equivalent`), per pixel at the plate, after the diattenuation field. The reduced
//! `(q, u)` are then what the plate gives; the individual `F_i` do not carry its `2 theta`
//! terms (which the demodulation removes for full-turn angle sets).

use mueller::causes::{self, UniaxialPlate};
use mueller::linear::LinearBlock;
use serde::{Deserialize, Serialize};
use stokes::StokesSolver;

/// `[effects.tilted_hwp]` of a scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TiltedHwpSpec {
    /// Tilt of the plate (deg) and the azimuth it is tilted towards (deg).
    pub tilt_deg: f64,
    #[serde(default)]
    pub tilt_azimuth_deg: f64,
    /// Angular magnification at the plate (telescope aperture over beam diameter).
    pub magnification: f64,
    /// Order of the quartz plate (0: zero order).
    #[serde(default)]
    pub order: u32,
}

/// `[effects.wedged_hwp]` of a scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WedgedHwpSpec {
    /// Retardance error on the axis (deg) and its gradient (deg per arcmin).
    #[serde(default)]
    pub retardance_error_deg: f64,
    #[serde(default)]
    pub gradient_deg_per_arcmin: [f64; 2],
}

impl TiltedHwpSpec {
    /// A clear error naming the key when the values are not usable.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.tilt_deg.abs() <= 60.0) || !self.tilt_azimuth_deg.is_finite() {
            return Err(format!("effects.tilted_hwp.tilt_deg = {} must be within +-60 deg", self.tilt_deg));
        }
        if !(self.magnification >= 0.0 && self.magnification <= 1000.0) {
            return Err(format!("effects.tilted_hwp.magnification = {} must be in [0, 1000]", self.magnification));
        }
        Ok(())
    }

    /// The equivalent block at `(x, y)` arcmin for the HWP angles of `solver`.
    pub fn block_at(&self, solver: &StokesSolver, x: f64, y: f64) -> LinearBlock {
        let plate = UniaxialPlate::quartz_half_wave_b(self.order);
        let (inc, alpha) = causes::hwp_incidence(
            x,
            y,
            self.tilt_deg.to_radians(),
            self.tilt_azimuth_deg.to_radians(),
            self.magnification,
        );
        stokes::equivalent::equivalent_block(solver, |t| causes::tilted_hwp(&plate, t, inc, alpha))
            .unwrap_or_else(LinearBlock::identity)
    }
}

impl WedgedHwpSpec {
    /// A clear error naming the key when the values are not usable.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.retardance_error_deg.abs() <= 180.0) || !self.gradient_deg_per_arcmin.iter().all(|v| v.abs() <= 180.0)
        {
            return Err(
                "effects.wedged_hwp: retardance_error_deg and gradient_deg_per_arcmin must be within +-180".into()
            );
        }
        Ok(())
    }

    /// The equivalent block at `(x, y)` arcmin for the HWP angles of `solver`.
    pub fn block_at(&self, solver: &StokesSolver, x: f64, y: f64) -> LinearBlock {
        let [gx, gy] = self.gradient_deg_per_arcmin;
        stokes::equivalent::equivalent_block(solver, |t| {
            causes::wedged_hwp(t, x, y, self.retardance_error_deg.to_radians(), gx.to_radians(), gy.to_radians())
        })
        .unwrap_or_else(LinearBlock::identity)
    }
}

/// The plate causes a scene calls for, with the solver of its HWP angles.
pub struct HwpCauses {
    solver: StokesSolver,
    tilted: Option<TiltedHwpSpec>,
    wedged: Option<WedgedHwpSpec>,
}

impl HwpCauses {
    /// The causes given (a scene's `effects`, through `Scene::hwp_causes`), None when neither is
    /// called for; `hwp_angles_deg` are the scene's plate angles, whose solver each cause's
    /// block goes through.
    pub fn new(
        tilted: Option<&TiltedHwpSpec>,
        wedged: Option<&WedgedHwpSpec>,
        hwp_angles_deg: &[f64],
    ) -> Result<Option<Self>, crate::Error> {
        if tilted.is_none() && wedged.is_none() {
            return Ok(None);
        }
        let th: Vec<f64> = hwp_angles_deg.iter().map(|a| a.to_radians()).collect();
        let solver = StokesSolver::new(&th).map_err(|e| crate::Error::Scene {
            path: std::path::PathBuf::from("<scene>"),
            message: format!("hwp_angles_deg: {e}"),
        })?;
        Ok(Some(Self { solver, tilted: tilted.cloned(), wedged: wedged.cloned() }))
    }

    /// The causes as one element of the chain: the plate's equivalent block
    /// ([`block_at`](Self::block_at)) at every field position.
    pub fn into_element(self) -> std::sync::Arc<dyn field::FieldModel> {
        std::sync::Arc::new(field::LinearElement(move |x, y| self.block_at(x, y)))
    }

    /// The product of the plates' equivalent blocks at `(x, y)` arcmin.
    pub fn block_at(&self, x: f64, y: f64) -> LinearBlock {
        let mut b = LinearBlock::identity();
        if let Some(t) = &self.tilted {
            b = LinearBlock(t.block_at(&self.solver, x, y).0 * b.0);
        }
        if let Some(w) = &self.wedged {
            b = LinearBlock(w.block_at(&self.solver, x, y).0 * b.0);
        }
        b
    }

    /// For `--explain`.
    pub fn describe(&self) -> String {
        format!("{:?} {:?}", self.tilted, self.wedged)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A wedge leaves `cos^2(eps / 2)` of the polarization at each point (the plate's
    /// modulation amplitude `(1 - cos delta) / 2` at `delta = pi + eps`).
    #[test]
    fn wedge_scales_polarization_by_cos_squared_half() {
        let w = WedgedHwpSpec { retardance_error_deg: 10.0, gradient_deg_per_arcmin: [5.0, 0.0] };
        let s = StokesSolver::new(&(0..8).map(|k| k as f64 * std::f64::consts::PI / 8.0).collect::<Vec<_>>()).unwrap();
        for x in [-3.0f64, 0.0, 2.0] {
            let eps = (10.0 + 5.0 * x).to_radians();
            let (q, u) = w.block_at(&s, x, 1.0).forward(0.0645, 0.0).unwrap();
            assert!((q - 0.0645 * (0.5 * eps).cos().powi(2)).abs() < 1e-12 && u.abs() < 1e-12);
        }
    }

    /// A scene calls for the plates by TOML; a tilt beyond 60 deg is refused naming the key.
    #[test]
    fn scenes_call_for_the_plates_and_bad_values_are_named() {
        let min = "instrument = \"fors1\"\nfilter = \"B\"\nhwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]\n[sky]\nbrightness_e = 1000\np = 0.0645\n";
        let path = std::path::Path::new("scene.toml");
        let ok = format!(
            "{min}[effects.tilted_hwp]\ntilt_deg = 5\nmagnification = 90\n[effects.wedged_hwp]\nretardance_error_deg = 3\n"
        );
        let sc = crate::scene::Scene::from_toml_str(&ok, path).unwrap();
        let hc = sc.hwp_causes().unwrap().unwrap();
        // At the centre the wedge depolarizes by sin^2(eps/2); the 5 deg tilt adds below 1e-5
        // to that (fourth order; its second-order offset is not a depolarization).
        let ph = mueller::causes::physical_of_block(&hc.block_at(0.0, 0.0));
        let want = (1.5f64.to_radians()).sin().powi(2);
        assert!((ph[5] - want).abs() < 1e-5, "{ph:?} vs {want}");
        let bad = format!("{min}[effects.tilted_hwp]\ntilt_deg = 80\nmagnification = 90\n");
        let e = crate::scene::Scene::from_toml_str(&bad, path).err().unwrap().to_string();
        assert!(e.contains("effects.tilted_hwp"), "{e}");
    }
}
