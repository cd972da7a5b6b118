//! The instrument as one value, end to end: a scene with a Nasmyth telescope (M3 over each
//! exposure's parallactic-angle track), the FORS1 V radial field of Patat & Romaniello 2006
//! (`p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3` %, section `fors1`, as in
//! `instruments/scenes/empty_V.toml`), a stressed lens, a tilted half-wave plate and the
//! plate's zero angle is simulated, reduced by `skyfield`, and corrected with the chain the
//! simulator rendered through (`sim::Plan::chain`, inverted exposure by exposure): every bin's
//! sky `q, u` comes back within its errors, and a chain that leaves the lens out does not.
//!
//! The chain's forward model is checked against a Jones-matrix calculation written for the
//! tests (`crates/mueller/tests/support/jones.rs`), not through the chain's code: each
//! element's Jones matrix (the mirror by Fresnel's equations for
//! a bare metal, Born & Wolf 14.2, with the reflection's axes as in `mueller::mirror`; the lens
//! a linear retarder; the partial polarizer of `eq:instpol` as the incoherent sum of clear glass
//! and an ideal polarizer, weights `(1 - p) / (1 + p)` and `2 p / (1 + p)`), turned into
//! Mueller matrices by `M = A (J (x) J*) A^-1`, the mirror averaged over the track by Simpson's
//! rule, multiplied in the order light meets them, and the zero angle turned last.

use field::FieldModel;
use jones::C64;
use mueller::telescope::{Exposure, Track};
use mueller::Qu;
use nalgebra::Matrix4;
use skyfield::reduce::{reduce_files, ReduceConfig};
use std::path::{Path, PathBuf};

use crate::common;

/// FORS1's 6.8' field on 256 x 256 px of 1.6" (so that the radial field reaches its 1.4 %
/// at the corners in few pixels), its telescope section replaced by a Nasmyth M3.
fn coarse_nasmyth_fors1(dir: &Path) -> PathBuf {
    let text = common::coarse_fors1_text();
    let out = common::with_nasmyth_m3(&text);
    let p = dir.join("coarse_nasmyth.toml");
    std::fs::write(&p, out).unwrap();
    p
}

const ANGLES: [f64; 8] = [0.0, 22.5, 45.0, 67.5, 90.0, 112.5, 135.0, 157.5];
const SKY_P: f64 = 0.03;
const SKY_CHI_DEG: f64 = 20.0;

fn scene(dir: &Path, lens: bool) -> sim::Scene {
    scene_with(dir, lens, "photon_noise = true\n")
}

/// The scene with `effects`, the lines of `[effects]` besides the zero angle, each ended.
fn scene_with(dir: &Path, lens: bool, effects: &str) -> sim::Scene {
    let inst = coarse_nasmyth_fors1(dir);
    let lens = if lens {
        "[effects.stressed_lens]\nretardance_edge_deg = 40.0\nradius_arcmin = 3.4\ncentre_arcmin = [0.3, -0.2]\n"
    } else {
        ""
    };
    let text = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = 11\nhwp_angles_deg = {ANGLES:?}\nexposure_s = 600\n\
         [output]\nbitpix = -64\n\
         [sky]\nbrightness_e = 50000.0\np = {SKY_P}\nchi_deg = {SKY_CHI_DEG}\n\
         [effects]\n{effects}hwp_chi_offset_deg = 7.0\n\
         [effects.instpol]\nkind = \"radial\"\ncoeffs_percent = [0.0, 0.012, 0.046, 0.002]\n\
         {lens}\
         [effects.tilted_hwp]\ntilt_deg = 2.0\nmagnification = 20.0\n\
         [telescope]\nfactor = 1.0\noffset_deg = 30.0\ndec_deg = -60.0\nha_start_deg = -20.0\noverhead_s = 30\n",
        inst.display()
    );
    sim::Scene::from_toml_str(&text, &dir.join("scene.toml")).unwrap()
}

// The Jones calculus of the tests, written apart from the library.
#[path = "../../../mueller/tests/support/jones.rs"]
mod jones;
use jones::{jones_mirror, jones_polarizer, jones_retarder, mueller_of_jones, textbook_r};

