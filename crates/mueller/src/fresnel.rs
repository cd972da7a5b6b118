//! Fresnel coefficients of a single plane interface between a lossless incident medium of
//! real index `n0` and a medium of complex index `n = n' + i k` (dielectric: `k = 0`;
//! metal or absorbing glass: `k > 0`).
//!
//! Conventions (shared with [`crate::thinfilm`] and [`crate::raytrace`]):
//! - fields vary in time as `exp(-i omega t)`, so an absorbing medium has `Im n > 0`
//!   (aluminium at 550 nm: `0.96 + 6.69 i`) and the circular convention of the crate
//!   (`V = 2 Im(E_x^* E_y)`, IAU) holds with `x = p`, `y = s`;
//! - `s` is perpendicular to the plane of incidence, `p` lies in it, and `(p, s, k)` is a
//!   right-handed frame for the incident, the transmitted *and* the reflected beam. Hence at
//!   normal incidence `r_p = -r_s` and a mirror reverses `U` and `V` (handedness flips);
//! - amplitude coefficients are ratios of electric-field amplitudes;
//! - power coefficients are ratios of the normal component of the Poynting vector:
//!   `T_s = Re(n cos t) / (n0 cos i) |t_s|^2`, `T_p = Re(conj(n) cos t) / (n0 cos i) |t_p|^2`;
//! - the *flux-normalized* transmission amplitudes `t_s_flux`, `t_p_flux` have the phase of
//!   `t_s`, `t_p` and modulus `sqrt(T)`: they are what a Jones/Mueller calculus that tracks
//!   power (not field in a denser medium) must use.

use crate::{Error, Mueller};
use nalgebra::Matrix2;
use num_complex::Complex64;

/// Complex number type used for refractive indices and amplitudes.
pub type C64 = Complex64;

/// Amplitude and power coefficients of an interface or a thin-film stack, in the local s/p
/// frame (see the module docs for the conventions).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coefficients {
    /// Reflected / incident electric-field amplitude, s and p.
    pub r_s: C64,
    pub r_p: C64,
    /// Transmitted / incident electric-field amplitude, s and p.
    pub t_s: C64,
    pub t_p: C64,
    /// Flux-normalized transmission amplitudes: phase of `t`, modulus `sqrt(T)`.
    pub t_s_flux: C64,
    pub t_p_flux: C64,
    /// Power reflectances `|r|^2`.
    pub reflectance_s: f64,
    pub reflectance_p: f64,
    /// Power transmittances (Poynting-vector ratios).
    pub transmittance_s: f64,
    pub transmittance_p: f64,
}

impl Coefficients {
    /// Polarization that transmission gives unpolarized light, `(T_p - T_s) / (T_p + T_s)`
    /// (positive: along the plane of incidence, the paper's section `sec:cause`).
    pub fn diattenuation_t(&self) -> f64 {
        let (tp, ts) = (self.transmittance_p, self.transmittance_s);
        if tp + ts > 0.0 {
            (tp - ts) / (tp + ts)
        } else {
            0.0
        }
    }

    /// Transmitted phase difference `arg t_p - arg t_s` (rad), in (-pi, pi].
    pub fn retardance_t(&self) -> f64 {
        (self.t_p_flux * self.t_s_flux.conj()).arg()
    }

    /// Reflected phase difference `arg r_p - arg r_s` (rad), in (-pi, pi].
    pub fn retardance_r(&self) -> f64 {
        (self.r_p * self.r_s.conj()).arg()
    }

    /// Jones matrix of transmission in the `(p, s)` frame, flux-normalized.
    pub fn jones_t(&self) -> Matrix2<C64> {
        Matrix2::new(self.t_p_flux, C64::new(0.0, 0.0), C64::new(0.0, 0.0), self.t_s_flux)
    }

    /// Jones matrix of reflection in the `(p, s)` frames of the incident and reflected beams.
    pub fn jones_r(&self) -> Matrix2<C64> {
        Matrix2::new(self.r_p, C64::new(0.0, 0.0), C64::new(0.0, 0.0), self.r_s)
    }

