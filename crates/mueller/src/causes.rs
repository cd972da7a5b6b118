//! Physical causes of a Mueller field: the optics each candidate explanation
//! of a fitted field puts in the beam, as functions of the field position and a few
//! parameters. `fit::mueller_field::explain` fits them to a fitted field; the simulator applies them
//! (`sim::stress`, `sim::hwp_causes`).
//!
//! - a stressed lens: stress birefringence growing as `r^2` from a stress centre, fast axis
//!   radial (or tangential: the same for linear polarimetry, see [`crate::linear`]);
//! - a tilted half-wave plate ([`UniaxialPlate`], [`tilted_hwp`]): a crystal plate crossed at
//!   an angle of incidence `i` that depends on the plate's tilt and on the field position
//!   (the plate sits in the collimated beam, where a field angle becomes a beam direction
//!   magnified by the ratio of the telescope aperture to the beam diameter). Its retardance
//!   and its axis, as seen along the ray, change with `i` and with the azimuth of the plane of
//!   incidence relative to the crystal axis, which turns with the plate;
//! - a wedged half-wave plate ([`wedged_hwp`]): a retardance error varying linearly across the
//!   field (a plate of varying thickness near a focal plane);
//! - a polarizing (diattenuating) half-wave plate: a weak partial polarizer that turns with
//!   the plate, which is [`crate::Hwp`]'s `pleochroism` harmonic (the simulator's existing
//!   effect); nothing new is needed here.
//!
//! A half-wave plate is the modulator, not a pre-analyzer element: what it does to the
//! measured `(q, u)` goes through the demodulation (`stokes::equivalent`).
//!
//! [`physical_of_block`] is the inverse of [`crate::linear::physical_block`]: the physical
//! parameters of a linear block, so any cause's block can be compared with a fitted field.

use crate::linear::LinearBlock;
use crate::{retarder, Mueller};

/// Retardance (rad) and fast-axis angle (rad) of the stressed-lens pattern at `(x, y)`
/// arcmin: `delta = delta_edge (r / radius)^2` with `r` measured from `centre`, axis at the
/// polar angle about the centre plus `axis_offset` (rad; `pi/2`: tangential).
pub fn stressed_lens(x: f64, y: f64, delta_edge: f64, radius: f64, centre: [f64; 2], axis_offset: f64) -> (f64, f64) {
    let (dx, dy) = (x - centre[0], y - centre[1]);
    let r2 = (dx * dx + dy * dy) / (radius * radius);
    (delta_edge * r2, dy.atan2(dx) + axis_offset)
}

/// A plane-parallel uniaxial crystal plate with its optic axis in its faces (a classical
/// wave plate), in air.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct UniaxialPlate {
    /// Ordinary and extraordinary indices.
    pub n_o: f64,
    pub n_e: f64,
    /// Thickness in wavelengths (`d / lambda`).
    pub thickness_waves: f64,
}

impl UniaxialPlate {
    /// Crystal quartz at 440 nm (B band): `n_o = 1.5565`, `n_e = 1.5659` (Ghosh 1999, Opt.
    /// Commun. 163, 95, dispersion formulae of crystal quartz, evaluated at 0.44 um), cut as
    /// a half-wave plate of order `order` (`order = 0`: zero order, retardance `pi` at normal
    /// incidence; `m`: `(2m + 1) pi`).
    pub fn quartz_half_wave_b(order: u32) -> Self {
        let (n_o, n_e) = (1.5565, 1.5659);
        Self { n_o, n_e, thickness_waves: (order as f64 + 0.5) / (n_e - n_o) }
    }

    /// Retardance (rad, extraordinary minus ordinary phase) at angle of incidence `inc` (rad,
    /// in air) with the plane of incidence at `azimuth` (rad) from the optic axis. The closed
    /// form of the two refracted waves' normal wave-vector components in a uniaxial plate with
    /// the axis in its faces (Yariv & Yeh, Optical Waves in Crystals, 1984, sec. 5.x;
    /// Veiras, Perez & Tocho 2010, Appl. Opt. 49, 2769, eq. 8 with the axis in the plane):
    /// `k_oz = k0 sqrt(n_o^2 - sin^2 i)`,
    /// `k_ez = k0 n_e sqrt(1 - sin^2 i (cos^2 az / n_o^2 + sin^2 az / n_e^2))`,
    /// `delta = d (k_ez - k_oz)`. Tested against a numerical root of the Fresnel equation.
    pub fn retardance(&self, inc: f64, azimuth: f64) -> f64 {
        let s2 = inc.sin().powi(2);
        let (sa, ca) = azimuth.sin_cos();
        let (no, ne) = (self.n_o, self.n_e);
        let kez = ne * (1.0 - s2 * (ca * ca / (no * no) + sa * sa / (ne * ne))).sqrt();
        let koz = (no * no - s2).sqrt();
        2.0 * std::f64::consts::PI * self.thickness_waves * (kez - koz)
    }
}

