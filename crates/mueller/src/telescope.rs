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
        let meas = [q - c0, u - c1];
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
}

/// The parallactic angle (rad) of a star of declination `dec` at hour angle `ha` (rad, positive
/// west of the meridian) seen from latitude `lat`: the position angle of the zenith at the
/// star, north through east, `q = atan2(sin H cos phi, sin phi cos dec - cos phi sin dec cos H)`
/// (spherical triangle pole-zenith-star; positive west of the meridian). For simulated nights.
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

    #[test]
    fn track_average_is_the_fine_numerical_mean_not_the_matrix_at_the_mean_angle() {
        let t = MetalTable::builtin("aluminium").unwrap();
        let b = BandModel {
            wavelength_um: 0.55,
            index: t.index(0.55).unwrap(),
            factor: 0.85,
            thickness_nm: 7.0,
            offset: 0.7,
            q0: 0.0,
            u0: 0.0,
        };
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
}
