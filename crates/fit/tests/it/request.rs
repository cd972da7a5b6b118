//! `fit::correction::request`: the one rule set of correcting rows with any calibration file. The field
//! path is checked against an inversion written here (nalgebra's inverse of `M_I`,
//! `eq:instpol`, after a rotation of the rows' `(q, u)` by the zero angle they lack); the
//! refusals and notes against the situations that call for them; the telescope path against the
//! chain called with the track and rotator angle each row should get.

use fit::correction::correct::{CorrectOptions, Corrector, Measurement, Method};
use fit::correction::request::{plan_rows, Note, PerRowAngles, Refusal, Request};
use fit::files::calibration::{CalibrationFile, Kind};
use fit::models::model::FieldModel;
use fit::telescope::{fit_band, FitOptions, ModelKind, Observation, TelescopeFit, Track};
use mueller::mirror::MetalTable;
use std::path::PathBuf;

/// The paper-like V field as a radial calibration of EFOSC2 with an HWP zero angle `z` (deg).
fn field(z: f64) -> fit::Calibration {
    crate::common::given::given_calibration(
        "EFOSC2",
        "V",
        550.0,
        z,
        fit::Model::Radial(fit::RadialModel {
            first_power: 0,
            coeffs: vec![2e-4, 1e-3, 3e-4],
            centre: [0.0, 0.0],
            centre_free: false,
            cov: vec![0.0; 25],
            scaling: None,
        }),
        2.0,
    )
}

/// A Nasmyth M3 model of one band (V) fitted to noise-free standards over the meridian.
fn telescope(with_rotator: bool) -> TelescopeFit {
    let table = MetalTable::builtin("aluminium").unwrap();
    let obs: Vec<_> = (0..12)
        .map(|k| {
            let pa = (-160.0 + 29.0 * k as f64).to_radians();
            let a = 2.0 * (0.6 - pa);
            Observation {
                star: format!("S{k}"),
                parallactic: pa,
                qu: mueller::Qu::from_sigmas(0.035 * a.cos(), -0.035 * a.sin(), 2e-4, 2e-4, 0.0),
                wavelength_um: 0.55,
                band: "V".into(),
                rotator: 0.0,
                sky: (0.0, 0.0),
                source: format!("t:{k}"),
            }
        })
        .collect();
    let mut f = fit_band(ModelKind::Wiersema, &obs, &table, &FitOptions::default()).unwrap();
    f.with_rotator = with_rotator;
    f
}

fn file(field: Option<fit::Calibration>, telescope: Option<TelescopeFit>) -> CalibrationFile {
    CalibrationFile {
        path: PathBuf::from("cal.fits"),
        instrument: "EFOSC2".into(),
        field,
        telescope,
        mueller: None,
        response: None,
        elements: vec![],
        product: None,
    }
}

fn request<'a>() -> Request<'a> {
    Request::new(Method::Exact, false, 0.5)
}

/// Rows carrying part of the zero angle: only the rest is turned, then `M_I` is inverted. The
/// reference: the row's (q, u) rotated by hand by `2 (z - carried)`, then `M_I(p, phi)^-1` by
/// nalgebra on the Stokes vector, renormalized.
#[test]
fn field_rows_turned_by_the_zero_angle_they_lack_then_inverted() {
    let (z, carried) = (2.9, 1.2);
    let f = file(Some(field(z)), None);
    let n = 3;
    let rows = [(0.5, -0.3, 0.012, -0.004), (-1.1, 0.7, -0.002, 0.009), (1.5, 1.5, 0.0, 0.0)];
    let frame = mueller::Frame::Sky { zero_angle_deg: carried };
    let req = Request { frame, ..request() };
    let plan = plan_rows(&f, &req, n).unwrap();
    assert_eq!(plan.kind, Kind::Field);
    assert!((plan.to_sky_deg - (z - carried)).abs() < 1e-15);
    assert_eq!(plan.notes, vec![Note::CarriedZeroAngle { carried, calibration: z, applied: z - carried }]);
    let cal = field(z);
    for (i, &(x, y, q, u)) in rows.iter().enumerate() {
        let r =
            plan.correct(i, &Measurement::at(x, y, mueller::Qu::from_sigmas(q, u, 1e-4, 1e-4, 0.0), frame)).unwrap();
        let d = 2.0 * (z - carried).to_radians();
        let (q1, u1) = (d.cos() * q - d.sin() * u, d.sin() * q + d.cos() * u);
        let (p, phi) = cal.eval(x, y).p_chi();
        let s0 = mueller::partial_polarizer(p, phi).try_inverse().unwrap() * mueller::stokes_qu(1.0, q1, u1);
        assert!((r.q0 - s0[1] / s0[0]).abs() < 1e-12 && (r.u0 - s0[2] / s0[0]).abs() < 1e-12, "row {i}");
    }
    // Without a carried angle the whole zero angle is turned and nothing is noted.
    let plan = plan_rows(&f, &request(), n).unwrap();
    assert_eq!((plan.to_sky_deg, plan.notes.len()), (z, 0));
}

