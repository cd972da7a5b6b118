//! A calibration file of two field elements, in order, corrected together: a scene whose light
//! meets a stressed lens first and then the radial partial polarizer of `eq:instpol` (the
//! paper's V-band form `p(r) = sum c_k r^k`, here `0.1 r + 0.2 r^2` % so that the order shows)
//! and the plate's zero angle, simulated by `sim`, reduced by `skyfield` into a Stokes map, and
//! corrected with a calibration file holding both elements with the scene's true parameters
//! (the lens, then the field model; `fit::files::elements`) through `instpol correct`'s library
//! call (`fit::correction::request::plan_map`): every bin comes back to the scene's sky within
//! its errors. The truth is the scene's sky, not the code under test. The same two elements in
//! the other order do not come back, nor does the field model alone.

use fit::correction::correct::Method;
use fit::correction::request::{plan_map, Request};
use fit::files::elements::Element;
use skyfield::reduce::{reduce_files, ReduceConfig};
use std::path::{Path, PathBuf};

const ANGLES: [f64; 8] = [0.0, 22.5, 45.0, 67.5, 90.0, 112.5, 135.0, 157.5];
const SKY_P: f64 = 0.03;
const SKY_CHI_DEG: f64 = 20.0;
const ZERO_ANGLE_DEG: f64 = 7.0;

/// FORS1's 6.8' field on 256 x 256 px of 1.6" (few pixels, the whole field).
fn coarse_fors1(dir: &Path) -> PathBuf {
    let text = crate::common::coarse_fors1_text();
    let p = dir.join("coarse_fors1.toml");
    std::fs::write(&p, text).unwrap();
    p
}

fn scene(dir: &Path) -> sim::Scene {
    let text = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 5\nhwp_angles_deg = {ANGLES:?}\nexposure_s = 600\n\
         [output]\nbitpix = -64\n\
         [sky]\nbrightness_e = 50000.0\np = {SKY_P}\nchi_deg = {SKY_CHI_DEG}\n\
         [effects]\nphoton_noise = true\nhwp_chi_offset_deg = {ZERO_ANGLE_DEG}\n\
         [effects.instpol]\nkind = \"radial\"\ncoeffs_percent = [0.0, 0.1, 0.2, 0.0]\n\
         [effects.stressed_lens]\nretardance_edge_deg = 90.0\nradius_arcmin = 3.4\ncentre_arcmin = [0.3, -0.2]\n\
         before_instpol = true\n",
        coarse_fors1(dir).display()
    );
    sim::Scene::from_toml_str(&text, &dir.join("scene.toml")).unwrap()
}

/// The scene's radial field as a calibration (its true coefficients, no errors), in the sky
/// frame of the scene's zero angle.
fn field_calibration() -> fit::Calibration {
    crate::given::given_calibration(
        "FORS1",
        "V",
        554.0,
        ZERO_ANGLE_DEG,
        fit::Model::Radial(fit::RadialModel::new(0, vec![0.0, 0.001, 0.002], [0.0, 0.0])),
        3.5,
    )
}

/// The RMS and worst pull of the corrected map's valid bins about the scene's sky, and the
/// number of bins.
fn pulls(cal: &Path, map: &skyfield::StokesMap) -> (f64, f64, usize) {
    let file = fit::files::calibration::load(cal).unwrap();
    let plan = plan_map(&file, &Request::new(Method::Exact, false, 0.5), map).unwrap();
    let (c, _) = plan.correct(map, "cal.fits").unwrap();
    let chi = SKY_CHI_DEG.to_radians();
    let truth = (SKY_P * (2.0 * chi).cos(), SKY_P * (2.0 * chi).sin());
    let m = &c.map;
    let (mut n, mut sum2, mut worst) = (0, 0.0, 0.0f64);
    for k in (0..m.q.len()).filter(|&k| m.valid[k]) {
        for p in [(m.q[k] - truth.0) / m.sigma_q[k], (m.u[k] - truth.1) / m.sigma_u[k]] {
            sum2 += p * p;
            worst = worst.max(p.abs());
        }
        n += 1;
    }
    ((sum2 / (2 * n) as f64).sqrt(), worst, n)
}

#[test]
fn a_lens_then_a_radial_field_in_one_file_come_back_to_the_sky() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path());
    let out = sim::simulate(&sc, &dir.path().join("out"), &|| {}).unwrap();
    let inst = instrument::Instrument::load(&sc.instrument).unwrap();
    let map = reduce_files(&out.frames, &inst, &ReduceConfig { bin_px: 7, ..Default::default() }, &|| {}).unwrap().map;
    let lens = sc.effects.stressed_lens.as_ref().unwrap().element();
    let cal = field_calibration();
    let write = |name: &str, order: &[Element]| {
        let p = dir.path().join(name);
        cal.save_with_elements(&p, order, |_, _| Ok(())).unwrap();
        p
    };
    let in_order = write("lens_then_field.fits", &[Element::StressedLens(lens), Element::Model]);
    let swapped = write("field_then_lens.fits", &[Element::Model, Element::StressedLens(lens)]);
    let alone = dir.path().join("field.fits");
    cal.save(&alone).unwrap();

    let (rms, worst, n) = pulls(&in_order, &map);
    let (rms_swapped, _, _) = pulls(&swapped, &map);
    let (rms_alone, _, _) = pulls(&alone, &map);
    eprintln!("{n} bins: RMS pull {rms:.2} (worst {worst:.2}); swapped {rms_swapped:.1}; field alone {rms_alone:.1}");
    assert!(n >= 100, "{n} bins");
    assert!(rms > 0.6 && rms < 1.5, "the corrected bins scatter by {rms} of their errors");
    assert!(worst < 5.0, "a bin {worst} sigma off");
    assert!(rms_swapped > 5.0, "the elements in the other order correct as well ({rms_swapped}): order is not shown");
    assert!(rms_alone > 5.0, "the field model alone corrects as well ({rms_alone}): the lens is not shown");

    // The file says what it holds: format version 2, two elements, the model second.
    let file = fit::files::calibration::load(&in_order).unwrap();
    assert_eq!(file.elements, vec![Element::StressedLens(lens), Element::Model]);
    assert_eq!(file.field.as_ref().unwrap().format_version, fit::files::keys::NEWEST_FORMAT_VERSION);
    assert!(fit::files::calibration::load(&alone).unwrap().elements.is_empty());
}
