//! `instpol reduce`: frames to a binned Stokes map.

use anyhow::Result;
use skyfield::reduce::ReduceConfig;
use std::path::PathBuf;
use stokes::stats::robust::{median, Middle};

/// Reduce a set of dual-beam frames (one filter, N HWP angles) to a binned Stokes map: per
/// pixel F_i and Q/I, U/I from the ordinary and extraordinary images of every mask strip,
/// then a sigma-clipped (3 sigma, median/MAD, iterative) mean per bin that rejects stars,
/// cosmic rays and bad pixels. Writes a multi-extension FITS map (Q, U, errors, P, CHI in deg,
/// COVERAGE, INTENSITY, ...; bin geometry in the header). NaN and saturated pixels are masked
/// with a warning; an incomplete angle set, mixed filters or sizes, a missing keyword or an
/// unreadable file are errors (exit 2) and leave no output file. When the instrument's
/// [telescope] section names the parallactic-angle keywords and the frames carry them, the map
/// records the exposures' track (PARANG1, PARANG2, ROTANG), which `correct` uses to remove a
/// telescope model. Through a quarter-wave plate (plate = "quarter_wave" in the instrument
/// file) the map holds V/I instead (STOKES = 'V': images V, SIGMA_V, SIGV_PHOT, ...), which
/// fit, calibrate and correct refuse.
///
/// Example: instpol reduce frames/*.fits --instrument fors1 --bin 30 --out map_V.fits
#[derive(clap::Args)]
pub struct Args {
    /// Frame files (FITS), real or simulated.
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Instrument: built-in name (fors1) or path to an instrument TOML.
    /// Default: the built-in instrument the first file's INSTRUME keyword names (said on
    /// stderr); a file without one, or of no built-in instrument, is refused.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Bin side in pixels (the paper uses 30).
    #[arg(long, default_value_t = workflow::steps::DEFAULT_BIN_PX)]
    pub bin: usize,
    /// Clipping threshold in robust sigmas.
    #[arg(long, default_value_t = 3.0)]
    pub nsigma: f64,
    /// Accept an incomplete set of optimal angles (least squares on what is there).
    #[arg(long)]
    pub allow_incomplete: bool,
    /// Output Stokes map (FITS).
    #[arg(long)]
    pub out: PathBuf,
    /// Print a summary as JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub frame: crate::cmd::frame_opts::FrameOpts,
}

#[derive(serde::Serialize)]
struct Summary {
    #[serde(rename = "output")]
    out: PathBuf,
    filter: String,
    #[serde(rename = "hwp_deg")]
    hwp_angles_deg: Vec<f64>,
    bin_px: usize,
    #[serde(rename = "n_bins")]
    bins: usize,
    #[serde(rename = "n_valid_bins")]
    valid_bins: usize,
    median_p: f64,
    median_chi_deg: f64,
    median_sigma_q: f64,
    warnings: Vec<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    grouping: Option<skyfield::calib::Grouping>,
    /// What the map is, as its header records it.
    product: Option<skyfield::provenance::Product>,
}

