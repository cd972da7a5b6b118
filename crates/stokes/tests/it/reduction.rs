//! The reduction of one source checked against the paper (Patat & Romaniello 2006) with the
//! `mueller` forward model as the independent generator of the fluxes.
//!
//! HWP circular sign convention relied on (retardance test): the `mueller` crate's retarder
//! (IAU V, fast axis at the commanded angle) puts `+V sin 2theta_i sin(Delta beta)` into `F_i`,
//! the sign printed in section `sec:HWP`.

use approx::assert_relative_eq;
use mueller::{
    optimal_angles, post_analyzer, stokes_p_chi, stokes_qu, DualBeam, Element, Harmonic as Defect, Hwp, Stokes,
    Wollaston,
};
use std::f64::consts::PI;
use stokes::{reduce, Error, Estimator, Measurement, Reduction, StokesSolver, Warning};

/// Noiseless fluxes of `train` for Stokes vector `s` (its `I` in electrons) at `theta`.
fn measure(train: &DualBeam, s: &Stokes, theta: &[f64]) -> Measurement {
    let fl = train.fluxes(s, theta);
    Measurement::poisson(theta.to_vec(), fl.iter().map(|b| b.f_o).collect(), fl.iter().map(|b| b.f_e).collect())
        .unwrap()
}

fn reduce_train(train: &DualBeam, s: &Stokes, theta: &[f64]) -> Reduction {
    reduce(&measure(train, s, theta)).unwrap()
}

fn with_t(t: f64) -> DualBeam {
    DualBeam { wollaston: Wollaston::with_t(t), ..Default::default() }
}

fn two_angles() -> Vec<f64> {
    vec![0.0, PI / 8.0]
}

// ---------------------------------------------------------------- eq:Q, eq:U, eq:sigp

/// eq:Q / eq:U: on the optimal set the reduction (Fourier sums) equals an independent
/// least-squares solution of eq:system (normal equations solved here by Cramer's rule).
#[test]
fn eq_q_eq_u_equal_least_squares_on_optimal_set() {
    for n in [4usize, 8, 12, 16] {
        let th = optimal_angles(n);
        // Arbitrary F (not a pure cosinusoid), made from fluxes.
        let f: Vec<f64> = (0..n).map(|i| 0.013 * (1.7 * i as f64).sin() + 0.004 * (i as f64).cos() + 0.002).collect();
        let f_o: Vec<f64> = f.iter().map(|x| 5e5 * (1.0 + x)).collect();
        let f_e: Vec<f64> = f.iter().map(|x| 5e5 * (1.0 - x)).collect();
        let r = reduce(&Measurement::poisson(th.clone(), f_o, f_e).unwrap()).unwrap();
        assert_eq!(r.estimator, Estimator::FourierSums);
        let (mut a, mut b, mut c, mut rq, mut ru) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for i in 0..n {
            let (s4, c4) = (4.0 * th[i]).sin_cos();
            a += c4 * c4;
            b += c4 * s4;
            c += s4 * s4;
            rq += c4 * r.f[i];
            ru += s4 * r.f[i];
        }
        let det = a * c - b * b;
        assert_relative_eq!(r.qu.q, (c * rq - b * ru) / det, epsilon = 1e-15);
        assert_relative_eq!(r.qu.u, (a * ru - b * rq) / det, epsilon = 1e-15);
        // And the printed sums themselves.
        let q: f64 = (0..n).map(|i| r.f[i] * (PI / 2.0 * i as f64).cos()).sum::<f64>() * 2.0 / n as f64;
        let u: f64 = (0..n).map(|i| r.f[i] * (PI / 2.0 * i as f64).sin()).sum::<f64>() * 2.0 / n as f64;
        assert_relative_eq!(r.qu.q, q, epsilon = 1e-15);
        assert_relative_eq!(r.qu.u, u, epsilon = 1e-15);
        // a_{N/4} = Q/I, b_{N/4} = U/I (section sec:HWP).
        assert_relative_eq!(r.fourier[n / 4].a, r.qu.q, epsilon = 1e-15);
        assert_relative_eq!(r.fourier[n / 4].b, r.qu.u, epsilon = 1e-15);
    }
}

