//! The Wollaston imbalance `kappa = (t - s)/(t + s)` from the data themselves (section
//! `sec:wollaston`: `eq:kappa`, `eq:g`, `eq:kappa2`, `eq:a0`) and the flux correction for a
//! known `kappa`.
//!
//! With an imbalanced prism `F_i = (kappa + m_i)/(1 + kappa m_i)` (`eq:kappa`), where
//! `m_i = Q cos 4theta_i + U sin 4theta_i`. Two plate positions `pi/4` apart have `4 theta`
//! differing by `pi`, hence `m` and `-m`; for such a pair `(F_a, F_b)`
//!
//! ```text
//! F_a + F_b     = 2 kappa (1 - m^2) / (1 - kappa^2 m^2)
//! 1 + F_a F_b   = (1 + kappa^2)(1 - m^2) / (1 - kappa^2 m^2)
//! g = (1 + F_a F_b)/(F_a + F_b) = (1 + kappa^2) / (2 kappa)          (eq:g)
//! ```
//!
//! so `kappa^2 - 2 g kappa + 1 = 0` and `kappa = g -+ sqrt(g^2 - 1)` (`eq:kappa2`), the root
//! with `|kappa| <= 1`. In the optimal set `theta_i = i pi/8` the pair is `(F_{j-1}, F_{j+1})`.
//!
//! **Indexing.** The paper writes `j = 1, ..., N/2 - 2`, which gives no estimate at all for
//! `N = 4`, while the next sentence promises two for `N = 4`. Every `j` with both neighbours
//! inside the set works, `j = 1, ..., N - 2`, which gives the promised two for `N = 4`
//! (`(F_0, F_2)` and `(F_1, F_3)`); we read the paper's bound as `N - 2`. For `N > 4` these
//! `N - 2` estimates share `F`s and are not independent.
//!
//! **Numerics.** Computing `g - sqrt(g^2 - 1)` subtracts near-equal numbers when `kappa -> 0`
//! (`g -> infinity`) and is `inf - inf` when `F_a + F_b = 0`. With `S = F_a + F_b`,
//! `R = 1 + F_a F_b` and the identity `R^2 - S^2 = (1 - F_a^2)(1 - F_b^2)`:
//!
//! ```text
//! kappa = 1 / (g + sign(g) sqrt(g^2 - 1)) = S / (R + sqrt((1 - F_a^2)(1 - F_b^2)))
//! ```
//!
//! which has no cancellation, gives `kappa = 0` exactly for `S = 0`, and `+-1` at the edges.
//! Since `|F| <= 1` whenever both beam fluxes are non-negative, `|g| >= 1` always holds for
//! such data; only a negative beam flux (background-subtracted noise) can break it, which is
//! flagged and clamped.

/// One estimate `kappa_j` from the pair `(F_{j-1}, F_{j+1})` (`eq:g`, `eq:kappa2`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct KappaEstimate {
    /// Middle index `j` (0-based positions `j - 1` and `j + 1` are used).
    pub j: usize,
    /// `g_j` of `eq:g` (infinite when `F_{j-1} + F_{j+1} = 0`).
    pub g: f64,
    /// `kappa_j` of `eq:kappa2`, in `[-1, 1]`.
    pub kappa: f64,
    /// True when the data were not consistent with `eq:kappa` (`|g| < 1`, possible only with
    /// `|F| > 1`, i.e. a negative beam flux) and `kappa` was clamped.
    pub clamped: bool,
}

/// `g = (1 + F_a F_b)/(F_a + F_b)` (`eq:g`); `+-inf` when `F_a + F_b = 0`.
pub fn g(f_a: f64, f_b: f64) -> f64 {
    (1.0 + f_a * f_b) / (f_a + f_b)
}

