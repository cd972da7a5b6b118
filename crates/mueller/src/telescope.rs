//! The telescope in front of the instrument as a Mueller chain: a Nasmyth M3 (a metal mirror
//! at 45 deg, optionally under an oxide layer) turned with the parallactic angle, the
//! instrument's angle offset and rotator, averaged over an exposure's parallactic-angle track.
//! The one forward model of the telescope term: the simulator puts it in front of a scene and
//! `fit::telescope` fits its parameters to standard stars (Wiersema et al. 2018, PASA 35, e012,
//! section 3: `S_instrument = R(offset) M3(plane at pi/2 - q) S_sky`).

use crate::mirror::{alumina_index, reflect, wiersema_m3, Reflection};
use crate::thinfilm::Layer;
use crate::{Stokes, C64};
use nalgebra::Matrix4;
use serde::{Deserialize, Serialize};
use std::f64::consts::FRAC_PI_4;

/// The telescope model of one band: M3 and the instrument's constants.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BandModel {
    pub wavelength_um: f64,
    /// Tabulated index of the metal at the band's wavelength.
    pub index: C64,
    /// Factor on `n` and `k` (1 for the physical model).
    pub factor: f64,
    /// Alumina over-layer (nm; 0 for the Wiersema model).
    pub thickness_nm: f64,
    /// Instrument angle offset (rad).
    pub offset: f64,
    /// Constant instrumental polarization in the instrument frame (fractions).
    pub q0: f64,
    pub u0: f64,
}

impl BandModel {
    /// M3's reflection at 45 deg for this band.
    pub fn m3(&self) -> Result<Reflection, crate::Error> {
        let layers = if self.thickness_nm > 0.0 {
            vec![Layer::new(alumina_index(self.wavelength_um), self.thickness_nm)]
        } else {
            vec![]
        };
        reflect(self.index * self.factor, &layers, 1000.0 * self.wavelength_um, FRAC_PI_4)
    }

    /// Sky to instrument for the intensity-normalized Stokes vector, without `(q0, u0)`:
    /// [`wiersema_m3`] at parallactic angle `parallactic` (rad).
    pub fn matrix(&self, parallactic: f64) -> Result<Matrix4<f64>, crate::Error> {
        Ok(wiersema_m3(&self.m3()?, parallactic, self.offset))
    }

    /// The `(q, u)` an unpolarized star shows in the instrument at parallactic angle `q`
    /// (Wiersema et al. 2018, section 3, plus `q0, u0`).
    pub fn unpolarized(&self, parallactic: f64) -> Result<(f64, f64), crate::Error> {
        let s = self.matrix(parallactic)? * Stokes::new(1.0, 0.0, 0.0, 0.0);
        Ok((s[1] / s[0] + self.q0, s[2] / s[0] + self.u0))
    }

    /// Sky `(q, u)` of a measured instrument `(q, u)` at parallactic angle `parallactic`:
    /// subtract `(q0, u0)` and invert the chain (V assumed zero at the instrument).
    pub fn correct(&self, q: f64, u: f64, parallactic: f64) -> Result<(f64, f64), crate::Error> {
        self.correct_track(q, u, Track::at(parallactic), true)
    }

    /// Sky to instrument averaged over an exposure's parallactic-angle track: light from the
    /// whole exposure adds incoherently, so the Mueller matrices average
    /// ([`track_average`]; not the matrix at the mean angle).
    pub fn matrix_track(&self, track: Track) -> Result<Matrix4<f64>, crate::Error> {
        let m3 = self.m3()?;
        let turn = self.offset + track.rotator;
        track_average(|q| Ok(wiersema_m3(&m3, q, turn)), track)
    }

    /// The sky's `(q, u)` as it reaches the instrument over `track` (without `q0, u0`): what a
    /// sky-field calibration must take as the known sky polarization on a Nasmyth focus, so
    /// that the field pattern it solves for is the instrument's alone.
    pub fn sky_through(&self, q: f64, u: f64, track: Track) -> Result<(f64, f64), crate::Error> {
        let s = self.matrix_track(track)? * Stokes::new(1.0, q, u, 0.0);
        Ok((s[1] / s[0], s[2] / s[0]))
    }

