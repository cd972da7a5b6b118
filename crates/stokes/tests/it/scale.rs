//! Scale invariance at extreme but finite scales. F_i = (f_O - f_E)/(f_O + f_E) and
//! its error are ratios: multiplying every flux and every error by the same s must leave Q, U,
//! their errors, P, chi and the harmonics unchanged. The reference is the same reduction at
//! s = 1 (an identity, independent of how the library computes its errors): before the scaled
//! forms, fluxes near 1e-200 or 1e200 and errors near 1e300 gave 0, inf or NaN errors.

use std::f64::consts::PI;
use stokes::{Measurement, Reduction};

/// Angles, f_O, f_E, sigma_O, sigma_E.
type Case = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>);

/// Two angle sets: the optimal N = 8 (Fourier sums) and an uneven set with unequal errors
/// (weighted least squares), with P ~ 5 % so that F does not cancel badly.
fn cases() -> Vec<Case> {
    let (q, u) = (0.04, -0.03);
    let mk = |theta: Vec<f64>, sig_scale: &dyn Fn(usize) -> f64| {
        let n = theta.len();
        let (mut fo, mut fe, mut so, mut se) = (vec![], vec![], vec![], vec![]);
        for (i, t) in theta.iter().enumerate() {
            let f = q * (4.0 * t).cos() + u * (4.0 * t).sin() + 1e-3 * ((i * 7 % 5) as f64 - 2.0);
            let tot = 1000.0 + 37.0 * i as f64;
            fo.push(tot * (1.0 + f) / 2.0);
            fe.push(tot * (1.0 - f) / 2.0);
            so.push(3.0 * sig_scale(i));
            se.push(2.5 * sig_scale(i));
        }
        assert_eq!(fo.len(), n);
        (theta, fo, fe, so, se)
    };
    vec![
        mk((0..8).map(|i| i as f64 * PI / 8.0).collect(), &|_| 1.0),
        mk(vec![0.0, 0.3, 0.8, 1.1, 1.9, 2.6], &|i| 1.0 + 0.5 * i as f64),
    ]
}

fn reduce(c: &Case, s: f64) -> Reduction {
    let sc = |v: &Vec<f64>| v.iter().map(|x| x * s).collect::<Vec<_>>();
    Measurement::with_errors(c.0.clone(), sc(&c.1), sc(&c.2), sc(&c.3), sc(&c.4))
        .unwrap_or_else(|e| panic!("scale {s:e}: {e}"))
        .reduce()
        .unwrap_or_else(|e| panic!("scale {s:e}: {e}"))
}

/// The scale-free numbers of a reduction.
fn numbers(r: &Reduction) -> Vec<(&'static str, f64)> {
    let mut v = vec![
        ("q", r.qu.q),
        ("u", r.qu.u),
        ("sigma_q", r.qu.var_q.sqrt()),
        ("sigma_u", r.qu.var_u.sqrt()),
        ("cov_qu", r.qu.cov_qu),
        ("p", r.p),
        ("chi", r.chi),
        ("sigma_p", r.sigma_p),
        ("sigma_chi", r.sigma_chi),
        ("snr", r.snr),
        ("sigma_p_analytic", r.sigma_p_analytic),
        ("a0", r.a0),
        ("sigma_a0", r.sigma_a0),
    ];
    for h in &r.fourier {
        v.push(("fourier a", h.a));
        v.push(("fourier sigma_a", h.sigma_a));
    }
    for (i, s) in r.sigma_f.iter().enumerate() {
        v.push((if i == 0 { "sigma_F[0]" } else { "sigma_F" }, *s));
    }
    v
}

fn check(s: f64, tol: f64) {
    for c in cases() {
        let want = numbers(&reduce(&c, 1.0));
        let got = numbers(&reduce(&c, s));
        for ((name, w), (_, g)) in want.iter().zip(&got) {
            assert!(g.is_finite(), "scale {s:e}: {name} = {g} (unscaled {w})");
            // Relative, except for values that are rounding residues of a cancellation (a0 and
            // some harmonics of the optimal set are 1e-17 here): those are compared on the
            // scale of the F_i (0.01 and above; rounding of f * s leaves ~1e-16 of it).
            let rel = (g - w).abs() / w.abs().max(1e-2);
            assert!(rel <= tol, "scale {s:e}: {name} = {g:e}, unscaled {w:e} (relative {rel:e})");
        }
    }
}

/// Powers of two scale exactly (no rounding in f * s), so every number must be bit-for-bit the
/// unscaled one over the whole normal range: any over- or underflow on the way shows.
#[test]
fn powers_of_two_are_exactly_scale_free() {
    // Fluxes ~1e3 and errors ~3: f * 2^k stays normal for k in -1000..=1000.
    for k in (-1000..=1000).step_by(7) {
        check(2f64.powi(k), 0.0);
    }
}

/// Powers of ten 1e-300 ... 1e300 (each flux and error rounded once when scaled): the same to
/// ~1e-14 relative. F ~ 0.05 amplifies the rounding of f_O - f_E by ~20.
#[test]
fn powers_of_ten_from_1e_minus_300_to_1e300() {
    for k in -300..=300 {
        check(10f64.powi(k), 2e-14);
    }
}

/// Errors near 1e300 with fluxes near 1: sigma_F = 2 sqrt(f_E^2 s_O^2 + f_O^2 s_E^2)/t^2 is
/// huge but finite, and so is sigma_Q; the old form squared 1e300 to inf.
#[test]
fn huge_errors_stay_finite() {
    let theta: Vec<f64> = (0..4).map(|i| i as f64 * PI / 8.0).collect();
    let m = Measurement::with_errors(
        theta,
        vec![1.0, 2.0, 1.5, 1.0],
        vec![1.0, 1.0, 1.5, 2.0],
        vec![1e300; 4],
        vec![1e300; 4],
    )
    .unwrap();
    let e = m.reduce();
    // Either a clear error or finite errors, never inf/NaN passed on as numbers.
    match e {
        Ok(r) => {
            // sigma_F ~ 2 sqrt(2) 1e300 / 4 at F = 0: the closed form.
            let want = 2.0 * (1e300f64).hypot(1e300) / 4.0;
            assert!((r.sigma_f[0] - want).abs() <= 1e-15 * want, "{:e} vs {want:e}", r.sigma_f[0]);
            assert!(r.qu.q.is_finite() && r.p.is_finite());
        }
        Err(e) => assert!(e.to_string().contains("sigma_F"), "{e}"),
    }
}