/// What a file without a telescope model refuses (arguments that would change nothing) and
/// notes (angles that are only data).
#[test]
fn field_only_refusals_and_notes() {
    let f = file(Some(field(0.0)), None);
    let pa = [10.0, 20.0];
    let rows = PerRowAngles { start_deg: &pa, end_deg: None, rotator_deg: None };
    for req in [
        Request { band: Some("V"), ..request() },
        Request { parang: Some(Track::at(0.1)), ..request() },
        Request { rotator: Some(0.1), ..request() },
        Request { per_row: Some(rows), angles_are_arguments: true, ..request() },
    ] {
        assert_eq!(plan_rows(&f, &req, 2).err(), Some(Refusal::TelescopeOptions { mueller: false }));
    }
    let plan = plan_rows(&f, &Request { per_row: Some(rows), ..request() }, 2).unwrap();
    assert_eq!(plan.notes, vec![Note::AnglesWithoutTelescope]);
    // A file built by hand with no model is refused, not a panic.
    assert_eq!(plan_rows(&file(None, None), &request(), 2).err(), Some(Refusal::NoModel));
}

/// The telescope's tracks: each row's own with its rotator angle (never an assumed 0 for a
/// model fitted with rotator angles), one track for all, and the refusals when neither or both
/// are given. Each row is corrected as the chain corrects it over the track it should get.
#[test]
fn telescope_rows_get_their_own_track_and_rotator() {
    let (cal, tel) = (field(0.0), telescope(true));
    let f = file(Some(cal.clone()), Some(tel.clone()));
    let pa = [-30.0, 5.0, 40.0];
    let rot = [10.0, -20.0, 0.0];
    let rows = PerRowAngles { start_deg: &pa, end_deg: None, rotator_deg: None };
    assert_eq!(
        plan_rows(&f, &Request { per_row: Some(rows), ..request() }, 3).err(),
        Some(Refusal::NoRotator { per_row: true })
    );
    assert_eq!(plan_rows(&f, &request(), 3).err(), Some(Refusal::NoParallactic));
    assert_eq!(
        plan_rows(
            &f,
            &Request { per_row: Some(rows), parang: Some(Track::at(0.0)), rotator: Some(0.0), ..request() },
            3
        )
        .err(),
        Some(Refusal::TwoTracks)
    );
    assert!(matches!(
        plan_rows(&f, &Request { per_row: Some(rows), ..request() }, 2).err(),
        Some(Refusal::Length { rows: 2, len: 3, .. })
    ));
    let with_rot = PerRowAngles { rotator_deg: Some(&rot), ..rows };
    let plan = plan_rows(&f, &Request { per_row: Some(with_rot), ..request() }, 3).unwrap();
    assert_eq!(plan.kind, Kind::FieldAndTelescope);
    let cor = Corrector::new(&cal, CorrectOptions { zero_angle_deg: 0.0, ..CorrectOptions::default() });
    let mut seen = vec![];
    for i in 0..3 {
        let m = Measurement::at_plate(0.4, -0.2, 0.02, 0.01, 1e-4, 1e-4, 0.0);
        let got = plan.correct(i, &m).unwrap();
        let track = Track::at(pa[i].to_radians()).with_rotator(rot[i].to_radians());
        let want = fit::telescope::cal::correct_chain(Some(&cor), &tel, "V", &m, track, Some(0.0)).unwrap();
        assert_eq!(got, want.with_telescope_in_inst(), "row {i}");
        seen.push(got.q0);
    }
    // The rows saw different tracks, so the same measurement comes out differently.
    assert!((seen[0] - seen[2]).abs() > 1e-4, "{seen:?}");
    // One rotator angle for every row stands in for the column.
    let plan = plan_rows(&f, &Request { per_row: Some(rows), rotator: Some(0.3), ..request() }, 3).unwrap();
    let m = Measurement::at_plate(0.4, -0.2, 0.02, 0.01, 1e-4, 1e-4, 0.0);
    let want = fit::telescope::cal::correct_chain(
        Some(&cor),
        &tel,
        "V",
        &m,
        Track::at(pa[1].to_radians()).with_rotator(0.3),
        Some(0.0),
    );
    assert_eq!(plan.correct(1, &m).unwrap(), want.unwrap().with_telescope_in_inst());
    // Arguments may not give per-row angles and a recorded track both.
    let rec =
        skyfield::RecordedAngles { parallactic_rad: Some((0.1, 0.2)), rotator_rad: Some(0.0), exposure_tracks: vec![] };
    let req = Request { per_row: Some(with_rot), recorded: Some(&rec), angles_are_arguments: true, ..request() };
    assert_eq!(plan_rows(&f, &req, 3).err(), Some(Refusal::TwoTracks));
    // A model fitted without rotator angles takes none, and a given one is noted as unused.
    let f0 = file(None, Some(telescope(false)));
    let plan = plan_rows(&f0, &Request { parang: Some(Track::at(0.2)), rotator: Some(0.5), ..request() }, 1).unwrap();
    assert_eq!((plan.kind, plan.notes.clone()), (Kind::Telescope, vec![Note::RotatorIgnored]));
}

