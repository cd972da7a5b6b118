//! The simulator renders through the whole chain in the order light meets it: a Nasmyth
//! telescope (its M3 matrix over each exposure's parallactic-angle track), then the FORS1 V
//! radial field (`eq:instpol`), a stressed lens and a tilted half-wave plate, then the
//! analyser. On a noiseless tiny FORS1 with a Nasmyth M3, each pixel's normalized beam
//! difference in each frame equals `q cos 4 theta + u sin 4 theta` of the sky carried through
//! the elements' 4 x 4 Mueller matrices, multiplied here one by one in that order (the
//! telescope's matrix rebuilt from `mueller::telescope` as the scene describes it, the lens a
//! retarder of its retardance at the pixel), and differs from the other order by far more
//! than the tolerance. The circular polarization M3 makes is turned back into linear
//! polarization by the lens: dropping it (3 x 3 blocks) is also far off.

use field::FieldModel;
use mueller::telescope::{exposure_track, BandModel};

use crate::common;

/// FORS1 cut to 128 x 128 px with 2 strips, its telescope section replaced by a Nasmyth M3.
fn tiny_nasmyth_fors1(dir: &std::path::Path) -> std::path::PathBuf {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 128")
        .replace("ny = 2048", "ny = 128")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 6.0")
        .replace("strip_count = 9", "strip_count = 2")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 8");
    let out = common::with_nasmyth_m3(&text);
    let p = dir.join("tiny_nasmyth.toml");
    std::fs::write(&p, out).unwrap();
    p
}

type B = [[f64; 4]; 4];

fn of(m: &mueller::Mueller) -> B {
    std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)]))
}

fn app(b: &B, s: [f64; 4]) -> [f64; 4] {
    std::array::from_fn(|i| b[i][0] * s[0] + b[i][1] * s[1] + b[i][2] * s[2] + b[i][3] * s[3])
}

/// `b` without its circular polarization: what a chain of 3 x 3 blocks would do.
fn linear_only(b: &B) -> B {
    std::array::from_fn(|i| std::array::from_fn(|j| if i == 3 || j == 3 { 0.0 } else { b[i][j] }))
}

#[test]
fn telescope_then_field_lens_and_plate() {
    let dir = tempfile::tempdir().unwrap();
    let inst_path = tiny_nasmyth_fors1(dir.path());
    let angles: [f64; 8] = [0.0, 22.5, 45.0, 67.5, 90.0, 112.5, 135.0, 157.5];
    let scene = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 3\nhwp_angles_deg = {angles:?}\nexposure_s = 600\n\
         [output]\nbitpix = -64\n\
         [sky]\nbrightness_e = 1000.0\np = 0.03\nchi_deg = 20.0\n\
         [effects]\n\
         [effects.instpol]\nkind = \"radial\"\ncoeffs_percent = [0.0, 0.3, 0.4, 0.0]\n\
         [effects.stressed_lens]\nretardance_edge_deg = 50.0\nradius_arcmin = 0.2\ncentre_arcmin = [0.05, 0.0]\n\
         [effects.tilted_hwp]\ntilt_deg = 3.0\nmagnification = 20.0\n\
         [telescope]\nfactor = 1.0\noffset_deg = 30.0\ndec_deg = -60.0\nha_start_deg = -20.0\noverhead_s = 30\n",
        inst_path.display()
    );
    let sc = sim::Scene::from_toml_str(&scene, &dir.path().join("scene.toml")).unwrap();
    let out = sim::simulate(&sc, &dir.path().join("out"), &|| {}).expect("the whole chain is simulated");
    let inst = instrument::Instrument::load(&sc.instrument).unwrap();
    let g = skyfield::beams::BeamGeometry::new(&inst);
    let frames: Vec<_> = out.frames.iter().map(|p| skyfield::io::read_frame(p, &inst).unwrap()).collect();

    // The telescope's matrix of each exposure, as the scene describes it.
    let t = sc.telescope.as_ref().unwrap();
    let table = mueller::mirror::MetalTable::builtin("aluminium").unwrap();
    let w = inst.filter("V").unwrap().lambda_eff_nm / 1000.0;
    let model = BandModel {
        wavelength_um: w,
        index: table.index(w).unwrap(),
        factor: t.factor,
        thickness_nm: t.overlayer_thickness_nm,
        offset: t.offset_deg.to_radians(),
        q0: 0.0,
        u0: 0.0,
    };
    let lat = sc.site_latitude_deg(&inst).unwrap().to_radians();
    let tel: Vec<B> = (0..angles.len())
        .map(|k| {
            let (a, b) = t.hour_angles(k, sc.exposure_s);
            let track = exposure_track(lat, t.dec_deg.to_radians(), a.to_radians(), b.to_radians())
                .with_rotator(t.rotator_deg.to_radians());
            let m = model.matrix_track(track).unwrap();
            std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)] / m[(0, 0)]))
        })
        .collect();
    // The elements, each on its own.
    let radial = field::RadialPattern::new(vec![0.0, 0.003, 0.004, 0.0], [0.0, 0.0]);
    let lens = sc.effects.stressed_lens.clone().unwrap();
    let plate = sc.hwp_causes().unwrap().unwrap();
    let chi = 20f64.to_radians();
    let sky = [1.0, 0.03 * (2.0 * chi).cos(), 0.03 * (2.0 * chi).sin(), 0.0];
    let coords = inst.field_coords();
    let (mut n, mut worst, mut order_matters, mut v_matters) = (0, 0.0f64, 0.0f64, 0.0f64);
    for (x, y) in g.sky_pixels().step_by(7) {
        let (o, e) = g.beams_of_sky(x, y).unwrap();
        let (xa, ya) = coords.pixel_to_arcmin((o % g.nx) as f64, (o / g.nx) as f64);
        let (p, phi) = radial.p_phi(xa, ya);
        let f = of(&mueller::partial_polarizer(p, phi));
        let (delta, axis) = lens.retardance_at(xa, ya);
        let l = of(&mueller::retarder(delta, axis));
        // The plate's equivalent block says nothing of V (it is last before the analyser).
        let h = of(&plate.block_at(xa, ya).to_mueller());
        for (k, fr) in frames.iter().enumerate() {
            let s = app(&h, app(&l, app(&f, app(&tel[k], sky))));
            let th = angles[k].to_radians();
            let want = (s[1] * (4.0 * th).cos() + s[2] * (4.0 * th).sin()) / s[0];
            let got = (fr.data[o] - fr.data[e]) / (fr.data[o] + fr.data[e]);
            worst = worst.max((got - want).abs());
            // The telescope after the instrument's elements instead: what the old order gave.
            let r = app(&tel[k], app(&h, app(&l, app(&f, sky))));
            order_matters =
                order_matters.max(((r[1] * (4.0 * th).cos() + r[2] * (4.0 * th).sin()) / r[0] - want).abs());
            let c = app(&h, app(&linear_only(&l), app(&f, app(&linear_only(&tel[k]), sky))));
            v_matters = v_matters.max(((c[1] * (4.0 * th).cos() + c[2] * (4.0 * th).sin()) / c[0] - want).abs());
        }
        n += 1;
    }
    assert!(n > 100, "{n} pixels");
    assert!(worst < 1e-9, "frames differ from the chain by {worst:e}");
    assert!(order_matters > 1e-5, "the orders are not told apart ({order_matters:e})");
    assert!(v_matters > 1e-5, "circular polarization made by M3 changes nothing ({v_matters:e})");
}
