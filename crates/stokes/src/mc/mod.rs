//! Monte Carlo engine of dual-beam polarimetry (section `sec:mc`).
//!
//! One trial draws the ordinary and extraordinary fluxes at the `N` HWP angles with photon
//! (Poisson) noise, plus sky and read noise when asked, forms the `F_i` with the one
//! [`crate::normalized_difference`], solves `Q`, `U` with the one [`crate::StokesSolver`] and
//! records `P`. Two faster approximations are offered: Gaussian noise on the `F_i`
//! (`gauss-f`, `sigma_F = 1/SNR`) and Gaussian noise directly on `Q`, `U` (`gauss-qu`,
//! `sigma = 1/(sqrt(N/2) SNR)`, `eq:sigp`). The noiseless fluxes come from the `mueller`
//! forward model, computed once, so instrument defects can be included.
//!
//! Conventions (the same as the numpy peer `shared/peers/numpy_mc.py`): `SNR` is the
//! signal-to-noise ratio of the intensity `f_O + f_E` at each angle, i.e. `SNR^2` total
//! counts per angle for Poisson noise; `rms_p` is the standard deviation of `P`.
//!
//! Statistics are streamed (shifted sums and a fixed histogram for mode and quantiles): no
//! trial is stored. Trials run in fixed chunks of [`CHUNK`]; chunk `c` draws from a
//! generator seeded by `(seed, c)`, and the floating-point sums are added in chunk order, so
//! the same seed gives bit-identical results on any number of threads.

pub mod budget;
pub mod poisson;
pub mod stream;
pub mod sweep;

use crate::stats::Error;
use crate::{normalized_difference, StokesSolver};
use mueller::DualBeam;
use poisson::PoissonSampler;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;
use rayon::prelude::*;
use std::fmt;
use std::str::FromStr;
use stream::{ChunkSums, Histogram};

/// Trials per chunk: the unit of parallel work and of seeding.
pub const CHUNK: u64 = 1 << 15;
/// Histogram bins for the mode and quantiles.
pub const BINS: usize = 4096;
/// Trials reduced together (see [`Engine::flush`]).
const BATCH: usize = 64;

/// Four interleaved partial sums of each statistic within a chunk.
#[derive(Default)]
struct Lanes {
    n: u64,
    s1: [f64; 4],
    s2: [f64; 4],
    sq: [f64; 4],
    su: [f64; 4],
    sd2: [f64; 4],
}

/// Noise model of a trial.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Noise {
    /// Exact Poisson counts in each beam (plus sky and read noise when configured).
    Poisson,
    /// Gaussian noise on each `F_i`, `sigma_F = 1/SNR`.
    GaussF,
    /// Gaussian noise on `Q`, `U` with the solver's covariance, `sigma_F = 1/SNR`.
    GaussQu,
}

impl Noise {
    pub const ALL: [Noise; 3] = [Noise::Poisson, Noise::GaussF, Noise::GaussQu];
    pub fn name(&self) -> &'static str {
        match self {
            Noise::Poisson => "poisson",
            Noise::GaussF => "gauss-f",
            Noise::GaussQu => "gauss-qu",
        }
    }
}

impl fmt::Display for Noise {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Noise {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        Noise::ALL
            .into_iter()
            .find(|n| n.name() == s.trim())
            .ok_or_else(|| Error::Model(format!("unknown noise model '{s}' (known: poisson, gauss-f, gauss-qu)")))
    }
}

