//! The Mueller field's smooth forms through the CLI:
//! `calibrate-mueller --smooth radial|interp` on maps of a centred stressed lens (radial: its
//! reduced chi^2 near 1) and of an off-centre one (radial: flagged), `correct` with each form
//! giving a fourth sky back within its errors, `plan --expected` refusing bins outside the
//! interpolant's hull; `explain` and `plan --expected` giving the same
//! answer from the FITS calibration as from the JSON of one field, and refusing a p, phi
//! calibration by name (exit 2).

use crate::common;
use common::mueller_maps;

use mueller::linear::{physical_block, retardance_vector, LinearBlock};
use mueller_maps::{map, sky_args};
use skyfield::maps::StokesMap;
use std::path::Path;

/// A radial diattenuation (0.3 % at 3.4') and a stressed lens of 18 deg at 3.4' centred at
/// `centre` (its axis radial about it).
fn lens_truth(centre: [f64; 2]) -> impl Fn(f64, f64) -> LinearBlock {
    move |x, y| {
        let (d, ax) = mueller::causes::stressed_lens(x, y, 18f64.to_radians(), 3.4, centre, 0.0);
        let a = 0.003 / (3.4 * 3.4);
        physical_block(a * (x * x - y * y), a * 2.0 * x * y, retardance_vector(d, ax), 0.0, 0.0)
    }
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

fn run(args: &[String]) -> (i32, serde_json::Value, String) {
    let (code, out, err) = common::run(args);
    (code, serde_json::from_str(&out).unwrap_or(serde_json::Value::Null), err)
}

fn calibrate(fields: &[String], extra: &[&str], out: &Path) -> serde_json::Value {
    let mut a = vec!["calibrate-mueller".to_string()];
    a.extend(fields.iter().cloned());
    a.extend(extra.iter().map(|s| s.to_string()));
    a.extend(["--json".to_string(), "--out".to_string(), s(out)]);
    let (code, j, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    j
}

#[test]
fn radial_and_interp_forms_calibrate_and_correct() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let truth = lens_truth([0.0, 0.0]);
    let fields = sky_args(d, 3e-4, &truth);
    // A fourth sky (5 %, 40 deg) to correct.
    let m4 = map(d, "b4.fits", 0.05, 40.0, 3e-4, &truth);
    let (qs, us) = (0.05 * 80f64.to_radians().cos(), 0.05 * 80f64.to_radians().sin());
    for form in ["radial", "interp"] {
        let cal = d.join(format!("{form}.fits"));
        let j = calibrate(&fields, &["--smooth", form, "--deg", "4"], &cal);
        assert_eq!(j["smooth"], form);
        if form == "radial" {
            // Noiseless maps with errors of 3e-4: chi^2 of a model that holds is far below 1.
            assert!(j["chi2_dof"].as_f64().unwrap() < 1.0, "{j}");
            assert!(!j["warnings"].to_string().contains("not radial"), "{j}");
        }
        let out = d.join(format!("b4_{form}.fits"));
        let a: Vec<String> =
            ["correct", "--cal", &s(&cal), "--in", &s(&m4), "--out", &s(&out)].iter().map(|v| v.to_string()).collect();
        let (code, _, err) = run(&a);
        assert_eq!(code, 0, "{form}: {err}");
        let cm = StokesMap::read_fits(&out).unwrap();
        let n = (0..cm.q.len()).filter(|&k| cm.valid[k]).count();
        assert!(n >= 200, "{form}: {n} bins corrected");
        let worst = (0..cm.q.len())
            .filter(|&k| cm.valid[k])
            .map(|k| ((cm.q[k] - qs) / cm.sigma_q[k]).abs().max(((cm.u[k] - us) / cm.sigma_u[k]).abs()))
            .fold(0.0, f64::max);
        assert!(worst < 3.0, "{form}: worst bin of the corrected fourth sky: {worst} sigma");
    }
    // plan --expected with the interpolant: bins outside its hull (64 px bins: centres 32 px
    // from the edge, the maps' outermost 64 px) are refused, not planned on a NaN field.
    let a: Vec<String> = [
        "plan",
        "--target-percent",
        "0.05",
        "--sky-rate",
        "2",
        "--candidate",
        "6.45:68.4",
        "--bin",
        "64",
        "--expected",
        &s(&d.join("interp.fits")),
    ]
    .iter()
    .map(|v| v.to_string())
    .collect();
    let (code, _, err) = run(&a);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("interp.fits") && err.contains("has no value"), "{err}");
    // An off-centre lens is not radial about the origin: the radial form says so.
    let off = lens_truth([0.8, -0.4]);
    let d2 = d.join("off");
    std::fs::create_dir_all(&d2).unwrap();
    let fields = sky_args(&d2, 3e-4, &off);
    let j = calibrate(&fields, &["--smooth", "radial", "--deg", "4"], &d2.join("r.fits"));
    assert!(j["chi2_dof"].as_f64().unwrap() > 2.0, "{j}");
    assert!(j["warnings"].to_string().contains("not radial"), "{j}");
    // The radial form refuses parameters with no radial pattern (exit 2, nothing written).
    let mut a = vec!["calibrate-mueller".to_string()];
    a.extend(fields.iter().cloned());
    a.extend(["--smooth", "radial", "--free", "retardance,rotation", "--out"].map(String::from));
    a.push(s(&d2.join("rot.fits")));
    let (code, _, err) = run(&a);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("radial") && err.contains("rotation"), "{err}");
    assert!(!d2.join("rot.fits").exists());
}

