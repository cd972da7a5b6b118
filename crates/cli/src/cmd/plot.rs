//! `instpol plot`: the paper's figures for a calibration file.

use anyhow::{Context, Result};
use fit::models::pipeline::{refit, CalibrateOptions, CalibrationRun};
use std::path::{Path, PathBuf};

/// Draw a calibration's figures as PNG and SVG into a folder: the instrumental polarization map
/// as vectors over contours of 0.3, 0.6 and 0.9% (fig:insmapB), the radial profile with the
/// fitted p(r) and the polar-angle test (fig:radprofB), and the residual field (fig:residB).
/// An imported map without a radial model gets a free-centre radial fit for the profile.
///
/// Example: instpol plot cal_V.fits --out plots/
#[derive(clap::Args)]
pub struct Args {
    /// Calibration file (FITS).
    pub calibration: PathBuf,
    /// Output folder (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// A ray-trace prediction drawn on the profile: CSV with columns r_arcmin,p (p a
    /// fraction, one header line), or JSON {"radius_arcmin": [...], "p": [...]} (the ray
    /// tracer's profile file).
    #[arg(long)]
    pub raytrace: Option<PathBuf>,
    /// Print the written files as JSON.
    #[arg(long)]
    pub json: bool,
}

fn read_raytrace(path: &Path) -> Result<Vec<(f64, f64)>> {
    if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("json")) {
        #[derive(serde::Deserialize)]
        struct Profile {
            radius_arcmin: Vec<f64>,
            p: Vec<f64>,
        }
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
        let pr: Profile = serde_json::from_str(&text)
            .with_context(|| format!("{}: expected {{\"radius_arcmin\": [...], \"p\": [...]}}", path.display()))?;
        if pr.radius_arcmin.is_empty() || pr.radius_arcmin.len() != pr.p.len() {
            anyhow::bail!("{}: radius_arcmin and p must be of one length, not empty", path.display());
        }
        return Ok(pr.radius_arcmin.into_iter().zip(pr.p).collect());
    }
    let mut rd = csv::ReaderBuilder::new()
        .has_headers(true)
        .from_path(path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    let mut v = vec![];
    for (i, rec) in rd.records().enumerate() {
        let rec = rec.with_context(|| format!("{}: row {}", path.display(), i + 2))?;
        let num = |k: usize| -> Result<f64> {
            rec.get(k)
                .and_then(|s| s.trim().parse::<f64>().ok())
                .with_context(|| format!("{}: row {}: column {} is not a number", path.display(), i + 2, k + 1))
        };
        v.push((num(0)?, num(1)?));
    }
    if v.is_empty() {
        anyhow::bail!("{}: no profile rows (expected a header line, then r_arcmin,p rows)", path.display());
    }
    Ok(v)
}

/// Plots of a calibration run (used by calibrate, fit and demo too).
pub fn plot_run(dir: &Path, stem: &str, run: &CalibrationRun) -> Result<Vec<PathBuf>> {
    plot_with(dir, stem, run, None, true)
}

/// A calibration file with the radial refit its profile panel draws (as `instpol plot` does).
pub fn refit_file(path: &Path) -> Result<CalibrationRun> {
    let cal = fit::Calibration::load(path)?;
    let fo = fit::models::pipeline::refit_options(&cal);
    let mut run = refit(&cal, &CalibrateOptions { fit: fo, ..Default::default() })
        .with_context(|| format!("radial fit of {} for the profile", path.display()))?;
    run.calibration = cal;
    Ok(run)
}

/// The figures of a calibration as SVG files only: `DIR/STEM_map.svg`, `_profile.svg`,
/// `_residual.svg` (a report's figures).
pub fn svg_figures(dir: &Path, stem: &str, run: &CalibrationRun) -> Result<Vec<PathBuf>> {
    plot_with(dir, stem, run, None, false)
}

fn plot_with(
    dir: &Path,
    stem: &str,
    run: &CalibrationRun,
    raytrace: Option<Vec<(f64, f64)>>,
    png: bool,
) -> Result<Vec<PathBuf>> {
    let cal = &run.calibration;
    let d = crate::plot::CalPlotData {
        cal,
        radial: Some(&run.fit.model),
        polar: Some(&run.polar).filter(|p| p.angles_defined()),
        raytrace,
        title: format!("{} {}", cal.instrument, cal.filter),
    };
    crate::plot::calibration_figures(dir, &stem.replace(['/', ' '], "_"), &d, png)
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs([a.calibration.as_path()].into_iter().chain(a.raytrace.as_deref()))?;
    let cal = fit::Calibration::load(&a.calibration)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("cannot create {}", a.out.display()))?;
    let raytrace = a.raytrace.as_deref().map(read_raytrace).transpose()?;
    // The stored model is drawn; the profile and polar-angle panels need the fit's products,
    // which a refit with the stored options reproduces (imported maps: free centre).
    let fo = fit::models::pipeline::refit_options(&cal);
    let mut run = refit(&cal, &CalibrateOptions { fit: fo, ..Default::default() })
        .with_context(|| format!("radial fit of {} for the profile", a.calibration.display()))?;
    // Draw the file's own model and images, not the refit's.
    run.calibration = cal;
    let stem = a.calibration.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "cal".into());
    let files = plot_with(&a.out, &stem, &run, raytrace, true)?;
    if a.json {
        crate::util::print_json(&serde_json::json!({ "outputs": files }))
    } else {
        for f in files {
            outln!("wrote {}", f.display());
        }
        Ok(())
    }
}
