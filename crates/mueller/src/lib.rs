//! Stokes vectors and Mueller matrices of the optics of a dual-beam polarimeter, and the
//! dual-beam forward model.
//!
//! This crate knows the *optics*: what each element (telescope and collimator as a partial
//! polarizer, half-wave plate with its defects, Wollaston prism, post-analyzer optics) does to
//! a Stokes vector, and what fluxes `f_O,i`, `f_E,i` a train of elements puts on the detector
//! at each half-wave-plate angle. It does not reduce measurements (that is the `stokes` crate)
//! and knows nothing of files or frames.
//!
//! Modules: [`fresnel`] (interface coefficients, dielectric and metal), [`thinfilm`]
//! (characteristic-matrix coatings), [`mirror`] (telescope mirrors: metals with over-layers,
//! tabulated n, k, the sky / alt-az / instrument rotations and the Nasmyth train), [`analysis`] (Jones to Mueller, realizability, inverse,
//! diattenuation / retardance), [`raytrace`] (polarization ray tracing of a lens collimator
//! from its prescription: the field pattern `p(r)`, `phi(alpha)` and its wavelength law),
//! [`telescope`] (the telescope term: M3 with the parallactic and rotator angles, averaged over
//! an exposure's track; fitted by `fit::telescope`, simulated by `sim`).
//!
//! Conventions (those of the whole workspace, `docs/architecture.md`):
//! - angles in radians; polarization angle `chi` measured as `eq:polang`, `Q/I = P cos 2chi`;
//! - a Stokes vector is `(I, Q, U, V)`; circular polarization follows the IAU convention
//!   (V > 0 for counter-clockwise rotation of the electric vector as seen by the observer);
//!   a linear retarder with its fast axis at 0 and retardance +pi/2 turns +45 deg linear
//!   light into V > 0; in Jones terms (time dependence `exp(-i omega t)`),
//!   `V = 2 Im(E_x^* E_y)` ([`analysis`]);
//! - an element at angle `theta` is `R(-theta) M(0) R(theta)` ([`rotate`]).

use nalgebra::{Matrix4, RowVector4, Vector4};
use serde::{Deserialize, Serialize};

pub mod analysis;
pub mod causes;
pub mod fresnel;
pub mod linear;
pub mod mirror;
pub mod qu;
pub mod raytrace;
pub mod telescope;
pub mod thinfilm;

pub use analysis::{inverse, is_physical, jones_to_mueller};
pub use fresnel::C64;
pub use qu::{sandwich, Frame, PolErrors, Qu};

/// A Stokes vector `(I, Q, U, V)`.
pub type Stokes = Vector4<f64>;
/// A 4 x 4 Mueller matrix.
pub type Mueller = Matrix4<f64>;

/// Errors of this crate: each says which parameter was out of its physical range.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum Error {
    #[error("{name} = {value} is outside its physical range {range}")]
    OutOfRange { name: &'static str, value: f64, range: &'static str },
    #[error("matrix is singular and cannot be inverted: {0}")]
    Singular(&'static str),
    /// A bad optical prescription or trace input; `what` names the surface or key.
    #[error("{what}: {why}")]
    Invalid { what: String, why: String },
}

/// Stokes vector of intensity `i` with normalized linear polarization `q = Q/I`, `u = U/I`.
pub fn stokes_qu(i: f64, q: f64, u: f64) -> Stokes {
    Stokes::new(i, i * q, i * u, 0.0)
}

/// Stokes vector from intensity, polarization degree `p` (fraction) and angle `chi` (rad); `eq:QU`.
///
/// ```
/// // eq:QU: 2 % at chi = 30 deg is Q/I = 0.02 cos 60 deg = 0.01, U/I = 0.02 sin 60 deg.
/// let s = mueller::stokes_p_chi(1000.0, 0.02, 30f64.to_radians());
/// assert!((s[1] - 10.0).abs() < 1e-12 && (s[2] - 1000.0 * 0.02 * 3f64.sqrt() / 2.0).abs() < 1e-12);
/// assert_eq!(s[3], 0.0);
/// ```
pub fn stokes_p_chi(i: f64, p: f64, chi: f64) -> Stokes {
    let (s, c) = (2.0 * chi).sin_cos();
    Stokes::new(i, i * p * c, i * p * s, 0.0)
}

/// `sqrt(a^2 + b^2)` without undue overflow or underflow, like `f64::hypot`, but about five
/// times cheaper where the squares are representable (libm's hypot is correctly rounded and
/// slow; this is within about one ulp of it there), and `f64::hypot` itself where they are
/// not. The one hypot of the hot paths: polarization degrees, radii, `sigma_F`.
#[inline]
pub fn hypot(a: f64, b: f64) -> f64 {
    let s = a * a + b * b;
    if s.is_finite() && s > 1e-290 {
        s.sqrt()
    } else {
        a.hypot(b)
    }
}

