//! Polarization statistics against independent references: closed forms, limits, quadrature
//! with a different rule (composite Simpson), and simulation of normal Q, U.

use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;
use std::f64::consts::{FRAC_PI_2, PI, SQRT_2};
use stokes::stats::angle::{half_width, mass_within, pdf_dev};
use stokes::stats::estimators::{as_n, ln_likelihood_n, mas_n, mb_n, ml_n, mp2_n, pr06_n, wk_n};
use stokes::stats::intervals::{hpd_n, neyman_n};
use stokes::stats::rice::{cdf_n, mean_bias_n, mean_n, mode_n, pdf_n, quantile_n, sf_n, std_n};
use stokes::stats::{hpd_interval, neyman_interval, AngleDist, Estimator, PolMeasurement, Rice, ONE_SIGMA};

/// Composite Simpson on [a, b] with `m` (even) intervals: an independent quadrature.
fn simpson<F: Fn(f64) -> f64>(f: F, a: f64, b: f64, m: usize) -> f64 {
    let h = (b - a) / m as f64;
    let mut s = f(a) + f(b);
    for i in 1..m {
        s += f(a + i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 };
    }
    s * h / 3.0
}

fn rice_support(a: f64) -> (f64, f64) {
    ((a - 15.0).max(0.0), a + 15.0)
}

#[test]
fn rice_pdf_is_normalized_and_moments_match_quadrature() {
    for &a in &[0.0, 0.3, 1.0, 2.5, 4.0, 7.0, 20.0, 150.0] {
        let (lo, hi) = rice_support(a);
        let m = 40_000;
        let norm = simpson(|x| pdf_n(x, a), lo, hi, m);
        assert!((norm - 1.0).abs() < 1e-11, "a={a}: norm {norm}");
        let mean = simpson(|x| x * pdf_n(x, a), lo, hi, m);
        assert!((mean_n(a) - mean).abs() < 1e-10 * mean.max(1.0), "a={a}: mean {} vs {mean}", mean_n(a));
        let bias = simpson(|x| (x - a) * pdf_n(x, a), lo, hi, m);
        assert!((mean_bias_n(a) - bias).abs() < 1e-10, "a={a}: bias {} vs {bias}", mean_bias_n(a));
        let var = simpson(|x| (x - a - bias).powi(2) * pdf_n(x, a), lo, hi, m);
        assert!((std_n(a) - var.sqrt()).abs() < 1e-9, "a={a}: std {} vs {}", std_n(a), var.sqrt());
        // Second raw moment: 2 + a^2 (closed form).
        let m2 = simpson(|x| x * x * pdf_n(x, a), lo, hi, m);
        assert!((m2 - (2.0 + a * a)).abs() < 1e-9 * (2.0 + a * a));
        // cdf against quadrature at a few points, and sf = 1 - cdf.
        for &x in &[0.2, 1.0, a, a + 1.3, a + 4.0] {
            if x <= lo {
                continue;
            }
            let c = simpson(|t| pdf_n(t, a), 0.0f64.max(lo), x, 20_000);
            assert!((cdf_n(x, a) - c).abs() < 1e-11, "a={a} x={x}: cdf {} vs {c}", cdf_n(x, a));
            assert!((cdf_n(x, a) + sf_n(x, a) - 1.0).abs() < 1e-12);
        }
        // Median and mode.
        let med = quantile_n(0.5, a);
        assert!((cdf_n(med, a) - 0.5).abs() < 1e-12);
        let mo = mode_n(a);
        let h = 1e-4;
        assert!(pdf_n(mo, a) >= pdf_n(mo - h, a) && pdf_n(mo, a) >= pdf_n(mo + h, a), "a={a}: mode {mo}");
    }
}