    /// Mueller matrix of transmission with the plane of incidence at `plane_angle` (rad) from
    /// the Stokes x axis: a diattenuator (`T_p`, `T_s`) and a retarder (`arg t_p - arg t_s`)
    /// with their axes along the plane of incidence.
    pub fn mueller_t(&self, plane_angle: f64) -> Mueller {
        crate::rotate(&crate::analysis::jones_to_mueller(&self.jones_t()), plane_angle)
    }

    /// Mueller matrix of reflection, in the reflected beam's right-handed frame, with the
    /// plane of incidence at `plane_angle` from the x axis of the incident frame.
    ///
    /// The reflected frame is a mirror image, in which the plane of incidence lies at
    /// `-plane_angle`: `M = R(plane_angle) M_sp R(plane_angle)` (at normal incidence this is
    /// `R diag(1, 1, -1, -1)` whatever the angle).
    pub fn mueller_r(&self, plane_angle: f64) -> Mueller {
        let r = crate::rotation(plane_angle);
        r * crate::analysis::jones_to_mueller(&self.jones_r()) * r
    }
}

/// `cos(theta)` in a medium of index `n` for a wave whose tangential index-sine is
/// `n0 sin(theta0)` (Snell's invariant). The branch gives a wave that decays (or, if lossless
/// and beyond the critical angle, is evanescent) away from the interface: `Im(n cos) >= 0`,
/// and `Re(n cos) >= 0` for propagating waves.
pub fn cos_in(n0_sin: f64, n: C64) -> C64 {
    let s = C64::new(n0_sin, 0.0) / n;
    let mut c = (C64::new(1.0, 0.0) - s * s).sqrt();
    let nc = n * c;
    if nc.im < 0.0 || (nc.im == 0.0 && nc.re < 0.0) {
        c = -c;
    }
    c
}

/// Check an incident-medium index, a substrate index and an angle of incidence.
pub(crate) fn check_inputs(n0: f64, n: C64, aoi: f64) -> Result<(), Error> {
    if !(n0.is_finite() && n0 > 0.0) {
        return Err(Error::OutOfRange { name: "incident index n0", value: n0, range: "(0, inf)" });
    }
    check_index(n, "substrate index (real part)", "substrate index (imaginary part)")?;
    if !(aoi.is_finite() && (0.0..std::f64::consts::FRAC_PI_2).contains(&aoi)) {
        return Err(Error::OutOfRange { name: "angle of incidence (rad)", value: aoi, range: "[0, pi/2)" });
    }
    Ok(())
}

/// A complex index must have a positive real part and a non-negative imaginary part.
pub(crate) fn check_index(n: C64, re_name: &'static str, im_name: &'static str) -> Result<(), Error> {
    if !(n.re.is_finite() && n.re > 0.0) {
        return Err(Error::OutOfRange { name: re_name, value: n.re, range: "(0, inf)" });
    }
    if !(n.im.is_finite() && n.im >= 0.0) {
        return Err(Error::OutOfRange { name: im_name, value: n.im, range: "[0, inf) (absorption, exp(-i omega t))" });
    }
    Ok(())
}

/// Fresnel coefficients of the interface from a lossless medium `n0` into a medium of complex
/// index `n` at angle of incidence `aoi` (rad, in `[0, pi/2)`).
///
/// Beyond the critical angle (`n0 > n`, lossless) the transmittances are 0 and `|r| = 1`.
///
/// ```
/// use mueller::fresnel::{interface, C64};
/// // Uncoated glass n = 1.5 at 30 deg: transmission polarizes by about 1.7% (sec:cause).
/// let c = interface(1.0, C64::new(1.5, 0.0), 30f64.to_radians()).unwrap();
/// assert!((c.diattenuation_t() - 0.0170).abs() < 2e-4);
/// ```
pub fn interface(n0: f64, n: C64, aoi: f64) -> Result<Coefficients, Error> {
    check_inputs(n0, n, aoi)?;
    Ok(interface_unchecked(n0, n, aoi.cos(), n0 * aoi.sin()))
}

