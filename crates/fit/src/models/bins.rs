//! One binned measurement of the instrumental polarization: the rows of the calibration
//! file's binary table and the input of every fit.

use serde::{Deserialize, Serialize};

/// The instrumental polarization measured in one bin of the field.
///
/// `q = p cos 2phi`, `u = p sin 2phi` are the normalized Stokes parameters of the partial
/// polarizer `M_I(p, phi)` (`eq:instpol`) found in this bin (fractions); positions are the
/// bin's centre in arcmin from the detector centre.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(into = "BinRow", from = "BinRow")]
pub struct Bin {
    pub x: f64,
    pub y: f64,
    /// `(q, u)` with their errors (no covariance: a bin's errors are taken as independent).
    pub qu: mueller::Qu,
    /// `p`, `phi` (rad) of the paper's approximate solution (`eq:approx`), NaN when the bin
    /// did not come from a sky-field solution (e.g. an imported map).
    pub p_approx: f64,
    pub phi_approx: f64,
    /// Whether the last fit used this bin (inside the region, not excluded, finite).
    pub used: bool,
}

/// `sign(v) sqrt(|v|)`: the error `s` of a variance stored as `s |s|`.
fn signed_sqrt(v: f64) -> f64 {
    v.signum() * v.abs().sqrt()
}

/// A bin as files and JSON write it: its errors as `sigma_q`, `sigma_u`.
#[derive(Serialize, Deserialize)]
struct BinRow {
    x: f64,
    y: f64,
    q: f64,
    u: f64,
    sigma_q: f64,
    sigma_u: f64,
    p_approx: f64,
    phi_approx: f64,
    used: bool,
}

impl From<Bin> for BinRow {
    fn from(b: Bin) -> Self {
        let Bin { x, y, qu, p_approx, phi_approx, used } = b;
        BinRow { x, y, q: qu.q, u: qu.u, sigma_q: b.sigma_q(), sigma_u: b.sigma_u(), p_approx, phi_approx, used }
    }
}

impl From<BinRow> for Bin {
    fn from(r: BinRow) -> Self {
        Bin {
            p_approx: r.p_approx,
            phi_approx: r.phi_approx,
            used: r.used,
            ..Bin::new(r.x, r.y, r.q, r.u, r.sigma_q, r.sigma_u)
        }
    }
}

impl Bin {
    /// A bin with no approximate solution attached; its errors are 1-sigma and independent.
    pub fn new(x: f64, y: f64, q: f64, u: f64, sigma_q: f64, sigma_u: f64) -> Self {
        let qu = mueller::Qu::from_sigmas(q, u, sigma_q, sigma_u, 0.0);
        Bin { x, y, qu, p_approx: f64::NAN, phi_approx: f64::NAN, used: true }
    }

    /// The 1-sigma error of `q` as given, its sign kept: [`mueller::Qu::from_sigmas`] stores
    /// `s |s|`, and `sqrt(fl(s^2)) = |s|` exactly in binary floating point, so a file's or a
    /// fit's error comes back bit for bit, and a negative one (refused by
    /// [`Bin::is_valid`] and by the calibration file's reader) stays negative.
    pub fn sigma_q(&self) -> f64 {
        signed_sqrt(self.qu.var_q)
    }

    /// The 1-sigma error of `u` (as [`Bin::sigma_q`]).
    pub fn sigma_u(&self) -> f64 {
        signed_sqrt(self.qu.var_u)
    }

    /// Whether every number a fit needs is finite and the errors are positive.
    pub fn is_valid(&self) -> bool {
        [self.x, self.y, self.qu.q, self.qu.u].iter().all(|v| v.is_finite())
            && self.sigma_q().is_finite()
            && self.sigma_u().is_finite()
            && self.sigma_q() > 0.0
            && self.sigma_u() > 0.0
    }

    /// `(p, phi)` of the bin, phi in [0, pi).
    pub fn p_phi(&self) -> (f64, f64) {
        stokes::polarization(self.qu.q, self.qu.u)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bin gives back the errors it was made with, bit for bit and with their sign, though
    /// it keeps them as variances: sqrt(fl(s^2)) = |s| for binary floating point (no overflow or
    /// underflow); and a bin's file row is the same numbers.
    #[test]
    fn errors_come_back_bit_for_bit_with_their_sign() {
        let mut s = 1.234_567_890_123e-6;
        for _ in 0..2000 {
            s *= 1.003_7;
            for v in [s, -s] {
                let b = Bin::new(0.5, -0.5, 0.01, -0.02, v, 2.0 * v);
                assert_eq!((b.sigma_q().to_bits(), b.sigma_u().to_bits()), (v.to_bits(), (2.0 * v).to_bits()));
                assert_eq!(b.is_valid(), v > 0.0);
            }
        }
        let b = Bin::new(0.0, 0.0, 0.0, 0.0, f64::NAN, 0.0);
        assert!(b.sigma_q().is_nan() && !b.is_valid());
        let row = BinRow::from(Bin::new(1.0, 2.0, 0.003, 0.004, 1e-4, -2e-4));
        assert_eq!((row.q, row.u, row.sigma_q, row.sigma_u), (0.003, 0.004, 1e-4, -2e-4));
    }
}
