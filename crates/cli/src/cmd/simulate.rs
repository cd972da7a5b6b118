//! `instpol simulate`: raw-like frames of a scene.

use anyhow::{bail, Context, Result};
use std::path::PathBuf;

/// Simulate raw-like dual-beam frames of a scene: one FITS file per HWP angle (the detector,
/// mask strips, o/e images and header keywords as the instrument file describes them) and a
/// truth.json with every input. Only the effects the scene's [effects] table lists are
/// computed. Scene format: see the `sim::scene` docs and instruments/scenes/*.toml; fluxes in
/// e- per exposure, polarization as fractions, angles in degrees.
#[derive(clap::Args)]
pub struct Args {
    /// Scene file (TOML).
    pub scene: PathBuf,
    /// Output folder (created if needed); files are written atomically.
    #[arg(long)]
    pub out: PathBuf,
    /// Instrumental field from a calibration file (`instpol calibrate` or `instpol import-map`):
    /// its model (any kind) is put into the frames instead of the scene's [effects.instpol].
    /// The calibration must be of the scene's instrument and filter.
    #[arg(long, value_name = "CAL.fits")]
    pub field: Option<PathBuf>,
    /// Print the optical train and the noise steps built for this scene.
    #[arg(long)]
    pub explain: bool,
    /// Print what was written as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs([a.scene.as_path()])?;
    let scene = sim::Scene::from_file(&a.scene)?;
    let field = match &a.field {
        Some(p) => {
            crate::util::inputs([p.as_path()])?;
            let cal = fit::Calibration::load(p).with_context(|| format!("cannot load calibration {}", p.display()))?;
            let inst = instrument::Instrument::load(&scene.instrument)?;
            if !fit::setup::matches_calibration(&inst.name, &scene.filter, &cal) {
                bail!(
                    "{} calibrates {} {} but the scene is {} {}: use a calibration of the scene's instrument and filter",
                    p.display(),
                    cal.instrument,
                    cal.filter,
                    inst.name,
                    scene.filter
                );
            }
            Some(std::sync::Arc::new(cal) as std::sync::Arc<dyn field::FieldModel>)
        }
        None => None,
    };
    let plan = sim::Plan::build_with_field(&scene, field).with_context(|| format!("scene {}", a.scene.display()))?;
    // No frame or truth file may land on the scene or its instrument file.
    crate::util::inputs(crate::util::file_arg(&scene.instrument))?;
    for k in 0..plan.n_frames() {
        crate::util::check_output(&a.out.join(plan.frame_name(k)))?;
    }
    crate::util::check_output(&a.out.join("truth.json"))?;
    if a.explain {
        eprintln!("{}", plan.explain());
    }
    let bar =
        if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(plan.n_frames() as u64) };
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} frames ({elapsed})")
            .expect("template")
            .progress_chars("=> "),
    );
    bar.set_message("writing");
    // A failed run (a full disk at frame 3) must not leave the frames it did write: they look
    // like a complete set to the next command. Only files this run created are removed.
    let planned: Vec<std::path::PathBuf> =
        (0..plan.n_frames()).map(|k| a.out.join(plan.frame_name(k))).chain([a.out.join("truth.json")]).collect();
    let existed: Vec<bool> = planned.iter().map(|p| p.exists()).collect();
    let out = match plan.write(&a.out, &|| bar.inc(1)) {
        Ok(o) => o,
        Err(e) => {
            bar.finish_and_clear();
            for (p, was) in planned.iter().zip(existed) {
                if !was {
                    let _ = std::fs::remove_file(p);
                }
            }
            return Err(e.into());
        }
    };
    bar.finish_and_clear();
    if a.json {
        crate::util::print_json(&out)?;
    } else {
        outln!("wrote {} frames and {} to {}", out.frames.len(), out.truth.display(), a.out.display());
    }
    Ok(())
}
