//! Robust statistics of a sample: the one median of the workspace, the one factor that turns a
//! median absolute deviation (MAD) into a Gaussian sigma, and the one-pass sigma-clipped mean.
//!
//! Every crate that needs a median, a robust sigma or a clipped mean uses these: the raw
//! calibration's master frames and robust means, the binning, the background mesh, the
//! photometry and the fits' robust scales. The iterative clippings that must be fast (the
//! binning's multi-column clipping and the background mesh's, in `skyfield::bin`) search their
//! medians by a windowed selection that gives exactly [`median`] with [`Middle::Mean`], and
//! their tests check them to the bit against plain versions written with [`median`].
//!
//! Values are ordered by `f64::total_cmp` (so `-0.0` sorts below `+0.0` and NaNs sort last):
//! equal values in that order have equal bits, so a selection and a full sort give the same
//! median to the bit.

/// `1 / Phi^-1(3/4) = 1.482602218505602...`: the median absolute deviation of a Gaussian sample
/// times this is its sigma (`Phi^-1` is the inverse of the standard normal distribution
/// function; `Phi^-1(3/4) = 0.6744897501960817`).
pub const MAD_TO_SIGMA: f64 = 1.482_602_218_505_602;

/// Which value the median of an even count of values is: the two middle values (ranks
/// `n/2 - 1` and `n/2`, 0-based, in `f64::total_cmp` order) are both medians.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Middle {
    /// Their mean, `0.5 * (lower + upper)`: the usual definition, used for nearly every
    /// statistic (robust centres and scales, clipping, summaries).
    Mean,
    /// The upper one (rank `n/2`), always a member of the sample: what the telescope fit's
    /// outlier flags, the o/e offset search's sky level and noise, and calibrate-mueller's
    /// summary of a Mueller field have always taken.
    Upper,
}

/// The median of `v`, reordering `v` (a selection, O(n)); NaN for an empty slice. For an odd
/// count the middle value (rank `n/2`); for an even count the choice `middle` makes.
pub fn median(v: &mut [f64], middle: Middle) -> f64 {
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    let (below, m, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let upper = *m;
    if n % 2 == 1 || middle == Middle::Upper {
        upper
    } else {
        // The largest value below rank n/2 is the value of rank n/2 - 1.
        let lower = below.iter().copied().max_by(f64::total_cmp).expect("n >= 2");
        0.5 * (lower + upper)
    }
}

/// The [`median`] of the finite values among `values` (NaN and infinities left out); `None`
/// when there are none.
pub fn finite_median(values: impl IntoIterator<Item = f64>, middle: Middle) -> Option<f64> {
    let mut v: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
    (!v.is_empty()).then(|| median(&mut v, middle))
}

/// What a one-pass clipping keeps when the robust sigma is zero (more than half the values
/// equal to the median).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ZeroSpread {
    /// Every value (nothing can be judged an outlier on a zero scale).
    KeepAll,
    /// Only the values equal to the median (the limit `nsigma * 0` taken literally); the
    /// median itself when none is.
    KeepMedian,
}