/// What to simulate.
#[derive(Debug, Clone)]
pub struct McConfig {
    /// Number of HWP angles (optimal set `i pi/8` unless `angles` is given).
    pub n_hwp: usize,
    /// Signal-to-noise ratio of the intensity at each angle.
    pub snr: f64,
    /// True polarization degree (fraction).
    pub p0: f64,
    /// True polarization angle (rad).
    pub chi0: f64,
    pub trials: u64,
    pub noise: Noise,
    pub seed: u64,
    /// Sky counts per beam and angle in the aperture (Poisson only; subtracted as known).
    pub sky: f64,
    /// Read noise per beam and angle in the aperture (electrons rms; Poisson only).
    pub read_noise: f64,
    /// The instrument (ideal by default).
    pub instrument: DualBeam,
    /// HWP angles (rad); `None` for the optimal set.
    pub angles: Option<Vec<f64>>,
    /// Also accumulate the polarization-angle error (one `atan2` per trial).
    pub angle_stats: bool,
}

impl McConfig {
    /// An ideal instrument with the optimal angle set, no sky, no read noise.
    pub fn new(n_hwp: usize, snr: f64, p0: f64, chi0: f64, trials: u64, noise: Noise) -> Self {
        Self {
            n_hwp,
            snr,
            p0,
            chi0,
            trials,
            noise,
            seed: 1,
            sky: 0.0,
            read_noise: 0.0,
            instrument: DualBeam::ideal(),
            angles: None,
            angle_stats: false,
        }
    }
}

/// Streamed statistics of a run.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct McResult {
    /// Trials that entered the statistics.
    pub trials: u64,
    /// Trials dropped because a beam pair had no counts (`f_O + f_E <= 0`).
    pub rejected: u64,
    pub mean_p: f64,
    /// Standard deviation of `P` (the paper's `sigma_P` of fig:deltap).
    pub rms_p: f64,
    /// Most probable `P` (histogram + local cubic fit); `None` if the histogram is empty.
    pub mode_p: Option<f64>,
    pub median_p: Option<f64>,
    /// 15.87 % and 84.13 % quantiles of `P`.
    pub q16_p: Option<f64>,
    pub q84_p: Option<f64>,
    pub mean_q: f64,
    pub mean_u: f64,
    /// RMS of the angle error (rad), when angle statistics were on.
    pub rms_chi: Option<f64>,
    /// `P` of the noiseless fluxes (equals `p0` for the ideal instrument).
    pub p_noiseless: f64,
    /// Analytic error of `Q` (and `U`) for this configuration: `eq:sigp` for the optimal set.
    pub sigma_p_analytic: f64,
}

/// A prepared simulation: forward model, solver and samplers built once.
pub struct Engine {
    cfg: McConfig,
    solver: StokesSolver,
    f0: Vec<f64>,
    samplers: Vec<(PoissonSampler, PoissonSampler)>,
    q0: f64,
    u0: f64,
    /// Cholesky factor of the (Q, U) covariance for gauss-qu.
    chol: [f64; 3],
    sigma_f: f64,
    sigma_qu: f64,
    p_ref: f64,
    rot: (f64, f64),
}

fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The generator of chunk `c` of a run with `seed`.
pub fn chunk_rng(seed: u64, c: u64) -> Xoshiro256PlusPlus {
    Xoshiro256PlusPlus::seed_from_u64(splitmix64(seed) ^ splitmix64(c.wrapping_add(0xD1B5_4A32_D192_ED03)))
}

