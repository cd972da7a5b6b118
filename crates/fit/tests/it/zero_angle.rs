//! The HWP chromatic zero angle between the sky-field calibration and the correction
//! (`docs/architecture.md`, "The two frames"): a Stokes map made through a plate whose zero is
//! off by `chi_offset` is in the plate frame (`chi_meas = chi_sky - chi_offset`,
//! `mueller::Hwp`); the calibration pipeline must turn it into the sky frame before the
//! sky-field solution (`eq:instpol`), because the correction (`fit::correction::correct`) assumes a
//! sky-frame instrumental field.
//!
//! The data come from the one forward model (`mueller::DualBeam`: the instrumental field as
//! `Element::PartialPolarizer`, a plate with `Hwp { chi_offset }`), reduced by the one `F_i`
//! (`eq:F`) and the one Stokes solver on 16 optimal HWP angles. The instrument is FORS1 with
//! its V-band zero angle set to 3 deg by editing `instruments/fors1.toml`.

use fit::correction::correct::{CorrectOptions, Corrector, Measurement};
use fit::models::pipeline::{
    calibrate_map, map_to_sky_frame, refit, CalibrateOptions, CalibrationMeta, CalibrationRun,
};
use fit::RadialModel;
use mueller::{optimal_angles, stokes_p_chi, DualBeam, Element, Hwp};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;
use skyfield::maps::BinGeometry;
use skyfield::solve::SkyPolarization;
use skyfield::StokesMap;
use stokes::{normalized_difference, StokesSolver};

const OFFSET_DEG: f64 = 3.0;
/// FORS1 V radial pattern of section `sec:fors1` (percent per arcmin^k, k = 1..3).
const V_COEFFS_PCT: [f64; 3] = [0.012, 0.046, 0.002];
/// Noise per bin and component (fraction).
const SIGMA: f64 = 3e-5;

fn truth() -> RadialModel {
    RadialModel::new(1, V_COEFFS_PCT.iter().map(|c| c / 100.0).collect(), [0.0, 0.0])
}

/// Table `tab:empty`, V: 1.74% at -53.8 deg.
fn sky() -> SkyPolarization {
    SkyPolarization::from_percent_deg(1.74, -53.8).unwrap()
}

/// The FORS1 instrument with the V-band zero angle replaced by `offset_deg` (text edit of the
/// shipped TOML, loaded from a file as a user's variant would be).
fn instrument_with_v_offset(offset_deg: f64) -> (tempfile::TempDir, instrument::Instrument) {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../instruments/fors1.toml");
    let text = std::fs::read_to_string(path).unwrap();
    // FORS1's file gives no zero angles (not measured): the V block gains one.
    let v_block = "lambda_eff_nm = 554.0\n";
    assert_eq!(text.matches(v_block).count(), 1, "fors1.toml's V block changed; update the test");
    assert!(
        !text.lines().any(|l| l.starts_with("hwp_chi_offset_deg")),
        "fors1.toml now gives zero angles; update the test"
    );
    let edited = text.replace(v_block, &format!("lambda_eff_nm = 554.0\nhwp_chi_offset_deg = {offset_deg:.1}\n"));
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("fors1_v_offset.toml");
    std::fs::write(&p, edited).unwrap();
    let inst = instrument::Instrument::load(p.to_str().unwrap()).unwrap();
    (dir, inst)
}

/// The measured, plate-frame `(q1, u1)` of a source `(p0, chi0)` seen through the instrumental
/// `M_I(p, phi)` and a plate of zero angle `chi_offset` (rad).
fn observe(p: f64, phi: f64, p0: f64, chi0: f64, chi_offset: f64) -> (f64, f64) {
    let train = DualBeam {
        pre: vec![Element::PartialPolarizer { p, phi }],
        hwp: Hwp { chi_offset, ..Hwp::ideal() },
        ..Default::default()
    };
    let th = optimal_angles(16);
    let f: Vec<f64> =
        train.fluxes(&stokes_p_chi(1.0, p0, chi0), &th).iter().map(|b| normalized_difference(b.f_o, b.f_e)).collect();
    StokesSolver::new(&th).unwrap().solve(&f)
}

