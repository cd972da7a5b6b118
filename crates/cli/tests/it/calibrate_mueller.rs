//! `instpol calibrate-mueller` end to end on Stokes maps written here: three sky fields of a
//! FORS1 B-band instrument with a diattenuation field and a stressed lens (sim's
//! `[effects.stressed_lens]` block as the truth) give back the lens's retardance; one field is
//! refused with the reason (exit 2, nothing written); a bad --field names itself.

use crate::common;
use common::mueller_maps;

use mueller::linear::{physical_block, retardance_vector, LinearBlock};
use skyfield::maps::{BinGeometry, StokesMap};
use std::path::{Path, PathBuf};

fn lens() -> sim::stress::StressedLensSpec {
    sim::stress::StressedLensSpec {
        retardance_edge_deg: 18.0,
        radius_arcmin: 3.4,
        centre_arcmin: [0.8, -0.4],
        tangential: false,
        axis_offset_deg: 0.0,
        before_instpol: false,
    }
}

fn truth(x: f64, y: f64) -> LinearBlock {
    let (d, ax) = lens().retardance_at(x, y);
    physical_block(2e-4 * (x * x - y * y), 4e-4 * x * y, retardance_vector(d, ax), 0.0, 0.0)
}

/// A noiseless map (64 px bins, errors 3e-4) of a sky of `p`, `chi_deg` seen through the truth.
fn map(dir: &Path, name: &str, p: f64, chi_deg: f64) -> PathBuf {
    mueller_maps::map_binned(dir, name, p, chi_deg, 3e-4, &truth, 64)
}

fn run(args: &[String]) -> std::process::Output {
    common::instpol().args(args).output().unwrap()
}

#[test]
fn three_fields_give_the_lens_retardance_and_one_field_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let f1 = map(d, "b1.fits", 0.0645, 68.4);
    let f2 = map(d, "b2.fits", 0.04, 10.0);
    let f3 = map(d, "b3.fits", 0.08, 130.0);
    let out = d.join("mf.json");
    let field = |p: &Path, s: &str| vec!["--field".to_string(), format!("{}:{s}", p.display())];
    let mut args = vec!["calibrate-mueller".to_string()];
    args.extend(field(&f1, "6.45:68.4"));
    args.extend(field(&f2, "4.0:10"));
    args.extend(field(&f3, "8.0:130"));
    args.extend(["--deg", "6", "--per-bin", "--json", "--out"].map(String::from));
    args.push(out.display().to_string());
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["n_fields"], 3);
    assert_eq!(j["n_obs"], 3 * 32 * 32);
    assert_eq!(j["output"], out.display().to_string());
    assert_eq!(j["n_bins_fitted"], 1024);
    // The truth's largest retardance over the bin centres.
    let g = BinGeometry::covering(64, 0, 0, 2048, 2048, 0.2);
    let mut dmax: f64 = 0.0;
    for jy in 0..g.ny {
        for ix in 0..g.nx {
            let (x, y) = g.centre_arcmin(ix, jy);
            dmax = dmax.max(lens().retardance_at(x, y).0.to_degrees());
        }
    }
    let got = j["max_retardance_deg"].as_f64().unwrap();
    assert!((got - dmax).abs() < 0.05 * dmax, "largest retardance {got} deg, truth {dmax} deg");
    let mf = fit::mueller_field::MuellerField::from_json(&std::fs::read_to_string(&out).unwrap(), "mf.json").unwrap();
    let (d0, _) = lens().retardance_at(2.0, 1.0);
    let ph = mf.physical_at(2.0, 1.0).unwrap();
    assert!((ph.retardance - d0).abs() < 0.02, "{} vs {d0}", ph.retardance);

    // One field: refused, exit 2, nothing written.
    let out1 = d.join("one.json");
    let mut args = vec!["calibrate-mueller".to_string()];
    args.extend(field(&f1, "6.45:68.4"));
    args.extend(["--out".to_string(), out1.display().to_string()]);
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("retardance unconstrained") && err.contains("one sky polarization state"), "{err}");
    assert!(!out1.exists());

    // A good fit has no chi^2-too-large warning; a field declared under another sky's P, chi
    // has one.
    assert!(j["warnings"].as_array().unwrap().iter().all(|w| !w.as_str().unwrap().contains("far from 1")), "{j}");
    let bad = d.join("bad.json");
    let mut args = vec!["calibrate-mueller".to_string()];
    args.extend(field(&f1, "6.45:68.4"));
    args.extend(field(&f2, "8.0:130"));
    args.extend(field(&f3, "4.0:10"));
    args.extend(["--json", "--out"].map(String::from));
    args.push(bad.display().to_string());
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let jb: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(
        jb["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("far from 1")),
        "chi2_dof {}: {jb}",
        jb["chi2_dof"]
    );

    // A bad --field spec names itself.
    let o = run(&["calibrate-mueller", "--field", "x.fits:abc:10", "--out", "y.json"].map(String::from));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2));
    assert!(err.contains("x.fits:abc:10") && err.contains("P_PERCENT"), "{err}");
}

