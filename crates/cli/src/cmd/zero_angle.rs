//! `instpol zero-angle`: the HWP zero angle of a filter from a polarized standard in frames.

use anyhow::{bail, Result};
use fit::zeroangle::{zero_angle, Sense, StandardChi};
use skyfield::photometry::{layout_for, photometry_with, Aperture, PhotOptions};
use skyfield::reduce::FrameSet;
use std::path::PathBuf;

/// Measure polarized standard stars in frames and compare their chi with the catalogued ones:
/// the difference is the HWP zero angle of the filter (the angle to add to a measured chi,
/// paper section HWP), printed as the line to put in the instrument file's filter entry.
/// The chi measured here ignores any zero angle the instrument file already has, so the
/// result replaces it.
///
/// One standard: `--x --y` with `--star NAME` (from the built-in list or --standards FILE) or
/// `--chi-deg`. Several standards in the same frames (a standard field, or a cluster with
/// published angles): `--standard X,Y:NAME` or `--standard X,Y:CHI+-SIGMA`, repeated. Their
/// offsets are averaged on the circle of period 180 deg, weighted by their errors; the output
/// gives the propagated error and the scatter-based one (times sqrt(chi2/dof)), each star's
/// pull, the star that disagrees with the others (pull > 3, three or more stars), and the
/// sense of the angle (decided when the stars' chi differ: counter-clockwise as the IAU, or
/// mirrored).
///
/// Examples:
///   instpol zero-angle std/*.fits --instrument fors1 --x 1024 --y 90 --star "Hiltner 652"
///   instpol zero-angle field/*.fits --instrument calcite \
///       --standard "150,200:136+-0.05" --standard "300,600:12+-0.1" --standard "500,300:70+-0.1"
#[derive(clap::Args)]
pub struct Args {
    /// Frame files (FITS) of the standard(s).
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Standard's x, y: 0-based pixel of its ordinary image (one standard).
    #[arg(long, allow_hyphen_values = true, requires = "y")]
    pub x: Option<f64>,
    #[arg(long, allow_hyphen_values = true, requires = "x")]
    pub y: Option<f64>,
    /// The standard, by name, from the built-in list (or --standards FILE).
    #[arg(long)]
    pub star: Option<String>,
    /// Several standards: "X,Y:NAME" (a star of the list) or "X,Y:CHI_DEG+-SIGMA_DEG", repeated.
    #[arg(long = "standard", value_name = "X,Y:NAME|X,Y:CHI+-SIGMA", conflicts_with_all = ["x", "star", "chi_deg"])]
    pub standard: Vec<String>,
    /// A standards file (TOML, the format of instruments/standards.toml).
    #[arg(long)]
    pub standards: Option<PathBuf>,
    /// Or the catalogued angle (deg) and its error, when the star is not in the list.
    #[arg(long, allow_hyphen_values = true)]
    pub chi_deg: Option<f64>,
    #[arg(long, default_value_t = 0.1)]
    pub sigma_chi_deg: f64,
    /// Aperture radius (px).
    #[arg(long, default_value_t = 8.0)]
    pub aperture: f64,
    /// Background annulus inner,outer radius (px).
    #[arg(long, default_value = "12,20")]
    pub annulus: String,
    /// Instrument: built-in name or path to an instrument TOML.
    #[arg(long, default_value = "fors1")]
    pub instrument: String,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub frame: crate::cmd::frame_opts::FrameOpts,
}

/// One standard's measurement and offset (JSON).
#[derive(serde::Serialize)]
struct StarOut {
    /// The star's name, or its catalogued angle when given by number.
    label: String,
    x: f64,
    y: f64,
    chi_measured_deg: f64,
    sigma_chi_measured_deg: f64,
    chi_catalogue_deg: f64,
    sigma_chi_catalogue_deg: f64,
    p_measured: f64,
    sigma_p_measured: f64,
    /// This star's own offset (deg, in the sense found) and its pull about the mean.
    offset_deg: f64,
    pull: f64,
}

#[derive(serde::Serialize)]
struct Out {
    filter: String,
    zero_angle_deg: f64,
    sigma_zero_angle_deg: f64,
    sigma_scatter_zero_angle_deg: Option<f64>,
    chi2_dof: Option<f64>,
    n_standards: usize,
    sense: Sense,
    outlier: Option<String>,
    standards: Vec<StarOut>,
    instrument_file_line: String,
}

/// A standard to measure: position and catalogued angle (deg) with its error.
struct Std {
    label: String,
    x: f64,
    y: f64,
    chi: f64,
    sigma: f64,
}