/// Angle `a` (rad) modulo pi, in [0, pi): the range of polarization angles (`eq:polang`).
/// `rem_euclid` alone returns pi itself for tiny negative inputs (-1e-17 + pi rounds to pi).
///
/// ```
/// use mueller::fold_pi;
/// // The paper's V sky angle, -53.8 deg, is the polarization angle 126.2 deg in [0, 180).
/// assert!((fold_pi((-53.8f64).to_radians()).to_degrees() - 126.2).abs() < 1e-12);
/// assert_eq!(fold_pi(-1e-17), 0.0); // not pi
/// ```
#[inline]
pub fn fold_pi(a: f64) -> f64 {
    let r = a.rem_euclid(std::f64::consts::PI);
    if r >= std::f64::consts::PI {
        0.0
    } else {
        r
    }
}

/// Whether `v` reads as an angle in degrees as the workspace's inputs give them (a header's
/// zero angle or parallactic angle, a table's or an array's): finite and within two turns either
/// way. The one rule of such inputs: a value beyond is not an angle of a plate or a sky (a
/// count, an uninitialised keyword) and is refused by its reader.
///
/// ```
/// assert!(mueller::plausible_degrees(-1.8) && mueller::plausible_degrees(720.0));
/// assert!(!mueller::plausible_degrees(f64::NAN) && !mueller::plausible_degrees(1e5));
/// ```
#[inline]
pub fn plausible_degrees(v: f64) -> bool {
    v.is_finite() && v.abs() <= 720.0
}

/// Angle `a` (rad) wrapped into (-pi/2, pi/2]: a difference of polarization angles, which are
/// defined modulo pi.
///
/// ```
/// use mueller::wrap_half_pi;
/// // 179 deg and 1 deg differ by 2 deg as polarization angles, not by 178.
/// let d = wrap_half_pi(179f64.to_radians() - 1f64.to_radians());
/// assert!((d.to_degrees() + 2.0).abs() < 1e-12);
/// ```
#[inline]
pub fn wrap_half_pi(a: f64) -> f64 {
    let pi = std::f64::consts::PI;
    let r = (a + 0.5 * pi).rem_euclid(pi) - 0.5 * pi;
    if r <= -0.5 * pi {
        r + pi
    } else {
        r
    }
}

/// The Stokes rotation matrix `R(theta)`: the same light described in axes rotated by `theta`.
///
/// ```
/// // Light at chi = 30 deg, described in axes turned by 30 deg, is at chi = 0: Q/I = 1, U/I = 0.
/// let s = mueller::rotation(30f64.to_radians()) * mueller::stokes_p_chi(1.0, 1.0, 30f64.to_radians());
/// assert!((s[1] - 1.0).abs() < 1e-15 && s[2].abs() < 1e-15);
/// ```
pub fn rotation(theta: f64) -> Mueller {
    let (s, c) = (2.0 * theta).sin_cos();
    #[rustfmt::skip]
    let m = Mueller::new(
        1.0, 0.0, 0.0, 0.0,
        0.0, c,   s,   0.0,
        0.0, -s,  c,   0.0,
        0.0, 0.0, 0.0, 1.0,
    );
    m
}

/// An element `m0` (given with its axis at 0) turned to angle `theta`: `R(-theta) m0 R(theta)`.
pub fn rotate(m0: &Mueller, theta: f64) -> Mueller {
    rotation(-theta) * m0 * rotation(theta)
}

/// The paper's partial polarizer `M_I(p, phi)` of section `sec:instr`: a fraction of an ideal
/// polarizer at angle `phi` mixed with clear glass, normalized by `1 / (1 + p)` so that the
/// largest transmission is 1. `M_I(0) = 1`, `M_I(1)` is an ideal polarizer. The `V` row, which
/// the paper drops, follows from the same mixture: `V' = (1 - p) / (1 + p) V`.
/// Its action on `(I, Q, U)` is `eq:instpol`.
///
/// ```
/// use mueller::{partial_polarizer, stokes_p_chi};
/// // Largest transmission 1 (light along phi), smallest (1 - p)/(1 + p) (perpendicular):
/// // the diattenuation (Tmax - Tmin)/(Tmax + Tmin) is p.
/// let (p, phi) = (0.012, 20f64.to_radians());
/// let m = partial_polarizer(p, phi);
/// let t_max = (m * stokes_p_chi(1.0, 1.0, phi))[0];
/// let t_min = (m * stokes_p_chi(1.0, 1.0, phi + std::f64::consts::FRAC_PI_2))[0];
/// assert!((t_max - 1.0).abs() < 1e-15 && (t_min - (1.0 - p) / (1.0 + p)).abs() < 1e-15);
/// assert!(((t_max - t_min) / (t_max + t_min) - p).abs() < 1e-15);
/// ```
pub fn partial_polarizer(p: f64, phi: f64) -> Mueller {
    let (s, c) = (2.0 * phi).sin_cos();
    let k = 1.0 / (1.0 + p);
    #[rustfmt::skip]
    let m = Mueller::new(
        1.0,   p * c,             p * s,             0.0,
        p * c, 1.0 - p * s * s,   p * c * s,         0.0,
        p * s, p * c * s,         1.0 - p * c * c,   0.0,
        0.0,   0.0,               0.0,               1.0 - p,
    );
    m * k
}

