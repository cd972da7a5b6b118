//! `instpol calibrate-stars` end to end on star catalogs: 200 stars over 4 dithered pointings
//! of FORS1 through the paper's V pattern (section `sec:fors1`), 20 of them polarized at
//! 1-5 %, sharing an interstellar 0.5 % at 30 deg, each measurement drawn in the test with
//! 0.05 % errors (`common::star_catalogs`). The radial coefficients come out within errors of
//! the paper's, the interstellar polarization within its error, every polarized star is named;
//! the file is the sky-field calibration's (read back by `fit::files::calibration::load`, IP SOURCE
//! "field stars"). The refusals name their input.

use crate::common;

use common::{run, star_catalogs};
use std::path::{Path, PathBuf};

const OFFSETS: [[f64; 2]; 4] = [[0.0, 0.0], [0.6, 0.25], [-0.35, 0.55], [0.3, -0.6]];

fn args(files: &[PathBuf], extra: &[&str]) -> Vec<String> {
    let mut a = vec!["calibrate-stars".to_string()];
    a.extend(files.iter().map(|f| f.display().to_string()));
    a.extend(["--filter", "V"].map(String::from));
    a.extend(extra.iter().map(|s| s.to_string()));
    a
}

fn offsets_args() -> Vec<String> {
    OFFSETS.iter().flat_map(|o| ["--offset".to_string(), format!("{},{}", o[0], o[1])]).collect()
}

