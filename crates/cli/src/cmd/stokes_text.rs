//! `instpol stokes`'s text report: Q/I, U/I, P, chi with their errors, a_0, kappa, the F_i and
//! the harmonics, as printed without --json.

use std::fmt::Write as _;
use stokes::Reduction;

/// `writeln!` into a String (cannot fail).
macro_rules! wl {
    ($o:expr, $($t:tt)*) => {{
        let _ = writeln!($o, $($t)*);
    }};
}

fn pct(x: f64) -> String {
    format!("{:9.4} %", 100.0 * x)
}

/// The text report of a reduction of `name` at the angles `hwp_deg` (per-beam errors given or
/// Poisson), with the kappa correction applied (and whether it was estimated from the data).
pub fn table(r: &Reduction, hwp_deg: &[f64], errors_given: bool, name: &str, kappa: Option<(f64, bool)>) -> String {
    let mut o = String::new();
    let how = match r.estimator {
        stokes::Estimator::FourierSums => "Fourier sums eq:Q/eq:U",
        stokes::Estimator::LeastSquares => "least squares of eq:system",
        stokes::Estimator::WeightedLeastSquares => "weighted least squares of eq:system",
    };
    let errs = if errors_given { "per-beam errors from the file" } else { "Poisson errors of counts" };
    wl!(o, "instpol stokes: {name}");
    wl!(o, "  N = {} HWP angles, {how}, {errs}", r.n);
    match kappa {
        Some((k, false)) => wl!(o, "  fluxes corrected for kappa = {k} (f_o/(1+kappa), f_e/(1-kappa))"),
        Some((k, true)) => wl!(
            o,
            "  fluxes corrected for kappa = {k:.6e}, estimated from these data (eq:kappa2; f_o/(1+kappa), f_e/(1-kappa))"
        ),
        None => {}
    }
    o.push('\n');
    wl!(o, "  {:<8} {:>11}   {:>11}", "", "value", "1-sigma");
    wl!(o, "  {:<8} {}   {}", "Q/I", pct(r.qu.q), pct(r.qu.var_q.sqrt()));
    wl!(o, "  {:<8} {}   {}", "U/I", pct(r.qu.u), pct(r.qu.var_u.sqrt()));
    wl!(
        o,
        "  {:<8} {}   {}   (eq:sigp: {} at SNR {:.0})",
        "P",
        pct(r.p),
        pct(r.sigma_p),
        pct(r.sigma_p_analytic).trim(),
        r.snr
    );
    let sc = match r.sigma_chi_deg_reported() {
        Some(s) => format!("{s:9.3} deg"),
        None => "undetermined".into(),
    };
    let chi = if r.chi_defined { format!("{:9.3} deg", r.chi_deg()) } else { "undefined".into() };
    wl!(o, "  {:<8} {chi:>11}   {sc:>11}", "chi");
    wl!(o, "  {:<8} {}   {}   (eq:a0: ~ kappa or post-analyzer B cos 2phi)", "a0", pct(r.a0), pct(r.sigma_a0));
    match r.kappa_mean {
        Some(k) => {
            let lo = r.kappa.iter().map(|e| e.kappa).fold(f64::INFINITY, f64::min);
            let hi = r.kappa.iter().map(|e| e.kappa).fold(f64::NEG_INFINITY, f64::max);
            wl!(
                o,
                "  {:<8} {:11.3e}   mean of {} estimates kappa_j (eq:kappa2), range [{lo:.3e}, {hi:.3e}]",
                "kappa",
                k,
                r.kappa.len()
            );
        }
        None => wl!(o, "  {:<8} {:>11}", "kappa", "-"),
    }
    o.push('\n');
    wl!(o, "  {:>3} {:>9} {:>11} {:>11}", "i", "hwp_deg", "F_i (%)", "sigma (%)");
    for i in 0..r.n {
        wl!(o, "  {:>3} {:>9.2} {:>11.4} {:>11.4}", i, hwp_deg[i], 100.0 * r.f[i], 100.0 * r.sigma_f[i]);
    }
    if !r.fourier.is_empty() {
        o.push('\n');
        wl!(o, "  Harmonics (eq:fourcoeff): amplitude sqrt(a_k^2 + b_k^2); k = {} is the polarization", r.n / 4);
        wl!(o, "  {:>3} {:>10} {:>10} {:>10} {:>8}", "k", "a_k (%)", "b_k (%)", "ampl (%)", "ampl/sig");
        let amax = r.fourier.iter().map(|h| h.amplitude()).fold(0.0f64, f64::max);
        for h in &r.fourier {
            let sig = super::stokes_plot::data::amplitude_sigma(h);
            let snr = if sig > 0.0 { format!("{:8.1}", h.amplitude() / sig) } else { format!("{:>8}", "-") };
            let w = if amax > 0.0 { (40.0 * h.amplitude() / amax).round() as usize } else { 0 };
            wl!(
                o,
                "  {:>3} {:>10.4} {:>10.4} {:>10.4} {snr} {}",
                h.k,
                100.0 * h.a,
                100.0 * h.b,
                100.0 * h.amplitude(),
                "#".repeat(w)
            );
        }
    }
    if !r.warnings.is_empty() {
        o.push('\n');
        wl!(o, "  warnings:");
        for w in &r.warnings {
            wl!(o, "  - {w}");
        }
    }
    o
}