/// The physical linear diattenuator with principal intensity transmittances `k1` (along the
/// axis at `angle`) and `k2` (perpendicular to it).
///
/// ```
/// // Transmittances 0.9 along 0 deg and 0.5 across: unpolarized light leaves with
/// // I = (0.9 + 0.5)/2 = 0.7 and P = (0.9 - 0.5)/(0.9 + 0.5) = 2/7 along 0 deg.
/// let s = mueller::diattenuator(0.9, 0.5, 0.0) * mueller::stokes_qu(1.0, 0.0, 0.0);
/// assert!((s[0] - 0.7).abs() < 1e-15 && (s[1] / s[0] - 2.0 / 7.0).abs() < 1e-15);
/// ```
pub fn diattenuator(k1: f64, k2: f64, angle: f64) -> Mueller {
    let a = 0.5 * (k1 + k2);
    let b = 0.5 * (k1 - k2);
    let g = (k1 * k2).max(0.0).sqrt();
    #[rustfmt::skip]
    let m0 = Mueller::new(
        a,   b,   0.0, 0.0,
        b,   a,   0.0, 0.0,
        0.0, 0.0, g,   0.0,
        0.0, 0.0, 0.0, g,
    );
    rotate(&m0, angle)
}

/// Ideal linear polarizer transmitting along `angle` (a diattenuator with k1 = 1, k2 = 0).
///
/// ```
/// use mueller::{polarizer, stokes_p_chi};
/// // Malus's law: light polarized at 0 through a polarizer at 30 deg keeps cos^2 30 deg = 3/4.
/// let s = polarizer(30f64.to_radians()) * stokes_p_chi(1.0, 1.0, 0.0);
/// assert!((s[0] - 0.75).abs() < 1e-15);
/// // Crossed polarizers pass nothing.
/// let crossed = polarizer(std::f64::consts::FRAC_PI_2) * polarizer(0.0) * mueller::stokes_qu(1.0, 0.0, 0.0);
/// assert!(crossed[0].abs() < 1e-16);
/// ```
pub fn polarizer(angle: f64) -> Mueller {
    diattenuator(1.0, 0.0, angle)
}

/// Linear retarder of retardance `delta` (rad) with its fast axis at `angle`.
/// A half-wave plate is `delta = pi + Delta beta` (section `sec:HWP`).
///
/// The slow axis lags by `delta`: with the fast axis at 0 and `delta = +pi/2`, light linearly
/// polarized at +45 deg leaves with the electric vector turning from +x towards +y, which is
/// counter-clockwise as seen by the observer in the IAU frame (x north, y east, z towards the
/// observer), i.e. `V > 0` (tested in `tests::iau_circular_sign`).
///
/// ```
/// use mueller::{retarder, stokes_p_chi};
/// use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};
/// // A half-wave plate at 22.5 deg turns chi = 0 into chi = 45 deg (chi -> 2 theta - chi).
/// let s = retarder(PI, 22.5f64.to_radians()) * stokes_p_chi(1.0, 1.0, 0.0);
/// assert!(s[1].abs() < 1e-15 && (s[2] - 1.0).abs() < 1e-15);
/// // A quarter-wave plate at 0 makes +45 deg light circular with V > 0 (IAU).
/// let s = retarder(FRAC_PI_2, 0.0) * stokes_p_chi(1.0, 1.0, FRAC_PI_4);
/// assert!((s[3] - 1.0).abs() < 1e-15 && s[2].abs() < 1e-15);
/// ```
pub fn retarder(delta: f64, angle: f64) -> Mueller {
    let (s, c) = delta.sin_cos();
    #[rustfmt::skip]
    let m0 = Mueller::new(
        1.0, 0.0, 0.0, 0.0,
        0.0, 1.0, 0.0, 0.0,
        0.0, 0.0, c,   -s,
        0.0, 0.0, s,   c,
    );
    rotate(&m0, angle)
}

/// A periodic defect of the half-wave plate that follows the plate as it turns, seen by the
/// analyzer as a harmonic of the HWP angle in `F_i` (section `sec:HWP`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Harmonic {
    /// Amplitude of the spurious modulation of `F` (fraction).
    pub amplitude: f64,
    /// Phase (rad).
    pub phase: f64,
}

/// The polarimeter's wave plate: retardance `nominal_retardance + retardance_error` (a linear
/// [`retarder`]), fast axis at the commanded angle plus `chi_offset / 2`, and optional defects.
/// The half-wave plate of linear polarimetry (`nominal_retardance = pi`, [`Hwp::ideal`],
/// section `sec:HWP`) and the quarter-wave plate of circular polarimetry (`pi / 2`,
/// [`Hwp::quarter_wave`]) are this one type; everything below holds for both.
///
/// `chi_offset` is the chromatic zero angle expressed, as instruments tabulate it for a
/// half-wave plate, as the polarization-angle correction to *add* to a measured chi: a plate
/// whose axis sits at `theta + chi_offset / 2` makes every measured chi smaller by
/// `chi_offset`. For a quarter-wave plate it is likewise twice the fast axis's offset from
/// the commanded angle.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Hwp {
    /// The plate's design retardance (rad): `pi` for a half-wave plate, `pi / 2` for a
    /// quarter-wave plate.
    #[serde(default = "half_wave")]
    pub nominal_retardance: f64,
    pub retardance_error: f64,
    pub chi_offset: f64,
    /// k = 1 harmonic (dust, dirt: repeats after a full turn): a weak partial polarizer aligned
    /// with the analyzer whose signed strength is `amplitude * cos(theta - phase)`.
    pub dust: Option<Harmonic>,
    /// k = 2 harmonic (pleochroism: period pi): a weak partial polarizer fixed to the plate,
    /// at angle `theta + phase / 2`, of strength `amplitude`.
    pub pleochroism: Option<Harmonic>,
}

