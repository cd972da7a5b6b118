//! Binning with a sigma-clipped average: iterative, centred on the median, with the scale from
//! the median absolute deviation, so stars, cosmic rays and bad pixels inside a bin do not
//! pull its mean (the paper's "clipped average in 30 x 30 px bins", section `sec:fors1`).
//!
//! This module holds skyfield's fast sigma-clipping kernels, each an exact implementation of a
//! plain clipping with the one median (`stokes::stats::robust::median`) and the one
//! `MAD_TO_SIGMA`, searched faster (windowed selections on integer keys): the binning's
//! clipping of several columns at once ([`sigma_clip_columns`], checked to the bit by
//! `tests/it/clip_reference.rs`) and the background mesh's median and sigma (`clipped_stats`,
//! checked by this module's tests). The one-pass clipped mean of the raw calibration is
//! `stokes::stats::robust::clipped_mean`.

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

use stokes::stats::robust::MAD_TO_SIGMA;

/// `x` as an integer whose order is `f64::total_cmp`'s (the same transform).
#[inline]
pub(crate) fn total_key(x: f64) -> i64 {
    let b = x.to_bits() as i64;
    b ^ ((((b >> 63) as u64) >> 1) as i64)
}

/// Inverse of [`total_key`] (the transform is its own inverse: it never touches the sign bit).
#[inline]
pub(crate) fn from_total_key(k: i64) -> f64 {
    f64::from_bits(total_key(f64::from_bits(k as u64)) as u64)
}

/// The median of `v` (not empty) in the order of `f64::total_cmp`, exactly, helped by a
/// `window` `[lo, hi]` believed to hold it: see [`median_near_by`].
#[cfg(test)]
fn median_near(v: &[f64], window: Option<(f64, f64)>) -> f64 {
    median_near_by(v, None, window, &mut Vec::new(), &mut Vec::new())
}

/// For finite values IEEE comparisons are the total order except -0 against +0, so a window
/// with a zero bound is never used.
#[inline]
fn usable(window: Option<(f64, f64)>) -> Option<(f64, f64)> {
    window.filter(|&(lo, hi)| lo != 0.0 && hi != 0.0)
}

/// The values a median is taken of: `v` itself, or the deviations `|v - c|` from a centre.
#[inline(always)]
fn value(v: f64, centre: Option<f64>) -> f64 {
    match centre {
        Some(c) => (v - c).abs(),
        None => v,
    }
}

/// One pass over the values ([`value`] of `vals`): the number below `lo`, and the
/// [`total_key`]s of those inside `[lo, hi]` gathered into `win` (truncated to them); also the
/// largest value's bits as an unsigned integer (the largest value when all are non-negative,
/// as deviations from a `centre` are: their bits are in the order of the values).
#[inline(always)]
fn window_pass(vals: &[f64], centre: Option<f64>, (lo, hi): (f64, f64), win: &mut Vec<i64>) -> (usize, u64) {
    let n = vals.len();
    // Room for whole vectors written past the last key kept, not cleared first (clearing it
    // for every pass was most of the clipping's memset).
    win.clear();
    win.reserve(n + 8);
    let room = &mut win.spare_capacity_mut()[..n + 8];
    #[cfg(target_arch = "x86_64")]
    let (below, m, top) = if n >= 8 && std::arch::is_x86_feature_detected!("avx512f") {
        // SAFETY: AVX-512F support was checked just above; room holds n + 8 keys.
        unsafe { window_pass_avx512(vals, centre, lo, hi, room) }
    } else {
        window_pass_scalar(vals, centre, lo, hi, room)
    };
    #[cfg(not(target_arch = "x86_64"))]
    let (below, m, top) = window_pass_scalar(vals, centre, lo, hi, room);
    // SAFETY: both passes wrote the first m keys (m <= n <= capacity).
    unsafe { win.set_len(m) };
    (below, top)
}

/// [`window_pass`] one value at a time: `(below, kept, largest bits)`, the kept keys at the
/// start of `win` (which holds at least `vals.len()` keys).
#[inline(always)]
fn window_pass_scalar(
    vals: &[f64],
    centre: Option<f64>,
    lo: f64,
    hi: f64,
    win: &mut [std::mem::MaybeUninit<i64>],
) -> (usize, usize, u64) {
    assert!(win.len() >= vals.len());
    // Branch-free: every value is written, the count advances only for values inside.
    let (mut below, mut m, mut top) = (0, 0, 0u64);
    let w = win.as_mut_ptr();
    for &v in vals {
        let x = value(v, centre);
        below += (x < lo) as usize;
        top = top.max(x.to_bits());
        // SAFETY: m <= (index of v) < vals.len() <= win.len() (m counts a subset of the values seen).
        unsafe { (*w.add(m)).write(total_key(x)) };
        m += ((x >= lo) & (x <= hi)) as usize;
    }
    (below, m, top)
}

