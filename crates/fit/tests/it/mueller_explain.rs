//! Which cause explains a Mueller field: fields simulated from a cause with known parameters
//! and noise, fitted by calibrate-mueller's library call (`fit_mueller_field`), are explained
//! by that cause with its parameters recovered within errors; a diattenuation-only field is not
//! claimed by a retardance cause; a polarizing half-wave plate's effect after the demodulation
//! follows the closed form derived in `stokes::equivalent`, checked against a frame-level
//! calculation with the simulator's own plate matrix at each angle.

use fit::mueller_field::explain::{explain, Cause, Context, Target};
use fit::mueller_field::{fit_mueller_field, CalField, Kind, MuellerFitOptions};
use mueller::linear::{physical_block, retardance_vector, LinearBlock};
use rand::SeedableRng;
use rand_xoshiro::Xoshiro256PlusPlus;
use std::f64::consts::PI;

use crate::common;
use common::mueller_fields::{diat, diat_and_lens, fors1_grid, sky_fields, LENS_CENTRE_ARCMIN, SIGMA};

/// 30 x 22 bins over the FORS1 field.
fn grid() -> Vec<(f64, f64)> {
    fors1_grid(30, 22)
}

/// The three sky fields of `common::mueller_fields::SKIES` whose measured `(q, u)` are what
/// `meas(x, y, q_sky, u_sky)` gives.
fn fields(meas: &dyn Fn(f64, f64, f64, f64) -> (f64, f64), seed: u64) -> Vec<CalField> {
    sky_fields(3, &grid(), meas, seed)
}

fn full_turn() -> Vec<f64> {
    (0..16).map(|k| k as f64 * PI / 8.0).collect()
}

fn opts(kind: Kind) -> MuellerFitOptions {
    MuellerFitOptions { kind, deg: 4, scale_arcmin: 3.4, ..Default::default() }
}

fn pick(e: &fit::mueller_field::explain::Explanation, c: Cause) -> &fit::mueller_field::explain::CauseFit {
    e.fits.iter().find(|f| f.cause == c).unwrap()
}

/// A stressed lens (18 deg at 3.4', centre off axis: about 0.3 % on the B sky) on top of the
/// paper's diattenuation: explain picks the stressed lens, over every other candidate by more
/// than the BIC threshold, and recovers its parameters within 3 sigma.
#[test]
fn stressed_lens_field_is_explained_by_a_stressed_lens() {
    let (a, c, off) = (18.0f64, [0.8, -0.4], 10.0f64);
    let truth = move |x: f64, y: f64| -> LinearBlock { diat_and_lens(x, y, a, c, off) };
    let f = fields(&common::mueller_fields::through(truth), 11);
    let mf = fit_mueller_field(&f, &opts(Kind::diattenuation_retardance())).unwrap();
    let target = Target::smooth(&mf, 16, "test").unwrap();
    let ctx = Context::new(&full_turn(), 90.0, 3.4).unwrap();
    let e = explain(&target, &ctx, &Cause::ALL).unwrap();
    for f in &e.fits {
        eprintln!("{:?} chi2 {:.1} dof {} dBIC {:.1} {:?}", f.cause, f.chi2, f.dof, f.delta_bic, f.params);
    }
    eprintln!("{}", e.verdict);
    assert_eq!(e.best, Cause::StressedLens, "{}", e.verdict);
    assert!(e.not_told_apart.is_empty(), "{}", e.verdict);
    assert!(e.adequate, "{}", e.verdict);
    let s = pick(&e, Cause::StressedLens);
    let p = &s.params;
    // The retardance enters as 1 - cos: its sign is not seen.
    let got = [p[0].value.abs(), p[1].value, p[2].value];
    for (k, want) in [(0usize, a), (1, c[0]), (2, c[1])] {
        assert!((got[k] - want).abs() < 3.0 * p[k].sigma, "{}: {} +- {} vs {want}", p[k].name, p[k].value, p[k].sigma);
    }
    // The axis is defined modulo 90 deg (linear polarimetry cannot tell fast from slow).
    let d = (p[3].value - off + 45.0).rem_euclid(90.0) - 45.0;
    assert!(d.abs() < 3.0 * p[3].sigma, "axis {} +- {}", p[3].value, p[3].sigma);
    assert!(pick(&e, Cause::DiattenuationOnly).delta_bic > 100.0);
}

