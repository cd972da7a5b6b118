//! `instpol catalog`: every paired star of a frame set, measured in one run.

use anyhow::{Context, Result};
use fit::correction::{catalog_correct, correct};
use skyfield::catalog::{flags, CatalogConfig};
use skyfield::detect::DetectConfig;
use std::path::PathBuf;

/// Find every star in the frames, pair its ordinary image with its extraordinary one through
/// the instrument's beam layout (mask strips or a maskless calcite offset), and measure each
/// pair at every HWP angle: apertures re-centred per frame with exact pixel weights, the
/// background removed in each beam before F_i (paper, section background), Q/I, U/I, P and
/// chi with propagated and scatter-based errors, and flags (saturated, mask edge, blended)
/// where a star cannot be measured honestly. Frames repeating an HWP position are summed,
/// and each star is also measured in every exposure alone: an exposure off its repeats or
/// short of light (a cloud, a cosmic ray in one beam) flags the star (outlier_exposure, with
/// the exposure's index in outlier_exposures) and is named when most stars flag it.
///
/// With a quarter-wave plate ([polarimetry] plate = "quarter_wave") every star's V/I and its
/// error are measured instead (columns and JSON keys v, sigma_v; the catalog's
/// qwp_zero_angle_deg): the linear columns are NaN, the 2- and 4-position sets not determining
/// Q and U, and --cal is refused.
///
/// Example:
///   instpol catalog frames/*.fits --instrument fors1 --fwhm 4 --out stars.csv
///
/// Example (circular polarization, docs/guide/circular.md):
///   instpol catalog qwp/*.fits --instrument instruments/calcite_qwp.toml --hwp-angles -45,45
///   --fwhm 4.2 --aperture 9 --annulus 14,24
#[derive(clap::Args)]
pub struct Args {
    /// Frame files (FITS), one or more per HWP angle.
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Instrument: built-in name or path to an instrument TOML.
    /// Default: the built-in instrument the first file's INSTRUME keyword names (said on
    /// stderr); a file without one, or of no built-in instrument, is refused.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Expected FWHM of the stars (px): the width of the detection filter.
    #[arg(long, default_value_t = workflow::steps::DEFAULT_FWHM_PX)]
    pub fwhm: f64,
    /// Detection threshold (sigma of the filtered image's noise).
    #[arg(long, default_value_t = 5.0)]
    pub threshold: f64,
    /// Largest distance (px) between where the instrument's o/e offset puts a star's e image
    /// and a detected source, for the two to pair. Widen it when a warning says the partner
    /// images sit off by a common shift (an instrument file made for another filter).
    #[arg(long, default_value_t = DetectConfig::default().pair_tol_px, value_name = "PX")]
    pub pair_tol: f64,
    /// Aperture radius: pixels (8), a multiple of each star's measured FWHM (2.5fwhm) or
    /// 'best': per star, the radius of best S/N of its total flux on the curve of growth,
    /// 0.5 to 4 FWHM inside the annulus (the radius used is the aperture_px column).
    #[arg(long, default_value = workflow::steps::DEFAULT_APERTURE, value_name = "PX|Kfwhm|best", allow_hyphen_values = true)]
    pub aperture: String,
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
    #[command(flatten)]
    pub kappa: crate::cmd::frame_opts::KappaOpts,
    /// Calibration file: remove the instrumental polarization in the same run (the columns of
    /// `instpol correct`: q0, u0, sigma_q0, sigma_u0, cov_qu0, p0, sigma_p0, chi0_deg,
    /// sigma_chi0_deg, q_inst, u_inst, extrapolated), exact inversion of eq:instpol. The
    /// catalog's q, u already carry the instrument file's HWP zero angle, so only the
    /// calibration's difference from it is applied. A calibration holding a telescope model
    /// (instpol fit-standards, alone or beside a field model) is undone after the field, as each
    /// exposure saw it: each over its own parallactic track from its header (the instrument's
    /// [telescope] keywords), demodulated together.
    #[arg(long, value_name = "CAL.fits")]
    pub cal: Option<PathBuf>,
    /// With --cal: correct stars outside the calibrated field too (flagged, errors inflated).
    #[arg(long)]
    pub allow_extrapolation: bool,
    /// Measure the stars even when the photometry is estimated at more than 2e10 pixel visits
    /// (about a minute of one core): stars x frames x the annulus's area. A threshold far
    /// below the noise or a huge annulus is refused with the estimate unless this is given.
    #[arg(long)]
    pub force: bool,
}

/// A star's correction in the JSON: the columns of `instpol correct`.
#[derive(serde::Serialize)]
struct CorrRow {
    q0: f64,
    u0: f64,
    sigma_q0: f64,
    sigma_u0: f64,
    cov_qu0: f64,
    p0: f64,
    sigma_p0: f64,
    chi0_deg: f64,
    sigma_chi0_deg: f64,
    q_inst: f64,
    u_inst: f64,
    extrapolated: bool,
}

