//! The steps of a telescope calibration from standard stars around the fit
//! ([`crate::telescope`]), as `instpol fit-standards` runs them: which mirror the models start
//! from, the fits of every band (and jointly), and their report (parameters in degrees and
//! nanometres, every point's pull).

use crate::telescope::{fit_band, fit_joint, FitOptions, ModelKind, Observation, TelescopeFit};
use mueller::mirror::MetalTable;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// The mirror the models start from: its optical constants, its name or file, its alumina
/// over-layer (nm, held fixed by the Wiersema model) and where it came from.
#[derive(Debug, Clone)]
pub struct Mirror {
    pub table: MetalTable,
    pub metal: String,
    pub overlayer_nm: f64,
    /// `instrument`, `--metal` (a metal given) or `default` (aluminium).
    pub source: &'static str,
}

/// Why the mirror could not be chosen.
#[derive(Debug, thiserror::Error)]
pub enum MirrorError {
    /// The instrument's oblique mirror has an over-layer the models do not know.
    #[error("instrument {instrument}: mirror {mirror} has over-layer '{overlayer}': the telescope models know alumina over-layers only")]
    Overlayer { instrument: String, mirror: String, overlayer: String },
    /// The metal table of the instrument's mirror (`from_instrument`) or of the given metal.
    #[error("metal {metal}: {source}")]
    Table {
        metal: String,
        from_instrument: Option<(String, String)>,
        #[source]
        source: mueller::Error,
    },
}

/// The chosen mirror, and the instrument's mirror a given metal overrides, if it differs
/// (instrument, mirror, its metal, its over-layer in nm): a face warns of it.
#[derive(Debug, Clone)]
pub struct MirrorChoice {
    pub mirror: Mirror,
    pub overrides: Option<(String, String, String, f64)>,
}

/// A metal by name (`aluminium`, `silver`: built-in tables) or a `lambda,n,k` table file,
/// relative to `base` when it is not a file where it is named.
fn metal_table(m: &str, base: Option<&Path>) -> Result<MetalTable, mueller::Error> {
    if let Ok(t) = MetalTable::builtin(m) {
        return Ok(t);
    }
    let p = match base {
        Some(b) if Path::new(m).is_relative() && !Path::new(m).is_file() => b.join(m),
        _ => PathBuf::from(m),
    };
    MetalTable::read(&p)
}

/// The mirror the telescope models start from: a metal given (`metal`, bare), else the
/// instrument's oblique mirror (the Nasmyth M3 of its `[telescope]` section: its metal, whose
/// table file is read relative to `inst_dir`, the folder of the instrument file, and its
/// alumina over-layer), else bare aluminium. A given metal that differs from the instrument's
/// mirror, or drops its over-layer, is reported in [`MirrorChoice::overrides`].
pub fn choose_mirror(
    metal: Option<&str>,
    inst: Option<&instrument::Instrument>,
    inst_dir: Option<&Path>,
) -> Result<MirrorChoice, MirrorError> {
    let m3 = inst.and_then(|i| i.telescope.as_ref()).and_then(|t| t.oblique_mirror());
    let mut overrides = None;
    if let (Some(i), Some(m)) = (inst, m3) {
        let thick = match m.overlayer.as_deref() {
            None => 0.0,
            Some(o) if o.eq_ignore_ascii_case("alumina") => m.overlayer_thickness_nm,
            Some(o) => {
                return Err(MirrorError::Overlayer {
                    instrument: i.name.clone(),
                    mirror: m.name.clone(),
                    overlayer: o.to_string(),
                })
            }
        };
        match metal {
            Some(given) => {
                if !given.eq_ignore_ascii_case(&m.metal) || thick > 0.0 {
                    overrides = Some((i.name.clone(), m.name.clone(), m.metal.clone(), thick));
                }
            }
            None => {
                let table = metal_table(&m.metal, inst_dir).map_err(|source| MirrorError::Table {
                    metal: m.metal.clone(),
                    from_instrument: Some((i.name.clone(), m.name.clone())),
                    source,
                })?;
                let mirror = Mirror { table, metal: m.metal.clone(), overlayer_nm: thick, source: "instrument" };
                return Ok(MirrorChoice { mirror, overrides: None });
            }
        }
    }
    let (metal, source) = match metal {
        Some(m) => (m.to_string(), "--metal"),
        None => ("aluminium".to_string(), "default"),
    };
    let table = metal_table(&metal, None).map_err(|source| MirrorError::Table {
        metal: metal.clone(),
        from_instrument: None,
        source,
    })?;
    Ok(MirrorChoice { mirror: Mirror { table, metal, overlayer_nm: 0.0, source }, overrides })
}

/// The bands of `obs` in the order they first appear.
pub fn bands_of(obs: &[Observation]) -> Vec<String> {
    let mut bands: Vec<String> = Vec::new();
    for o in obs {
        if !bands.contains(&o.band) {
            bands.push(o.band.clone());
        }
    }
    bands
}

/// Every fit asked for: each band on its own with each of `models`, then (with `joint`) all
/// bands together with each model; each with whether it is joint. A failed fit names its band
/// (or "joint fit") and model.
pub fn fit_all(
    obs: &[Observation],
    models: &[ModelKind],
    table: &MetalTable,
    opts: &FitOptions,
    joint: bool,
) -> Result<Vec<(TelescopeFit, bool)>, (String, crate::Error)> {
    let mut fits = Vec::new();
    for b in &bands_of(obs) {
        let sel: Vec<Observation> = obs.iter().filter(|o| &o.band == b).cloned().collect();
        for &m in models {
            let f = fit_band(m, &sel, table, opts).map_err(|e| (format!("band {b}, model {}", m.name()), e))?;
            fits.push((f, false));
        }
    }
    if joint {
        for &m in models {
            let f = fit_joint(m, obs, table, opts, true).map_err(|e| (format!("joint fit, model {}", m.name()), e))?;
            fits.push((f, true));
        }
    }
    Ok(fits)
}

