//! `instpol fresnel`: transmission and reflection of one (optionally coated) interface.

use anyhow::{bail, Context, Result};
use mueller::thinfilm::{stack, Layer};
use mueller::C64;
use serde::Serialize;

/// Fresnel transmittance, reflectance, diattenuation and retardance of light going from an
/// incident medium (air by default) through optional thin-film coating layers into a
/// substrate of complex index n + i k (a dielectric, an absorbing glass, or a metal).
///
/// The diattenuation (Tp - Ts) / (Tp + Ts) is the polarization that transmission gives
/// unpolarized light, along the plane of incidence (the paper's section "cause": about 1.7%
/// for uncoated n = 1.5 at 30 deg). Example: a MgF2 quarter-wave at 450 nm on BK7 seen at
/// 30 deg in V:
///
///   instpol fresnel --n-real 1.52 --aoi-deg 30 --wavelength-nm 550 --coating 1.38:81.52
#[derive(clap::Args)]
pub struct Args {
    /// Real part of the substrate refractive index (> 0).
    #[arg(long, allow_negative_numbers = true)]
    pub n_real: f64,
    /// Imaginary part of the substrate index (>= 0; absorption, e.g. 6.69 for aluminium).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0)]
    pub n_imag: f64,
    /// Angle of incidence in degrees, in [0, 90).
    #[arg(long, allow_negative_numbers = true)]
    pub aoi_deg: f64,
    /// Vacuum wavelength in nm (matters only with a coating).
    #[arg(long, allow_negative_numbers = true, default_value_t = 550.0)]
    pub wavelength_nm: f64,
    /// Coating layers from the incident side, "index:thickness_nm,index:thickness_nm,...",
    /// e.g. "1.38:81.52" (a MgF2 quarter-wave at 450 nm: 450 / (4 x 1.38) nm).
    #[arg(long)]
    pub coating: Option<String>,
    /// Refractive index of the (lossless) incident medium.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0)]
    pub n_incident: f64,
    /// Print JSON (fields Ts, Tp, Rs, Rp, diattenuation, retardance_deg) instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Out {
    #[serde(rename = "Ts")]
    ts: f64,
    #[serde(rename = "Tp")]
    tp: f64,
    #[serde(rename = "Rs")]
    rs: f64,
    #[serde(rename = "Rp")]
    rp: f64,
    diattenuation: f64,
    retardance_deg: f64,
    reflection_retardance_deg: f64,
    aoi_deg: f64,
    wavelength_nm: f64,
    n_incident: f64,
    n_real: f64,
    n_imag: f64,
    layers: Vec<LayerOut>,
}

#[derive(Serialize)]
struct LayerOut {
    index: f64,
    thickness_nm: f64,
}

/// Parse "n1:d1,n2:d2,..." into layers, naming the bad item.
fn parse_coating(s: &str) -> Result<Vec<Layer>> {
    let mut out = Vec::new();
    for (k, item) in s.split(',').map(str::trim).enumerate() {
        let k = k + 1;
        let (n, d) = item
            .split_once(':')
            .with_context(|| format!("--coating layer {k} '{item}': expected index:thickness_nm, e.g. 1.38:81.5"))?;
        let n: f64 = n.trim().parse().with_context(|| format!("--coating layer {k}: index '{n}' is not a number"))?;
        let d: f64 =
            d.trim().parse().with_context(|| format!("--coating layer {k}: thickness '{d}' is not a number (nm)"))?;
        if !(n.is_finite() && n > 0.0) {
            bail!("--coating layer {k}: index {n} must be > 0");
        }
        if !(d.is_finite() && d >= 0.0) {
            bail!("--coating layer {k}: thickness {d} nm must be >= 0");
        }
        out.push(Layer::new(n, d));
    }
    Ok(out)
}

pub fn run(a: Args) -> Result<()> {
    if !(a.n_real.is_finite() && a.n_real > 0.0) {
        bail!("--n-real {} must be > 0", a.n_real);
    }
    if !(a.n_imag.is_finite() && a.n_imag >= 0.0) {
        bail!("--n-imag {} must be >= 0 (absorption)", a.n_imag);
    }
    if !(a.n_incident.is_finite() && a.n_incident > 0.0) {
        bail!("--n-incident {} must be > 0", a.n_incident);
    }
    if !(a.aoi_deg.is_finite() && (0.0..90.0).contains(&a.aoi_deg)) {
        bail!("--aoi-deg {} must be in [0, 90)", a.aoi_deg);
    }
    if !(a.wavelength_nm.is_finite() && a.wavelength_nm > 0.0) {
        bail!("--wavelength-nm {} must be > 0", a.wavelength_nm);
    }
    let layers = match &a.coating {
        Some(s) => parse_coating(s)?,
        None => Vec::new(),
    };
    let c = stack(a.n_incident, &layers, C64::new(a.n_real, a.n_imag), a.wavelength_nm, a.aoi_deg.to_radians())?;
    let out = Out {
        ts: c.transmittance_s,
        tp: c.transmittance_p,
        rs: c.reflectance_s,
        rp: c.reflectance_p,
        diattenuation: c.diattenuation_t(),
        retardance_deg: c.retardance_t().to_degrees(),
        reflection_retardance_deg: c.retardance_r().to_degrees(),
        aoi_deg: a.aoi_deg,
        wavelength_nm: a.wavelength_nm,
        n_incident: a.n_incident,
        n_real: a.n_real,
        n_imag: a.n_imag,
        layers: layers.iter().map(|l| LayerOut { index: l.n.re, thickness_nm: l.thickness_nm }).collect(),
    };
    if a.json {
        return crate::util::print_json(&out);
    }
    println!(
        "n0 = {} -> {} layer(s) -> n = {} + {}i at {} deg, {} nm",
        a.n_incident,
        layers.len(),
        a.n_real,
        a.n_imag,
        a.aoi_deg,
        a.wavelength_nm
    );
    println!("{:<14}{:>12}{:>12}", "", "s", "p");
    println!("{:<14}{:>12.6}{:>12.6}", "T", out.ts, out.tp);
    println!("{:<14}{:>12.6}{:>12.6}", "R", out.rs, out.rp);
    println!("{:<14}{:>12.6}{:>12.6}", "T + R", out.ts + out.rs, out.tp + out.rp);
    println!("diattenuation (Tp-Ts)/(Tp+Ts) = {:.4} %", 100.0 * out.diattenuation);
    println!(
        "retardance (p - s): transmitted {:.4} deg, reflected {:.4} deg",
        out.retardance_deg, out.reflection_retardance_deg
    );
    Ok(())
}