    /// Sky `(q, u)` of a measured instrument `(q, u)` over an exposure's track: subtract
    /// `(q0, u0)` when `constant` (leave it out when a field model holds the instrument's own
    /// polarization), then invert the track-averaged chain `M` for a sky without circular
    /// polarization. A dual-beam linear polarimeter does not measure V, and M3's retardance
    /// turns the sky's U partly into V, so "V = 0 at the instrument" would be wrong by
    /// `P sin(retardance)`; with `V = 0` on the sky the measured `m_k = (M S)_k / (M S)_0`,
    /// `S = (1, q, u, 0)`, are two linear equations in `(q, u)`:
    /// `(M_k1 - m_k M_01) q + (M_k2 - m_k M_02) u = m_k M_00 - M_k0`, `k = 1, 2`.
    pub fn correct_track(&self, q: f64, u: f64, track: Track, constant: bool) -> Result<(f64, f64), crate::Error> {
        let m = self.matrix_track(track)?;
        let (c0, c1) = if constant { (self.q0, self.u0) } else { (0.0, 0.0) };
        invert_normalized(&m, [q - c0, u - c1])
    }
}

/// The sky `(q, u)` (without circular polarization) that a Mueller matrix `m` turns into the
/// normalized `meas = (q, u)`: with `S = (1, q, u, 0)` the measured `m_k = (M S)_k / (M S)_0`
/// are two linear equations, `(M_k1 - m_k M_01) q + (M_k2 - m_k M_02) u = m_k M_00 - M_k0`,
/// `k = 1, 2`, solved exactly; a singular system is an error, not a guess.
pub fn invert_normalized(m: &Matrix4<f64>, meas: [f64; 2]) -> Result<(f64, f64), crate::Error> {
    let a = nalgebra::Matrix2::new(
        m[(1, 1)] - meas[0] * m[(0, 1)],
        m[(1, 2)] - meas[0] * m[(0, 2)],
        m[(2, 1)] - meas[1] * m[(0, 1)],
        m[(2, 2)] - meas[1] * m[(0, 2)],
    );
    let rhs = nalgebra::Vector2::new(meas[0] * m[(0, 0)] - m[(1, 0)], meas[1] * m[(0, 0)] - m[(2, 0)]);
    let det = a.determinant();
    if !(det.is_finite() && det.abs() > 1e-12 * a.abs().max().powi(2).max(f64::MIN_POSITIVE)) {
        return Err(crate::Error::Singular(
            "the telescope chain cannot be inverted for a linearly polarized sky (singular 2x2 system)",
        ));
    }
    let x = a.lu().solve(&rhs).ok_or(crate::Error::Singular("LU of the telescope chain failed"))?;
    Ok((x[0], x[1]))
}

/// One exposure of a demodulated set ([`BandModel::correct_exposures`]): its HWP angle (rad)
/// and its track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exposure {
    pub hwp: f64,
    pub track: Track,
}

/// A set of exposures as the dual-beam reduction demodulates them: each exposure's chain
/// matrix over its own track, grouped by HWP angle (repeats at one angle are summed before
/// `F_i` is formed: equal exposures of one sky, their `F` weighted by the intensity the chain
/// passes), with each angle's `cos 4 theta`, `sin 4 theta`.
#[derive(Debug, Clone)]
pub struct Demodulation {
    /// Per HWP angle: `(cos 4 theta, sin 4 theta)` and its exposures' matrices.
    angles: Vec<((f64, f64), Vec<Matrix4<f64>>)>,
}