/// Four exposures of 22.5 deg plate steps recorded over a parallactic track from -0.6 to 0.4
/// rad, as a catalog records them, and the same exposures as the chain's forward model takes
/// them (HWP angle in rad, each over its own track).
fn recorded_exposures() -> (skyfield::RecordedAngles, Vec<mueller::telescope::Exposure>) {
    let rec = skyfield::RecordedAngles {
        parallactic_rad: Some((-0.6, 0.4)),
        rotator_rad: Some(0.0),
        exposure_tracks: (0..4)
            .map(|k| skyfield::ExposureTrack {
                hwp_deg: 22.5 * k as f64,
                start: -0.6 + 0.25 * k as f64,
                end: -0.6 + 0.25 * (k + 1) as f64,
            })
            .collect(),
    };
    let exposures = rec
        .exposure_tracks
        .iter()
        .map(|e| mueller::telescope::Exposure { hwp: e.hwp_deg.to_radians(), track: Track::new(e.start, Some(e.end)) })
        .collect();
    (rec, exposures)
}

/// The plan's chain as a forward model ([`fit::correction::chain::Chain::instrument`], the
/// `field::InstrumentChain` the simulator renders through and that is checked against a Jones
/// calculation in `crates/sim/tests/it/chain_end_to_end.rs`) and the plan's correction are each
/// other's inverse, for every kind of calibration file and every way the rows saw the
/// telescope: one track, their own tracks, the recorded exposures each over its own track.
#[test]
fn the_correction_inverts_the_chain_it_holds() {
    let z = 2.9;
    let (rec, exposures) = recorded_exposures();
    let pa = [10.0, -35.0, 70.0];
    let rows = PerRowAngles { start_deg: &pa, end_deg: None, rotator_deg: None };
    let sky = mueller::Qu::new(0.021, -0.013, 0.0, 0.0, 0.0);
    let (x, y) = (1.3, -0.7);
    let (mut worst_exact, mut worst_exposures) = (0.0f64, 0.0f64);
    for (f, kind) in [
        (file(Some(field(z)), None), Kind::Field),
        (file(None, Some(telescope(false))), Kind::Telescope),
        (file(Some(field(z)), Some(telescope(false))), Kind::FieldAndTelescope),
    ] {
        let mut requests = vec![(request(), false)];
        if f.telescope.is_some() {
            requests = vec![
                (Request { parang: Some(Track::new(-0.3, Some(0.1))), ..request() }, false),
                (Request { per_row: Some(rows), ..request() }, false),
                (Request { recorded: Some(&rec), ..request() }, true),
            ];
        }
        for (req, by_exposure) in requests {
            let plan = plan_rows(&f, &req, 3).unwrap();
            assert_eq!(plan.kind, kind);
            for i in 0..3 {
                let (chain, track) = plan.chain.instrument(i);
                let measured = if by_exposure {
                    chain.forward_exposures(x, y, &sky, &exposures).unwrap()
                } else {
                    chain.forward(x, y, &sky, track).unwrap()
                };
                let got = plan.correct(i, &Measurement::at(x, y, measured, mueller::Frame::Plate)).unwrap();
                let d = (got.q0 - sky.q).abs().max((got.u0 - sky.u).abs());
                if by_exposure && kind == Kind::FieldAndTelescope {
                    worst_exposures = worst_exposures.max(d);
                } else {
                    worst_exact = worst_exact.max(d);
                }
            }
        }
    }
    assert!(worst_exact < 1e-12, "the correction misses its own chain by {worst_exact:e}");
    // A demodulated set whose exposures each saw another telescope matrix behind the field:
    // undoing the field and then the telescope would be 1.4e-5 off here; the chain is inverted
    // whole.
    assert!(worst_exposures < 1e-12, "exposure by exposure: {worst_exposures:e}");
}