/// Angle of incidence (rad) and azimuth of the plane of incidence (rad) on a plate in the
/// collimated beam at field point `(x, y)` arcmin: the plate's tilt (rad) towards
/// `tilt_azimuth` plus the beam direction of the field point, the field angle times the
/// angular `magnification` (telescope aperture over collimated beam diameter). Small-angle
/// vector sum (the tilt and the field directions add as vectors to first order).
pub fn hwp_incidence(x: f64, y: f64, tilt: f64, tilt_azimuth: f64, magnification: f64) -> (f64, f64) {
    let k = magnification * (1.0f64 / 60.0).to_radians();
    let (sa, ca) = tilt_azimuth.sin_cos();
    let (vx, vy) = (tilt * ca + k * x, tilt * sa + k * y);
    (vx.hypot(vy), vy.atan2(vx))
}

/// Mueller matrix of a tilted half-wave plate with its crystal axis at commanded angle
/// `theta` (rad), for a ray of incidence `inc` in the plane at `alpha` ([`hwp_incidence`]).
///
/// A Jones calculation with the plate's two refracted waves: wave vectors `k_o`, `k_e` with
/// the normal components of [`UniaxialPlate::retardance`]; the ordinary field along
/// `c x k_o`, the extraordinary field `E = eps^-1 D` with `D` along the part of `c`
/// transverse to `k_e` (`c` the crystal axis, `eps` the uniaxial dielectric tensor). Both
/// fields are projected on the transverse basis of the ray (the global x, y axes carried to
/// the ray by the minimal rotation of `z` onto it, as in `raytrace`); an incoming field is
/// split on these two (not quite orthogonal) directions, each part takes its wave's phase,
/// and the parts recombine: `J = V diag(e^{i phi_o}, e^{i phi_e}) V^-1`. At normal incidence
/// this is `retarder(pi, theta)`. The different Fresnel transmissions of the two waves at the
/// faces (a diattenuation of order `i^2`, the polarizing-plate case) are left out.
pub fn tilted_hwp(plate: &UniaxialPlate, theta: f64, inc: f64, alpha: f64) -> Mueller {
    use crate::C64;
    use nalgebra::{Matrix2, Vector3};
    let (si, ci) = inc.sin_cos();
    let (sa, ca) = alpha.sin_cos();
    let c = Vector3::new(theta.cos(), theta.sin(), 0.0);
    let (no, ne) = (plate.n_o, plate.n_e);
    let az = alpha - theta;
    let (sz, cz) = az.sin_cos();
    let koz = (no * no - si * si).sqrt();
    let kez = ne * (1.0 - si * si * (cz * cz / (no * no) + sz * sz / (ne * ne))).sqrt();
    let ko = Vector3::new(si * ca, si * sa, koz);
    let ke = Vector3::new(si * ca, si * sa, kez);
    let eo = c.cross(&ko);
    let khat = ke.normalize();
    let d = c - khat * c.dot(&khat);
    let ee = d / (no * no) + c * (c.dot(&d) * (1.0 / (ne * ne) - 1.0 / (no * no)));
    // Transverse basis of the ray in air.
    let p = Vector3::new(ci * ca, ci * sa, -si);
    let s = Vector3::new(-sa, ca, 0.0);
    let e1 = p * ca - s * sa;
    let e2 = p * sa + s * ca;
    let v = Matrix2::new(eo.dot(&e1), ee.dot(&e1), eo.dot(&e2), ee.dot(&e2));
    // V is singular only where the two waves' fields coincide, which no plate of real indices
    // reaches (non-finite inputs do): the matrix is then NaN, never a silent identity.
    let vinv = v.try_inverse().unwrap_or_else(|| Matrix2::from_element(f64::NAN));
    let k = 2.0 * std::f64::consts::PI * plate.thickness_waves;
    // Phases relative to the ordinary wave (a common phase does not change the Mueller matrix).
    let ph = C64::from_polar(1.0, k * (kez - koz));
    let vc = v.map(|x| C64::new(x, 0.0));
    let vic = vinv.map(|x| C64::new(x, 0.0));
    let j = vc * Matrix2::new(C64::new(1.0, 0.0), C64::new(0.0, 0.0), C64::new(0.0, 0.0), ph) * vic;
    crate::jones_to_mueller(&j)
}

/// Mueller matrix of a wedged half-wave plate at `(x, y)` arcmin and commanded angle `theta`:
/// retardance `pi + eps0 + gx x + gy y` (rad; gradients per arcmin), axis at `theta`.
pub fn wedged_hwp(theta: f64, x: f64, y: f64, eps0: f64, gx: f64, gy: f64) -> Mueller {
    retarder(std::f64::consts::PI + eps0 + gx * x + gy * y, theta)
}

