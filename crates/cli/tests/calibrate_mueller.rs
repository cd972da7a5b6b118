//! `instpol calibrate-mueller` end to end on Stokes maps written here: three sky fields of a
//! FORS1 B-band instrument with a diattenuation field and a stressed lens (sim's
//! `[effects.stressed_lens]` block as the truth) give back the lens's retardance; one field is
//! refused with the reason (exit 2, nothing written); a bad --field names itself.

mod common;

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
    }
}

fn truth(x: f64, y: f64) -> LinearBlock {
    let (d, ax) = lens().retardance_at(x, y);
    physical_block(2e-4 * (x * x - y * y), 4e-4 * x * y, retardance_vector(d, ax), 0.0, 0.0)
}

/// A noiseless map (errors 3e-4) of a sky of `p`, `chi_deg` seen through the truth.
fn map(dir: &Path, name: &str, p: f64, chi_deg: f64) -> PathBuf {
    let g = BinGeometry::covering(64, 0, 0, 2048, 2048, 0.2);
    let mut m = StokesMap::empty(g.clone(), "fors1", "B", vec![0.0, 22.5, 45.0, 67.5]);
    let c = 2.0 * chi_deg.to_radians();
    for j in 0..g.ny {
        for i in 0..g.nx {
            let k = j * g.nx + i;
            let (x, y) = g.centre_arcmin(i, j);
            let (q, u) = truth(x, y).forward(p * c.cos(), p * c.sin()).unwrap();
            m.q[k] = q;
            m.u[k] = u;
            m.sigma_q[k] = 3e-4;
            m.sigma_u[k] = 3e-4;
            m.cov_qu[k] = 0.0;
            m.sigma_q_phot[k] = 3e-4;
            m.sigma_u_phot[k] = 3e-4;
            let (pp, ch) = stokes::polarization(q, u);
            m.p[k] = pp;
            m.chi[k] = ch;
            m.n_pixels[k] = 4096;
            m.intensity[k] = 1000.0;
            m.intensity_snr[k] = 100.0;
            m.valid[k] = true;
        }
    }
    let path = dir.join(name);
    m.write_fits(&path).unwrap();
    path
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

    // A good fit has no chi^2 warning; a field declared under another sky's P, chi has one.
    assert!(j["warnings"].as_array().unwrap().iter().all(|w| !w.as_str().unwrap().contains("chi^2")), "{j}");
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