/// A 16 x 16-bin V sky-field map of the FORS1 detector (128 px bins) observed through a plate
/// of zero angle `data_offset_deg`, with Gaussian noise `SIGMA` per component.
fn sky_field_map(inst: &instrument::Instrument, data_offset_deg: f64) -> StokesMap {
    let d = &inst.detector;
    let g = BinGeometry::covering(128, 0, 0, d.nx, d.ny, d.pixel_scale_arcsec);
    let mut map =
        StokesMap::empty(g.clone(), &inst.name, "V", optimal_angles(16).iter().map(|a| a.to_degrees()).collect());
    let (truth, sky) = (truth(), sky());
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(5);
    let noise = Normal::new(0.0, SIGMA).unwrap();
    for j in 0..g.ny {
        for i in 0..g.nx {
            let k = j * g.nx + i;
            let (x, y) = g.centre_arcmin(i, j);
            let (q, u) = truth.qu(x, y);
            let (p, phi) = stokes::polarization(q, u);
            let (q1, u1) = observe(p, phi, sky.p, sky.chi, data_offset_deg.to_radians());
            map.q[k] = q1 + noise.sample(&mut rng);
            map.u[k] = u1 + noise.sample(&mut rng);
            map.sigma_q[k] = SIGMA;
            map.sigma_u[k] = SIGMA;
            map.cov_qu[k] = 0.0;
            map.sigma_q_phot[k] = SIGMA;
            map.sigma_u_phot[k] = SIGMA;
            let (pm, chim) = stokes::polarization(map.q[k], map.u[k]);
            map.p[k] = pm;
            map.chi[k] = chim;
            map.n_pixels[k] = 128 * 128;
            map.intensity[k] = 2.0e4;
            map.intensity_snr[k] = 1.0e4;
            map.valid[k] = true;
        }
    }
    map
}

/// Calibrate as `instpol calibrate` does: the filter's zero angle from the instrument.
fn calibrate(inst: &instrument::Instrument, map: &StokesMap) -> CalibrationRun {
    let f = inst.filter("V").unwrap();
    let meta = CalibrationMeta {
        instrument: inst.name.clone(),
        filter: f.name.clone(),
        lambda_nm: f.lambda_eff_nm,
        hwp_chi_offset_deg: f.chi_offset_deg(),
        pixel: None,
        provenance: fit::files::calfile::Provenance::now("test", vec![]),
    };
    calibrate_map(map, &sky(), meta, &CalibrateOptions::default()).unwrap()
}

/// A 2% star at chi0 = 30 deg at (2.5, -1.5) arcmin (where the V pattern gives p ~ 0.5%),
/// measured through the instrument and the plate, corrected with the calibration and the
/// calibration's own zero angle. Returns the corrected `(P0, chi0 in deg)` and `sigma_chi0` (deg).
fn correct_star(run: &CalibrationRun, data_offset_deg: f64) -> (f64, f64, f64) {
    let (x, y) = (2.5, -1.5);
    let (q, u) = truth().qu(x, y);
    let (p, phi) = stokes::polarization(q, u);
    let (q1, u1) = observe(p, phi, 0.02, 30f64.to_radians(), data_offset_deg.to_radians());
    let cal = &run.calibration;
    let cor = Corrector::new(cal, CorrectOptions::for_calibration(cal));
    let r = cor.correct(&Measurement::at_plate(x, y, q1, u1, 1e-5, 1e-5, 0.0)).unwrap();
    (r.p0, r.chi0.to_degrees(), r.sigma_chi0.to_degrees())
}