impl Engine {
    /// Validate the configuration and build the forward model, solver and samplers.
    pub fn new(cfg: &McConfig) -> Result<Self, Error> {
        let inval = |name, value, why| Err(Error::Invalid { name, value, why });
        if cfg.n_hwp < 2 || cfg.n_hwp > 1024 {
            return inval("number of HWP angles", cfg.n_hwp as f64, "must be in 2..=1024");
        }
        if !(cfg.snr.is_finite() && cfg.snr > 0.0) {
            return inval("SNR", cfg.snr, "must be finite and > 0");
        }
        // Below SNR 1 the noise of F_i exceeds its whole range [-1, 1] (and with Poisson noise
        // most trials have no counts at all): a run would print numbers that are only noise.
        if cfg.snr < 1.0 {
            return inval("SNR", cfg.snr, "must be >= 1: below it every trial is noise (sigma_F > 1)");
        }
        // SNR^2 counts are drawn per HWP angle: beyond 1e150 they overflow on the way.
        if cfg.snr > 1e150 {
            return inval("SNR", cfg.snr, "must be <= 1e150 (SNR^2 counts per angle are simulated)");
        }
        if !(cfg.p0.is_finite() && (0.0..=1.0).contains(&cfg.p0)) {
            return inval("P0", cfg.p0, "must be in [0, 1]");
        }
        if !cfg.chi0.is_finite() {
            return inval("chi0", cfg.chi0, "must be finite");
        }
        if !(cfg.sky.is_finite() && cfg.sky >= 0.0) {
            return inval("sky", cfg.sky, "must be finite and >= 0");
        }
        if !(cfg.read_noise.is_finite() && cfg.read_noise >= 0.0) {
            return inval("read noise", cfg.read_noise, "must be finite and >= 0");
        }
        if cfg.noise != Noise::Poisson && (cfg.sky > 0.0 || cfg.read_noise > 0.0) {
            return Err(Error::Model("sky and read noise are modelled only with --noise poisson".into()));
        }
        let theta = match &cfg.angles {
            Some(a) => {
                if a.len() != cfg.n_hwp {
                    return inval("number of HWP angles", a.len() as f64, "must equal n_hwp");
                }
                a.clone()
            }
            None => mueller::optimal_angles(cfg.n_hwp),
        };
        let solver = StokesSolver::new(&theta).map_err(|e| Error::Model(e.to_string()))?;
        let s = mueller::stokes_p_chi(1.0, cfg.p0, cfg.chi0);
        let fl = cfg.instrument.compile().fluxes(&s, &theta);
        let total_counts = cfg.snr * cfg.snr;
        let mut f0 = Vec::with_capacity(fl.len());
        let mut samplers = Vec::with_capacity(fl.len());
        for (i, b) in fl.iter().enumerate() {
            if !(b.f_o >= 0.0 && b.f_e >= 0.0 && b.f_o + b.f_e > 0.0) {
                return Err(Error::Model(format!(
                    "the forward model gives non-physical fluxes f_O = {}, f_E = {} at HWP angle {:.3} deg",
                    b.f_o,
                    b.f_e,
                    theta[i].to_degrees()
                )));
            }
            f0.push(normalized_difference(b.f_o, b.f_e));
            if cfg.noise == Noise::Poisson {
                let mk = |l: f64| {
                    PoissonSampler::new(l).ok_or(Error::Invalid {
                        name: "Poisson mean",
                        value: l,
                        why: if l.is_finite() && l >= 0.0 {
                            "too large to draw as a count (Poisson means are drawn below 1.8e19): lower the counts"
                        } else {
                            "must be finite and >= 0"
                        },
                    })
                };
                samplers.push((mk(total_counts * b.f_o + cfg.sky)?, mk(total_counts * b.f_e + cfg.sky)?));
            }
        }
        let (q0, u0) = solver.solve(&f0);
        // Per-angle error of F: photon noise of the source plus sky and read noise of both beams.
        let sigma_f = match cfg.noise {
            Noise::Poisson => {
                (total_counts + 2.0 * cfg.sky + 2.0 * cfg.read_noise * cfg.read_noise).sqrt() / total_counts
            }
            _ => 1.0 / cfg.snr,
        };
        // Sky or read noise so large that sigma_F exceeds the range of F: the run measures noise.
        if !(sigma_f.is_finite() && sigma_f <= 1.0) {
            return Err(Error::Model(format!(
                "the error of F_i per angle would be {sigma_f:e} (SNR {:e}, sky {:e} e-, read noise {:e} e-): \
                 above 1, the whole range of F, so every trial is noise; lower the sky or read noise",
                cfg.snr, cfg.sky, cfg.read_noise
            )));
        }
        let cov = solver.unit_covariance();
        let v = sigma_f * sigma_f;
        let (c00, c01, c11) = (cov[0][0] * v, cov[0][1] * v, cov[1][1] * v);
        let l11 = c00.sqrt();
        let l21 = c01 / l11;
        let l22 = (c11 - l21 * l21).max(0.0).sqrt();
        let sigma_qu = c00.max(c11).sqrt();
        let (p_ref, chi_ref) = crate::polarization(q0, u0);
        Ok(Self {
            cfg: cfg.clone(),
            solver,
            f0,
            samplers,
            q0,
            u0,
            chol: [l11, l21, l22],
            sigma_f,
            sigma_qu,
            p_ref,
            rot: (2.0 * chi_ref).sin_cos(),
        })
    }