/// eq:sigp: sigma_P = 1/(sqrt(N/2) SNR) with SNR that of the intensity image (Poisson counts:
/// sqrt(f_O + f_E)); the error propagated from the per-beam Poisson errors agrees to O(P^2)
/// (sigma_F^2 = (1 - F^2)/I exactly), and eq:sigchi = sigma_P/(2P).
#[test]
fn eq_sigp_and_eq_sigchi_for_poisson_counts() {
    let i0 = 1600.0f64 * 1600.0;
    let (p0, chi0) = (0.01, 0.4);
    for n in [4usize, 8, 16] {
        let r = reduce_train(&DualBeam::ideal(), &stokes_p_chi(i0, p0, chi0), &optimal_angles(n));
        let expected = 1.0 / ((n as f64 / 2.0).sqrt() * 1600.0);
        assert_relative_eq!(r.snr, 1600.0, max_relative = 1e-12);
        assert_relative_eq!(r.sigma_p_analytic, expected, max_relative = 1e-12);
        assert_relative_eq!(r.sigma_p, expected, max_relative = p0 * p0);
        assert!(r.sigma_p < expected, "(1 - F^2) makes the propagated error slightly smaller");
        assert_relative_eq!(r.sigma_chi_analytic, expected / (2.0 * p0), max_relative = 1e-9);
        assert_relative_eq!(r.sigma_chi, r.sigma_chi_analytic, max_relative = 2.0 * p0 * p0);
        // The same numbers when the per-beam errors are given explicitly as sqrt(f).
        let m = measure(&DualBeam::ideal(), &stokes_p_chi(i0, p0, chi0), &optimal_angles(n));
        let so: Vec<f64> = m.f_o().iter().map(|x| x.sqrt()).collect();
        let se: Vec<f64> = m.f_e().iter().map(|x| x.sqrt()).collect();
        let r2 =
            reduce(&Measurement::with_errors(m.theta().to_vec(), m.f_o().to_vec(), m.f_e().to_vec(), so, se).unwrap())
                .unwrap();
        assert_relative_eq!(r2.sigma_p, r.sigma_p, max_relative = 1e-14);
        // Exact propagation: var(Q) = (2/N)^2 sum cos^2(pi i/2) (1 - F_i^2)/I.
        let vq: f64 = (0..n).map(|i| (PI / 2.0 * i as f64).cos().powi(2) * (1.0 - r.f[i] * r.f[i]) / i0).sum::<f64>()
            * (2.0 / n as f64).powi(2);
        assert_relative_eq!(r.qu.var_q, vq, max_relative = 1e-12);
    }
}

/// eq:sigp for a plate that turns through 22.5 deg during each exposure: every F_i keeps
/// sin(2d)/(2d) = 0.9003 of the modulation, so the analytic error is the fixed plate's divided
/// by it (it was the fixed plate's, 10 % too small), and agrees with the error propagated
/// through the solver with the averaged modulation as for a fixed plate (to O(P^2)).
#[test]
fn eq_sigp_with_a_turning_plate() {
    let i0 = 1600.0f64 * 1600.0;
    let (p0, chi0) = (0.01, 0.4);
    let d = 22.5f64.to_radians();
    let e = (2.0 * d).sin() / (2.0 * d);
    assert_relative_eq!(e, 0.9003, max_relative = 1e-4);
    for n in [4usize, 16] {
        let m = measure(&DualBeam::ideal(), &stokes_p_chi(i0, p0, chi0), &optimal_angles(n));
        let r = reduce(&m.with_sweeps(vec![d; n]).unwrap()).unwrap();
        let fixed = 1.0 / ((n as f64 / 2.0).sqrt() * 1600.0);
        assert_relative_eq!(r.sigma_p_analytic, fixed / e, max_relative = 1e-12);
        assert_relative_eq!(r.sigma_p, r.sigma_p_analytic, max_relative = 2.0 * p0);
    }
}

// ---------------------------------------------------------------- Wollaston (sec:wollaston)

/// sec:wollaston: unpolarized light gives F_i = 2t - 1; N = 2 gives the spurious
/// P = sqrt(2)(2t - 1) at chi = pi/8 (for t > 1/2; 5pi/8 for t < 1/2, same line, other sign),
/// while N = 4 gives exactly zero.
#[test]
fn wp_imbalance_n2_spurious_n4_zero() {
    for t in [0.55, 0.45, 0.502] {
        let s = stokes_qu(1e6, 0.0, 0.0);
        let r2 = reduce_train(&with_t(t), &s, &two_angles());
        for &f in &r2.f {
            assert_relative_eq!(f, 2.0 * t - 1.0, epsilon = 1e-15);
        }
        assert_relative_eq!(r2.p, 2f64.sqrt() * (2.0 * t - 1.0).abs(), max_relative = 1e-12);
        let chi = if t > 0.5 { PI / 8.0 } else { 5.0 * PI / 8.0 };
        assert_relative_eq!(r2.chi, chi, epsilon = 1e-12);
        assert!(r2.warnings.contains(&Warning::TwoAngles));
        let r4 = reduce_train(&with_t(t), &s, &optimal_angles(4));
        assert!(r4.p < 1e-16, "N = 4: P = {}", r4.p);
        // eq:a0: the average of the F is kappa.
        assert_relative_eq!(r4.a0, 2.0 * t - 1.0, epsilon = 1e-15);
    }
}