#[test]
fn sky_field_calibration_with_hwp_zero_angle_is_radial_and_corrects_a_star() {
    let (_dir, inst) = instrument_with_v_offset(OFFSET_DEG);
    assert_eq!(inst.filter("V").unwrap().hwp_chi_offset_deg, Some(OFFSET_DEG));
    let map = sky_field_map(&inst, OFFSET_DEG);
    let run = calibrate(&inst, &map);
    assert_eq!(run.calibration.hwp_chi_offset_deg, OFFSET_DEG);

    // (a) a radial field: polar-angle slope 1, intercept 0 (section sec:fors1), and the input
    // coefficients back within 3 sigma.
    let pol = &run.polar;
    assert!(
        pol.intercept_deg.abs() < 0.05 && pol.intercept_deg.abs() < 4.0 * pol.intercept_err_deg.max(0.005),
        "polar-angle intercept {:.4} +- {:.4} deg (want 0)",
        pol.intercept_deg,
        pol.intercept_err_deg
    );
    assert!((pol.slope - 1.0).abs() < 0.005, "polar-angle slope {:.5} +- {:.5}", pol.slope, pol.slope_err);
    let m = &run.fit.model;
    for ((c, e), want) in m.coeffs.iter().zip(m.coefficient_errors()).zip(V_COEFFS_PCT) {
        let want = want / 100.0;
        assert!((c - want).abs() < 3.0 * e + 1e-7, "coefficient {c:.6e} +- {e:.1e}, input {want:.6e}");
    }

    // (b) a star through the same instrument comes back at its true angle and degree.
    let (p0, chi0, s_chi) = correct_star(&run, OFFSET_DEG);
    assert!((chi0 - 30.0).abs() < 0.02, "corrected chi0 {chi0:.4} deg +- {s_chi:.4} (true 30)");
    assert!((p0 - 0.02).abs() < 2e-5, "corrected P0 {:.5}% (true 2%)", 100.0 * p0);

    println!(
        "zero angle applied: intercept {:.4} +- {:.4} deg, slope {:.5}, star chi0 {chi0:.4} deg, P0 {:.5}% \
         (true 30 deg, 2%)",
        pol.intercept_deg,
        pol.intercept_err_deg,
        pol.slope,
        100.0 * p0
    );

    // Exactly once: refitting the calibration's (already sky-frame) bins rotates nothing again.
    let again = refit(&run.calibration, &CalibrateOptions::default()).unwrap();
    assert!(
        (again.polar.intercept_deg - pol.intercept_deg).abs() < 1e-9,
        "refit moved the intercept from {} to {} deg",
        pol.intercept_deg,
        again.polar.intercept_deg
    );
    for (a, b) in again.fit.model.coeffs.iter().zip(&m.coeffs) {
        assert!((a - b).abs() < 1e-12 * b.abs().max(1e-6), "refit coefficient {a} vs {b}");
    }
}

#[test]
fn without_the_rotation_the_field_is_not_radial_and_the_star_is_off() {
    // The same data (plate at 3 deg) calibrated with an instrument that claims 0 deg: this is
    // what the pipeline did before it rotated the map, and what the correction then undid
    // nothing of. Both checks of the test above must fail, by far.
    let (_dir, inst3) = instrument_with_v_offset(OFFSET_DEG);
    let map = sky_field_map(&inst3, OFFSET_DEG);
    let (_dir0, inst0) = instrument_with_v_offset(0.0);
    let wrong = calibrate(&inst0, &map);
    let pol = &wrong.polar;
    assert!(
        pol.intercept_deg.abs() > 1.0,
        "with the zero angle ignored the polar-angle intercept is {:.3} +- {:.3} deg: expected it far from 0",
        pol.intercept_deg,
        pol.intercept_err_deg
    );
    let (p0, chi0, _) = correct_star(&wrong, OFFSET_DEG);
    assert!(
        (chi0 - 30.0).abs() > 1.0,
        "with the zero angle ignored the corrected chi0 is {chi0:.3} deg (P0 {:.4}%): expected it off 30 deg by ~{OFFSET_DEG}",
        100.0 * p0
    );
    // The numbers, for the record (shown with --nocapture).
    println!(
        "zero angle ignored: intercept {:.3} +- {:.3} deg, slope {:.4}, star chi0 {chi0:.3} deg, P0 {:.4}% \
         (true 30 deg, 2%)",
        pol.intercept_deg,
        pol.intercept_err_deg,
        pol.slope,
        100.0 * p0
    );
}