/// `instpol plan` linearized at a fitted Mueller field: one field is refused with the reason,
/// the cheapest plan uses >= 2 fields, and --check simulates it at the target (exit 0); the
/// plot is written.
#[test]
fn plan_from_a_fitted_field_is_checked_by_simulation() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let maps = [map(d, "b1.fits", 0.0645, 68.4), map(d, "b2.fits", 0.04, 10.0), map(d, "b3.fits", 0.08, 130.0)];
    let mf = d.join("mf.json");
    let mut args = vec!["calibrate-mueller".to_string()];
    for (m, s) in maps.iter().zip(["6.45:68.4", "4.0:10", "8.0:130"]) {
        args.extend(["--field".to_string(), format!("{}:{s}", m.display())]);
    }
    args.extend(["--deg".to_string(), "6".to_string(), "--out".to_string(), mf.display().to_string()]);
    assert!(run(&args).status.success());
    let plot = d.join("plan.png");
    let args: Vec<String> = [
        "plan",
        "--target-percent",
        "0.05",
        "--sky-rate",
        "2",
        "--candidate",
        "6.45:68.4",
        "--candidate",
        "4:10",
        "--candidate",
        "8:130",
        "--bin",
        "128",
        "--deg",
        "4",
        "--check",
        "--json",
    ]
    .iter()
    .map(|s| s.to_string())
    .chain(["--expected".to_string(), mf.display().to_string(), "--plot".to_string(), plot.display().to_string()])
    .collect();
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(j["best"]["n_fields"].as_u64().unwrap() >= 2, "{j}");
    assert!(j["refused"][0].as_str().unwrap().contains("retardance unconstrained"), "{j}");
    let sim = j["simulated_rms_qu"].as_f64().unwrap();
    assert!((sim / 5e-4 - 1.0).abs() < 0.25, "simulated {sim} against 5e-4");
    assert_eq!(j["output"], plot.display().to_string());
    assert!(std::fs::metadata(&plot).unwrap().len() > 1000);
}

/// `instpol correct --cal CAL --in INPUT --out OUT` and further arguments.
fn correct_args(cal: &Path, input: &Path, out: &Path, extra: &[&str]) -> Vec<String> {
    let mut v = vec!["correct".to_string()];
    for (k, p) in [("--cal", cal), ("--in", input), ("--out", out)] {
        v.extend([k.to_string(), p.display().to_string()]);
    }
    v.extend(extra.iter().map(|s| s.to_string()));
    v
}

/// A deterministic normal deviate stream (splitmix64 and Box-Muller), written here so the
/// test needs no random-number crate.
struct Gauss(u64);

impl Gauss {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
    }
}

