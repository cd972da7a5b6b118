//! Numerical stability of the Mueller algebra and the dual-beam forward model over wide
//! random ranges: every quantity finite, `M^-1 M = 1` wherever `M` is invertible
//! (with an error bound set by the condition number), rotation covariance of the whole train,
//! and closed forms at the edges (P -> 0 and 1, kappa -> +-1, angles at the 0/180 deg wrap).

use mueller::{
    inverse, partial_polarizer, polarizer, retarder, rotate, rotation, stokes_p_chi, DualBeam, Element, Hwp, Mueller,
    Stokes, Wollaston,
};
use proptest::prelude::*;
use std::f64::consts::PI;

fn cfg() -> ProptestConfig {
    ProptestConfig { cases: 256, failure_persistence: None, ..ProptestConfig::default() }
}

/// An angle in [0, pi], with the wrap points (0, pi and their neighbours) drawn often.
fn angle() -> impl Strategy<Value = f64> {
    prop_oneof![
        0.0..PI,
        Just(0.0),
        Just(PI),
        Just(PI - 1e-12),
        Just(1e-12),
        Just(PI.next_down()),
        Just(-0.0),
        Just(PI / 2.0),
    ]
}

/// A polarization degree in [0, 1] with the edges drawn often.
fn pdeg() -> impl Strategy<Value = f64> {
    prop_oneof![0.0..1.0f64, Just(0.0), Just(1.0), Just(1e-12), Just(1.0 - 1e-12), 0.0..0.3f64]
}

/// Wollaston imbalance kappa in [-0.999, 0.999] with the edges.
fn kappa() -> impl Strategy<Value = f64> {
    prop_oneof![-0.999..0.999f64, Just(-0.999), Just(0.999), Just(0.0)]
}

fn max_abs(m: &Mueller) -> f64 {
    m.iter().fold(0.0f64, |a, x| a.max(x.abs()))
}

/// A random element of a polarimeter train with its Mueller matrix.
fn element() -> impl Strategy<Value = Mueller> {
    prop_oneof![
        (pdeg(), angle()).prop_map(|(p, phi)| partial_polarizer(p, phi)),
        (-PI..PI, angle()).prop_map(|(d, a)| retarder(d, a)),
        (1e-3..1.0f64, 1e-3..1.0f64, angle()).prop_map(|(k1, k2, a)| mueller::diattenuator(k1, k2, a)),
        angle().prop_map(rotation),
    ]
}

