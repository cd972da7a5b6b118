//! Mueller-matrix utilities: Jones to Mueller, physical realizability, exact inverse,
//! diattenuation, polarizance and retardance.
//!
//! Stokes from a Jones vector `(E_x, E_y)` (time dependence `exp(-i omega t)`):
//! `I = |E_x|^2 + |E_y|^2`, `Q = |E_x|^2 - |E_y|^2`, `U = 2 Re(E_x^* E_y)`,
//! `V = 2 Im(E_x^* E_y)` (IAU sign, see the crate docs).

use crate::C64;
use crate::{Error, Mueller};
use nalgebra::{Matrix2, Matrix3, Matrix4, Vector3};

/// `A` with `S = A (E (x) E^*)`, `(E (x) E^*) = (ExEx*, ExEy*, EyEx*, EyEy*)`.
fn a_matrix() -> Matrix4<C64> {
    let (o, z, i) = (C64::new(1.0, 0.0), C64::new(0.0, 0.0), C64::new(0.0, 1.0));
    #[rustfmt::skip]
    let a = Matrix4::new(
        o, z, z, o,
        o, z, z, -o,
        z, o, o, z,
        z, i, -i, z,
    );
    a
}

fn a_inverse() -> Matrix4<C64> {
    let (h, z, i) = (C64::new(0.5, 0.0), C64::new(0.0, 0.0), C64::new(0.0, 0.5));
    #[rustfmt::skip]
    let a = Matrix4::new(
        h, h, z, z,
        z, z, h, -i,
        z, z, h, i,
        h, -h, z, z,
    );
    a
}

/// Mueller matrix of a Jones matrix `j` (acting on `(E_x, E_y)`): `A (J (x) J^*) A^-1`.
pub fn jones_to_mueller(j: &Matrix2<C64>) -> Mueller {
    let mut k = Matrix4::<C64>::zeros();
    for r in 0..4 {
        for c in 0..4 {
            k[(r, c)] = j[(r / 2, c / 2)] * j[(r % 2, c % 2)].conj();
        }
    }
    (a_matrix() * k * a_inverse()).map(|z| z.re)
}

/// The Hermitian coherency matrix `H` of a Mueller matrix (Cloude 1986): `H` is linear in
/// `M`, equals `vec(J) vec(J)^H` for a Mueller-Jones matrix, and `M` is a physical (ensemble
/// of Jones) matrix if and only if `H` is positive semidefinite.
pub fn coherency(m: &Mueller) -> Matrix4<C64> {
    let k = a_inverse() * m.map(|x| C64::new(x, 0.0)) * a_matrix();
    // Reshuffle: K_{(ik),(jl)} = J_ij J*_kl  ->  H_{(ij),(kl)}.
    let mut h = Matrix4::<C64>::zeros();
    for i in 0..2 {
        for j in 0..2 {
            for kk in 0..2 {
                for l in 0..2 {
                    h[(2 * i + j, 2 * kk + l)] = k[(2 * i + kk, 2 * j + l)];
                }
            }
        }
    }
    // Normalize to trace m00, and symmetrize against rounding so the Hermitian eigen-solver
    // sees an exact Hermitian matrix.
    (h + h.adjoint()) * C64::new(0.25, 0.0)
}

/// Eigenvalues of the coherency matrix, ascending; their sum is `m00`. All NaN for a matrix
/// with a non-finite element (the eigen-solver would not terminate on it).
pub fn coherency_eigenvalues(m: &Mueller) -> [f64; 4] {
    if !m.iter().all(|x| x.is_finite()) {
        return [f64::NAN; 4];
    }
    let e = coherency(m).symmetric_eigenvalues();
    let mut v = [e[0], e[1], e[2], e[3]];
    v.sort_by(|a, b| a.total_cmp(b));
    v
}

/// Physical realizability (Cloude's test): every coherency eigenvalue is `>= -tol * m00`.
/// A physical matrix also maps every Stokes vector to one with `I >= sqrt(Q^2+U^2+V^2)`.
pub fn is_physical(m: &Mueller, tol: f64) -> bool {
    if !m.iter().all(|x| x.is_finite()) || m[(0, 0)] < 0.0 {
        return false;
    }
    let scale = m[(0, 0)].max(f64::MIN_POSITIVE);
    coherency_eigenvalues(m)[0] >= -tol * scale
}

