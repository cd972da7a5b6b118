//! `instpol fit`: refit a calibration file (native or imported) with the radial model.

use anyhow::{Context, Result};
use fit::models::pipeline::refit;
use std::path::PathBuf;

/// Refit the binned measurements of any calibration file (made by `calibrate` or by
/// `import-map`) with the radial model p(r) = sum c_k r^k, optionally with a free centre,
/// exclusions and a residual map; print the same numbers (and JSON) as `calibrate`.
///
/// Example: instpol fit fors2_v.fits --free-centre --json
#[derive(clap::Args)]
pub struct Args {
    /// Calibration file (FITS).
    pub calibration: PathBuf,
    #[command(flatten)]
    pub fit: crate::cmd::calibrate::FitArgs,
    /// Write the refitted calibration (radial model) to this file.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Draw the map, profile and residual plots (PNG and SVG) into this folder.
    #[arg(long)]
    pub plots: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs([a.calibration.as_path()])?;
    if let Some(o) = &a.out {
        crate::util::check_output(o)?;
    }
    let opts = a.fit.options()?;
    let cal = fit::Calibration::load(&a.calibration)?;
    let run = refit(&cal, &opts).with_context(|| format!("fitting {}", a.calibration.display()))?;
    crate::cmd::calibrate::finish(&run, a.out.as_deref(), a.plots.as_deref(), a.json)
}
