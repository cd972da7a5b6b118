//! `instpol zero-angle`: the HWP zero angle of a filter from a polarized standard in frames.

use anyhow::{bail, Result};
use fit::zeroangle::{zero_angle, Sense, StandardChi};
use skyfield::photometry::{layout_for, photometry_with, Aperture, PhotOptions};
use skyfield::reduce::FrameSet;
use std::path::PathBuf;

/// Measure a polarized standard star in frames and compare its chi with the catalogued one:
/// the difference is the HWP zero angle of the filter (the angle to add to a measured chi,
/// paper section HWP), printed as the line to put in the instrument file's filter entry.
/// The chi measured here ignores any zero angle the instrument file already has, so the
/// result replaces it.
///
/// Several standards (`--x/--y` for one star per run) give one offset each; with stars of
/// different chi, run them through `--star` one by one and average, or check the sense of
/// the angle (two standards of different chi tell whether the instrument's angles are
/// mirrored).
///
/// Example:
///   instpol zero-angle std/*.fits --instrument fors1 --x 1024 --y 90 --star "Hiltner 652"
#[derive(clap::Args)]
pub struct Args {
    /// Frame files (FITS) of the standard.
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Standard's x, y: 0-based pixel of its ordinary image.
    #[arg(long, allow_hyphen_values = true)]
    pub x: f64,
    #[arg(long, allow_hyphen_values = true)]
    pub y: f64,
    /// The standard, by name, from the built-in list (or --standards FILE).
    #[arg(long)]
    pub star: Option<String>,
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

#[derive(serde::Serialize)]
struct Out {
    filter: String,
    chi_measured_deg: f64,
    sigma_chi_measured_deg: f64,
    chi_catalogue_deg: f64,
    sigma_chi_catalogue_deg: f64,
    p_measured: f64,
    sigma_p_measured: f64,
    zero_angle_deg: f64,
    sigma_zero_angle_deg: f64,
    sense: Sense,
    instrument_file_line: String,
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
    let (chi_cat, sig_cat) = match (&a.star, a.chi_deg) {
        (Some(name), None) => {
            let list = match &a.standards {
                Some(p) => fit::standards::Standards::load(p)?,
                None => fit::standards::Standards::builtin()?,
            };
            let star = list.star(name)?;
            let b = star.band(&set.filter)?;
            match (b.chi_deg, b.sigma_chi_deg) {
                (Some(c), Some(s)) => (c, s),
                _ => bail!(
                    "{} has no catalogued chi in {} ({}): a zero angle needs a polarized standard",
                    star.name,
                    set.filter,
                    b.source
                ),
            }
        }
        (None, Some(c)) => (c, a.sigma_chi_deg),
        _ => bail!("give the standard either by --star NAME or by --chi-deg (not both)"),
    };
    if !(chi_cat.is_finite() && sig_cat.is_finite() && sig_cat >= 0.0 && sig_cat < 90.0) {
        bail!("--chi-deg {chi_cat} / --sigma-chi-deg {sig_cat}: need a finite angle and an error in [0, 90) deg");
    }
    let g = layout_for(&set, &inst)?;
    let ap = Aperture { radius_px: a.aperture, annulus: Some(annulus) };
    let ph = photometry_with(&set, &g, a.x, a.y, &ap, &PhotOptions::default())?;
    let r = &ph.reduction;
    if !(r.p > 3.0 * r.sigma_p) {
        bail!(
            "the star at ({}, {}) has P = {:.3} +- {:.3} %: too little polarization to measure an angle (need P > 3 sigma)",
            a.x,
            a.y,
            100.0 * r.p,
            100.0 * r.sigma_p
        );
    }
    let z = zero_angle(&[StandardChi {
        chi_measured: r.chi,
        sigma_measured: r.sigma_chi,
        chi_catalogue: chi_cat.to_radians(),
        sigma_catalogue: sig_cat.to_radians(),
    }])
    .ok_or_else(|| anyhow::anyhow!("the angles have no finite error"))?;
    let zd = z.offset.to_degrees();
    let o = Out {
        filter: set.filter.clone(),
        chi_measured_deg: r.chi.to_degrees(),
        sigma_chi_measured_deg: r.sigma_chi.to_degrees(),
        chi_catalogue_deg: chi_cat,
        sigma_chi_catalogue_deg: sig_cat,
        p_measured: r.p,
        sigma_p_measured: r.sigma_p,
        zero_angle_deg: zd,
        sigma_zero_angle_deg: z.sigma.to_degrees(),
        sense: z.sense,
        instrument_file_line: format!("hwp_chi_offset_deg = {zd:.2}   # filter {}", set.filter),
    };
    if a.json {
        crate::util::print_json(&o)?;
    } else {
        outln!(
            "filter {}: measured chi = {:.2} +- {:.2} deg (P = {:.3} +- {:.3} %), catalogue {:.2} +- {:.2} deg",
            o.filter,
            o.chi_measured_deg,
            o.sigma_chi_measured_deg,
            100.0 * o.p_measured,
            100.0 * o.sigma_p_measured,
            o.chi_catalogue_deg,
            o.sigma_chi_catalogue_deg
        );
        outln!("HWP zero angle: {zd:.2} +- {:.2} deg (to add to a measured chi)", o.sigma_zero_angle_deg);
        outln!("sense of the angle: undetermined from one standard (assumed counter-clockwise, IAU)");
        outln!("in the instrument file, filter {}:  {}", o.filter, o.instrument_file_line);
    }
    Ok(())
}