/// Rayleigh limit (P0 = 0): cdf 1 - exp(-x^2/2), mean sqrt(pi/2), std sqrt(2 - pi/2), mode 1.
#[test]
fn rayleigh_limit() {
    let s = 0.003;
    let r = Rice::new(0.0, s).unwrap();
    assert!((r.std() - s * (2.0 - PI / 2.0).sqrt()).abs() < 1e-15);
    assert!((r.mean() - s * FRAC_PI_2.sqrt()).abs() < 1e-15);
    assert!((r.mode() - s).abs() < 1e-15);
    assert!((r.median() - s * (2.0 * 2f64.ln()).sqrt()).abs() < 1e-13);
    for &x in &[0.1f64, 0.7, 1.0, 2.0, 5.0, 9.0] {
        let exact = -(-0.5 * x * x).exp_m1();
        assert!((cdf_n(x, 0.0) - exact).abs() < 1e-13, "x={x}");
        let tail = (-0.5 * x * x).exp();
        assert!((sf_n(x, 0.0) - tail).abs() < 1e-13 * tail.max(1e-3), "x={x}");
    }
    assert!((stokes::stats::rice::rayleigh_std(1.0) - (2.0 - PI / 2.0).sqrt()).abs() < 1e-15);
}

/// High signal-to-noise: bias of the mean -> 1/(2a) + 1/(8a^3), variance -> 1 - 1/(2a^2),
/// mode -> a + 1/(2a): the asymptotic expansions of the Rice distribution.
#[test]
fn rice_high_snr_asymptotes_without_cancellation() {
    for &a in &[200.0, 1e3, 1e4] {
        let b = mean_bias_n(a);
        let asym = 0.5 / a + 0.125 / (a * a * a);
        assert!((b - asym).abs() < 1e-3 * asym, "a={a}: {b} vs {asym}");
        let s = std_n(a);
        assert!((s - (1.0 - 0.5 / (a * a)).sqrt()).abs() < 1e-9, "a={a}: std {s}");
        let mo = mode_n(a) - a;
        assert!((mo - 0.5 / a).abs() < 1e-3 * 0.5 / a + 1e-12, "a={a}: mode bias {mo}");
    }
    // P P0 / sigma^2 = 1e6 and 1e8: the density is sqrt(x/a) phi(x - a).
    for &(x, a) in &[(1e3, 1e3), (1e4, 1e4 - 1.0)] {
        let p = pdf_n(x, a);
        let approx = (x / a).sqrt() * (-0.5 * (x - a) * (x - a)).exp() / (2.0 * PI).sqrt();
        assert!((p - approx).abs() < 1e-6 * approx, "{p} vs {approx}");
    }
}

/// No overflow, NaN or panic on a grid of P / sigma from 0 to 1e4.
#[test]
fn no_nan_on_grid() {
    let mut xs = vec![0.0, 1e-12, 1.0, SQRT_2, 2.0];
    xs.extend((0..=40).map(|i| 10f64.powf(-3.0 + i as f64 * 7.0 / 40.0)));
    for &x in &xs {
        for &a in &[0.0, 0.01, 1.0, 3.0, 30.0, x, 1e4] {
            for v in [pdf_n(x, a), ln_pdf_or_zero(x, a), cdf_n(x, a), sf_n(x, a)] {
                assert!(v.is_finite() || v == f64::NEG_INFINITY, "x={x} a={a}: {v}");
            }
            assert!((0.0..=1.0).contains(&cdf_n(x, a)));
        }
        for e in Estimator::ALL {
            let v = e.estimate_p(x * 0.01, 0.01).unwrap().value;
            assert!(v.is_finite() && v >= 0.0, "{e} at x={x}: {v}");
        }
        let m = PolMeasurement::new(0.6 * x, -0.8 * x, 1.0, 2.0).unwrap();
        assert!(Estimator::Mas.estimate(&m).value.is_finite());
        let n = neyman_interval(x, 1.0, ONE_SIGMA).unwrap();
        assert!(n.lo.unwrap().is_finite() && n.hi.is_none_or(|h| h.is_finite()));
        let h = hpd_interval(x, 1.0, 0.95).unwrap();
        assert!(h.lo.unwrap().is_finite() && h.hi.unwrap().is_finite() && h.hi >= h.lo, "x={x}: {h:?}");
        let ad = AngleDist::new(x, 1.0, 0.3).unwrap();
        assert!(ad.pdf(0.3).is_finite() && ad.pdf(1.9).is_finite());
        assert!(ad.half_width(ONE_SIGMA).unwrap().is_finite());
    }
    assert!(Rice::new(-1.0, 1.0).is_err());
    assert!(Rice::new(1.0, 0.0).is_err());
    assert!(Estimator::As.estimate_p(f64::NAN, 1.0).is_err());
    assert!("bogus".parse::<Estimator>().is_err());
}