fn half_wave() -> f64 {
    std::f64::consts::PI
}

impl Default for Hwp {
    /// The ideal half-wave plate.
    fn default() -> Self {
        Self { nominal_retardance: half_wave(), retardance_error: 0.0, chi_offset: 0.0, dust: None, pleochroism: None }
    }
}

impl Hwp {
    /// The ideal half-wave plate.
    pub fn ideal() -> Self {
        Self::default()
    }

    /// The ideal quarter-wave plate (retardance `pi / 2`): with its fast axis at 0 it turns
    /// +45 deg linear light into `V > 0` (IAU, the crate's convention).
    ///
    /// ```
    /// use mueller::{stokes_p_chi, Hwp};
    /// let s = Hwp::quarter_wave().matrix(0.0) * stokes_p_chi(1.0, 1.0, std::f64::consts::FRAC_PI_4);
    /// assert!((s[3] - 1.0).abs() < 1e-15 && s[1].abs() < 1e-15 && s[2].abs() < 1e-15);
    /// ```
    pub fn quarter_wave() -> Self {
        Self { nominal_retardance: std::f64::consts::FRAC_PI_2, ..Self::default() }
    }

    /// Whether this is a quarter-wave plate (nominal retardance `pi / 2`).
    pub fn is_quarter_wave(&self) -> bool {
        self.nominal_retardance == std::f64::consts::FRAC_PI_2
    }

    /// Mueller matrix of the plate (with its defects) at commanded angle `theta`.
    /// Only the defects that are present are computed.
    pub fn matrix(&self, theta: f64) -> Mueller {
        let mut m = retarder(self.nominal_retardance + self.retardance_error, theta + 0.5 * self.chi_offset);
        if let Some(h) = self.pleochroism {
            m = partial_polarizer_signed(h.amplitude, theta + 0.5 * h.phase) * m;
        }
        if let Some(h) = self.dust {
            m = partial_polarizer_signed(h.amplitude * (theta - h.phase).cos(), 0.0) * m;
        }
        m
    }

    /// The plate's Mueller matrix averaged over an exposure during which it turns uniformly
    /// through `sweep` (rad) centred on the commanded angle `theta_mid` (the middle of the
    /// exposure's begin and end angles). `sweep = 0` is [`Self::matrix`] itself.
    ///
    /// Without defects the plate's matrix is `A_0 + A_2(2 phi) + A_4(4 phi)` (`phi = theta +
    /// chi_offset/2`: the retarder's elements are products of `cos 2 phi`, `sin 2 phi`), so its
    /// mean is `A_0 + sinc(d) A_2 + sinc(2d) A_4` at the middle angle ([`sweep_factor`] with
    /// `k = 2, 4`); the three parts are read off the matrix at `theta_mid + j pi/4`,
    /// `j = 0..3` (a 4-point discrete Fourier transform, exact for these harmonics). A plate
    /// with a dust or pleochroism harmonic has products of higher harmonics, and the dust's
    /// polarizer a kink where it changes sides: its mean is taken by 5-point Gauss-Legendre
    /// quadrature on panels of at most pi/64 between the kinks (error below 1e-12).
    pub fn matrix_swept(&self, theta_mid: f64, sweep: f64) -> Mueller {
        if sweep == 0.0 {
            return self.matrix(theta_mid);
        }
        if self.dust.is_none() && self.pleochroism.is_none() {
            let q = std::f64::consts::FRAC_PI_4;
            let g: [Mueller; 4] = std::array::from_fn(|j| self.matrix(theta_mid + j as f64 * q));
            let h0 = (g[0] + g[1] + g[2] + g[3]) / 4.0;
            let h4 = (g[0] - g[1] + g[2] - g[3]) / 4.0;
            let h2 = (g[0] - g[2]) / 2.0;
            return h0 + h2 * sweep_factor(2.0, sweep) + h4 * sweep_factor(4.0, sweep);
        }
        const X: [f64; 5] = [0.0, -0.5384693101056831, 0.5384693101056831, -0.906179845938664, 0.906179845938664];
        const W: [f64; 5] =
            [0.5688888888888889, 0.47862867049936647, 0.47862867049936647, 0.23692688505618908, 0.23692688505618908];
        // The dust harmonic's polarizer changes sides (a kink of the matrix) where
        // cos(theta - phase) = 0: the quadrature's pieces end there, so each is smooth.
        let (a, b) = (theta_mid - 0.5 * sweep.abs(), theta_mid + 0.5 * sweep.abs());
        let mut cuts = vec![a];
        if let Some(h) = self.dust {
            let pi = std::f64::consts::PI;
            let first = h.phase + 0.5 * pi + ((a - h.phase - 0.5 * pi) / pi).ceil() * pi;
            cuts.extend((0..).map(|n| first + n as f64 * pi).take_while(|&t| t < b).filter(|&t| t > a));
        }
        cuts.push(b);
        let mut sum = Mueller::zeros();
        for piece in cuts.windows(2) {
            let len = piece[1] - piece[0];
            let panels = (len / (std::f64::consts::PI / 64.0)).ceil().max(1.0) as usize;
            let h = len / panels as f64;
            for p in 0..panels {
                let c = piece[0] + (p as f64 + 0.5) * h;
                for (x, w) in X.iter().zip(W) {
                    sum += self.matrix(c + 0.5 * h * x) * (0.5 * w * h);
                }
            }
        }
        sum / (b - a)
    }
}

