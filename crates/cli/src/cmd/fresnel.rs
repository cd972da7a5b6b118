//! `instpol fresnel`: transmission and reflection of one (optionally coated) interface.

use anyhow::{bail, Context, Result};
use mueller::mirror::MetalTable;
use mueller::thinfilm::{stack, Layer};
use mueller::C64;
use serde::Serialize;

/// Fresnel transmittance, reflectance, polarization and retardance of light going from an
/// incident medium (air by default) through optional thin-film coating layers (dielectric or
/// absorbing) into a substrate of complex index n + i k (a dielectric, an absorbing glass, or a
/// metal, given by --n-real/--n-imag or read from a table with --metal).
///
/// The transmission diattenuation (Tp - Ts) / (Tp + Ts) is the polarization that transmission
/// gives unpolarized light, along the plane of incidence (the paper's section "cause": about
/// 1.7% for uncoated n = 1.5 at 30 deg). The reflection polarization (Rs - Rp) / (Rs + Rp) is
/// what a mirror gives it, perpendicular to the plane of incidence (a telescope's 45 deg M3).
///
/// Examples: a MgF2 quarter-wave at 450 nm on BK7 seen at 30 deg in V; aluminium at 45 deg in
/// V under 5 nm of oxide:
///
///   instpol fresnel --n-real 1.52 --aoi-deg 30 --wavelength-nm 550 --coating 1.38:81.52
///   instpol fresnel --metal aluminium --aoi-deg 45 --wavelength-nm 550 --coating 1.77:5
#[derive(clap::Args)]
pub struct Args {
    /// Real part of the substrate refractive index (> 0); required unless --metal.
    #[arg(long, allow_negative_numbers = true, required_unless_present = "metal", conflicts_with = "metal")]
    pub n_real: Option<f64>,
    /// Imaginary part of the substrate index (>= 0; absorption, e.g. 6.69 for aluminium).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0, conflicts_with = "metal")]
    pub n_imag: f64,
    /// Substrate n, k from a table at --wavelength-nm: "aluminium" or "silver" (the built-in
    /// tables of instruments/metals/, Rakic et al. 1998), or a file of lines
    /// "lambda_micron,n,k" (header "lambda,n,k" allowed).
    #[arg(long)]
    pub metal: Option<String>,
    /// Angle of incidence in degrees, in [0, 90).
    #[arg(long, allow_negative_numbers = true)]
    pub aoi_deg: f64,
    /// Vacuum wavelength in nm (matters only with a coating).
    #[arg(long, allow_negative_numbers = true, default_value_t = 550.0)]
    pub wavelength_nm: f64,
    /// Coating layers from the incident side, "index:thickness_nm,..." or, for an absorbing
    /// layer, "n:k:thickness_nm", e.g. "1.38:81.52" (a MgF2 quarter-wave at 450 nm:
    /// 450 / (4 x 1.38) nm) or "1.77:5,2.0:0.1:3".
    #[arg(long)]
    pub coating: Option<String>,
    /// Refractive index of the (lossless) incident medium.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0)]
    pub n_incident: f64,
    /// Print JSON (fields t_s, t_p, r_s, r_p, transmission_diattenuation, retardance_deg
    /// (transmitted), reflection_polarization, reflection_retardance_deg, index_real,
    /// index_imag of the substrate used; schemas/fresnel.schema.json) instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Out {
    #[serde(rename = "t_s")]
    ts: f64,
    #[serde(rename = "t_p")]
    tp: f64,
    #[serde(rename = "r_s")]
    rs: f64,
    #[serde(rename = "r_p")]
    rp: f64,
    /// (Tp - Ts) / (Tp + Ts) (one name per quantity: the older `diattenuation` is gone).
    transmission_diattenuation: f64,
    retardance_deg: f64,
    /// (Rs - Rp) / (Rs + Rp).
    reflection_polarization: f64,
    reflection_retardance_deg: f64,
    aoi_deg: f64,
    wavelength_nm: f64,
    #[serde(rename = "index_incident")]
    n_incident: f64,
    #[serde(rename = "index_real")]
    n_real: f64,
    #[serde(rename = "index_imag")]
    n_imag: f64,
    layers: Vec<LayerOut>,
}

#[derive(Serialize)]
struct LayerOut {
    #[serde(rename = "index_real")]
    index: f64,
    #[serde(rename = "index_imag")]
    k: f64,
    thickness_nm: f64,
}