/// Rows in another sky frame than the calibration's: a catalog made with an instrument file of
/// zero angle 1.2 deg, corrected with a field calibration of 2.9 deg. The light the plan's own
/// forward model puts at the plate, written into the rows' frame by a rotation by hand
/// (`chi + 1.2 deg`), comes back to the sky through the field alone and through the field and
/// the telescope over one track and over the recorded exposures, as the same light given at
/// the plate does. Each measurement says its frame (`mueller::Frame`), so the exact inversion
/// over the exposures takes it back to the plate from there (it had turned such rows by
/// `2.9 - 2 x 1.2` deg instead of `-1.2`, and demodulated them through a plate of 1.2 deg).
#[test]
fn rows_in_another_sky_frame_come_back_to_the_sky() {
    let (z, carried) = (2.9, 1.2);
    let (rec, exposures) = recorded_exposures();
    let sky = mueller::Qu::new(0.021, -0.013, 1e-8, 1e-8, 0.0);
    let (x, y) = (1.3, -0.7);
    let frame = mueller::Frame::Sky { zero_angle_deg: carried };
    let (s2, c2) = (2.0 * carried.to_radians()).sin_cos();
    let mut worst = 0.0f64;
    for (f, req) in [
        (file(Some(field(z)), None), request()),
        (
            file(Some(field(z)), Some(telescope(false))),
            Request { parang: Some(Track::new(-0.3, Some(0.1))), ..request() },
        ),
        (file(Some(field(z)), Some(telescope(false))), Request { recorded: Some(&rec), ..request() }),
    ] {
        let by_exposure = req.recorded.is_some();
        let plan = plan_rows(&f, &Request { frame, ..req }, 1).unwrap();
        let at_plate_plan = plan_rows(&f, &req, 1).unwrap();
        assert_eq!(plan.plate_deg, z, "the exposures were taken through the calibration's plate");
        let (chain, track) = plan.chain.instrument(0);
        let plate = if by_exposure {
            chain.forward_exposures(x, y, &sky, &exposures).unwrap()
        } else {
            chain.forward(x, y, &sky, track).unwrap()
        };
        // The same light in the sky frame of the rows' zero angle, by hand.
        let (q, u) = (c2 * plate.q - s2 * plate.u, s2 * plate.q + c2 * plate.u);
        let row = mueller::Qu::new(q, u, 1e-8, 1e-8, 0.0);
        let got = plan.correct(0, &Measurement::at(x, y, row, frame)).unwrap();
        let plate = mueller::Qu::new(plate.q, plate.u, 1e-8, 1e-8, 0.0);
        let from_plate = at_plate_plan.correct(0, &Measurement::at(x, y, plate, mueller::Frame::Plate)).unwrap();
        for (a, b) in [(got.q0, sky.q), (got.u0, sky.u), (from_plate.q0, sky.q), (from_plate.u0, sky.u)] {
            worst = worst.max((a - b).abs());
        }
        assert!(
            (got.var_q0 / from_plate.var_q0 - 1.0).abs() < 1e-8 && (got.var_u0 / from_plate.var_u0 - 1.0).abs() < 1e-8,
            "{got:?}\n{from_plate:?}"
        );
    }
    assert!(worst < 1e-12, "rows in another frame miss the sky by {worst:e}");
}

