//! Numerical stability of the reduction and the statistics over wide random ranges:
//! P in [0, 1], SNR 1..1e7, kappa in [-0.999, 0.999], angles across the 0/180 deg wrap, P near 0.
//!
//! Every quantity is finite; forward-then-reduce recovers the input for every angle set the
//! solver accepts; rotating the source and the instrument by `a` turns chi by `a`; and the f64
//! results agree with a double-double (~106-bit) evaluation written here, independently of
//! the crate, for the sums of near-equal `F_i`, `eq:F` itself, the kappa root (`eq:kappa2`),
//! the Bessel ratio `I1/I0` and the ML and WK estimator roots.

use mueller::{stokes_p_chi, DualBeam, Element, Wollaston};
use proptest::prelude::*;
use std::f64::consts::PI;
use stokes::kappa::{kappa_estimates, kappa_from_pair};
use stokes::stats::estimators::{ml_n, wk_n, Estimator};
use stokes::stats::special::bessel_ratio;
use stokes::{normalized_difference, polarization, reduce, Measurement, StokesSolver};

fn cfg(cases: u32) -> ProptestConfig {
    ProptestConfig { cases, failure_persistence: None, ..ProptestConfig::default() }
}

// ---------------------------------------------------------------------------------------
// Double-double arithmetic (Dekker / Knuth error-free transformations): the reference.
// ---------------------------------------------------------------------------------------

#[derive(Clone, Copy, Debug)]
struct Dd(f64, f64);

fn two_sum(a: f64, b: f64) -> Dd {
    let s = a + b;
    let bb = s - a;
    Dd(s, (a - (s - bb)) + (b - bb))
}
fn quick(a: f64, b: f64) -> Dd {
    let s = a + b;
    Dd(s, b - (s - a))
}
impl Dd {
    fn from(x: f64) -> Dd {
        Dd(x, 0.0)
    }
    fn add(self, o: Dd) -> Dd {
        let s = two_sum(self.0, o.0);
        let t = two_sum(self.1, o.1);
        let s = quick(s.0, s.1 + t.0);
        quick(s.0, s.1 + t.1)
    }
    fn neg(self) -> Dd {
        Dd(-self.0, -self.1)
    }
    fn sub(self, o: Dd) -> Dd {
        self.add(o.neg())
    }
    fn mul(self, o: Dd) -> Dd {
        let p = self.0 * o.0;
        let e = self.0.mul_add(o.0, -p);
        quick(p, e + (self.0 * o.1 + self.1 * o.0))
    }
    fn div(self, o: Dd) -> Dd {
        let q1 = self.0 / o.0;
        let r = self.sub(o.mul(Dd::from(q1)));
        let q2 = r.0 / o.0;
        let r = r.sub(o.mul(Dd::from(q2)));
        let q3 = r.0 / o.0;
        quick(q1, q2).add(Dd::from(q3))
    }
    fn sqrt(self) -> Dd {
        if self.0 <= 0.0 {
            return Dd::from(0.0);
        }
        let s = Dd::from(self.0.sqrt());
        // One Newton step doubles the ~53 correct bits.
        s.add(self.sub(s.mul(s)).div(s.mul(Dd::from(2.0))))
    }
    fn f(self) -> f64 {
        self.0 + self.1
    }
}