/// [`window_pass`] eight values at a time: the same IEEE operations (subtraction, clearing the
/// sign bit, ordered comparisons), the same [`total_key`] transform in integer lanes, the keys
/// inside the window compressed into a register and stored whole (a compressing store to
/// memory is slow on some CPUs), so the same count and keys in the same order.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn window_pass_avx512(
    vals: &[f64],
    centre: Option<f64>,
    lo: f64,
    hi: f64,
    win: &mut [std::mem::MaybeUninit<i64>],
) -> (usize, usize, u64) {
    use std::arch::x86_64::*;
    let n = vals.len();
    assert!(win.len() >= n + 8);
    let (vlo, vhi) = (_mm512_set1_pd(lo), _mm512_set1_pd(hi));
    let (mut below, mut m) = (0usize, 0usize);
    let mut top = _mm512_setzero_si512();
    let w = win.as_mut_ptr();
    let mut i = 0;
    while i + 8 <= n {
        // SAFETY: i + 8 <= n.
        let mut x = unsafe { _mm512_loadu_pd(vals.as_ptr().add(i)) };
        if let Some(c) = centre {
            let d = _mm512_sub_pd(x, _mm512_set1_pd(c));
            // |d|: the sign bit cleared, as f64::abs does.
            x = _mm512_castsi512_pd(_mm512_and_si512(_mm512_castpd_si512(d), _mm512_set1_epi64(i64::MAX)));
        }
        let b = _mm512_castpd_si512(x);
        top = _mm512_max_epu64(top, b);
        let key = _mm512_xor_si512(b, _mm512_srli_epi64::<1>(_mm512_srai_epi64::<63>(b)));
        below += (_mm512_cmp_pd_mask::<_CMP_LT_OQ>(x, vlo) as u32).count_ones() as usize;
        let inside = _mm512_cmp_pd_mask::<_CMP_GE_OQ>(x, vlo) & _mm512_cmp_pd_mask::<_CMP_LE_OQ>(x, vhi);
        // SAFETY: m <= i, so m + 8 <= n + 8 <= win.len().
        unsafe { _mm512_storeu_si512(w.add(m).cast(), _mm512_maskz_compress_epi64(inside, key)) };
        m += (inside as u32).count_ones() as usize;
        i += 8;
    }
    // The tail: m <= i, so win[m..] holds at least n - i keys.
    let (b, k, t) = window_pass_scalar(&vals[i..], centre, lo, hi, &mut win[m..]);
    (below + b, m + k, _mm512_reduce_max_epu64(top).max(t))
}

/// The lower of the ranks (0-based) a median of `n > 0` values is taken from: `n / 2` for odd
/// `n`, `n / 2 - 1` (with `n / 2`) for even.
#[inline]
fn lower_middle(n: usize) -> usize {
    if n % 2 == 1 {
        n / 2
    } else {
        n / 2 - 1
    }
}

/// The median of `n` values of which `below` lie under a window and `win` holds the keys of
/// those inside it, if both middle ranks (`k - 1` and `k` for even `n`) fall inside (`win` is
/// reordered, the same multiset).
#[inline]
fn median_in_window(n: usize, below: usize, win: &mut [i64]) -> Option<f64> {
    let (k, first) = (n / 2, lower_middle(n));
    if !(below <= first && k < below + win.len()) {
        return None;
    }
    let (left, m, _) = win.select_nth_unstable(k - below);
    let hi_v = from_total_key(*m);
    if n % 2 == 1 {
        return Some(hi_v);
    }
    let lo_v = from_total_key(*left.iter().max().expect("rank k - 1 is in the window"));
    Some(0.5 * (lo_v + hi_v))
}

/// The median of all `n` keys (`n > 0`), selected in place.
fn median_of_keys(keys: &mut [i64]) -> f64 {
    let n = keys.len();
    let k = n / 2;
    let (_, m, _) = keys.select_nth_unstable(k);
    let hi = from_total_key(*m);
    if n % 2 == 1 {
        hi
    } else {
        let lo = from_total_key(*keys[..k].iter().max().expect("n >= 2"));
        0.5 * (lo + hi)
    }
}

/// The median of the finite values ([`value`] of `vals`, not empty) in the order of
/// `f64::total_cmp`, exactly what `stokes::stats::robust::median` with `Middle::Mean` gives,
/// helped by a `window` `[lo, hi]` believed to hold it (the previous clipping iteration's
/// median, or a neighbouring bin's: both move little). One pass counts the values below the window and gathers those
/// inside (`win`, scratch); when the median's ranks fall inside, only those are searched.
/// Otherwise, or without a window, all values are (`keys`, scratch). Searches run on
/// [`total_key`]s.
pub(crate) fn median_near_by(
    vals: &[f64],
    centre: Option<f64>,
    window: Option<(f64, f64)>,
    keys: &mut Vec<i64>,
    win: &mut Vec<i64>,
) -> f64 {
    // Never None: no bound is enough.
    median_and_top(vals, centre, window, keys, win, |_, _| false).0.unwrap_or(f64::NAN)
}

/// [`median_near_by`], and the largest value's bits (see [`window_pass`]; with a `centre`, the
/// largest deviation from it), found in the same pass. The median is `None` when a window was
/// searched, the median's ranks are not below it (so the median is at least the window's
/// lower end `lo`), `lo` is positive, and `enough(lo, largest value)` says that bound is all
/// the caller needs (the clipping's test of whether a column can reject anything).
fn median_and_top(
    vals: &[f64],
    centre: Option<f64>,
    window: Option<(f64, f64)>,
    keys: &mut Vec<i64>,
    win: &mut Vec<i64>,
    enough: impl Fn(f64, f64) -> bool,
) -> (Option<f64>, u64) {
    if let Some(w) = usable(window) {
        let (below, top) = window_pass(vals, centre, w, win);
        let n = vals.len();
        if w.0 > 0.0 && below <= lower_middle(n) && enough(w.0, f64::from_bits(top)) {
            return (None, top);
        }
        if let Some(m) = median_in_window(n, below, win) {
            return (Some(m), top);
        }
    }
    keys.clear();
    let mut top = 0u64;
    keys.extend(vals.iter().map(|&v| {
        let x = value(v, centre);
        top = top.max(x.to_bits());
        total_key(x)
    }));
    (Some(median_of_keys(keys)), top)
}