/// Exact inverse of a Mueller matrix, or [`Error::Singular`] when it has none (an ideal
/// polarizer, a fully opaque element): the ratio of the smallest to the largest singular
/// value must exceed `1e-12`. A matrix with a NaN or infinite element is [`Error::Invalid`].
pub fn inverse(m: &Mueller) -> Result<Mueller, Error> {
    // nalgebra's SVD iterates without end on non-finite input: refuse it first.
    if let Some(v) = m.iter().find(|v| !v.is_finite()) {
        return Err(Error::Invalid { what: "Mueller matrix".into(), why: format!("holds a non-finite element ({v})") });
    }
    let sv = m.singular_values();
    let (mx, mn) = (sv.max(), sv.min());
    if !(mx.is_finite() && mx > 0.0 && mn > 1e-12 * mx) {
        return Err(Error::Singular("smallest singular value below 1e-12 of the largest (e.g. an ideal polarizer)"));
    }
    // LU with partial pivoting: nalgebra's closed-form 4x4 inverse loses digits on
    // ill-conditioned matrices (near-ideal polarizers).
    m.lu().try_inverse().ok_or(Error::Singular("LU decomposition failed"))
}

/// Diattenuation `|(m01, m02, m03)| / m00`: the polarization dependence of the transmittance.
pub fn diattenuation(m: &Mueller) -> f64 {
    Vector3::new(m[(0, 1)], m[(0, 2)], m[(0, 3)]).norm() / m[(0, 0)]
}

/// Polarizance `|(m10, m20, m30)| / m00`: the polarization given to unpolarized light.
pub fn polarizance(m: &Mueller) -> f64 {
    Vector3::new(m[(1, 0)], m[(2, 0)], m[(3, 0)]).norm() / m[(0, 0)]
}