/// The catalogued chi of a named star in `filter`.
fn catalogued(list: &fit::standards::Standards, name: &str, filter: &str) -> Result<(String, f64, f64)> {
    let star = list.star(name)?;
    let b = star.band(filter)?;
    match (b.chi_deg, b.sigma_chi_deg) {
        (Some(c), Some(s)) => Ok((star.name.clone(), c, s)),
        _ => bail!(
            "{} has no catalogued chi in {} ({}): a zero angle needs a polarized standard",
            star.name,
            filter,
            b.source
        ),
    }
}

/// Parse `--standard X,Y:NAME` or `X,Y:CHI+-SIGMA`.
fn parse_standard(spec: &str, list: &dyn Fn() -> Result<fit::standards::Standards>, filter: &str) -> Result<Std> {
    let bad = || {
        anyhow::anyhow!("--standard '{spec}': expected X,Y:NAME or X,Y:CHI_DEG+-SIGMA_DEG, e.g. 150,200:Hiltner 652 or 150,200:136+-0.05")
    };
    let (pos, what) = spec.split_once(':').ok_or_else(bad)?;
    let xy: Option<Vec<f64>> = pos.split(',').map(|t| t.trim().parse().ok()).collect();
    let Some([x, y]) = xy.as_deref().and_then(|v| <[f64; 2]>::try_from(v).ok()) else { return Err(bad()) };
    let what = what.trim();
    let num = what.replace('±', "+-");
    let angle = match num.split_once("+-") {
        Some((c, s)) => {
            Some((c.trim().parse::<f64>().map_err(|_| bad())?, s.trim().parse::<f64>().map_err(|_| bad())?))
        }
        None => what.parse::<f64>().ok().map(|c| (c, f64::NAN)),
    };
    let (label, chi, sigma) = match angle {
        Some((_, s)) if s.is_nan() => {
            bail!("--standard '{spec}': give the catalogued angle with its error, CHI+-SIGMA")
        }
        Some((c, s)) => (format!("chi {c} deg at ({x}, {y})"), c, s),
        None if what.is_empty() => return Err(bad()),
        None => catalogued(&list()?, what, filter)?,
    };
    Ok(Std { label, x, y, chi, sigma })
}