fn ln_pdf_or_zero(x: f64, a: f64) -> f64 {
    stokes::stats::rice::ln_pdf_n(x, a)
}

/// Wardle & Kronberg: the returned P0 has the observed P as its Rice mode; zero for P <= sigma.
#[test]
fn wk_is_the_rice_mode_inverse() {
    for &x in &[1.001, 1.2, 1.5, 2.0, 3.3, 10.0, 100.0, 1e4] {
        let a = wk_n(x);
        assert!(a > 0.0);
        assert!((mode_n(a) - x).abs() < 1e-10 * x, "x={x}: mode({a}) = {}", mode_n(a));
    }
    for &x in &[0.0, 0.3, 0.999, 1.0] {
        assert_eq!(wk_n(x), 0.0);
        assert_eq!(as_n(x), 0.0);
    }
    assert!((as_n(2.0) - 3f64.sqrt()).abs() < 1e-15);
}

/// Simmons & Stewart ML: the root satisfies a = x I1(xa)/I0(xa), is a likelihood maximum,
/// and is zero for P <= sqrt(2) sigma.
#[test]
fn ml_solves_the_likelihood_equation() {
    use spec_math::cephes64::{i0e, i1e};
    for &x in &[1.4143, 1.5, 2.0, 4.0, 30.0, 1e4] {
        let a = ml_n(x);
        assert!(a > 0.0, "x={x}");
        let rhs = x * i1e(x * a) / i0e(x * a);
        assert!((a - rhs).abs() < 1e-9 * x.max(1.0), "x={x}: {a} vs {rhs}");
        let d = 1e-3 * a.max(1e-3);
        assert!(ln_likelihood_n(x, a) >= ln_likelihood_n(x, a + d));
        assert!(ln_likelihood_n(x, a) >= ln_likelihood_n(x, (a - d).max(0.0)));
    }
    for &x in &[0.0, 0.5, 1.0, 1.41, SQRT_2] {
        assert_eq!(ml_n(x), 0.0, "x={x}");
    }
}

/// MAS (Plaszczynski et al. 2014): P - b^2 (1 - exp(-P^2/b^2)) / (2P) -> P/2 as P -> 0 (true
/// of the formula: 1 - exp(-y) ~ y), -> P - b^2/(2P) at high S/N; b is the noise along the
/// measured direction.
#[test]
fn mas_limits_and_unequal_errors() {
    for &x in &[1e-8, 1e-5, 1e-3, 0.01] {
        assert!((mas_n(x) / x - 0.5).abs() < 0.6 * x * x + 1e-15, "x={x}: {}", mas_n(x) / x);
    }
    assert_eq!(mas_n(0.0), 0.0);
    assert!((mas_n(20.0) - (20.0 - 1.0 / 40.0)).abs() < 1e-15);
    // Pure Q measurement: b = sigma_U.
    let m = PolMeasurement::new(0.03, 0.0, 0.01, 0.02).unwrap();
    assert!((m.b() - 0.02).abs() < 1e-16);
    let e = Estimator::Mas.estimate(&m).value;
    assert!((e - 0.02 * mas_n(1.5)).abs() < 1e-15);
    // Equal errors: b = sigma at any angle.
    let m = PolMeasurement::new(0.03, -0.04, 0.01, 0.01).unwrap();
    assert!((m.b() - 0.01).abs() < 1e-16);
}