/// The physical parameters `[q_diat, u_diat, g1, g2, rotation, depolarization]` of a linear
/// block (the full parameter vector of `crate::linear::physical_block`), its exact inverse
/// for blocks of that form: the diattenuation from row 0 (`m01, m02` of the normalized
/// block), then `B = L M_I^-1`, whose Q, U part is `(1 - depol) Rot(2 rotation) R_ret`, split
/// by the polar decomposition of a 2 x 2 matrix (rotation angle `atan2(b21 - b12, b11 +
/// b22)`; the symmetric factor's largest eigenvalue is `1 - depol`, its anisotropy the
/// retardance vector). A block of another form (e.g. an additive offset in `m10, m20` after a
/// demodulation) gets the physical parameters of its row 0 and Q, U part. A perfect
/// polarizer (diattenuation 1: `M_I` has no inverse) leaves the rest undetermined: NaN, so that
/// a fit through it fails rather than read the block as having no retardance.
pub fn physical_of_block(block: &LinearBlock) -> [f64; 6] {
    let l = block.normalized().0;
    let (qd, ud) = (l[(0, 1)], l[(0, 2)]);
    let mi = crate::linear::physical_block(qd, ud, [0.0, 0.0], 0.0, 0.0).normalized().0;
    let Some(mi_inv) = mi.try_inverse() else {
        return [qd, ud, f64::NAN, f64::NAN, f64::NAN, f64::NAN];
    };
    let b = l * mi_inv;
    let (b11, b12, b21, b22) = (b[(1, 1)], b[(1, 2)], b[(2, 1)], b[(2, 2)]);
    let ang = (b21 - b12).atan2(b11 + b22);
    let (s, c) = ang.sin_cos();
    // S = Rot(-ang) B2.
    let s11 = c * b11 + s * b21;
    let s12 = c * b12 + s * b22;
    let s21 = -s * b11 + c * b21;
    let s22 = -s * b12 + c * b22;
    let off = 0.5 * (s12 + s21);
    let half = 0.5 * (s11 - s22);
    let f = 0.5 * (s11 + s22) + half.hypot(off);
    let (g1, g2) = if f > 0.0 { (half / f, off / f) } else { (0.0, 0.0) };
    [qd, ud, g1, g2, 0.5 * ang, 1.0 - f]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linear::{physical_block, retardance_vector};

    /// The decomposition returns the parameters a block was built from (the construction is
    /// `physical_block`, a separate product of the element matrices).
    #[test]
    fn physical_of_block_inverts_physical_block() {
        for &(qd, ud, d, ax, rot, dep) in &[
            (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
            (0.003, -0.002, 0.3, 0.4, 0.01, 0.02),
            (0.05, 0.01, 1.2, -0.3, -0.2, 0.1),
            (-0.001, 0.0, 0.05, 1.0, 0.0, 0.0),
        ] {
            let g = retardance_vector(d, ax);
            let got = physical_of_block(&physical_block(qd, ud, g, rot, dep));
            let want = [qd, ud, g[0], g[1], rot, dep];
            for (a, b) in got.iter().zip(want) {
                assert!((a - b).abs() < 1e-12, "{got:?} vs {want:?}");
            }
        }
    }

    /// Normal incidence: the plate's nominal retardance, for any azimuth; the change with
    /// incidence is second order, of the size of the small-angle expansion
    /// `delta0 sin^2 i / (2 n^2) (sin^2 az - cos^2 az)` (to first order in the birefringence).
    #[test]
    fn oblique_retardance_limits() {
        let p = UniaxialPlate::quartz_half_wave_b(0);
        for az in [0.0, 0.7, 2.0] {
            assert!((p.retardance(0.0, az) - std::f64::consts::PI).abs() < 1e-12);
        }
        let i = 5f64.to_radians();
        let n = p.n_o;
        for az in [0.0f64, 0.5, std::f64::consts::FRAC_PI_2] {
            let d = p.retardance(i, az) - std::f64::consts::PI;
            let approx = std::f64::consts::PI * i.sin().powi(2) / (2.0 * n * n) * (az.sin().powi(2) - az.cos().powi(2));
            assert!((d - approx).abs() < 0.02 * approx.abs().max(1e-4), "az {az}: {d} vs {approx}");
        }
    }

    /// At normal incidence the tilted plate is the ideal half-wave plate at `theta`; with the
    /// plane of incidence along the crystal axis the two waves' fields are orthogonal and the
    /// plate is a pure retarder of the closed-form retardance, fast axis across the crystal axis.
    #[test]
    fn tilted_plate_limits() {
        let p = UniaxialPlate::quartz_half_wave_b(0);
        let m = tilted_hwp(&p, 0.4, 0.0, 1.0);
        assert!((m - retarder(std::f64::consts::PI, 0.4)).abs().max() < 1e-12, "{m}");
        let i = 10f64.to_radians();
        let m = tilted_hwp(&p, 0.4, i, 0.4);
        // Quartz is positive (n_e > n_o): the ordinary direction, across the axis, is the fast one.
        let want = retarder(p.retardance(i, 0.0), 0.4 + std::f64::consts::FRAC_PI_2);
        assert!((m - want).abs().max() < 1e-12, "{m} vs {want}");
    }
}