/// The factor by which a half-wave plate turning uniformly through `sweep` (rad) during an
/// exposure scales a modulation term of harmonic `k` of the plate angle: the mean of
/// `cos k theta` over `[theta_m - d/2, theta_m + d/2]` is
///
/// `(1/d) int cos k theta d theta = (sin(k theta_m + k d/2) - sin(k theta_m - k d/2)) / (k d)
///  = cos k theta_m * sin(k d/2) / (k d/2)`,
///
/// and the same factor multiplies `sin k theta_m`: the averaged term is the fixed plate's at
/// the middle angle `theta_m`, scaled by `sinc(k d / 2)`. For the modulation of `eq:F`
/// (`k = 4`, [`hwp_sweep_efficiency`]) that is `sin(2d) / (2d)`. Below `|k d / 2| = 1e-3` the
/// Taylor series `1 - x^2/6 + x^4/120` is used (its next term is below 3e-18), so that a
/// fixed plate (`d = 0`) gives exactly 1 and no `0/0` arises.
///
/// ```
/// // A sweep of 22.5 deg: the modulated terms of eq:F keep sin(pi/4)/(pi/4) = 0.9003.
/// let f = mueller::sweep_factor(4.0, 22.5f64.to_radians());
/// assert!((f - 0.900316316157106).abs() < 1e-14);
/// assert_eq!(mueller::sweep_factor(4.0, 0.0), 1.0);
/// ```
pub fn sweep_factor(k: f64, sweep: f64) -> f64 {
    let x = 0.5 * k * sweep;
    if x.abs() < 1e-3 {
        let x2 = x * x;
        1.0 - x2 / 6.0 * (1.0 - x2 / 20.0)
    } else {
        x.sin() / x
    }
}

/// The modulation efficiency of a half-wave plate that turns uniformly through `sweep` (rad)
/// during an exposure: `sin(2d) / (2d)` ([`sweep_factor`] of the `4 theta` terms of `eq:F`,
/// `eq:Q`, `eq:U`). 1 for a fixed plate, 0.9003 for 22.5 deg, 0 for 90 deg (the plate turns
/// through a whole modulation period: nothing is modulated).
pub fn hwp_sweep_efficiency(sweep: f64) -> f64 {
    sweep_factor(4.0, sweep)
}

/// `M_I(|p|, phi)` for `p >= 0`, `M_I(|p|, phi + pi/2)` for `p < 0`.
fn partial_polarizer_signed(p: f64, phi: f64) -> Mueller {
    if p >= 0.0 {
        partial_polarizer(p, phi)
    } else {
        partial_polarizer(-p, phi + std::f64::consts::FRAC_PI_2)
    }
}

/// The Wollaston prism as two analyzers (section `sec:wollaston`, `eq:WP`): the ordinary beam
/// transmits a fraction `2t` of the light polarized along 0, the extraordinary beam a fraction
/// `2s` of the light polarized along `pi/2 + delta_alpha`. The ideal prism has
/// `t = s = 1/2`, `delta_alpha = 0`; `eq:WP` is the case `s = 1 - t`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Wollaston {
    pub t: f64,
    pub s: f64,
    pub delta_alpha: f64,
}

impl Default for Wollaston {
    fn default() -> Self {
        Self { t: 0.5, s: 0.5, delta_alpha: 0.0 }
    }
}

impl Wollaston {
    /// The ideal prism.
    pub fn ideal() -> Self {
        Self::default()
    }
    /// The prism of `eq:WP`: `s = 1 - t`, orthogonal beams.
    pub fn with_t(t: f64) -> Self {
        Self { t, s: 1.0 - t, delta_alpha: 0.0 }
    }
    /// Mueller matrices of the ordinary and extraordinary beams.
    pub fn beams(&self) -> (Mueller, Mueller) {
        (polarizer(0.0) * (2.0 * self.t), polarizer(std::f64::consts::FRAC_PI_2 + self.delta_alpha) * (2.0 * self.s))
    }
    /// `kappa = (t - s) / (t + s)` (section `sec:wollaston`).
    ///
    /// ```
    /// // t = 0.55, s = 0.45: kappa = (t - s)/(t + s) = 0.1, and unpolarized light gives
    /// // F = (f_O - f_E)/(f_O + f_E) = 2t - 1 = 0.1 at every plate angle.
    /// let w = mueller::Wollaston::with_t(0.55);
    /// assert!((w.kappa() - 0.1).abs() < 1e-15);
    /// let f = mueller::DualBeam { wollaston: w, ..Default::default() }
    ///     .fluxes(&mueller::stokes_qu(1.0, 0.0, 0.0), &mueller::optimal_angles(4));
    /// assert!(f.iter().all(|b| ((b.f_o - b.f_e) / (b.f_o + b.f_e) - 0.1).abs() < 1e-15));
    /// ```
    pub fn kappa(&self) -> f64 {
        (self.t - self.s) / (self.t + self.s)
    }
}