/// Retardance (rad, in `[0, pi]`) of a non-depolarizing Mueller matrix, by the Lu-Chipman
/// decomposition `M = M_R M_D` (Lu & Chipman 1996, JOSA A 13, 1106): `M_R = M M_D^-1`,
/// `cos R = tr(M_R) / 2 - 1`. Fails with [`Error::Singular`] for a total diattenuator.
pub fn retardance(m: &Mueller) -> Result<f64, Error> {
    let t = m[(0, 0)];
    if t.is_nan() || t <= 0.0 {
        return Err(Error::Singular("m00 <= 0"));
    }
    let d = Vector3::new(m[(0, 1)], m[(0, 2)], m[(0, 3)]) / t;
    let dd = d.norm();
    if dd >= 1.0 - 1e-12 {
        return Err(Error::Singular("total diattenuator: retardance undefined"));
    }
    let s = (1.0 - dd * dd).sqrt();
    let md3 = if dd > 0.0 {
        let u = d / dd;
        Matrix3::identity() * s + u * u.transpose() * (1.0 - s)
    } else {
        Matrix3::identity()
    };
    let mut md = Mueller::zeros();
    md[(0, 0)] = 1.0;
    for k in 0..3 {
        md[(0, k + 1)] = d[k];
        md[(k + 1, 0)] = d[k];
        for l in 0..3 {
            md[(k + 1, l + 1)] = md3[(k, l)];
        }
    }
    let mr = m * inverse(&(md * t))?;
    let c = 0.5 * (mr.trace()) - 1.0;
    Ok(c.clamp(-1.0, 1.0).acos())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::*;
    use approx::assert_relative_eq;
    use proptest::prelude::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    fn pure_stokes(chi: f64, eps: f64) -> Stokes {
        // Fully polarized light: ellipticity angle eps, orientation chi.
        let (c2e, s2e) = ((2.0 * eps).cos(), (2.0 * eps).sin());
        Stokes::new(1.0, c2e * (2.0 * chi).cos(), c2e * (2.0 * chi).sin(), s2e)
    }

    fn stokes_bound_holds(m: &Mueller) -> bool {
        for i in 0..12 {
            for j in 0..7 {
                let s = m * pure_stokes(i as f64 * PI / 12.0, -PI / 4.0 + j as f64 * PI / 12.0);
                if s[0] + 1e-12 < (s[1] * s[1] + s[2] * s[2] + s[3] * s[3]).sqrt() {
                    return false;
                }
            }
        }
        true
    }

    #[test]
    fn iau_circular_sign() {
        // Crate docs: fast axis 0, retardance +pi/2 turns +45 deg linear into V > 0.
        let s = retarder(FRAC_PI_2, 0.0) * stokes_p_chi(1.0, 1.0, PI / 4.0);
        assert_relative_eq!(s, Stokes::new(1.0, 0.0, 0.0, 1.0), epsilon = 1e-15);
        // Same from the Jones matrix diag(1, e^{i pi/2}) (slow axis y lags) and the Stokes
        // definition V = 2 Im(Ex* Ey): (1, i)/sqrt2 turns x -> y, counter-clockwise.
        let j = Matrix2::new(C64::new(1.0, 0.0), C64::new(0.0, 0.0), C64::new(0.0, 0.0), C64::new(0.0, 1.0));
        assert_relative_eq!(jones_to_mueller(&j), retarder(FRAC_PI_2, 0.0), epsilon = 1e-15);
    }

    #[test]
    fn partial_polarizer_limits() {
        assert_relative_eq!(partial_polarizer(0.0, 0.7), Mueller::identity(), epsilon = 1e-15);
        for &phi in &[0.0, 0.3, FRAC_PI_2, 2.0] {
            assert_relative_eq!(partial_polarizer(1.0, phi), polarizer(phi), epsilon = 1e-15);
        }
        assert_relative_eq!(retarder(0.0, 0.4), Mueller::identity(), epsilon = 1e-15);
    }

    #[test]
    fn jones_diattenuator_matches_mueller_diattenuator() {
        let (k1, k2) = (0.9_f64, 0.3_f64);
        let j =
            Matrix2::new(C64::new(k1.sqrt(), 0.0), C64::new(0.0, 0.0), C64::new(0.0, 0.0), C64::new(k2.sqrt(), 0.0));
        assert_relative_eq!(jones_to_mueller(&j), diattenuator(k1, k2, 0.0), epsilon = 1e-15);
        assert_relative_eq!(diattenuation(&diattenuator(k1, k2, 0.3)), 0.6 / 1.2, epsilon = 1e-15);
        assert_relative_eq!(polarizance(&partial_polarizer(0.02, 0.3)), 0.02, epsilon = 1e-15);
    }

    #[test]
    fn coherency_of_jones_matrix_is_rank_one() {
        let j = Matrix2::new(C64::new(0.9, 0.1), C64::new(0.05, -0.2), C64::new(0.0, 0.3), C64::new(0.7, 0.0));
        let e = coherency_eigenvalues(&jones_to_mueller(&j));
        let tr: f64 = e.iter().sum();
        assert_relative_eq!(tr, jones_to_mueller(&j)[(0, 0)], epsilon = 1e-14);
        assert!(e[0].abs() < 1e-14 && e[1].abs() < 1e-14 && e[2].abs() < 1e-14 && e[3] > 0.0, "{e:?}");
    }

    #[test]
    fn unphysical_matrices_fail() {
        // Amplifies polarized light: I' < |P'| for some inputs.
        let mut m = Mueller::identity();
        m[(1, 1)] = 1.2;
        assert!(!is_physical(&m, 1e-12));
        assert!(!stokes_bound_holds(&m));
        // Linear diattenuator with |D| > 1.
        let mut d = Mueller::identity();
        d[(0, 1)] = 1.1;
        d[(1, 0)] = 1.1;
        assert!(!is_physical(&d, 1e-12));
        // Every element of the crate passes.
        assert!(is_physical(&polarizer(0.3), 1e-12));
        assert!(is_physical(&Mueller::identity(), 1e-12));
    }

    #[test]
    fn inverse_round_trip_and_singular_cases() {
        let m = diattenuator(0.9, 0.4, 0.2) * retarder(1.0, 0.7) * partial_polarizer(0.05, 1.1);
        let inv = inverse(&m).unwrap();
        assert_relative_eq!(inv * m, Mueller::identity(), epsilon = 1e-12);
        assert_relative_eq!(m * inv, Mueller::identity(), epsilon = 1e-12);
        assert!(matches!(inverse(&polarizer(0.4)), Err(Error::Singular(_))));
        assert!(matches!(inverse(&partial_polarizer(1.0, 0.0)), Err(Error::Singular(_))));
        assert!(matches!(inverse(&Mueller::zeros()), Err(Error::Singular(_))));
        // Near the singular limit the inverse still exists and is exact.
        let m = partial_polarizer(1.0 - 1e-6, 0.3);
        assert_relative_eq!(inverse(&m).unwrap() * m, Mueller::identity(), epsilon = 1e-9);
    }

    #[test]
    fn retardance_extraction() {
        for &d in &[0.0, 0.3, 1.5, 3.0] {
            assert_relative_eq!(retardance(&retarder(d, 0.4)).unwrap(), d, epsilon = 1e-7);
            let m = retarder(d, 0.4) * diattenuator(0.9, 0.5, 1.0);
            assert_relative_eq!(retardance(&m).unwrap(), d, epsilon = 1e-7);
        }
        assert!(retardance(&polarizer(0.0)).is_err());
    }

    /// Each element at `theta` equals `R(-theta) M(0) R(theta)`.
    fn elements(a: f64, b: f64, c: f64) -> Vec<(Box<dyn Fn(f64) -> Mueller>, &'static str)> {
        vec![
            (Box::new(move |t| partial_polarizer(a, t)), "partial_polarizer"),
            (Box::new(move |t| diattenuator(a, b, t)), "diattenuator"),
            (Box::new(move |t| retarder(c, t)), "retarder"),
            (Box::new(polarizer), "polarizer"),
            (Box::new(move |t| Hwp { retardance_error: c - PI, ..Hwp::ideal() }.matrix(t)), "hwp"),
            (
                Box::new(move |t| {
                    crate::fresnel::interface(1.0, crate::fresnel::C64::new(1.0 + b, a), c.abs().min(1.5))
                        .unwrap()
                        .mueller_t(t)
                }),
                "fresnel_t",
            ),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn every_element_is_physical(a in 0.0..=1.0f64, b in 0.0..=1.0f64, c in -PI..PI, t in -PI..PI) {
            for (f, name) in elements(a, b, c) {
                let m = f(t);
                prop_assert!(is_physical(&m, 1e-10), "{name} {a} {b} {c} {t}: {:?}", coherency_eigenvalues(&m));
                prop_assert!(stokes_bound_holds(&m), "{name}");
            }
            // The paper's M_PA is physical when its axis is at 0 and C <= sqrt(1 - B^2) (a
            // depolarizing diattenuator); at other angles it is a first-order approximation
            // (no Q-U cross terms) whose coherency eigenvalues dip below 0 by O(B^2).
            let bb = 0.5 * b;
            let pa = post_analyzer(a, bb, (1.0 - bb * bb).sqrt(), 0.0);
            prop_assert!(is_physical(&pa, 1e-10), "post_analyzer at 0");
            let pa = post_analyzer(1.0, bb, (1.0 - bb * bb).sqrt(), t);
            prop_assert!(coherency_eigenvalues(&pa)[0] >= -bb * bb, "post_analyzer {:?}", coherency_eigenvalues(&pa));
            let (o, e) = Wollaston { t: 0.5 * a, s: 0.5 * b, delta_alpha: 0.1 * c }.beams();
            prop_assert!(is_physical(&o, 1e-10) && is_physical(&e, 1e-10), "wollaston");
        }

        #[test]
        fn rotation_consistency(a in 0.0..=1.0f64, b in 0.0..=1.0f64, c in -PI..PI, t in -PI..PI) {
            for (f, name) in elements(a, b, c) {
                let lhs = f(t);
                let rhs = rotation(-t) * f(0.0) * rotation(t);
                prop_assert!((lhs - rhs).abs().max() < 1e-12, "{name}");
            }
        }

        #[test]
        fn mirror_rotation_rule_and_realizability(c in 0.0..1.5f64, t in -PI..PI) {
            // A reflection hands the light to a mirrored (right-handed about the reflected
            // ray) frame, where the plane of incidence sits at -theta: M(theta) = R(theta)
            // M(0) R(theta), not R(-theta) M(0) R(theta).
            let m = |t| crate::fresnel::mirror(crate::fresnel::ALUMINIUM_550, c, t).unwrap();
            prop_assert!((m(t) - rotation(t) * m(0.0) * rotation(t)).abs().max() < 1e-12);
            prop_assert!(is_physical(&m(t), 1e-10) && stokes_bound_holds(&m(t)));
        }

        #[test]
        fn inverse_round_trips(a in 0.0..0.99f64, b in 0.05..=1.0f64, c in -PI..PI, t in -PI..PI) {
            let m = partial_polarizer(a, t) * retarder(c, 0.5 * t) * diattenuator(b, 0.5 * b + 0.1, t);
            let inv = inverse(&m).unwrap();
            prop_assert!((inv * m - Mueller::identity()).abs().max() < 1e-8);
        }
    }
}