#[test]
fn field_interstellar_and_polarized_stars_from_catalogs() {
    let dir = tempfile::tempdir().unwrap();
    let (iq, iu) = (0.0025, 0.005 * 3f64.sqrt() / 2.0);
    let (files, pol) = star_catalogs(dir.path(), 21, 200, 20, (iq, iu), 5e-4, &OFFSETS);
    let out = dir.path().join("cal_V.fits");
    let plots = dir.path().join("plots");
    let mut a = args(&files, &["--out", out.to_str().unwrap(), "--plots", plots.to_str().unwrap(), "--json"]);
    a.extend(offsets_args());
    let (code, stdout, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    for (k, t) in fit::models::paper::V_COEFFS_PCT.iter().enumerate() {
        let (c, s) = (f(&j["coefficients"][k]), f(&j["sigma_coefficients"][k]));
        assert!(((c - t / 100.0) / s).abs() < 3.0, "c_{}: {c} +- {s} against {t} %", k + 1);
    }
    let i = &j["interstellar"];
    assert_eq!(i["mode"], "free");
    assert!(((f(&i["q"]) - iq) / f(&i["sigma_q"])).abs() < 3.0, "{i}");
    assert!(((f(&i["u"]) - iu) / f(&i["sigma_u"])).abs() < 3.0, "{i}");
    assert!((f(&i["p"]) - 0.005).abs() < 1e-4 && (f(&i["chi_deg"]) - 30.0).abs() < 1.0, "{i}");
    assert_eq!(j["n_stars"], 200);
    assert_eq!(j["n_catalogs"], 4);
    // Every polarized star named, at its sky position; at most 2 others (0.18 expected).
    let rejected = j["rejected"].as_array().unwrap();
    for (x, y) in &pol {
        assert!(
            rejected.iter().any(|r| (f(&r["x_arcmin"]) - x).hypot(f(&r["y_arcmin"]) - y) < 1e-6),
            "polarized star at ({x}, {y}) not named"
        );
    }
    assert!(rejected.len() <= pol.len() + 2, "{} rejected", rejected.len());
    assert!(f(&j["expected_false_rejections"]) < 0.2);
    // The sky-field calibration's plots, drawn from this calibration.
    let drawn: Vec<&str> = j["plot_outputs"].as_array().unwrap().iter().map(|p| p.as_str().unwrap()).collect();
    for name in ["V_map.png", "V_profile.png", "V_residual.svg"] {
        assert!(drawn.iter().any(|p| p.ends_with(name)) && plots.join(name).is_file(), "{name}: {drawn:?}");
    }
    // The calibration file is the sky-field calibration's, read by the one loader.
    let loaded = fit::files::calibration::load(&out).unwrap();
    let cal = loaded.field.expect("a field calibration");
    assert_eq!(cal.provenance.source, "field stars");
    assert_eq!(cal.model.kind(), "RADIAL");
    assert_eq!(cal.provenance.inputs.len(), 4);
    let product = loaded.product.expect("the calibration's product");
    assert_eq!(
        (product.instrument.as_deref(), product.plate.as_deref()),
        (Some(cal.instrument.as_str()), Some("half_wave"))
    );
    assert_eq!(product.inputs.len(), 4, "the four catalogs' BLAKE3: {:?}", product.inputs);
    // The table form names the rejected stars too.
    let mut t = args(&files, &["--out", dir.path().join("cal2.fits").to_str().unwrap()]);
    t.extend(offsets_args());
    let (code, text, err) = run(&t);
    assert_eq!(code, 0, "{err}");
    assert!(text.contains("rejected as polarized: ") && text.contains("interstellar (free)"), "{text}");
}

fn refused(a: &[String], needle: &str) {
    let (code, _, err) = run(a);
    assert_eq!(code, 2, "{a:?}: {err}");
    assert!(err.contains(needle), "expected '{needle}' in: {err}");
}

#[test]
fn refusals_name_their_input() {
    let dir = tempfile::tempdir().unwrap();
    let (files, _) = star_catalogs(dir.path(), 22, 120, 0, (0.0, 0.0), 5e-4, &OFFSETS);
    let out = dir.path().join("c.fits");
    let o = out.to_str().unwrap();
    // A catalog without the zero-angle column: its q, u frame is unknown.
    let bare = dir.path().join("bare.csv");
    let text = std::fs::read_to_string(&files[0]).unwrap();
    let stripped: String = text.lines().map(|l| l.rsplit_once(',').unwrap().0.to_string() + "\n").collect();
    std::fs::write(&bare, stripped).unwrap();
    refused(&args(std::slice::from_ref(&bare), &["--out", o]), "no column 'hwp_chi_offset_deg'");
    // Pointings not matching: the third catalog of another field (another draw of stars),
    // the offsets to measure.
    let other_dir = dir.path().join("other");
    std::fs::create_dir_all(&other_dir).unwrap();
    let (others, _) = star_catalogs(&other_dir, 23, 120, 0, (0.0, 0.0), 5e-4, &OFFSETS);
    let other = others[2].clone();
    let three = [files[0].clone(), files[1].clone(), other, files[3].clone()];
    refused(&args(&three, &["--out", o]), "pointing 3: only");
    // With the offsets given, the same catalogs run and the JSON says the third shares (next to)
    // no star.
    let mut a = args(&three, &["--out", o, "--json"]);
    a.extend(offsets_args());
    let (code, stdout, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let w = j["warnings"][0].as_str().unwrap();
    assert!(w.starts_with("pointing 3 shares ") && w.contains("stars of their own"), "{j}");
    assert!(err.contains("warning: pointing 3 shares "), "{err}");
    std::fs::remove_file(o).unwrap();
    // Offsets of the wrong number.
    refused(&args(&files, &["--out", o, "--offset", "0,0"]), "1 --offset for 4 catalogs");
    // Catalogs whose q, u carry different HWP zero angles (a calibration has one).
    let turned = dir.path().join("turned.csv");
    let t2: String = std::fs::read_to_string(&files[1])
        .unwrap()
        .lines()
        .enumerate()
        .map(|(i, l)| if i == 0 { format!("{l}\n") } else { format!("{},1.5\n", l.rsplit_once(',').unwrap().0) })
        .collect();
    std::fs::write(&turned, t2).unwrap();
    refused(&args(&[files[0].clone(), turned], &["--out", o]), "carry the HWP zero angle 1.5 deg");
    // Too few stars for the model.
    let few = dir.path().join("few.csv");
    let head: String = text.lines().take(3).map(|l| format!("{l}\n")).collect();
    std::fs::write(&few, head).unwrap();
    refused(&args(&[few], &["--out", o]), "too few star measurements");
    // Errors understated 100 times and taken as they are: every star rejected.
    let tight: Vec<PathBuf> = files
        .iter()
        .map(|f| {
            let t = std::fs::read_to_string(f).unwrap().replace(",0.0005,0.0005,", ",0.000005,0.000005,");
            let p = f.with_extension("tight.csv");
            std::fs::write(&p, t).unwrap();
            p
        })
        .collect();
    let mut a = args(&tight, &["--out", o, "--error-scaling", "absolute"]);
    a.extend(offsets_args());
    refused(&a, "every one of the 120 stars was rejected");
    assert!(!Path::new(o).exists(), "a refused run wrote its output");
}

/// End to end through the simulator and `instpol catalog`: 80 stars of 2e6 e- on FORS1 in V
/// through the paper's V pattern (`instpol = radial` in the scene), 16 of them polarized at 3 %,
/// four pointings dithered along x by the telescope (`frame_shifts_px`: 0, +90, -90, +45 px;
/// along y a dither would move stars behind the strip mask), catalogued, then
/// `calibrate-stars` with the offsets measured from the stars. The offsets come out as the
/// dithers (-0.3' for +90 px of 0.2": the stars move with the telescope's shift), the
/// coefficients within 3 sigma of the paper's, every polarized star that was measured is named,
/// and few others (the catalog's errors at the field's corners are a little optimistic: the
/// fit's reduced chi^2 is 1.4). About 9 s.
#[test]
fn end_to_end_through_the_simulator_and_catalog() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Stars drawn here (seeded), at least 5" apart.
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
    let mut stars: Vec<(f64, f64, bool)> = vec![];
    while stars.len() < 80 {
        let (x, y): (f64, f64) = (rng.random_range(-3.2..3.2), rng.random_range(-3.2..3.2));
        if stars.iter().all(|s| (s.0 - x).hypot(s.1 - y) > 0.09) {
            stars.push((x, y, stars.len().is_multiple_of(5)));
        }
    }
    let shifts = [0.0, 90.0, -90.0, 45.0];
    let mut cats = vec![];
    for (k, sh) in shifts.iter().enumerate() {
        let mut s = format!(
            "instrument = \"fors1\"\nfilter = \"V\"\nhwp_angles_deg = [0, 22.5, 45, 67.5]\nexposure_s = 20\nseed = {}\n\
             frame_shifts_px = [[{sh}, 0], [{sh}, 0], [{sh}, 0], [{sh}, 0]]\n\n[sky]\nbrightness_e = 200\np = 0.0\nchi_deg = 0\n\n",
            31 + k
        );
        for (i, (x, y, pol)) in stars.iter().enumerate() {
            let (p, chi) = if *pol { (0.03, 22.5 * i as f64) } else { (0.0, 0.0) };
            s.push_str(&format!(
                "[[stars]]\nx = {x}\ny = {y}\ncoords = \"arcmin\"\nflux_e = 2e6\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 0.8\n\n"
            ));
        }
        s.push_str(
            "[effects]\ninstpol = { kind = \"radial\", coeffs_percent = [0.0, 0.012, 0.046, 0.002] }\n\
             photon_noise = true\nread_noise = true\n",
        );
        let scene = d.join(format!("p{k}.toml"));
        std::fs::write(&scene, s).unwrap();
        let frames = d.join(format!("sim{k}"));
        let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "--out", frames.to_str().unwrap()]);
        assert_eq!(code, 0, "{err}");
        let cat = d.join(format!("cat{k}.ecsv"));
        let mut a = vec!["catalog".to_string()];
        a.extend(common::fits_in(&frames).iter().map(|p| p.display().to_string()));
        a.extend(["--instrument", "fors1", "--out", cat.to_str().unwrap()].map(String::from));
        let (code, _, err) = run(&a);
        assert_eq!(code, 0, "{err}");
        cats.push(cat);
    }
    let out = d.join("cal.fits");
    let (code, stdout, err) = run(&args(&cats, &["--interstellar", "zero", "--out", out.to_str().unwrap(), "--json"]));
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    for (k, sh) in shifts.iter().enumerate() {
        let o = &j["offsets_arcmin"][k];
        assert!((f(&o[0]) + sh * 0.2 / 60.0).abs() < 2e-3 && f(&o[1]).abs() < 2e-3, "pointing {k}: {o}");
    }
    for (k, t) in fit::models::paper::V_COEFFS_PCT.iter().enumerate() {
        let (c, s) = (f(&j["coefficients"][k]), f(&j["sigma_coefficients"][k]));
        assert!(((c - t / 100.0) / s).abs() < 3.0, "c_{}: {c} +- {s} against {t} %", k + 1);
    }
    // The polarized stars the first catalog measured (the others fell behind the mask).
    let t = skyfield::table::Table::read(&cats[0], None).unwrap();
    let (xs, ys, qs) = (
        t.numbers("x_arcmin", &cats[0]).unwrap(),
        t.numbers("y_arcmin", &cats[0]).unwrap(),
        t.numbers("q", &cats[0]).unwrap(),
    );
    let measured: Vec<(f64, f64)> = stars
        .iter()
        .filter(|s| s.2)
        .filter(|s| (0..xs.len()).any(|i| qs[i].is_finite() && (xs[i] - s.0).hypot(ys[i] - s.1) < 0.02))
        .map(|s| (s.0, s.1))
        .collect();
    assert!(measured.len() >= 3, "only {} polarized stars measured", measured.len());
    let rejected = j["rejected"].as_array().unwrap();
    for (x, y) in &measured {
        let r = rejected.iter().find(|r| (f(&r["x_arcmin"]) - x).hypot(f(&r["y_arcmin"]) - y) < 0.02);
        let r = r.unwrap_or_else(|| panic!("polarized star at ({x}, {y}) not named: {j}"));
        assert!((f(&r["residual_p"]) - 0.03).abs() < 0.002, "{r}");
    }
    assert!(
        rejected.len() <= measured.len() + 3,
        "{} rejected for {} polarized: {rejected:?} {measured:?} chi2 {}",
        rejected.len(),
        measured.len(),
        j["chi2_dof"]
    );
}

