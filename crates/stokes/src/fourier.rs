//! Fourier analysis of the normalized flux differences over the HWP angle (`eq:fourcoeff`,
//! sections `sec:basics` and `sec:HWP`).
//!
//! For the optimal angle set `theta_i = i pi/8` the `F_i` are equally spaced samples of a
//! function of the plate angle, and
//!
//! ```text
//! F_i = a_0 + sum_{k=1}^{N/2} [ a_k cos(2 pi k i / N) + b_k sin(2 pi k i / N) ]
//! ```
//!
//! with `a_k` the **cosine** and `b_k` the **sine** coefficient, as the coefficient definitions
//! of `eq:fourcoeff` say. (The series printed just above `eq:fourcoeff` swaps `sin` and `cos`;
//! with that series `a_{N/4}` would be `U/I`, contradicting `a_4 = Q/I` of section `sec:HWP`.
//! We follow the definitions.) The polarization is the `k = N/4` harmonic:
//! `a_{N/4} = Q/I`, `b_{N/4} = U/I`.
//!
//! The Nyquist harmonic `k = N/2` (N even) is special: `sin(pi i) = 0`, so `b_{N/2} = 0`, and
//! `cos(pi i) = (-1)^i` is its own square, so `a_{N/2}` takes `1/N` (like `a_0`), not `2/N`;
//! with `2/N` the series would not reproduce the data.

use crate::Error;

/// One harmonic of the Fourier series of the `F_i`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Harmonic {
    /// Harmonic number: `k` cycles over the `N` sampled plate positions (`N pi/8` of plate
    /// rotation; `k = 1` is one cycle per full turn when `N = 16`).
    pub k: usize,
    /// Cosine coefficient `a_k`.
    pub a: f64,
    /// Sine coefficient `b_k` (0 for `k = 0` and for the Nyquist harmonic).
    pub b: f64,
    /// Standard error of `a_k`.
    pub sigma_a: f64,
    /// Standard error of `b_k`.
    pub sigma_b: f64,
}

impl Harmonic {
    /// The power `a_k^2 + b_k^2` (the harmonics power spectrum of `fig:fourier`).
    pub fn power(&self) -> f64 {
        self.a * self.a + self.b * self.b
    }
    /// The amplitude `sqrt(a_k^2 + b_k^2)`.
    pub fn amplitude(&self) -> f64 {
        self.a.hypot(self.b)
    }
}

/// `(cos, sin)` of `2 pi m / n`, exact (no rounding residue) at the quarter turns, so that
/// harmonics that are absent come out as exact zeros where the sampling allows.
pub(crate) fn cis(m: usize, n: usize) -> (f64, f64) {
    let m = m % n;
    if (4 * m).is_multiple_of(n) {
        return match 4 * m / n {
            0 => (1.0, 0.0),
            1 => (0.0, 1.0),
            2 => (-1.0, 0.0),
            _ => (0.0, -1.0),
        };
    }
    let a = 2.0 * std::f64::consts::PI * m as f64 / n as f64;
    (a.cos(), a.sin())
}

/// Fourier coefficients `a_k`, `b_k` (`eq:fourcoeff`) of equally spaced `F_i` for
/// `k = 0 ..= N/2`, with errors propagated from the per-point errors `sigma_f`:
/// `sigma_a_k = (2/N) sqrt(sum sigma_i^2 cos^2(2 pi k i/N))` (and `sin` for `b_k`), the
/// expression of section `sec:HWP` with `1/SNR` generalised to a per-point `sigma_i`;
/// `k = 0` and the Nyquist `k = N/2` take `1/N` instead of `2/N`.
///
/// The caller decides whether the `F_i` are equally spaced in plate angle (the optimal set
/// `theta_i = i pi/8`); the paper uses `N = 4, 8, 12, 16`.
///
/// ```
/// use stokes::fourier::fourier_coefficients;
/// // F_i = 0.01 + 0.03 cos(pi i / 2) on N = 4 points.
/// let f = [0.04, 0.01, -0.02, 0.01];
/// let h = fourier_coefficients(&f, &[1e-3; 4]).unwrap();
/// assert!((h[0].a - 0.01).abs() < 1e-15 && (h[1].a - 0.03).abs() < 1e-15);
/// ```
pub fn fourier_coefficients(f: &[f64], sigma_f: &[f64]) -> Result<Vec<Harmonic>, Error> {
    let n = f.len();
    if n < 2 {
        return Err(Error::TooFewAngles(n));
    }
    if sigma_f.len() != n {
        return Err(Error::LengthMismatch { what: "sigma_F", got: sigma_f.len(), expected: n });
    }
    let nf = n as f64;
    (0..=n / 2)
        .map(|k| {
            let nyquist = n.is_multiple_of(2) && k == n / 2;
            let norm = if k == 0 || nyquist { 1.0 / nf } else { 2.0 / nf };
            let (mut a, mut b, mut va, mut vb) = (0.0, 0.0, 0.0, 0.0);
            for i in 0..n {
                let (c, s) = cis(k * i, n);
                let v = sigma_f[i] * sigma_f[i];
                a += f[i] * c;
                b += f[i] * s;
                va += v * c * c;
                vb += v * s * s;
            }
            Ok(Harmonic { k, a: norm * a, b: norm * b, sigma_a: norm * va.sqrt(), sigma_b: norm * vb.sqrt() })
        })
        .collect()
}