impl From<&correct::Corrected> for CorrRow {
    fn from(c: &correct::Corrected) -> Self {
        Self {
            q0: c.q0,
            u0: c.u0,
            sigma_q0: c.var_q0.sqrt(),
            sigma_u0: c.var_u0.sqrt(),
            cov_qu0: c.cov_qu0,
            p0: c.p0,
            sigma_p0: c.sigma_p0,
            chi0_deg: c.chi0.to_degrees(),
            sigma_chi0_deg: c.sigma_chi0.to_degrees(),
            q_inst: c.inst.q,
            u_inst: c.inst.u,
            extrapolated: c.extrapolated,
        }
    }
}

/// The JSON of a catalog corrected in the same run: the catalog, and per row its correction.
#[derive(serde::Serialize)]
struct CorrectedJson<'a> {
    #[serde(flatten)]
    catalog: &'a skyfield::catalog::Catalog,
    /// One entry per row (null for a star not measured).
    corrected: Vec<Option<CorrRow>>,
    calibration: String,
    chi_offset_applied_deg: f64,
    n_extrapolated: usize,
    /// With a telescope model: its name, its band used, and the exposures undone one by one.
    #[serde(skip_serializing_if = "Option::is_none")]
    telescope_model: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    telescope_band: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    telescope_exposures: Option<usize>,
}

pub fn run(a: Args) -> Result<()> {
    let instrument = crate::util::instrument_of(&a.instrument, a.frames.first().map(|p| p.as_path()))?;
    let inst = instrument::Instrument::load(&instrument)?;
    let annulus = crate::util::parse_radii(&a.annulus)?;
    let radius = crate::util::parse_aperture(&a.aperture)?;
    let cfg = CatalogConfig {
        detect: DetectConfig {
            fwhm_px: a.fwhm,
            threshold_sigma: a.threshold,
            pair_tol_px: a.pair_tol,
            ..Default::default()
        },
        radius,
        annulus: Some(annulus),
        weighting: skyfield::aperture::Weighting::Exact,
        kappa: a.kappa.correction()?,
        force: a.force,
    };
    cfg.check().map_err(|e| anyhow::anyhow!("--{e}"))?;
    if let Some(out) = &a.out {
        skyfield::table::Format::from_path(out).map_err(|e| anyhow::anyhow!("--out {e}"))?;
    }
    let frames: Vec<&std::path::Path> = a.frames.iter().map(|p| p.as_path()).collect();
    // The calibration frames and file are inputs too (provenance, and never written over).
    let others = [a.frame.bias.as_deref(), a.frame.flat.as_deref(), a.cal.as_deref()];
    crate::util::inputs_read_in_order(&frames, others.into_iter().flatten().chain(crate::util::file_arg(&instrument)))?;
    if let Some(out) = &a.out {
        crate::util::check_output(out)?;
    }
    let bar =
        if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(a.frames.len() as u64) };
    bar.set_message("reading");
    let read = a.frame.read_options()?;
    let loaded = match &a.cal {
        None => None,
        Some(path) => Some(
            fit::files::calibration::load(path)
                .with_context(|| format!("cannot load calibration {}", path.display()))?,
        ),
    };
    let opts = correct::CorrectOptions { allow_extrapolation: a.allow_extrapolation, ..Default::default() };
    let tick = bar.clone();
    // The one step (workflow::steps::catalog): measured, corrected with --cal, written.
    let res = workflow::steps::catalog(
        &a.frames,
        &inst,
        &read,
        &cfg,
        loaded.as_ref().map(|l| (l, opts)),
        a.out.as_deref(),
        Box::new(move || tick.inc(1)),
    );
    bar.finish_and_clear();
    let workflow::steps::CatalogRun { catalog: cat, warnings, corrected } = res.map_err(|e| match (e, &a.cal) {
        (workflow::steps::CatalogError::Correction(e), Some(p)) => anyhow::anyhow!("--cal {}: {e}", p.display()),
        (e, _) => e.into(),
    })?;
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    for e in cat.exposures.iter().flatten().filter(|e| e.outlier) {
        eprintln!(
            "warning: exposure {} (HWP {} deg) flagged by {} of {} stars (median light {:.0} % of their typical exposure's): kept in the sum",
            e.file,
            e.hwp_deg,
            e.n_stars_flagged,
            e.n_stars,
            100.0 * e.median_transparency
        );
    }
    // With a telescope model: its name, the band used and how many exposures were undone one by one.
    let (corrected, telescope_used): (Option<catalog_correct::CorrectedCatalog>, _) = match corrected {
        Some((c, used)) => (Some(c), used),
        None => (None, None),
    };
    if let Some(c) = corrected.as_ref().filter(|c| c.n_extrapolated > 0) {
        eprintln!(
            "warning: {} stars lie outside the calibrated field; corrected by extrapolation with inflated errors (flagged)",
            c.n_extrapolated
        );
    }
    let measured = cat.rows.iter().filter(|r| r.q.is_finite() || r.v.is_some_and(f64::is_finite)).count();
    // Frames turned against each other: said, since apertures then follow each star by its
    // own centroid only (a star too faint to centre would sit off its aperture).
    for f in cat.alignment.iter().filter(|f| f.rotation_significant) {
        eprintln!(
            "warning: the frame at HWP {} deg is rotated by {:.3} +- {:.3} deg against the first (from {} stars): apertures follow each star's centroid",
            f.hwp_deg, f.rotation_deg, f.sigma_rotation_deg, f.n_stars
        );
    }
    if a.json {
        match &corrected {
            None => crate::util::print_json(&cat)?,
            Some(c) => crate::util::print_json(&CorrectedJson {
                catalog: &cat,
                corrected: c.rows.iter().map(|r| r.as_ref().map(CorrRow::from)).collect(),
                calibration: a.cal.as_ref().map(|p| p.display().to_string()).unwrap_or_default(),
                chi_offset_applied_deg: c.chi_offset_applied_deg,
                n_extrapolated: c.n_extrapolated,
                telescope_model: telescope_used.as_ref().map(|t| t.model),
                telescope_band: telescope_used.as_ref().map(|t| t.band.clone()),
                telescope_exposures: telescope_used.as_ref().map(|t| t.exposures),
            })?,
        }
    } else {
        print_summary(&cat, measured, a.out.as_deref());
    }
    Ok(())
}