impl Demodulation {
    /// The demodulation of exposures each given by its HWP angle (rad) and the Mueller matrix
    /// the light went through before the plate (any chain: the telescope alone, or the
    /// telescope and the field's elements). Exposures at one angle are grouped as repeats.
    pub fn of_matrices(exposures: impl IntoIterator<Item = (f64, Matrix4<f64>)>) -> Result<Self, crate::Error> {
        let mut angles: Vec<((f64, f64), Vec<Matrix4<f64>>)> = vec![];
        let mut keys: Vec<f64> = vec![];
        for (hwp, m) in exposures {
            match keys.iter().position(|&k| k == hwp) {
                Some(i) => angles[i].1.push(m),
                None => {
                    keys.push(hwp);
                    let (sn, c) = (4.0 * hwp).sin_cos();
                    angles.push(((c, sn), vec![m]));
                }
            }
        }
        if angles.len() < 2 {
            return Err(crate::Error::Singular("a demodulation needs exposures at two HWP angles or more"));
        }
        Ok(Demodulation { angles })
    }

    /// `(q, u)` that eq:Q, eq:U give for a sky `(q, u)` without circular polarization: at each
    /// angle `F = sum_i ((M_i S)_1 cos 4 theta + (M_i S)_2 sin 4 theta) / sum_i (M_i S)_0` over
    /// its exposures (eq:F of their summed beams), then `Q = (2/N) sum F cos 4 theta`,
    /// `U = (2/N) sum F sin 4 theta` over the `N` angles.
    pub fn forward(&self, q: f64, u: f64) -> (f64, f64) {
        let s = Stokes::new(1.0, q, u, 0.0);
        let n = self.angles.len() as f64;
        let (mut qm, mut um) = (0.0, 0.0);
        for ((c, sn), ms) in &self.angles {
            // Repeats' fluxes are summed before F is formed: their F weighted by intensity.
            let (mut diff, mut sum) = (0.0, 0.0);
            for m in ms {
                let v = m * s;
                diff += v[1] * c + v[2] * sn;
                sum += v[0];
            }
            let f = diff / sum;
            qm += f * c;
            um += f * sn;
        }
        (2.0 * qm / n, 2.0 * um / n)
    }

    /// `d forward / d (q, u)` at the sky `(q, u)`, row `i` the derivatives of the `i`-th
    /// output: the derivative of each angle's `F = D / S` (`D`, `S` the sums of
    /// [`forward`](Self::forward), linear in `(q, u)` through the columns 1 and 2 of the
    /// matrices) is `(D' S - D S') / S^2`, and `Q`, `U` are linear in the `F`.
    pub fn jacobian(&self, q: f64, u: f64) -> [[f64; 2]; 2] {
        let s = Stokes::new(1.0, q, u, 0.0);
        let n = self.angles.len() as f64;
        let mut j = [[0.0; 2]; 2];
        for ((c, sn), ms) in &self.angles {
            let (mut diff, mut sum) = (0.0, 0.0);
            let (mut d_diff, mut d_sum) = ([0.0; 2], [0.0; 2]);
            for m in ms {
                let v = m * s;
                diff += v[1] * c + v[2] * sn;
                sum += v[0];
                for (k, col) in [1, 2].into_iter().enumerate() {
                    d_diff[k] += m[(1, col)] * c + m[(2, col)] * sn;
                    d_sum[k] += m[(0, col)];
                }
            }
            for k in 0..2 {
                let df = (d_diff[k] * sum - diff * d_sum[k]) / (sum * sum);
                j[0][k] += 2.0 * df * c / n;
                j[1][k] += 2.0 * df * sn / n;
            }
        }
        j
    }