/// The sigma-clipped mean of `v`: the median and the robust sigma ([`MAD_TO_SIGMA`] times the
/// MAD, both with [`Middle::Mean`]), the values farther than `nsigma` robust sigmas from the
/// median rejected, the mean of the rest (summed in the order of `v`); the median when nothing
/// is kept. `None` for an empty `v`. One pass: the statistics are not recomputed after the
/// rejection. `zero` says what is kept when the robust sigma is zero.
pub fn clipped_mean(v: &[f64], nsigma: f64, zero: ZeroSpread) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mut w = v.to_vec();
    let med = median(&mut w, Middle::Mean);
    for x in w.iter_mut() {
        *x = (*x - med).abs();
    }
    let s = MAD_TO_SIGMA * median(&mut w, Middle::Mean);
    let keep_all = s == 0.0 && zero == ZeroSpread::KeepAll;
    let (sum, n) =
        v.iter().filter(|x| keep_all || (*x - med).abs() <= nsigma * s).fold((0.0, 0usize), |(a, n), x| (a + x, n + 1));
    Some(if n > 0 { sum / n as f64 } else { med })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The median by a full sort, written out for each middle.
    fn sorted(v: &[f64], middle: Middle) -> f64 {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        let n = s.len();
        match (n % 2, middle) {
            (1, _) | (_, Middle::Upper) => s[n / 2],
            _ => (s[n / 2 - 1] + s[n / 2]) / 2.0,
        }
    }

    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0], Middle::Mean), 2.0);
        assert_eq!(median(&mut [3.0, 1.0, 2.0], Middle::Upper), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0], Middle::Mean), 2.5);
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0], Middle::Upper), 3.0);
        assert_eq!(median(&mut [7.0], Middle::Mean), 7.0);
        assert!(median(&mut [], Middle::Mean).is_nan());
        assert!(median(&mut [], Middle::Upper).is_nan());
    }

    #[test]
    fn median_is_the_sorted_median_to_the_bit() {
        // A deterministic scramble with ties, signed zeros and both signs.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for n in 1..60 {
            let v: Vec<f64> = (0..n)
                .map(|_| {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    match state % 7 {
                        0 => 0.0,
                        1 => -0.0,
                        _ => ((state >> 20) % 23) as f64 * 0.1 - 1.1,
                    }
                })
                .collect();
            for middle in [Middle::Mean, Middle::Upper] {
                let got = median(&mut v.clone(), middle);
                assert_eq!(got.to_bits(), sorted(&v, middle).to_bits(), "n = {n}, {middle:?}: {v:?}");
            }
        }
    }

    /// The constant against its closed form: `1 / Phi^-1(3/4)` with cephes' inverse normal,
    /// and `Phi(1 / MAD_TO_SIGMA) = 3/4` with cephes' error function.
    #[test]
    fn mad_to_sigma_is_one_over_the_upper_quartile_of_the_normal() {
        use spec_math::cephes64::{erf, ndtri};
        assert!((MAD_TO_SIGMA * ndtri(0.75) - 1.0).abs() < 1e-15);
        assert!((0.5 * (1.0 + erf(1.0 / MAD_TO_SIGMA / 2f64.sqrt())) - 0.75).abs() < 1e-15);
    }

    #[test]
    fn finite_median_leaves_out_nan_and_infinities() {
        let v = [f64::NAN, 4.0, f64::INFINITY, 1.0, f64::NEG_INFINITY, 3.0, 2.0];
        assert_eq!(finite_median(v, Middle::Mean), Some(2.5));
        assert_eq!(finite_median(v, Middle::Upper), Some(3.0));
        assert_eq!(finite_median([f64::NAN], Middle::Mean), None);
        assert_eq!(finite_median([], Middle::Upper), None);
    }

    #[test]
    fn clipped_mean_rejects_an_outlier_and_handles_zero_spread() {
        // Median 3, deviations {2, 1, 0, 1, 97}: MAD 1, so 1e2 is rejected at 3 sigma.
        assert_eq!(clipped_mean(&[1.0, 2.0, 3.0, 4.0, 100.0], 3.0, ZeroSpread::KeepAll), Some(2.5));
        // More than half equal: zero spread.
        let v = [5.0, 5.0, 5.0, 6.0];
        assert_eq!(clipped_mean(&v, 3.0, ZeroSpread::KeepAll), Some(21.0 / 4.0));
        assert_eq!(clipped_mean(&v, 3.0, ZeroSpread::KeepMedian), Some(5.0));
        // Median 5.5 of two values, MAD 0.5: both kept.
        assert_eq!(clipped_mean(&[5.0, 6.0], 3.0, ZeroSpread::KeepMedian), Some(5.5));
        // Nothing kept at nsigma 0 with a spread: the median.
        assert_eq!(clipped_mean(&[1.0, 2.0, 4.0, 8.0], 0.0, ZeroSpread::KeepAll), Some(3.0));
        assert_eq!(clipped_mean(&[], 3.0, ZeroSpread::KeepAll), None);
    }
}
