//! The polar-angle test of section `sec:fors1` (lower panels of fig:radprofB): the angle `phi`
//! of the instrumental polarization against the polar angle `alpha` of the bin about the
//! centre. A radial pattern lies on `phi = alpha` (slope 1, intercept 0, modulo 180 deg).

use crate::models::bins::Bin;
use crate::models::radial::ErrorScaling;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// The fitted line `phi = slope * alpha + intercept` (degrees) and the points it was fitted to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolarAngleTest {
    pub slope: f64,
    pub slope_err: f64,
    pub intercept_deg: f64,
    pub intercept_err_deg: f64,
    /// Per used bin: `alpha` in (-180, 180] deg and `phi` unwrapped onto the fitted line (deg).
    pub alpha_deg: Vec<f64>,
    pub phi_deg: Vec<f64>,
    pub sigma_phi_deg: Vec<f64>,
    /// The test against noise: the probability that bins of pure noise (no instrumental
    /// polarization at all) give a chi^2 of (q, u) about zero at least as large as observed,
    /// `chi^2 = sum q^2/sigma_q^2 + u^2/sigma_u^2` with `2 n` degrees of freedom. The line
    /// above is fitted whatever the data (noise unwrapped onto a line of slope 1 gives slope
    /// ~1), so it means something only when this is small.
    #[serde(default = "one")]
    pub noise_p_value: f64,
    /// The weighted mean radial component `q cos 2alpha + u sin 2alpha` in units of its error:
    /// > 0 radial, < 0 tangential, ~N(0, 1) for noise.
    #[serde(default)]
    pub radial_z: f64,
}

fn one() -> f64 {
    1.0
}

/// Below this noise probability the pattern counts as detected (1 %).
pub const NOISE_P_THRESHOLD: f64 = 0.01;

impl PolarAngleTest {
    /// True when the bins carry a polarization pattern at all (noise rejected at
    /// [`NOISE_P_THRESHOLD`]); when false the slope and intercept describe noise.
    pub fn pattern_detected(&self) -> bool {
        self.noise_p_value < NOISE_P_THRESHOLD
    }

    /// False when fewer than three bins have a polarization angle (`P = 0` to rounding): the
    /// line is then undefined (NaN), the test against noise still made.
    pub fn angles_defined(&self) -> bool {
        self.slope.is_finite()
    }

    /// One line for tables: the fit, or "no radial pattern" with the noise probability.
    pub fn verdict(&self) -> String {
        if !self.angles_defined() {
            format!(
                "no polarization angle: P = 0 in (almost) every bin, the line is undefined (against noise: p = {:.3})",
                self.noise_p_value
            )
        } else if self.pattern_detected() {
            format!(
                "pattern detected (noise p = {:.2e}; radial component {:+.1} sigma)",
                self.noise_p_value, self.radial_z
            )
        } else {
            format!(
                "no radial pattern: the bins are consistent with noise (p = {:.3}, radial component {:+.1} sigma); \
                 the slope below describes noise",
                self.noise_p_value, self.radial_z
            )
        }
    }
}

/// Upper tail of chi^2 with `2 n` degrees of freedom at `chi2`: `exp(-x) sum_{k<n} x^k/k!`,
/// `x = chi2/2` (closed form for even degrees of freedom), summed in logs (no overflow for
/// thousands of bins).
pub fn chi2_even_sf(chi2: f64, n: usize) -> f64 {
    let x = 0.5 * chi2;
    if !(x > 0.0) {
        return 1.0;
    }
    let (lx, mut lt, mut best) = (x.ln(), -x, f64::NEG_INFINITY);
    let mut terms = Vec::with_capacity(n);
    for k in 0..n {
        if k > 0 {
            lt += lx - (k as f64).ln();
        }
        terms.push(lt);
        best = best.max(lt);
    }
    let s: f64 = terms.iter().map(|t| (t - best).exp()).sum();
    (best + s.ln()).exp().min(1.0)
}

/// `a` wrapped into (-90, 90]: differences of polarization angles are taken modulo 180 deg.
pub fn wrap_half_turn_deg(a: f64) -> f64 {
    let w = (a + 90.0).rem_euclid(180.0) - 90.0;
    if w <= -90.0 {
        w + 180.0
    } else {
        w
    }
}

/// Fit `phi` against `alpha` for the bins (about `centre`, arcmin) by weighted least squares
/// with weights `1 / sigma_phi^2`, unwrapping each `phi` onto the current line (modulo 180
/// deg) and iterating. Bins closer than `r_min` arcmin to the centre are left out (their
/// polar angle is ill defined). The errors are scaled by `max(1, chi2_red)`
/// ([`ErrorScaling::Conservative`]; [`polar_angle_test_with`] chooses).
pub fn polar_angle_test(bins: &[Bin], centre: [f64; 2], r_min: f64) -> Result<PolarAngleTest> {
    polar_angle_test_with(bins, centre, r_min, ErrorScaling::Conservative, 1.0)
}

