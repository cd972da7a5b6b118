//! What `instpol stokes --plot` draws (the paper's fig:fourier for one source), as numbers:
//! the F_i with their errors, the eq:system curve through the solver's Q/I and U/I, a_0, and
//! the harmonic amplitudes. Nothing is solved here: every number is the `stokes` reduction's.
//! Kept apart from the drawing and free of `crate::` paths, so that
//! `tests/it/stokes_plot.rs` can include this file and check it against the solver.

use stokes::fourier::Harmonic;
use stokes::Reduction;

/// Points of the drawn curve per period of `cos 4 theta` (90 deg of plate angle): steps of
/// 1.25 deg, so that the optimal angles (multiples of 22.5 deg) are points of the curve.
const PER_PERIOD: usize = 72;

/// One measurement: `F_i` (eq:F) at its HWP angle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    /// HWP angle in degrees, folded into [0, 360).
    pub theta_deg: f64,
    /// `F_i`, fraction.
    pub f: f64,
    /// 1-sigma error of `F_i`, fraction.
    pub sigma: f64,
}

/// One harmonic of the lower panel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bar {
    pub k: usize,
    /// `sqrt(a_k^2 + b_k^2)`, fraction.
    pub amplitude: f64,
    /// Its 1-sigma noise level ([`amplitude_sigma`]), fraction.
    pub sigma: f64,
}

/// Everything the plot shows.
#[derive(Debug, Clone, PartialEq)]
pub struct FourierPlot {
    pub n: usize,
    pub points: Vec<Point>,
    /// End of the angle axis: 180 deg when every angle is below 180 deg, else 360 deg.
    pub theta_max_deg: f64,
    /// eq:system, `Q cos 4theta + U sin 4theta` with the solver's Q/I, U/I, raised by `a0`
    /// when that is given, as (theta in deg, F) from 0 to `theta_max_deg`.
    pub curve: Vec<(f64, f64)>,
    /// `a_0 = mean F_i` (eq:a0: the Wollaston imbalance kappa, or a post-analyzer term), on the
    /// optimal angle sets only: there it is the k = 0 harmonic, orthogonal to the k = N/4 one,
    /// so `a_0 + Q cos 4theta + U sin 4theta` is the Fourier series cut to those two terms
    /// (the partial reconstruction of fig:fourier). On other sets the mean of the F_i mixes
    /// in Q and U, and the curve is eq:system alone.
    pub a0: Option<f64>,
    /// Harmonics `k = 0 ..= N/2` (eq:fourcoeff); empty unless the angles are the optimal set.
    pub bars: Vec<Bar>,
    /// The harmonic that carries the polarization, `k = N/4` (a_{N/4} = Q/I, b_{N/4} = U/I).
    pub k_pol: Option<usize>,
    pub q: f64,
    pub u: f64,
    pub p: f64,
    pub sigma_p: f64,
    /// chi in degrees, [0, 180); `None` when P = 0.
    pub chi_deg: Option<f64>,
}

/// eq:system: `F = Q cos 4theta + U sin 4theta` (theta in rad) for normalized Stokes Q/I, U/I.
pub fn model(q: f64, u: f64, theta: f64) -> f64 {
    let (s, c) = (4.0 * theta).sin_cos();
    q * c + u * s
}

/// The 1-sigma noise of a harmonic's amplitude: the rms of sigma_a_k and sigma_b_k
/// (eq:fourcoeff), or sigma_a_k alone for k = 0 and the Nyquist harmonic, which have no sine
/// part.
pub fn amplitude_sigma(h: &Harmonic) -> f64 {
    if h.sigma_b == 0.0 {
        h.sigma_a
    } else {
        h.sigma_a.hypot(h.sigma_b) / std::f64::consts::SQRT_2
    }
}

/// The plot's numbers from a reduction.
pub fn fourier_plot(r: &Reduction) -> FourierPlot {
    let points: Vec<Point> = r
        .theta
        .iter()
        .zip(&r.f)
        .zip(&r.sigma_f)
        .map(|((t, f), s)| Point { theta_deg: t.to_degrees().rem_euclid(360.0), f: *f, sigma: *s })
        .collect();
    let theta_max_deg = if points.iter().all(|p| p.theta_deg < 180.0) { 180.0 } else { 360.0 };
    let m = (theta_max_deg / 90.0) as usize * PER_PERIOD;
    let bars: Vec<Bar> =
        r.fourier.iter().map(|h| Bar { k: h.k, amplitude: h.amplitude(), sigma: amplitude_sigma(h) }).collect();
    let a0 = (!bars.is_empty()).then_some(r.a0);
    let curve = (0..=m)
        .map(|j| {
            let deg = theta_max_deg * j as f64 / m as f64;
            (deg, a0.unwrap_or(0.0) + model(r.qu.q, r.qu.u, deg.to_radians()))
        })
        .collect();
    let k_pol = (!bars.is_empty() && r.n.is_multiple_of(4)).then_some(r.n / 4);
    FourierPlot {
        n: r.n,
        points,
        theta_max_deg,
        curve,
        a0,
        bars,
        k_pol,
        q: r.qu.q,
        u: r.qu.u,
        p: r.p,
        sigma_p: r.sigma_p,
        chi_deg: r.chi_defined.then(|| r.chi.to_degrees().rem_euclid(180.0)),
    }
}
