//! Streaming statistics of the Monte Carlo: shifted sums per chunk and a fixed histogram, so
//! no trial is stored.
//!
//! Determinism: histogram counts are integers (merging them in any order gives the same
//! result); floating-point sums are kept per chunk and added in chunk order at the end, so the
//! same seed gives bit-identical results on any number of threads.

/// Sums of one chunk, shifted by a reference value to avoid cancellation in the variance.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ChunkSums {
    pub n: u64,
    /// Sum of `P - p_ref`.
    pub s1: f64,
    /// Sum of `(P - p_ref)^2`.
    pub s2: f64,
    pub sq: f64,
    pub su: f64,
    /// Sum of the squared angle deviation (rad^2), when angle statistics are on.
    pub sd2: f64,
}

impl ChunkSums {
    pub fn add(&mut self, o: &ChunkSums) {
        self.n += o.n;
        self.s1 += o.s1;
        self.s2 += o.s2;
        self.sq += o.sq;
        self.su += o.su;
        self.sd2 += o.sd2;
    }
}

/// A fixed-range histogram of `P` with under- and overflow counters (kept as the first and
/// last cells of one array, so filling is branch-free).
#[derive(Debug, Clone, PartialEq)]
pub struct Histogram {
    pub lo: f64,
    pub hi: f64,
    inv_w: f64,
    nb: usize,
    /// `[underflow, bins..., overflow]`.
    raw: Vec<u64>,
}

impl Histogram {
    pub fn new(lo: f64, hi: f64, bins: usize) -> Self {
        Self { lo, hi, inv_w: bins as f64 / (hi - lo), nb: bins, raw: vec![0; bins + 2] }
    }
    /// Cell of `p` in the raw array (NaN goes to the underflow).
    #[inline(always)]
    fn cell(&self, p: f64) -> usize {
        let t = ((p - self.lo) * self.inv_w).max(-1.0).min(self.nb as f64);
        (t + 1.0) as usize
    }
    #[inline(always)]
    pub fn push(&mut self, p: f64) {
        let c = self.cell(p);
        self.raw[c] += 1;
    }
    /// The in-range bin counts.
    pub fn counts(&self) -> &[u64] {
        &self.raw[1..=self.nb]
    }
    pub fn under(&self) -> u64 {
        self.raw[0]
    }
    pub fn over(&self) -> u64 {
        self.raw[self.nb + 1]
    }
    pub fn merge(&mut self, o: &Histogram) {
        for (a, b) in self.raw.iter_mut().zip(&o.raw) {
            *a += b;
        }
    }
    pub fn width(&self) -> f64 {
        (self.hi - self.lo) / self.nb as f64
    }
    pub fn total(&self) -> u64 {
        self.raw.iter().sum::<u64>()
    }
    fn center(&self, i: usize) -> f64 {
        self.lo + (i as f64 + 0.5) * self.width()
    }

    /// Quantile `q` by linear interpolation of the cumulative counts inside a bin; `None` when
    /// it falls in the under- or overflow.
    pub fn quantile(&self, q: f64) -> Option<f64> {
        let n = self.total() as f64;
        let target = q * n;
        let mut cum = self.under() as f64;
        if target < cum {
            return None;
        }
        let w = self.width();
        for (i, &c) in self.counts().iter().enumerate() {
            let next = cum + c as f64;
            if next >= target && c > 0 {
                return Some(self.lo + w * (i as f64 + (target - cum) / c as f64));
            }
            cum = next;
        }
        None
    }