/// eq:g, eq:kappa2: kappa recovered exactly (noiseless) from the g_j for t = 0.45 and 0.55 at
/// P0 = 0.05, for every estimate (j = 1..N-2) and for N = 4, 8, 16; and for s != 1 - t
/// (kappa = (t - s)/(t + s)).
#[test]
fn kappa_from_g_recovers_t() {
    for (t, s_) in [(0.45, 0.55), (0.55, 0.45), (0.47, 0.58)] {
        let train = DualBeam { wollaston: Wollaston { t, s: s_, delta_alpha: 0.0 }, ..Default::default() };
        let kappa = (t - s_) / (t + s_);
        for n in [4usize, 8, 16] {
            let r = reduce_train(&train, &stokes_p_chi(1e6, 0.05, 0.3), &optimal_angles(n));
            assert_eq!(r.kappa.len(), n - 2, "j = 1..N-2");
            for e in &r.kappa {
                assert!(!e.clamped);
                assert_relative_eq!(e.kappa, kappa, max_relative = 1e-12);
                assert_relative_eq!(e.g, (1.0 + kappa * kappa) / (2.0 * kappa), max_relative = 1e-12);
            }
            assert_relative_eq!(r.kappa_mean.unwrap(), kappa, max_relative = 1e-12);
            // Correcting the fluxes for the recovered kappa gives the input back exactly.
            let m = measure(&train, &stokes_p_chi(1e6, 0.05, 0.3), &optimal_angles(n));
            let rc = reduce(&m.corrected_for_kappa(r.kappa_mean.unwrap()).unwrap()).unwrap();
            assert_relative_eq!(rc.p, 0.05, max_relative = 1e-12);
            assert_relative_eq!(rc.chi, 0.3, epsilon = 1e-12);
            assert!(rc.a0.abs() < 1e-15);
        }
    }
}

/// sec:wollaston: the blind N = 4 result is Q (1 - kappa^2)/(1 - kappa^2 Q^2) (Q only, U = 0).
/// The general case (U != 0) follows from the same pair algebra, component by component,
/// and holds for every N multiple of 4: checked numerically.
#[test]
fn blind_n4_attenuation() {
    for t in [0.45, 0.55, 0.7] {
        let kappa = 2.0 * t - 1.0;
        let k2 = kappa * kappa;
        for q in [0.05, 0.5, -0.3] {
            let r = reduce_train(&with_t(t), &stokes_qu(1e6, q, 0.0), &optimal_angles(4));
            assert_relative_eq!(r.qu.q, q * (1.0 - k2) / (1.0 - k2 * q * q), max_relative = 1e-12);
            assert!(r.qu.u.abs() < 1e-15);
        }
        let (q, u) = (0.3, -0.2);
        for n in [4usize, 8, 16] {
            let r = reduce_train(&with_t(t), &stokes_qu(1e6, q, u), &optimal_angles(n));
            assert_relative_eq!(r.qu.q, q * (1.0 - k2) / (1.0 - k2 * q * q), max_relative = 1e-12);
            assert_relative_eq!(r.qu.u, u * (1.0 - k2) / (1.0 - k2 * u * u), max_relative = 1e-12);
        }
    }
}

/// sec:wollaston, non-orthogonal beams: F_i ~ (m(theta) + m(theta - Delta alpha/2))/2 makes
/// the measured polarization P cos(Delta alpha) at chi - Delta alpha/2, whatever N. The
/// paper's "0.05% on P and 5 deg on chi" for Delta alpha = 10 deg: the angle error is
/// Delta alpha/2 = 5 deg exactly; the P error is relative, 1 - cos 10 deg = 1.5% of P, i.e.
/// 0.05% absolute for P ~ 3% (and 0.015% for P = 1%): the paper's number is for P of a few %.
#[test]
fn wollaston_non_orthogonality() {
    let da = 10f64.to_radians();
    let train = DualBeam { wollaston: Wollaston { t: 0.5, s: 0.5, delta_alpha: da }, ..Default::default() };
    for n in [4usize, 16] {
        let (p0, chi0) = (0.033, 1.0);
        let r = reduce_train(&train, &stokes_p_chi(1e6, p0, chi0), &optimal_angles(n));
        assert_relative_eq!(r.p, p0 * da.cos(), max_relative = 2e-3);
        let dp = p0 - r.p;
        assert!(dp > 3e-4 && dp < 8e-4, "N = {n}: Delta P = {dp}: order 0.05%");
        let dchi = (r.chi - chi0).to_degrees();
        assert!((dchi.abs() - 5.0).abs() < 0.1, "N = {n}: Delta chi = {dchi} deg");
    }
}