/// The approximate post-analyzer matrix `M_PA(A, B, C, phi)` of section `sec:postwp`.
pub fn post_analyzer(a: f64, b: f64, c: f64, phi: f64) -> Mueller {
    let (s2, c2) = (2.0 * phi).sin_cos();
    #[rustfmt::skip]
    let m = Mueller::new(
        1.0,    b * c2, b * s2, 0.0,
        b * c2, 1.0,    0.0,    0.0,
        b * s2, 0.0,    c,      0.0,
        0.0,    0.0,    0.0,    c,
    );
    m * a
}

/// An optical element placed before the half-wave plate (telescope, collimator, ...).
#[derive(Debug, Clone, PartialEq)]
pub enum Element {
    /// The paper's `M_I(p, phi)`.
    PartialPolarizer { p: f64, phi: f64 },
    /// Physical diattenuator with transmittances `k1`, `k2` along / across `angle`.
    Diattenuator { k1: f64, k2: f64, angle: f64 },
    /// Linear retarder.
    Retarder { retardance: f64, angle: f64 },
    /// Any Mueller matrix (e.g. from the ray tracer).
    Matrix(Mueller),
    /// Transmission through a bare interface from a lossless medium `n_incident` into a medium
    /// of complex index `n` at angle of incidence `aoi`, with the plane of incidence at
    /// `plane_angle` ([`fresnel::Coefficients::mueller_t`]). Inputs outside their range give
    /// a zero matrix (no light): validate them with [`fresnel::interface`] first.
    Interface { n_incident: f64, n: C64, aoi: f64, plane_angle: f64 },
    /// Reflection by a mirror of complex index `n` in air ([`fresnel::mirror`]); same caveat.
    Mirror { n: C64, aoi: f64, plane_angle: f64 },
}

impl Element {
    /// The element's Mueller matrix.
    pub fn matrix(&self) -> Mueller {
        match *self {
            Element::PartialPolarizer { p, phi } => partial_polarizer(p, phi),
            Element::Diattenuator { k1, k2, angle } => diattenuator(k1, k2, angle),
            Element::Retarder { retardance, angle } => retarder(retardance, angle),
            Element::Matrix(m) => m,
            Element::Interface { n_incident, n, aoi, plane_angle } => fresnel::interface(n_incident, n, aoi)
                .map(|c| c.mueller_t(plane_angle))
                .unwrap_or_else(|_| Mueller::zeros()),
            Element::Mirror { n, aoi, plane_angle } => {
                fresnel::mirror(n, aoi, plane_angle).unwrap_or_else(|_| Mueller::zeros())
            }
        }
    }
}

/// A dual-beam polarimeter: elements before the plate (listed in the order light meets
/// them), the half-wave plate, the Wollaston prism and optional post-analyzer optics.
/// Absent elements cost nothing: an empty `pre` list or `post = None` is skipped, not
/// multiplied as an identity.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DualBeam {
    pub pre: Vec<Element>,
    pub hwp: Hwp,
    pub wollaston: Wollaston,
    pub post: Option<Mueller>,
}

/// The two fluxes measured at one HWP angle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BeamFluxes {
    pub f_o: f64,
    pub f_e: f64,
}

/// A [`DualBeam`] with everything that does not depend on the HWP angle composed once.
#[derive(Debug, Clone)]
pub struct CompiledDualBeam {
    pre: Option<Mueller>,
    hwp: Hwp,
    /// First rows of `post * beam`: the detector measures intensity only.
    row_o: RowVector4<f64>,
    row_e: RowVector4<f64>,
}

impl DualBeam {
    /// The ideal instrument: no pre-optics, ideal plate and prism, no post-analyzer optics.
    pub fn ideal() -> Self {
        Self::default()
    }

    /// Compose the angle-independent parts once.
    pub fn compile(&self) -> CompiledDualBeam {
        let pre = self.pre.iter().fold(None, |acc: Option<Mueller>, e| {
            let m = e.matrix();
            Some(match acc {
                None => m,
                Some(a) => m * a,
            })
        });
        let (o, e) = self.wollaston.beams();
        let (o, e) = match self.post {
            Some(p) => (p * o, p * e),
            None => (o, e),
        };
        CompiledDualBeam { pre, hwp: self.hwp, row_o: o.row(0).into_owned(), row_e: e.row(0).into_owned() }
    }

    /// The dual-beam forward model: the fluxes `f_O,i`, `f_E,i` for input Stokes vector `s`
    /// at HWP angles `theta` (rad). For the ideal train this is `eq:ord`; with a prism of
    /// `s = 1 - t` it is `eq:WP`.
    ///
    /// ```
    /// use mueller::{optimal_angles, stokes_p_chi, DualBeam};
    /// // eq:F for the ideal instrument: F_i = P cos(4 theta_i - 2 chi) = q cos 4theta_i + u sin 4theta_i.
    /// let (p, chi) = (0.02, 30f64.to_radians());
    /// let theta = optimal_angles(16);
    /// for (b, t) in DualBeam::ideal().fluxes(&stokes_p_chi(1.0, p, chi), &theta).iter().zip(&theta) {
    ///     let f = (b.f_o - b.f_e) / (b.f_o + b.f_e);
    ///     assert!((f - p * (4.0 * t - 2.0 * chi).cos()).abs() < 1e-15);
    /// }
    /// ```
    pub fn fluxes(&self, s: &Stokes, theta: &[f64]) -> Vec<BeamFluxes> {
        self.compile().fluxes(s, theta)
    }
}

