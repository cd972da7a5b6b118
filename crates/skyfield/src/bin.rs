//! Binning with a sigma-clipped average: iterative, centred on the median, with the scale from
//! the median absolute deviation, so stars, cosmic rays and bad pixels inside a bin do not
//! pull its mean (the paper's "clipped average in 30 x 30 px bins", section `sec:fors1`).

/// Sigma-clipping settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ClipConfig {
    /// Rejection threshold in units of the robust sigma (default 3).
    pub nsigma: f64,
    /// Maximum number of iterations (default 10); clipping stops earlier when nothing changes.
    pub max_iter: usize,
}

impl Default for ClipConfig {
    fn default() -> Self {
        Self { nsigma: 3.0, max_iter: 10 }
    }
}

/// `1 / Phi^-1(3/4)`: turns a median absolute deviation into a Gaussian sigma.
pub const MAD_TO_SIGMA: f64 = 1.482_602_218_505_602;

/// Median of `v` (reorders `v`); NaN for an empty slice.
pub fn median_in_place(v: &mut [f64]) -> f64 {
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    let cmp = |a: &f64, b: &f64| a.total_cmp(b);
    let (_, m, _) = v.select_nth_unstable_by(n / 2, cmp);
    let hi = *m;
    if n % 2 == 1 {
        hi
    } else {
        let lo = v[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (lo + hi)
    }
}

/// `x` as an integer whose order is `f64::total_cmp`'s (the same transform).
#[inline]
fn total_key(x: f64) -> i64 {
    let b = x.to_bits() as i64;
    b ^ ((((b >> 63) as u64) >> 1) as i64)
}

/// Inverse of [`total_key`] (the transform is its own inverse: it never touches the sign bit).
#[inline]
fn from_total_key(k: i64) -> f64 {
    f64::from_bits(total_key(f64::from_bits(k as u64)) as u64)
}

/// [`median_in_place`] on [`total_key`]s (`v` not empty), exactly, helped by a `window` of keys `[lo, hi]` believed to hold the
/// median (the previous clipping iteration's, which moves little): one counting pass finds
/// how many keys lie below and inside it, and when the median's ranks fall inside, only the
/// window's keys (`win`, scratch) are searched. Otherwise, or without a window, the whole
/// slice is (`v` is then reordered).
fn median_keys_near(v: &mut [i64], window: Option<(i64, i64)>, win: &mut Vec<i64>) -> f64 {
    let n = v.len();
    let k = n / 2;
    if let Some((lo, hi)) = window {
        // Branch-free: every key is written, the count advances only for keys inside.
        win.resize(n + 1, 0);
        let (mut below, mut m) = (0, 0);
        for &x in v.iter() {
            below += (x < lo) as usize;
            win[m] = x;
            m += ((x >= lo) & (x <= hi)) as usize;
        }
        let win = &mut win[..m];
        // Both middle ranks (k - 1 and k for even n) must be inside the window.
        let first = if n % 2 == 1 { k } else { k - 1 };
        if below <= first && k < below + win.len() {
            let (left, m, _) = win.select_nth_unstable(k - below);
            let hi_v = from_total_key(*m);
            if n % 2 == 1 {
                return hi_v;
            }
            let lo_v = from_total_key(*left.iter().max().expect("rank k - 1 is in the window"));
            return 0.5 * (lo_v + hi_v);
        }
    }
    let (_, m, _) = v.select_nth_unstable(k);
    let hi = from_total_key(*m);
    if n % 2 == 1 {
        hi
    } else {
        let lo = from_total_key(*v[..k].iter().max().expect("n >= 2"));
        0.5 * (lo + hi)
    }
}

/// Keys of `[c - w, c + w]`, the window [`median_keys_near`] searches first.
fn key_window(c: f64, w: f64) -> (i64, i64) {
    (total_key(c - w), total_key(c + w))
}

/// Half-widths of the search windows, in units of the previous iteration's robust sigma:
/// about a tenth of a Gaussian sample falls inside either window, far more than the few
/// ranks the median and the MAD move when an iteration rejects a handful of values.
const MEDIAN_WINDOW: f64 = 0.125;
const MAD_WINDOW: f64 = 0.15;

/// Where a column's clipping ended: its median, MAD and robust sigma. Passed to the clipping
/// of a neighbouring bin as a hint of where to look first (it changes nothing but speed).
pub type ClipHint = Option<(f64, f64, f64)>;

/// Iterative sigma clipping of several columns at once: a row is kept only if it lies within
/// `nsigma` robust sigmas of the median in *every* column (so a star, bright in intensity but
/// with the sky's polarization, is still rejected). The robust sigma is `1.4826 MAD`; when the
/// MAD is zero (more than half the values identical) the standard deviation of the kept values
/// is used instead, and a column with zero spread rejects only values that differ from it.
/// Returns the keep mask.
pub fn sigma_clip_columns(cols: &[&[f64]], cfg: ClipConfig) -> Vec<bool> {
    sigma_clip_columns_hinted(cols, cfg, &mut vec![None; cols.len()])
}

/// [`sigma_clip_columns`] with one [`ClipHint`] per column: on entry where the medians and
/// MADs are probably (a neighbouring bin's: the sky changes little from bin to bin), on return
/// where this clipping ended. The result is the same whatever the hints.
pub fn sigma_clip_columns_hinted(cols: &[&[f64]], cfg: ClipConfig, hints: &mut [ClipHint]) -> Vec<bool> {
    assert_eq!(hints.len(), cols.len(), "one hint per column");
    let n = cols.first().map_or(0, |c| c.len());
    // The kept rows, compacted (row order kept): their indices and each column's values, so
    // that every pass below runs over contiguous memory without a mask.
    let mut rows: Vec<usize> = (0..n).filter(|&r| cols.iter().all(|c| c[r].is_finite())).collect();
    let mut vals: Vec<Vec<f64>> = cols.iter().map(|c| rows.iter().map(|&r| c[r]).collect()).collect();
    // Medians are selected on integer keys of the IEEE total order (what `median_in_place`
    // compares with `total_cmp`, without the per-comparison transform): same values. Each
    // median and MAD is first looked for near the previous iteration's (the hint's, at first).
    let mut buf: Vec<i64> = Vec::with_capacity(n);
    let mut win: Vec<i64> = Vec::new();
    let mut centre: Vec<(f64, f64)> = Vec::with_capacity(cols.len());
    for _ in 0..cfg.max_iter {
        let m = rows.len();
        if m < 3 {
            break;
        }
        centre.clear();
        for (ci, v) in vals.iter().enumerate() {
            buf.clear();
            buf.extend(v.iter().map(|&x| total_key(x)));
            let hint = hints[ci];
            let med = median_keys_near(&mut buf, hint.map(|(m, _, s)| key_window(m, MEDIAN_WINDOW * s)), &mut win);
            buf.clear();
            buf.extend(v.iter().map(|&x| total_key((x - med).abs())));
            let mad = median_keys_near(&mut buf, hint.map(|(_, d, s)| key_window(d, MAD_WINDOW * s)), &mut win);
            let mut sigma = MAD_TO_SIGMA * mad;
            if sigma == 0.0 {
                let mean = v.iter().sum::<f64>() / m as f64;
                sigma = (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / m as f64).sqrt();
            }
            hints[ci] = Some((med, mad, sigma));
            centre.push((med, cfg.nsigma * sigma));
        }
        // Keep the rows within every column's limit, compacting in place.
        let mut w = 0;
        for k in 0..m {
            let inside = vals.iter().zip(&centre).all(|(v, &(med, lim))| !((v[k] - med).abs() > lim));
            if inside {
                rows[w] = rows[k];
                for v in vals.iter_mut() {
                    v[w] = v[k];
                }
                w += 1;
            }
        }
        if w == m {
            break;
        }
        rows.truncate(w);
        for v in vals.iter_mut() {
            v.truncate(w);
        }
    }
    let mut keep = vec![false; n];
    for r in rows {
        keep[r] = true;
    }
    keep
}

/// One pixel's contribution to a bin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelSample {
    pub q: f64,
    pub u: f64,
    /// Intensity `f_O + f_E` per exposure (e-).
    pub i: f64,
    /// Photon + read noise variances of this pixel's q and u.
    pub var_q: f64,
    pub var_u: f64,
}