/// Pull statistics `(rms, mean)` of the corrected q0, u0 against the true q, u of a corrected
/// catalog (columns q_true, u_true kept from the input), and the RMS of the residuals.
fn pulls(path: &Path) -> (f64, f64, f64) {
    let mut r = csv::ReaderBuilder::new().comment(Some(b'#')).from_path(path).unwrap();
    let h = r.headers().unwrap().clone();
    let col = |name: &str| h.iter().position(|c| c == name).unwrap_or_else(|| panic!("no column {name}"));
    let (iq, iu, it, iv, isq, isu) =
        (col("q0"), col("u0"), col("q_true"), col("u_true"), col("sigma_q0"), col("sigma_u0"));
    let (mut s2, mut s1, mut r2, mut n) = (0.0, 0.0, 0.0, 0.0);
    for rec in r.records() {
        let rec = rec.unwrap();
        let v = |i: usize| rec[i].parse::<f64>().unwrap();
        for (a, t, s) in [(v(iq), v(it), v(isq)), (v(iu), v(iv), v(isu))] {
            let p = (a - t) / s;
            s2 += p * p;
            s1 += p;
            r2 += (a - t) * (a - t);
            n += 1.0;
        }
    }
    ((s2 / n).sqrt(), s1 / n, (r2 / n).sqrt())
}

/// The Mueller field end to end through the CLI: three simulated FORS1 B sky fields with a
/// diattenuation field and a stressed-lens retardance field -> `calibrate-mueller --out
/// CAL.fits` -> `instpol correct` on a catalog of polarized stars across the field (P up to
/// 8 %, every angle, noise 3e-4): the corrected q, u come back within their errors (pull RMS
/// ~1), where a p, phi calibration of the same B data (`--free none`, one field, the paper's
/// method) leaves a residual several times the errors. A Stokes map of a fourth sky comes back
/// to that sky too.
#[test]
fn mueller_calibration_corrects_polarized_stars_where_p_phi_leaves_a_residual() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let maps = [map(d, "b1.fits", 0.0645, 68.4), map(d, "b2.fits", 0.04, 10.0), map(d, "b3.fits", 0.08, 130.0)];
    let cal = d.join("cal.fits");
    let mut args = vec!["calibrate-mueller".to_string()];
    for (m, s) in maps.iter().zip(["6.45:68.4", "4.0:10", "8.0:130"]) {
        args.extend(["--field".to_string(), format!("{}:{s}", m.display())]);
    }
    args.extend(["--deg", "6", "--per-bin", "--json", "--out"].map(String::from));
    args.push(cal.display().to_string());
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["model"], "physical");
    assert_eq!(j["free"], serde_json::json!(["diattenuation", "retardance"]));
    // Noiseless maps with errors of 3e-4: the errors are over-estimated, and it is said.
    assert!(j["warnings"].as_array().unwrap().iter().any(|w| w.as_str().unwrap().contains("over-estimated")), "{j}");
    let mc = fit::mueller_field::cal::MuellerCal::load(&cal).unwrap();
    assert_eq!((mc.instrument.as_str(), mc.filter.as_str(), mc.skies.len(), mc.per_bin.len()), ("fors1", "B", 3, 1024));

    // The paper's p, phi calibration of the same B data.
    let pphi = d.join("pphi.fits");
    let mut args =
        vec!["calibrate-mueller".to_string(), "--field".to_string(), format!("{}:6.45:68.4", maps[0].display())];
    args.extend(["--free", "none", "--deg", "6", "--out"].map(String::from));
    args.push(pphi.display().to_string());
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    // Polarized stars across the field.
    let mut g = Gauss(2006);
    let mut text = String::from("x,y,q,u,sigma_q,sigma_u,q_true,u_true\n");
    let s = 3e-4;
    for _ in 0..200 {
        let (x, y) = (6.4 * g.uniform() - 3.2, 6.4 * g.uniform() - 3.2);
        let (p, chi) = (0.005 + 0.075 * g.uniform(), std::f64::consts::PI * g.uniform());
        let (qt, ut) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
        let (q, u) = truth(x, y).forward(qt, ut).unwrap();
        let (q, u) = (q + s * g.normal(), u + s * g.normal());
        text.push_str(&format!("{x},{y},{q},{u},{s},{s},{qt},{ut}\n"));
    }
    let stars = d.join("stars.csv");
    std::fs::write(&stars, text).unwrap();

    let corrected = d.join("stars_mueller.csv");
    let o = run(&correct_args(&cal, &stars, &corrected, &["--json"]));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let jc: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((jc["n_rows"].as_u64(), jc["mueller_model"].as_str()), (Some(200), Some("physical")));
    let (rms, mean, res) = pulls(&corrected);
    assert!(rms > 0.8 && rms < 1.25 && mean.abs() < 0.15, "Mueller: pull RMS {rms}, mean {mean}, residual {res}");

    let corrected_pphi = d.join("stars_pphi.csv");
    let o = run(&correct_args(&pphi, &stars, &corrected_pphi, &[]));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (rms_p, _, res_p) = pulls(&corrected_pphi);
    eprintln!("pull RMS: Mueller {rms:.3} (residual {res:.2e}), p, phi {rms_p:.3} (residual {res_p:.2e})");
    assert!(rms_p > 3.0 && res_p > 3.0 * s, "p, phi: pull RMS {rms_p}, residual {res_p}");

    // A map of a fourth sky (5 %, 40 deg) comes back to that sky within its errors.
    let m4 = map(d, "b4.fits", 0.05, 40.0);
    let out4 = d.join("b4_corr.fits");
    let o = run(&correct_args(&cal, &m4, &out4, &[]));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cm = StokesMap::read_fits(&out4).unwrap();
    let (qs, us) = (0.05 * 80f64.to_radians().cos(), 0.05 * 80f64.to_radians().sin());
    let worst = (0..cm.q.len())
        .filter(|&k| cm.valid[k])
        .map(|k| ((cm.q[k] - qs) / cm.sigma_q[k]).abs().max(((cm.u[k] - us) / cm.sigma_u[k]).abs()))
        .fold(0.0, f64::max);
    assert!(worst < 3.0, "worst bin of the corrected fourth sky: {worst} sigma");

    // Outside the fitted field: refused naming the row, unless --allow-extrapolation.
    let far = d.join("far.csv");
    std::fs::write(&far, "x,y,q,u,sigma_q,sigma_u\n0,0,0.01,0,3e-4,3e-4\n5.0,0,0.01,0,3e-4,3e-4\n").unwrap();
    let o = run(&correct_args(&cal, &far, &d.join("far_out.csv"), &[]));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("far.csv") && err.contains("outside"), "{err}");
    assert!(!d.join("far_out.csv").exists());
}