/// [`interface`] without input checks, given `cos(aoi)` and Snell's invariant `n0 sin(aoi)`
/// (the ray tracer's hot path).
pub(crate) fn interface_unchecked(n0: f64, n: C64, cos_i: f64, n0_sin: f64) -> Coefficients {
    let ci = C64::new(cos_i, 0.0);
    let ct = cos_in(n0_sin, n);
    let n0c = C64::new(n0, 0.0);
    let (a, b) = (n0c * ci, n * ct); // s admittances
    let (c, d) = (n * ci, n0c * ct); // p
    let r_s = (a - b) / (a + b);
    let r_p = (c - d) / (c + d);
    let t_s = 2.0 * a / (a + b);
    let t_p = 2.0 * a / (c + d);
    let fs = (n * ct).re / (n0 * cos_i);
    let fp = (n.conj() * ct).re / (n0 * cos_i);
    let (fs, fp) = (fs.max(0.0), fp.max(0.0));
    Coefficients {
        r_s,
        r_p,
        t_s,
        t_p,
        t_s_flux: t_s * fs.sqrt(),
        t_p_flux: t_p * fp.sqrt(),
        reflectance_s: r_s.norm_sqr(),
        reflectance_p: r_p.norm_sqr(),
        transmittance_s: fs * t_s.norm_sqr(),
        transmittance_p: fp * t_p.norm_sqr(),
    }
}

/// Mueller matrix of a metal (or any) mirror in air: reflection at angle of incidence `aoi`
/// with the plane of incidence at `plane_angle` from the x axis, in the reflected beam's
/// right-handed frame. At normal incidence it is `R diag(1, 1, -1, -1)`.
///
/// ```
/// use mueller::fresnel::{mirror, C64};
/// // A mirror at normal incidence does not polarize: unpolarized light stays unpolarized, and
/// // linear light keeps Q and turns U (the reflected beam's frame is mirrored).
/// let m = mirror(C64::new(1.2, 7.3), 0.0, 0.0).unwrap();
/// let s = m * mueller::stokes_p_chi(1.0, 1.0, 22.5f64.to_radians());
/// assert!((s[1] / s[0] - 0.5f64.sqrt()).abs() < 1e-12 && (s[2] / s[0] + 0.5f64.sqrt()).abs() < 1e-12);
/// assert!(m[(0, 1)].abs() < 1e-15 && m[(0, 2)].abs() < 1e-15);
/// ```
pub fn mirror(n: C64, aoi: f64, plane_angle: f64) -> Result<Mueller, Error> {
    Ok(interface(1.0, n, aoi)?.mueller_r(plane_angle))
}