#[test]
fn map_rotation_is_a_rotation_of_q_u_and_their_covariance() {
    // R(2 off) preserves p, the trace and the determinant of the covariance, shifts chi by
    // +off, and R(-off) R(+off) is the identity.
    let (_dir, inst) = instrument_with_v_offset(OFFSET_DEG);
    let mut map = sky_field_map(&inst, OFFSET_DEG);
    for k in 0..map.q.len() {
        // Unequal errors and a correlation, to exercise every term of R C R^T.
        map.sigma_u[k] = 2.0 * SIGMA;
        map.cov_qu[k] = 0.3 * SIGMA * 2.0 * SIGMA;
    }
    let off = OFFSET_DEG.to_radians();
    let r = map_to_sky_frame(&map, off);
    let back = map_to_sky_frame(&r, -off);
    for k in 0..map.q.len() {
        let (p, p1) = (map.q[k].hypot(map.u[k]), r.q[k].hypot(r.u[k]));
        assert!((p - p1).abs() < 1e-15, "bin {k}: p {p} -> {p1}");
        let (_, chi) = stokes::polarization(map.q[k], map.u[k]);
        let (_, chi1) = stokes::polarization(r.q[k], r.u[k]);
        let d = fit::models::polar::wrap_half_turn_deg((chi1 - chi).to_degrees());
        assert!((d - OFFSET_DEG).abs() < 1e-9, "bin {k}: chi moved by {d} deg");
        assert!(
            (fit::models::polar::wrap_half_turn_deg((r.chi[k] - map.chi[k]).to_degrees()) - OFFSET_DEG).abs() < 1e-9
        );
        let tr = |m: &StokesMap| m.sigma_q[k].powi(2) + m.sigma_u[k].powi(2);
        let det = |m: &StokesMap| m.sigma_q[k].powi(2) * m.sigma_u[k].powi(2) - m.cov_qu[k].powi(2);
        assert!((tr(&r) - tr(&map)).abs() < 1e-12 * tr(&map));
        assert!((det(&r) - det(&map)).abs() < 1e-9 * det(&map));
        assert!(r.cov_qu[k] != map.cov_qu[k], "bin {k}: the covariance did not turn");
        for (a, b) in [
            (back.q[k], map.q[k]),
            (back.u[k], map.u[k]),
            (back.sigma_q[k], map.sigma_q[k]),
            (back.sigma_u[k], map.sigma_u[k]),
            (back.cov_qu[k], map.cov_qu[k]),
        ] {
            assert!((a - b).abs() < 1e-12 * b.abs().max(1e-12), "bin {k}: {a} != {b} after turning back");
        }
    }
    // A zero offset changes nothing, bit for bit.
    assert_eq!(map_to_sky_frame(&map, 0.0), map);
}

/// A zero angle is a filter's: its inputs' filters are compared as the instrument names them
/// (FORS1's `V_BESS` is its `V`), and two filters are refused naming both and where each is
/// named.
#[test]
fn one_filter_compares_as_the_instrument_names_filters() {
    use fit::zeroangle::{one_filter, FilterError};
    let fors1 = instrument::Instrument::load("fors1").unwrap();
    let named = |v: &[(&str, &str)]| v.iter().map(|(f, w)| (f.to_string(), w.to_string())).collect::<Vec<_>>();
    let alias = named(&[("V", "the frames"), ("v_bess", "--measured a.csv")]);
    assert_eq!(one_filter(&alias, Some(&fors1)), Ok("V".to_string()));
    // Without the instrument an alias is not known: two names.
    assert!(matches!(one_filter(&alias, None), Err(FilterError::Differ { .. })));
    let two = named(&[("V", "the frames"), ("I", "--measured b.csv")]);
    let e = one_filter(&two, Some(&fors1)).unwrap_err();
    let words = e.to_string();
    assert!(words.contains("--measured b.csv") && words.contains("'I'") && words.contains("'V'"), "{words}");
    assert_eq!(one_filter(&[], None), Err(FilterError::None));
}