/// The clipped mean of a bin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BinStats {
    pub q: f64,
    pub u: f64,
    /// Standard errors of the means from the scatter of the kept pixels.
    pub sigma_q: f64,
    pub sigma_u: f64,
    pub cov_qu: f64,
    /// Standard errors of the means propagated from the per-pixel noise.
    pub sigma_q_phot: f64,
    pub sigma_u_phot: f64,
    pub intensity: f64,
    pub n_kept: usize,
}

/// Sigma-clipped mean of the pixels of one bin (clipping on q, u and intensity together).
/// `None` when fewer than `min_pixels` (at least 2) survive.
pub fn clipped_bin(samples: &[PixelSample], cfg: ClipConfig, min_pixels: usize) -> Option<BinStats> {
    clipped_bin_hinted(samples, cfg, min_pixels, &mut [None; 3])
}

/// [`clipped_bin`] with [`ClipHint`]s for q, u and intensity (see
/// [`sigma_clip_columns_hinted`]): same result, found faster along a row of bins.
pub fn clipped_bin_hinted(
    samples: &[PixelSample],
    cfg: ClipConfig,
    min_pixels: usize,
    hints: &mut [ClipHint; 3],
) -> Option<BinStats> {
    let q: Vec<f64> = samples.iter().map(|s| s.q).collect();
    let u: Vec<f64> = samples.iter().map(|s| s.u).collect();
    let i: Vec<f64> = samples.iter().map(|s| s.i).collect();
    let keep = sigma_clip_columns_hinted(&[&q, &u, &i], cfg, hints);
    let kept: Vec<&PixelSample> = samples.iter().zip(&keep).filter(|(_, &k)| k).map(|(s, _)| s).collect();
    let n = kept.len();
    if n < min_pixels.max(2) {
        return None;
    }
    let nf = n as f64;
    let mq = kept.iter().map(|s| s.q).sum::<f64>() / nf;
    let mu = kept.iter().map(|s| s.u).sum::<f64>() / nf;
    let mi = kept.iter().map(|s| s.i).sum::<f64>() / nf;
    let (mut vq, mut vu, mut cqu, mut pq, mut pu) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for s in &kept {
        vq += (s.q - mq) * (s.q - mq);
        vu += (s.u - mu) * (s.u - mu);
        cqu += (s.q - mq) * (s.u - mu);
        pq += s.var_q;
        pu += s.var_u;
    }
    // Sample (co)variances with n - 1, then of the mean: / n.
    let d = (nf - 1.0) * nf;
    Some(BinStats {
        q: mq,
        u: mu,
        sigma_q: (vq / d).sqrt(),
        sigma_u: (vu / d).sqrt(),
        cov_qu: cqu / d,
        sigma_q_phot: pq.sqrt() / nf,
        sigma_u_phot: pu.sqrt() / nf,
        intensity: mi,
        n_kept: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_odd_even() {
        assert_eq!(median_in_place(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median_in_place(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(median_in_place(&mut []).is_nan());
    }

    /// The integer-key median is `median_in_place` (total order) to the bit: odd and even
    /// counts, negatives, infinities, subnormals.
    #[test]
    fn key_median_is_total_order_median() {
        let pool = [-3.5, 2.0, -0.0, 0.0, 1e-310, -1e-310, f64::INFINITY, f64::NEG_INFINITY, 7.0, -7.0, 0.25, 1e300];
        for n in 1..pool.len() {
            for rot in 0..pool.len() {
                let v: Vec<f64> = (0..n).map(|k| pool[(k * 5 + rot) % pool.len()]).collect();
                let want = median_in_place(&mut v.clone());
                let mut keys: Vec<i64> = v.iter().map(|&x| total_key(x)).collect();
                let got = median_keys_near(&mut keys, None, &mut Vec::new());
                assert!(got == want || (got.is_nan() && want.is_nan()), "{v:?}: {got} vs {want}");
                assert!(v.iter().all(|&x| from_total_key(total_key(x)).to_bits() == x.to_bits()));
            }
        }
    }

    /// The windowed search is the plain median whatever the window: containing the median,
    /// off to either side, empty, inverted, or cutting between the two middle ranks.
    #[test]
    fn windowed_median_is_exact_for_any_window() {
        let pool: Vec<f64> = rand_like::quantiles(101, 1.0);
        let mut win = Vec::new();
        for n in [3usize, 4, 10, 11, 100, 101] {
            let v = &pool[..n];
            let want = median_in_place(&mut v.to_vec());
            for (c, w) in [(want, 0.1), (want, 0.0), (want + 0.3, 0.2), (want - 0.5, 0.45), (10.0, 1.0), (want, -1.0)] {
                let mut keys: Vec<i64> = v.iter().map(|&x| total_key(x)).collect();
                let got = median_keys_near(&mut keys, Some(key_window(c, w)), &mut win);
                assert_eq!(got.to_bits(), want.to_bits(), "n {n}, window {c} +- {w}");
            }
        }
    }

    #[test]
    fn mad_of_gaussian_is_sigma() {
        // The MAD scale of a Gaussian sample is sigma (to ~1.1% / sqrt(n/1000) here).
        use rand_like::quantiles;
        let v = quantiles(20001, 2.0);
        let mut b = v.clone();
        let m = median_in_place(&mut b);
        let mut d: Vec<f64> = v.iter().map(|x| (x - m).abs()).collect();
        let s = MAD_TO_SIGMA * median_in_place(&mut d);
        assert!((s - 2.0).abs() < 0.04, "{s}");
    }

    #[test]
    fn clipping_rejects_a_star_and_a_cosmic_ray() {
        let mut s: Vec<PixelSample> = rand_like::quantiles(900, 1e-3)
            .iter()
            .enumerate()
            .map(|(k, &d)| PixelSample {
                q: 0.01 + d,
                u: -0.02 - d * 0.5,
                i: 5000.0 + (k % 7) as f64,
                var_q: 1e-6,
                var_u: 1e-6,
            })
            .collect();
        // A star: bright, same polarization; a cosmic ray: wild q.
        s[10].i = 50000.0;
        s[11].i = 20000.0;
        s[500].q = 0.5;
        let b = clipped_bin(&s, ClipConfig::default(), 10).unwrap();
        assert!(b.n_kept <= 897 && b.n_kept > 880, "{}", b.n_kept);
        assert!((b.q - 0.01).abs() < 1e-4, "{}", b.q);
        assert!((b.intensity - 5003.0).abs() < 0.2, "{}", b.intensity);
        // Photon error of the mean: sqrt(n * 1e-6) / n.
        assert!((b.sigma_q_phot - 1e-3 / (b.n_kept as f64).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn identical_values_survive_and_outlier_goes() {
        let mut s = vec![PixelSample { q: 0.02, u: 0.01, i: 100.0, var_q: 0.0, var_u: 0.0 }; 50];
        s[3].q = 0.9;
        let b = clipped_bin(&s, ClipConfig::default(), 2).unwrap();
        assert_eq!(b.n_kept, 49);
        assert!((b.q - 0.02).abs() < 1e-15);
        assert!(b.sigma_q < 1e-15);
    }

    /// Seeded Gaussian samples.
    mod rand_like {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        pub fn quantiles(n: usize, sigma: f64) -> Vec<f64> {
            let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
            let d = Normal::new(0.0, sigma).unwrap();
            (0..n).map(|_| d.sample(&mut rng)).collect()
        }
    }
}
