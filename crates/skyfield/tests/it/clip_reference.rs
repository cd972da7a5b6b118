//! The bins' sigma clipping (`skyfield::bin`) against a straightforward implementation written
//! here: every median by a full sort in `f64::total_cmp` order, every pass over the kept rows
//! recomputed from scratch. The library selects medians on integer keys inside windows guessed
//! from the previous iteration or a neighbouring bin (`ClipHint`s); whatever the guesses, the
//! keep mask and the bin statistics must be the reference's to the bit: Gaussian bins with
//! outliers, ties (MAD zero), all values equal, everything clipped, non-finite rows, fewer than
//! three rows, and hints that are right, wrong, absurd or stale.

use rand::SeedableRng;
use rand_distr::{Distribution, Normal, Uniform};
use rand_xoshiro::Xoshiro256PlusPlus as Rand;
use skyfield::bin::{
    clipped_bin, clipped_bin_hinted, sigma_clip_columns, sigma_clip_columns_hinted, BinSamples, ClipConfig, ClipHint,
    PixelSample,
};
use stokes::stats::robust::{median, Middle, MAD_TO_SIGMA};

/// The one median (`stokes::stats::robust::median`, itself checked against a full sort), of
/// the mean of the two middle values for an even count: the definition the fast kernels'
/// windowed searches must give.
fn sorted_median(v: &[f64]) -> f64 {
    median(&mut v.to_vec(), Middle::Mean)
}