/// Bad input around Mueller calibrations, each exit 2 with a message naming it and nothing
/// written: an output of unknown format, fields of two filters, `--method first-order` with a
/// Mueller file, a Mueller file where a p, phi calibration is needed (`plot`).
#[test]
fn mueller_calibration_bad_inputs_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (b1, b2) = (map(d, "b1.fits", 0.0645, 68.4), map(d, "b2.fits", 0.04, 10.0));
    let field = |p: &Path, s: &str| format!("{}:{s}", p.display());
    let base = |out: &Path| {
        vec![
            "calibrate-mueller".to_string(),
            "--field".into(),
            field(&b1, "6.45:68.4"),
            "--field".into(),
            field(&b2, "4.0:10"),
            "--deg".into(),
            "2".into(),
            "--out".into(),
            out.display().to_string(),
        ]
    };
    let txt = d.join("cal.txt");
    let o = run(&base(&txt));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("cal.txt") && err.contains(".fits"), "{err}");
    assert!(!txt.exists());

    // A V map among B maps.
    let v = d.join("v.fits");
    let mut m = StokesMap::read_fits(&b2).unwrap();
    m.filter = "V".into();
    m.write_fits(&v).unwrap();
    let out = d.join("mixed.fits");
    let mut args = base(&out);
    args[4] = field(&v, "4.0:10");
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("v.fits") && err.contains("one instrument and filter"), "{err}");
    assert!(!out.exists());

    // Two maps whose products say two detectors (2048 and 1000 px a side): the one
    // compatibility check refuses them naming both sides' detectors.
    let with_detector = |from: &Path, name: &str, n: usize| {
        let to = d.join(name);
        let mut m = StokesMap::read_fits(from).unwrap();
        let mut p = m.product.clone().unwrap_or_default();
        p.detector_px = Some((n, n));
        p.pixel_scale_arcsec = Some(m.geometry.pixel_scale_arcsec);
        m.product = Some(p);
        m.write_fits(&to).unwrap();
        to
    };
    let (first, other) = (with_detector(&b1, "b1_2048.fits", 2048), with_detector(&b2, "other_detector.fits", 1000));
    let mut args = base(&out);
    args[2] = field(&first, "6.45:68.4");
    args[4] = field(&other, "4.0:10");
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("other_detector.fits") && err.contains("1000x1000 px") && err.contains("2048x2048 px"),
        "{err}"
    );
    assert!(!out.exists());
    // The same detector on both: fitted (the control).
    args[4] = field(&with_detector(&b2, "b2_2048.fits", 2048), "4.0:10");
    assert!(run(&args).status.success());
    std::fs::remove_file(&out).unwrap();

    let cal = d.join("cal.fits");
    assert!(run(&base(&cal)).status.success());
    let stars = d.join("s.csv");
    std::fs::write(&stars, "x,y,q,u,sigma_q,sigma_u\n0,0,0.01,0,3e-4,3e-4\n").unwrap();
    let o = run(&correct_args(&cal, &stars, &d.join("s_out.csv"), &["--method", "first-order"]));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("first-order") && err.contains("Mueller field"), "{err}");
    assert!(!d.join("s_out.csv").exists());

    let png = d.join("cal.png");
    let o = run(&["plot".to_string(), cal.display().to_string(), "--out".into(), png.display().to_string()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("Mueller field") && err.contains("cal.fits"), "{err}");
    assert!(!png.exists());
}

