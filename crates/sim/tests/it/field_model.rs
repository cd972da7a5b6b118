//! The simulator takes any field model as a value (`Plan::build_with_field`) and puts into the
//! frames exactly what the fitter's evaluation of the same object says: for each sky pixel,
//! the noise-free frames of an unpolarized sky (ideal HWP and Wollaston) give back the model's
//! `(q, u)` at the pixel's field position, `q = (F(0) - F(45))/2`, `u = (F(22.5) - F(67.5))/2`
//! (eq:F with the ideal optics of eq:ord), computed here from the o and e pixels alone.

use field::{FieldCoords, FieldModel, GridMap};
use fit::RadialModel;
use sim::{Plan, Scene};
use skyfield::beams::BeamGeometry;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A 256 x 256 detector, 0.2"/px, 8" throw (40 px strips), 3 strips from row 8.
fn tiny_instrument(dir: &Path) -> PathBuf {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 256")
        .replace("ny = 2048", "ny = 256")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 8.0")
        .replace("strip_count = 9", "strip_count = 3")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 8");
    let p = dir.join("tiny.toml");
    std::fs::write(&p, text).unwrap();
    p
}

/// The frames of `model` over an unpolarized sky, checked pixel by pixel against
/// `model.eval` at the fitter's coordinates of each pixel.
fn frames_carry_the_model(model: Arc<dyn FieldModel>, tol: f64) {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = tiny_instrument(dir.path());
    let text = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 1\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n\
         [output]\nbitpix = -64\n[sky]\nbrightness_e = 1000.0\n",
        inst_path.display()
    );
    let scene = Scene::from_toml_str(&text, &dir.path().join("scene.toml")).unwrap();
    let plan = Plan::build_with_field(&scene, Some(model.clone())).unwrap();
    let frames: Vec<Vec<f64>> = (0..4).map(|k| plan.render(k)).collect();
    let inst = instrument::Instrument::load(inst_path.to_str().unwrap()).unwrap();
    // The fitter's coordinates: arcmin from the detector centre.
    let coords = FieldCoords::centred(inst.detector.nx, inst.detector.ny, inst.detector.pixel_scale_arcsec);
    let geom = BeamGeometry::new(&inst);
    let mut n = 0;
    for (x, y) in geom.sky_pixels().step_by(7) {
        let (o, e) = geom.beams_of_sky(x, y).unwrap();
        let f: Vec<f64> = frames.iter().map(|img| (img[o] - img[e]) / (img[o] + img[e])).collect();
        let (q, u) = (0.5 * (f[0] - f[2]), 0.5 * (f[1] - f[3]));
        let (xa, ya) = coords.pixel_to_arcmin((o % inst.detector.nx) as f64, (o / inst.detector.nx) as f64);
        let want = model.eval(xa, ya);
        assert!(
            (q - want.q).abs() < tol && (u - want.u).abs() < tol,
            "pixel ({x}, {y}) = ({xa:.4}, {ya:.4})': frames give ({q:e}, {u:e}), the model ({:e}, {:e})",
            want.q,
            want.u
        );
        n += 1;
    }
    assert!(n > 1000, "{n} pixels checked");
}

/// A fitted-style radial model (the paper's V coefficients, exaggerated x 10 so the check is
/// not near zero, an off-centre optical axis) from the fitter's own crate.
#[test]
fn simulator_evaluates_a_fit_radial_model_as_the_fitter_does() {
    let m = RadialModel::new(1, vec![0.12e-2, 0.46e-2, 0.02e-2], [0.3, -0.2]);
    frames_carry_the_model(Arc::new(m), 1e-13);
}

/// A gridded map (bilinear, as a calibration file's images are evaluated): the simulator uses
/// the same interpolation, not a copy of its own.
#[test]
fn simulator_evaluates_a_grid_map_as_the_fitter_does() {
    let cells = FieldCoords::centred(256, 256, 0.2).binned(32);
    let (nx, ny) = (8, 8);
    let q: Vec<f64> = (0..nx * ny).map(|k| 0.01 * ((k % nx) as f64 - 3.5) / 4.0).collect();
    let u: Vec<f64> = (0..nx * ny).map(|k| -0.008 * ((k / nx) as f64 - 3.5) / 4.0 + 0.001 * (k % 3) as f64).collect();
    let g = GridMap::on_pixels(&cells, nx, ny, q, u, vec![1e-4; nx * ny], vec![1e-4; nx * ny]);
    frames_carry_the_model(Arc::new(g), 1e-13);
}

/// A scene that names its own `[effects.instpol]` and is given a model too is refused.
#[test]
fn a_model_and_a_scene_field_together_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = tiny_instrument(dir.path());
    let text = format!(
        "instrument = \"{}\"\nfilter = \"V\"\n[sky]\nbrightness_e = 1000.0\n[effects.instpol]\nkind = \"radial\"\ncoeffs_percent = [0.0, 0.1]\n",
        inst_path.display()
    );
    let scene = Scene::from_toml_str(&text, &dir.path().join("scene.toml")).unwrap();
    let m: Arc<dyn FieldModel> = Arc::new(field::RadialPattern::new(vec![0.0, 0.001], [0.0, 0.0]));
    let e = Plan::build_with_field(&scene, Some(m)).err().expect("refused").to_string();
    assert!(e.contains("instpol"), "{e}");
}