/// `[c - w, c + w]`, the window [`median_near_by`] searches first.
pub(crate) fn window(c: f64, w: f64) -> (f64, f64) {
    (c - w, c + w)
}

/// Half-widths of the search windows, in units of the previous iteration's robust sigma:
/// about a tenth of a Gaussian sample falls inside either window, far more than the few
/// ranks the median and the MAD move when an iteration rejects a handful of values.
const MEDIAN_WINDOW: f64 = 0.125;
const MAD_WINDOW: f64 = 0.15;

/// Half-width of the MAD's search window in an iteration after the first, in units of the
/// previous iteration's robust sigma: the MAD moves by about `0.8 k / n` sigma when `k` of `n`
/// values are rejected (the density of `|x - median|` at the MAD is `0.64 / sigma`, and the
/// MAD's rank moves by about `k / 2`), so the window is a small floor plus three times that.
/// It holds a few percent of the values where the first window held a fifth: the select inside
/// it was the largest part of a clipping.
fn mad_window_next(rejected: usize, n: usize) -> f64 {
    0.01 + 2.4 * rejected as f64 / n.max(1) as f64
}

/// Where a column's clipping ended: its median, MAD and robust sigma. Passed to the clipping
/// of a neighbouring bin as a hint of where to look first (it changes nothing but speed).
pub type ClipHint = Option<(f64, f64, f64)>;

/// Iterative sigma clipping of several columns at once: a row is kept only if it lies within
/// `nsigma` robust sigmas of the median in *every* column (so a star, bright in intensity but
/// with the sky's polarization, is still rejected). The robust sigma is `MAD_TO_SIGMA` times the
/// MAD; when the
/// MAD is zero (more than half the values identical) the standard deviation of the kept values
/// is used instead, and a column with zero spread rejects only values that differ from it.
/// Returns the keep mask.
pub fn sigma_clip_columns(cols: &[&[f64]], cfg: ClipConfig) -> Vec<bool> {
    sigma_clip_columns_hinted(cols, cfg, &mut vec![None; cols.len()])
}

/// One column of a clipping in progress: its kept values (compacted, row order), and the
/// window its last median was searched in with what that pass found (the count of values
/// below it and the keys inside), kept up to date as rows are rejected, so that the next
/// iteration's median is selected among those keys without another pass over the values.
#[derive(Default)]
struct Column {
    vals: Vec<f64>,
    med_win: Option<(f64, f64)>,
    below: usize,
    win: Vec<i64>,
}

impl Column {
    /// A fresh column holding `vals` (buffers kept).
    fn reset(&mut self, vals: &[f64]) {
        self.vals.clear();
        self.vals.extend_from_slice(vals);
        self.med_win = None;
        self.below = 0;
        self.win.clear();
    }

    /// The median of the kept values, from the window of the previous pass while both middle
    /// ranks are still inside it; otherwise after a pass over the values with the window
    /// `w` (which becomes the kept one).
    fn median(&mut self, w: Option<(f64, f64)>, keys: &mut Vec<i64>) -> f64 {
        let n = self.vals.len();
        if self.med_win.is_some() {
            if let Some(m) = median_in_window(n, self.below, &mut self.win) {
                return m;
            }
        }
        self.med_win = usable(w);
        match self.med_win {
            Some(w) => {
                self.below = window_pass(&self.vals, None, w, &mut self.win).0;
                if let Some(m) = median_in_window(n, self.below, &mut self.win) {
                    return m;
                }
            }
            None => self.win.clear(),
        }
        keys.clear();
        keys.extend(self.vals.iter().map(|&x| total_key(x)));
        median_of_keys(keys)
    }

    /// Account for the rejection of value `x` in the kept window.
    #[inline]
    fn forget(&mut self, x: f64) {
        if let Some((lo, hi)) = self.med_win {
            // The window pass's own tests (a NaN bound counts nothing anywhere).
            if x < lo {
                self.below -= 1;
            } else if (x >= lo) & (x <= hi) {
                let key = total_key(x);
                let p = self.win.iter().position(|&k| k == key).expect("a value inside the window has its key there");
                self.win.swap_remove(p);
            }
        }
    }
}

/// Median and robust sigma (`MAD_TO_SIGMA` times the MAD) after three 3-sigma clipping passes
/// (the background mesh's boxes and the noise of [`crate::detect`]); `None` when no finite
/// value is left.
pub(crate) fn clipped_stats(v: &[f64]) -> Option<(f64, f64)> {
    clipped_stats_hinted(v, &mut None)
}

/// Where a clipping ended (median, MAD, sigma): passed to the next box of a mesh row, whose sky
/// is much the same, as where to look first. It changes nothing but speed.
pub(crate) type StatsHint = Option<(f64, f64, f64)>;