// ---------------------------------------------------------------- post-analyzer (sec:postwp)

/// sec:postwp: the post-analyzer term B cos 2phi appears as a_0 (and, exactly, as kappa:
/// the first row of M_PA gives F = (B cos 2phi + m)/(1 + B cos 2phi m)), spoils N = 2 at
/// first order and cancels for N >= 4 (to second order, as the Wollaston kappa does).
#[test]
fn post_analyzer_is_a0_and_cancels_for_n4() {
    let (b, phi) = (0.01f64, 0.3f64);
    let bc = b * (2.0 * phi).cos();
    let train = DualBeam { post: Some(post_analyzer(1.0, b, 0.98, phi)), ..Default::default() };
    let (q, u) = (0.02, 0.01);
    let s = stokes_qu(1e6, q, u);
    let r2 = reduce_train(&train, &s, &two_angles());
    assert!((r2.qu.q - q - bc).abs() < 1e-5 && (r2.qu.u - u - bc).abs() < 1e-5, "N = 2 shifted by B cos 2phi");
    for n in [4usize, 8, 16] {
        let r = reduce_train(&train, &s, &optimal_angles(n));
        assert_relative_eq!(r.a0, bc, max_relative = 1e-3);
        assert_relative_eq!(r.kappa_mean.unwrap(), bc, max_relative = 1e-12);
        assert!((r.qu.q - q).abs() < 2.0 * bc * bc * q && (r.qu.u - u).abs() < 2.0 * bc * bc * u);
    }
}

// ---------------------------------------------------------------- HWP (sec:HWP)

fn n16_harmonics(hwp: Hwp, s: &Stokes) -> Vec<stokes::fourier::Harmonic> {
    let train = DualBeam { hwp, ..Default::default() };
    reduce_train(&train, s, &optimal_angles(16)).fourier
}

/// sec:HWP: dust (k = 1) and pleochroism (k = 2) show up as exactly those harmonics of the
/// N = 16 power spectrum. Alone, on unpolarized light, each defect is a pure harmonic and
/// everything else is zero to rounding. Together, and on a polarized source, the (physical)
/// cross terms put A1*A2 and A*P (~1e-6 here) into k = 1, 3, 5, ...: far below the 5e-4
/// harmonics, and k = 4 still gives Q, U.
#[test]
fn hwp_dust_and_pleochroism_harmonics() {
    let (a1, ph1, a2, ph2) = (5e-4, 0.7, 5e-4, -1.1);
    let dust = Some(Defect { amplitude: a1, phase: ph1 });
    let pleo = Some(Defect { amplitude: a2, phase: ph2 });
    let unpol = stokes_qu(1e6, 0.0, 0.0);

    let h = n16_harmonics(Hwp { dust, ..Hwp::ideal() }, &unpol);
    assert_relative_eq!(h[1].a, a1 * ph1.cos(), max_relative = 1e-9);
    assert_relative_eq!(h[1].b, a1 * ph1.sin(), max_relative = 1e-9);
    for hk in h.iter().filter(|x| x.k != 1) {
        assert!(hk.amplitude() < 1e-15, "dust alone: k = {} amplitude {}", hk.k, hk.amplitude());
    }
    let h = n16_harmonics(Hwp { pleochroism: pleo, ..Hwp::ideal() }, &unpol);
    assert_relative_eq!(h[2].power(), a2 * a2, max_relative = 1e-9);
    for hk in h.iter().filter(|x| x.k != 2) {
        assert!(hk.amplitude() < 1e-15, "pleochroism alone: k = {} amplitude {}", hk.k, hk.amplitude());
    }

    // Both, on a FORS1-like 0.4% polarized source.
    let (q, u) = (0.004 * 0.5f64.cos(), 0.004 * 0.5f64.sin());
    let h = n16_harmonics(Hwp { dust, pleochroism: pleo, ..Hwp::ideal() }, &stokes_qu(1e6, q, u));
    assert_relative_eq!(h[1].power(), a1 * a1, max_relative = 0.02);
    assert_relative_eq!(h[2].power(), a2 * a2, max_relative = 0.02);
    assert_relative_eq!(h[4].a, q, max_relative = 1e-3);
    assert_relative_eq!(h[4].b, u, max_relative = 1e-3);
    for k in [3usize, 5, 6, 7, 8] {
        assert!(h[k].amplitude() < 5e-6, "k = {k}: amplitude {}", h[k].amplitude());
    }
}