/// `I1(z)/I0(z)` in double-double: backward recurrence of `r_n = I_{n+1}/I_n =
/// 1 / (2(n+1)/z + r_{n+1})` (Gauss continued fraction) started far above `z`, and for
/// `z > 2e4` the Hankel asymptotic series of `I0`, `I1` to `z^-5` (truncation below 1e-21).
fn bessel_ratio_dd(z: f64) -> Dd {
    if z <= 0.0 {
        return Dd::from(0.0);
    }
    if z > 2e4 {
        let w = Dd::from(1.0).div(Dd::from(z));
        let series = |c: &[f64]| c.iter().rev().fold(Dd::from(0.0), |acc, &ck| acc.mul(w).add(Dd::from(ck)));
        // I_nu ~ e^z / sqrt(2 pi z) sum_k (-1)^k a_k(nu) / z^k, a_k from mu = 4 nu^2.
        let i0 = series(&[1.0, 1.0 / 8.0, 9.0 / 128.0, 225.0 / 3072.0, 11025.0 / 98304.0, 893025.0 / 3932160.0]);
        let i1 = series(&[1.0, -3.0 / 8.0, -15.0 / 128.0, -315.0 / 3072.0, -14175.0 / 98304.0, -1091475.0 / 3932160.0]);
        return i1.div(i0);
    }
    let k = (2.0 * z).ceil() as usize + 80;
    let zz = Dd::from(z);
    let mut r = Dd::from(0.0);
    for n in (0..k).rev() {
        r = Dd::from(1.0).div(Dd::from(2.0 * (n as f64 + 1.0)).div(zz).add(r));
    }
    r
}

/// Neumaier-free exact dot product: double-double accumulation of exact products.
fn dot_dd(a: &[f64], b: &[f64]) -> Dd {
    a.iter().zip(b).fold(Dd::from(0.0), |acc, (&x, &y)| acc.add(Dd::from(x).mul(Dd::from(y))))
}