/// `M_I(p, phi)` as clear glass and an ideal polarizer mixed incoherently.
fn partial_polarizer(p: f64, phi: f64) -> Matrix4<f64> {
    mueller_of_jones(&nalgebra::Matrix2::identity()) * ((1.0 - p) / (1.0 + p))
        + mueller_of_jones(&jones_polarizer(phi)) * (2.0 * p / (1.0 + p))
}

/// The Nasmyth M3 seen from the instrument at parallactic angle `q`: the mirror with its plane
/// at `pi/2 - q`, then the instrument's angle offset (axes turned by `offset`); Wiersema et al.
/// 2018 (PASA 35, e012), section 3.
fn m3(rp: C64, rs: C64, q: f64, offset: f64) -> Matrix4<f64> {
    mueller_of_jones(&(jones::jones_axes(offset) * jones_mirror(rp, rs, std::f64::consts::FRAC_PI_2 - q)))
}

/// M3 averaged over a track by Simpson's rule (2000 intervals) and divided by its `M_00`.
fn m3_track(rp: C64, rs: C64, t: Track, offset: f64) -> Matrix4<f64> {
    let n = 2000;
    let mut sum = Matrix4::zeros();
    for k in 0..=n {
        let w = if k == 0 || k == n {
            1.0
        } else if k % 2 == 1 {
            4.0
        } else {
            2.0
        };
        let q = t.start + (t.end - t.start) * k as f64 / n as f64;
        sum += m3(rp, rs, q, offset + t.rotator) * w;
    }
    sum / sum[(0, 0)]
}

/// The sky `(q, u)` through the elements in order, normalized, turned by `-zero` (rad).
fn through(ms: &[Matrix4<f64>], sky: (f64, f64), zero: f64) -> (f64, f64) {
    let mut s = nalgebra::Vector4::new(1.0, sky.0, sky.1, 0.0);
    for m in ms {
        s = m * s;
    }
    let (q, u) = (s[1] / s[0], s[2] / s[0]);
    let (sn, cs) = (2.0 * zero).sin_cos();
    (q * cs + u * sn, -q * sn + u * cs)
}

#[test]
fn forward_model_matches_a_jones_calculation() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path(), true);
    let plan = sim::Plan::build(&sc).unwrap();
    let chain = plan.chain();
    let band = chain.telescope.expect("the scene's telescope is in the chain");
    let (rp, rs) = textbook_r(band.index * band.factor, std::f64::consts::FRAC_PI_4);
    let zero = 7f64.to_radians();
    assert_eq!(chain.zero_angle, zero, "the scene's zero angle");
    let radial = field::RadialPattern::new(vec![0.0, 0.00012, 0.00046, 0.00002], [0.0, 0.0]);
    let lens = sc.effects.stressed_lens.clone().unwrap();
    let plate = sc.hwp_causes().unwrap().unwrap();
    let exposures = plan.exposures();
    assert!(exposures.windows(2).all(|w| w[0].track.start != w[1].track.start), "the exposures' tracks differ");
    let (mut worst, mut n) = (0.0f64, 0);
    for &(x, y) in &[(0.0, 0.0), (2.9, 3.1), (-3.3, 1.2), (1.0, -3.4), (-2.0, -2.5)] {
        let (p, phi) = radial.p_phi(x, y);
        let (delta, axis) = lens.retardance_at(x, y);
        // The tilted plate's equivalent block (its own code, tested in `sim::hwp_causes`),
        // last before the analyser: it passes no circular polarization.
        let h = plate.block_at(x, y).to_mueller();
        for e in exposures.iter().step_by(3).copied().chain([Exposure { hwp: 0.0, track: Track::at(0.7) }]) {
            let tel = m3_track(rp, rs, e.track, band.offset);
            let ms = [tel, partial_polarizer(p, phi), mueller_of_jones(&jones_retarder(delta, axis)), h];
            for &(sq, su) in &[(0.0, 0.0), (0.03, -0.02), (-0.1, 0.05)] {
                let want = through(&ms, (sq, su), zero);
                let got = chain.forward(x, y, &Qu::new(sq, su, 0.0, 0.0, 0.0), Some(e.track)).unwrap();
                worst = worst.max((got.q - want.0).abs()).max((got.u - want.1).abs());
                n += 1;
            }
        }
    }
    assert!(n >= 60, "{n} cases");
    assert!(worst < 1e-9, "the chain's forward model differs from the Jones calculation by {worst:e}");
}

