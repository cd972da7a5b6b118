//! `sim::Scene::from_toml_str` (parse + validation, which loads the instrument), then, for
//! scenes on the 64 x 64 instrument whose files are the scratch folder's own, the plan
//! (`sim::Plan::build`: instrumental field files, maps, extended images) and the first frame
//! (`Plan::render`). Scenes on FORS1 stop after validation (a 2048 x 2048 plan is too slow
//! per input).
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fn ours(p: &Path) -> bool {
    p.starts_with(instpol_fuzz::scratch())
        && !p.components().any(|c| matches!(c, std::path::Component::ParentDir))
        && p.is_file()
}

fuzz_target!(
    init: {
        instpol_fuzz::scene_files();
    },
    |data: &[u8]| {
        let Ok(text) = std::str::from_utf8(data) else { return };
        let label = instpol_fuzz::scratch().join("scene.toml");
        let Ok(scene) = sim::Scene::from_toml_str(text, &label) else { return };
        if !Path::new(&scene.instrument).starts_with(instpol_fuzz::scratch()) {
            return;
        }
        let Ok(inst) = instrument::Instrument::load(&scene.instrument) else { return };
        if inst.detector.nx * inst.detector.ny > 128 * 128 {
            return;
        }
        let files_ok = scene.extended.iter().filter_map(|e| e.image.as_deref()).all(ours)
            && match &scene.effects.instpol {
                Some(sim::scene::InstPolSpec::Map { q_file, u_file, .. }) => ours(q_file) && ours(u_file),
                Some(sim::scene::InstPolSpec::Raytrace { file, .. }) => ours(file),
                _ => true,
            };
        if !files_ok {
            return;
        }
        if let Ok(plan) = sim::Plan::build(&scene) {
            let (nx, ny) = plan.size();
            let frame = plan.render(0);
            assert_eq!(frame.len(), nx * ny, "a rendered frame has the detector's size");
        }
    }
);