/// A catalog of `n` stars on a tilted plane with noise drawn here (a fixed LCG), as
/// `instpol catalog` writes its columns, every row written `times` times.
fn plane_catalog(path: &Path, n: usize, times: usize) {
    let mut state = 12345u64;
    let mut uniform = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut rows = vec![];
    for i in 0..n {
        let (x, y) = (6.0 * uniform() - 3.0, 6.0 * uniform() - 3.0);
        let (nq, nu) = (uniform() - 0.5, uniform() - 0.5);
        let q = 0.001 + 0.0004 * x - 0.0003 * y + 6e-4 * nq;
        let u = -0.0005 + 0.0002 * x + 0.0006 * y + 6e-4 * nu;
        rows.push(format!("{i},{x},{y},{q},{u},0.0003,0.0003,0\n"));
    }
    let mut text = String::from("id,x_arcmin,y_arcmin,q,u,sigma_q,sigma_u,hwp_chi_offset_deg\n");
    for _ in 0..times {
        text.extend(rows.iter().cloned());
    }
    std::fs::write(path, text).unwrap();
}

/// The same catalog under two names (the same path, a copy, a hard link, a symlink) is refused
/// naming both; a catalog with every row written twice is used once, with a warning naming the
/// repeats: its plane's errors are those of the catalog written once (counted twice they would
/// shrink by sqrt(2)).
#[test]
fn the_same_catalog_under_two_names_is_one_input() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    plane_catalog(&p("a.csv"), 120, 1);
    plane_catalog(&p("twice.csv"), 120, 2);
    std::fs::copy(p("a.csv"), p("copy.csv")).unwrap();
    std::fs::hard_link(p("a.csv"), p("link.csv")).unwrap();
    std::os::unix::fs::symlink(p("a.csv"), p("sym.csv")).unwrap();
    let extra = ["--model", "plane", "--interstellar", "zero", "--error-scaling", "absolute", "--json"];
    let fit = |files: &[&str]| {
        let files: Vec<PathBuf> = files.iter().map(|f| p(f)).collect();
        let mut a = args(&files, &extra);
        a.extend(["--out".to_string(), p(&format!("cal{}.fits", files.len())).display().to_string()]);
        run(&a)
    };
    let sigmas = |stdout: &str| -> Vec<f64> {
        let j: serde_json::Value = serde_json::from_str(stdout).unwrap();
        j["poly"]["sigma_q"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect()
    };
    let (code, once, err) = fit(&["a.csv"]);
    assert_eq!(code, 0, "{err}");
    for other in ["a.csv", "copy.csv", "link.csv", "sym.csv"] {
        let (code, _, err) = fit(&["a.csv", other]);
        assert_eq!(code, 2, "a.csv and {other}: {err}");
        assert!(err.contains("a.csv") && err.contains(other) && err.contains("given once"), "{err}");
    }
    let (code, twice, err) = fit(&["twice.csv"]);
    assert_eq!(code, 0, "{err}");
    let repeat = format!("twice.csv row 121 repeats {} row 1;", p("twice.csv").display());
    assert!(err.contains("120 measurements repeat") && err.contains(&repeat), "{err}");
    let (s1, s2) = (sigmas(&once), sigmas(&twice));
    assert_eq!(s1.len(), 3);
    for (a, b) in s1.iter().zip(&s2) {
        assert!((a / b - 1.0).abs() < 1e-9, "sigma once {s1:?}, every row twice {s2:?}");
    }
}