/// sec:HWP: a retardance error Delta beta = 10 deg with Q = U = V = 0.01 gives about 0.1%
/// error on P for N = 4 and about 0.01% for N = 16.
///
/// From the Mueller algebra (the paper's printed F_i has the wrong sign on its
/// sin^2 2theta (1 - cos Delta beta) term: a plate with zero retardance must act as the
/// identity): F_i = Q [cos 4theta + sin^2 2theta (1 - cos db)] + U sin 4theta (1 + cos db)/2
/// plus sigma V sin 2theta sin db. The sign sigma of the V term depends on the circular
/// convention: with the `mueller` retarder (IAU V, documented there) it is -1, the paper
/// prints +1 without stating its convention; so both signs of V are checked. N = 16 gives
/// exactly P (1 + cos db)/2 (the V term cancels over the full turn: 0.011%); for N = 4 the V
/// term survives in Q as sigma V sin(db)/2, giving |Delta P| = 0.05% or 0.07% depending on
/// the relative sign: "about 0.1%" in the paper's rounding. With V = 0 and db <= 10 deg the
/// error is below 0.05% (paper).
#[test]
fn retardance_error_paper_numbers() {
    let db = 10f64.to_radians();
    let hwp = Hwp { retardance_error: db, ..Hwp::ideal() };
    let train = DualBeam { hwp, ..Default::default() };
    let p0 = 0.01 * 2f64.sqrt();
    for v in [0.01, -0.01] {
        let s = Stokes::new(1e6, 0.01e6, 0.01e6, v * 1e6);
        let r4 = reduce_train(&train, &s, &optimal_angles(4));
        let d4 = (r4.p - p0).abs();
        assert!(d4 > 0.4e-3 && d4 < 1.5e-3, "N = 4, V = {v}: |Delta P| = {d4}, paper: about 0.1%");
        // Q carries the V term (theta = 45 deg position), U does not.
        assert_relative_eq!(
            (r4.qu.q - 0.01 * (1.0 + db.cos()) / 2.0).abs(),
            0.01 * db.sin() / 2.0,
            max_relative = 1e-9
        );
        assert_relative_eq!(r4.qu.u, 0.01 * (1.0 + db.cos()) / 2.0, max_relative = 1e-9);
        let r16 = reduce_train(&train, &s, &optimal_angles(16));
        let d16 = (r16.p - p0).abs();
        assert!(d16 > 0.5e-4 && d16 < 1.5e-4, "N = 16: |Delta P| = {d16}, paper: about 0.01%");
        assert_relative_eq!(r16.p, p0 * (1.0 + db.cos()) / 2.0, max_relative = 1e-9);
    }
    // V = 0: below 0.05%.
    for n in [4usize, 16] {
        let r = reduce_train(&train, &stokes_qu(1e6, 0.05, 0.03), &optimal_angles(n));
        assert!((r.p - 0.05f64.hypot(0.03)).abs() < 5e-4);
    }
}

// ---------------------------------------------------------------- hard cases

/// P = 0: chi reported (finite, in [0, pi)), flagged undefined, sigma_chi infinite.
#[test]
fn zero_polarization_flags_chi() {
    // Ideal prism: F = 0 exactly, P = 0 exactly.
    let r = reduce_train(&DualBeam::ideal(), &stokes_qu(1e6, 0.0, 0.0), &optimal_angles(8));
    assert_eq!(r.p, 0.0);
    assert!(!r.chi_defined && r.warnings.contains(&Warning::ChiUndefined));
    // Imbalanced prism: the F are equal only to rounding, P ~ 1e-18: still "zero".
    let r = reduce_train(&with_t(0.52), &stokes_qu(1e6, 0.0, 0.0), &optimal_angles(8));
    assert!(r.p < 1e-16);
    assert!(!r.chi_defined && r.chi.is_finite() && (0.0..PI).contains(&r.chi));
    assert!(r.sigma_chi.is_infinite() && r.sigma_chi_analytic.is_infinite());
    assert!(r.sigma_p.is_finite() && r.sigma_p > 0.0);
    assert!(r.warnings.contains(&Warning::ChiUndefined));
    assert!(r.kappa.iter().all(|e| e.kappa.is_finite()));
}