proptest! {
    #![proptest_config(cfg())]

    /// M^-1 M = 1 for products of up to four elements, to within eps times the condition
    /// number; when `inverse` refuses, the matrix really is (numerically) singular.
    #[test]
    fn inverse_round_trip(ms in prop::collection::vec(element(), 1..5)) {
        let m = ms.iter().fold(Mueller::identity(), |acc, e| e * acc);
        prop_assert!(m.iter().all(|x| x.is_finite()));
        let sv = m.singular_values();
        let cond = sv.max() / sv.min();
        match inverse(&m) {
            Ok(mi) => {
                prop_assert!(mi.iter().all(|x| x.is_finite()));
                let err = max_abs(&(mi * m - Mueller::identity()));
                prop_assert!(err <= 1e3 * f64::EPSILON * cond, "err {err:e}, cond {cond:e}");
                let err2 = max_abs(&(m * mi - Mueller::identity()));
                prop_assert!(err2 <= 1e3 * f64::EPSILON * cond, "err {err2:e}, cond {cond:e}");
            }
            Err(_) => prop_assert!(!(cond < 1e11), "refused an invertible matrix: cond {cond:e}"),
        }
    }

    /// Rotation matrices: orthogonal, R(a) R(-a) = 1, and an element turned by a + pi is the
    /// same element (period pi of linear optics), including at the 0/180 wrap.
    #[test]
    fn rotation_identities(a in angle(), b in angle(), m in element()) {
        let r = rotation(a);
        prop_assert!(max_abs(&(r * r.transpose() - Mueller::identity())) < 4.0 * f64::EPSILON);
        prop_assert!(max_abs(&(rotation(a) * rotation(-a) - Mueller::identity())) < 4.0 * f64::EPSILON);
        prop_assert!(max_abs(&(rotation(a) * rotation(b) - rotation(a + b))) < 16.0 * f64::EPSILON);
        let d = max_abs(&(rotate(&m, a + PI) - rotate(&m, a)));
        prop_assert!(d < 64.0 * f64::EPSILON * max_abs(&m).max(1.0), "{d:e}");
    }

    /// `M_I(p, phi)` turns unpolarized light into light of degree exactly `p` at angle `phi`
    /// (eq:instpol with Q = U = 0), for p in [0, 1] and phi across the wrap.
    #[test]
    fn partial_polarizer_closed_form(p in pdeg(), phi in angle()) {
        let s = partial_polarizer(p, phi) * Stokes::new(1.0, 0.0, 0.0, 0.0);
        let (q, u) = (s[1] / s[0], s[2] / s[0]);
        prop_assert!((q.hypot(u) - p).abs() <= 4.0 * f64::EPSILON);
        if p > 1e-9 {
            let chi = (0.5 * u.atan2(q)).rem_euclid(PI);
            let d = (chi - phi.rem_euclid(PI)).abs();
            prop_assert!(d.min(PI - d) * p <= 8.0 * f64::EPSILON, "chi {chi} phi {phi}");
        }
    }

    /// Forward model over the whole parameter box: every flux finite and non-negative, and the
    /// two beams never carry more than the light that enters (the train is passive).
    #[test]
    fn forward_model_finite_and_passive(
        i in prop_oneof![1.0..1e14f64, Just(1.0), Just(1e14)],
        p in pdeg(), chi in angle(), p_inst in 0.0..0.3f64, phi in angle(), k in kappa(),
        dbeta in -0.3..0.3f64, off in -0.1..0.1f64, theta in prop::collection::vec(angle(), 1..17),
    ) {
        let train = DualBeam {
            pre: vec![Element::PartialPolarizer { p: p_inst, phi }],
            hwp: Hwp { retardance_error: dbeta, chi_offset: off, ..Hwp::ideal() },
            wollaston: Wollaston { t: 0.5 * (1.0 + k), s: 0.5 * (1.0 - k), delta_alpha: 0.0 },
            post: None,
        };
        let s = stokes_p_chi(i, p, chi);
        for b in train.fluxes(&s, &theta) {
            prop_assert!(b.f_o.is_finite() && b.f_e.is_finite());
            prop_assert!(b.f_o >= -1e-12 * i && b.f_e >= -1e-12 * i, "{b:?}");
            // Each beam is at most 2t (resp. 2s) of the incoming intensity.
            prop_assert!(b.f_o <= (1.0 + k) * i * (1.0 + 1e-12) && b.f_e <= (1.0 - k) * i * (1.0 + 1e-12));
        }
    }

    /// Rotation covariance: turning the source and the pre-optics by `a` and the half-wave
    /// plate by `a/2` (the Wollaston fixed) leaves every flux unchanged, because an ideal plate
    /// at theta maps chi to 2 theta - chi. Any kappa.
    #[test]
    fn rotating_source_and_instrument_leaves_fluxes(
        p in pdeg(), chi in angle(), p_inst in 0.0..0.3f64, phi in angle(), k in kappa(), a in angle(),
        theta in prop::collection::vec(angle(), 1..17),
    ) {
        let w = Wollaston { t: 0.5 * (1.0 + k), s: 0.5 * (1.0 - k), delta_alpha: 0.0 };
        let t0 = DualBeam { pre: vec![Element::PartialPolarizer { p: p_inst, phi }], wollaston: w, ..Default::default() };
        let t1 = DualBeam { pre: vec![Element::PartialPolarizer { p: p_inst, phi: phi + a }], wollaston: w, ..Default::default() };
        let th1: Vec<f64> = theta.iter().map(|t| t + 0.5 * a).collect();
        let f0 = t0.fluxes(&stokes_p_chi(1.0, p, chi), &theta);
        let f1 = t1.fluxes(&stokes_p_chi(1.0, p, chi + a), &th1);
        for (x, y) in f0.iter().zip(&f1) {
            prop_assert!((x.f_o - y.f_o).abs() <= 64.0 * f64::EPSILON && (x.f_e - y.f_e).abs() <= 64.0 * f64::EPSILON,
                "{x:?} vs {y:?}");
        }
    }
}