/// MP2 = P - sigma^2 / P (zero below sigma), MB at P = 0 is the half-normal mean sqrt(2/pi),
/// PR06 is the paper's law.
#[test]
fn mp2_mb_pr06_closed_forms() {
    assert_eq!(mp2_n(0.9), 0.0);
    assert!((mp2_n(4.0) - 3.75).abs() < 1e-15);
    assert!((mb_n(0.0) - (2.0 / PI).sqrt()).abs() < 1e-12, "{}", mb_n(0.0));
    // At high S/N the posterior mean -> x - 1/(2x)... minus the prior-free shift: within 1e-3.
    assert!((mb_n(50.0) - ml_n(50.0)).abs() < 0.02);
    let x: f64 = 6.0;
    assert!((pr06_n(x) - x * (1.0 - (0.62 / x).powf(1.92))).abs() < 1e-15);
    let e = Estimator::Pr06.estimate_p(0.02, 0.01).unwrap();
    assert!(!e.in_validity_range);
    let e = Estimator::Pr06.estimate_p(0.05, 0.01).unwrap();
    assert!(e.in_validity_range);
    for e in Estimator::ALL {
        assert_eq!(e.name().parse::<Estimator>().unwrap(), e);
    }
}

/// Draw x = |(a, 0) + (n1, n2)| with independent normals: the Rice variate by construction.
fn draw_rice(rng: &mut Xoshiro256PlusPlus, a: f64) -> f64 {
    let z1: f64 = StandardNormal.sample(rng);
    let z2: f64 = StandardNormal.sample(rng);
    (a + z1).hypot(z2)
}

/// Neyman central intervals cover the truth with probability cl (within Monte Carlo error).
#[test]
fn neyman_coverage_by_simulation() {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(42);
    let cl = ONE_SIGMA;
    let n = 1500;
    for &a in &[0.5, 2.0, 6.0] {
        let mut hit = 0;
        for _ in 0..n {
            let x = draw_rice(&mut rng, a);
            let (lo, hi) = neyman_n(x, cl);
            if lo <= a && hi.is_some_and(|h| a <= h) {
                hit += 1;
            }
        }
        let cov = hit as f64 / n as f64;
        let err = (cl * (1.0 - cl) / n as f64).sqrt();
        assert!((cov - cl).abs() < 4.0 * err, "a={a}: coverage {cov} vs {cl} +- {err}");
    }
    // Upper limit only / empty interval at small P.
    let i = neyman_interval(0.8, 1.0, cl).unwrap();
    assert!(i.upper_limit_only && i.hi.is_some() && !i.empty);
    let i = neyman_interval(0.2, 1.0, cl).unwrap();
    assert!(i.empty && i.hi.is_none());
    let i = neyman_interval(5.0, 1.0, cl).unwrap();
    assert!(!i.upper_limit_only && i.lo.unwrap() > 0.0);
}

/// HPD: the posterior mass inside is cl and the density is equal at both ends (or the
/// interval starts at 0 where the posterior peaks at 0).
#[test]
fn hpd_mass_and_equal_density() {
    for &(x, cl) in &[(0.5, 0.6827), (1.0, 0.95), (2.0, 0.6827), (5.0, 0.9), (40.0, 0.6827)] {
        let (l, u) = hpd_n(x, cl);
        let post = |a: f64| (ln_likelihood_n(x, a) - ln_likelihood_n(x, x)).exp();
        let z = simpson(post, 0.0, x + 16.0, 40_000);
        let inside = simpson(post, l, u, 20_000) / z;
        assert!((inside - cl).abs() < 1e-7, "x={x}: mass {inside}");
        if l > 0.0 {
            assert!((post(l) - post(u)).abs() < 1e-7 * post(u), "x={x}");
        } else {
            assert!(post(0.0) >= post(u) * (1.0 - 1e-7));
            assert!(x <= 2.5);
        }
    }
}