/// kappa -> 0 (g -> infinity) stays accurate; F_{j-1} + F_{j+1} = 0 exactly gives kappa = 0,
/// g infinite, no NaN anywhere.
#[test]
fn kappa_to_zero_and_exact_cancellation() {
    for dt in [1e-4, 1e-7, 1e-10] {
        let r = reduce_train(&with_t(0.5 + dt), &stokes_p_chi(1e6, 0.05, 0.2), &optimal_angles(8));
        // F carries ~1e-16 absolute rounding: kappa is good to that absolute level.
        for e in &r.kappa {
            assert!((e.kappa - 2.0 * dt).abs() < 1e-14 + 1e-9 * dt, "dt = {dt}: kappa = {}", e.kappa);
        }
    }
    let (q, u) = (0.02, -0.01);
    let f_o = vec![1.0 + q, 1.0 + u, 1.0 - q, 1.0 - u];
    let f_e = vec![1.0 - q, 1.0 - u, 1.0 + q, 1.0 + u];
    let r = reduce(&Measurement::poisson(optimal_angles(4), f_o, f_e).unwrap()).unwrap();
    for e in &r.kappa {
        assert!(e.g.is_infinite());
        assert_eq!(e.kappa, 0.0);
    }
    assert_eq!(r.kappa_mean, Some(0.0));
    assert_relative_eq!(r.qu.q, q, epsilon = 1e-16);
}

/// SNR = 1e7 (I = 1e14 e-): errors follow eq:sigp and the values stay exact.
#[test]
fn snr_1e7() {
    let r = reduce_train(&with_t(0.502), &stokes_p_chi(1e14, 0.004, 0.8), &optimal_angles(16));
    assert_relative_eq!(r.sigma_p_analytic, 1.0 / (8f64.sqrt() * 1e7), max_relative = 1e-12);
    assert_relative_eq!(r.kappa_mean.unwrap(), 0.004, max_relative = 1e-10);
    // The blind attenuation of sec:wollaston, component by component.
    let k2 = 0.004f64 * 0.004;
    let (q, u) = (0.004 * 1.6f64.cos(), 0.004 * 1.6f64.sin());
    assert_relative_eq!(r.qu.q, q * (1.0 - k2) / (1.0 - k2 * q * q), max_relative = 1e-9);
    assert_relative_eq!(r.qu.u, u * (1.0 - k2) / (1.0 - k2 * u * u), max_relative = 1e-9);
}

/// Single-precision-like inputs (fluxes rounded to f32, ~6e-8 relative): results move by
/// no more than that rounding propagated (~1e-7 absolute in F).
#[test]
fn single_precision_inputs() {
    let th = optimal_angles(16);
    let train = with_t(0.502);
    let m = measure(&train, &stokes_p_chi(2.56e6, 0.004, 0.8), &th);
    let f_o: Vec<f64> = m.f_o().iter().map(|&x| x as f32 as f64).collect();
    let f_e: Vec<f64> = m.f_e().iter().map(|&x| x as f32 as f64).collect();
    let r32 = reduce(&Measurement::poisson(th.clone(), f_o, f_e).unwrap()).unwrap();
    let r64 = reduce(&m).unwrap();
    assert!((r32.qu.q - r64.qu.q).abs() < 1e-7 && (r32.qu.u - r64.qu.u).abs() < 1e-7);
    assert!((r32.kappa_mean.unwrap() - r64.kappa_mean.unwrap()).abs() < 1e-7);
    assert!((r32.chi - r64.chi).abs() < 1e-4);
    assert!(r32.fourier.iter().all(|h| h.a.is_finite() && h.b.is_finite()));
}

/// kappa -> +-1: one beam almost (or fully) dark. The estimates stay in [-1, 1], finite, and
/// the correction for the recovered kappa gives the input back.
#[test]
fn kappa_edges() {
    for t in [0.999, 0.001, 0.99999] {
        let kappa = 2.0 * t - 1.0;
        let m = measure(&with_t(t), &stokes_p_chi(1e6, 0.05, 0.3), &optimal_angles(4));
        let r = reduce(&m).unwrap();
        assert_relative_eq!(r.kappa_mean.unwrap(), kappa, max_relative = 1e-9);
        let rc = reduce(&m.corrected_for_kappa(r.kappa_mean.unwrap()).unwrap()).unwrap();
        assert_relative_eq!(rc.p, 0.05, max_relative = 1e-6);
    }
    // A completely dark extraordinary beam: F = 1, kappa = 1, P = 0, nothing NaN.
    for t in [1.0, 0.0] {
        let r = reduce_train(&with_t(t), &stokes_p_chi(1e6, 0.05, 0.3), &optimal_angles(4));
        assert_eq!(r.kappa_mean, Some(2.0 * t - 1.0));
        assert!(r.p < 1e-15 && !r.chi_defined);
        assert!(r.sigma_p.is_finite() && r.a0.is_finite());
    }
}

// ---------------------------------------------------------------- angle sets, warnings

