//! `instpol bias`: correct a measured polarization degree for the noise bias and give an
//! interval on the true value.

use anyhow::{bail, Result};
use serde::Serialize;
use stokes::stats::{Estimator, IntervalKind};

/// Estimate the true polarization degree P0 from a measured P and its error sigma, and give a
/// confidence interval on P0.
///
/// P is biased high at low signal-to-noise (P/sigma below ~5; Patat & Romaniello 2006,
/// section "bias"). Estimators (--estimator):
///   naive  P itself;
///   as     sqrt(P^2 - sigma^2), 0 for P <= sigma;
///   wk     Wardle & Kronberg 1974: the P0 whose most probable P is the measured one (exact);
///   ml     Simmons & Stewart 1985 maximum likelihood, 0 for P <= sqrt(2) sigma;
///   mp2    2-D most probable, P - sigma^2/P (Quinn 2012), 0 for P <= sigma;
///   mas    Plaszczynski et al. 2014 modified asymptotic (continuous, never 0; default);
///   mb     posterior mean with a flat prior on P0 >= 0 (Vaillancourt 2006);
///   pr06   the paper's law P [1 - (0.62 sigma/P)^1.92], valid for P/sigma > 4.
///
/// Intervals (--interval): neyman (classical central interval from the Rice distribution;
/// the upper limit is absent when P is so small that no P0 accepts it) or hpd (Bayesian
/// highest posterior density, flat prior). When the lower limit is 0 the result is an upper
/// limit only.
///
/// P and sigma are in the same units (fraction or percent); so are the outputs. sigma is the
/// error of each of Q and U (eq:sigp: 1/(sqrt(N/2) SNR)). Example:
///
///   instpol bias --p 0.012 --sigma 0.005 --estimator wk --interval neyman
#[derive(clap::Args)]
pub struct Args {
    /// Measured polarization degree P (>= 0).
    #[arg(long)]
    pub p: f64,
    /// Error sigma of each of Q and U (> 0), same units as P.
    #[arg(long)]
    pub sigma: f64,
    /// Estimator: naive, as, wk, ml, mp2, mas, mb, pr06.
    #[arg(long, default_value = "mas")]
    pub estimator: String,
    /// Confidence level of the interval, in (0, 1); 0.6827 is "1 sigma".
    #[arg(long, default_value_t = 0.6827)]
    pub cl: f64,
    /// Interval kind: neyman or hpd.
    #[arg(long, default_value = "neyman")]
    pub interval: String,
    /// Unequal errors (MAS only): error of Q, same units as P (default: --sigma).
    #[arg(long)]
    pub sigma_q: Option<f64>,
    /// Unequal errors (MAS only): error of U, same units as P (default: --sigma).
    #[arg(long)]
    pub sigma_u: Option<f64>,
    /// Measured polarization angle in degrees (matters only for MAS with unequal errors).
    #[arg(long, default_value_t = 0.0)]
    pub chi: f64,
    /// Print JSON: estimator, estimate, interval [lo, hi] (null where a limit does not exist),
    /// upper_limit_only, and the other estimators.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Out {
    estimator: String,
    estimate: f64,
    interval: [Option<f64>; 2],
    upper_limit_only: bool,
    interval_kind: String,
    cl: f64,
    /// The classical construction accepts no P0 at all (Neyman only).
    empty: bool,
    in_validity_range: bool,
    p: f64,
    #[serde(rename = "sigma_p")]
    sigma: f64,
    snr_p: f64,
    all_estimators: std::collections::BTreeMap<String, f64>,
}

pub fn run(a: Args) -> Result<()> {
    let est: Estimator = a.estimator.parse()?;
    let kind: IntervalKind = a.interval.parse()?;
    if !(a.p.is_finite() && a.p >= 0.0) {
        bail!("--p = {} must be a finite number >= 0", a.p);
    }
    if !(a.sigma.is_finite() && a.sigma > 0.0) {
        bail!("--sigma = {} must be a finite number > 0", a.sigma);
    }
    if !a.chi.is_finite() {
        bail!("--chi = {} must be finite (degrees)", a.chi);
    }
    // The science is the library's (the Python `instpol.bias` calls the same function).
    let d = stokes::stats::debias(a.p, a.sigma, est, kind, a.cl, a.sigma_q, a.sigma_u, a.chi.to_radians())?;
    let (e, iv) = (d.estimate, d.interval);
    let out = Out {
        estimator: est.name().into(),
        estimate: e.value,
        interval: [iv.lo, iv.hi],
        upper_limit_only: iv.upper_limit_only,
        interval_kind: kind.to_string(),
        cl: a.cl,
        empty: iv.empty,
        in_validity_range: e.in_validity_range,
        p: a.p,
        sigma: a.sigma,
        snr_p: a.p / a.sigma,
        all_estimators: Estimator::ALL.iter().zip(d.all).map(|(x, v)| (x.name().to_string(), v)).collect(),
    };
    if a.json {
        return crate::util::print_json(&out);
    }
    let fmt = |v: Option<f64>| v.map_or("none".to_string(), |x| format!("{x:.6}"));
    // Fixed notation for the usual range, exponent beyond it (1e-300 printed 300 digits).
    let g = |v: f64| if v != 0.0 && !(1e-4..1e6).contains(&v.abs()) { format!("{v:.4e}") } else { format!("{v}") };
    let snr = if out.snr_p < 1e6 { format!("{:.3}", out.snr_p) } else { format!("{:.3e}", out.snr_p) };
    outln!("measured P = {} +- {} (P/sigma = {snr})", g(a.p), g(a.sigma));
    outln!(
        "estimate ({}): P0 = {:.6}{}",
        out.estimator,
        out.estimate,
        if out.in_validity_range { "" } else { "  (outside this estimator's validity range)" }
    );
    let what = if iv.empty {
        "empty: no P0 accepts this P at this level; see --interval hpd"
    } else if iv.upper_limit_only {
        "upper limit only"
    } else {
        "two-sided"
    };
    outln!("{} interval at {:.2}%: [{}, {}]  ({what})", out.interval_kind, 100.0 * a.cl, fmt(iv.lo), fmt(iv.hi));
    outln!();
    outln!("{:<8} {:>12}", "estimator", "P0");
    for (n, v) in &out.all_estimators {
        outln!("{n:<8} {v:>12.6}");
    }
    Ok(())
}