/// Angle pdf (Naghizadeh-Khouei & Clarke 1993): normalized to 1e-12 (trapezoid over a full
/// period converges exponentially for this periodic, smooth density); uniform at P0 = 0;
/// Gaussian of width sigma/(2P0) (eq:sigchi) at high S/N.
#[test]
fn angle_pdf_normalized_and_limits() {
    for &eta0 in &[0.0, 0.1, 0.5, 1.0, 2.0, 5.0, 10.0, 50.0, 300.0] {
        let m = 4000 + (100.0 * eta0) as usize;
        let h = PI / m as f64;
        // Compensated (Neumaier) sum so rounding does not mask the 1e-12 test.
        let (mut sum, mut comp) = (0.0f64, 0.0f64);
        for i in 0..m {
            let v = pdf_dev(-FRAC_PI_2 + i as f64 * h, eta0);
            let t = sum + v;
            comp += if sum.abs() >= v.abs() { (sum - t) + v } else { (v - t) + sum };
            sum = t;
        }
        let s = (sum + comp) * h;
        assert!((s - 1.0).abs() < 1e-12, "eta0={eta0}: {s}");
        assert!((mass_within(FRAC_PI_2, eta0) - 1.0).abs() < 1e-12, "eta0={eta0}");
    }
    assert!((pdf_dev(0.7, 0.0) - 1.0 / PI).abs() < 1e-16);
    assert!((half_width(ONE_SIGMA, 0.0) - ONE_SIGMA * FRAC_PI_2).abs() < 1e-12);
    let eta0 = 2000.0;
    assert!((half_width(ONE_SIGMA, eta0) - 0.5 / eta0).abs() < 1e-3 * 0.5 / eta0);
    // Simulated angles: the fraction within the half-width is cl.
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(5);
    let (a, n) = (1.3, 40_000);
    let hw = half_width(ONE_SIGMA, a);
    let mut hit = 0;
    for _ in 0..n {
        let z1: f64 = StandardNormal.sample(&mut rng);
        let z2: f64 = StandardNormal.sample(&mut rng);
        let th = 0.5 * z2.atan2(a + z1);
        if th.abs() <= hw {
            hit += 1;
        }
    }
    let f = hit as f64 / n as f64;
    assert!((f - ONE_SIGMA).abs() < 4.0 * (ONE_SIGMA * (1.0 - ONE_SIGMA) / n as f64).sqrt(), "{f}");
}

/// SNR -> infinity: every estimator tends to `P` (each is `P (1 - O(sigma^2 / P^2))`), and it
/// must reach it, not overflow: at `P / sigma` = 1e7 the closed form `sqrt(x^2 - 1)` of AS is
/// within 1e-14 relative of each estimator; beyond (1e9, 1e200, 1e298: `--sigma 1e-300` gave
/// NaN for six estimators and 0 for ML) every one returns `P` itself, in its validity range.
#[test]
fn every_estimator_reaches_p_at_infinite_snr() {
    let p = 0.01;
    for e in Estimator::ALL {
        let x = 1e7;
        let v = e.estimate_p(p, p / x).unwrap().value;
        let want = p * ((x - 1.0) * (x + 1.0)).sqrt() / x;
        assert!(((v - want) / want).abs() < 1e-14, "{e} at x = {x}: {v} vs {want}");
        for x in [1e9, 1e200, 1e298] {
            let r = e.estimate_p(p, p / x).unwrap();
            assert!(r.value == p && r.in_validity_range, "{e} at x = {x}: {r:?}");
        }
    }
}
