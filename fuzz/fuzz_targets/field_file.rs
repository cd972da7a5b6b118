//! The ray tracer's field file (`instpol-field-v1`, `mueller::raytrace::FieldFile`) as the
//! simulator reads it: a scene on the 64 x 64 instrument with
//! `instpol = { kind = "raytrace", file = ... }` pointing at the input, `sim::Plan::build`
//! (JSON parse + the reader's checks), the first frame rendered (the field evaluated at every
//! pixel), and `FieldFile::eval` at the centre, far out and at non-finite positions.
#![no_main]
use libfuzzer_sys::fuzz_target;

const SCENE: &str = r#"instrument = "mini.toml"
filter = "V"
[sky]
brightness_e = 1000
p = 0.01
[effects]
instpol = { kind = "raytrace", file = "input.json", centre_arcmin = [0.1, -0.2] }
"#;

fuzz_target!(|data: &[u8]| {
    let d = instpol_fuzz::scratch();
    let _ = instpol_fuzz::write_input("input.json", data);
    let scene = sim::Scene::from_toml_str(SCENE, &d.join("scene.toml")).expect("the fixed scene is valid");
    let Ok(plan) = sim::Plan::build(&scene) else { return };
    let frame = plan.render(0);
    assert_eq!(frame.len(), 64 * 64);
    // The plan accepted the file: the evaluator must cope with any position.
    let f: mueller::raytrace::FieldFile = serde_json::from_slice(data).expect("the plan parsed it");
    for (x, y) in [(0.0, 0.0), (1.0, 1.0), (1e6, -1e6), (f64::NAN, 0.0), (f64::INFINITY, 1.0)] {
        let _ = f.eval(x, y);
    }
});