/// Parse "n1:d1,n2:d2,..." into layers, naming the bad item.
fn parse_coating(s: &str) -> Result<Vec<Layer>> {
    let mut out = Vec::new();
    for (k, item) in s.split(',').map(str::trim).enumerate() {
        let k = k + 1;
        let parts: Vec<&str> = item.split(':').collect();
        let (n, kk, d) = match parts[..] {
            [n, d] => (n, "0", d),
            [n, kk, d] => (n, kk, d),
            _ => bail!("--coating layer {k} '{item}': expected index:thickness_nm or n:k:thickness_nm, e.g. 1.38:81.5"),
        };
        let n: f64 = n.trim().parse().with_context(|| format!("--coating layer {k}: index '{n}' is not a number"))?;
        let kk: f64 = kk.trim().parse().with_context(|| format!("--coating layer {k}: k '{kk}' is not a number"))?;
        let d: f64 =
            d.trim().parse().with_context(|| format!("--coating layer {k}: thickness '{d}' is not a number (nm)"))?;
        if !(n.is_finite() && n > 0.0) {
            bail!("--coating layer {k}: index {n} must be > 0");
        }
        if !(kk.is_finite() && kk >= 0.0) {
            bail!("--coating layer {k}: k {kk} must be >= 0 (absorption)");
        }
        if !(d.is_finite() && d >= 0.0) {
            bail!("--coating layer {k}: thickness {d} nm must be >= 0");
        }
        out.push(Layer { n: C64::new(n, kk), thickness_nm: d });
    }
    Ok(out)
}

pub fn run(a: Args) -> Result<()> {
    if !(a.wavelength_nm.is_finite() && a.wavelength_nm > 0.0) {
        bail!("--wavelength-nm {} must be > 0", a.wavelength_nm);
    }
    let n_sub = match (&a.metal, a.n_real) {
        (Some(m), _) => {
            let table = if std::path::Path::new(m).is_file() {
                MetalTable::read(std::path::Path::new(m))
            } else {
                MetalTable::builtin(m)
            }
            .with_context(|| format!("--metal {m}"))?;
            table
                .index(a.wavelength_nm / 1000.0)
                .with_context(|| format!("--metal {m} at --wavelength-nm {}", a.wavelength_nm))?
        }
        (None, Some(n)) => C64::new(n, a.n_imag),
        (None, None) => bail!("give the substrate index with --n-real (and --n-imag) or --metal"),
    };
    let (n_real, n_imag) = (n_sub.re, n_sub.im);
    if !(n_real.is_finite() && n_real > 0.0) {
        bail!("--n-real {} must be > 0", n_real);
    }
    if !(n_imag.is_finite() && n_imag >= 0.0) {
        bail!("--n-imag {} must be >= 0 (absorption)", n_imag);
    }
    if !(a.n_incident.is_finite() && a.n_incident > 0.0) {
        bail!("--n-incident {} must be > 0", a.n_incident);
    }
    if !(a.aoi_deg.is_finite() && (0.0..90.0).contains(&a.aoi_deg)) {
        bail!("--aoi-deg {} must be in [0, 90)", a.aoi_deg);
    }
    let layers = match &a.coating {
        Some(s) => parse_coating(s)?,
        None => Vec::new(),
    };
    let c = stack(a.n_incident, &layers, n_sub, a.wavelength_nm, a.aoi_deg.to_radians())?;
    let (rs, rp) = (c.reflectance_s, c.reflectance_p);
    let out = Out {
        ts: c.transmittance_s,
        tp: c.transmittance_p,
        rs: c.reflectance_s,
        rp: c.reflectance_p,
        transmission_diattenuation: c.diattenuation_t(),
        retardance_deg: c.retardance_t().to_degrees(),
        reflection_polarization: if rs + rp > 0.0 { (rs - rp) / (rs + rp) } else { 0.0 },
        reflection_retardance_deg: c.retardance_r().to_degrees(),
        aoi_deg: a.aoi_deg,
        wavelength_nm: a.wavelength_nm,
        n_incident: a.n_incident,
        n_real,
        n_imag,
        layers: layers.iter().map(|l| LayerOut { index: l.n.re, k: l.n.im, thickness_nm: l.thickness_nm }).collect(),
    };
    if a.json {
        return crate::util::print_json(&out);
    }
    outln!(
        "n0 = {} -> {} layer(s) -> n = {} + {}i at {} deg, {} nm",
        a.n_incident,
        layers.len(),
        n_real,
        n_imag,
        a.aoi_deg,
        a.wavelength_nm
    );
    outln!("{:<14}{:>12}{:>12}", "", "s", "p");
    outln!("{:<14}{:>12.6}{:>12.6}", "T", out.ts, out.tp);
    outln!("{:<14}{:>12.6}{:>12.6}", "R", out.rs, out.rp);
    outln!("{:<14}{:>12.6}{:>12.6}", "T + R", out.ts + out.rs, out.tp + out.rp);
    outln!("transmission diattenuation (Tp-Ts)/(Tp+Ts) = {:.4} %", 100.0 * out.transmission_diattenuation);
    outln!("reflection polarization (Rs-Rp)/(Rs+Rp) = {:.4} %", 100.0 * out.reflection_polarization);
    outln!(
        "retardance (p - s): transmitted {:.4} deg, reflected {:.4} deg",
        out.retardance_deg,
        out.reflection_retardance_deg
    );
    Ok(())
}