/// Missing angle and uneven errors: weighted least squares recovers noiseless Q, U exactly,
/// Fourier analysis is skipped with a warning; N = 2 works.
#[test]
fn non_optimal_sets() {
    let (q, u) = (0.02, -0.03);
    let mut th = optimal_angles(16);
    th.remove(5);
    let m = measure(&DualBeam::ideal(), &stokes_qu(1e6, q, u), &th);
    // Uneven errors: every other exposure twice as noisy.
    let so: Vec<f64> = (0..th.len()).map(|i| 700.0 * (1.0 + (i % 2) as f64)).collect();
    let r = reduce(&Measurement::with_errors(th.clone(), m.f_o().to_vec(), m.f_e().to_vec(), so.clone(), so).unwrap())
        .unwrap();
    assert_eq!(r.estimator, Estimator::WeightedLeastSquares);
    assert_relative_eq!(r.qu.q, q, epsilon = 1e-15);
    assert_relative_eq!(r.qu.u, u, epsilon = 1e-15);
    assert!(r.fourier.is_empty());
    assert!(r.warnings.contains(&Warning::FourierSkipped { n: 15 }));
    assert_eq!(r.kappa.len(), 15 - 2 - 2, "the two triples around the gap are not pi/4 pairs");

    let r = reduce_train(&DualBeam::ideal(), &stokes_qu(1e6, q, u), &two_angles());
    assert_relative_eq!(r.qu.q, q, epsilon = 1e-15);
    assert!(r.kappa.is_empty() && r.kappa_mean.is_none());
    assert!(r.warnings.contains(&Warning::KappaNeedsFour { n: 2 }));
    // The solver's checks are the reduction's checks.
    assert!(matches!(
        Measurement::poisson(vec![0.0, PI / 8.0, PI / 8.0], vec![1.0; 3], vec![1.0; 3]),
        Err(Error::DuplicateAngle { first: 1, second: 2, .. })
    ));
    assert!(StokesSolver::new(&th).is_ok());
}

/// A telescope-like pre-optics partial polarizer M_I(p, phi) (sec:instr) on an unpolarized
/// star is measured as P = p, chi = phi (FORS1's 0.4% of fig:fourier).
#[test]
fn instrumental_partial_polarizer_is_measured() {
    let train = DualBeam { pre: vec![Element::PartialPolarizer { p: 0.004, phi: 1.2 }], ..Default::default() };
    let r = reduce_train(&train, &stokes_qu(1e6, 0.0, 0.0), &optimal_angles(16));
    assert_relative_eq!(r.p, 0.004, max_relative = 1e-12);
    assert_relative_eq!(r.chi, 1.2, epsilon = 1e-12);
}

/// kappa estimated and applied in one run (`KappaCorrection::FromData`): with the Wollaston's
/// beams transmitting t and s (fluxes written here in closed form, not through `mueller`),
/// the estimate is (t - s)/(t + s) exactly on noiseless data and q, u come back exactly, where
/// the uncorrected reduction carries the second-order term of `F = (kappa + m)/(1 + kappa m)`.
/// A known kappa gives the same numbers; two angles cannot give kappa and are refused.
#[test]
fn kappa_from_the_data_is_applied_in_the_same_run() {
    use stokes::KappaCorrection;
    let (t, s) = (1.06, 0.94);
    let kappa = (t - s) / (t + s);
    let (q, u) = (0.04, -0.03);
    let theta: Vec<f64> = (0..8).map(|i| i as f64 * PI / 8.0).collect();
    let m = |th: f64| q * (4.0 * th).cos() + u * (4.0 * th).sin();
    let f_o: Vec<f64> = theta.iter().map(|&th| 5e5 * t * (1.0 + m(th))).collect();
    let f_e: Vec<f64> = theta.iter().map(|&th| 5e5 * s * (1.0 - m(th))).collect();
    let meas = Measurement::poisson(theta.clone(), f_o.clone(), f_e.clone()).unwrap();
    let (plain, none) = meas.reduce_with(KappaCorrection::None).unwrap();
    assert_eq!(none, None);
    let off = (plain.qu.q - q).abs().max((plain.qu.u - u).abs());
    assert!(off > 1e-5, "the uncorrected reduction should show kappa's second-order term, off by {off:e}");
    let (r, applied) = meas.reduce_with(KappaCorrection::FromData).unwrap();
    assert_relative_eq!(applied.unwrap(), kappa, max_relative = 1e-12);
    assert!((r.qu.q - q).abs() < 1e-13 && (r.qu.u - u).abs() < 1e-13, "{} {}", r.qu.q, r.qu.u);
    let (k, _) = meas.reduce_with(KappaCorrection::Known(kappa)).unwrap();
    assert_relative_eq!(k.qu.q, r.qu.q, max_relative = 1e-12);
    let two = Measurement::poisson(theta[..2].to_vec(), f_o[..2].to_vec(), f_e[..2].to_vec()).unwrap();
    match two.reduce_with(KappaCorrection::FromData) {
        Err(Error::KappaNotEstimable(why)) => assert!(why.contains("N >= 4"), "{why}"),
        other => panic!("two angles gave {other:?}"),
    }
}

