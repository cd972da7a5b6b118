//! `instpol simulate`: raw-like frames of a scene.

use anyhow::{bail, Context, Result};
use std::path::PathBuf;

/// Simulate raw-like dual-beam frames of a scene: one FITS file per HWP angle (the detector,
/// mask strips, o/e images and header keywords as the instrument file describes them) and a
/// truth.json with every input. An instrument whose [format] has chips (fors2, efosc2) gets
/// raw chip files instead, one per chip and frame with pre/overscan on a bias level, and bias
/// frames in OUT/bias/ when no overscan removes the bias (make a master bias of them with
/// `instpol master-bias`). A two-camera instrument (layout = "two_cameras", the built-in
/// moptop) gets one file per camera and frame. A scene's hwp_motion = { sweep_deg = 22.5 }
/// turns the plate through that range (deg) during each exposure, and the frames carry the
/// range under the instrument's [polarimetry.rotation] keywords (begin/end angles or rotor
/// position). Only the effects the scene's [effects] table lists are computed.
/// Scene format: every key in docs/guide/scene-file.md, examples in instruments/scenes/*.toml;
/// fluxes in e- per exposure, polarization as fractions, angles in degrees.
///
/// `--night DIR` writes a whole archive night instead (sim::night: bias frames, sky flats, empty
/// fields, standards, a target, an aborted set and another instrument's frames of a FORS2 shrunk
/// to 160 x 216 px): the instrument file, one scene per block, the frames under DIR/raw and the
/// sky fields' table DIR/skies.csv, for `instpol scan`, `run` and `report` (docs/nights.md).
///
/// Example: instpol simulate instruments/scenes/empty_V.toml --out frames_V
///
/// Example: instpol simulate --night night
#[derive(clap::Args)]
pub struct Args {
    /// Scene file (TOML).
    #[arg(required_unless_present = "night")]
    pub scene: Option<PathBuf>,
    /// Output folder (created if needed); files are written atomically.
    #[arg(long, required_unless_present = "night")]
    pub out: Option<PathBuf>,
    /// Write the documented archive night into this new (or empty) folder instead of a scene's
    /// frames.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["scene", "out", "field", "explain", "force"])]
    pub night: Option<PathBuf>,
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
    /// Write the frames even when they take more than 16 GB (the scene's frames are estimated
    /// before any is written).
    #[arg(long)]
    pub force: bool,
}

pub fn run(a: Args) -> Result<()> {
    if let Some(dir) = &a.night {
        return night(dir, a.json);
    }
    let (Some(scene_path), Some(out_dir)) = (&a.scene, &a.out) else { bail!("give a scene and --out, or --night DIR") };
    crate::util::inputs([scene_path.as_path()])?;
    let scene = sim::Scene::from_file(scene_path)?;
    let field = match &a.field {
        Some(p) => {
            crate::util::inputs([p.as_path()])?;
            let cal = fit::Calibration::load(p).with_context(|| format!("cannot load calibration {}", p.display()))?;
            let inst = instrument::Instrument::load(&scene.instrument)?;
            if !fit::correction::setup::matches_calibration(&inst.name, &scene.filter, &cal) {
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
    let plan = sim::Plan::build_with_field(&scene, field).with_context(|| format!("scene {}", scene_path.display()))?;
    plan.check_output_size(scene_path, a.force)?;
    if plan.output_bytes() > 1_000_000_000 && !a.json {
        eprintln!("note: writing about {:.1} GB of frames", plan.output_bytes() as f64 / 1e9);
    }
    // No frame or truth file may land on the scene or its instrument file.
    crate::util::inputs(crate::util::file_arg(&scene.instrument))?;
    let planned: Vec<PathBuf> = plan.output_files().iter().map(|f| out_dir.join(f)).collect();
    for p in &planned {
        crate::util::check_output(p)?;
    }
    if a.explain {
        eprintln!("{}", plan.explain());
    }
    let bar =
        if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(plan.n_frames() as u64) };
    // (Bias frames, when written, take a fraction of a frame's time each: not counted.)
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} frames ({elapsed})")
            .expect("template")
            .progress_chars("=> "),
    );
    bar.set_message("writing");
    // A failed run (a full disk at frame 3) must not leave the frames it did write: they look
    // like a complete set to the next command. Only files this run created are removed.
    let existed: Vec<bool> = planned.iter().map(|p| p.exists()).collect();
    let out = match plan.write(out_dir, &|| bar.inc(1)) {
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
        outln!("wrote {} frames and {} to {}", plan.n_frames(), out.truth.display(), out_dir.display());
        if plan.writes_chips() {
            outln!(
                "{}'s frames are raw chip files ({} files, {} per frame, with pre/overscan and a bias level): reduce them with --instrument {}",
                plan.inst.name,
                out.frames.len(),
                plan.inst.format.chips.len(),
                scene.instrument
            );
        }
        if !out.bias.is_empty() {
            let dir = out_dir.join("bias");
            outln!(
                "its bias level needs a master bias: {} bias frames in {}; make it (outside the frames' folder) with\n  instpol master-bias {}/*.fits --instrument {} --out master_bias.fits\nthen give --bias master_bias.fits to reduce",
                plan.n_bias_frames(),
                dir.display(),
                dir.display(),
                scene.instrument,
            );
        }
    }
    Ok(())
}

/// `--night DIR`: the archive night of `sim::night`, and what to run on it.
fn night(dir: &std::path::Path, json: bool) -> Result<()> {
    let w = sim::night::write_archive_night(dir)?;
    if json {
        return crate::util::print_json(&w);
    }
    outln!(
        "wrote {} frame files of {} blocks to {}, the instrument file {} and the sky fields {}",
        w.frames.len(),
        w.scenes.len(),
        w.raw.display(),
        w.instrument.display(),
        w.sky_table.display()
    );
    outln!(
        "sort and run it with\n  instpol scan {} --instrument {} --sky-table {} --bin 8 --fwhm 3 --aperture 4 --out night.toml\n  instpol run night.toml",
        w.raw.display(),
        w.instrument.display(),
        w.sky_table.display()
    );
    Ok(())
}
