//! The quarter-wave plate (`Hwp::quarter_wave`, a retarder of retardance pi/2 with a
//! retardance error and a zero angle) against a Jones calculation written here: the complex
//! 2 x 2 Jones matrix of a retarder, turned to its axis, taken to a Mueller matrix by
//! `M = A (J (x) J^*) A^-1` with `A` written out below (Stokes from the coherency vector
//! `(ExEx*, ExEy*, EyEx*, EyEy*)`: `I = |Ex|^2 + |Ey|^2`, `Q = |Ex|^2 - |Ey|^2`,
//! `U = 2 Re(Ex^* Ey)`, `V = 2 Im(Ex^* Ey)`, the IAU sign of the crate's docs).
//! And the flux difference behind a Wollaston, `F(theta) = q cos^2 2theta +
//! u sin 2theta cos 2theta + v sin 2theta`, which the circular demodulation inverts.

use mueller::{stokes_p_chi, DualBeam, Hwp, Mueller, Stokes, C64};
use nalgebra::{Matrix2, Matrix4};
use std::f64::consts::{FRAC_PI_2, PI};

/// Jones matrix of a linear retarder of retardance `delta` with its fast axis at `angle`:
/// `Rot(angle) diag(1, e^{i delta}) Rot(-angle)` (the slow axis lags, time dependence
/// `exp(-i omega t)`).
fn jones_retarder(delta: f64, angle: f64) -> Matrix2<C64> {
    let (s, c) = angle.sin_cos();
    let r = |s: f64| Matrix2::new(C64::new(c, 0.0), C64::new(-s, 0.0), C64::new(s, 0.0), C64::new(c, 0.0));
    let d = Matrix2::new(C64::new(1.0, 0.0), C64::new(0.0, 0.0), C64::new(0.0, 0.0), C64::from_polar(1.0, delta));
    r(s) * d * r(-s)
}

/// `A (J (x) J^*) A^-1`, everything written out here.
fn mueller_of_jones(j: &Matrix2<C64>) -> Mueller {
    let (o, z, i) = (C64::new(1.0, 0.0), C64::new(0.0, 0.0), C64::new(0.0, 1.0));
    #[rustfmt::skip]
    let a = Matrix4::new(
        o, z, z, o,
        o, z, z, -o,
        z, o, o, z,
        z, i, -i, z,
    );
    let a_inv = a.try_inverse().expect("A is invertible");
    // Kronecker product J (x) J^*: element ((r1, r2), (c1, c2)) = J[r1, c1] conj(J[r2, c2]).
    let mut k = Matrix4::<C64>::zeros();
    for r1 in 0..2 {
        for r2 in 0..2 {
            for c1 in 0..2 {
                for c2 in 0..2 {
                    k[(2 * r1 + r2, 2 * c1 + c2)] = j[(r1, c1)] * j[(r2, c2)].conj();
                }
            }
        }
    }
    let m = a * k * a_inv;
    for x in m.iter() {
        assert!(x.im.abs() < 1e-14, "a Mueller matrix is real: {x}");
    }
    m.map(|x| x.re)
}

#[test]
fn quarter_wave_plate_is_the_jones_retarder() {
    for err in [0.0, 0.05, -0.12] {
        for zero in [0.0, 3f64.to_radians(), -0.4] {
            let plate = Hwp { retardance_error: err, chi_offset: zero, ..Hwp::quarter_wave() };
            for theta_deg in [-45.0, 0.0, 17.0, 45.0, 90.0, 135.0, 225.0, 301.5] {
                let theta = f64::to_radians(theta_deg);
                let want = mueller_of_jones(&jones_retarder(FRAC_PI_2 + err, theta + 0.5 * zero));
                let got = plate.matrix(theta);
                assert!((got - want).abs().max() < 1e-14, "err {err}, zero {zero}, theta {theta_deg}: {got} vs {want}");
            }
        }
    }
    // The half-wave plate is the same type at retardance pi: its Jones matrix too.
    let hwp = Hwp { retardance_error: 0.03, chi_offset: 0.1, ..Hwp::ideal() };
    assert!((hwp.matrix(0.3) - mueller_of_jones(&jones_retarder(PI + 0.03, 0.35))).abs().max() < 1e-14);
    assert!(Hwp::quarter_wave().is_quarter_wave() && !Hwp::ideal().is_quarter_wave());
}

/// Behind an ideal Wollaston (o beam along 0), the plate at `theta` gives
/// `F = q cos^2 2theta + u sin 2theta cos 2theta + v sin 2theta`: the Q row of the retarder of
/// retardance pi/2 (`Q' = c^2 Q + c s U + s V`, `c = cos 2theta`, `s = sin 2theta`), with the
/// sign of `v` positive in the IAU convention.
#[test]
fn flux_difference_behind_a_quarter_wave_plate() {
    let train = DualBeam { hwp: Hwp::quarter_wave(), ..DualBeam::ideal() };
    for (q, u, v) in [(0.0, 0.0, 0.02), (0.01, -0.03, -0.015), (0.05, 0.02, 0.0)] {
        let s = Stokes::new(1.0, q, u, v);
        let theta: Vec<f64> = [-45.0, 0.0, 10.0, 45.0, 135.0, 225.0].iter().map(|d: &f64| d.to_radians()).collect();
        for (b, &t) in train.fluxes(&s, &theta).iter().zip(&theta) {
            let f = (b.f_o - b.f_e) / (b.f_o + b.f_e);
            let (s2, c2) = (2.0 * t).sin_cos();
            assert!((f - (q * c2 * c2 + u * s2 * c2 + v * s2)).abs() < 1e-15, "{q} {u} {v} at {t}");
        }
    }
    // A linear source alone gives F = 0 at +-45 deg: the plate's axes bisect the analyser's.
    let f = train.fluxes(&stokes_p_chi(1.0, 0.05, 0.3), &[FRAC_PI_2 / 2.0, -FRAC_PI_2 / 2.0]);
    assert!(f.iter().all(|b| ((b.f_o - b.f_e) / (b.f_o + b.f_e)).abs() < 1e-15));
}