#[test]
fn p_at_the_field_edge_is_the_mean_over_the_four_sides() {
    // P(r) = 2e-4 + 1e-3 r + 3e-4 r^2 over x in [-1, 3], y in [-2, 2] (arcmin): the sides'
    // midpoints lie at r = 1, 3 and sqrt(5) twice.
    let mut cal = field(0.0);
    cal.region = fit::FieldRegion { x_min: -1.0, x_max: 3.0, y_min: -2.0, y_max: 2.0 };
    if let fit::Model::Radial(r) = &mut cal.model {
        r.cov[0] = 1e-8; // sigma(c0) = 1e-4: every P moves with c0, so each side's error is 1e-4
    }
    let p = |r: f64| 2e-4 + 1e-3 * r + 3e-4 * r * r;
    let expected = (p(1.0) + p(3.0) + 2.0 * p(5f64.sqrt())) / 4.0;
    let (v, s) = cal.p_at_edge().unwrap();
    assert!((v - expected).abs() < 1e-15, "{v} vs {expected}");
    assert!((s - 1e-4).abs() < 1e-15, "{s}");
}

/// `(q, u)` turned by `deg` (added to chi), by hand.
fn turned(q: f64, u: f64, deg: f64) -> (f64, f64) {
    let (s, c) = (2.0 * deg.to_radians()).sin_cos();
    (c * q - s * u, s * q + c * u)
}