    /// Analytic `sigma` of `Q` and `U` (`eq:sigp` for the optimal set).
    pub fn sigma_qu(&self) -> f64 {
        self.sigma_qu
    }

    /// Per-angle error of `F` used by the Gaussian modes and the histogram range.
    pub fn sigma_f(&self) -> f64 {
        self.sigma_f
    }

    fn new_hist(&self) -> Histogram {
        let s = self.sigma_qu;
        let lo = (self.p_ref - 10.0 * s).max(0.0);
        let hi = self.p_ref + 12.0 * s;
        Histogram::new(lo, hi, BINS)
    }

    /// Run all trials (on the current rayon pool); `progress` is called with the number of
    /// trials of each finished chunk.
    pub fn run(&self, progress: Option<&(dyn Fn(u64) + Sync)>) -> McResult {
        let trials = self.cfg.trials;
        let n_chunks = trials.div_ceil(CHUNK);
        let (hist, mut sums) = (0..n_chunks)
            .into_par_iter()
            .fold(
                || (self.new_hist(), Vec::new()),
                |(mut h, mut v), c| {
                    let len = CHUNK.min(trials - c * CHUNK);
                    let s = self.run_chunk(c, len, &mut h);
                    if let Some(p) = progress {
                        p(len);
                    }
                    v.push((c, s));
                    (h, v)
                },
            )
            .reduce(
                || (self.new_hist(), Vec::new()),
                |(mut h1, mut v1), (h2, v2)| {
                    h1.merge(&h2);
                    v1.extend(v2);
                    (h1, v1)
                },
            );
        sums.sort_by_key(|x| x.0);
        let mut t = ChunkSums::default();
        for (_, s) in &sums {
            t.add(s);
        }
        self.finish(&t, &hist)
    }

    fn finish(&self, t: &ChunkSums, hist: &Histogram) -> McResult {
        let n = t.n.max(1) as f64;
        let m1 = t.s1 / n;
        let var = (t.s2 / n - m1 * m1).max(0.0);
        let sd = var.sqrt();
        let bw = 0.9 * sd.max(hist.width()) * n.powf(-0.2);
        let mode = if t.n > 0 { hist.mode(bw, 1.5 * sd.max(self.sigma_qu * 0.3)) } else { None };
        McResult {
            trials: t.n,
            rejected: self.cfg.trials - t.n,
            mean_p: self.p_ref + m1,
            rms_p: sd,
            mode_p: mode,
            median_p: hist.quantile(0.5),
            q16_p: hist.quantile(0.5 * (1.0 - crate::stats::ONE_SIGMA)),
            q84_p: hist.quantile(0.5 * (1.0 + crate::stats::ONE_SIGMA)),
            mean_q: t.sq / n,
            mean_u: t.su / n,
            rms_chi: if self.cfg.angle_stats { Some((t.sd2 / n).sqrt()) } else { None },
            p_noiseless: self.p_ref,
            sigma_p_analytic: self.sigma_qu,
        }
    }