/// The clipping as documented, in the plainest form: keep the rows finite in every column;
/// then, while at least 3 rows remain and at most `max_iter` times, take each column's median
/// and MAD of the kept rows (sigma = `MAD_TO_SIGMA` MAD, or the population standard deviation of the
/// kept values when the MAD is zero) and keep the rows within `nsigma` sigma of the median in
/// every column; stop when an iteration keeps every row.
fn reference_keep(cols: &[&[f64]], cfg: ClipConfig) -> Vec<bool> {
    let n = cols.first().map_or(0, |c| c.len());
    let mut keep: Vec<bool> = (0..n).map(|r| cols.iter().all(|c| c[r].is_finite())).collect();
    for _ in 0..cfg.max_iter {
        let rows: Vec<usize> = (0..n).filter(|&r| keep[r]).collect();
        let m = rows.len();
        if m < 3 {
            break;
        }
        let mut limits = Vec::new();
        for c in cols {
            let v: Vec<f64> = rows.iter().map(|&r| c[r]).collect();
            let med = sorted_median(&v);
            let dev: Vec<f64> = v.iter().map(|x| (x - med).abs()).collect();
            let mut sigma = MAD_TO_SIGMA * sorted_median(&dev);
            if sigma == 0.0 {
                let mean = v.iter().sum::<f64>() / m as f64;
                sigma = (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / m as f64).sqrt();
            }
            limits.push((med, cfg.nsigma * sigma));
        }
        let mut changed = false;
        for &r in &rows {
            if cols.iter().zip(&limits).any(|(c, &(med, lim))| (c[r] - med).abs() > lim) {
                keep[r] = false;
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
    keep
}

/// Mean, standard errors and covariance of the kept rows, summed in row order.
fn reference_stats(s: &[PixelSample], keep: &[bool], min_pixels: usize) -> Option<[f64; 8]> {
    let k: Vec<&PixelSample> = s.iter().zip(keep).filter(|(_, &k)| k).map(|(p, _)| p).collect();
    let n = k.len();
    if n < min_pixels.max(2) {
        return None;
    }
    let nf = n as f64;
    let mean = |f: &dyn Fn(&PixelSample) -> f64| k.iter().map(|p| f(p)).sum::<f64>() / nf;
    let (mq, mu, mi) = (mean(&|p| p.qu.q), mean(&|p| p.qu.u), mean(&|p| p.i));
    let (mut vq, mut vu, mut c, mut pq, mut pu) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in &k {
        vq += (p.qu.q - mq) * (p.qu.q - mq);
        vu += (p.qu.u - mu) * (p.qu.u - mu);
        c += (p.qu.q - mq) * (p.qu.u - mu);
        pq += p.qu.var_q;
        pu += p.qu.var_u;
    }
    let d = (nf - 1.0) * nf;
    Some([mq, mu, (vq / d).sqrt(), (vu / d).sqrt(), c / d, pq.sqrt() / nf, pu.sqrt() / nf, mi])
}

fn bits(b: &skyfield::bin::BinStats) -> [u64; 8] {
    [b.qu.q, b.qu.u, b.qu.sigma_q(), b.qu.sigma_u(), b.qu.cov_qu, b.sigma_q_phot, b.sigma_u_phot, b.intensity]
        .map(f64::to_bits)
}

/// Checks one bin every way the library offers (plain, hinted with several hint sets, and the
/// bin statistics), against the reference.
fn check(label: &str, s: &[PixelSample], cfg: ClipConfig, min_pixels: usize, rng: &mut Rand) {
    let q: Vec<f64> = s.iter().map(|p| p.qu.q).collect();
    let u: Vec<f64> = s.iter().map(|p| p.qu.u).collect();
    let i: Vec<f64> = s.iter().map(|p| p.i).collect();
    let cols: [&[f64]; 3] = [&q, &u, &i];
    let want = reference_keep(&cols, cfg);
    assert_eq!(sigma_clip_columns(&cols, cfg), want, "{label}: keep mask");
    // Hints: none; where the clipping ends (the exact answer); shifted by a few sigma; absurd
    // (zero, negative, infinite, NaN widths); random.
    let mut exact: [ClipHint; 3] = [None; 3];
    sigma_clip_columns_hinted(&cols, cfg, &mut exact);
    let mut hint_sets: Vec<[ClipHint; 3]> = vec![[None; 3], exact];
    if let [Some(a), Some(b), Some(c)] = exact {
        hint_sets.push([a, b, c].map(|(m, d, s)| Some((m + 2.0 * s, d * 1.5, s))));
        hint_sets.push([a, b, c].map(|(m, d, s)| Some((m - 0.01 * s, d, s * 0.1))));
    }
    hint_sets.push([Some((0.0, 0.0, 0.0)), Some((-1.0, -1.0, -1.0)), Some((f64::INFINITY, f64::NAN, f64::INFINITY))]);
    for _ in 0..3 {
        hint_sets.push([(); 3].map(|_| {
            Some((
                Uniform::new(-1.0, 1.0).unwrap().sample(rng),
                Uniform::new(0.0, 0.1).unwrap().sample(rng),
                Uniform::new(0.0, 0.2).unwrap().sample(rng),
            ))
        }));
    }
    let want_stats = reference_stats(s, &want, min_pixels);
    let samples: BinSamples = s.iter().copied().collect();
    for (h, hints) in hint_sets.iter().enumerate() {
        let mut hh = *hints;
        assert_eq!(sigma_clip_columns_hinted(&cols, cfg, &mut hh), want, "{label}: keep mask with hint set {h}");
        let mut hh = *hints;
        let got = clipped_bin_hinted(&samples, cfg, min_pixels, &mut hh);
        match (&got, &want_stats) {
            (None, None) => {}
            (Some(g), Some(w)) => {
                assert_eq!(bits(g), w.map(f64::to_bits), "{label}: statistics with hint set {h}");
                assert_eq!(g.n_kept, want.iter().filter(|&&k| k).count(), "{label}: n_kept");
            }
            _ => panic!("{label}: hint set {h}: library {got:?}, reference {want_stats:?}"),
        }
    }
    let plain = clipped_bin(s, cfg, min_pixels);
    assert_eq!(plain.map(|b| bits(&b)), want_stats.map(|w| w.map(f64::to_bits)), "{label}: clipped_bin");
}

fn sample(q: f64, u: f64, i: f64) -> PixelSample {
    PixelSample { qu: mueller::Qu::new(q, u, 1e-6 * (1.0 + q.abs()), 2e-6, 0.0), i }
}

#[test]
fn clipping_matches_a_sort_based_reference() {
    let mut rng = Rand::seed_from_u64(12);
    let cfg = ClipConfig::default();
    let g = Normal::new(0.0, 1.0).unwrap();
    // Gaussian bins of sizes around the 30 x 30 px default, odd and even, with outliers: a
    // star (bright, the sky's polarization), cosmic rays, a saturated column.
    for n in [3usize, 4, 5, 10, 31, 64, 225, 899, 900, 901] {
        for rep in 0..4 {
            let mut s: Vec<PixelSample> = (0..n)
                .map(|_| {
                    sample(
                        0.01 + 1e-3 * g.sample(&mut rng),
                        -0.02 + 1e-3 * g.sample(&mut rng),
                        5000.0 + 70.0 * g.sample(&mut rng),
                    )
                })
                .collect();
            for _ in 0..(n / 40 + rep) {
                let k = Uniform::new(0, n).unwrap().sample(&mut rng);
                match Uniform::new(0, 3).unwrap().sample(&mut rng) {
                    0 => s[k].i *= 10.0,
                    1 => s[k].qu.q += 0.3,
                    _ => s[k].qu.u -= 5e-3,
                }
            }
            check(&format!("gaussian n={n} rep={rep}"), &s, cfg, 3, &mut rng);
        }
    }
    // Ties: values quantized so that the MAD is zero (more than half identical), or the two
    // middle values differ by one quantum.
    for n in [6usize, 7, 50, 51, 900] {
        let s: Vec<PixelSample> = (0..n)
            .map(|k| {
                let t = if k % 5 < 3 { 0.0 } else { (k % 7) as f64 - 3.0 };
                sample(0.02 + 1e-3 * t, 0.01 - 1e-3 * ((k % 3) as f64), 100.0 + t.abs())
            })
            .collect();
        check(&format!("ties n={n}"), &s, cfg, 2, &mut rng);
    }
    // All equal but one: the zero-spread column rejects only the value that differs.
    let mut s = vec![sample(0.02, 0.01, 100.0); 50];
    s[3].qu.q = 0.9;
    check("all equal but one", &s, cfg, 2, &mut rng);
    // All equal: nothing clipped, zero scatter.
    check("all equal", &vec![sample(0.02, 0.01, 100.0); 40], cfg, 2, &mut rng);
    // Everything clipped: nsigma 0 and an even count whose two middle values differ, so that no
    // value equals the median.
    let s: Vec<PixelSample> = (0..10).map(|k| sample(k as f64 * 1e-3, 0.0, 1.0)).collect();
    check("all clipped", &s, ClipConfig { nsigma: 0.0, max_iter: 10 }, 2, &mut rng);
    // Non-finite rows (NaN, infinities) never count; fewer than three finite rows are not
    // clipped; no iterations at all.
    let mut s: Vec<PixelSample> = (0..40)
        .map(|_| sample(1e-3 * g.sample(&mut rng), 1e-3 * g.sample(&mut rng), 10.0 + g.sample(&mut rng)))
        .collect();
    s[0].qu.q = f64::NAN;
    s[5].qu.u = f64::INFINITY;
    s[9].i = f64::NEG_INFINITY;
    check("non-finite rows", &s, cfg, 3, &mut rng);
    check("two rows", &s[10..12], cfg, 2, &mut rng);
    check("one row", &s[10..11], cfg, 1, &mut rng);
    check("no rows", &[], cfg, 1, &mut rng);
    check("no iterations", &s, ClipConfig { nsigma: 3.0, max_iter: 0 }, 3, &mut rng);
    check("one iteration", &s, ClipConfig { nsigma: 1.0, max_iter: 1 }, 3, &mut rng);
    // Signed zeros and values straddling zero (where IEEE and total order differ).
    let s: Vec<PixelSample> =
        (0..21).map(|k| sample([0.0, -0.0, 1e-9, -1e-9][k % 4], [-0.0, 0.0][k % 2], 1.0 + (k % 3) as f64)).collect();
    check("signed zeros", &s, cfg, 2, &mut rng);
}