/// [`clipped_stats`], its first median and MAD looked for near `hint`'s, which it updates.
pub(crate) fn clipped_stats_hinted(v: &[f64], hint: &mut StatsHint) -> Option<(f64, f64)> {
    let mut w: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if w.is_empty() {
        return None;
    }
    // Each pass's median and MAD are first looked for near the previous pass's (a few values
    // rejected move them little): exactly the medians a selection over all values gives
    // ([`median_near_by`]), found by one counting pass and a selection among the few values
    // near them. The mesh's selections were a tenth of a catalog's CPU time.
    let (mut keys, mut win) = (Vec::new(), Vec::new());
    let first = hint.map(|(m, _, s)| window(m, 0.125 * s));
    let mut med = median_near_by(&w, None, first, &mut keys, &mut win);
    let (mut sig, mut mad_window) = (0.0, hint.map(|(_, d, s)| window(d, 0.15 * s)));
    for _ in 0..3 {
        let mad = median_near_by(&w, Some(med), mad_window, &mut keys, &mut win);
        sig = MAD_TO_SIGMA * mad;
        if !(sig > 0.0) {
            break;
        }
        let before = w.len();
        w.retain(|x| (x - med).abs() <= 3.0 * sig);
        if w.len() == before {
            break;
        }
        if w.is_empty() {
            return None;
        }
        med = median_near_by(&w, None, Some(window(med, 0.125 * sig)), &mut keys, &mut win);
        mad_window = Some(window(mad, 0.15 * sig));
    }
    *hint = (sig > 0.0).then_some((med, sig / MAD_TO_SIGMA, sig));
    Some((med, sig))
}

/// [`sigma_clip_columns`] with one [`ClipHint`] per column: on entry where the medians and
/// MADs are probably (a neighbouring bin's: the sky changes little from bin to bin), on return
/// where this clipping ended. The result is the same whatever the hints.
pub fn sigma_clip_columns_hinted(cols: &[&[f64]], cfg: ClipConfig, hints: &mut [ClipHint]) -> Vec<bool> {
    let n = cols.first().map_or(0, |c| c.len());
    with_scratch(|sc| {
        sc.clip(cols, cfg, hints);
        let mut keep = vec![false; n];
        for &r in &sc.rows {
            keep[r as usize] = true;
        }
        keep
    })
}

/// The clipping of one column ([`sigma_clip_columns_hinted`]): `f` gets the kept values, in
/// order.
pub(crate) fn with_clipped<T>(v: &[f64], cfg: ClipConfig, hint: &mut ClipHint, f: impl FnOnce(&[f64]) -> T) -> T {
    with_scratch(|sc| {
        sc.clip(&[v], cfg, std::slice::from_mut(hint));
        f(&sc.state[0].vals)
    })
}

/// The buffers of a clipping, reused from bin to bin on a thread (a bin's clipping takes a few
/// microseconds, and allocating these for each bin was a fifth of it): the kept rows and each
/// column's kept values, compacted in row order, which is what the clipping returns.
#[derive(Default)]
struct Clip {
    rows: Vec<u32>,
    state: Vec<Column>,
    /// Per kept row: non-zero when a column's value is beyond its limit.
    out: Vec<u8>,
    /// The indices of those rows.
    outs: Vec<usize>,
    buf: Vec<i64>,
    win: Vec<i64>,
    /// Per column: its median, its rejection limit, and whether any value lies beyond it.
    centre: Vec<(f64, f64, bool)>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Clip> = std::cell::RefCell::new(Clip::default());
}

/// Runs `f` with this thread's clipping buffers.
fn with_scratch<T>(f: impl FnOnce(&mut Clip) -> T) -> T {
    SCRATCH.with(|c| match c.try_borrow_mut() {
        Ok(mut sc) => f(&mut sc),
        // Not reentrant; a fresh set should a caller ever nest clippings.
        Err(_) => f(&mut Clip::default()),
    })
}

/// `true` when every value is finite: an exponent field of all ones marks infinities and NaN,
/// tested in integer lanes eight at a time (`Iterator::all` stops at the first failure, so it
/// tests one value at a time).
fn all_finite(v: &[f64]) -> bool {
    let exp = f64::INFINITY.to_bits();
    let mut acc = [0u64; 8];
    let mut blocks = v.chunks_exact(8);
    for b in &mut blocks {
        for j in 0..8 {
            acc[j] |= ((b[j].to_bits() & exp) == exp) as u64;
        }
    }
    acc.iter().all(|&a| a == 0) && blocks.remainder().iter().all(|x| x.is_finite())
}

/// Removes the elements at `outs` (ascending, not empty) from `v`, keeping the others' order.
fn remove_sorted<T: Copy>(v: &mut Vec<T>, outs: &[usize]) {
    let mut w = outs[0];
    for (j, &o) in outs.iter().enumerate() {
        let end = outs.get(j + 1).copied().unwrap_or(v.len());
        v.copy_within(o + 1..end, w);
        w += end - o - 1;
    }
    v.truncate(w);
}

impl Clip {
    /// The clipping of [`sigma_clip_columns_hinted`]: on return `rows` holds the kept rows and
    /// `state[c].vals` column `c`'s kept values, both in row order.
    fn clip(&mut self, cols: &[&[f64]], cfg: ClipConfig, hints: &mut [ClipHint]) {
        self.state.resize_with(cols.len(), Column::default);
        self.state.truncate(cols.len());
        for (c, col) in self.state.iter_mut().zip(cols) {
            c.reset(col);
        }
        self.clip_loaded(cfg, hints);
    }

    /// [`Clip::clip`] of columns the caller gives up: moved in rather than copied (the
    /// caller's vectors get this clipping's previous buffers, of no particular content). A
    /// reduction's bins are cleared after their clipping, and copying their three columns was
    /// a twentieth of it.
    fn clip_taking(&mut self, cols: &mut [&mut Vec<f64>], cfg: ClipConfig, hints: &mut [ClipHint]) {
        self.state.resize_with(cols.len(), Column::default);
        self.state.truncate(cols.len());
        for (c, col) in self.state.iter_mut().zip(cols.iter_mut()) {
            c.reset(&[]);
            std::mem::swap(&mut c.vals, col);
        }
        self.clip_loaded(cfg, hints);
    }