/// Rows in the celestial frame (a catalog of an instrument on a rotator, turned by its position
/// angle on the sky). A field model alone acts in the instrument's frame, which saw the sky
/// turned by minus that angle: the rows are made here by hand (the sky turned by -PA,
/// `M_I(p, phi)` by `mueller::partial_polarizer`, then turned by the zero angle the rows carry
/// less the calibration's and by +PA), and the correction gives the sky's `(q, u)` back, north
/// through east, to 1e-12. Behind a telescope model the chain's inverse ends on the sky already
/// (its offset and rotator turn the sky into the instrument): the rows are the chain's forward
/// model of the sky turned by +PA, and their correction is the correction of the same light
/// given in the instrument's frame (the sky itself with a field model, 1e-12; a telescope model
/// alone also subtracts a constant the forward model leaves out).
#[test]
fn celestial_rows_are_corrected_in_the_instruments_frame_and_come_back_to_the_sky() {
    let (z, carried, pa) = (2.9, 1.2, -142.0);
    let sky = mueller::Qu::new(0.021, -0.013, 1e-8, 1e-8, 0.0);
    let (x, y) = (1.3, -0.7);
    let frame = mueller::Frame::Celestial { zero_angle_deg: carried, position_angle_deg: pa };
    let seen = turned(sky.q, sky.u, -pa);
    // A field model alone, by hand.
    let cal = field(z);
    let (p, phi) = cal.eval(x, y).p_chi();
    let s1 = mueller::partial_polarizer(p, phi) * mueller::stokes_qu(1.0, seen.0, seen.1);
    let (q, u) = turned(s1[1] / s1[0], s1[2] / s1[0], carried - z + pa);
    let alone = file(Some(field(z)), None);
    let plan = plan_rows(&alone, &Request { frame, ..request() }, 1).unwrap();
    assert!((plan.to_sky_deg - (z - carried)).abs() < 1e-15, "only the zero angle is reported as the turn");
    let got = plan.correct(0, &Measurement::at(x, y, mueller::Qu::new(q, u, 1e-8, 1e-8, 0.0), frame)).unwrap();
    assert!((got.q0 - sky.q).abs() < 1e-12 && (got.u0 - sky.u).abs() < 1e-12, "field alone: {got:?}");
    let chi = 0.5 * sky.u.atan2(sky.q);
    assert!(mueller::wrap_half_pi(got.chi0 - chi).abs() < 1e-10, "chi0 {} vs {chi}", got.chi0);

    let (rec, exposures) = recorded_exposures();
    let mut worst = 0.0f64;
    for (f, req) in [
        (
            file(Some(field(z)), Some(telescope(false))),
            Request { parang: Some(Track::new(-0.3, Some(0.1))), ..request() },
        ),
        (file(Some(field(z)), Some(telescope(false))), Request { recorded: Some(&rec), ..request() }),
        (file(None, Some(telescope(false))), Request { parang: Some(Track::new(-0.3, Some(0.1))), ..request() }),
    ] {
        let by_exposure = req.recorded.is_some();
        let plan = plan_rows(&f, &Request { frame, ..req }, 1).unwrap();
        let (chain, track) = plan.chain.instrument(0);
        let plate = if by_exposure {
            chain.forward_exposures(x, y, &sky, &exposures).unwrap()
        } else {
            chain.forward(x, y, &sky, track).unwrap()
        };
        // In the frame the instrument saw (a telescope model alone takes the rows as they are),
        // then onto the sky by +PA.
        let carried_here = if f.field.is_some() { carried } else { 0.0 };
        let inst_frame = mueller::Frame::Sky { zero_angle_deg: carried_here };
        let (qi, ui) = turned(plate.q, plate.u, carried_here);
        let (q, u) = turned(qi, ui, pa);
        let got = plan.correct(0, &Measurement::at(x, y, mueller::Qu::new(q, u, 1e-8, 1e-8, 0.0), frame)).unwrap();
        let plan_i = plan_rows(&f, &Request { frame: inst_frame, ..req }, 1).unwrap();
        let inst =
            plan_i.correct(0, &Measurement::at(x, y, mueller::Qu::new(qi, ui, 1e-8, 1e-8, 0.0), inst_frame)).unwrap();
        let mut pairs = vec![(got.q0, inst.q0), (got.u0, inst.u0)];
        if f.field.is_some() {
            pairs.extend([(got.q0, sky.q), (got.u0, sky.u)]);
        }
        for (a, b) in pairs {
            worst = worst.max((a - b).abs());
        }
        let (v_sky, v_inst) = (got.var_q0 + got.var_u0, inst.var_q0 + inst.var_u0);
        assert!((v_sky / v_inst - 1.0).abs() < 1e-9, "{got:?}\n{inst:?}");
    }
    assert!(worst < 1e-12, "celestial rows miss the sky by {worst:e}");
}

/// A telescope model alone is of its file's instrument: rows of another instrument are refused
/// naming both (it checked the band only), corrected with a note under `allow_mismatch`, and
/// rows of its own instrument (or that say none) go through.
#[test]
fn a_telescope_model_alone_is_checked_against_the_data_instrument() {
    let f = file(None, Some(telescope(false)));
    let setup = |inst: &str| fit::correction::setup::Setup::named(inst, "V");
    let other = setup("FORS2");
    let req = Request { data: Some(&other), parang: Some(Track::at(0.2)), ..request() };
    match plan_rows(&f, &req, 1).err() {
        Some(Refusal::Mismatch { mismatch: fit::correction::setup::Mismatch::Setup { data, calibration }, .. }) => {
            assert_eq!(data.0, "FORS2");
            assert_eq!(calibration.0, "EFOSC2");
        }
        e => panic!("{e:?}"),
    }
    let plan = plan_rows(&f, &Request { allow_mismatch: true, ..req }, 1).unwrap();
    assert!(plan.notes.iter().any(|n| matches!(n, Note::MismatchAllowed(_))), "{:?}", plan.notes);
    for inst in ["EFOSC2", "efosc2 ", "unknown"] {
        let own = setup(inst);
        let req = Request { data: Some(&own), parang: Some(Track::at(0.2)), ..request() };
        assert!(plan_rows(&f, &req, 1).is_ok(), "{inst}");
    }
}