    /// Reduce a batch of `(Q, U)`: `P` for the whole batch first (the square roots then
    /// pipeline and vectorize), then the histogram and four interleaved partial sums (short
    /// dependency chains). The summation order is fixed by the chunk, so results stay
    /// identical on any thread count.
    #[inline(always)]
    fn flush(&self, qb: &[f64], ub: &[f64], l: &mut Lanes, h: &mut Histogram) {
        let k = qb.len().min(ub.len());
        let mut pb = [0.0f64; BATCH];
        for i in 0..k {
            // |q|, |u| <= ~1: the plain square root cannot overflow and is faster than hypot.
            pb[i] = (qb[i] * qb[i] + ub[i] * ub[i]).sqrt();
        }
        for &p in &pb[..k] {
            h.push(p);
        }
        for i in 0..k {
            let j = i & 3;
            let d = pb[i] - self.p_ref;
            l.s1[j] += d;
            l.s2[j] += d * d;
            l.sq[j] += qb[i];
            l.su[j] += ub[i];
        }
        if self.cfg.angle_stats {
            let (sn, cs) = self.rot;
            for i in 0..k {
                let (q, u) = (qb[i], ub[i]);
                let dev = 0.5 * (u * cs - q * sn).atan2(q * cs + u * sn);
                l.sd2[i & 3] += dev * dev;
            }
        }
        l.n += k as u64;
    }

    /// Trials of chunk `c` (length `len`), accumulated into `h` and the returned sums.
    pub fn run_chunk(&self, c: u64, len: u64, h: &mut Histogram) -> ChunkSums {
        let mut rng = chunk_rng(self.cfg.seed, c);
        let mut l = Lanes::default();
        let n = self.f0.len();
        // Per batch: draw everything first, then reduce (the divisions of F_i over the whole
        // batch vectorize, and the draws are not stalled by the arithmetic).
        let mut ob = vec![0.0f64; BATCH * n];
        let mut eb = vec![0.0f64; BATCH * n];
        let mut fb = vec![0.0f64; BATCH * n];
        let mut qb = [0.0f64; BATCH];
        let mut ub = [0.0f64; BATCH];
        let mut done = 0u64;
        while done < len {
            let m = (BATCH as u64).min(len - done) as usize;
            done += m as u64;
            let mut k = 0;
            match self.cfg.noise {
                Noise::GaussQu => {
                    let [l11, l21, l22] = self.chol;
                    for i in 0..m {
                        let z1: f64 = StandardNormal.sample(&mut rng);
                        let z2: f64 = StandardNormal.sample(&mut rng);
                        qb[i] = self.q0 + l11 * z1;
                        ub[i] = self.u0 + l21 * z1 + l22 * z2;
                    }
                    k = m;
                }
                Noise::GaussF => {
                    let sf = self.sigma_f;
                    for trial in fb[..m * n].chunks_exact_mut(n) {
                        for (fj, f0) in trial.iter_mut().zip(&self.f0) {
                            let z: f64 = StandardNormal.sample(&mut rng);
                            *fj = f0 + sf * z;
                        }
                    }
                    for (i, trial) in fb[..m * n].chunks_exact(n).enumerate() {
                        (qb[i], ub[i]) = self.solver.solve(trial);
                    }
                    k = m;
                }
                Noise::Poisson => {
                    let sky = self.cfg.sky;
                    let rn = self.cfg.read_noise;
                    for (o, e) in ob[..m * n].chunks_exact_mut(n).zip(eb[..m * n].chunks_exact_mut(n)) {
                        for (j, (so, se)) in self.samplers.iter().enumerate() {
                            o[j] = so.sample(&mut rng);
                            e[j] = se.sample(&mut rng);
                        }
                    }
                    if sky > 0.0 || rn > 0.0 {
                        for (o, e) in ob[..m * n].iter_mut().zip(eb[..m * n].iter_mut()) {
                            let zo: f64 = StandardNormal.sample(&mut rng);
                            let ze: f64 = StandardNormal.sample(&mut rng);
                            *o += rn * zo - sky;
                            *e += rn * ze - sky;
                        }
                    }
                    for ((fj, &o), &e) in fb[..m * n].iter_mut().zip(&ob[..m * n]).zip(&eb[..m * n]) {
                        *fj = normalized_difference(o, e);
                    }
                    for t in 0..m {
                        let r = t * n..(t + 1) * n;
                        // No light at some angle (f_O + f_E <= 0): F is undefined; drop the trial.
                        if ob[r.clone()].iter().zip(&eb[r.clone()]).all(|(o, e)| o + e > 0.0) {
                            (qb[k], ub[k]) = self.solver.solve(&fb[r]);
                            k += 1;
                        }
                    }
                }
            }
            self.flush(&qb[..k], &ub[..k], &mut l, h);
        }
        let sum4 = |a: [f64; 4]| (a[0] + a[1]) + (a[2] + a[3]);
        ChunkSums { n: l.n, s1: sum4(l.s1), s2: sum4(l.s2), sq: sum4(l.sq), su: sum4(l.su), sd2: sum4(l.sd2) }
    }