/// The Fourier series evaluated at sample `i` of `n`: `a_0 + sum (a_k cos + b_k sin)` over the
/// given harmonics (pass a subset for a partial reconstruction, as in `fig:fourier`).
pub fn reconstruct(harmonics: &[Harmonic], i: usize, n: usize) -> f64 {
    harmonics
        .iter()
        .map(|h| {
            let (c, s) = cis(h.k * i, n);
            h.a * c + h.b * s
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// A synthetic series with every harmonic present, Nyquist included, is reproduced
    /// exactly: this pins the 1/N normalisation of a_0 and a_{N/2} and the a<->cos pairing.
    #[test]
    fn synthetic_series_round_trip_with_nyquist() {
        for n in [4usize, 8, 12, 16, 7] {
            let coef: Vec<(f64, f64)> =
                (0..=n / 2).map(|k| (0.01 * (k as f64 + 1.0), if k == 0 { 0.0 } else { -0.003 * k as f64 })).collect();
            let f: Vec<f64> = (0..n)
                .map(|i| {
                    coef.iter()
                        .enumerate()
                        .map(|(k, &(a, b))| {
                            let (c, s) = cis(k * i, n);
                            a * c + b * s
                        })
                        .sum()
                })
                .collect();
            let h = fourier_coefficients(&f, &vec![1e-3; n]).unwrap();
            for (k, hk) in h.iter().enumerate() {
                assert_eq!(hk.k, k);
                let nyq = n % 2 == 0 && k == n / 2;
                assert_relative_eq!(hk.a, coef[k].0, epsilon = 1e-15);
                // sin(pi i) = 0: the Nyquist sine is invisible, so b_{N/2} = 0.
                let b_expected = if nyq { 0.0 } else { coef[k].1 };
                assert_relative_eq!(hk.b, b_expected, epsilon = 1e-15);
            }
            for i in 0..n {
                assert_relative_eq!(reconstruct(&h, i, n), f[i], epsilon = 1e-15);
            }
        }
    }

    /// section sec:HWP: sigma_a_k = 2/(N SNR) sqrt(sum cos^2) for equal errors; for
    /// 0 < k < N/2 that is sqrt(2/N)/SNR.
    #[test]
    fn sigma_matches_paper_formula() {
        let (n, snr) = (16usize, 1600.0);
        let h = fourier_coefficients(&vec![0.0; n], &vec![1.0 / snr; n]).unwrap();
        for hk in &h[1..n / 2] {
            let sum_c2: f64 = (0..n).map(|i| cis(hk.k * i, n).0.powi(2)).sum();
            assert_relative_eq!(hk.sigma_a, 2.0 / (n as f64 * snr) * sum_c2.sqrt(), max_relative = 1e-14);
            assert_relative_eq!(hk.sigma_a, (2.0 / n as f64).sqrt() / snr, max_relative = 1e-12);
            assert_relative_eq!(hk.sigma_b, (2.0 / n as f64).sqrt() / snr, max_relative = 1e-12);
        }
        assert_relative_eq!(h[0].sigma_a, 1.0 / ((n as f64).sqrt() * snr), max_relative = 1e-14);
        assert_relative_eq!(h[n / 2].sigma_a, 1.0 / ((n as f64).sqrt() * snr), max_relative = 1e-14);
        assert_eq!(h[n / 2].sigma_b, 0.0);
    }
}