/// Rows whose frame nobody stated are refused for a calibration of an instrument on a rotator
/// (MOPTOP's `[polarimetry.sky_angle]`), not taken in the instrument's frame; stated (on the
/// sky, or by a table), or of an instrument without a rotator, they go through.
#[test]
fn rows_of_a_rotator_instrument_must_state_their_frame() {
    let moptop = CalibrationFile { instrument: "MOPTOP".into(), ..file(Some(field(0.0)), None) };
    let unstated = Request { frame_unstated: true, ..request() };
    assert_eq!(plan_rows(&moptop, &unstated, 1).err(), Some(Refusal::FrameUnstated { instrument: "MOPTOP".into() }));
    let celestial = mueller::Frame::Celestial { zero_angle_deg: 0.0, position_angle_deg: 0.0 };
    assert!(plan_rows(&moptop, &Request { frame: celestial, ..unstated }, 1).is_ok());
    assert!(plan_rows(&moptop, &request(), 1).is_ok(), "a table states its frame");
    assert!(plan_rows(&file(Some(field(0.0)), None), &unstated, 1).is_ok(), "EFOSC2 has no rotator");
}

/// A Mueller field beside a telescope model, in one file, corrected together: rows each over
/// their own track come back to the sky through the product, formed here, of the telescope's
/// matrix over the row's track (`mueller::telescope`, divided by its `M_00`), the Mueller
/// field's block at the row's position and the zero angle's turn, in the order light meets
/// them. The file is written with the telescope HDU beside the field and read back by the one
/// loader.
/// A Mueller field fitted to three skies seen through a diattenuation and a retardance
/// varying over a 3.6' field, as a calibration of EFOSC2 in V with an HWP zero angle of 3 deg.
fn mueller_cal() -> fit::mueller_field::cal::MuellerCal {
    use fit::mueller_field::{fit_mueller_field, MuellerFitOptions};
    let truth = |x: f64, y: f64| {
        mueller::linear::physical_block(0.002 + 3e-4 * x, -0.001 + 2e-4 * y, [0.01, -0.006 + 0.003 * x], 0.0, 0.0)
    };
    let grid: Vec<(f64, f64)> = (0..49).map(|i| ((i % 7) as f64 * 0.6 - 1.8, (i / 7) as f64 * 0.6 - 1.8)).collect();
    let meas = crate::common::mueller_fields::through(truth);
    let mut rng = <rand_xoshiro::Xoshiro256PlusPlus as rand::SeedableRng>::seed_from_u64(4);
    let fields: Vec<_> = crate::common::mueller_fields::SKIES
        .iter()
        .enumerate()
        .map(|(k, &(p, chi))| {
            crate::common::mueller_fields::cal_field(&format!("s{k}"), p, chi, &grid, &meas, 1e-4, &mut rng)
        })
        .collect();
    let mf =
        fit_mueller_field(&fields, &MuellerFitOptions { deg: 1, scale_arcmin: 1.8, ..Default::default() }).unwrap();
    fit::mueller_field::cal::MuellerCal {
        instrument: "EFOSC2".into(),
        filter: "V".into(),
        field: mf,
        coords: None,
        skies: vec![],
        per_bin: vec![],
        provenance: fit::files::calfile::Provenance::now("test", vec![]),
        hwp_chi_offset_deg: 3.0,
    }
}

