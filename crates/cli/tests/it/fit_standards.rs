//! End-to-end: `instpol fit-standards` on a synthetic CSV made here from the closed form of an
//! aluminium M3 (Born & Wolf 14.2) turned by the parallactic angle, on the real EFOSC2 files
//! when present, and on bad input.

use crate::common;

use std::process::Command;

fn run(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_instpol")).arg("fit-standards").args(args).output().expect("run instpol")
}

/// (Rs - Rp) / (Rs + Rp) at 45 deg for N = n + i k, in real arithmetic.
fn p45(n: f64, k: f64) -> f64 {
    let (er, ei) = (n * n - k * k - 0.5, 2.0 * n * k);
    let m = (er * er + ei * ei).sqrt();
    let (a, b) = (((m + er) / 2.0).sqrt(), ((m - er) / 2.0).sqrt());
    let c = 0.5f64.sqrt();
    let rs = ((c - a).powi(2) + b * b) / ((c + a).powi(2) + b * b);
    let (pr, pi) = ((n * n - k * k) * c, 2.0 * n * k * c);
    let rp = ((pr - a).powi(2) + (pi - b).powi(2)) / ((pr + a).powi(2) + (pi + b).powi(2));
    (rs - rp) / (rs + rp)
}

#[test]
fn synthetic_csv_recovers_factor_and_offset() {
    let dir = tempfile::tempdir().unwrap();
    // A flat table: n = 1, k = 6.5 at every wavelength.
    let table = dir.path().join("metal.txt");
    std::fs::write(&table, "lambda,n,k\n0.3,1.0,6.5\n0.9,1.0,6.5\n").unwrap();
    let (f, off) = (0.9, 25.0f64);
    let p = p45(f * 1.0, f * 6.5);
    let mut csv = String::from("filter,star,pa_deg,q,sigma_q,u,sigma_u,wavelength_um\n");
    for i in 0..12 {
        let pa = -165.0 + 30.0 * i as f64;
        let a = 2.0 * (off - pa).to_radians();
        csv += &format!("V,S{i},{pa},{},0.001,{},0.001,0.55\n", p * a.cos(), -p * a.sin());
    }
    let data = dir.path().join("std.csv");
    std::fs::write(&data, csv).unwrap();
    let plots = dir.path().join("plots");
    let o = run(&[
        data.to_str().unwrap(),
        "--model",
        "wiersema",
        "--metal",
        table.to_str().unwrap(),
        "--plot-dir",
        plots.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let params = &v[0]["params"];
    assert_eq!(params[0]["name"], "factor");
    assert!((params[0]["value"].as_f64().unwrap() - f).abs() < 1e-6, "{v}");
    assert_eq!(params[1]["unit"], "deg");
    assert!((params[1]["value"].as_f64().unwrap() - off).abs() < 1e-5, "{v}");
    assert!(v[0]["chi2"].as_f64().unwrap() < 1e-6);
    assert!(plots.join("standards_wiersema_V.png").is_file());
}

#[test]
fn real_efosc2_files_fit_in_every_band() {
    let Some(d) = efosc2_dir("the fit of every band of the real EFOSC2 files") else { return };
    let files: Vec<String> = ["pu", "pb", "pv", "pr", "pi"]
        .iter()
        .map(|b| d.join(format!("{b}_standards.txt")).display().to_string())
        .collect();
    let mut args: Vec<&str> = files.iter().map(String::as_str).collect();
    args.extend(["--joint", "--json"]);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // 5 bands x 2 models + 2 joint fits.
    assert_eq!(v.as_array().unwrap().len(), 12);
    for f in v.as_array().unwrap() {
        assert!(f["chi2_dof"].as_f64().unwrap().is_finite());
        assert!(f["rms_q"].as_f64().unwrap() < 0.01, "{f}");
    }
}

#[test]
fn bad_input_is_named_and_help_has_an_example() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.txt");
    std::fs::write(&bad, "A, 10, 0.01, 0.001, 0.0, 0.001, 0.55\nB, x, 0.01, 0.001, 0.0, 0.001, 0.55\n").unwrap();
    let o = run(&[bad.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("bad.txt") && e.contains("line 2, column 2"), "{e}");
    let o = run(&[bad.to_str().unwrap(), "--model", "fancy"]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("--model"));
    let h = Command::new(env!("CARGO_BIN_EXE_instpol")).args(["fit-standards", "--help"]).output().unwrap();
    assert!(String::from_utf8_lossy(&h.stdout)
        .contains("instpol fit-standards ../shared/data/efosc2-standards/p?_standards.txt"));
}

/// The real EFOSC2 standards' folder, or `None` after saying loudly that `what` did not run.
fn efosc2_dir(what: &str) -> Option<std::path::PathBuf> {
    crate::common::shared_data::shared_data("efosc2-standards", &[], what)
}

/// `fit-standards` of the real V standards (Wiersema model, EFOSC2's mirror) written to `cal`,
/// with `extra` arguments; it must succeed.
fn fit_v_standards(d: &std::path::Path, cal: &std::path::Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        d.join("pv_standards.txt").to_str().unwrap().to_string(),
        "--model".into(),
        "wiersema".into(),
        "--instrument".into(),
        "efosc2".into(),
        "--output".into(),
        cal.to_str().unwrap().into(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let o = run(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

/// The real EFOSC2 V standards: fitted and written as a calibration (`--output`), then each
/// standard's own measurement corrected by `instpol correct` with its parallactic angle per
/// row: unpolarized within the errors (scaled by the fit's sqrt(chi2/dof)), where raw they
/// show the M3's 3-4 %. Without the angle column the correction is refused, naming it.
#[test]
fn efosc2_v_calibration_corrects_the_standards_through_the_cli() {
    let Some(d) = efosc2_dir("the EFOSC2 CLI chain test") else { return };
    let dir = tempfile::tempdir().unwrap();
    let cal = dir.path().join("tel_V.fits");
    let o = fit_v_standards(&d, &cal, &["--json"]);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v[0]["output"].as_str().unwrap(), cal.to_str().unwrap());
    let s = v[0]["chi2_dof"].as_f64().unwrap().max(1.0).sqrt();
    // The standards as a catalog, read here without instpol.
    let mut csv = String::from("x,y,q,u,sigma_q,sigma_u,parang_deg\n");
    let mut raw_p = vec![];
    for l in std::fs::read_to_string(d.join("pv_standards.txt")).unwrap().lines().filter(|l| !l.trim().is_empty()) {
        let f: Vec<f64> = l.split(',').skip(1).map(|x| x.trim().parse().unwrap()).collect();
        csv += &format!("0,0,{},{},{},{},{}\n", f[1], f[3], f[2] * s, f[4] * s, f[0]);
        raw_p.push(f[1].hypot(f[3]));
    }
    let cat = dir.path().join("std.csv");
    std::fs::write(&cat, &csv).unwrap();
    let out = dir.path().join("std_corr.csv");
    let correct = |cat: &std::path::Path| {
        Command::new(env!("CARGO_BIN_EXE_instpol"))
            .args(["correct", "--cal", cal.to_str().unwrap(), "--in", cat.to_str().unwrap(), "--out"])
            .arg(&out)
            .arg("--json")
            .output()
            .unwrap()
    };
    let o = correct(&cat);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let sum: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(sum["telescope_model"], "wiersema");
    let mut rdr = csv::ReaderBuilder::new().comment(Some(b'#')).from_path(&out).unwrap();
    let h = rdr.headers().unwrap().clone();
    let col = |n: &str| h.iter().position(|x| x == n).unwrap();
    let (iq, iu, isq, isu) = (col("q0"), col("u0"), col("sigma_q0"), col("sigma_u0"));
    let (mut chi2, mut n) = (0.0, 0);
    for r in rdr.records() {
        let r = r.unwrap();
        let g = |i: usize| r[i].parse::<f64>().unwrap();
        chi2 += (g(iq) / g(isq)).powi(2) + (g(iu) / g(isu)).powi(2);
        n += 2;
    }
    // The model was fitted to these very rows (2 parameters): chi2 about n - 2 after the
    // scaling; below n + 4 sqrt(2n) says P = 0 within the errors.
    assert!(chi2 < n as f64 + 4.0 * (2.0 * n as f64).sqrt(), "chi2 {chi2} for {n}");
    assert!(raw_p.iter().all(|&p| p > 0.02), "{raw_p:?}");
    assert!(sum["median_p0"].as_f64().unwrap() < 0.004, "{sum}");
    // No angle column: refused, naming it.
    let bare = dir.path().join("bare.csv");
    std::fs::write(
        &bare,
        csv.lines().map(|l| l.rsplitn(2, ',').last().unwrap().to_string() + "\n").collect::<String>(),
    )
    .unwrap();
    let o = correct(&bare);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("parang_deg"), "{}", String::from_utf8_lossy(&o.stderr));
}

/// Eight standards per band of a 3.5 % mirror at offset 30 deg, `(filter, wavelength_um)`.
fn mirror_csv(bands: &[(&str, f64)]) -> String {
    let mut csv = String::from("filter,star,pa_deg,q,sigma_q,u,sigma_u,wavelength_um\n");
    for (b, w) in bands {
        for i in 0..8 {
            let pa = -160.0 + 40.0 * i as f64;
            let a = (2.0 * (30.0 - pa)).to_radians();
            csv += &format!("{b},S{i},{pa},{},0.001,{},0.001,{w}\n", 0.035 * a.cos(), -0.035 * a.sin());
        }
    }
    csv
}

/// Calibration output that cannot be right is refused (exit 2, naming the cause): several
/// bands into one file, a Cassegrain instrument, an unknown saved model.
#[test]
fn calibration_output_refuses_what_it_cannot_write() {
    let dir = tempfile::tempdir().unwrap();
    let csv = mirror_csv(&[("V", 0.55), ("R", 0.64)]);
    let data = dir.path().join("std.csv");
    std::fs::write(&data, csv).unwrap();
    let out = dir.path().join("cal.fits");
    let d = data.to_str().unwrap();
    let o = out.to_str().unwrap();
    for (args, says) in [
        (vec![d, "--output", o], "--output-dir"),
        (vec![d, "--joint", "--instrument", "fors1", "--output", o], "Cassegrain"),
        (vec![d, "--joint", "--save-model", "mirror", "--output", o], "--save-model"),
        (vec![d, "--field-cal", d], "--field-cal needs --output"),
    ] {
        let r = run(&args);
        assert_eq!(r.status.code(), Some(2), "{args:?}");
        let e = String::from_utf8_lossy(&r.stderr);
        assert!(e.contains(says), "{args:?}: {e}");
        assert!(!out.exists(), "{args:?} wrote a file");
    }
    // Jointly, one file with both bands; --output-dir, one per band.
    let r = run(&[d, "--joint", "--output", o]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(out.is_file());
    let per = dir.path().join("per");
    let r = run(&[d, "--output-dir", per.to_str().unwrap()]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(per.join("telescope_V.fits").is_file() && per.join("telescope_R.fits").is_file());
}

/// --field-cal of another instrument than --instrument: refused naming both (exit 2, nothing
/// written); the same field calibration labelled with the instrument's name is taken.
#[test]
fn field_cal_of_another_instrument_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let csv = mirror_csv(&[("V", 0.55)]);
    let data = dir.path().join("std.csv");
    std::fs::write(&data, csv).unwrap();
    let fors1 = dir.path().join("fors1_v.fits");
    let mut cal = common::fors1_radial_calibration("V", common::V_COEFFS);
    cal.save(&fors1).unwrap();
    let out = dir.path().join("tel.fits");
    let args = |fc: &std::path::Path| {
        run(&[
            data.to_str().unwrap(),
            "--instrument",
            "efosc2",
            "--field-cal",
            fc.to_str().unwrap(),
            "--output",
            out.to_str().unwrap(),
        ])
    };
    let r = args(&fors1);
    let e = String::from_utf8_lossy(&r.stderr);
    assert_eq!(r.status.code(), Some(2), "{e}");
    assert!(e.contains("fors1_v.fits") && e.contains("FORS1") && e.contains("EFOSC2"), "{e}");
    assert!(!out.exists(), "a refused --field-cal wrote {}", out.display());
    cal.instrument = "EFOSC2".into();
    let efosc2 = dir.path().join("efosc2_v.fits");
    cal.save(&efosc2).unwrap();
    let r = args(&efosc2);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(out.is_file());
}

/// A telescope model fitted from the real EFOSC2 V standards names its band by wavelength
/// (`0.550um`: the file has no filter column). A V map of EFOSC2 is corrected with it as it
/// is (the band is the filter at that wavelength, fit::correction::setup::band_is_filter), with the map
/// turned back by the model at the parallactic angle given; a B map is refused, naming the band.
#[test]
fn a_wavelength_band_corrects_the_filter_at_that_wavelength() {
    use skyfield::{BinGeometry, StokesMap};
    let Some(d) = efosc2_dir("the EFOSC2 band test") else { return };
    let dir = tempfile::tempdir().unwrap();
    let cal = dir.path().join("tel_V.fits");
    fit_v_standards(&d, &cal, &[]);
    let inst = instrument::Instrument::load("efosc2").unwrap();
    let g = BinGeometry::covering(256, 0, 0, inst.detector.nx, inst.detector.ny, inst.detector.pixel_scale_arcsec);
    let map = |filter: &str, path: &std::path::Path| {
        let mut m = StokesMap::empty(g.clone(), "EFOSC2", filter, vec![0.0, 22.5, 45.0, 67.5]);
        for k in 0..g.len() {
            (m.q[k], m.u[k]) = (0.03, -0.01);
            (m.sigma_q[k], m.sigma_u[k], m.sigma_q_phot[k], m.sigma_u_phot[k]) = (1e-4, 1e-4, 1e-4, 1e-4);
            m.cov_qu[k] = 0.0;
            (m.p[k], m.chi[k]) = stokes::polarization(0.03, -0.01);
            (m.n_pixels[k], m.intensity[k], m.intensity_snr[k], m.valid[k]) = (100, 1e4, 100.0, true);
        }
        m.write_fits(path).unwrap();
    };
    let correct = |input: &std::path::Path, out: &std::path::Path| {
        Command::new(env!("CARGO_BIN_EXE_instpol"))
            .args(["correct", "--cal", cal.to_str().unwrap(), "--in", input.to_str().unwrap(), "--out"])
            .arg(out)
            .args(["--parang", "30", "--json"])
            .output()
            .unwrap()
    };
    let (v_map, b_map) = (dir.path().join("v.fits"), dir.path().join("b.fits"));
    map("V", &v_map);
    map("B", &b_map);
    let o = correct(&v_map, &dir.path().join("v_corr.fits"));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let js: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(js["telescope_band"], "0.550um", "{js}");
    // The telescope's few percent taken out: the corrected P differs from the observed 3.2 %.
    let p0 = js["median_p0"].as_f64().unwrap();
    assert!((p0 - 0.03f64.hypot(0.01)).abs() > 0.005, "{js}");
    let o = correct(&b_map, &dir.path().join("b_corr.fits"));
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("B map") && e.contains("0.550um"), "{e}");
}

/// A run that writes several files succeeds whole or leaves none of them
/// (`skyfield::durable::stage`): with one band's model file named like the input (a hard link
/// to it, refused as an output), neither the other band's model nor any plot is left, whichever
/// band comes first; the input is unchanged. Before, the files written before the refusal
/// stayed.
#[test]
fn a_failed_run_leaves_none_of_its_files() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("std.csv");
    let csv = mirror_csv(&[("V", 0.55), ("R", 0.64)]);
    std::fs::write(&data, &csv).unwrap();
    for linked in ["V", "R"] {
        let per = dir.path().join(format!("per_{linked}"));
        let plots = dir.path().join(format!("plots_{linked}"));
        std::fs::create_dir_all(&per).unwrap();
        std::fs::hard_link(&data, per.join(format!("telescope_{linked}.fits"))).unwrap();
        let r = run(&[
            data.to_str().unwrap(),
            "--output-dir",
            per.to_str().unwrap(),
            "--plot-dir",
            plots.to_str().unwrap(),
        ]);
        assert_eq!(r.status.code(), Some(2), "{}", String::from_utf8_lossy(&r.stderr));
        assert!(String::from_utf8_lossy(&r.stderr).contains("is the input"));
        assert_eq!(common::listing(&per), vec![format!("telescope_{linked}.fits")], "linked {linked}");
        assert!(
            !plots.exists() || common::listing(&plots).is_empty(),
            "linked {linked}: {:?}",
            common::listing(&plots)
        );
        assert_eq!(std::fs::read_to_string(&data).unwrap(), csv);
    }
}

/// A standard with chi_true_deg but no p_true is a row half filled in: refused naming the line
/// and the column, where it was taken as an unpolarized star (its angle silently dropped). An
/// empty p_true and chi_true_deg together is an unpolarized star, as before.
#[test]
fn an_angle_without_a_degree_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut csv = String::from("filter,star,pa_deg,q,sigma_q,u,sigma_u,wavelength_um,p_true,chi_true_deg\n");
    for i in 0..8 {
        let pa = -160.0 + 40.0 * i as f64;
        let a = (2.0 * (30.0 - pa)).to_radians();
        csv += &format!("V,S{i},{pa},{},0.001,{},0.001,0.55,,\n", 0.035 * a.cos(), -0.035 * a.sin());
    }
    let good = dir.path().join("good.csv");
    std::fs::write(&good, &csv).unwrap();
    let r = run(&[good.to_str().unwrap()]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let half = dir.path().join("half.csv");
    std::fs::write(&half, csv.replacen("0.55,,\n", "0.55,,42.0\n", 1)).unwrap();
    let r = run(&[half.to_str().unwrap()]);
    assert_eq!(r.status.code(), Some(2));
    let e = String::from_utf8_lossy(&r.stderr);
    assert!(e.contains("half.csv") && e.contains("line 2") && e.contains("p_true is empty"), "{e}");
}

/// The same table of standards under two names (the same path, a copy, a hard link, a symlink)
/// is refused naming both; a table with every row written twice is fitted once, with a warning
/// naming the repeats: the parameters' errors are those of the table written once (counted
/// twice they would shrink by sqrt(2)).
#[test]
fn the_same_table_under_two_names_is_one_input() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let pm = p45(1.0 * 0.9, 6.5 * 0.9);
    let mut rows = vec![];
    for i in 0..12 {
        let pa = -165.0 + 30.0 * i as f64;
        let a = 2.0 * (25.0 - pa).to_radians();
        // Deterministic scatter of about one sigma, so that the errors are the data's.
        let (dq, du) = (0.001 * ((i * 7 % 5) as f64 - 2.0) / 2.0, 0.001 * ((i * 3 % 5) as f64 - 2.0) / 2.0);
        rows.push(format!("V,S{i},{pa},{},0.001,{},0.001,0.55\n", pm * a.cos() + dq, -pm * a.sin() + du));
    }
    let head = "filter,star,pa_deg,q,sigma_q,u,sigma_u,wavelength_um\n";
    std::fs::write(p("std.csv"), format!("{head}{}", rows.concat())).unwrap();
    std::fs::write(p("twice.csv"), format!("{head}{}{}", rows.concat(), rows.concat())).unwrap();
    std::fs::copy(p("std.csv"), p("copy.csv")).unwrap();
    std::fs::hard_link(p("std.csv"), p("link.csv")).unwrap();
    std::os::unix::fs::symlink(p("std.csv"), p("sym.csv")).unwrap();
    let fit = |files: &[&str]| {
        let mut a: Vec<String> = files.iter().map(|f| p(f).display().to_string()).collect();
        a.extend(["--model", "wiersema", "--json"].map(String::from));
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        run(&a)
    };
    let sigmas = |o: &std::process::Output| -> Vec<f64> {
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        v[0]["params"].as_array().unwrap().iter().map(|x| x["sigma_value"].as_f64().unwrap()).collect()
    };
    let once = fit(&["std.csv"]);
    assert!(once.status.success(), "{}", String::from_utf8_lossy(&once.stderr));
    for other in ["std.csv", "copy.csv", "link.csv", "sym.csv"] {
        let o = fit(&["std.csv", other]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "std.csv and {other}: {err}");
        assert!(err.contains("std.csv") && err.contains(other) && err.contains("given once"), "{err}");
    }
    let twice = fit(&["twice.csv"]);
    let err = String::from_utf8_lossy(&twice.stderr);
    assert!(twice.status.success(), "{err}");
    assert!(err.contains("12 measurements repeat") && err.contains("twice.csv:14 repeats"), "{err}");
    let (s1, s2) = (sigmas(&once), sigmas(&twice));
    assert!(!s1.is_empty() && s1.iter().all(|s| *s > 0.0), "{s1:?}");
    for (a, b) in s1.iter().zip(&s2) {
        assert!((a / b - 1.0).abs() < 1e-9, "sigma once {s1:?}, every row twice {s2:?}");
    }
}