/// A field made by the diattenuation alone, fitted with a free retardance: no retardance cause
/// is claimed (the null candidate is the best or not told apart from it).
#[test]
fn diattenuation_only_field_claims_no_retardance_cause() {
    let f = fields(
        &|x, y, q, u| {
            let (qd, ud) = diat(x, y);
            physical_block(qd, ud, [0.0, 0.0], 0.0, 0.0).forward(q, u).unwrap()
        },
        21,
    );
    let mf = fit_mueller_field(&f, &opts(Kind::diattenuation_retardance())).unwrap();
    let target = Target::smooth(&mf, 16, "test").unwrap();
    let ctx = Context::new(&full_turn(), 90.0, 3.4).unwrap();
    let e = explain(&target, &ctx, &Cause::ALL).unwrap();
    eprintln!("{}", e.verdict);
    assert!(
        e.best == Cause::DiattenuationOnly || e.not_told_apart.contains(&Cause::DiattenuationOnly),
        "{}",
        e.verdict
    );
    assert!(e.verdict.contains("no"), "{}", e.verdict);
}

/// A field fitted with the diattenuation alone has nothing to compare: refused, naming the
/// input and the remedy.
#[test]
fn diattenuation_only_fit_is_refused() {
    let f = fields(&|_, _, q, u| (q, u), 31);
    let kind = Kind::Physical { retardance: false, rotation: false, depolarization: false };
    let mf = fit_mueller_field(&f, &opts(kind)).unwrap();
    let err = Target::smooth(&mf, 16, "cal.json").err().unwrap().to_string();
    assert!(err.contains("cal.json") && err.contains("--free"), "{err}");
}

/// Frame-level: the simulator's plate (`mueller::Hwp` with its pleochroism, a partial
/// polarizer turning with the plate) in the dual-beam train at each angle, `F` from the beam
/// fluxes, demodulated by the Fourier sums written out here (`eq:Q`, `eq:U` for the optimal
/// set; least squares for four angles). The equivalent block reproduces it; its offset is the
/// closed form of the derivation: for an unpolarized sky `F_k = d cos(2 theta_k + psi)`
/// exactly, so the offset is `d sum_k w_k cos(2 theta_k + psi)`, zero for a full turn (the
/// `2 theta` harmonic is orthogonal to `4 theta`) and `(d cos psi, 0) / 2 + ...` leaking for the
/// four angles 0 ... 67.5 deg.
#[test]
fn polarizing_plate_after_demodulation_matches_frames_and_closed_form() {
    let (d, psi) = (0.01f64, 0.6f64);
    let hwp = mueller::Hwp { pleochroism: Some(mueller::Harmonic { amplitude: d, phase: psi }), ..Default::default() };
    let train = mueller::DualBeam { pre: vec![], hwp, wollaston: mueller::Wollaston::ideal(), post: None }.compile();
    for angles in [full_turn(), (0..4).map(|k| k as f64 * PI / 8.0).collect::<Vec<_>>()] {
        let solver = stokes::StokesSolver::new(&angles).unwrap();
        let blk = stokes::equivalent::equivalent_block(&solver, |t| hwp.matrix(t)).unwrap();
        // Least-squares weights of q, u on (cos 4t, sin 4t), written out.
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for t in &angles {
            let (s4, c4) = (4.0 * t).sin_cos();
            a += c4 * c4;
            b += c4 * s4;
            c += s4 * s4;
        }
        let det = a * c - b * b;
        let demod = |f: &[f64]| -> (f64, f64) {
            let (mut xq, mut xu) = (0.0, 0.0);
            for (t, fk) in angles.iter().zip(f) {
                let (s4, c4) = (4.0 * t).sin_cos();
                xq += c4 * fk;
                xu += s4 * fk;
            }
            ((c * xq - b * xu) / det, (a * xu - b * xq) / det)
        };
        for &(p, chi) in &[(0.0, 0.0), (0.0645, 68.4f64.to_radians()), (0.02, -0.9)] {
            let s = mueller::stokes_p_chi(1.0, p, chi);
            let f: Vec<f64> = angles
                .iter()
                .map(|&t| {
                    let fl = train.fluxes_at_plate(&s, t);
                    stokes::normalized_difference(fl.f_o, fl.f_e)
                })
                .collect();
            let (qf, uf) = demod(&f);
            let (qb, ub) = blk.forward(p * (2.0 * chi).cos(), p * (2.0 * chi).sin()).unwrap();
            // The block is the affine map at the origin; its curvature is O(d p^2).
            assert!(
                (qf - qb).abs() < 2.0 * d * p * p + 1e-13 && (uf - ub).abs() < 2.0 * d * p * p + 1e-13,
                "{qf} {qb} {uf} {ub}"
            );
        }
        let fc: Vec<f64> = angles.iter().map(|t| d * (2.0 * t + psi).cos()).collect();
        let (oq, ou) = demod(&fc);
        assert!((blk.0[(1, 0)] - oq).abs() < 1e-14 && (blk.0[(2, 0)] - ou).abs() < 1e-14);
        if angles.len() == 16 {
            assert!(oq.abs() < 1e-15 && ou.abs() < 1e-15);
        } else {
            assert!(oq.hypot(ou) > 0.3 * d, "four angles leak: {oq} {ou}");
        }
    }
}