/// The frames are the chain's forward model to the detector: without noise, the o and e pixels
/// of a sky point hold the sky's brightness times the fluxes of a Jones calculation of the
/// whole instrument (telescope over the exposure's track, field, lens, tilted plate, then an
/// ideal half-wave plate with its axis at the frame's angle plus half the zero angle and an
/// ideal Wollaston: `f_O, f_E = (I +- Q) / 2` behind the plate), in ADU of the scene's gain
/// (1e-9 relative).
#[test]
fn frames_are_the_chains_fluxes_of_a_jones_calculation() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene_with(dir.path(), true, "gain_e_per_adu = 1.0\n");
    let plan = sim::Plan::build(&sc).unwrap();
    let chain = plan.chain();
    let band = chain.telescope.expect("the scene's telescope is in the chain");
    let (rp, rs) = textbook_r(band.index * band.factor, std::f64::consts::FRAC_PI_4);
    let zero = 7f64.to_radians();
    let lens = sc.effects.stressed_lens.clone().unwrap();
    let plate = sc.hwp_causes().unwrap().unwrap();
    let radial = field::RadialPattern::new(vec![0.0, 0.00012, 0.00046, 0.00002], [0.0, 0.0]);
    let inst = instrument::Instrument::load(&sc.instrument).unwrap();
    let geom = skyfield::beams::BeamGeometry::new(&inst.for_filter(&sc.filter));
    let coords = inst.field_coords();
    let sky: Vec<(usize, usize)> = geom.sky_pixels().filter_map(|(x, y)| geom.beams_of_sky(x, y)).collect();
    let brightness = 50000.0;
    let chi = SKY_CHI_DEG.to_radians();
    let (sq, su) = (SKY_P * (2.0 * chi).cos(), SKY_P * (2.0 * chi).sin());
    let (mut worst, mut n) = (0.0f64, 0);
    for (k, e) in plan.exposures().iter().enumerate().step_by(3) {
        let img = plan.render(k);
        let tel = m3_track(rp, rs, e.track, band.offset);
        let hwp = mueller_of_jones(&jones_retarder(std::f64::consts::PI, e.hwp + 0.5 * zero));
        for &(o, ex) in sky.iter().step_by(sky.len() / 40) {
            let (x, y) = coords.pixel_to_arcmin((o % geom.nx) as f64, (o / geom.nx) as f64);
            let (p, phi) = radial.p_phi(x, y);
            let (delta, axis) = lens.retardance_at(x, y);
            let h = plate.block_at(x, y).to_mueller();
            let lensm = mueller_of_jones(&jones_retarder(delta, axis));
            let s = hwp * h * lensm * partial_polarizer(p, phi) * tel * nalgebra::Vector4::new(1.0, sq, su, 0.0);
            let (fo, fe) = (0.5 * (s[0] + s[1]) * brightness, 0.5 * (s[0] - s[1]) * brightness);
            for (got, want) in [(img[o], fo), (img[ex], fe)] {
                worst = worst.max((got - want).abs() / want);
                n += 1;
            }
        }
    }
    assert!(n >= 200, "{n} pixels");
    assert!(worst < 1e-9, "a frame differs from the Jones calculation by {worst:e} of its flux");
}