/// Polarized standards as inputs (`--stars`): one B sky field alone cannot give a retardance
/// (refused), but with 150 standards across the field at every angle (P 3-8 %, errors 3e-4)
/// the joint fit returns one, and the lens's retardance at a point far from its centre comes
/// back within 0.03 rad; a star row in percent is refused by row.
#[test]
fn polarized_standards_constrain_the_retardance_one_sky_field_cannot() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let b1 = map(d, "b1.fits", 0.0645, 68.4);
    let mut g = Gauss(16);
    let mut text = String::from("x_arcmin,y_arcmin,q,u,sigma_q,sigma_u,p_true,chi_true_deg\n");
    let s = 3e-4;
    for _ in 0..150 {
        let (x, y) = (6.4 * g.uniform() - 3.2, 6.4 * g.uniform() - 3.2);
        let (p, chi) = (0.03 + 0.05 * g.uniform(), 180.0 * g.uniform());
        let c = 2.0 * f64::to_radians(chi);
        let (q, u) = truth(x, y).forward(p * c.cos(), p * c.sin()).unwrap();
        text.push_str(&format!("{x},{y},{},{},{s},{s},{p},{chi}\n", q + s * g.normal(), u + s * g.normal()));
    }
    let stars = d.join("standards.csv");
    std::fs::write(&stars, &text).unwrap();
    let base = |out: &Path| {
        vec![
            "calibrate-mueller".to_string(),
            "--field".into(),
            format!("{}:6.45:68.4", b1.display()),
            "--deg".into(),
            "4".into(),
            "--json".into(),
            "--out".into(),
            out.display().to_string(),
        ]
    };
    let alone = d.join("alone.json");
    let o = run(&base(&alone));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("retardance unconstrained"), "{err}");

    let with = d.join("with.json");
    let mut args = base(&with);
    args.extend(["--stars".to_string(), stars.display().to_string()]);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((j["n_fields"].as_u64(), j["n_stars"].as_u64()), (Some(1), Some(150)));
    let mf =
        fit::mueller_field::MuellerField::from_json(&std::fs::read_to_string(&with).unwrap(), "with.json").unwrap();
    let (dt, _) = lens().retardance_at(-2.5, 2.5);
    let ph = mf.physical_at(-2.5, 2.5).unwrap();
    eprintln!("retardance at (-2.5, 2.5): {} rad, truth {dt} rad", ph.retardance);
    assert!((ph.retardance - dt).abs() < 0.03, "retardance {} rad, truth {dt} rad", ph.retardance);

    // A p_true in percent is refused naming the row.
    let bad = d.join("bad.csv");
    std::fs::write(&bad, "x,y,q,u,sigma_q,sigma_u,p_true,chi_true_deg\n0,0,0.01,0,3e-4,3e-4,5,30\n").unwrap();
    let out = d.join("bad.json");
    let mut args = base(&out);
    args.extend(["--stars".to_string(), bad.display().to_string()]);
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("bad.csv row 1") && err.contains("p_true"), "{err}");
    assert!(!out.exists());

    // A standard 50' off a 6.8' field (pixels taken for arcmin, or a wrong table) would pull the
    // polynomials far outside their data: refused naming the row.
    let far = d.join("far.csv");
    let mut text = text.clone();
    text.push_str(&format!("50.0,0.0,0.01,0.0,{s},{s},0.01,0.0\n"));
    std::fs::write(&far, &text).unwrap();
    let out = d.join("far.json");
    let mut args = base(&out);
    args.extend(["--stars".to_string(), far.display().to_string()]);
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("far.csv row 151") && err.contains("outside the maps' detector"), "{err}");
    assert!(!out.exists());
}