/// The paper's B-band hypothesis on a simulation: a stressed lens (9 deg at 3.4', centre
/// off axis: about 0.3 % on the B sky) on top of the radial diattenuation, seen through the paper's three empty fields
/// (tab:empty: B 6.45 % at 68.4 deg, V 1.74 % at -53.8 deg, I 1.34 % at 68.7 deg), one per
/// band. Each band has one sky: the joint fit refuses the retardance (unconstrained), and a
/// diattenuation-only fit absorbs the lens completely (chi^2/dof ~ 1): the three fields alone
/// cannot tell a retardance from a diattenuation. What they can test: an achromatic retardance
/// makes an apparent (asymmetric) field proportional to P_sky, so B : V : I follow
/// 6.45 : 1.74 : 1.34 up to the sky angle; the numbers printed here are those of
/// docs/guide/mueller-and-planning.md.
#[test]
fn paper_three_fields_one_sky_per_band() {
    let paper = [("B", 0.0645, 68.4f64), ("V", 0.0174, -53.8), ("I", 0.0134, 68.7)];
    let lens = |x: f64, y: f64| {
        let (d, ax) = mueller::causes::stressed_lens(x, y, 9f64.to_radians(), 3.4, [0.8, -0.4], 0.0);
        physical_block(0.0, 0.0, retardance_vector(d, ax), 0.0, 0.0)
    };
    let mut shift = Vec::new();
    for (k, &(band, p, chi)) in paper.iter().enumerate() {
        let chi = chi.to_radians();
        let (q0, u0) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
        // The apparent field the lens adds to what the sky-field method calls instrumental.
        let worst = grid()
            .into_iter()
            .map(|(x, y)| {
                let (q, u) = lens(x, y).forward(q0, u0).unwrap();
                (q - q0).hypot(u - u0)
            })
            .fold(0.0, f64::max);
        shift.push(worst);
        let truth = common::mueller_fields::through(|x, y| diat_and_lens(x, y, 9.0, LENS_CENTRE_ARCMIN, 0.0));
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(40 + k as u64);
        let f = vec![common::mueller_fields::cal_field(band, p, chi.to_degrees(), &grid(), &truth, SIGMA, &mut rng)];
        let err = fit_mueller_field(&f, &opts(Kind::diattenuation_retardance())).err().unwrap().to_string();
        assert!(err.contains("retardance unconstrained"), "{band}: {err}");
        let none = Kind::Physical { retardance: false, rotation: false, depolarization: false };
        let mf = fit_mueller_field(&f, &MuellerFitOptions { deg: 6, ..opts(none) }).unwrap();
        eprintln!(
            "{band}: P_sky {:.2} %, largest apparent shift from the lens {:.3} %, diattenuation-only fit chi2/dof {:.3}",
            100.0 * p,
            100.0 * worst,
            mf.chi2_dof
        );
        assert!(mf.chi2_dof < 1.3, "{band}: one sky, the diattenuation absorbs the lens: {}", mf.chi2_dof);
    }
    assert!(shift[0] > 0.002 && shift[0] < 0.0045, "B {}", shift[0]);
    for k in 1..3 {
        let r = (shift[k] / shift[0]) / (paper[k].1 / paper[0].1);
        eprintln!("{}/B shift ratio over P_sky ratio: {r:.3}", paper[k].0);
        assert!(r > 0.3 && r < 3.0, "{r}");
    }
}

