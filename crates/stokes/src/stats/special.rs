//! Numerical building blocks of the statistics: stable Bessel ratios, `erfcx`, adaptive
//! Gauss-Legendre quadrature and Brent's bracketed root finder.
//!
//! Everything here works on normalized quantities (`x = P / sigma`) and never forms
//! `I0(z)` or `exp(z^2)` directly where they could overflow.

use spec_math::cephes64::{erfc, i0e, i1e};
use std::sync::OnceLock;

/// `ln I0(z)` for `z >= 0`, from the exponentially scaled `i0e` (no overflow at any `z`).
#[inline]
pub fn ln_i0(z: f64) -> f64 {
    i0e(z).ln() + z
}

/// `I1(z) / I0(z)` for `z >= 0` (ratio of exponentially scaled functions: no overflow).
#[inline]
pub fn bessel_ratio(z: f64) -> f64 {
    if z <= 0.0 {
        return 0.0;
    }
    i1e(z) / i0e(z)
}

/// `I1(z) / (z I0(z))`, finite at `z = 0` (limit 1/2).
#[inline]
pub fn bessel_ratio_over_z(z: f64) -> f64 {
    if z < 1e-6 {
        // I1/I0 = z/2 - z^3/16 + ...
        return 0.5 - z * z / 16.0;
    }
    bessel_ratio(z) / z
}

/// Scaled complementary error function `erfcx(x) = exp(x^2) erfc(x)`, finite for
/// `x > -26` (for `x < -26` the value exceeds 1e293 and is returned as computed, possibly inf).
///
/// For large positive `x` it uses the continued fraction of `erfc`, where `exp(x^2)` and
/// `erfc(x)` would overflow and underflow separately.
pub fn erfcx(x: f64) -> f64 {
    if x < 0.0 {
        // erfc(-x) = 2 - erfc(x)
        return 2.0 * (x * x).exp() - erfcx(-x);
    }
    if x < 10.0 {
        return (x * x).exp() * erfc(x);
    }
    // Lentz-free backward evaluation of the continued fraction
    // erfcx(x) = (1/sqrt(pi)) / (x + (1/2)/(x + 1/(x + (3/2)/(x + 2/(x + ...))))).
    let mut t = x;
    for k in (1..=60).rev() {
        t = x + 0.5 * k as f64 / t;
    }
    1.0 / (std::f64::consts::PI.sqrt() * t)
}

/// Gauss-Legendre nodes and weights on [-1, 1] (computed once by Newton iteration on P_n).
fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut x = vec![0.0; n];
    let mut w = vec![0.0; n];
    let m = n.div_ceil(2);
    for i in 0..m {
        let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut pp = 0.0;
        for _ in 0..100 {
            let (mut p1, mut p2) = (1.0, 0.0);
            for j in 0..n {
                let p3 = p2;
                p2 = p1;
                p1 = ((2 * j + 1) as f64 * z * p2 - j as f64 * p3) / (j + 1) as f64;
            }
            pp = n as f64 * (z * p1 - p2) / (z * z - 1.0);
            let z1 = z;
            z = z1 - p1 / pp;
            if (z - z1).abs() < 1e-15 {
                break;
            }
        }
        x[i] = -z;
        x[n - 1 - i] = z;
        w[i] = 2.0 / ((1.0 - z * z) * pp * pp);
        w[n - 1 - i] = w[i];
    }
    (x, w)
}

const GL_N: usize = 20;

fn gl_table() -> &'static (Vec<f64>, Vec<f64>) {
    static T: OnceLock<(Vec<f64>, Vec<f64>)> = OnceLock::new();
    T.get_or_init(|| gauss_legendre(GL_N))
}

/// 20-point Gauss-Legendre rule on `[a, b]`.
pub fn gl20<F: FnMut(f64) -> f64>(f: &mut F, a: f64, b: f64) -> f64 {
    let (x, w) = gl_table();
    let h = 0.5 * (b - a);
    let c = 0.5 * (b + a);
    let mut s = 0.0;
    for i in 0..GL_N {
        s += w[i] * f(c + h * x[i]);
    }
    s * h
}

