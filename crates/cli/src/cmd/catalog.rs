//! `instpol catalog`: every paired star of a frame set, measured in one run.

use anyhow::{bail, Result};
use skyfield::catalog::{catalog, flags, CatalogConfig};
use skyfield::detect::DetectConfig;
use skyfield::photometry::Aperture;
use skyfield::reduce::FrameSet;
use std::path::PathBuf;

/// Find every star in the frames, pair its ordinary image with its extraordinary one through
/// the instrument's beam layout (mask strips or a maskless calcite offset), and measure each
/// pair at every HWP angle: apertures re-centred per frame with exact pixel weights, the
/// background removed in each beam before F_i (paper, section background), Q/I, U/I, P and
/// chi with propagated and scatter-based errors, and flags (saturated, mask edge, blended)
/// where a star cannot be measured honestly.
///
/// Example:
///   instpol catalog frames/*.fits --instrument fors1 --fwhm 4 --out stars.csv
#[derive(clap::Args)]
pub struct Args {
    /// Frame files (FITS), one or more per HWP angle.
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Instrument: built-in name or path to an instrument TOML.
    #[arg(long, default_value = "fors1")]
    pub instrument: String,
    /// Expected FWHM of the stars (px): the width of the detection filter.
    #[arg(long, default_value_t = 4.0)]
    pub fwhm: f64,
    /// Detection threshold (sigma of the filtered image's noise).
    #[arg(long, default_value_t = 5.0)]
    pub threshold: f64,
    /// Aperture radius (px).
    #[arg(long, default_value_t = 8.0)]
    pub aperture: f64,
    /// Background annulus inner,outer radius (px).
    #[arg(long, default_value = "12,20")]
    pub annulus: String,
    /// Output table, one row per star (F_i as columns f_0, f_1, ...), in the format of its
    /// extension: .csv, .fits, .ecsv or .vot (units in the FITS, ECSV and VOTable headers).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub frame: crate::cmd::frame_opts::FrameOpts,
}

pub fn run(a: Args) -> Result<()> {
    let inst = instrument::Instrument::load(&a.instrument)?;
    let annulus = crate::util::parse_radii(&a.annulus)?;
    if !(a.aperture.is_finite() && a.aperture > 0.0 && a.aperture < 1000.0) {
        bail!("--aperture {} px: expected a radius between 0 and 1000 px", a.aperture);
    }
    if !(a.fwhm.is_finite() && a.fwhm > 0.5 && a.fwhm < 200.0) {
        bail!("--fwhm {} px: expected a star width between 0.5 and 200 px", a.fwhm);
    }
    if !(a.threshold.is_finite() && a.threshold > 0.0) {
        bail!("--threshold {}: must be a positive number of sigma", a.threshold);
    }
    if let Some(out) = &a.out {
        skyfield::table::Format::from_path(out).map_err(|e| anyhow::anyhow!("--out {e}"))?;
    }
    crate::util::inputs(a.frames.iter().map(|p| p.as_path()).chain(crate::util::file_arg(&a.instrument)))?;
    if let Some(out) = &a.out {
        crate::util::check_output(out)?;
    }
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
    let cfg = CatalogConfig {
        detect: DetectConfig { fwhm_px: a.fwhm, threshold_sigma: a.threshold, ..Default::default() },
        aperture: Aperture { radius_px: a.aperture, annulus: Some(annulus) },
        weighting: skyfield::aperture::Weighting::Exact,
    };
    let cat = catalog(&set, &inst, &cfg)?;
    if let Some(out) = &a.out {
        crate::util::check_output(out)?;
        cat.to_table().write(out)?;
    }
    let measured = cat.rows.iter().filter(|r| r.q.is_finite()).count();
    if a.json {
        crate::util::print_json(&cat)?;
    } else {
        println!(
            "{} sources, {} stars paired ({} measured, {} flagged), {} unpaired; filter {}, {} HWP angles, chi zero angle {} deg",
            cat.n_sources,
            cat.rows.len(),
            measured,
            cat.rows.len() - measured,
            cat.unpaired.len(),
            cat.filter,
            cat.hwp_deg.len(),
            cat.chi_offset_deg
        );
        println!("  id        x        y      P %     +-   chi deg     +-  flags");
        for r in &cat.rows {
            println!(
                "{:4} {:8.2} {:8.2} {:8.3} {:6.3} {:9.2} {:6.2}  {}",
                r.id,
                r.x,
                r.y,
                100.0 * r.p,
                100.0 * r.sigma_p,
                r.chi_deg,
                r.sigma_chi_deg,
                flags::names(r.flags)
            );
        }
        if let Some(out) = &a.out {
            println!("wrote {}", out.display());
        }
    }
    Ok(())
}