/// Aluminium at 550 nm, `n = 0.96 + 6.69 i` (Rakic 1995 tabulation, rounded).
pub const ALUMINIUM_550: C64 = C64::new(0.96, 6.69);

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use std::f64::consts::FRAC_PI_2;

    /// Textbook (Born & Wolf, sec. 1.5) transmittances of a lossless dielectric interface,
    /// written from Snell's law independently of the code above.
    fn textbook_t(n1: f64, n2: f64, ti: f64) -> (f64, f64) {
        let tt = (n1 * ti.sin() / n2).asin();
        let ts = 2.0 * n1 * ti.cos() / (n1 * ti.cos() + n2 * tt.cos());
        let tp = 2.0 * n1 * ti.cos() / (n2 * ti.cos() + n1 * tt.cos());
        let k = n2 * tt.cos() / (n1 * ti.cos());
        (k * ts * ts, k * tp * tp)
    }

    #[test]
    fn sec_cause_uncoated_glass_30deg_gives_1_7_percent() {
        let c = interface(1.0, C64::new(1.5, 0.0), 30f64.to_radians()).unwrap();
        let (ts, tp) = textbook_t(1.0, 1.5, 30f64.to_radians());
        assert_relative_eq!(c.transmittance_s, ts, epsilon = 1e-14);
        assert_relative_eq!(c.transmittance_p, tp, epsilon = 1e-14);
        let d = (tp - ts) / (tp + ts);
        assert_relative_eq!(c.diattenuation_t(), d, epsilon = 1e-14);
        // The paper: "about B = 1.7% per optical surface".
        assert!((c.diattenuation_t() - 0.017).abs() < 0.0005, "{}", c.diattenuation_t());
        // A lossless dielectric transmits without retardance.
        assert!(c.retardance_t().abs() < 1e-15);
    }

    #[test]
    fn energy_conserved_lossless_and_absorbing() {
        for &n in &[C64::new(1.5, 0.0), C64::new(1.9, 0.0), ALUMINIUM_550, C64::new(1.6, 0.3)] {
            for k in 0..18 {
                let a = k as f64 * 5f64.to_radians();
                let c = interface(1.0, n, a).unwrap();
                // The Poynting flux is continuous across the interface even into a metal.
                assert_relative_eq!(c.transmittance_s + c.reflectance_s, 1.0, epsilon = 1e-12);
                assert_relative_eq!(c.transmittance_p + c.reflectance_p, 1.0, epsilon = 1e-12);
            }
        }
        // Glass to air, both sides of the critical angle.
        for k in 0..18 {
            let a = k as f64 * 5f64.to_radians();
            let c = interface(1.5, C64::new(1.0, 0.0), a).unwrap();
            assert_relative_eq!(c.transmittance_s + c.reflectance_s, 1.0, epsilon = 1e-12);
            assert_relative_eq!(c.transmittance_p + c.reflectance_p, 1.0, epsilon = 1e-12);
        }
    }

    #[test]
    fn normal_incidence_gives_no_polarization() {
        let c = interface(1.0, C64::new(1.5, 0.0), 0.0).unwrap();
        assert_eq!(c.diattenuation_t(), 0.0);
        assert_relative_eq!(c.reflectance_s, 0.04, epsilon = 1e-15);
        assert!((c.r_p + c.r_s).norm() < 1e-15);
        let m = mirror(ALUMINIUM_550, 0.0, 0.3).unwrap();
        let r = m[(0, 0)];
        let expect = ((ALUMINIUM_550 - 1.0) / (ALUMINIUM_550 + 1.0)).norm_sqr();
        assert_relative_eq!(r, expect, epsilon = 1e-14);
        assert_relative_eq!(m, Mueller::from_diagonal(&nalgebra::Vector4::new(r, r, -r, -r)), epsilon = 1e-14);
    }

    #[test]
    fn brewster_angle_kills_p_reflection() {
        let c = interface(1.0, C64::new(1.5, 0.0), 1.5f64.atan()).unwrap();
        assert!(c.reflectance_p < 1e-28);
    }

    #[test]
    fn aluminium_mirror_at_45_deg() {
        // Closed form: R_s = |(cos i - n cos t)/(cos i + n cos t)|^2 with n cos t =
        // sqrt(n^2 - sin^2 i) (Born & Wolf 14.2), evaluated here independently.
        let n = ALUMINIUM_550;
        let i = 45f64.to_radians();
        let nct = (n * n - i.sin().powi(2)).sqrt();
        let rs = ((i.cos() - nct) / (i.cos() + nct)).norm_sqr();
        let rp = ((n * n * i.cos() - nct) / (n * n * i.cos() + nct)).norm_sqr();
        let c = interface(1.0, n, i).unwrap();
        assert_relative_eq!(c.reflectance_s, rs, epsilon = 1e-13);
        assert_relative_eq!(c.reflectance_p, rp, epsilon = 1e-13);
        assert!(rs > rp && rs > 0.9);
        let m = mirror(n, i, 0.0).unwrap();
        assert!(crate::analysis::is_physical(&m, 1e-12));
    }

    #[test]
    fn bad_inputs_are_named() {
        assert!(matches!(interface(0.0, C64::new(1.5, 0.0), 0.1), Err(Error::OutOfRange { .. })));
        assert!(interface(1.0, C64::new(-1.5, 0.0), 0.1).is_err());
        assert!(interface(1.0, C64::new(1.5, -0.1), 0.1).is_err());
        let e = interface(1.0, C64::new(1.5, 0.0), FRAC_PI_2).unwrap_err().to_string();
        assert!(e.contains("angle of incidence"), "{e}");
    }
}