impl CompiledDualBeam {
    /// The Stokes vector that reaches the plate.
    pub fn at_plate(&self, s: &Stokes) -> Stokes {
        match &self.pre {
            Some(m) => m * s,
            None => *s,
        }
    }

    /// Fluxes at one HWP angle for a Stokes vector already at the plate ([`Self::at_plate`]).
    pub fn fluxes_at_plate(&self, s_plate: &Stokes, theta: f64) -> BeamFluxes {
        let s2 = self.hwp.matrix(theta) * s_plate;
        BeamFluxes { f_o: (self.row_o * s2)[0], f_e: (self.row_e * s2)[0] }
    }

    /// Fluxes at every HWP angle of `theta`.
    pub fn fluxes(&self, s: &Stokes, theta: &[f64]) -> Vec<BeamFluxes> {
        let sp = self.at_plate(s);
        theta.iter().map(|&t| self.fluxes_at_plate(&sp, t)).collect()
    }

    /// Fluxes of an exposure during which the plate turns uniformly through `sweep` (rad)
    /// about the middle angle `theta_mid`, for a Stokes vector already at the plate: the
    /// plate's matrix averaged over the motion ([`Hwp::matrix_swept`]). The detector integrates
    /// intensity, which is linear in the plate's matrix, so this is the exposure's mean flux.
    pub fn fluxes_at_plate_swept(&self, s_plate: &Stokes, theta_mid: f64, sweep: f64) -> BeamFluxes {
        let s2 = self.hwp.matrix_swept(theta_mid, sweep) * s_plate;
        BeamFluxes { f_o: (self.row_o * s2)[0], f_e: (self.row_e * s2)[0] }
    }

    /// Fluxes of exposures at middle angles `theta` (rad), exposure `i` sweeping `sweep[i]`
    /// (rad; 0 for a fixed plate, and beyond the end of a shorter `sweep`).
    pub fn fluxes_swept(&self, s: &Stokes, theta: &[f64], sweep: &[f64]) -> Vec<BeamFluxes> {
        let sp = self.at_plate(s);
        theta
            .iter()
            .enumerate()
            .map(|(i, &t)| self.fluxes_at_plate_swept(&sp, t, sweep.get(i).copied().unwrap_or(0.0)))
            .collect()
    }
}

