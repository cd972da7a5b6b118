//! `instpol photometry`: Q, U, P, chi of a point source from a set of frames.

use anyhow::{bail, Result};
use skyfield::photometry::Aperture;
use skyfield::reduce::FrameSet;
use std::path::PathBuf;

/// Aperture photometry of a point source in both beams at every HWP angle, with the local
/// background (annulus, sigma-clipped mean) subtracted beam by beam before F_i, so that a
/// polarized background is removed vectorially (paper, section background). Prints Q/I, U/I,
/// P (%), chi (deg) and their errors.
#[derive(clap::Args)]
pub struct Args {
    /// Frame files (FITS).
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Source x: 0-based pixel of the ordinary image, or arcmin from the detector centre.
    #[arg(long, allow_hyphen_values = true)]
    pub x: f64,
    /// Source y (as --x).
    #[arg(long, allow_hyphen_values = true)]
    pub y: f64,
    /// Units of --x/--y.
    #[arg(long, value_enum, default_value = "pixel")]
    pub coords: CoordsArg,
    /// Aperture radius (px).
    #[arg(long, default_value_t = 8.0)]
    pub aperture: f64,
    /// Background annulus inner,outer radius (px).
    #[arg(long, default_value = "12,20")]
    pub annulus: String,
    /// No background subtraction (the combined source + background values).
    #[arg(long)]
    pub no_background: bool,
    /// Instrument: built-in name or path to an instrument TOML.
    #[arg(long, default_value = "fors1")]
    pub instrument: String,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub frame: crate::cmd::frame_opts::FrameOpts,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum CoordsArg {
    Pixel,
    Arcmin,
}

#[derive(serde::Serialize)]
struct Out {
    x_px: f64,
    y_px: f64,
    hwp_deg: Vec<f64>,
    f_o: Vec<f64>,
    f_e: Vec<f64>,
    q: f64,
    u: f64,
    sigma_q: f64,
    sigma_u: f64,
    p: f64,
    sigma_p: f64,
    chi_deg: f64,
    sigma_chi_deg: f64,
    /// The filter's HWP zero angle added to chi (deg).
    hwp_chi_offset_deg: f64,
    n_aperture: usize,
    n_annulus: usize,
}

pub fn run(a: Args) -> Result<()> {
    let inst = instrument::Instrument::load(&a.instrument)?;
    let (x, y) = match a.coords {
        CoordsArg::Pixel => (a.x, a.y),
        CoordsArg::Arcmin => inst.arcmin_to_pixel(a.x, a.y),
    };
    let annulus = if a.no_background {
        None
    } else {
        let v: Vec<&str> = a.annulus.split(',').collect();
        let parsed: Option<Vec<f64>> = v.iter().map(|s| s.trim().parse().ok()).collect();
        match parsed.as_deref() {
            Some([r1, r2]) => Some((*r1, *r2)),
            _ => bail!("--annulus '{}': expected two radii in px, e.g. 12,20", a.annulus),
        }
    };
    let bar =
        if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(a.frames.len() as u64) };
    bar.set_message("reading");
    let read = a.frame.read_options()?;
    let frames = skyfield::reduce::read_frames_with(&a.frames, &inst, &read, &|| bar.inc(1));
    bar.finish_and_clear();
    let set = FrameSet::from_frames(frames?, &inst, true)?;
    for w in &set.warnings {
        eprintln!("warning: {w}");
    }
    let ph = skyfield::photometry::photometry(&set, &inst, x, y, &Aperture { radius_px: a.aperture, annulus })?;
    let r = &ph.reduction;
    // The HWP zero angle of the filter (the angle to add to a measured chi): Q, U and chi are
    // reported in the sky's frame, as the calibration and validation report them.
    let offset = inst.filter(&set.filter).map(|f| f.hwp_chi_offset_deg).unwrap_or(0.0);
    let (c, s) = ((2.0 * offset.to_radians()).cos(), (2.0 * offset.to_radians()).sin());
    let (q, u) = (c * r.qu.q - s * r.qu.u, s * r.qu.q + c * r.qu.u);
    let var_q = c * c * r.qu.var_q + s * s * r.qu.var_u - 2.0 * c * s * r.qu.cov_qu;
    let var_u = s * s * r.qu.var_q + c * c * r.qu.var_u + 2.0 * c * s * r.qu.cov_qu;
    let o = Out {
        x_px: x,
        y_px: y,
        hwp_deg: ph.hwp_deg.clone(),
        f_o: ph.f_o.clone(),
        f_e: ph.f_e.clone(),
        q,
        u,
        sigma_q: var_q.max(0.0).sqrt(),
        sigma_u: var_u.max(0.0).sqrt(),
        p: r.p,
        sigma_p: r.sigma_p,
        chi_deg: (r.chi.to_degrees() + offset).rem_euclid(180.0),
        hwp_chi_offset_deg: offset,
        sigma_chi_deg: r.sigma_chi.to_degrees(),
        n_aperture: ph.n_aperture,
        n_annulus: ph.n_annulus,
    };
    if a.json {
        crate::util::print_json(&o)?;
    } else {
        println!("source at ({:.2}, {:.2}) px, aperture {} px, {} HWP angles", x, y, a.aperture, o.hwp_deg.len());
        println!("  Q/I = {:+.5} +- {:.5}", o.q, o.sigma_q);
        println!("  U/I = {:+.5} +- {:.5}", o.u, o.sigma_u);
        println!("  P   = {:.4}% +- {:.4}%", 100.0 * o.p, 100.0 * o.sigma_p);
        println!("  chi = {:.2} +- {:.2} deg", o.chi_deg, o.sigma_chi_deg);
    }
    Ok(())
}