/// `kappa` from a pair of `F` at plate positions `pi/4` apart (`eq:kappa2`), in the
/// cancellation-free form `S / (R + sqrt((1 - F_a^2)(1 - F_b^2)))`. Returns `(kappa, clamped)`.
///
/// ```
/// use stokes::kappa::kappa_from_pair;
/// // eq:kappa: F = (m + kappa)/(1 + kappa m); two plate positions pi/4 apart see m and -m.
/// let (kappa, m) = (0.08, 0.03);
/// let fa = (m + kappa) / (1.0 + kappa * m);
/// let fb = (-m + kappa) / (1.0 - kappa * m);
/// let (k, clamped) = kappa_from_pair(fa, fb);
/// assert!((k - kappa).abs() < 1e-15 && !clamped);
/// ```
pub fn kappa_from_pair(f_a: f64, f_b: f64) -> (f64, bool) {
    let s = f_a + f_b;
    let r = 1.0 + f_a * f_b;
    // (1 - F)(1 + F) rather than 1 - F^2: exact near |F| = 1.
    let d = (1.0 - f_a) * (1.0 + f_a) * (1.0 - f_b) * (1.0 + f_b);
    let mut clamped = d < 0.0;
    let den = r + d.max(0.0).sqrt();
    let mut k = if s == 0.0 {
        0.0
    } else if den > 0.0 {
        s / den
    } else {
        clamped = true;
        s.signum()
    };
    if !(k.abs() <= 1.0) {
        clamped = true;
        k = k.clamp(-1.0, 1.0);
    }
    (k, clamped)
}

/// All estimates `kappa_j` (`eq:kappa2`) for `j = 1 ..= N - 2` whose neighbours
/// `theta_{j-1}`, `theta_{j+1}` are `pi/4` apart modulo `pi/2` (always true for the optimal
/// set). Empty when `N < 3` or no triple qualifies (for the optimal set: `N < 4`).
pub fn kappa_estimates(theta: &[f64], f: &[f64]) -> Vec<KappaEstimate> {
    let n = theta.len().min(f.len());
    if n < 3 {
        return Vec::new();
    }
    (1..n - 1)
        .filter(|&j| {
            // 4 (theta_{j+1} - theta_{j-1}) = pi (mod 2 pi): the modulations are m and -m.
            let d = (4.0 * (theta[j + 1] - theta[j - 1]) - std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI);
            d.min(2.0 * std::f64::consts::PI - d) < 1e-9
        })
        .map(|j| {
            let (kappa, clamped) = kappa_from_pair(f[j - 1], f[j + 1]);
            KappaEstimate { j, g: g(f[j - 1], f[j + 1]), kappa, clamped }
        })
        .collect()
}

/// `kappa` at one HWP angle when the input polarization is known (section `sec:wollaston`):
/// `kappa_i = (F_i - m_i)/(1 - F_i m_i)` with `m_i = Q cos 4theta_i + U sin 4theta_i`, the
/// inversion of `eq:kappa`. (The paper prints the denominator as `F_i m_i`; inverting
/// `eq:kappa` gives `1 - F_i m_i`, and only this form returns `kappa` for noiseless data.)
///
/// ```
/// // eq:kappa inverted at one angle: a source of known m = 0.02 measured at
/// // F = (m + kappa)/(1 + kappa m) with kappa = 0.05.
/// let f = (0.02 + 0.05) / (1.0 + 0.05 * 0.02);
/// assert!((stokes::kappa::kappa_from_known(f, 0.02) - 0.05).abs() < 1e-15);
/// ```
pub fn kappa_from_known(f: f64, m: f64) -> f64 {
    (f - m) / (1.0 - f * m)
}

/// `a_0 = (1/N) sum F_i` (`eq:a0`): for `N` a multiple of 4 on the optimal set and `P << 1`
/// it approximates `kappa` (or the post-analyzer term `B cos 2phi`, section `sec:postwp`).
///
/// ```
/// // eq:a0: the mean of the F_i; the polarization's cos 4theta term cancels over the optimal
/// // set and leaves a Wollaston imbalance F = 2t - 1 = 0.004 (t = 0.502) alone.
/// let f: Vec<f64> = mueller::optimal_angles(8).iter().map(|t| 0.004 + 0.01 * (4.0 * t).cos()).collect();
/// assert!((stokes::kappa::a0(&f) - 0.004).abs() < 1e-16);
/// ```
pub fn a0(f: &[f64]) -> f64 {
    f.iter().sum::<f64>() / f.len() as f64
}