/// The optimal HWP angle set of `N` positions, `theta_i = i pi / 8` (section `sec:basics`).
///
/// ```
/// let deg: Vec<f64> = mueller::optimal_angles(4).iter().map(|t| t.to_degrees()).collect();
/// assert_eq!(deg, [0.0, 22.5, 45.0, 67.5]);
/// ```
pub fn optimal_angles(n: usize) -> Vec<f64> {
    (0..n).map(|i| i as f64 * std::f64::consts::PI / 8.0).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fast hypot is `f64::hypot` (correctly rounded) to within one ulp where the squares
    /// are representable, and exactly it beyond (overflow, underflow, subnormals, inf, NaN).
    #[test]
    fn hypot_is_libm_hypot_within_an_ulp_and_safe_at_the_extremes() {
        let mags =
            [0.0, 5e-324, 1e-300, 1e-160, 1e-145, 3e-8, 0.25, 1.0, 3.0, 1234.5, 1e150, 1e154, 1e160, 1e300, f64::MAX];
        for &a in &mags {
            for &b in &mags {
                for (x, y) in [(a, b), (-a, b), (a * 0.7, -b * 1.3)] {
                    let (got, want) = (hypot(x, y), x.hypot(y));
                    let ulp = f64::EPSILON * want;
                    assert!(got == want || (got - want).abs() <= ulp, "{x:e}, {y:e}: {got:e} vs {want:e}");
                }
            }
        }
        assert_eq!(hypot(3.0, 4.0), 5.0);
        assert_eq!(hypot(f64::INFINITY, f64::NAN), f64::INFINITY);
        assert!(hypot(f64::NAN, 1.0).is_nan());
    }
    use approx::assert_relative_eq;
    use std::f64::consts::{FRAC_PI_2, PI};

    #[test]
    fn ideal_train_is_eq_ord() {
        let s = stokes_qu(1000.0, 0.03, -0.02);
        let th = optimal_angles(16);
        for (f, &t) in DualBeam::ideal().fluxes(&s, &th).iter().zip(&th) {
            let m = s[1] * (4.0 * t).cos() + s[2] * (4.0 * t).sin();
            assert_relative_eq!(f.f_o, 0.5 * (s[0] + m), epsilon = 1e-9);
            assert_relative_eq!(f.f_e, 0.5 * (s[0] - m), epsilon = 1e-9);
        }
    }

    #[test]
    fn eq_wp_imbalance() {
        let s = stokes_qu(1.0, 0.05, 0.01);
        let t = 0.45;
        let train = DualBeam { wollaston: Wollaston::with_t(t), ..Default::default() };
        let th = optimal_angles(4);
        for (f, &a) in train.fluxes(&s, &th).iter().zip(&th) {
            let m = s[1] * (4.0 * a).cos() + s[2] * (4.0 * a).sin();
            assert_relative_eq!(f.f_o, t * (s[0] + m), epsilon = 1e-12);
            assert_relative_eq!(f.f_e, (1.0 - t) * (s[0] - m), epsilon = 1e-12);
        }
    }

    #[test]
    fn chi_offset_rotates_measured_angle() {
        // A plate whose zero sits chi_offset/2 away shifts F_i = P cos(4 theta - 2 chi) to
        // chi - chi_offset.
        let (p, chi, off) = (0.02, 0.3, 0.1);
        let train = DualBeam { hwp: Hwp { chi_offset: off, ..Hwp::ideal() }, ..Default::default() };
        let th = optimal_angles(8);
        for (f, &a) in train.fluxes(&stokes_p_chi(1.0, p, chi), &th).iter().zip(&th) {
            let fi = (f.f_o - f.f_e) / (f.f_o + f.f_e);
            assert_relative_eq!(fi, p * (4.0 * a - 2.0 * (chi - off)).cos(), epsilon = 1e-12);
        }
    }

    #[test]
    fn rotation_composes() {
        let m = retarder(1.1, 0.0);
        assert_relative_eq!(rotate(&rotate(&m, 0.2), 0.3), rotate(&m, 0.5), epsilon = 1e-12);
        assert_relative_eq!(rotate(&m, PI), m, epsilon = 1e-12);
    }

    /// The plate's matrix averaged over a sweep, against the plain mean of the matrix over
    /// 20000 equal sub-steps (midpoint rule, written here; its error is of order
    /// (8 h)^2 / 24 < 1e-9): the ideal plate with a zero angle and a retardance error (closed
    /// form), a plate with dust and pleochroism (quadrature), and a quarter-wave plate (closed
    /// form: its elements have the same harmonics); sweeps of 22.5, 60 and 90 deg.
    #[test]
    fn swept_plate_is_the_mean_over_its_motion() {
        let plates = [
            Hwp { retardance_error: 0.07, chi_offset: 0.05, ..Hwp::ideal() },
            Hwp {
                retardance_error: -0.03,
                chi_offset: 0.02,
                dust: Some(Harmonic { amplitude: 0.01, phase: 0.4 }),
                pleochroism: Some(Harmonic { amplitude: 0.02, phase: 1.1 }),
                ..Hwp::ideal()
            },
            Hwp { retardance_error: 0.04, chi_offset: -0.06, ..Hwp::quarter_wave() },
        ];
        for hwp in plates {
            for (mid_deg, sweep_deg) in [(11.25, 22.5), (47.0, 60.0), (100.0, 90.0), (3.0, -22.5)] {
                let (mid, d) = (f64::to_radians(mid_deg), f64::to_radians(sweep_deg));
                let n = 20000;
                let mut mean = Mueller::zeros();
                for k in 0..n {
                    mean += hwp.matrix(mid - 0.5 * d + (k as f64 + 0.5) * d / n as f64);
                }
                mean /= n as f64;
                assert_relative_eq!(hwp.matrix_swept(mid, d), mean, epsilon = 1e-9);
            }
            assert_eq!(hwp.matrix_swept(0.3, 0.0), hwp.matrix(0.3));
        }
    }

    /// eq:F of the ideal train with a swept plate: `F = sinc(2d) P cos(4 theta_m - 2 chi)`,
    /// 0.9003 of the fixed plate's for 22.5 deg and nothing for 90 deg; the series below
    /// `2d = 1e-3` joins `sin(2d)/(2d)` (1e-16) and tends to 1.
    #[test]
    fn swept_modulation_is_scaled_by_sinc() {
        let (p, chi) = (0.03, 0.6);
        let th: Vec<f64> = (0..16).map(|k| (11.25 + 22.5 * k as f64).to_radians()).collect();
        for sweep_deg in [22.5, 45.0, 90.0] {
            let d = f64::to_radians(sweep_deg);
            let f = DualBeam::ideal().compile().fluxes_swept(&stokes_p_chi(1.0, p, chi), &th, &[d; 16]);
            let eff = (2.0 * d).sin() / (2.0 * d);
            for (b, &t) in f.iter().zip(&th) {
                let fi = (b.f_o - b.f_e) / (b.f_o + b.f_e);
                assert_relative_eq!(fi, eff * p * (4.0 * t - 2.0 * chi).cos(), epsilon = 1e-15);
            }
        }
        assert_relative_eq!(hwp_sweep_efficiency(22.5f64.to_radians()), 0.9003163161571061, epsilon = 1e-15);
        assert!(hwp_sweep_efficiency(FRAC_PI_2).abs() < 1e-15);
        let x = 0.999e-3 / 2.0;
        assert_relative_eq!(hwp_sweep_efficiency(x), (2.0 * x).sin() / (2.0 * x), epsilon = 1e-16);
        assert_relative_eq!(hwp_sweep_efficiency(1.001e-3 / 2.0), (1.001e-3f64).sin() / 1.001e-3, epsilon = 1e-16);
        assert_eq!(hwp_sweep_efficiency(1e-300), 1.0);
    }
}

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
