//! The simulator and the main job end to end (`instpol.simulate`, `instpol.demo`, as `instpol
//! simulate` and `instpol demo`).

use crate::convert::*;
use crate::errors::*;
use pyo3::prelude::*;
use std::path::PathBuf;

/// The main job end to end on the paper's fields (`workflow::demo::run`, what `instpol demo` runs)
/// into the folder `out`: its report as JSON text (the `instpol demo --json` keys; no plots,
/// so `plot_outputs` lists none). FileError when a file cannot be written, InputError else.
#[pyfunction]
#[pyo3(signature = (out, through_frames, keep_frames, seed))]
pub(crate) fn _demo(
    py: Python<'_>,
    out: PathBuf,
    through_frames: bool,
    keep_frames: bool,
    seed: u64,
) -> PyResult<String> {
    let opts = workflow::demo::DemoOptions { through_frames, keep_frames, seed };
    let demo = py.detach(|| workflow::demo::run(&out, &opts, &|_| {})).map_err(|e| match e {
        workflow::demo::Error::Create { .. }
        | workflow::demo::Error::Fit(fit::Error::Io { .. } | fit::Error::Fits { .. }) => {
            FileError::new_err(e.to_string())
        }
        workflow::demo::Error::Frames(e) => sky_err(e),
        e => input_err(e),
    })?;
    serde_json::to_string(&demo.report).map_err(|e| input_err(format!("the demo's report: {e}")))
}

/// Raw-like frames of a scene (`sim::Plan::write`, what `instpol simulate` runs) into the folder
/// `out`: what was written as JSON text (`instpol simulate --json`'s keys). `scene`: a scene
/// file, or with `scene_json` the scene's table as JSON text (`label` names it in errors, its
/// paths taken as they are). `field`: a calibration whose model replaces the scene's
/// `[effects.instpol]` (of the scene's instrument and filter). No frame lands on the scene, its
/// instrument file or the calibration; a run that fails removes the files it created.
#[pyfunction]
#[pyo3(signature = (scene, scene_json, out, field, force))]
pub(crate) fn _simulate(
    py: Python<'_>,
    scene: PathBuf,
    scene_json: Option<&str>,
    out: PathBuf,
    field: Option<PathBuf>,
    force: bool,
) -> PyResult<String> {
    let sim_err = |e: sim::Error| match e {
        sim::Error::File { .. } => FileError::new_err(e.to_string()),
        sim::Error::Frames(e) => sky_err(e),
        sim::Error::Instrument(e) => inst_err(e),
        e => input_err(e),
    };
    let sc = match scene_json {
        Some(text) => serde_json::from_str::<sim::Scene>(text)
            .map_err(|e| input_err(format!("scene {}: {e}", scene.display())))?
            .checked(&scene)
            .map_err(sim_err)?,
        None => sim::Scene::from_file(&scene).map_err(sim_err)?,
    };
    let mut inputs: Vec<PathBuf> = vec![];
    if scene_json.is_none() {
        inputs.push(scene.clone());
    }
    if std::path::Path::new(&sc.instrument).is_file() {
        inputs.push(PathBuf::from(&sc.instrument));
    }
    let model = match &field {
        Some(p) => {
            inputs.push(p.clone());
            let cal = fit::Calibration::load(p).map_err(|e| load_err(p, e))?;
            let inst = instrument::Instrument::load(&sc.instrument).map_err(inst_err)?;
            if !fit::correction::setup::matches_calibration(&inst.name, &sc.filter, &cal) {
                return Err(input_err(format!(
                    "{} calibrates {} {} but the scene is {} {}: use a calibration of the scene's instrument and filter",
                    p.display(),
                    cal.instrument,
                    cal.filter,
                    inst.name,
                    sc.filter
                )));
            }
            Some(std::sync::Arc::new(cal) as std::sync::Arc<dyn field::FieldModel>)
        }
        None => None,
    };
    let plan = sim::Plan::build_with_field(&sc, model).map_err(sim_err)?;
    plan.check_output_size(&scene, force).map_err(sim_err)?;
    let planned: Vec<PathBuf> = plan.output_files().iter().map(|f| out.join(f)).collect();
    for p in &planned {
        refuse_overwrite(Some(p), &inputs)?;
    }
    let existed: Vec<bool> = planned.iter().map(|p| p.exists()).collect();
    let written = py.detach(|| plan.write(&out, &|| {}));
    let written = match written {
        Ok(w) => w,
        Err(e) => {
            for (p, was) in planned.iter().zip(existed) {
                if !was {
                    let _ = std::fs::remove_file(p);
                }
            }
            return Err(sim_err(e));
        }
    };
    serde_json::to_string(&written).map_err(|e| input_err(format!("what was written: {e}")))
}
