//! Time per 2048 x 2048 FORS1 frame: the ideal scene, then with each effect added in turn
//! (cumulative), and the whole N = 16 set rendered and written. Run with
//! `cargo bench -p instpol-sim --features bench --bench frame`.

use criterion::{criterion_group, criterion_main, Criterion};
use sim::{Plan, Scene};
use std::path::Path;

const BASE: &str =
    "instrument = \"fors1\"\nfilter = \"V\"\nseed = 1\n[sky]\nbrightness_e = 20000\np = 0.0174\nchi_deg = -53.8\n";

/// Each step adds one effect to the ones before it.
const STEPS: &[(&str, &str)] = &[
    ("ideal", ""),
    ("+instpol radial", "instpol = { kind = \"radial\", coeffs_percent = [0, 0.012, 0.046, 0.002] }\n"),
    (
        "+wollaston+hwp+post",
        "wollaston = { t = 0.51 }\nhwp_retardance_error_deg = 1\npost_analyzer = { b = 0.004, phi_deg = 20 }\n",
    ),
    ("+flat", "flat = { pixel_rms_o = 0.01, pixel_rms_e = 0.012, large_scale_o = 0.02, large_scale_e = 0.03 }\n"),
    ("+photon noise", "photon_noise = true\n"),
    ("+read noise", "read_noise = true\n"),
    ("+cosmic rays", "cosmic_rays = { rate_per_frame = 200 }\n"),
    ("+saturation", "saturation = true\n"),
];

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("frame_2048");
    g.sample_size(10);
    let mut effects = String::from("[effects]\n");
    for (name, add) in STEPS {
        effects.push_str(add);
        let scene = Scene::from_toml_str(&format!("{BASE}{effects}"), Path::new("bench.toml")).unwrap();
        let plan = Plan::build(&scene).unwrap();
        g.bench_function(*name, |b| b.iter(|| plan.render(0)));
    }
    g.finish();
    let mut g = c.benchmark_group("write_n16");
    g.sample_size(10);
    let text = format!(
        "hwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5, 180, 202.5, 225, 247.5, 270, 292.5, 315, 337.5]\n{BASE}{effects}"
    );
    let scene = Scene::from_toml_str(&text, Path::new("bench.toml")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    g.bench_function("simulate 16 frames, all effects", |b| {
        b.iter(|| sim::simulate(&scene, dir.path(), &|| {}).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