/// Writes a catalog of 40 stars at `(x, y(x))`, `x` over -3..3 arcmin, each with the plane
/// `q = 0.001 + 0.0004 x`, `u = -0.0005` (no noise), and returns its path.
fn line_catalog(dir: &Path, name: &str, y: impl Fn(usize, f64) -> f64) -> PathBuf {
    let path = dir.join(name);
    let mut s = String::from("id,x_arcmin,y_arcmin,q,u,sigma_q,sigma_u,hwp_chi_offset_deg\n");
    for i in 0..40 {
        let x = -3.0 + 6.0 * i as f64 / 39.0;
        s += &format!("{i},{x},{},{},-0.0005,0.0003,0.0003,0\n", y(i, x), 0.001 + 0.0004 * x);
    }
    std::fs::write(&path, s).unwrap();
    path
}

/// A plane through stars on a tilted line (`y = 0.5 x + 0.2`) is not determined: refused
/// (exit 2) as on the line `y = 0`, naming the terms left free and the star layout, where it
/// was written with coefficients of +-2000. The same stars with every second one moved 0.3
/// arcmin off the line give the plane back: its coefficients are the written ones (closed
/// form, no noise), `q = 0.001 + 0.0004 x + 0 y`.
#[test]
fn a_plane_on_stars_on_a_line_is_refused_and_off_it_is_fitted() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cal.fits");
    let common = ["--instrument", "fors1", "--model", "plane", "--interstellar", "zero", "--json"];
    for (name, y) in [("tilted.csv", 0.5), ("flat.csv", 0.0)] {
        let cat = line_catalog(dir.path(), name, |_, x| y * x + 0.2 * y);
        let mut a = args(&[cat], &common);
        a.extend(["--out".into(), out.display().to_string()]);
        let (code, _, err) = run(&a);
        assert_eq!(code, 2, "{name}: {err}");
        assert!(err.contains("do not determine") && err.contains("the y term"), "{name}: {err}");
        assert!(err.contains("not on one line"), "{name}: {err}");
        assert!(!out.exists(), "{name}: a calibration was written");
    }
    let cat = line_catalog(dir.path(), "off.csv", |i, x| 0.5 * x + 0.2 + if i % 2 == 0 { 0.3 } else { 0.0 });
    let mut a = args(&[cat], &common);
    a.extend(["--out".into(), out.display().to_string()]);
    let (code, stdout, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let q: Vec<f64> = j["poly"]["q"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    for (got, want) in q.iter().zip([0.001, 0.0004, 0.0]) {
        assert!((got - want).abs() < 1e-10, "{q:?}");
    }
}

/// Catalogs say what they are: one whose keywords say filter I, given for a V calibration, is
/// refused naming both (exit 2, no calibration written); `--allow-mismatch` uses it, with the
/// numbers of the same catalog that says nothing; without `--instrument` the instrument is the
/// one the catalogs say, and a catalog that says nothing is taken as FORS1's with a warning.
#[test]
fn catalogs_of_another_filter_are_refused_naming_both() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    plane_catalog(&p("plain.csv"), 120, 1);
    let plain = std::fs::read_to_string(p("plain.csv")).unwrap();
    std::fs::write(p("i.csv"), format!("# INSTRUME = FORS1\n# FILTER = I\n{plain}")).unwrap();
    std::fs::write(p("v.csv"), format!("# INSTRUME = FORS1\n# FILTER = V\n{plain}")).unwrap();
    let extra = ["--model", "plane", "--interstellar", "zero", "--json"];
    let fit = |file: &str, more: &[&str]| {
        let mut a = args(&[p(file)], &extra);
        a.extend(more.iter().map(|s| s.to_string()));
        a.extend(["--out".to_string(), p(&format!("{file}.fits")).display().to_string()]);
        run(&a)
    };
    let (code, _, err) = fit("i.csv", &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("i.csv") && err.contains("filter I") && err.contains("filter V"), "{err}");
    assert!(!p("i.csv.fits").exists());
    let (code, forced, err) = fit("i.csv", &["--allow-mismatch"]);
    assert_eq!(code, 0, "{err}");
    let (code, said, err) = fit("v.csv", &[]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("instrument fors1, which the catalogs say"), "{err}");
    let (code, bare, err) = fit("plain.csv", &[]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("warning: the catalogs do not say which instrument"), "{err}");
    let q = |s: &str| serde_json::from_str::<serde_json::Value>(s).unwrap()["poly"]["q"].clone();
    assert_eq!(q(&forced), q(&bare));
    assert_eq!(q(&said), q(&bare));
}