    /// The sky `(q, u)` (without circular polarization) whose demodulation is `meas`:
    /// [`forward`](Self::forward)`(q, u) = meas` solved by Newton's method from `start`, with
    /// the forward model's Jacobian by central differences (the model is linear-fractional in
    /// `(q, u)`: from a start near the answer, such as the solution over the set's whole
    /// track, it converges in a few steps). The answer is refused unless it reproduces `meas`
    /// to 1e-12.
    pub fn solve(&self, meas: (f64, f64), start: (f64, f64)) -> Result<(f64, f64), crate::Error> {
        let (mut x, mut y) = start;
        let h = 1e-6;
        // Newton steps until one no longer shrinks (rounding) or is below 1e-16 (q, u are
        // fractions): quadratic convergence from the whole track's solution takes 2 to 4.
        let mut last = f64::INFINITY;
        for _ in 0..30 {
            let (fq, fu) = self.forward(x, y);
            let (aq, au) = self.forward(x + h, y);
            let (bq, bu) = self.forward(x - h, y);
            let (cq, cu) = self.forward(x, y + h);
            let (dq, du) = self.forward(x, y - h);
            let j = nalgebra::Matrix2::new(
                (aq - bq) / (2.0 * h),
                (cq - dq) / (2.0 * h),
                (au - bu) / (2.0 * h),
                (cu - du) / (2.0 * h),
            );
            let Some(step) = j.lu().solve(&nalgebra::Vector2::new(fq - meas.0, fu - meas.1)) else { break };
            let size = step[0].abs().max(step[1].abs());
            if !(size < last) {
                break;
            }
            x -= step[0];
            y -= step[1];
            last = size;
            if size <= 1e-16 {
                break;
            }
        }
        let (fq, fu) = self.forward(x, y);
        if x.is_finite() && y.is_finite() && (fq - meas.0).abs().max((fu - meas.1).abs()) <= 1e-12 {
            return Ok((x, y));
        }
        Err(crate::Error::Singular("the exposures' telescope chain could not be inverted for a linearly polarized sky"))
    }
}

impl BandModel {
    /// The [`Demodulation`] of `exposures` through this band's chain.
    pub fn demodulation(&self, exposures: &[Exposure]) -> Result<Demodulation, crate::Error> {
        let matrices = exposures
            .iter()
            .map(|e| Ok((e.hwp, self.matrix_track(e.track)?)))
            .collect::<Result<Vec<_>, crate::Error>>()?;
        Demodulation::of_matrices(matrices)
    }

    /// Sky `(q, u)` of a measured `(q, u)` demodulated from `exposures` that each saw the chain
    /// over their own track: subtract `(q0, u0)` when `constant`, then solve
    /// [`Demodulation::forward`]`(q, u) = measured` (Newton's method from the solution over the
    /// set's whole track, [`BandModel::correct_track`], with the forward model's exact
    /// Jacobian by central differences; the model is linear-fractional in `(q, u)` and
    /// converges in a few steps). Where all exposures share one track this is
    /// [`BandModel::correct_track`]'s answer.
    pub fn correct_exposures(
        &self,
        q: f64,
        u: f64,
        demod: &Demodulation,
        whole: Track,
        constant: bool,
    ) -> Result<(f64, f64), crate::Error> {
        let (c0, c1) = if constant { (self.q0, self.u0) } else { (0.0, 0.0) };
        let start = self.correct_track(q, u, whole, constant)?;
        demod.solve((q - c0, u - c1), start)
    }
}

/// The parallactic angle (rad) of a star of declination `dec` at hour angle `ha` (rad, positive
/// west of the meridian) seen from latitude `lat`: the position angle of the zenith at the
/// star, north through east, `q = atan2(sin H cos phi, sin phi cos dec - cos phi sin dec cos H)`
/// (spherical triangle pole-zenith-star; positive west of the meridian). For simulated nights.
///
/// ```
/// use mueller::telescope::parallactic_angle;
/// let (lat, rad) = ((-29.26f64).to_radians(), |d: f64| d.to_radians());
/// // On the meridian a star south of the zenith has the zenith due north (0); north of it, due
/// // south (180 deg).
/// assert!(parallactic_angle(lat, rad(-60.0), 0.0).abs() < 1e-12);
/// assert!((parallactic_angle(lat, rad(0.0), 0.0).abs() - std::f64::consts::PI).abs() < 1e-12);
/// // Elsewhere the classic form tan q = sin H / (tan phi cos dec - sin dec cos H).
/// let (dec, ha) = (rad(-10.0), rad(30.0));
/// let q = ha.sin().atan2(lat.tan() * dec.cos() - dec.sin() * ha.cos());
/// assert!((parallactic_angle(lat, dec, ha) - q).abs() < 1e-12);
/// ```
pub fn parallactic_angle(lat: f64, dec: f64, ha: f64) -> f64 {
    (ha.sin() * lat.cos()).atan2(lat.sin() * dec.cos() - lat.cos() * dec.sin() * ha.cos())
}