pub fn run(a: Args) -> Result<()> {
    let inst = instrument::Instrument::load(&a.instrument)?;
    let annulus = crate::util::parse_radii(&a.annulus)?;
    crate::util::inputs(
        a.frames.iter().map(|p| p.as_path()).chain(crate::util::file_arg(&a.instrument)).chain(a.standards.as_deref()),
    )?;
    let frames = skyfield::reduce::read_frames_with(&a.frames, &inst, &a.frame.read_options()?, &|| {})?;
    let set = FrameSet::from_frames(frames, &inst, true)?;
    for w in &set.warnings {
        eprintln!("warning: {w}");
    }
    let list = || -> Result<fit::standards::Standards> {
        Ok(match &a.standards {
            Some(p) => fit::standards::Standards::load(p)?,
            None => fit::standards::Standards::builtin()?,
        })
    };
    let stds: Vec<Std> = if !a.standard.is_empty() {
        a.standard.iter().map(|s| parse_standard(s, &list, &set.filter)).collect::<Result<_>>()?
    } else {
        let (Some(x), Some(y)) = (a.x, a.y) else {
            bail!("give the standard's position by --x --y (one star) or --standard X,Y:NAME (repeated)")
        };
        let (label, chi, sigma) = match (&a.star, a.chi_deg) {
            (Some(name), None) => catalogued(&list()?, name, &set.filter)?,
            (None, Some(c)) => (format!("chi {c} deg at ({x}, {y})"), c, a.sigma_chi_deg),
            _ => bail!("give the standard either by --star NAME or by --chi-deg (not both)"),
        };
        vec![Std { label, x, y, chi, sigma }]
    };
    for s in &stds {
        if !(s.chi.is_finite() && s.sigma.is_finite() && s.sigma >= 0.0 && s.sigma < 90.0) {
            bail!(
                "standard {}: catalogued chi {} +- {} deg: need a finite angle and an error in [0, 90) deg",
                s.label,
                s.chi,
                s.sigma
            );
        }
    }
    let g = layout_for(&set, &inst)?;
    let ap = Aperture { radius_px: a.aperture, annulus: Some(annulus) };
    let mut meas = Vec::with_capacity(stds.len());
    for s in &stds {
        let ph = photometry_with(&set, &g, s.x, s.y, &ap, &PhotOptions::default())
            .map_err(|e| anyhow::anyhow!("standard {}: {e}", s.label))?;
        let r = ph.reduction;
        if !(r.p > 3.0 * r.sigma_p) {
            bail!(
                "standard {} at ({}, {}) has P = {:.3} +- {:.3} %: too little polarization to measure an angle (need P > 3 sigma)",
                s.label,
                s.x,
                s.y,
                100.0 * r.p,
                100.0 * r.sigma_p
            );
        }
        meas.push(r);
    }
    let chis: Vec<StandardChi> = stds
        .iter()
        .zip(&meas)
        .map(|(s, r)| StandardChi {
            chi_measured: r.chi,
            sigma_measured: r.sigma_chi,
            chi_catalogue: s.chi.to_radians(),
            sigma_catalogue: s.sigma.to_radians(),
        })
        .collect();
    let z = zero_angle(&chis).ok_or_else(|| anyhow::anyhow!("the angles have no finite error"))?;
    if z.offsets.len() != stds.len() {
        bail!("some standards' angles have no finite error: cannot combine them");
    }
    let zd = z.offset.to_degrees();
    let o = Out {
        filter: set.filter.clone(),
        zero_angle_deg: zd,
        sigma_zero_angle_deg: z.sigma.to_degrees(),
        sigma_scatter_zero_angle_deg: z.sigma_scatter.map(f64::to_degrees),
        chi2_dof: (z.dof > 0).then(|| z.chi2 / z.dof as f64),
        n_standards: stds.len(),
        sense: z.sense,
        outlier: z.outlier.map(|k| stds[k].label.clone()),
        standards: stds
            .iter()
            .zip(&meas)
            .zip(z.offsets.iter().zip(&z.pulls))
            .map(|((s, r), (d, p))| StarOut {
                label: s.label.clone(),
                x: s.x,
                y: s.y,
                chi_measured_deg: r.chi.to_degrees(),
                sigma_chi_measured_deg: r.sigma_chi.to_degrees(),
                chi_catalogue_deg: s.chi,
                sigma_chi_catalogue_deg: s.sigma,
                p_measured: r.p,
                sigma_p_measured: r.sigma_p,
                offset_deg: d.to_degrees(),
                pull: *p,
            })
            .collect(),
        instrument_file_line: format!("hwp_chi_offset_deg = {zd:.2}   # filter {}", set.filter),
    };
    if let Some(name) = &o.outlier {
        eprintln!(
            "warning: standard {name} disagrees with the others (pull {:.1} > {}): check its identification and catalogue value, or leave it out",
            z.pulls[z.outlier.unwrap()],
            fit::zeroangle::OUTLIER_PULL
        );
    }
    if let Some(c) = o.chi2_dof {
        if c > 4.0 && o.outlier.is_none() {
            eprintln!(
                "warning: the standards scatter beyond their errors (chi2/dof = {c:.1}): quote the scatter-based error {:.2} deg",
                o.sigma_scatter_zero_angle_deg.unwrap_or(f64::NAN)
            );
        }
    }
    if a.json {
        crate::util::print_json(&o)?;
    } else {
        for s in &o.standards {
            outln!(
                "{}: measured chi = {:.2} +- {:.2} deg (P = {:.3} +- {:.3} %), catalogue {:.2} +- {:.2} deg, offset {:.2} deg (pull {:+.1})",
                s.label,
                s.chi_measured_deg,
                s.sigma_chi_measured_deg,
                100.0 * s.p_measured,
                100.0 * s.sigma_p_measured,
                s.chi_catalogue_deg,
                s.sigma_chi_catalogue_deg,
                s.offset_deg,
                s.pull
            );
        }
        out!(
            "filter {}: HWP zero angle {zd:.2} +- {:.2} deg (to add to a measured chi)",
            o.filter,
            o.sigma_zero_angle_deg
        );
        match (o.sigma_scatter_zero_angle_deg, o.chi2_dof) {
            (Some(s), Some(c)) => {
                outln!("; from the scatter +- {s:.2} deg (chi2/dof = {c:.2}, {} stars)", o.n_standards)
            }
            _ => outln!(),
        }
        match o.sense {
            Sense::Undetermined => outln!("sense of the angle: undetermined (one standard, or standards of one chi); assumed counter-clockwise (IAU)"),
            Sense::Iau => outln!("sense of the angle: counter-clockwise on the sky (IAU), as assumed"),
            Sense::Mirrored => outln!("sense of the angle: MIRRORED (chi_true = offset - chi_measured): the instrument's angles run clockwise"),
        }
        outln!("in the instrument file, filter {}:  {}", o.filter, o.instrument_file_line);
    }
    Ok(())
}