/// Bisection on the sign of `f` (evaluated in double-double) between `lo` and `hi`.
fn bisect(f: impl Fn(f64) -> Dd, mut lo: f64, mut hi: f64) -> f64 {
    let flo = f(lo).f();
    for _ in 0..400 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if (f(mid).f() > 0.0) == (flo > 0.0) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

// ---------------------------------------------------------------------------------------
// Strategies
// ---------------------------------------------------------------------------------------

fn angle() -> impl Strategy<Value = f64> {
    prop_oneof![0.0..PI, Just(0.0), Just(PI - 1e-12), Just(1e-12), Just(PI.next_down()), Just(PI / 2.0)]
}
fn pdeg() -> impl Strategy<Value = f64> {
    prop_oneof![0.0..1.0f64, 0.0..0.3f64, Just(0.0), Just(1.0), (-15.0..-3.0f64).prop_map(|e| 10f64.powf(e))]
}
fn kappa() -> impl Strategy<Value = f64> {
    prop_oneof![-0.999..0.999f64, Just(-0.999), Just(0.999), Just(0.0)]
}
/// log-uniform SNR of one exposure in [1, 1e7].
fn snr() -> impl Strategy<Value = f64> {
    (0.0..7.0f64).prop_map(|e| 10f64.powf(e))
}
/// The optimal sets N = 4, 8, 16 or an arbitrary set of 2..16 plate angles in [0, 2 pi).
fn angle_set() -> impl Strategy<Value = Vec<f64>> {
    prop_oneof![
        prop::sample::select(vec![4usize, 8, 16]).prop_map(mueller::optimal_angles),
        prop::collection::vec(0.0..2.0 * PI, 2..17),
    ]
}

fn train(k: f64) -> DualBeam {
    DualBeam { wollaston: Wollaston { t: 0.5 * (1.0 + k), s: 0.5 * (1.0 - k), delta_alpha: 0.0 }, ..Default::default() }
}

/// Angular distance modulo pi.
fn dchi(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(PI);
    d.min(PI - d)
}

/// Condition number of the normal matrix of eq:system for this angle set.
fn normal_condition(s: &StokesSolver) -> f64 {
    let (c4, s4) = s.modulation();
    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
    for i in 0..c4.len() {
        a += c4[i] * c4[i];
        b += c4[i] * s4[i];
        c += s4[i] * s4[i];
    }
    let tr = a + c;
    let disc = ((a - c).powi(2) + 4.0 * b * b).sqrt();
    (tr + disc) / (tr - disc).max(f64::MIN_POSITIVE)
}

proptest! {
    #![proptest_config(cfg(256))]

    /// eq:F in f64 against double-double: relative error a few ulp over counts 1..1e15 and
    /// near-equal beams (f_O - f_E is exact there by Sterbenz).
    #[test]
    fn normalized_difference_vs_double_double(
        f_o in prop_oneof![1.0..1e15f64, Just(1.0)],
        rel in prop_oneof![-1.0..1.0f64, (-15.0..0.0f64).prop_map(|e| 10f64.powf(e)), Just(0.0)],
    ) {
        let f_e = f_o * (1.0 + rel);
        let f = normalized_difference(f_o, f_e);
        let r = Dd::from(f_o).sub(Dd::from(f_e)).div(Dd::from(f_o).add(Dd::from(f_e))).f();
        prop_assert!(f.is_finite());
        prop_assert!((f - r).abs() <= 4.0 * f64::EPSILON * r.abs(), "{f:e} vs {r:e}");
    }

    /// Sums of near-equal F_i (a strong kappa with P down to 1e-15 makes every F_i ~ kappa):
    /// the solver's f64 dot products agree with an exact double-double dot product of the same
    /// weights to N eps sum |c_i F_i|, the bound the reduction's `chi_defined` test relies on.
    #[test]
    fn solver_sums_vs_double_double(theta in angle_set(), p in pdeg(), chi in angle(), k in kappa()) {
        let Ok(solver) = StokesSolver::new(&theta) else { return Ok(()) };
        let fl = train(k).fluxes(&stokes_p_chi(1.0, p, chi), &theta);
        let f: Vec<f64> = fl.iter().map(|b| normalized_difference(b.f_o, b.f_e)).collect();
        let (q, u) = solver.solve(&f);
        let (cq, cu) = solver.weights();
        let n = f.len() as f64;
        for (got, w) in [(q, cq), (u, cu)] {
            let exact = dot_dd(w, &f).f();
            let scale: f64 = w.iter().zip(&f).map(|(a, b)| (a * b).abs()).sum();
            prop_assert!((got - exact).abs() <= 2.0 * n * f64::EPSILON * scale, "{got:e} vs {exact:e}");
        }
    }

    /// Forward-then-reduce: for every angle set the solver accepts, any kappa (corrected with
    /// the prism's own kappa), P in [0, 1] and chi across the wrap, the reduction recovers
    /// (Q/I, U/I) to rounding amplified by the condition of the angle set, every reported
    /// number is finite, and chi (when defined) is within its rounding of the input.
    #[test]
    fn forward_then_reduce_recovers_input(theta in angle_set(), p in pdeg(), chi in angle(), k in kappa(), snr in snr()) {
        let Ok(solver) = StokesSolver::new(&theta) else { return Ok(()) };
        let w = train(k).wollaston;
        let i = snr * snr;
        let fl = train(k).fluxes(&stokes_p_chi(i, p, chi), &theta);
        let (fo, fe): (Vec<f64>, Vec<f64>) = fl.iter().map(|b| (b.f_o.max(0.0), b.f_e.max(0.0))).unzip();
        let m = Measurement::poisson(theta.clone(), fo, fe).unwrap();
        let m = m.corrected_for_kappa(w.kappa()).unwrap();
        let r = reduce(&m).unwrap();
        let (q0, u0) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
        let tol = 1e3 * f64::EPSILON * normal_condition(&solver) * (1.0 + 1.0 / (1.0 - k.abs()));
        prop_assert!((r.qu.q - q0).abs() <= tol && (r.qu.u - u0).abs() <= tol,
            "q {} vs {q0}, u {} vs {u0}, tol {tol:e}", r.qu.q, r.qu.u);
        for x in [r.p, r.chi, r.sigma_p, r.snr, r.sigma_p_analytic, r.a0, r.sigma_a0, r.qu.var_q, r.qu.var_u, r.qu.cov_qu] {
            prop_assert!(x.is_finite(), "{r:?}");
        }
        prop_assert!((0.0..PI).contains(&r.chi));
        if r.chi_defined {
            prop_assert!(r.sigma_chi.is_finite());
            if p > 1e3 * tol {
                prop_assert!(dchi(r.chi, chi) <= 2.0 * tol / p, "chi {} vs {chi}", r.chi);
            }
        }
        for h in &r.fourier {
            prop_assert!(h.power().is_finite());
        }
        for e in &r.kappa {
            prop_assert!(e.kappa.is_finite() && e.kappa.abs() <= 1.0);
        }
    }

    /// Rotation invariance: source and pre-optics turned by `a`, plate angles by `a/2`, the
    /// Wollaston fixed: the reduced (Q, U) turns by 2a, i.e. chi by a (mod 180 deg), for any
    /// accepted angle set, kappa and instrumental polarization.
    #[test]
    fn rotating_source_and_instrument_turns_chi(
        theta in angle_set(), p in pdeg(), chi in angle(), p_inst in 0.0..0.3f64, phi in angle(),
        k in kappa(), a in angle(),
    ) {
        let Ok(_) = StokesSolver::new(&theta) else { return Ok(()) };
        let th1: Vec<f64> = theta.iter().map(|t| t + 0.5 * a).collect();
        let w = train(k).wollaston;
        let run = |th: &[f64], chi_s: f64, phi_i: f64| {
            let t = DualBeam { pre: vec![Element::PartialPolarizer { p: p_inst, phi: phi_i }], wollaston: w, ..Default::default() };
            let fl = t.fluxes(&stokes_p_chi(1e6, p, chi_s), th);
            let (fo, fe): (Vec<f64>, Vec<f64>) = fl.iter().map(|b| (b.f_o.max(0.0), b.f_e.max(0.0))).unzip();
            let m = Measurement::with_errors(th.to_vec(), fo, fe, vec![1.0; th.len()], vec![1.0; th.len()]).unwrap();
            reduce(&m.corrected_for_kappa(w.kappa()).unwrap()).unwrap()
        };
        let r0 = run(&theta, chi, phi);
        let r1 = match StokesSolver::new(&th1) { Ok(_) => run(&th1, chi + a, phi + a), Err(_) => return Ok(()) };
        let (c, s) = (2.0 * a).sin_cos();
        let (qe, ue) = (r0.qu.q * s - r0.qu.u * c, r0.qu.q * c + r0.qu.u * s);
        let solver = StokesSolver::new(&theta).unwrap();
        let tol = 1e3 * f64::EPSILON * normal_condition(&solver) * (1.0 + 1.0 / (1.0 - k.abs()));
        prop_assert!((r1.qu.q - qe).abs() <= tol && (r1.qu.u - ue).abs() <= tol,
            "({}, {}) vs ({qe}, {ue})", r1.qu.q, r1.qu.u);
        if r0.p > 1e3 * tol {
            prop_assert!(dchi(r1.chi, r0.chi + a) <= 2.0 * tol / r0.p);
        }
    }

    /// eq:kappa2: the cancellation-free root against the textbook root `g -+ sqrt(g^2 - 1)`
    /// evaluated in double-double from the same F pair, for kappa up to +-0.999 and |m| <= 0.3.
    #[test]
    fn kappa_root_vs_double_double(k in kappa(), m in -0.3..0.3f64) {
        let fa = (k + m) / (1.0 + k * m);
        let fb = (k - m) / (1.0 - k * m);
        let (got, clamped) = kappa_from_pair(fa, fb);
        prop_assert!(!clamped);
        let s = Dd::from(fa).add(Dd::from(fb));
        if s.f() == 0.0 {
            prop_assert_eq!(got, 0.0);
            return Ok(());
        }
        let g = Dd::from(1.0).add(Dd::from(fa).mul(Dd::from(fb))).div(s);
        let root = g.mul(g).sub(Dd::from(1.0)).sqrt();
        let reference = if g.0 > 0.0 { g.sub(root) } else { g.add(root) }.f();
        prop_assert!((got - reference).abs() <= 8.0 * f64::EPSILON * reference.abs().max(1e-300),
            "{got:e} vs {reference:e}");
        // And the estimates of a reduction use it unchanged.
        let theta = mueller::optimal_angles(4);
        let est = kappa_estimates(&theta, &[fa, 0.0, fb, 0.0]);
        prop_assert_eq!(est[0].kappa, got);
    }

    /// I1/I0 (scaled Bessel functions) against the double-double continued fraction /
    /// asymptotic series, z from 1e-8 to 1e12.
    #[test]
    fn bessel_ratio_vs_double_double(e in -8.0..12.0f64) {
        let z = 10f64.powf(e);
        let got = bessel_ratio(z);
        let r = bessel_ratio_dd(z).f();
        prop_assert!(got.is_finite() && (0.0..=1.0).contains(&got));
        prop_assert!((got - r).abs() <= 1e-14 * r, "z {z:e}: {got:e} vs {r:e}");
    }

    /// The maximum-likelihood root (a = x I1(ax)/I0(ax)) against a bisection of the same
    /// equation evaluated in double-double, x from just above sqrt 2 to 1e5.
    #[test]
    fn ml_root_vs_double_double(e in -3.0..5.0f64) {
        let x = std::f64::consts::SQRT_2 + 10f64.powf(e);
        let got = ml_n(x);
        // a (x^2 I1(ax)/(ax I0(ax))) - 1 = 0 written as x I1(ax)/I0(ax) - a = 0 for a > 0.
        let f = |a: f64| Dd::from(x).mul(bessel_ratio_dd(a * x)).sub(Dd::from(a));
        let reference = bisect(f, 1e-300, x);
        prop_assert!(got.is_finite() && got >= 0.0 && got <= x);
        // Near the sqrt 2 threshold the root is a square root of the distance: allow its
        // conditioning (a ~ sqrt(x - sqrt 2)) on top of 1e-12.
        let tol = 1e-12 * x + 1e-15 / (reference.max(1e-8));
        prop_assert!((got - reference).abs() <= tol, "x {x}: {got:e} vs {reference:e}");
    }

    /// The Wardle & Kronberg root (1/x - x + a I1(ax)/I0(ax) = 0) likewise, x from 1 to 1e5.
    #[test]
    fn wk_root_vs_double_double(e in -3.0..5.0f64) {
        let x = 1.0 + 10f64.powf(e);
        let got = wk_n(x);
        let target = Dd::from(x).sub(Dd::from(1.0).div(Dd::from(x)));
        let f = |a: f64| Dd::from(a).mul(bessel_ratio_dd(a * x)).sub(target);
        let mut hi = target.f() + 1.0;
        while f(hi).f() < 0.0 {
            hi *= 2.0;
        }
        let reference = bisect(f, target.f().max(0.0), hi);
        prop_assert!(got.is_finite() && got >= 0.0);
        prop_assert!((got - reference).abs() <= 1e-12 * x + 1e-15 / reference.max(1e-8), "x {x}: {got:e} vs {reference:e}");
    }
}

proptest! {
    #![proptest_config(cfg(64))]

    /// Every estimator, the Rice pdf/cdf/moments and both intervals stay finite and ordered
    /// for x = P/sigma from 0 to 1e7 (SNR 1..1e7 times P up to 1).
    #[test]
    fn statistics_finite(e in -6.0..7.0f64, cl in 0.5..0.999f64) {
        use stokes::stats::{intervals, rice};
        let x = 10f64.powf(e);
        for est in Estimator::ALL {
            let v = est.apply_n(x);
            prop_assert!(v.is_finite() && v >= 0.0, "{est:?} at x {x}: {v}");
            if est != Estimator::Mb {
                // Every estimator except the posterior mean debiases downward.
                prop_assert!(v <= x * (1.0 + 1e-12), "{est:?} at x {x}: {v}");
            }
        }
        for a in [0.0, x, 1.0] {
            for v in [rice::pdf_n(x, a), rice::cdf_n(x, a), rice::sf_n(x, a), rice::mean_n(a), rice::std_n(a), rice::mode_n(a)] {
                prop_assert!(v.is_finite() && v >= 0.0, "x {x} a {a}: {v}");
            }
            prop_assert!((rice::cdf_n(x, a) + rice::sf_n(x, a) - 1.0).abs() < 1e-10);
        }
        if x < 1e4 {
            let (lo, hi) = intervals::neyman_n(x, cl);
            prop_assert!(lo.is_finite() && lo >= 0.0);
            if let Some(h) = hi {
                prop_assert!(h.is_finite() && h >= lo);
            }
            let (lo, hi) = intervals::hpd_n(x, cl);
            prop_assert!(lo.is_finite() && hi.is_finite() && lo >= 0.0 && hi > lo, "hpd {lo} {hi}");
        }
    }
}

/// `polarization` at the wrap: chi is in [0, pi) for every sign combination of tiny q, u,
/// including -0.0, and P is exactly hypot(q, u).
#[test]
fn polarization_angle_wrap() {
    for &(q, u) in &[
        (1.0, -0.0),
        (1.0, 0.0),
        (1.0, -1e-300),
        (-1.0, 1e-300),
        (-1.0, -1e-300),
        (0.0, 0.0),
        (-0.0, -0.0),
        (1e-300, -1e-300),
    ] {
        let (p, chi) = polarization(q, u);
        assert!((0.0..PI).contains(&chi), "q {q} u {u}: chi {chi}");
        assert_eq!(p, f64::hypot(q, u));
    }
}

/// The double-double reference itself, against closed forms: I1/I0 at z = 1 (Abramowitz &
/// Stegun table 9.8: I0(1) = 1.266065877752008, I1(1) = 0.565159103992485) and the
/// continuity of the recurrence / asymptotic switch at z = 2e4.
#[test]
fn reference_is_sane() {
    let r = bessel_ratio_dd(1.0).f();
    assert!((r - 0.565159103992485 / 1.266065877752008).abs() < 1e-14);
    let a = bessel_ratio_dd(2e4).f();
    let b = bessel_ratio_dd(2e4 * (1.0 + 1e-15)).f();
    assert!((a - b).abs() < 1e-18, "{a} {b}");
    let two = Dd::from(2.0).sqrt();
    assert!((two.mul(two).sub(Dd::from(2.0))).f().abs() < 1e-30);
}

proptest! {
    #![proptest_config(cfg(256))]

    /// sigma_F (eq:F propagated) and its variance form (what frame reduction adds up) against
    /// double-double, over fluxes and errors from 1e-100 to 1e100 (the fast paths and their
    /// fallbacks where squares under- or overflow).
    #[test]
    fn sigma_and_variance_of_normalized_difference_vs_double_double(
        eo in -100.0..100.0f64, ratio in 1e-3..1e3f64, es in -3.0..3.0f64, rs in 1e-3..1e3f64,
    ) {
        let f_o = 10f64.powf(eo);
        let f_e = f_o * ratio;
        let s_o = f_o * 10f64.powf(es);
        let s_e = s_o * rs;
        let sig = stokes::sigma_normalized_difference(f_o, f_e, s_o, s_e);
        let var = stokes::variance_normalized_difference(f_o, f_e, s_o * s_o, s_e * s_e);
        // Scale out the magnitude so that the double-double products stay in range.
        let k = 1.0 / f_o.max(f_e);
        let (fo, fe, so, se) = (Dd::from(f_o * k), Dd::from(f_e * k), Dd::from(s_o * k), Dd::from(s_e * k));
        let a = fe.mul(so);
        let b = fo.mul(se);
        let tot = fo.add(fe);
        let t2 = tot.mul(tot);
        let s2 = a.mul(a).add(b.mul(b));
        let r = Dd::from(2.0).mul(s2.sqrt()).div(t2).f();
        let r2 = Dd::from(4.0).mul(s2).div(t2.mul(t2)).f();
        prop_assert!(sig.is_finite() && sig > 0.0, "{sig}");
        prop_assert!((sig - r).abs() <= 8.0 * f64::EPSILON * r, "{sig:e} vs {r:e}");
        prop_assert!(var.is_finite() && var > 0.0, "{var}");
        prop_assert!((var - r2).abs() <= 16.0 * f64::EPSILON * r2, "{var:e} vs {r2:e}");
    }
}
