//! A Jones calculation of a quarter-wave plate before an ideal Wollaston, written apart from
//! the simulator's Mueller matrices: the independent number the circular-polarization tests
//! (`circular.rs`, `circular_map.rs`) check the simulator and the reduction against.

type C = mueller::C64;

/// `(f_o, f_e)` of unit intensity with normalized Stokes `(q, u, v)` behind a quarter-wave
/// plate whose fast axis is at `axis` (rad) and an ideal Wollaston: Jones calculus.
pub fn jones_fluxes(q: f64, u: f64, v: f64, axis: f64) -> (f64, f64) {
    // The plate: Rot(axis) diag(1, i) Rot(-axis) (the slow axis lags by pi/2).
    let (s, c) = axis.sin_cos();
    let i = C::new(0.0, 1.0);
    let j = [
        [C::from(c * c) + i * s * s, C::from(c * s) - i * c * s],
        [C::from(c * s) - i * c * s, C::from(s * s) + i * c * c],
    ];
    let through = |e: [C; 2]| {
        let ex = j[0][0] * e[0] + j[0][1] * e[1];
        let ey = j[1][0] * e[0] + j[1][1] * e[1];
        (ex.norm_sqr(), ey.norm_sqr())
    };
    let p = (q * q + u * u + v * v).sqrt();
    let mut fo = 0.0;
    let mut fe = 0.0;
    // The unpolarized part, 1 - p: half along x, half along y, incoherent.
    for e in [[C::from(1.0), C::from(0.0)], [C::from(0.0), C::from(1.0)]] {
        let (o, x) = through(e);
        fo += 0.5 * (1.0 - p) * o;
        fe += 0.5 * (1.0 - p) * x;
    }
    if p > 0.0 {
        // The polarized part: |E_x|^2 - |E_y|^2 = q/p, 2 |E_x||E_y| e^{i d} = (u + i v)/p.
        let (qn, un, vn) = (q / p, u / p, v / p);
        let e = [C::from(((1.0 + qn) / 2.0).sqrt()), C::from_polar(((1.0 - qn) / 2.0).sqrt(), vn.atan2(un))];
        let (o, x) = through(e);
        fo += p * o;
        fe += p * x;
    }
    (fo, fe)
}