#[test]
fn a_mueller_field_beside_a_telescope_is_corrected_with_it() {
    let mc = mueller_cal();
    let (mf, z) = (mc.field.clone(), mc.hwp_chi_offset_deg);
    let tel = telescope(false);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mueller_tel.fits");
    mc.save_with(&path, |f, p| fit::telescope::cal::write_hdu(f, p, &tel, "aluminium")).unwrap();
    let f = fit::files::calibration::load(&path).unwrap();
    assert!(f.mueller.is_some() && f.telescope.is_some(), "{:?}", f.kind());
    let pa = [-50.0, 10.0, 70.0];
    let rows = PerRowAngles { start_deg: &pa, end_deg: None, rotator_deg: None };
    let plan = plan_rows(&f, &Request { per_row: Some(rows), ..request() }, 3).unwrap();
    assert_eq!(plan.kind, Kind::Mueller);
    let sky = mueller::Stokes::new(1.0, 0.015, -0.02, 0.0);
    let band = tel.band("V").unwrap();
    let mut seen = vec![];
    for (i, &(x, y)) in [(0.4, -0.2), (-1.1, 1.3), (1.5, 0.9)].iter().enumerate() {
        let t = band.matrix_track(Track::at(pa[i].to_radians())).unwrap();
        let t = t / t[(0, 0)];
        let v = mf.block_at(x, y).to_mueller() * t * sky;
        let (q, u) = turned(v[1] / v[0], v[2] / v[0], -z);
        let m = Measurement::at_plate(x, y, q, u, 1e-4, 1e-4, 0.0);
        let got = plan.correct(i, &m).unwrap();
        assert!((got.q0 - sky[1]).abs() < 1e-10 && (got.u0 - sky[2]).abs() < 1e-10, "row {i}: {got:?}");
        seen.push(q);
    }
    // The rows saw different tracks: the telescope is not left out.
    assert!((seen[0] - seen[2]).abs() > 1e-4, "{seen:?}");
}

/// A Mueller field then a stressed lens in one file: rows come back to the sky through the
/// product, formed here, of the field's block, the lens's retarder (`mueller::retarder` of its
/// retardance and axis at the row, `mueller::causes::stressed_lens`) and the zero angle's turn;
/// the field alone does not give them back.
#[test]
fn a_mueller_field_then_a_lens_in_one_file_are_corrected_together() {
    use fit::files::elements::Element;
    let mc = mueller_cal();
    let lens = field::StressedLens {
        retardance_edge: 60f64.to_radians(),
        radius_arcmin: 1.8,
        centre_arcmin: [0.2, 0.1],
        axis_offset: 0.0,
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mueller_lens.fits");
    mc.save_with_elements(&path, &[Element::Model, Element::StressedLens(lens)], |_, _| Ok(())).unwrap();
    let f = fit::files::calibration::load(&path).unwrap();
    assert_eq!(f.elements, vec![Element::Model, Element::StressedLens(lens)]);
    let plan = plan_rows(&f, &request(), 1).unwrap();
    let alone = file(None, None);
    let alone = CalibrationFile { mueller: Some(mc.clone()), ..alone };
    let plan_alone = plan_rows(&alone, &request(), 1).unwrap();
    let sky = mueller::Stokes::new(1.0, 0.015, -0.02, 0.0);
    let mut missed = 0.0f64;
    for (x, y) in [(0.4, -0.2), (-1.1, 1.3), (1.5, 0.9)] {
        let (delta, axis) = mueller::causes::stressed_lens(x, y, lens.retardance_edge, 1.8, [0.2, 0.1], 0.0);
        let v = mueller::retarder(delta, axis) * mc.field.block_at(x, y).to_mueller() * sky;
        let (q, u) = turned(v[1] / v[0], v[2] / v[0], -mc.hwp_chi_offset_deg);
        let m = Measurement::at_plate(x, y, q, u, 1e-4, 1e-4, 0.0);
        let got = plan.correct(0, &m).unwrap();
        assert!((got.q0 - sky[1]).abs() < 1e-10 && (got.u0 - sky[2]).abs() < 1e-10, "({x}, {y}): {got:?}");
        let a = plan_alone.correct(0, &m).unwrap();
        missed = missed.max((a.q0 - sky[1]).abs().max((a.u0 - sky[2]).abs()));
    }
    assert!(missed > 1e-4, "the field alone corrects as well ({missed:e}): the lens is not shown");
}