pub fn run(a: Args) -> Result<()> {
    let instrument = crate::util::instrument_of(&a.instrument, a.frames.first().map(|p| p.as_path()))?;
    crate::util::inputs(a.frames.iter().map(|p| p.as_path()).chain(crate::util::file_arg(&instrument)))?;
    crate::util::check_output(&a.out)?;
    let inst = instrument::Instrument::load(&instrument)?;
    crate::util::check_bin(a.bin, &inst)?;
    let cfg = ReduceConfig {
        bin_px: a.bin,
        clip: skyfield::bin::ClipConfig { nsigma: a.nsigma, ..Default::default() },
        min_pixels: None,
        require_complete_set: !a.allow_incomplete,
    };
    let bar =
        if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(a.frames.len() as u64) };
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} frames ({elapsed})")
            .expect("template")
            .progress_chars("=> "),
    );
    bar.set_message("reading");
    // The library's fast path: frames stay in their stored type, no f64 copies. The instrument's
    // plate decides the map (the library's rule: Q/I, U/I or, through a quarter-wave plate, V/I).
    let read = a.frame.read_options()?;
    // The one step (workflow::steps::reduce): the map, its telescope angles recorded, written.
    let r = workflow::steps::reduce(&a.frames, &inst, &cfg, &read, Some(&a.out), &|| bar.inc(1));
    bar.finish_and_clear();
    let r = match r? {
        skyfield::reduce::PlateReduced::Linear(r) => *r,
        skyfield::reduce::PlateReduced::Circular(r) => return circular(&a, *r),
    };
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    let m = &r.map;
    let pick = |v: &[f64]| median(&mut m.valid_bins().map(|(k, _, _)| v[k]).collect::<Vec<_>>(), Middle::Mean);
    let s = Summary {
        out: a.out.clone(),
        filter: m.filter.clone(),
        hwp_angles_deg: m.hwp_angles_deg.clone(),
        bin_px: m.geometry.bin_px,
        bins: m.geometry.len(),
        valid_bins: m.n_valid(),
        median_p: pick(&m.p),
        median_chi_deg: pick(&m.chi).to_degrees(),
        median_sigma_q: pick(&m.sigma_q),
        warnings: r.warnings.iter().map(|w| w.to_string()).collect(),
        grouping: skyfield::calib::Grouping::of(&inst, &read, a.frames.len(), r.exposures.len()),
        product: m.product.as_ref().map(|p| p.with_run_inputs()),
    };
    if a.json {
        crate::util::print_json(&s)?;
    } else {
        if let Some(g) = &s.grouping {
            outln!("{}", g.describe());
        }
        outln!(
            "{}: filter {}, N = {} ({:?} deg), {} of {} bins of {} px valid; median P = {:.3}%, chi = {:.1} deg, sigma_Q/I = {:.4}%",
            s.out.display(),
            s.filter,
            s.hwp_angles_deg.len(),
            s.hwp_angles_deg,
            s.valid_bins,
            s.bins,
            s.bin_px,
            100.0 * s.median_p,
            s.median_chi_deg,
            100.0 * s.median_sigma_q
        );
    }
    Ok(())
}

/// `instpol reduce --json` through a quarter-wave plate (`schemas/reduce-circular.schema.json`).
#[derive(serde::Serialize)]
struct CircularSummary {
    #[serde(rename = "output")]
    out: PathBuf,
    filter: String,
    /// Always "V": the map holds V/I.
    stokes: &'static str,
    plate_deg: Vec<f64>,
    qwp_zero_angle_deg: f64,
    bin_px: usize,
    n_bins: usize,
    n_valid_bins: usize,
    median_v: f64,
    median_sigma_v: f64,
    warnings: Vec<String>,
    /// What the map is, as its header records it.
    product: Option<skyfield::provenance::Product>,
}

/// Report a quarter-wave plate's V/I map (written by the step).
fn circular(a: &Args, r: skyfield::reduce::CircularReduced) -> Result<()> {
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    let m = &r.map;
    let pick = |v: &[f64]| median(&mut m.valid_bins().map(|(k, _, _)| v[k]).collect::<Vec<_>>(), Middle::Mean);
    let s = CircularSummary {
        out: a.out.clone(),
        filter: m.filter.clone(),
        stokes: "V",
        plate_deg: m.plate_angles_deg.clone(),
        qwp_zero_angle_deg: m.qwp_zero_angle_deg,
        bin_px: m.geometry.bin_px,
        n_bins: m.geometry.len(),
        n_valid_bins: m.n_valid(),
        median_v: pick(&m.v),
        median_sigma_v: pick(&m.sigma_v),
        warnings: r.warnings.iter().map(|w| w.to_string()).collect(),
        product: m.product.as_ref().map(|p| p.with_run_inputs()),
    };
    if a.json {
        crate::util::print_json(&s)?;
    } else {
        outln!(
            "{}: filter {}, V/I map from {} quarter-wave plate angles ({:?} deg, zero angle {} deg), {} of {} bins of {} px valid; median V/I = {:+.4}%, sigma_V/I = {:.4}%",
            s.out.display(),
            s.filter,
            s.plate_deg.len(),
            s.plate_deg,
            s.qwp_zero_angle_deg,
            s.n_valid_bins,
            s.n_bins,
            s.bin_px,
            100.0 * s.median_v,
            100.0 * s.median_sigma_v
        );
    }
    Ok(())
}
