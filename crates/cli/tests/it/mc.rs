//! `instpol mc` end to end: the JSON contract shared with the numpy peer, thread-count
//! independence, eq:sigp, the sweep and accuracy-report plots, errors.

use crate::common;

fn mc(args: &[&str]) -> (i32, String, String) {
    common::run_sub("mc", args)
}

fn json(args: &[&str]) -> serde_json::Value {
    common::run_json("mc", args)
}

/// The contract fields, eq:sigp at high eta, and the same seed on 1 and 2 threads.
#[test]
fn json_contract_threads_and_eq_sigp() {
    let args =
        ["--n-hwp", "4", "--snr", "100", "--p0", "0.1", "--trials", "100000", "--noise", "poisson", "--seed", "7"];
    let mut a1 = args.to_vec();
    a1.extend(["--threads", "1"]);
    let mut a2 = args.to_vec();
    a2.extend(["--threads", "2"]);
    let v1 = json(&a1);
    let v2 = json(&a2);
    for k in ["n_trials", "mean_p", "rms_p", "mode_p", "seconds", "trials_per_second"] {
        assert!(!v1[k].is_null(), "missing {k}");
    }
    assert_eq!(v1["n_trials"], 100000);
    for k in ["mean_p", "rms_p", "mode_p"] {
        assert_eq!(v1[k], v2[k], "{k} differs between thread counts");
    }
    let sigp = 1.0 / (2f64.sqrt() * 100.0);
    let rms = v1["rms_p"].as_f64().unwrap();
    assert!((rms / sigp - 1.0).abs() < 0.05, "{rms} vs eq:sigp {sigp}");
}

/// --sweep --plot writes a PNG and prints the fitted constants beside the paper's.
#[test]
fn sweep_writes_plot_and_fit() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("sweep.png");
    let (code, out, err) = mc(&["--sweep", "--trials", "3000", "--noise", "gauss-qu", "--plot", png.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    assert!(out.contains("paper (sec:bias)") && out.contains("0.620") && out.contains("1.920"), "{out}");
    // No temporary files left behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

/// --accuracy-report --json has the three tables.
#[test]
fn accuracy_report_json() {
    let v = json(&["--accuracy-report", "--trials", "2000", "--noise", "gauss-qu"]);
    assert!(!v["precision"].as_array().unwrap().is_empty());
    assert_eq!(v["observer"].as_array().unwrap().len(), 3);
    assert_eq!(v["noise_modes"].as_array().unwrap().len(), 15);
}

#[test]
fn bad_input_exits_2() {
    for (args, what) in [
        (vec!["--snr", "0", "--trials", "10"], "SNR"),
        (vec!["--p0", "1.5", "--trials", "10"], "P0"),
        (vec!["--noise", "gauss", "--trials", "10"], "gauss"),
        (vec!["--trials", "0"], "--trials"),
        (vec!["--threads", "0", "--trials", "10"], "--threads"),
        (vec!["--noise", "gauss-f", "--sky", "5", "--trials", "10"], "poisson"),
        (vec!["--plot", "x.png", "--trials", "10"], "--sweep"),
    ] {
        let (code, _, err) = mc(&args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(err.starts_with("error:") && err.contains(what), "{args:?}: {err}");
    }
}