/// The parallactic-angle track of an exposure of a star at `dec` from hour angle `ha_start` to
/// `ha_end` (rad) at latitude `lat`: its end angle unwrapped to the start (`Track::new`). The
/// angle is not linear in time; for exposures of minutes away from the zenith the error of
/// the uniform sweep that [`track_average`] assumes is second order in the turn.
pub fn exposure_track(lat: f64, dec: f64, ha_start: f64, ha_end: f64) -> Track {
    Track::new(parallactic_angle(lat, dec, ha_start), Some(parallactic_angle(lat, dec, ha_end)))
}

/// The parallactic-angle range of one exposure (rad, unwrapped: `end` may pass +-pi), swept at
/// a uniform rate from `start` to `end` (`instrument::Telescope::track` makes one from header
/// values). A single angle is `start == end`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Track {
    pub start: f64,
    pub end: f64,
    /// The rotator / adapter angle `rho` (rad) during the exposure, in the sense of
    /// [`crate::rotation`] (the instrument axes turned by `rho` from +x towards +y: a
    /// polarization angle `chi` reads `chi - rho`): the chain is `R(offset + rho) M3(plane at
    /// pi/2 - q)`, so `offset` is the instrument's angle zero at rotator angle 0. An
    /// instrument whose rotator keeps one position (EFOSC2's adapter in Wiersema et al. 2018)
    /// has `rho = 0` throughout and its fixed angle inside `offset`.
    #[serde(default)]
    pub rotator: f64,
}

impl Track {
    /// A track of zero length (an instant, or a measurement that gives one angle).
    pub fn at(parallactic: f64) -> Self {
        Track { start: parallactic, end: parallactic, rotator: 0.0 }
    }

    /// This track with the rotator at `rho` (rad, [`Track::rotator`]).
    pub fn with_rotator(self, rho: f64) -> Self {
        Track { rotator: rho, ..self }
    }

    /// The track of an exposure from the angles (rad) at its start and end as a header or a
    /// catalog gives them (each in (-pi, pi] or any other turn): `end` is moved by whole turns
    /// to lie within pi of `start`, the short way round (an exposure does not turn by half a
    /// circle; near the zenith, where it might, split the exposure). No end: an instant.
    pub fn new(start: f64, end: Option<f64>) -> Self {
        match end {
            None => Track::at(start),
            Some(e) => Track { start, end: start + 2.0 * crate::wrap_half_pi(0.5 * (e - start)), rotator: 0.0 },
        }
    }
}

/// `sin(x) / x`, stable at 0.
fn sinc(x: f64) -> f64 {
    if x.abs() < 1e-4 {
        1.0 - x * x / 6.0
    } else {
        x.sin() / x
    }
}