/// Every number of `a` equals `b`'s within `rel` (relative, absolute below 1) where both are numbers (candidate
/// parameters in absolute value); strings and structure equal; keys in `skip` ignored.
fn same(a: &serde_json::Value, b: &serde_json::Value, rel: f64, skip: &[&str], at: &str) {
    use serde_json::Value as V;
    match (a, b) {
        (V::Number(x), V::Number(y)) => {
            let (mut x, mut y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            // A retardance of -delta with its axis turned by 90 deg is the same linear block:
            // the candidates' fits may land on either from inputs an ulp apart.
            if at.contains(".params") {
                (x, y) = (x.abs(), y.abs());
                if (x - y).abs() > 45.0 {
                    (x, y) = (x.rem_euclid(90.0), y.rem_euclid(90.0));
                }
            }
            assert!((x - y).abs() <= rel * x.abs().max(y.abs()).max(1.0), "{at}: {x} vs {y}");
        }
        (V::Object(x), V::Object(y)) => {
            assert_eq!(x.len(), y.len(), "{at}");
            for (k, v) in x {
                if !skip.contains(&k.as_str()) {
                    same(v, &y[k], rel, skip, &format!("{at}.{k}"));
                }
            }
        }
        (V::Array(x), V::Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}");
            for (i, (u, v)) in x.iter().zip(y).enumerate() {
                same(u, v, rel, skip, &format!("{at}[{i}]"));
            }
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

#[test]
fn explain_and_plan_read_the_fits_calibration_as_the_json() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let fields = sky_args(d, 3e-4, &lens_truth([0.5, 0.3]));
    let (fits, json) = (d.join("mf.fits"), d.join("mf.json"));
    calibrate(&fields, &["--deg", "4"], &fits);
    calibrate(&fields, &["--deg", "4"], &json);
    let explain = |f: &Path| {
        let a: Vec<String> = [
            "explain",
            &s(f),
            "--instrument",
            "fors1",
            "--causes",
            "stressed_lens,diattenuation_only",
            "--grid",
            "8",
            "--json",
        ]
        .iter()
        .map(|v| v.to_string())
        .collect();
        let (code, j, err) = run(&a);
        assert_eq!(code, 0, "{err}");
        j
    };
    let (ef, ej) = (explain(&fits), explain(&json));
    assert_eq!(ef["best"], "stressed_lens", "{ef}");
    // FITS doubles are exact; the JSON's floats parse to within an ulp, which the candidates'
    // optimizers carry to ~1e-7 of a poorly fitting chi^2.
    same(&ef, &ej, 1e-6, &["input", "provenance", "inputs"], "explain");
    let plan = |f: &Path| {
        let a: Vec<String> = [
            "plan",
            "--target-percent",
            "0.05",
            "--sky-rate",
            "2",
            "--candidate",
            "6.45:68.4",
            "--candidate",
            "4:10",
            "--bin",
            "256",
            "--deg",
            "2",
            "--json",
            "--expected",
            &s(f),
        ]
        .iter()
        .map(|v| v.to_string())
        .collect();
        let (code, j, err) = run(&a);
        assert_eq!(code, 0, "{err}");
        j
    };
    let (pf, pj) = (plan(&fits), plan(&json));
    assert!(pf["best"].is_object(), "{pf}");
    same(&pf, &pj, 1e-5, &["provenance"], "plan");

    // A p, phi calibration is not a Mueller field: refused by name, exit 2, by content (the
    // extension says nothing).
    let pphi = d.join("pphi.cal");
    common::fors1_radial_calibration("B", common::V_COEFFS).save(&pphi).unwrap();
    for sub in ["explain", "plan"] {
        let a: Vec<String> = if sub == "explain" {
            vec!["explain".into(), s(&pphi)]
        } else {
            ["plan", "--target-percent", "0.05", "--sky-rate", "2", "--candidate", "6.45:68.4", "--expected", &s(&pphi)]
                .iter()
                .map(|v| v.to_string())
                .collect()
        };
        let (code, _, err) = run(&a);
        assert_eq!(code, 2, "{sub}: {err}");
        assert!(err.contains("pphi.cal") && err.contains("not a Mueller field"), "{sub}: {err}");
    }
    // A FITS calibration copied under a .json name is still read as FITS.
    let renamed = d.join("really_fits.json");
    std::fs::copy(&fits, &renamed).unwrap();
    same(&explain(&renamed), &ef, 1e-12, &["input", "provenance", "inputs"], "renamed");
}