/// Integral of `f` over `[a, b]` split into `panels` equal panels of 20-point Gauss-Legendre.
/// Exact to rounding for the smooth, unit-width-scale integrands of this module when the
/// panels are at most about one `sigma` wide.
pub fn integrate_panels<F: FnMut(f64) -> f64>(mut f: F, a: f64, b: f64, panels: usize) -> f64 {
    let panels = panels.max(1);
    let h = (b - a) / panels as f64;
    let mut s = 0.0;
    for k in 0..panels {
        let lo = a + h * k as f64;
        let hi = if k + 1 == panels { b } else { lo + h };
        s += gl20(&mut f, lo, hi);
    }
    s
}

/// `(int f, int t f(t))` over `[a, b]` in `panels` 20-point panels, evaluating `f` once per
/// node (posterior normalizer and first moment together).
pub fn integrate_panels2<F: FnMut(f64) -> f64>(mut f: F, a: f64, b: f64, panels: usize) -> (f64, f64) {
    let (x, w) = gl_table();
    let panels = panels.max(1);
    let h = (b - a) / panels as f64;
    let (mut s0, mut s1) = (0.0, 0.0);
    for k in 0..panels {
        let lo = a + h * k as f64;
        let hi = if k + 1 == panels { b } else { lo + h };
        let (c, hh) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        for i in 0..GL_N {
            let t = c + hh * x[i];
            let v = w[i] * f(t) * hh;
            s0 += v;
            s1 += v * t;
        }
    }
    (s0, s1)
}

/// Adaptive Gauss-Legendre quadrature: a panel is accepted when it agrees with the sum of its
/// two halves to `rel_tol` (relative to the running total) or `abs_tol`.
pub fn integrate_adaptive<F: FnMut(f64) -> f64>(mut f: F, a: f64, b: f64, rel_tol: f64, abs_tol: f64) -> f64 {
    fn rec<F: FnMut(f64) -> f64>(f: &mut F, a: f64, b: f64, whole: f64, rel: f64, abs: f64, depth: u32) -> f64 {
        let m = 0.5 * (a + b);
        let l = gl20(f, a, m);
        let r = gl20(f, m, b);
        let two = l + r;
        if depth == 0 || (two - whole).abs() <= abs.max(rel * two.abs()) {
            return two;
        }
        rec(f, a, m, l, rel, abs * 0.5, depth - 1) + rec(f, m, b, r, rel, abs * 0.5, depth - 1)
    }
    let whole = gl20(&mut f, a, b);
    rec(&mut f, a, b, whole, rel_tol, abs_tol, 30)
}

/// Brent's bracketed root finder on `[a, b]` (`f(a)` and `f(b)` of opposite signs or zero).
/// Returns `None` if the bracket does not bracket a sign change or a value is not finite; never
/// leaves the bracket, so it cannot diverge near a threshold the way a bare Newton can.
pub fn brent<F: FnMut(f64) -> f64>(mut f: F, a: f64, b: f64, tol: f64) -> Option<f64> {
    let (mut a, mut b) = (a, b);
    let mut fa = f(a);
    let mut fb = f(b);
    if !(fa.is_finite() && fb.is_finite()) {
        return None;
    }
    if fa == 0.0 {
        return Some(a);
    }
    if fb == 0.0 {
        return Some(b);
    }
    if (fa > 0.0) == (fb > 0.0) {
        return None;
    }
    let (mut c, mut fc) = (a, fa);
    let mut d = b - a;
    let mut e = d;
    for _ in 0..300 {
        if (fb > 0.0) == (fc > 0.0) {
            c = a;
            fc = fa;
            d = b - a;
            e = d;
        }
        if fc.abs() < fb.abs() {
            a = b;
            b = c;
            c = a;
            fa = fb;
            fb = fc;
            fc = fa;
        }
        let tol1 = 2.0 * f64::EPSILON * b.abs() + 0.5 * tol;
        let xm = 0.5 * (c - b);
        if xm.abs() <= tol1 || fb == 0.0 {
            return Some(b);
        }
        if e.abs() >= tol1 && fa.abs() > fb.abs() {
            // Inverse quadratic interpolation (secant when only two points are distinct).
            let s = fb / fa;
            let (mut p, mut q);
            if a == c {
                p = 2.0 * xm * s;
                q = 1.0 - s;
            } else {
                let qq = fa / fc;
                let r = fb / fc;
                p = s * (2.0 * xm * qq * (qq - r) - (b - a) * (r - 1.0));
                q = (qq - 1.0) * (r - 1.0) * (s - 1.0);
            }
            if p > 0.0 {
                q = -q;
            }
            p = p.abs();
            let min1 = 3.0 * xm * q - (tol1 * q).abs();
            let min2 = (e * q).abs();
            if 2.0 * p < min1.min(min2) {
                e = d;
                d = p / q;
            } else {
                d = xm;
                e = d;
            }
        } else {
            d = xm;
            e = d;
        }
        a = b;
        fa = fb;
        b += if d.abs() > tol1 { d } else { tol1.copysign(xm) };
        fb = f(b);
        if !fb.is_finite() {
            return None;
        }
    }
    Some(b)
}