    /// Draw exactly the random numbers a run would draw, without reducing them: the cost
    /// floor of the engine, for benchmarks. Returns a checksum so the draws are not optimized
    /// away.
    pub fn draw_only(&self) -> f64 {
        let trials = self.cfg.trials;
        let n_chunks = trials.div_ceil(CHUNK);
        (0..n_chunks)
            .into_par_iter()
            .map(|c| {
                let len = CHUNK.min(trials - c * CHUNK);
                let mut rng = chunk_rng(self.cfg.seed, c);
                self.draw_chunk(&mut rng, len)
            })
            .sum()
    }

    fn draw_chunk<R: Rng>(&self, rng: &mut R, len: u64) -> f64 {
        let mut acc = 0.0;
        let n = self.f0.len();
        match self.cfg.noise {
            Noise::GaussQu => {
                for _ in 0..len {
                    let z1: f64 = StandardNormal.sample(rng);
                    let z2: f64 = StandardNormal.sample(rng);
                    acc += z1 + z2;
                }
            }
            Noise::GaussF => {
                for _ in 0..len * n as u64 {
                    let z: f64 = StandardNormal.sample(rng);
                    acc += z;
                }
            }
            Noise::Poisson => {
                for _ in 0..len {
                    for (so, se) in &self.samplers {
                        acc += so.sample(rng) + se.sample(rng);
                    }
                }
            }
        }
        acc
    }
}

/// Trials of the timed probe of [`estimate_seconds`].
pub const PROBE_TRIALS: u64 = 100_000;

/// The wall time (s) `total` trials of `cfg` are expected to take on the calling thread pool,
/// and the rate (trials/s) it is estimated from: a timed run of [`PROBE_TRIALS`] of the same
/// configuration. `None` when `total` is at most ten probes (not worth estimating).
pub fn estimate_seconds(cfg: &McConfig, total: u64) -> Result<Option<(f64, f64)>, Error> {
    if total <= 10 * PROBE_TRIALS {
        return Ok(None);
    }
    let mut c = cfg.clone();
    c.trials = PROBE_TRIALS;
    let e = Engine::new(&c)?;
    let t0 = std::time::Instant::now();
    std::hint::black_box(e.run(None));
    let rate = PROBE_TRIALS as f64 / t0.elapsed().as_secs_f64().max(1e-9);
    Ok(Some((total as f64 / rate, rate)))
}

/// Run a configuration on `threads` threads (`None`: rayon's default pool).
pub fn run(cfg: &McConfig, threads: Option<usize>, progress: Option<&(dyn Fn(u64) + Sync)>) -> Result<McResult, Error> {
    let engine = Engine::new(cfg)?;
    match threads {
        None => Ok(engine.run(progress)),
        Some(j) => {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(j.max(1))
                .build()
                .map_err(|e| Error::Model(format!("cannot start {j} threads: {e}")))?;
            Ok(pool.install(|| engine.run(progress)))
        }
    }
}