/// Beams dark at some HWP angles (zero counts, so zero Poisson error): F = +-1 there, and the
/// four angles give q = u = 1, P = 141 % with no error. Light cannot be more than
/// fully polarized (eq:poldeg): refused, naming the dark beam; a dark beam at every angle
/// (the kappa edge above) still reduces.
#[test]
fn more_than_fully_polarized_is_refused() {
    let theta = optimal_angles(4);
    let m = Measurement::poisson(theta, vec![1e4, 1e4, 0.0, 0.0], vec![0.0, 0.0, 1e4, 1e4]).unwrap();
    let e = reduce(&m).unwrap_err();
    assert!(matches!(e, Error::MoreThanFullyPolarized { dark_beam: Some(0), .. }), "{e}");
    assert!(e.to_string().contains("index 0"), "{e}");
}

/// Degrees that look like radians are refused by the one check every entry point calls,
/// saying what they were and what they would span; a degree set is accepted.
#[test]
fn degrees_that_look_like_radians() {
    let e = stokes::check_degrees(&[0.0, 0.39, 0.79, 1.18]).unwrap_err().to_string();
    assert!(e.contains("[0.0, 0.39, 0.79, 1.18]") && e.contains("span only 1.18 deg"), "{e}");
    assert!(stokes::check_degrees(&[0.0, 22.5, 45.0, 67.5]).is_ok());
}

/// The telescope chain's forward model (`mueller::telescope::Demodulation`: each exposure's
/// matrix before the plate, the plate at its angle) holds for a plate that turns during each
/// exposure, as the reduction takes it (its F_i divided by the sweep's efficiency,
/// `Measurement::with_sweeps`): the exposure's fluxes integrate the fixed plate's over its
/// range (2000 midpoint steps here, not the closed form), and reduced they give the
/// demodulation at the middle angles. 16 exposures over 22.5 deg each, each through its own
/// matrix (a retarder and a partial polarizer turning from exposure to exposure, as a
/// telescope's mirror does with the parallactic angle).
#[test]
fn the_chain_forward_model_holds_for_a_turning_plate() {
    use mueller::telescope::Demodulation;
    let train = DualBeam::ideal();
    let d = 22.5f64.to_radians();
    let (q0, u0) = (0.015, -0.008);
    let sky = Stokes::new(1e6, 1e6 * q0, 1e6 * u0, 0.0);
    let theta = optimal_angles(16);
    let mats: Vec<mueller::Mueller> = (0..16)
        .map(|k| mueller::retarder(0.3, 0.1 * k as f64) * mueller::partial_polarizer(0.02, 0.3 + 0.05 * k as f64))
        .collect();
    let steps = 2000;
    let (mut fo, mut fe) = (vec![], vec![]);
    for (k, &t) in theta.iter().enumerate() {
        let s = mats[k] * sky;
        let (mut so, mut se) = (0.0, 0.0);
        for j in 0..steps {
            let a = t - 0.5 * d + d * (j as f64 + 0.5) / steps as f64;
            let b = train.fluxes(&s, &[a])[0];
            so += b.f_o;
            se += b.f_e;
        }
        fo.push(so / steps as f64);
        fe.push(se / steps as f64);
    }
    let m = Measurement::poisson(theta.clone(), fo, fe).unwrap().with_sweeps(vec![d; 16]).unwrap();
    let r = reduce(&m).unwrap();
    let demod = Demodulation::of_matrices(theta.iter().copied().zip(mats.iter().copied())).unwrap();
    let (fq, fu) = demod.forward(q0, u0);
    assert!(
        (r.qu.q - fq).abs() < 1e-8 && (r.qu.u - fu).abs() < 1e-8,
        "reduced ({}, {}), chain ({fq}, {fu})",
        r.qu.q,
        r.qu.u
    );
    // Reduced as if the plate stood still, they would be 10 % off the chain's.
    let fixed = reduce(&Measurement::poisson(theta.clone(), m.f_o().to_vec(), m.f_e().to_vec()).unwrap()).unwrap();
    assert!((fixed.qu.q / fq - 0.9003).abs() < 2e-3, "{} / {fq}", fixed.qu.q);
}