/// The tilted plate's effect after the demodulation: what a diattenuation cannot make
/// (retardance vector, rotation, depolarization of `physical_of_block`) is fourth order in the
/// angle of incidence, bounded by the depolarization `eps^2 / 4` of the closed-form retardance
/// change `eps <= pi sin^2 i / (2 n^2)`, plus the `2 theta` axis wobble's leak (none over a
/// full turn); what it does make is an offset along the plane of incidence (the two waves'
/// fields are not orthogonal once projected on the ray's transverse plane: a weak polarizance),
/// second order, below `sin^2 i`, which the comparison treats as diattenuation.
#[test]
fn tilted_plate_effect_is_second_order_in_incidence() {
    let plate = mueller::causes::UniaxialPlate::quartz_half_wave_b(0);
    let four: Vec<f64> = (0..4).map(|k| k as f64 * PI / 8.0).collect();
    for inc_deg in [5.0f64, 10.0] {
        let i = inc_deg.to_radians();
        let eps = PI * i.sin().powi(2) / (2.0 * plate.n_o * plate.n_o);
        for (name, angles) in [("16 angles", full_turn()), ("4 angles", four.clone())] {
            let solver = stokes::StokesSolver::new(&angles).unwrap();
            let (mut ret, mut off) = (0.0f64, 0.0f64);
            for k in 0..12 {
                let alpha = k as f64 * PI / 6.0;
                let b =
                    stokes::equivalent::equivalent_block(&solver, |t| mueller::causes::tilted_hwp(&plate, t, i, alpha))
                        .unwrap();
                let ph = mueller::causes::physical_of_block(&b);
                ret = ret.max(ph[2].hypot(ph[3]).max(ph[4].abs()).max(ph[5].abs()));
                off = off.max(b.0[(1, 0)].hypot(b.0[(2, 0)]));
            }
            eprintln!("tilt {inc_deg} deg, {name}: retardance/rotation/depolarization <= {ret:.2e}, offset {off:.2e}");
            assert!(off < i.sin().powi(2), "{off}");
            if angles.len() == 16 {
                assert!(ret < eps * eps / 4.0 + 1e-7, "{ret} vs {}", eps * eps / 4.0);
            } else {
                assert!(ret < eps * eps / 4.0 + 2.0 * (1.0 - i.cos()), "{ret}");
            }
        }
    }
}

/// Bins at one position cannot tell a stressed lens's centre from its strength and axis: four
/// parameters against the one retardance vector measured there. The
/// cause's fit is judged by the one conditioning judge: its note names a free parameter of the
/// lens and no error is claimed; the same lens over the full grid is determined (the control).
#[test]
fn a_cause_the_bin_layout_leaves_free_is_said_naming_the_parameter() {
    let lens = |x: f64, y: f64, q: f64, u: f64| {
        diat_and_lens(x, y, common::mueller_fields::LENS_EDGE_DEG, LENS_CENTRE_ARCMIN, 0.0).forward(q, u).unwrap()
    };
    let ctx = Context::new(&full_turn(), 90.0, 3.4).unwrap();
    let per_bin_opts = MuellerFitOptions { kind: Kind::diattenuation_retardance(), deg: 0, ..Default::default() };
    let run = |positions: &[(f64, f64)]| {
        let f = sky_fields(3, positions, &lens, 5);
        let (bins, _) = fit::mueller_field::fit_per_bin(&f, &per_bin_opts).unwrap();
        let target = Target::per_bin(&bins, "test").unwrap();
        explain(&target, &ctx, &[Cause::StressedLens]).unwrap()
    };
    let one = run(&[(LENS_CENTRE_ARCMIN[0] + 1.5, LENS_CENTRE_ARCMIN[1])]);
    let w = pick(&one, Cause::StressedLens);
    let note = w.note.clone().unwrap_or_default();
    let names = Cause::StressedLens.param_names();
    assert!(
        note.contains("do not determine") && names.iter().any(|n| note.contains(n)),
        "the note must name a free parameter of the lens: {note:?}"
    );
    assert!(w.params.iter().all(|p| !p.sigma.is_finite()), "no error where the fit is undetermined: {:?}", w.params);
    let full = run(&fors1_grid(10, 8));
    let w = pick(&full, Cause::StressedLens);
    assert!(w.note.is_none(), "{:?}", w.note);
    assert!(w.params.iter().all(|p| p.sigma.is_finite() && p.sigma > 0.0), "{:?}", w.params);
}
