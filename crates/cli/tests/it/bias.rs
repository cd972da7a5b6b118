//! `instpol bias` end to end: the JSON contract, the interval cases, errors.

use crate::common;

fn bias(args: &[&str]) -> (i32, String, String) {
    common::run_sub("bias", args)
}

fn json(args: &[&str]) -> serde_json::Value {
    common::run_json("bias", args)
}

/// JSON fields estimator, estimate, interval [lo, hi], upper_limit_only, and the estimate is
/// the library's (WK: the P0 whose Rice mode is the measured P).
#[test]
fn json_contract_and_wk_fixed_point() {
    let v = json(&["--p", "0.03", "--sigma", "0.01", "--estimator", "wk"]);
    assert_eq!(v["estimator"], "wk");
    let est = v["estimate"].as_f64().unwrap();
    let mode = stokes::stats::Rice::new(est, 0.01).unwrap().mode();
    assert!((mode - 0.03).abs() < 1e-10, "{mode}");
    let iv = v["interval"].as_array().unwrap();
    assert_eq!(iv.len(), 2);
    let (lo, hi) = (iv[0].as_f64().unwrap(), iv[1].as_f64().unwrap());
    assert!(lo > 0.0 && lo < est && est < hi);
    assert_eq!(v["upper_limit_only"], false);
    // The Neyman limits put the measurement at the (1 +- cl)/2 points of the Rice cdf.
    let cl = 0.6827;
    let c_lo = stokes::stats::Rice::new(lo, 0.01).unwrap().cdf(0.03);
    let c_hi = stokes::stats::Rice::new(hi, 0.01).unwrap().cdf(0.03);
    assert!((c_lo - 0.5 * (1.0 + cl)).abs() < 1e-8 && (c_hi - 0.5 * (1.0 - cl)).abs() < 1e-8);
}

/// Small P: an upper limit only (lower limit 0), and for very small P no upper limit (null).
#[test]
fn upper_limits_and_missing_limits() {
    let v = json(&["--p", "0.8", "--sigma", "1"]);
    assert_eq!(v["upper_limit_only"], true);
    assert_eq!(v["interval"][0].as_f64().unwrap(), 0.0);
    assert!(v["interval"][1].as_f64().unwrap() > 0.0);
    let v = json(&["--p", "0.1", "--sigma", "1"]);
    assert!(v["interval"][1].is_null());
    let v = json(&["--p", "1", "--sigma", "1", "--interval", "hpd", "--cl", "0.95"]);
    assert_eq!(v["upper_limit_only"], true);
    assert!(v["interval"][1].as_f64().unwrap() > 1.0);
    // ML is zero below sqrt(2) sigma; MAS is P/2 as P -> 0.
    let v = json(&["--p", "1.4", "--sigma", "1", "--estimator", "ml"]);
    assert_eq!(v["estimate"].as_f64().unwrap(), 0.0);
    let v = json(&["--p", "1e-6", "--sigma", "1", "--estimator", "mas"]);
    assert!((v["estimate"].as_f64().unwrap() - 0.5e-6).abs() < 1e-15);
}

#[test]
fn bad_input_exits_2_naming_the_input() {
    for (args, what) in [
        (vec!["--p", "-1", "--sigma", "1"], "--p"),
        (vec!["--p", "1", "--sigma", "0"], "--sigma"),
        (vec!["--p", "1", "--sigma", "1", "--estimator", "xyz"], "xyz"),
        (vec!["--p", "1", "--sigma", "1", "--cl", "1.5"], "confidence level"),
        (vec!["--p", "1", "--sigma", "1", "--interval", "bayes"], "bayes"),
    ] {
        let (code, _, err) = bias(&args);
        assert_eq!(code, 2, "{args:?}");
        assert!(err.starts_with("error:") && err.contains(what), "{err}");
    }
}