/// A fitted parameter in the report's units: angles (`offset`) in degrees, the over-layer in
/// nm, `q0`, `u0` as fractions.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParamReport {
    pub name: String,
    pub value: f64,
    pub sigma_value: f64,
    pub unit: &'static str,
}

/// One standard's measurement against the model.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PointReport {
    pub star: String,
    pub band: String,
    pub source: String,
    pub parallactic_deg: f64,
    pub q: f64,
    pub u: f64,
    pub q_model: f64,
    pub u_model: f64,
    pub pull: f64,
    pub flagged: bool,
}

/// One of the oxide model's local minima in the over-layer thickness.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MinimumReport {
    pub thickness_nm: f64,
    pub chi2: f64,
    pub delta_chi2: f64,
}

/// One telescope fit, reported (`instpol fit-standards --json`, one per fit).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FitReport {
    pub model: &'static str,
    /// The mirror's metal table, its fixed over-layer (nm) and where they came from
    /// (instrument, --metal or default).
    pub metal: String,
    pub overlayer_nm: f64,
    pub mirror_source: &'static str,
    /// The oxide model's local minima in the thickness within delta chi2 < 4, best first.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub minima: Vec<MinimumReport>,
    pub bands: Vec<String>,
    pub joint: bool,
    pub params: Vec<ParamReport>,
    pub chi2: f64,
    pub n_dof: usize,
    pub chi2_dof: f64,
    pub error_scaling: &'static str,
    pub error_factor: f64,
    pub rms_q: f64,
    pub rms_u: f64,
    pub n_used: usize,
    pub n_total: usize,
    /// The flagged points: "star (source, pull P)".
    pub flagged: Vec<String>,
    pub points: Vec<PointReport>,
    /// The calibration file this fit was written to, if any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub output: Option<PathBuf>,
    /// What the model is of: the instrument file and detector (`--instrument`), the run's
    /// inputs; omitted without an instrument.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub product: Option<skyfield::provenance::Product>,
}

impl FitReport {
    /// The report of fit `f` (`joint` or of one band) from `mirror`, of the instrument
    /// `product` says (`None`: none given).
    pub fn new(f: &TelescopeFit, joint: bool, mirror: &Mirror, product: Option<skyfield::provenance::Product>) -> Self {
        FitReport {
            model: f.model.name(),
            metal: mirror.metal.clone(),
            overlayer_nm: mirror.overlayer_nm,
            mirror_source: mirror.source,
            minima: f
                .minima
                .iter()
                .map(|m| MinimumReport { thickness_nm: m.thickness_nm, chi2: m.chi2, delta_chi2: m.delta_chi2 })
                .collect(),
            bands: f.bands.iter().map(|b| b.0.clone()).collect(),
            joint,
            params: f
                .params
                .iter()
                .map(|p| {
                    let angle = p.name.starts_with("offset");
                    let unit = if angle {
                        "deg"
                    } else if p.name == "thickness_nm" {
                        "nm"
                    } else if p.name.starts_with('q') || p.name.starts_with('u') {
                        "fraction"
                    } else {
                        ""
                    };
                    let s = if angle { 180.0 / std::f64::consts::PI } else { 1.0 };
                    ParamReport { name: p.name.clone(), value: p.value * s, sigma_value: p.sigma * s, unit }
                })
                .collect(),
            chi2: f.chi2,
            n_dof: f.dof,
            chi2_dof: f.chi2_reduced,
            error_scaling: f.error_scaling.name(),
            error_factor: f.error_factor,
            rms_q: f.rms_q,
            rms_u: f.rms_u,
            n_used: f.n_used(),
            n_total: f.points.len(),
            flagged: f
                .points
                .iter()
                .filter(|p| p.flagged)
                .map(|p| format!("{} ({}, pull {:.1})", p.obs.star, p.obs.source, p.pull))
                .collect(),
            points: f
                .points
                .iter()
                .map(|p| PointReport {
                    star: p.obs.star.clone(),
                    band: p.obs.band.clone(),
                    source: p.obs.source.clone(),
                    parallactic_deg: p.obs.parallactic.to_degrees(),
                    q: p.obs.qu.q,
                    u: p.obs.qu.u,
                    q_model: p.q_model,
                    u_model: p.u_model,
                    pull: p.pull,
                    flagged: p.flagged,
                })
                .collect(),
            output: None,
            product,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Without an instrument the models start from bare aluminium, or the metal given; an
    /// unknown metal is refused naming it.
    #[test]
    fn mirror_defaults_and_given_metal() {
        let c = choose_mirror(None, None, None).unwrap();
        assert_eq!((c.mirror.metal.as_str(), c.mirror.overlayer_nm, c.mirror.source), ("aluminium", 0.0, "default"));
        assert!(c.overrides.is_none());
        let c = choose_mirror(Some("silver"), None, None).unwrap();
        assert_eq!((c.mirror.metal.as_str(), c.mirror.source), ("silver", "--metal"));
        let e = choose_mirror(Some("no-such-metal.txt"), None, None).unwrap_err().to_string();
        assert!(e.contains("no-such-metal.txt"), "{e}");
    }
}