/// `forward` and `invert` are each other's inverse, the covariance included
/// (`J^-1 (J C J^T) J^-T = C`), for one exposure and for a demodulated set (both through
/// analytic Jacobians; the set's inverse is Newton's, converged to rounding).
#[test]
fn invert_undoes_forward_with_its_covariance() {
    let dir = tempfile::tempdir().unwrap();
    let plan = sim::Plan::build(&scene(dir.path(), true)).unwrap();
    let chain = plan.chain();
    let exposures = plan.exposures();
    let sky = Qu::new(0.021, -0.013, 4e-8, 9e-8, -1e-8);
    for &(x, y) in &[(0.0, 0.0), (2.9, 3.1), (-3.3, 1.2)] {
        let m = chain.forward(x, y, &sky, Some(exposures[2].track)).unwrap();
        let back = chain.invert(x, y, &m, Some(exposures[2].track)).unwrap();
        let m2 = chain.forward_exposures(x, y, &sky, &exposures).unwrap();
        let back2 = chain.invert_exposures(x, y, &m2, &exposures).unwrap();
        for (b, var_tol) in [(back, 1e-12), (back2, 1e-11)] {
            for (a, w, tol) in [
                (b.q, sky.q, 1e-13),
                (b.u, sky.u, 1e-13),
                (b.var_q, sky.var_q, var_tol),
                (b.var_u, sky.var_u, var_tol),
                (b.cov_qu, sky.cov_qu, var_tol),
            ] {
                assert!((a - w).abs() <= tol * w.abs().max(1e-7), "at ({x}, {y}): {a} vs {w}");
            }
        }
        // The exposures differ: the demodulated set is not one exposure's forward model.
        assert!((m2.q - m.q).abs() + (m2.u - m.u).abs() > 1e-6);
    }
}

/// Simulated, reduced, corrected: each bin's sky back within its errors.
#[test]
fn simulated_reduced_and_corrected_through_one_chain() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path(), true);
    let plan = sim::Plan::build(&sc).unwrap();
    let out = plan.write(&dir.path().join("out"), &|| {}).unwrap();
    let inst = instrument::Instrument::load(&sc.instrument).unwrap();
    // Half a strip (14 px) per bin.
    let cfg = ReduceConfig { bin_px: 7, ..Default::default() };
    let map = reduce_files(&out.frames, &inst, &cfg, &|| {}).unwrap().map;
    let exposures = plan.exposures();
    // The same chain without the lens: what a calibration that missed it would do.
    let dir2 = tempfile::tempdir().unwrap();
    let no_lens = sim::Plan::build(&scene(dir2.path(), false)).unwrap();
    let chi = SKY_CHI_DEG.to_radians();
    let truth = (SKY_P * (2.0 * chi).cos(), SKY_P * (2.0 * chi).sin());
    let g = &map.geometry;
    let (mut n, mut sum2, mut worst, mut raw2, mut no_lens2) = (0, 0.0, 0.0f64, 0.0, 0.0);
    for k in (0..g.len()).filter(|&k| map.valid[k]) {
        let (x, y) = g.centre_arcmin(k % g.nx, k / g.nx);
        let m = Qu::from_sigmas(map.q[k], map.u[k], map.sigma_q[k], map.sigma_u[k], map.cov_qu[k]);
        let sky = plan.chain().invert_exposures(x, y, &m, &exposures).unwrap();
        let pull = |v: f64, t: f64, var: f64| (v - t) / var.sqrt();
        for p in [pull(sky.q, truth.0, sky.var_q), pull(sky.u, truth.1, sky.var_u)] {
            sum2 += p * p;
            worst = worst.max(p.abs());
        }
        for p in [pull(m.q, truth.0, m.var_q), pull(m.u, truth.1, m.var_u)] {
            raw2 += p * p;
        }
        let s2 = no_lens.chain().invert_exposures(x, y, &m, &exposures).unwrap();
        for p in [pull(s2.q, truth.0, s2.var_q), pull(s2.u, truth.1, s2.var_u)] {
            no_lens2 += p * p;
        }
        n += 1;
    }
    assert!(n >= 100, "{n} bins");
    let rms = (sum2 / (2 * n) as f64).sqrt();
    let rms_raw = (raw2 / (2 * n) as f64).sqrt();
    let rms_no_lens = (no_lens2 / (2 * n) as f64).sqrt();
    eprintln!(
        "{n} bins: RMS pull {rms:.2} (worst {worst:.2}); uncorrected {rms_raw:.1}; without the lens {rms_no_lens:.1}"
    );
    assert!(rms > 0.6 && rms < 1.5, "the corrected bins scatter by {rms} of their errors");
    assert!(worst < 5.0, "a bin {worst} sigma off");
    assert!(rms_raw > 20.0, "the uncorrected bins are already right ({rms_raw}): the test shows nothing");
    assert!(rms_no_lens > 5.0, "a chain without the lens corrects as well ({rms_no_lens}): the test shows nothing");
}