/// [`polar_angle_test`] with the errors scaled as `scaling` says and the variances multiplied
/// by `inflation` (the correlated-errors factor of the radial fit on the same bins, or 1).
pub fn polar_angle_test_with(
    bins: &[Bin],
    centre: [f64; 2],
    r_min: f64,
    scaling: ErrorScaling,
    inflation: f64,
) -> Result<PolarAngleTest> {
    let mut alpha = vec![];
    let mut phi = vec![];
    let mut sig = vec![];
    // The noise test on the same bins: chi^2 about zero and the radial component.
    let (mut chi2_zero, mut n_noise, mut zr_num, mut zr_w) = (0.0, 0usize, 0.0, 0.0);
    for b in bins.iter().filter(|b| b.used && b.is_valid()) {
        let (dx, dy) = (b.x - centre[0], b.y - centre[1]);
        if dx.hypot(dy) < r_min {
            continue;
        }
        if b.sigma_q() > 0.0 && b.sigma_u() > 0.0 {
            chi2_zero += (b.qu.q / b.sigma_q()).powi(2) + (b.qu.u / b.sigma_u()).powi(2);
            n_noise += 1;
            let al = 2.0 * dy.atan2(dx);
            let radial = b.qu.q * al.cos() + b.qu.u * al.sin();
            let var = (b.sigma_q() * al.cos()).powi(2) + (b.sigma_u() * al.sin()).powi(2);
            zr_num += radial / var;
            zr_w += 1.0 / var;
        }
        let (p, ph) = b.p_phi();
        if p <= 0.0 {
            continue;
        }
        // sigma_phi = sqrt(u^2 sq^2 + q^2 su^2) / (2 p^2) (rad), from phi = atan2(u, q) / 2.
        let s = (b.qu.u * b.qu.u * b.sigma_q() * b.sigma_q() + b.qu.q * b.qu.q * b.sigma_u() * b.sigma_u()).sqrt()
            / (2.0 * p * p);
        alpha.push(crate::models::region::polar_angle(dx, dy).to_degrees());
        phi.push(ph.to_degrees());
        // Floor at 1e-3 deg: maps given without noise must not get infinite weights.
        sig.push(s.to_degrees().clamp(1e-3, 90.0));
    }
    let noise_p_value = if n_noise == 0 { 0.0 } else { chi2_even_sf(chi2_zero / inflation.max(1.0), n_noise) };
    let radial_z = if zr_w > 0.0 { zr_num / zr_w.sqrt() } else { 0.0 };
    if alpha.len() < 3 && n_noise >= 3 {
        // Bins enough, but (almost) none with a polarization angle: P = 0 to rounding, a field
        // free of instrumental polarization (an imported all-zero map). The line is undefined,
        // the test against noise is not: the field is measured, not unusable.
        let nan = f64::NAN;
        return Ok(PolarAngleTest {
            slope: nan,
            slope_err: nan,
            intercept_deg: nan,
            intercept_err_deg: nan,
            alpha_deg: alpha,
            phi_deg: phi,
            sigma_phi_deg: sig,
            noise_p_value,
            radial_z,
        });
    }
    if alpha.len() < 3 {
        return Err(Error::TooFewBins { used: alpha.len(), total: bins.len(), needed: 3 });
    }
    // Start from slope 1 and the circular mean offset of phi - alpha (period 180 deg), so that
    // a tangential pattern (offset 90) is not torn apart at the +-90 wrap.
    let (mut ss, mut cc) = (0.0, 0.0);
    for k in 0..alpha.len() {
        let d = 2.0 * (phi[k] - alpha[k]).to_radians();
        let w = 1.0 / (sig[k] * sig[k]);
        ss += w * d.sin();
        cc += w * d.cos();
    }
    let (mut a, mut b) = (1.0, 0.5 * ss.atan2(cc).to_degrees());
    let mut unwrapped = phi.clone();
    let mut cov = [[0.0; 2]; 2];
    for _ in 0..8 {
        for k in 0..alpha.len() {
            let line = a * alpha[k] + b;
            unwrapped[k] = line + wrap_half_turn_deg(phi[k] - line);
        }
        // Weighted linear regression.
        let (mut s, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for k in 0..alpha.len() {
            let w = 1.0 / (sig[k] * sig[k]);
            s += w;
            sx += w * alpha[k];
            sy += w * unwrapped[k];
            sxx += w * alpha[k] * alpha[k];
            sxy += w * alpha[k] * unwrapped[k];
        }
        let det = s * sxx - sx * sx;
        if !(det > 0.0) {
            return Err(Error::Degenerate("the bins do not span a range of polar angles".into()));
        }
        let (na, nb) = ((s * sxy - sx * sy) / det, (sxx * sy - sx * sxy) / det);
        cov = [[s / det, -sx / det], [-sx / det, sxx / det]];
        let done = (na - a).abs() < 1e-10 && (nb - b).abs() < 1e-8;
        a = na;
        b = nb;
        if done {
            break;
        }
    }
    let chi2: f64 = (0..alpha.len()).map(|k| ((unwrapped[k] - a * alpha[k] - b) / sig[k]).powi(2)).sum();
    let scale = scaling.factor(chi2 / (alpha.len() as f64 - 2.0).max(1.0)) * inflation;
    Ok(PolarAngleTest {
        slope: a,
        slope_err: (cov[0][0] * scale).sqrt(),
        intercept_deg: wrap_half_turn_deg(b),
        intercept_err_deg: (cov[1][1] * scale).sqrt(),
        alpha_deg: alpha,
        phi_deg: unwrapped,
        sigma_phi_deg: sig,
        // Bins without errors (noise-free maps) cannot be tested against noise: count as
        // detected, as before the test existed.
        noise_p_value,
        radial_z,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radial_and_tangential_patterns() {
        // A radial pattern (phi = alpha) has slope 1, intercept 0; a tangential one
        // (phi = alpha + 90) slope 1, intercept 90 == -90 modulo 180.
        for (offset, want) in [(0.0, 0.0), (90.0f64, 90.0)] {
            let mut bins = vec![];
            for k in 0..72 {
                let a = (k as f64 * 5.0 + 1.0).to_radians();
                let (x, y) = (2.0 * a.cos(), 2.0 * a.sin());
                let ph = a + offset.to_radians();
                bins.push(Bin::new(x, y, 0.01 * (2.0 * ph).cos(), 0.01 * (2.0 * ph).sin(), 1e-4, 1e-4));
            }
            let t = polar_angle_test(&bins, [0.0, 0.0], 0.1).unwrap();
            assert!((t.slope - 1.0).abs() < 1e-9, "{}", t.slope);
            assert!(wrap_half_turn_deg(t.intercept_deg - want).abs() < 1e-6, "{}", t.intercept_deg);
        }
    }

    /// chi^2 upper tail for even degrees of freedom against closed forms: 2 dof is exp(-x/2);
    /// 4 dof is (1 + x/2) exp(-x/2); the median of chi^2(200) is about 199.3.
    #[test]
    fn chi2_tail_closed_forms() {
        for x in [0.1, 1.0, 5.0, 30.0] {
            assert!((chi2_even_sf(x, 1) - (-x / 2.0f64).exp()).abs() < 1e-15);
            assert!((chi2_even_sf(x, 2) - (1.0 + x / 2.0) * (-x / 2.0f64).exp()).abs() < 1e-15);
        }
        let m = chi2_even_sf(199.33, 100);
        assert!((m - 0.5).abs() < 0.01, "{m}");
        assert!(chi2_even_sf(1e5, 3000) < 1e-300 || chi2_even_sf(1e5, 3000) == 0.0);
    }

    /// A field of pure noise (no instrumental polarization): the line fit reports slope ~1
    /// (noise unwrapped onto the starting line), but the test against noise does not reject
    /// noise: "no radial pattern". A weak radial pattern (3 sigma per bin) is detected, with a
    /// positive radial component; a tangential one with a negative one.
    #[test]
    fn pure_noise_is_no_radial_pattern() {
        let mut x = 0x9E3779B97F4A7C15u64;
        let mut gauss = move || {
            let mut u = || {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                ((x >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (a, b) = (u(), u());
            (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
        };
        let field = |amp: f64, offset: f64, g: &mut dyn FnMut() -> f64| {
            let mut bins = vec![];
            for i in 0..12 {
                for j in 0..12 {
                    let (x, y) = (i as f64 - 5.5, j as f64 - 5.5);
                    let a = y.atan2(x) + offset;
                    let s = 1e-4;
                    bins.push(Bin::new(x, y, amp * (2.0 * a).cos() + s * g(), amp * (2.0 * a).sin() + s * g(), s, s));
                }
            }
            polar_angle_test(&bins, [0.0, 0.0], 0.5).unwrap()
        };
        let noise = field(0.0, 0.0, &mut gauss);
        assert!(!noise.pattern_detected(), "{}", noise.noise_p_value);
        assert!(noise.radial_z.abs() < 3.0, "{}", noise.radial_z);
        assert!(noise.verdict().starts_with("no radial pattern"), "{}", noise.verdict());
        let radial = field(3e-4, 0.0, &mut gauss);
        assert!(radial.pattern_detected() && radial.radial_z > 10.0, "{} {}", radial.noise_p_value, radial.radial_z);
        let tangential = field(3e-4, std::f64::consts::FRAC_PI_2, &mut gauss);
        assert!(tangential.pattern_detected() && tangential.radial_z < -10.0, "{}", tangential.radial_z);
    }

    #[test]
    fn wrap_edges() {
        assert_eq!(wrap_half_turn_deg(90.0), 90.0);
        assert_eq!(wrap_half_turn_deg(-90.0), 90.0);
        assert!((wrap_half_turn_deg(179.0) + 1.0).abs() < 1e-12);
        assert!((wrap_half_turn_deg(-181.0) + 1.0).abs() < 1e-12);
    }
}