/// The fluxes corrected for a known `kappa` (section `sec:wollaston`): `f_O / (1 + kappa)` and
/// `f_E / (1 - kappa)` (the paper's `2t` and `2(1 - t)`; with `s != 1 - t` this divides by
/// `2t/(t+s)` and `2s/(t+s)`, which is what makes `F_i = m_i` again).
///
/// ```
/// // A prism of t = 0.55 (kappa = 0.1) puts 2t = 1.1 and 2(1 - t) = 0.9 of an unpolarized
/// // source's 1000 e- per beam in the two beams; corrected, they are equal again.
/// let (o, e) = stokes::kappa::correct_fluxes(1100.0, 900.0, 0.1);
/// assert!((o - 1000.0).abs() < 1e-12 && (e - 1000.0).abs() < 1e-12);
/// ```
pub fn correct_fluxes(f_o: f64, f_e: f64, kappa: f64) -> (f64, f64) {
    (f_o / (1.0 + kappa), f_e / (1.0 - kappa))
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn f_of(kappa: f64, m: f64) -> f64 {
        (kappa + m) / (1.0 + kappa * m)
    }

    /// eq:kappa2 in the cancellation-free form agrees with the textbook root where that
    /// root is well conditioned, and with eq:g.
    #[test]
    fn matches_textbook_root_and_eq_g() {
        for &kappa in &[0.3, -0.3, 0.1, -0.1, 0.9, -0.9] {
            for &m in &[0.0, 0.05, -0.2, 0.5] {
                let (fa, fb) = (f_of(kappa, m), f_of(kappa, -m));
                let gg = g(fa, fb);
                assert_relative_eq!(gg, (1.0 + kappa * kappa) / (2.0 * kappa), max_relative = 1e-12);
                let textbook = if gg > 0.0 { gg - (gg * gg - 1.0).sqrt() } else { gg + (gg * gg - 1.0).sqrt() };
                let (k, clamped) = kappa_from_pair(fa, fb);
                assert!(!clamped);
                assert_relative_eq!(k, textbook, max_relative = 1e-10);
                assert_relative_eq!(k, kappa, max_relative = 1e-12);
            }
        }
    }

    /// kappa -> 0 (g -> infinity): relative accuracy stays at rounding level, where the
    /// textbook g - sqrt(g^2-1) loses every digit.
    #[test]
    fn tiny_kappa_relative_accuracy() {
        for &kappa in &[1e-6, -1e-9, 1e-12, 1e-15] {
            let m = 0.03;
            let (k, _) = kappa_from_pair(f_of(kappa, m), f_of(kappa, -m));
            assert_relative_eq!(k, kappa, max_relative = 1e-6);
        }
        // F_{j-1} + F_{j+1} = 0: g infinite, kappa exactly 0, no NaN.
        let (k, c) = kappa_from_pair(0.02, -0.02);
        assert_eq!((k, c), (0.0, false));
        assert!(g(0.02, -0.02).is_infinite());
    }

    #[test]
    fn edges_and_noise() {
        // kappa = +-1: one beam is dark, F = +-1 everywhere.
        assert_eq!(kappa_from_pair(1.0, 1.0), (1.0, false));
        assert_eq!(kappa_from_pair(-1.0, -1.0), (-1.0, false));
        // Close to the edge.
        let kappa = 1.0 - 1e-9;
        let (k, _) = kappa_from_pair(f_of(kappa, 0.1), f_of(kappa, -0.1));
        assert_relative_eq!(k, kappa, max_relative = 1e-12);
        // |F| > 1 (a negative beam flux): flagged, clamped, finite.
        let (k, c) = kappa_from_pair(1.2, 0.9);
        assert!(c && k.is_finite() && k.abs() <= 1.0);
    }

    #[test]
    fn known_polarization_inverts_eq_kappa() {
        let (kappa, m) = (0.1, 0.05);
        assert_relative_eq!(kappa_from_known(f_of(kappa, m), m), kappa, max_relative = 1e-13);
    }

    #[test]
    fn correction_restores_eq_system() {
        // Any t, s: f_O = t (1 + m), f_E = s (1 - m).
        let (t, s, m) = (0.47, 0.58, 0.03);
        let kappa = (t - s) / (t + s);
        let (o, e) = correct_fluxes(t * (1.0 + m), s * (1.0 - m), kappa);
        assert_relative_eq!((o - e) / (o + e), m, max_relative = 1e-13);
    }
}
