//! A Jones calculus written for the tests, apart from the library's Mueller code, so that the
//! library's matrices (mirrors, retarders, the instrument chain) can be checked against it.
//! Included by path where it is used (`mueller::mirror`'s unit tests,
//! `crates/sim/tests/it/chain_end_to_end.rs`).

#![allow(dead_code)]

/// Complex numbers as the library takes them (`mueller::C64`).
pub type C64 = nalgebra::Complex<f64>;
use nalgebra::{Matrix2, Matrix4};

pub fn c(re: f64) -> C64 {
    C64::new(re, 0.0)
}

/// `M = A (J (x) J*) A^-1` with `A` from I = |Ex|^2+|Ey|^2, Q = |Ex|^2-|Ey|^2,
/// U = 2 Re(Ex* Ey), V = 2 Im(Ex* Ey) (the IAU sense), and the inverse solved numerically.
pub fn mueller_of_jones(j: &Matrix2<C64>) -> Matrix4<f64> {
    let i = C64::new(0.0, 1.0);
    // Rows act on (Ex Ex*, Ex Ey*, Ey Ex*, Ey Ey*).
    #[rustfmt::skip]
    let a = Matrix4::new(
        c(1.0), c(0.0), c(0.0), c(1.0),
        c(1.0), c(0.0), c(0.0), c(-1.0),
        c(0.0), c(1.0), c(1.0), c(0.0),
        c(0.0), i, -i, c(0.0),
    );
    let ainv = a.try_inverse().expect("A is invertible");
    let k = Matrix4::from_fn(|r, col| j[(r / 2, col / 2)] * j[(r % 2, col % 2)].conj());
    (a * k * ainv).map(|z| z.re)
}

/// Jones matrix that describes a field in axes turned by `t` (x towards y).
pub fn jones_axes(t: f64) -> Matrix2<C64> {
    Matrix2::new(c(t.cos()), c(t.sin()), c(-t.sin()), c(t.cos()))
}

/// Jones matrix of reflection with the plane of incidence at `a` from x of the incident
/// frame: to (p, s) axes (turned by `a`), reflect, and to the axes of the mirror-image
/// reflected frame, in which p lies at `-a`, so that these axes are the (p, s) axes turned
/// by `a` again.
pub fn jones_mirror(rp: C64, rs: C64, a: f64) -> Matrix2<C64> {
    jones_axes(a) * Matrix2::new(rp, c(0.0), c(0.0), rs) * jones_axes(a)
}

/// Textbook Fresnel amplitudes of a bare metal (Born & Wolf 14.2, n cos t =
/// sqrt(N^2 - sin^2 i)); p with the sign that makes r_p = -r_s at normal incidence.
pub fn textbook_r(n: C64, i: f64) -> (C64, C64) {
    let nct = (n * n - c(i.sin().powi(2))).sqrt();
    let rs = (c(i.cos()) - nct) / (c(i.cos()) + nct);
    let rp = (n * n * i.cos() - nct) / (n * n * i.cos() + nct);
    (rp, rs)
}

/// A linear retarder: retardance `delta`, fast axis at `a` (the slow axis lags).
pub fn jones_retarder(delta: f64, a: f64) -> Matrix2<C64> {
    jones_axes(a).transpose() * Matrix2::new(c(1.0), c(0.0), c(0.0), C64::from_polar(1.0, delta)) * jones_axes(a)
}

/// An ideal polarizer transmitting along `phi`.
pub fn jones_polarizer(phi: f64) -> Matrix2<C64> {
    let (s, co) = phi.sin_cos();
    Matrix2::new(c(co * co), c(co * s), c(co * s), c(s * s))
}
