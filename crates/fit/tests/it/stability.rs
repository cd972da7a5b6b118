//! Stability of the correction (`fit::correction::correct`, `eq:instpol` inverted) over wide ranges:
//! source P in [0, 0.99], instrumental p in [0, 0.3] and up to 1 - 1e-6, angles
//! across the 0/180 deg wrap. The observed (q1, u1) come from the Mueller matrix `M_I(p, phi)`
//! (mueller crate), independent of the closed form. Deterministic pseudo-random sweeps (no
//! proptest dependency in this crate).

use fit::correction::correct::{exact_jacobian, invert_exact, invert_exact_matrix, invert_first_order, rotate_chi};
use std::f64::consts::PI;

struct Rng(u64);
impl Rng {
    fn u(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn angle(&mut self) -> f64 {
        match (self.u() * 8.0) as u32 {
            0 => 0.0,
            1 => PI.next_down(),
            2 => 1e-12,
            3 => PI - 1e-12,
            _ => self.u() * PI,
        }
    }
    fn degree(&mut self, max: f64) -> f64 {
        match (self.u() * 6.0) as u32 {
            0 => 0.0,
            1 => 1e-12,
            2 => max * 10f64.powf(-6.0 * self.u()),
            _ => max * self.u(),
        }
    }
}

fn observed(p: f64, phi: f64, q0: f64, u0: f64) -> (f64, f64) {
    let s = mueller::partial_polarizer(p, phi) * mueller::stokes_qu(1.0, q0, u0);
    (s[1] / s[0], s[2] / s[0])
}

/// Forward with `M_I` then `invert_exact` recovers the source to rounding amplified by the
/// conditioning 1/(1 - p); the nalgebra 4x4 reference agrees; every number finite.
#[test]
fn exact_correction_round_trip() {
    let mut r = Rng(0xF17_0001);
    for k in 0..20000 {
        let p = if k % 10 == 0 { 1.0 - 10f64.powf(-1.0 - 5.0 * r.u()) } else { r.degree(0.3) };
        let (phi, p0, chi0) = (r.angle(), r.degree(0.99), r.angle());
        let (q0, u0) = (p0 * (2.0 * chi0).cos(), p0 * (2.0 * chi0).sin());
        let (q1, u1) = observed(p, phi, q0, u0);
        let (qi, ui) = (p * (2.0 * phi).cos(), p * (2.0 * phi).sin());
        let Ok((qc, uc)) = invert_exact(qi, ui, q1, u1) else {
            // Only near-singular combinations (1 - qi q1 - ui u1 -> 0) may be refused.
            assert!(1.0 - (qi * q1 + ui * u1) < 1e-6, "refused p {p} p0 {p0}");
            continue;
        };
        let tol = 64.0 * f64::EPSILON / (1.0 - p) / (1.0 - p0).max(1e-3);
        assert!(
            (qc - q0).abs() <= tol && (uc - u0).abs() <= tol,
            "p {p} phi {phi} p0 {p0} chi0 {chi0}: ({qc}, {uc}) vs ({q0}, {u0})"
        );
        // The 4x4 nalgebra reference itself loses digits as p -> 1 (cond ~ 1/(1-p)^2).
        if let (true, Ok((qm, um))) = (p < 0.9, invert_exact_matrix(p, phi, q1, u1)) {
            assert!((qm - qc).abs() <= 1e3 * tol && (um - uc).abs() <= 1e3 * tol);
        }
        let (qf, uf) = invert_first_order(qi, ui, q1, u1);
        assert!(qf.is_finite() && uf.is_finite());
    }
}

/// The analytic Jacobians of the exact correction against central differences.
#[test]
fn jacobian_matches_finite_differences() {
    let mut r = Rng(0xF17_0002);
    for _ in 0..3000 {
        let (p, phi, p0, chi0) = (r.degree(0.3), r.angle(), r.degree(0.5), r.angle());
        let (q0, u0) = (p0 * (2.0 * chi0).cos(), p0 * (2.0 * chi0).sin());
        let (q1, u1) = observed(p, phi, q0, u0);
        let (qi, ui) = (p * (2.0 * phi).cos(), p * (2.0 * phi).sin());
        let (_, jm, ja) = exact_jacobian(qi, ui, q1, u1).unwrap();
        let h = 1e-6;
        let f = |a: f64, b: f64, c: f64, d: f64| invert_exact(a, b, c, d).unwrap();
        let d = |x: (f64, f64), y: (f64, f64)| ((x.0 - y.0) / (2.0 * h), (x.1 - y.1) / (2.0 * h));
        let dq1 = d(f(qi, ui, q1 + h, u1), f(qi, ui, q1 - h, u1));
        let du1 = d(f(qi, ui, q1, u1 + h), f(qi, ui, q1, u1 - h));
        // d/dqi at p -> 0 is one-sided in direction; skip the kink at p = 0.
        for (num, col) in [(dq1, 0), (du1, 1)] {
            assert!((jm[0][col] - num.0).abs() < 1e-6 && (jm[1][col] - num.1).abs() < 1e-6, "Jm {jm:?} vs {num:?}");
        }
        if p > 1e-3 {
            let dqi = d(f(qi + h, ui, q1, u1), f(qi - h, ui, q1, u1));
            let dui = d(f(qi, ui + h, q1, u1), f(qi, ui - h, q1, u1));
            for (num, col) in [(dqi, 0), (dui, 1)] {
                assert!((ja[0][col] - num.0).abs() < 1e-5 && (ja[1][col] - num.1).abs() < 1e-5, "Ja {ja:?} vs {num:?}");
            }
        }
    }
}

/// rotate_chi turns chi by the offset and keeps P, across the wrap.
#[test]
fn rotate_chi_is_a_rotation() {
    let mut r = Rng(0xF17_0003);
    for _ in 0..5000 {
        let (p, chi, a) = (r.degree(1.0), r.angle(), r.angle() - 0.5 * PI);
        let (q, u) = rotate_chi(p * (2.0 * chi).cos(), p * (2.0 * chi).sin(), a);
        assert!((q.hypot(u) - p).abs() <= 4.0 * f64::EPSILON);
        if p > 1e-9 {
            let c = (0.5 * u.atan2(q)).rem_euclid(PI);
            let dd = (c - chi - a).rem_euclid(PI);
            assert!(dd.min(PI - dd) <= 1e-12 / p.min(1.0));
        }
    }
}

/// p >= 1, NaN: refused with an error, not NaN output.
#[test]
fn unphysical_instrument_is_refused() {
    assert!(invert_exact(1.0, 0.0, 0.1, 0.0).is_err());
    assert!(invert_exact(f64::NAN, 0.0, 0.1, 0.0).is_err());
}