    /// The clipping of the columns in `state` (all of one length).
    fn clip_loaded(&mut self, cfg: ClipConfig, hints: &mut [ClipHint]) {
        assert_eq!(hints.len(), self.state.len(), "one hint per column");
        let n = self.state.first().map_or(0, |c| c.vals.len());
        assert!(self.state.iter().all(|c| c.vals.len() == n), "columns of one length");
        assert!(n <= u32::MAX as usize, "a bin of more than 2^32 pixels");
        // The kept rows, compacted (row order kept): their indices and each column's values, so
        // that every pass below runs over contiguous memory without a mask.
        self.rows.clear();
        if self.state.iter().all(|c| all_finite(&c.vals)) {
            self.rows.extend(0..n as u32);
        } else {
            let state = &self.state;
            self.rows.extend((0..n as u32).filter(|&r| state.iter().all(|c| c.vals[r as usize].is_finite())));
            for c in self.state.iter_mut() {
                for (w, &r) in self.rows.iter().enumerate() {
                    c.vals[w] = c.vals[r as usize];
                }
                c.vals.truncate(self.rows.len());
            }
        }
        // Medians are selected on integer keys of the IEEE total order (what `robust::median`
        // compares with `total_cmp`, without the per-comparison transform): same values. Each
        // median and MAD is first looked for near the previous iteration's (the hint's, at
        // first); a median whose ranks stay inside the previous iteration's window (a few rows
        // rejected) needs no pass at all.
        let Self { rows, state, out, outs, buf, win, centre } = self;
        // Rows rejected by the previous iteration (none before the first, whose hints come from
        // another bin and get the wide windows).
        let mut rejected: Option<usize> = None;
        for _ in 0..cfg.max_iter {
            let m = rows.len();
            if m < 3 {
                break;
            }
            centre.clear();
            let mad_w = rejected.map_or(MAD_WINDOW, |k| mad_window_next(k, m + k));
            for (ci, c) in state.iter_mut().enumerate() {
                let hint = hints[ci];
                let med = c.median(hint.map(|(m, _, s)| window(m, MEDIAN_WINDOW * s)), buf);
                let w_mad = hint.map(|(_, d, s)| window(d, mad_w * s));
                let v = &c.vals;
                // The MAD's pass also finds the largest deviation |x - med| (the same IEEE
                // operations as the test below). When even the window's lower end, which the
                // MAD cannot be below, gives a limit beyond that deviation, the column rejects
                // nothing whatever its MAD: the MAD is not selected (its hint stays the
                // previous one, which only decides where the next search looks first).
                let mad_floor = |lo: f64| cfg.nsigma * (MAD_TO_SIGMA * lo);
                let bounded = cfg.nsigma > 0.0;
                let (mad, top) =
                    match median_and_top(v, Some(med), w_mad, buf, win, |lo, top| bounded && top <= mad_floor(lo)) {
                        (Some(mad), top) => (mad, f64::from_bits(top)),
                        (None, _) => {
                            let (_, d, s) = hint.expect("a window came from the hint");
                            hints[ci] = Some((med, d, s));
                            centre.push((med, f64::NAN, false));
                            continue;
                        }
                    };
                let mut sigma = MAD_TO_SIGMA * mad;
                if sigma == 0.0 {
                    let mean = v.iter().sum::<f64>() / m as f64;
                    sigma = (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / m as f64).sqrt();
                }
                hints[ci] = Some((med, mad, sigma));
                let lim = cfg.nsigma * sigma;
                // A column whose largest deviation is within its limit rejects nothing: its
                // test below is skipped (in most iterations, and always the last, no column
                // rejects anything).
                centre.push((med, lim, !(top <= lim)));
            }
            if centre.iter().all(|c| !c.2) {
                break;
            }
            // Which rows are out, column by column in passes that vectorize.
            out.clear();
            out.resize(m, 0);
            for (c, &(med, lim, _)) in state.iter().zip(centre.iter()).filter(|(_, c)| c.2) {
                for (o, &x) in out.iter_mut().zip(&c.vals) {
                    *o |= ((x - med).abs() > lim) as u8;
                }
            }
            // The rows out, in order: few, so they are found by blocks of the mask and taken
            // out by moving the runs between them (a copy per kept value was most of a
            // clipping's time).
            outs.clear();
            for (b, block) in out.chunks(64).enumerate() {
                if block.iter().fold(0, |a, &o| a | o) != 0 {
                    outs.extend(block.iter().enumerate().filter(|(_, &o)| o != 0).map(|(j, _)| b * 64 + j));
                }
            }
            if outs.is_empty() {
                break;
            }
            // Keep the rows within every column's limit, and take the rejected values out of
            // each column's kept median window.
            for c in state.iter_mut() {
                for &k in outs.iter() {
                    let x = c.vals[k];
                    c.forget(x);
                }
                remove_sorted(&mut c.vals, outs);
            }
            remove_sorted(rows, outs);
            rejected = Some(outs.len());
        }
    }
}

/// One pixel's contribution to a bin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelSample {
    /// The pixel's `q`, `u` with the photon + read noise variances of each (the covariance is
    /// not used: a bin's covariance comes from its pixels' scatter).
    pub qu: mueller::Qu,
    /// Intensity `f_O + f_E` per exposure (e-).
    pub i: f64,
}