/// The mean over `track` of `m(q)`, a Mueller matrix that depends on the parallactic angle `q`
/// through a mirror's plane of incidence (`R(a) M R(a)` with `a` linear in `q`, as in
/// [`wiersema_m3`] and [`crate::mirror::nasmyth`]): every element is then a trigonometric
/// polynomial in `2q` of degree 2. Its five harmonics are found exactly from eight samples over
/// a period (a discrete Fourier transform; degree 2 < 8 / 2, no aliasing), and each averages in
/// closed form: `mean of exp(2inq) over [a, b] = exp(2in (a+b)/2) sinc(n (b - a))`. Exact for
/// any track length, and the matrix at the angle itself for a zero-length track.
pub fn track_average<E>(m: impl Fn(f64) -> Result<Matrix4<f64>, E>, track: Track) -> Result<Matrix4<f64>, E> {
    let len = track.end - track.start;
    if len == 0.0 {
        return m(track.start);
    }
    const N: usize = 8;
    let samples: Vec<(f64, Matrix4<f64>)> = (0..N)
        .map(|j| {
            let q = std::f64::consts::PI * j as f64 / N as f64;
            m(q).map(|v| (q, v))
        })
        .collect::<Result<_, E>>()?;
    let mid = 0.5 * (track.start + track.end);
    let mut out = Matrix4::zeros();
    for n in 0..=2i32 {
        // c_n = (1/N) sum_j m(q_j) exp(-2 i n q_j); the pair n, -n gives 2 Re(c_n exp(2inq)).
        let (mut re, mut im) = (Matrix4::<f64>::zeros(), Matrix4::<f64>::zeros());
        for (q, v) in &samples {
            let (s, c) = (2.0 * n as f64 * q).sin_cos();
            re += v * c;
            im -= v * s;
        }
        re /= N as f64;
        im /= N as f64;
        let (s, c) = (2.0 * n as f64 * mid).sin_cos();
        let w = if n == 0 { 1.0 } else { 2.0 } * sinc(n as f64 * len);
        out += (re * c - im * s) * w;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mirror::MetalTable;

    /// An aluminium M3 in V with a 7 nm oxide, offset 0.7 rad.
    fn aluminium_v(factor: f64, q0: f64, u0: f64) -> BandModel {
        let t = MetalTable::builtin("aluminium").unwrap();
        BandModel { wavelength_um: 0.55, index: t.index(0.55).unwrap(), factor, thickness_nm: 7.0, offset: 0.7, q0, u0 }
    }

    /// The demodulation's analytic Jacobian: the identity through ideal optics (eq:Q, eq:U
    /// give back the sky), the derivatives of the closed form through a partial polarizer
    /// along `Q` of degree `p` seen at four angles (`eq:instpol` normalized:
    /// `q' = (q + p) / (1 + p q)`, `u' = u (1 - p) / (1 + p q)`), and central differences of
    /// the forward model through a telescope's exposures.
    #[test]
    fn demodulation_jacobian_is_the_derivative_of_its_forward_model() {
        let angles = [0.0, 22.5, 45.0, 67.5].map(f64::to_radians);
        let ideal = Demodulation::of_matrices(angles.iter().map(|&a| (a, Matrix4::identity()))).unwrap();
        let j = ideal.jacobian(0.03, -0.02);
        assert!((j[0][0] - 1.0).abs() < 1e-15 && (j[1][1] - 1.0).abs() < 1e-15, "{j:?}");
        assert!(j[0][1].abs() < 1e-15 && j[1][0].abs() < 1e-15, "{j:?}");
        let p = 0.04;
        let pol = crate::partial_polarizer(p, 0.0);
        let d = Demodulation::of_matrices(angles.iter().map(|&a| (a, pol))).unwrap();
        let (q, u) = (0.03, -0.02);
        let den = 1.0 + p * q;
        let want = [[(1.0 - p * p) / (den * den), 0.0], [-u * (1.0 - p) * p / (den * den), (1.0 - p) / den]];
        let got = d.jacobian(q, u);
        for i in 0..2 {
            for k in 0..2 {
                assert!((got[i][k] - want[i][k]).abs() < 1e-15, "{got:?} vs {want:?}");
            }
        }
        let b = aluminium_v(0.85, 0.0, 0.0);
        let exposures: Vec<Exposure> = angles
            .iter()
            .enumerate()
            .map(|(k, &a)| Exposure { hwp: a, track: Track::new(0.2 * k as f64, Some(0.2 * k as f64 + 0.15)) })
            .collect();
        let d = b.demodulation(&exposures).unwrap();
        let h = 1e-6;
        let j = d.jacobian(q, u);
        for k in 0..2 {
            let dq = if k == 0 { h } else { 0.0 };
            let du = if k == 1 { h } else { 0.0 };
            let (a, c) = (d.forward(q + dq, u + du), d.forward(q - dq, u - du));
            for (i, fd) in [(a.0 - c.0) / (2.0 * h), (a.1 - c.1) / (2.0 * h)].into_iter().enumerate() {
                assert!((j[i][k] - fd).abs() < 1e-8, "d{i}/d{k}: {} vs {fd}", j[i][k]);
            }
        }
    }

    #[test]
    fn track_average_is_the_fine_numerical_mean_not_the_matrix_at_the_mean_angle() {
        let b = aluminium_v(0.85, 0.0, 0.0);
        let d = f64::to_radians;
        for (a, e) in [(10.0, 10.0), (10.0, 12.0), (-30.0, 30.0), (170.0, 185.0), (-80.0, 120.0), (0.0, 360.0)] {
            let track = Track { start: d(a), end: d(e), rotator: 0.0 };
            let avg = b.matrix_track(track).unwrap();
            // Midpoint rule over 20000 slices of the track, matrix by matrix.
            let n = 20_000;
            let mut fine = Matrix4::zeros();
            for k in 0..n {
                let q = d(a) + (d(e) - d(a)) * (k as f64 + 0.5) / n as f64;
                fine += b.matrix(q).unwrap();
            }
            fine /= n as f64;
            if a == e {
                fine = b.matrix(d(a)).unwrap();
            }
            assert!((avg - fine).abs().max() < 1e-9, "{a}..{e}: {}", (avg - fine).abs().max());
            // A long track blurs the polarization: the mean matrix is not the matrix at the
            // mean angle (over a full turn, an unpolarized star comes out unpolarized).
            let at_mid = b.matrix(d(0.5 * (a + e))).unwrap();
            let pol = |m: &Matrix4<f64>| crate::hypot(m[(1, 0)], m[(2, 0)]) / m[(0, 0)];
            if e - a >= 60.0 {
                assert!(pol(&avg) < 0.95 * pol(&at_mid), "{a}..{e}: {} vs {}", pol(&avg), pol(&at_mid));
            }
            if e - a == 360.0 {
                assert!(pol(&avg) < 1e-12, "{}", pol(&avg));
            }
        }
        // The correction over a track inverts the track's mean matrix: a star measured through
        // it (the fine mean) comes back.
        let track = Track { start: d(-40.0), end: d(25.0), rotator: 0.0 };
        let sky = Stokes::new(1.0, 0.02, -0.01, 0.0);
        let n = 4000;
        let mut meas = Stokes::zeros();
        for k in 0..n {
            meas += b.matrix(d(-40.0) + d(65.0) * (k as f64 + 0.5) / n as f64).unwrap() * sky;
        }
        let (q, u) = b.correct_track(meas[1] / meas[0], meas[2] / meas[0], track, true).unwrap();
        assert!((q - 0.02).abs() < 1e-7 && (u + 0.01).abs() < 1e-7, "{q} {u}");
    }

    #[test]
    fn track_goes_the_short_way_across_the_wrap() {
        let d = f64::to_radians;
        let t = Track::new(d(170.0), Some(d(-175.0)));
        assert!((t.start - d(170.0)).abs() < 1e-12 && (t.end - d(185.0)).abs() < 1e-12, "{t:?}");
        let t = Track::new(d(-175.0), Some(d(170.0)));
        assert!((t.end - d(-190.0)).abs() < 1e-12, "{t:?}");
        let t = Track::new(d(10.0), Some(d(30.0)));
        assert!((t.end - d(30.0)).abs() < 1e-12, "{t:?}");
        assert_eq!(Track::new(0.3, None), Track::at(0.3));
    }

    /// Dual-beam fluxes written out in the test: each exposure's light through the chain over
    /// its own track, a half-wave plate at theta (its Mueller matrix written here) and the
    /// Wollaston's two beams, `F = (f_o - f_e) / (f_o + f_e)`, then eq:Q, eq:U over the angles
    /// (repeats at one angle summed first, as the reduction sums their fluxes).
    fn dual_beam(b: &BandModel, sky: (f64, f64), set: &[(f64, Track)]) -> (f64, f64) {
        let s = Stokes::new(1.0, sky.0, sky.1, 0.0);
        let mut by_angle: Vec<(f64, f64, f64)> = vec![]; // theta, sum f_o, sum f_e
        for &(theta, track) in set {
            let (s4, c4) = (4.0 * theta).sin_cos();
            #[rustfmt::skip]
            let hwp = Matrix4::new(
                1.0, 0.0, 0.0, 0.0,
                0.0, c4, s4, 0.0,
                0.0, s4, -c4, 0.0,
                0.0, 0.0, 0.0, -1.0,
            );
            let v = hwp * (b.matrix_track(track).unwrap() * s);
            let (fo, fe) = (0.5 * (v[0] + v[1]), 0.5 * (v[0] - v[1]));
            match by_angle.iter_mut().find(|a| a.0 == theta) {
                Some(a) => {
                    a.1 += fo;
                    a.2 += fe;
                }
                None => by_angle.push((theta, fo, fe)),
            }
        }
        let n = by_angle.len() as f64;
        by_angle.iter().fold((0.0, 0.0), |(q, u), &(t, fo, fe)| {
            let f = (fo - fe) / (fo + fe);
            (q + 2.0 / n * f * (4.0 * t).cos(), u + 2.0 / n * f * (4.0 * t).sin())
        })
    }

    /// Exposures that each saw the mirror at their own parallactic angles: the sky comes back
    /// from the dual-beam fluxes to 1e-12 (where the whole set's average track leaves an error
    /// of the order of the mirror's polarization change over the set), for 4, 8 and 16 angles,
    /// repeated angles and turns through the meridian; one shared track gives
    /// `correct_track`'s answer; one angle alone is refused.
    #[test]
    fn exposures_are_undone_each_at_its_own_track() {
        let b = aluminium_v(0.86, 0.001, -0.0005);
        let d = f64::to_radians;
        let sky = (0.012, -0.021);
        let sets: Vec<Vec<(f64, Track)>> = vec![
            // Four angles, 20 deg of parallactic angle each, one after the other.
            (0..4)
                .map(|i| (d(22.5 * i as f64), Track::new(d(-40.0 + 20.0 * i as f64), Some(d(-22.0 + 20.0 * i as f64)))))
                .collect(),
            // Sixteen angles through the meridian (the angle runs fast there).
            (0..16)
                .map(|i| (d(22.5 * i as f64), Track::new(d(-80.0 + 10.0 * i as f64), Some(d(-72.0 + 10.0 * i as f64)))))
                .collect(),
            // Eight angles, each repeated later in the night.
            (0..16)
                .map(|i| {
                    (d(22.5 * (i % 8) as f64), Track::new(d(30.0 + 4.0 * i as f64), Some(d(33.0 + 4.0 * i as f64))))
                })
                .collect(),
        ];
        for (k, set) in sets.iter().enumerate() {
            let (qm, um) = dual_beam(&b, sky, set);
            let (qm, um) = (qm + b.q0, um + b.u0);
            let whole = Track::new(set[0].1.start, Some(set.last().unwrap().1.end));
            let ex: Vec<Exposure> = set.iter().map(|&(hwp, track)| Exposure { hwp, track }).collect();
            let demod = b.demodulation(&ex).unwrap();
            let (q, u) = b.correct_exposures(qm, um, &demod, whole, true).unwrap();
            assert!((q - sky.0).abs() < 1e-12 && (u - sky.1).abs() < 1e-12, "set {k}: ({q}, {u}) vs {sky:?}");
            let (qa, ua) = b.correct_track(qm, um, whole, true).unwrap();
            let off = (qa - sky.0).hypot(ua - sky.1);
            assert!(off > 1e-5, "set {k}: the average track is off by {off} only: the test shows nothing");
        }
        // One track shared by every exposure: the whole track's inversion.
        let track = Track::new(d(10.0), Some(d(25.0)));
        let set: Vec<(f64, Track)> = (0..4).map(|i| (d(22.5 * i as f64), track)).collect();
        let (qm, um) = dual_beam(&b, sky, &set);
        let ex: Vec<Exposure> = set.iter().map(|&(hwp, track)| Exposure { hwp, track }).collect();
        let demod = b.demodulation(&ex).unwrap();
        let (q, u) = b.correct_exposures(qm, um, &demod, track, false).unwrap();
        let (qt, ut) = b.correct_track(qm, um, track, false).unwrap();
        assert!((q - qt).abs() < 1e-14 && (u - ut).abs() < 1e-14);
        assert!((q - sky.0).abs() < 1e-12 && (u - sky.1).abs() < 1e-12);
        let one = [Exposure { hwp: 0.0, track }, Exposure { hwp: 0.0, track }];
        assert!(b.demodulation(&one).is_err());
    }
}