/// The console summary of a catalog: the grouping of chip files, the counts, the frames'
/// alignment and a line per star (V/I through a quarter-wave plate, P and chi otherwise).
fn print_summary(cat: &skyfield::catalog::Catalog, measured: usize, out: Option<&std::path::Path>) {
    let plate = match cat.qwp_zero_angle_deg {
        None => format!("{} HWP angles, chi zero angle {} deg", cat.hwp_deg.len(), cat.chi_offset_deg),
        Some(z) => format!("{} quarter-wave plate angles, plate zero angle {z} deg", cat.hwp_deg.len()),
    };
    if let Some(g) = &cat.grouping {
        outln!("{}", g.describe());
    }
    outln!(
        "{} sources, {} stars paired ({} measured, {} flagged), {} unpaired; filter {}, {plate}",
        cat.n_sources,
        cat.rows.len(),
        measured,
        cat.rows.len() - measured,
        cat.unpaired.len(),
        cat.filter,
    );
    if let Some(why) = unpaired_words(cat) {
        outln!("unpaired: {why}");
    }
    if !cat.alignment.is_empty() {
        let shift = cat.alignment.iter().map(|f| f.dx_px.hypot(f.dy_px)).fold(0.0, f64::max);
        let rot = cat.alignment.iter().map(|f| f.rotation_deg.abs()).fold(0.0, f64::max);
        let n_rot = cat.alignment.iter().filter(|f| f.rotation_significant).count();
        outln!(
            "frames against the first: largest shift {shift:.2} px, largest rotation {rot:.3} deg ({} significant at {} sigma)",
            if n_rot == 0 { "none".to_string() } else { format!("{n_rot} frames") },
            skyfield::catalog::ROTATION_SIGNIFICANT_SIGMA
        );
    }
    if cat.qwp_zero_angle_deg.is_some() {
        outln!("V/I of every star (IAU sign); P and chi are not measured through a quarter-wave plate");
        outln!("  id        x        y    V/I %     +-  flags");
        for r in &cat.rows {
            outln!(
                "{:4} {:8.2} {:8.2} {:+8.3} {:6.3}  {}{}",
                r.id,
                r.x,
                r.y,
                100.0 * r.v.unwrap_or(f64::NAN),
                100.0 * r.sigma_v.unwrap_or(f64::NAN),
                flags::names(r.flags),
                note_of(r)
            );
        }
        if let Some(out) = &out {
            outln!("wrote {}", out.display());
        }
        return;
    }
    outln!("  id        x        y      P %     +-   chi deg     +-  flags");
    for r in &cat.rows {
        outln!(
            "{:4} {:8.2} {:8.2} {:8.3} {:6.3} {:9.2} {:6.2}  {}{}",
            r.id,
            r.x,
            r.y,
            100.0 * r.p,
            100.0 * r.sigma_p,
            r.chi_deg,
            r.sigma_chi_deg,
            flags::names(r.flags),
            note_of(r)
        );
    }
    if let Some(out) = &out {
        outln!("wrote {}", out.display());
    }
}

/// A star's note (why it was not measured, or what was done to it) after its flags.
fn note_of(r: &skyfield::catalog::Row) -> String {
    if r.note.is_empty() {
        String::new()
    } else {
        format!("  ({})", r.note)
    }
}

/// How many sources went unpaired for each reason the library gives, most first.
fn unpaired_words(cat: &skyfield::catalog::Catalog) -> Option<String> {
    use skyfield::detect::Unpaired;
    let mut counts: Vec<(usize, Unpaired)> = [Unpaired::NoPartner, Unpaired::OffDetector, Unpaired::LoneE]
        .into_iter()
        .map(|w| (cat.unpaired_why.iter().filter(|&&x| x == w).count(), w))
        .filter(|(n, _)| *n > 0)
        .collect();
    counts.sort_by_key(|c| std::cmp::Reverse(c.0));
    let parts: Vec<String> = counts.iter().map(|(n, w)| format!("{n} {}", w.words())).collect();
    (!parts.is_empty()).then(|| parts.join("; "))
}