/// The clipped mean of a bin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BinStats {
    /// The clipped means of `q`, `u` with the covariance of the means from the scatter of the
    /// kept pixels.
    pub qu: mueller::Qu,
    /// Standard errors of the means propagated from the per-pixel noise.
    pub sigma_q_phot: f64,
    pub sigma_u_phot: f64,
    pub intensity: f64,
    pub n_kept: usize,
}

/// The pixels of one bin, column by column (what the clipping and the sums read).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BinSamples {
    pub q: Vec<f64>,
    pub u: Vec<f64>,
    pub i: Vec<f64>,
    pub var_q: Vec<f64>,
    pub var_u: Vec<f64>,
}

impl BinSamples {
    pub fn push(&mut self, s: PixelSample) {
        self.q.push(s.qu.q);
        self.u.push(s.qu.u);
        self.i.push(s.i);
        self.var_q.push(s.qu.var_q);
        self.var_u.push(s.qu.var_u);
    }

    pub fn clear(&mut self) {
        for c in [&mut self.q, &mut self.u, &mut self.i, &mut self.var_q, &mut self.var_u] {
            c.clear();
        }
    }

    pub fn len(&self) -> usize {
        self.q.len()
    }

    pub fn is_empty(&self) -> bool {
        self.q.is_empty()
    }
}

impl FromIterator<PixelSample> for BinSamples {
    fn from_iter<T: IntoIterator<Item = PixelSample>>(iter: T) -> Self {
        let mut b = BinSamples::default();
        for s in iter {
            b.push(s);
        }
        b
    }
}

/// Sigma-clipped mean of the pixels of one bin (clipping on q, u and intensity together).
/// `None` when fewer than `min_pixels` (at least 2) survive.
pub fn clipped_bin(samples: &[PixelSample], cfg: ClipConfig, min_pixels: usize) -> Option<BinStats> {
    clipped_bin_hinted(&samples.iter().copied().collect(), cfg, min_pixels, &mut [None; 3])
}

/// [`clipped_bin`] with [`ClipHint`]s for q, u and intensity (see
/// [`sigma_clip_columns_hinted`]): same result, found faster along a row of bins.
pub fn clipped_bin_hinted(
    s: &BinSamples,
    cfg: ClipConfig,
    min_pixels: usize,
    hints: &mut [ClipHint; 3],
) -> Option<BinStats> {
    with_scratch(|sc| {
        sc.clip(&[&s.q, &s.u, &s.i], cfg, hints);
        kept_stats(sc, s, min_pixels)
    })
}

/// [`clipped_bin_hinted`] of a bin whose q, u and intensity columns the caller gives up (the
/// reduction's, cleared after): moved into the clipping instead of copied. The same result.
pub(crate) fn clipped_bin_taking(
    s: &mut BinSamples,
    cfg: ClipConfig,
    min_pixels: usize,
    hints: &mut [ClipHint; 3],
) -> Option<BinStats> {
    with_scratch(|sc| {
        sc.clip_taking(&mut [&mut s.q, &mut s.u, &mut s.i], cfg, hints);
        kept_stats(sc, s, min_pixels)
    })
}