    /// Mode of the sampled distribution: a Gaussian-kernel density estimate on the histogram
    /// (bandwidth `bw`) locates the peak; then a quartic in `ln(counts / P)`, fitted by
    /// weighted least squares over `+- window` around it, gives the stationary point. The fit
    /// follows the skewness of the Rice distribution that would bias a kernel mode, and uses
    /// every trial in the window, so its error falls as `1/sqrt(trials)`.
    pub fn mode(&self, bw: f64, window: f64) -> Option<f64> {
        let nb = self.nb;
        let counts = self.counts();
        let w = self.width();
        let hb = (bw / w).max(1.0);
        let reach = (4.0 * hb).ceil() as isize;
        let kern: Vec<f64> = (-reach..=reach).map(|j| (-0.5 * (j as f64 / hb).powi(2)).exp()).collect();
        let mut best = (0usize, -1.0);
        for i in 0..nb {
            let mut s = 0.0;
            for (jj, k) in kern.iter().enumerate() {
                let j = i as isize + jj as isize - reach;
                if j >= 0 && (j as usize) < nb {
                    s += k * counts[j as usize] as f64;
                }
            }
            if s > best.1 {
                best = (i, s);
            }
        }
        if best.1 <= 0.0 {
            return None;
        }
        let m0 = self.center(best.0);
        // Weighted polynomial fit of g = ln(counts / P) around m0 (t scaled to [-1, 1]).
        // Dividing by the Jacobian P leaves the smooth log-density of the 2-D (Q, U)
        // distribution (exactly quadratic for the Rayleigh case), which a low-degree
        // polynomial fits over a wide window; the mode of P is then the root of
        // 1/P + g'(P) = 0.
        let (a, b) = ((m0 - window).max(self.lo), (m0 + window).min(self.hi));
        let half = 0.5 * (b - a);
        let mid = 0.5 * (a + b);
        const D: usize = 5;
        let mut ata = [[0.0f64; D]; D];
        let mut atb = [0.0f64; D];
        let mut used = 0;
        for i in 0..nb {
            let c = counts[i] as f64;
            let x = self.center(i);
            if c < 1.0 || x < a || x > b || x <= 0.0 {
                continue;
            }
            used += 1;
            let t = (x - mid) / half;
            let mut basis = [1.0; D];
            for k in 1..D {
                basis[k] = basis[k - 1] * t;
            }
            let y = (c / x).ln();
            for r in 0..D {
                atb[r] += c * basis[r] * y;
                for s in 0..D {
                    ata[r][s] += c * basis[r] * basis[s];
                }
            }
        }
        if used < 3 * D {
            return Some(m0);
        }
        let Some(coef) = solve(ata, atb) else { return Some(m0) };
        // h(x) = d/dx ln f = 1/x + g'(x); find the sign change (+ to -) nearest m0.
        let h = |x: f64| {
            let t = (x - mid) / half;
            let mut d = 0.0;
            let mut tp = 1.0;
            for (k, ck) in coef.iter().enumerate().skip(1) {
                d += k as f64 * ck * tp;
                tp *= t;
            }
            1.0 / x + d / half
        };
        let steps = 400;
        let xs = |k: usize| a.max(1e-300) + (b - a.max(1e-300)) * k as f64 / steps as f64;
        let mut best_root: Option<f64> = None;
        for k in 0..steps {
            let (x0, x1) = (xs(k), xs(k + 1));
            if h(x0) > 0.0 && h(x1) <= 0.0 {
                let r = crate::stats::special::brent(h, x0, x1, 1e-12 * x1.abs()).unwrap_or(0.5 * (x0 + x1));
                if best_root.is_none_or(|br| (r - m0).abs() < (br - m0).abs()) {
                    best_root = Some(r);
                }
            }
        }
        Some(best_root.unwrap_or(m0))
    }
}

/// Solve a small linear system by Gaussian elimination with partial pivoting.
fn solve<const D: usize>(mut a: [[f64; D]; D], mut b: [f64; D]) -> Option<[f64; D]> {
    for col in 0..D {
        let piv = (col..D).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() < 1e-300 {
            return None;
        }
        a.swap(col, piv);
        b.swap(col, piv);
        for r in col + 1..D {
            let f = a[r][col] / a[col][col];
            for c in col..D {
                a[r][c] -= f * a[col][c];
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = [0.0; D];
    for r in (0..D).rev() {
        let mut s = b[r];
        for c in r + 1..D {
            s -= a[r][c] * x[c];
        }
        x[r] = s / a[r][r];
    }
    Some(x)
}