/// Find a root of an increasing-then-crossing function by expanding the upper end of the
/// bracket `[lo, hi]` (doubling its width) until `f` changes sign, then Brent.
pub fn brent_expand<F: FnMut(f64) -> f64>(mut f: F, lo: f64, mut hi: f64, tol: f64) -> Option<f64> {
    let flo = f(lo);
    if flo == 0.0 {
        return Some(lo);
    }
    for _ in 0..200 {
        let fhi = f(hi);
        if !fhi.is_finite() {
            return None;
        }
        if (fhi > 0.0) != (flo > 0.0) || fhi == 0.0 {
            return brent(f, lo, hi, tol);
        }
        hi = lo + 2.0 * (hi - lo);
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gauss_legendre_integrates_polynomials_exactly() {
        // A 20-point rule is exact for degree 39.
        let v = gl20(&mut |x: f64| x.powi(38) * 39.0, 0.0, 1.0);
        assert!((v - 1.0).abs() < 1e-13, "{v}");
        let v = integrate_adaptive(|x: f64| (-x * x).exp(), -30.0, 30.0, 1e-14, 0.0);
        assert!((v - std::f64::consts::PI.sqrt()).abs() < 1e-13, "{v}");
    }

    #[test]
    fn erfcx_matches_definition_and_asymptote() {
        for &x in &[-3.0f64, -0.5, 0.0, 0.3, 2.0, 9.9] {
            let direct = (x * x).exp() * erfc(x);
            assert!((erfcx(x) - direct).abs() <= 1e-14 * direct, "{x}");
        }
        // Continuity across the switch at 10 and the asymptote 1/(x sqrt(pi)) (1 - 1/(2x^2)).
        let a = (10.0f64 * 10.0).exp() * erfc(10.0);
        assert!((erfcx(10.0) - a).abs() < 1e-13 * a);
        let x = 1e4;
        let asym = 1.0 / (x * std::f64::consts::PI.sqrt()) * (1.0 - 0.5 / (x * x));
        assert!((erfcx(x) - asym).abs() < 1e-15 * asym);
    }

    #[test]
    fn brent_finds_roots_and_refuses_bad_brackets() {
        let r = brent(|x| x * x - 2.0, 0.0, 2.0, 1e-15).unwrap();
        assert!((r - 2f64.sqrt()).abs() < 1e-14);
        assert!(brent(|x| x * x + 1.0, -1.0, 1.0, 1e-12).is_none());
        let r = brent_expand(|x| 1.0 - x, 0.0, 1e-3, 1e-14).unwrap();
        assert!((r - 1.0).abs() < 1e-12);
    }

    #[test]
    fn bessel_ratio_limits() {
        assert_eq!(bessel_ratio(0.0), 0.0);
        assert!((bessel_ratio_over_z(1e-9) - 0.5).abs() < 1e-15);
        // Large-argument limit: 1 - 1/(2z) - 1/(8z^2).
        let z = 1e6;
        assert!((bessel_ratio(z) - (1.0 - 0.5 / z - 0.125 / (z * z))).abs() < 1e-15);
        assert!(ln_i0(1e6).is_finite());
    }
}