/// The statistics of the rows a clipping kept (`None` below `min_pixels`, at least 2): means
/// of q, u and intensity, their scatter errors and covariance, and the propagated errors from
/// the kept rows' variances in `s`.
fn kept_stats(sc: &Clip, s: &BinSamples, min_pixels: usize) -> Option<BinStats> {
    // The clipping leaves the kept q, u and I compacted in row order: the sums below add
    // the kept rows in row order, as over the rows of a keep mask.
    let (q, u, i) = (&sc.state[0].vals, &sc.state[1].vals, &sc.state[2].vals);
    let n = sc.rows.len();
    if n < min_pixels.max(2) {
        return None;
    }
    let nf = n as f64;
    // The three sums side by side (three chains of additions at once), each in row order.
    let (mut sq, mut su, mut si) = (0.0, 0.0, 0.0);
    for ((&a, &b), &c) in q.iter().zip(u).zip(i) {
        sq += a;
        su += b;
        si += c;
    }
    let (mq, mu, mi) = (sq / nf, su / nf, si / nf);
    let (mut vq, mut vu, mut cqu, mut pq, mut pu) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for ((&qk, &uk), &r) in q.iter().zip(u).zip(&sc.rows) {
        let (dq, du) = (qk - mq, uk - mu);
        vq += dq * dq;
        vu += du * du;
        cqu += dq * du;
        pq += s.var_q[r as usize];
        pu += s.var_u[r as usize];
    }
    // Sample (co)variances with n - 1, then of the mean: / n.
    let d = (nf - 1.0) * nf;
    Some(BinStats {
        qu: mueller::Qu::new(mq, mu, vq / d, vu / d, cqu / d),
        sigma_q_phot: pq.sqrt() / nf,
        sigma_u_phot: pu.sqrt() / nf,
        intensity: mi,
        n_kept: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one median (`stokes::stats::robust::median`), of the mean of the two middles: the
    /// definition every kernel here is checked against.
    fn one_median(v: &mut [f64]) -> f64 {
        stokes::stats::robust::median(v, stokes::stats::robust::Middle::Mean)
    }

    #[test]
    fn median_odd_even() {
        assert_eq!(one_median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(one_median(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(one_median(&mut []).is_nan());
    }

    /// The integer-key median is the one median (total order) to the bit: odd and even
    /// counts, negatives, infinities, subnormals.
    #[test]
    fn key_median_is_total_order_median() {
        let pool = [-3.5, 2.0, -0.0, 0.0, 1e-310, -1e-310, f64::INFINITY, f64::NEG_INFINITY, 7.0, -7.0, 0.25, 1e300];
        for n in 1..pool.len() {
            for rot in 0..pool.len() {
                let v: Vec<f64> = (0..n).map(|k| pool[(k * 5 + rot) % pool.len()]).collect();
                let want = one_median(&mut v.clone());
                let got = median_near(&v, None);
                assert!(got == want || (got.is_nan() && want.is_nan()), "{v:?}: {got} vs {want}");
                assert!(v.iter().all(|&x| from_total_key(total_key(x)).to_bits() == x.to_bits()));
            }
        }
    }

    /// The windowed search is the plain median (total order) whatever the window: containing
    /// the median, off to either side, empty, inverted, cutting between the two middle ranks,
    /// with a zero bound, or about signed zeros (where IEEE and total order differ).
    #[test]
    fn windowed_median_is_exact_for_any_window() {
        let pool: Vec<f64> = rand_like::quantiles(101, 1.0);
        let zeros: Vec<f64> = (0..40).map(|k| [0.0, -0.0, 1e-3, -1e-3, -0.0][k % 5] * (1 + k % 3) as f64).collect();
        let cases: Vec<&[f64]> =
            vec![&pool[..3], &pool[..4], &pool[..10], &pool[..11], &pool[..100], &pool, &zeros, &zeros[..39]];
        for v in cases {
            let want = one_median(&mut v.to_vec());
            for (c, w) in [
                (want, 0.1),
                (want, 0.0),
                (want + 0.3, 0.2),
                (want - 0.5, 0.45),
                (10.0, 1.0),
                (want, -1.0),
                (0.0, 1e-3),
                (5e-4, 5e-4),
                (want, 1e-9),
            ] {
                let got = median_near(v, Some(window(c, w)));
                assert_eq!(got.to_bits(), want.to_bits(), "n {}, window {c} +- {w}", v.len());
            }
        }
    }

    /// The 8-wide window pass gives the one-at-a-time pass's count and keys, in order, for
    /// values and for deviations, windows inside, outside, inverted and NaN, lengths with and
    /// without a tail (on a CPU without AVX-512F there is nothing to compare: said so).
    #[test]
    fn vector_window_pass_is_the_scalar_one() {
        #[cfg(target_arch = "x86_64")]
        {
            if !std::arch::is_x86_feature_detected!("avx512f") {
                eprintln!("SKIPPED vector_window_pass_is_the_scalar_one: this CPU has no AVX-512F");
                return;
            }
            let mut v = rand_like::quantiles(203, 1.0);
            v[7] = -0.0;
            v[8] = 0.0;
            v[9] = 1e-310;
            for n in [8, 9, 15, 16, 64, 203] {
                for centre in [None, Some(0.1), Some(-0.3)] {
                    for (lo, hi) in [(-0.1, 0.1), (0.5, 2.0), (1.0, -1.0), (f64::NAN, 1.0), (-5.0, f64::INFINITY)] {
                        let zero = std::mem::MaybeUninit::new(0i64);
                        let (mut a, mut b) = (vec![zero; n + 8], vec![zero; n + 8]);
                        let s = window_pass_scalar(&v[..n], centre, lo, hi, &mut a);
                        // SAFETY: AVX-512F checked above; b holds n + 8 keys.
                        let x = unsafe { window_pass_avx512(&v[..n], centre, lo, hi, &mut b) };
                        assert_eq!(s, x, "n {n} centre {centre:?} window {lo}..{hi}");
                        // SAFETY: every element was initialised (zero) before the passes.
                        let (a, b): (Vec<i64>, Vec<i64>) = unsafe {
                            (a.iter().map(|k| k.assume_init()).collect(), b.iter().map(|k| k.assume_init()).collect())
                        };
                        let top = v[..n].iter().map(|&x| value(x, centre).to_bits()).max();
                        assert_eq!(Some(s.2), top, "n {n} centre {centre:?}: largest value");
                        assert_eq!(a[..s.1], b[..x.1], "n {n} centre {centre:?} window {lo}..{hi}");
                    }
                }
            }
        }
    }

    /// The block-wise finiteness test and the run-moving removal against their plain forms:
    /// NaN and infinities in the blocks and in the tail; removals at the ends, adjacent and
    /// alone.
    #[test]
    fn finite_test_and_removal_are_the_plain_ones() {
        for n in [0, 1, 7, 8, 9, 17, 64, 70] {
            for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, f64::MAX, -0.0, 1e-310] {
                for at in 0..n {
                    let mut v: Vec<f64> = (0..n).map(|k| k as f64 - 3.5).collect();
                    v[at] = bad;
                    assert_eq!(all_finite(&v), v.iter().all(|x| x.is_finite()), "n {n}, {bad} at {at}");
                }
            }
            let v: Vec<u32> = (0..n as u32).collect();
            let sets: Vec<Vec<usize>> =
                vec![vec![0], vec![n.saturating_sub(1)], vec![0, 1, 2], (0..n).step_by(3).collect(), (0..n).collect()];
            for outs in sets.into_iter().filter(|o| !o.is_empty() && o.iter().all(|&k| k < n)) {
                let mut got = v.clone();
                remove_sorted(&mut got, &outs);
                let want: Vec<u32> = v.iter().copied().filter(|&x| !outs.contains(&(x as usize))).collect();
                assert_eq!(got, want, "n {n}, removing {outs:?}");
            }
        }
    }

    #[test]
    fn mad_of_gaussian_is_sigma() {
        // The MAD scale of a Gaussian sample is sigma (to ~1.1% / sqrt(n/1000) here).
        use rand_like::quantiles;
        let v = quantiles(20001, 2.0);
        let mut b = v.clone();
        let m = one_median(&mut b);
        let mut d: Vec<f64> = v.iter().map(|x| (x - m).abs()).collect();
        let s = MAD_TO_SIGMA * one_median(&mut d);
        assert!((s - 2.0).abs() < 0.04, "{s}");
    }

    #[test]
    fn clipping_rejects_a_star_and_a_cosmic_ray() {
        let mut s: Vec<PixelSample> = rand_like::quantiles(900, 1e-3)
            .iter()
            .enumerate()
            .map(|(k, &d)| PixelSample {
                qu: mueller::Qu::new(0.01 + d, -0.02 - d * 0.5, 1e-6, 1e-6, 0.0),
                i: 5000.0 + (k % 7) as f64,
            })
            .collect();
        // A star: bright, same polarization; a cosmic ray: wild q.
        s[10].i = 50000.0;
        s[11].i = 20000.0;
        s[500].qu.q = 0.5;
        let b = clipped_bin(&s, ClipConfig::default(), 10).unwrap();
        assert!(b.n_kept <= 897 && b.n_kept > 880, "{}", b.n_kept);
        assert!((b.qu.q - 0.01).abs() < 1e-4, "{}", b.qu.q);
        assert!((b.intensity - 5003.0).abs() < 0.2, "{}", b.intensity);
        // Photon error of the mean: sqrt(n * 1e-6) / n.
        assert!((b.sigma_q_phot - 1e-3 / (b.n_kept as f64).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn identical_values_survive_and_outlier_goes() {
        let mut s = vec![PixelSample { qu: mueller::Qu::new(0.02, 0.01, 0.0, 0.0, 0.0), i: 100.0 }; 50];
        s[3].qu.q = 0.9;
        let b = clipped_bin(&s, ClipConfig::default(), 2).unwrap();
        assert_eq!(b.n_kept, 49);
        assert!((b.qu.q - 0.02).abs() < 1e-15);
        assert!(b.qu.sigma_q() < 1e-15);
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

    /// The clipping as documented, written plainly: every median the one median over all values.
    fn clipped_stats_reference(v: &[f64]) -> Option<(f64, f64)> {
        let median = |w: &[f64]| one_median(&mut w.to_vec());
        let mut w: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
        if w.is_empty() {
            return None;
        }
        let mut med = median(&w);
        let mut sig = 0.0;
        for _ in 0..3 {
            let dev: Vec<f64> = w.iter().map(|x| (x - med).abs()).collect();
            sig = MAD_TO_SIGMA * median(&dev);
            if !(sig > 0.0) {
                break;
            }
            let before = w.len();
            w.retain(|x| (x - med).abs() <= 3.0 * sig);
            if w.len() == before {
                break;
            }
            if w.is_empty() {
                return None;
            }
            med = median(&w);
        }
        Some((med, sig))
    }

    /// The mesh's clipping (medians searched near the previous pass's) gives the plain
    /// clipping's median and sigma to the bit: sky boxes with stars in them, integer ADU (ties
    /// everywhere), a constant box (MAD zero), NaNs, tiny boxes, a box that is mostly star.
    #[test]
    fn clipped_stats_is_the_plain_clipping() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(11);
        let mut cases: Vec<Vec<f64>> = vec![vec![], vec![f64::NAN; 5], vec![7.0; 100], vec![1.0, 2.0], vec![3.0]];
        for k in 0..300 {
            let n = rng.random_range(1..5000);
            let sky = rng.random_range(-50.0..5000.0);
            let noise = rng.random_range(0.5..80.0);
            let mut v: Vec<f64> = (0..n)
                .map(|_| {
                    // Box-Muller: a Gaussian sky.
                    let (a, b): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
                    sky + noise * (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
                })
                .collect();
            // Stars: a tail of bright values, sometimes most of the box.
            let stars = rng.random_range(0..n / (1 + k % 7) + 1);
            for x in v.iter_mut().take(stars) {
                *x += rng.random_range(0.0..50.0 * noise);
            }
            if k % 3 == 0 {
                v.iter_mut().for_each(|x| *x = x.round());
            }
            if k % 11 == 0 {
                v[0] = f64::NAN;
            }
            cases.push(v);
        }
        // Hints as a mesh row passes them (the previous box's), and absurd ones.
        let mut chained = None;
        for (k, v) in cases.iter().enumerate() {
            let want = clipped_stats_reference(v);
            let bits = |r: Option<(f64, f64)>| r.map(|(m, s)| (m.to_bits(), s.to_bits()));
            let absurd = [None, Some((1e30, 1e-30, 1e-30)), Some((-5.0, 0.0, 0.0)), Some((f64::NAN, 1.0, 1.0))];
            for (h, mut hint) in absurd.into_iter().chain([chained]).enumerate() {
                let got = clipped_stats_hinted(v, &mut hint);
                assert_eq!(bits(got), bits(want), "case {k}, hint {h}: {got:?} vs {want:?}");
                if h == 4 {
                    chained = hint;
                }
            }
        }
    }
}
