//! The simulator's map reader (`read_map` in crates/sim/src/plan.rs: a 2-D image or the first
//! plane of a cube) through two scenes on the 64 x 64 instrument: one whose instrumental field
//! is `{ kind = "map", q_file = <input>, u_file = <input> }` (any size), one whose extended
//! source is the input image (must be 64 x 64): `sim::Plan::build`, then the first frame.
#![no_main]
use libfuzzer_sys::fuzz_target;

const MAP: &str = r#"instrument = "mini.toml"
filter = "V"
[sky]
brightness_e = 1000
[effects]
instpol = { kind = "map", q_file = "input.fits", u_file = "input.fits", bin_px = 8 }
"#;

const IMAGE: &str = r#"instrument = "mini.toml"
filter = "V"
[[extended]]
profile = "image"
image = "input.fits"
p = 0.05
"#;

fuzz_target!(
    init: {
        instpol_fuzz::seed_mode(instpol_fuzz::write_map_seeds);
    },
    |data: &[u8]| {
        let d = instpol_fuzz::scratch();
        let _ = instpol_fuzz::write_input("input.fits", data);
        for text in [MAP, IMAGE] {
            let scene = sim::Scene::from_toml_str(text, &d.join("scene.toml")).expect("the fixed scenes are valid");
            if let Ok(plan) = sim::Plan::build(&scene) {
                assert_eq!(plan.render(0).len(), 64 * 64);
            }
        }
    }
);