/// The three sky fields as a plate of HWP zero angle 2.89 deg (FORS2 I_BESS's) reads them: each
/// map's q, u turned by -2z here (the plate's frame), recording z (`HWPZERO`).
fn plate_map(dir: &Path, name: &str, p: f64, chi_deg: f64, z_deg: f64) -> PathBuf {
    let path = map(dir, name, p, chi_deg);
    let mut m = StokesMap::read_fits(&path).unwrap();
    let (s, c) = (2.0 * z_deg.to_radians()).sin_cos();
    for k in 0..m.q.len() {
        let (q, u) = (m.q[k], m.u[k]);
        (m.q[k], m.u[k]) = (c * q + s * u, -s * q + c * u);
        (m.p[k], m.chi[k]) = stokes::polarization(m.q[k], m.u[k]);
    }
    m.hwp_zero_angle_deg = Some(z_deg);
    m.write_fits(&path).unwrap();
    path
}

/// Maps that record an HWP zero angle are turned by it into the sky frame of their known
/// polarization before the fit: the same field as from the sky-frame maps (chi2/dof, the
/// retardance at a point), the calibration records the angle (`HWP CHI OFFSET DEG`), and
/// `correct` turns a catalog measured at the plate by it first, giving the stars of the
/// sky-frame calibration back to 1e-12. Fitted as they are (the angle not recorded), the same
/// maps need a rotation the model has not got: chi2/dof far from 1. Maps of two zero angles
/// are refused, naming both.
#[test]
fn maps_are_turned_by_their_recorded_zero_angle_before_the_fit() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let z = 2.89;
    let skies = [
        ("b1.fits", 0.0645, 68.4, "6.45:68.4"),
        ("b2.fits", 0.04, 10.0, "4.0:10"),
        ("b3.fits", 0.08, 130.0, "8.0:130"),
    ];
    let fit = |maps: &[PathBuf], out: &Path| -> serde_json::Value {
        let mut args = vec!["calibrate-mueller".to_string()];
        for (m, s) in maps.iter().zip(skies.iter().map(|s| s.3)) {
            args.extend(["--field".to_string(), format!("{}:{s}", m.display())]);
        }
        args.extend(["--deg", "6", "--json", "--out"].map(String::from));
        args.push(out.display().to_string());
        let o = run(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    };
    let sky_dir = d.join("sky");
    let plate_dir = d.join("plate");
    std::fs::create_dir_all(&sky_dir).unwrap();
    std::fs::create_dir_all(&plate_dir).unwrap();
    let sky_maps: Vec<PathBuf> = skies.iter().map(|s| map(&sky_dir, s.0, s.1, s.2)).collect();
    let plate_maps: Vec<PathBuf> = skies.iter().map(|s| plate_map(&plate_dir, s.0, s.1, s.2, z)).collect();
    let (cal_sky, cal_plate) = (d.join("sky.fits"), d.join("plate.fits"));
    let (js, jp) = (fit(&sky_maps, &cal_sky), fit(&plate_maps, &cal_plate));
    let c2 = |j: &serde_json::Value| j["chi2_dof"].as_f64().unwrap();
    assert!((c2(&js) - c2(&jp)).abs() < 1e-6 * c2(&js).max(1e-3), "{} vs {}", c2(&js), c2(&jp));
    let (a, b) = (
        fit::mueller_field::cal::MuellerCal::load(&cal_sky).unwrap(),
        fit::mueller_field::cal::MuellerCal::load(&cal_plate).unwrap(),
    );
    assert_eq!((a.hwp_chi_offset_deg, b.hwp_chi_offset_deg), (0.0, z));
    let (pa, pb) = (a.field.physical_at(2.0, 1.0).unwrap(), b.field.physical_at(2.0, 1.0).unwrap());
    assert!((pa.retardance - pb.retardance).abs() < 1e-9, "{} vs {}", pa.retardance, pb.retardance);

    // Stars measured at the plate, corrected with the plate calibration, are the sky-frame
    // stars corrected with the sky-frame calibration.
    let (sky_csv, plate_csv) = (d.join("stars_sky.csv"), d.join("stars_plate.csv"));
    let (s2, c2z) = (2.0 * f64::to_radians(z)).sin_cos();
    let mut ts = String::from("x,y,q,u,sigma_q,sigma_u\n");
    let mut tp = ts.clone();
    for k in 0..12 {
        let (x, y) = (-2.5 + 0.45 * k as f64, 1.8 - 0.3 * k as f64);
        let (q, u) = (0.01 * (k as f64).cos(), 0.02 * (0.7 * k as f64).sin());
        ts += &format!("{x},{y},{q},{u},3e-4,3e-4\n");
        tp += &format!("{x},{y},{},{},3e-4,3e-4\n", c2z * q + s2 * u, -s2 * q + c2z * u);
    }
    std::fs::write(&sky_csv, ts).unwrap();
    std::fs::write(&plate_csv, tp).unwrap();
    let (out_s, out_p) = (d.join("out_s.csv"), d.join("out_p.csv"));
    for (cal, inp, out) in [(&cal_sky, &sky_csv, &out_s), (&cal_plate, &plate_csv, &out_p)] {
        let o = run(&correct_args(cal, inp, out, &["--coords", "arcmin"]));
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let cols = |p: &Path| -> Vec<(f64, f64)> {
        let mut r = csv::ReaderBuilder::new().comment(Some(b'#')).from_path(p).unwrap();
        let h = r.headers().unwrap().clone();
        let (iq, iu) = (h.iter().position(|c| c == "q0").unwrap(), h.iter().position(|c| c == "u0").unwrap());
        r.records().map(|x| x.unwrap()).map(|x| (x[iq].parse().unwrap(), x[iu].parse().unwrap())).collect()
    };
    for ((qa, ua), (qb, ub)) in cols(&out_s).into_iter().zip(cols(&out_p)) {
        assert!((qa - qb).abs() < 1e-12 && (ua - ub).abs() < 1e-12, "({qa}, {ua}) vs ({qb}, {ub})");
    }

    // The plate maps fitted without their zero angle: a rotation the retardance model cannot
    // make, chi2/dof far from the sky frame's.
    for m in &plate_maps {
        let mut s = StokesMap::read_fits(m).unwrap();
        s.hwp_zero_angle_deg = None;
        s.write_fits(m).unwrap();
    }
    let jn = fit(&plate_maps, &d.join("unturned.fits"));
    assert!(c2(&jn) > 100.0 * c2(&js).max(1.0), "unturned chi2/dof {} vs {}", c2(&jn), c2(&js));

    // Maps of two zero angles: refused, naming both.
    let other = plate_map(&plate_dir, "b9.fits", 0.04, 10.0, 1.5);
    let mut args = vec!["calibrate-mueller".to_string()];
    args.extend(["--field".to_string(), format!("{}:6.45:68.4", sky_maps[0].display())]);
    args.extend(["--field".to_string(), format!("{}:4.0:10", other.display())]);
    args.extend(["--out".to_string(), d.join("mixed.fits").display().to_string()]);
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("b9.fits") && err.contains("1.5 deg (HWPZERO)") && err.contains("b1.fits records none"),
        "{err}"
    );
}