/// The ideal polarizer is singular and `inverse` says so instead of returning garbage.
#[test]
fn ideal_polarizer_has_no_inverse() {
    assert!(inverse(&polarizer(0.3)).is_err());
    assert!(inverse(&partial_polarizer(1.0, 1.1)).is_err());
    assert!(inverse(&Mueller::zeros()).is_err());
}

/// Regression (a defect found here, fixed in 50e8393): `inverse` of a matrix holding a NaN
/// (or inf) never returned:
/// nalgebra's SVD does not converge on non-finite input and `inverse` calls
/// `singular_values()` before looking at the entries. Fix (crates/mueller/src/analysis.rs,
/// `inverse`): return `Error::Singular` first when `!m.iter().all(|x| x.is_finite())`.
/// The call runs in a thread so that the hang shows as a failure after 5 s, not a stuck suite.
#[test]
fn non_finite_matrix_inverse_returns_an_error() {
    for bad in [f64::NAN, f64::INFINITY] {
        let mut m = Mueller::identity();
        m[(1, 2)] = bad;
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(inverse(&m).is_err());
        });
        match rx.recv_timeout(std::time::Duration::from_secs(5)) {
            Ok(is_err) => assert!(is_err, "a matrix with {bad} must not be inverted"),
            Err(_) => panic!("mueller::inverse hangs on a matrix holding {bad} (SVD of non-finite input)"),
        }
    }
}

proptest! {
    #![proptest_config(cfg())]

    /// Fresnel interfaces between lossless dielectrics: R + T = 1 for s and p at every angle
    /// below the critical angle, including normal and grazing incidence (aoi up to 90 deg -
    /// 1e-9) and Brewster's angle (R_p = 0 at tan aoi = n1/n0); everything finite; the
    /// transmission Mueller matrix is physical and has M00 = (T_s + T_p)/2.
    #[test]
    fn fresnel_energy_conservation(n0 in 1.0..1.8f64, n1 in 1.0..2.5f64, t in prop_oneof![0.0..1.0f64, Just(0.0), Just(1.0 - 1e-11)]) {
        use mueller::fresnel::interface;
        use mueller::C64;
        // Keep below the critical angle when going to a lower index.
        let max_aoi = if n1 < n0 { (n1 / n0).asin() } else { std::f64::consts::FRAC_PI_2 };
        let aoi = t * max_aoi * (1.0 - 1e-9);
        let c = interface(n0, C64::new(n1, 0.0), aoi).unwrap();
        for (r, tt) in [(c.reflectance_s, c.transmittance_s), (c.reflectance_p, c.transmittance_p)] {
            prop_assert!(r.is_finite() && tt.is_finite() && r >= 0.0 && tt >= 0.0);
            prop_assert!((r + tt - 1.0).abs() <= 1e-12, "R {r} + T {tt} != 1 at aoi {aoi} n0 {n0} n1 {n1}");
        }
        let m = c.mueller_t(0.3);
        prop_assert!(m.iter().all(|x| x.is_finite()));
        prop_assert!((m[(0, 0)] - 0.5 * (c.transmittance_s + c.transmittance_p)).abs() <= 1e-12);
        prop_assert!(mueller::is_physical(&m, 1e-9));
        let brewster = (n1 / n0).atan();
        let cb = interface(n0, C64::new(n1, 0.0), brewster).unwrap();
        prop_assert!(cb.reflectance_p <= 1e-20, "R_p at Brewster = {}", cb.reflectance_p);
    }
}
