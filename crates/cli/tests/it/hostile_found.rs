//! Defects the hostile-input generator (hostile.rs) found, each checked here on its own with
//! the input that showed it, so that the fix is tested where it is explained.

use crate::common;

use std::path::Path;

/// A NaN or infinite option value was taken as given when the run did not check it: an imported
/// map with a zero angle of NaN, a star's FWHM of inf. Every floating-point option is now
/// refused unless finite (exit 2), naming the option and the value, and nothing is written.
#[test]
fn a_non_finite_option_is_refused_naming_it() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let field = fit::RadialModel::new(1, vec![1e-4, 4e-4, 0.0], [0.0, 0.0]);
    fit::models::synth::write_qu_cubes(
        &d.path().join("q.fits"),
        &d.path().join("u.fits"),
        &field,
        96,
        96,
        4.0,
        8,
        1e-4,
    )
    .unwrap();
    let import = |flag: &str, value: &str| {
        let a = [
            "import-map",
            "--q",
            &p("q.fits"),
            "--u",
            &p("u.fits"),
            "--pixel-scale",
            "4",
            "--bin",
            "8",
            "--filter",
            "V",
            "--out",
            &p("imported.fits"),
            flag,
            value,
        ];
        common::run(&a)
    };
    let (code, _, err) = import("--zero-angle", "0");
    assert_eq!(code, 0, "control: {err}");
    std::fs::remove_file(p("imported.fits")).unwrap();
    for (flag, value) in [("--zero-angle", "NaN"), ("--lambda-nm", "inf"), ("--zero-angle", "-inf")] {
        let (code, _, err) = import(flag, value);
        assert_eq!(code, 2, "{flag} {value}: {err}");
        assert!(err.contains(flag) && err.contains("not a finite number"), "{flag} {value}: {err}");
        assert!(!Path::new(&p("imported.fits")).exists(), "{flag} {value}: a calibration was written");
    }
    // Under --json the refusal is the JSON error object.
    let (code, _, err) = common::run(&["bias", "--p", "0.01", "--sigma", "0.003", "--chi", "NaN", "--json"]);
    assert_eq!(code, 2, "{err}");
    let j: serde_json::Value = serde_json::from_str(err.trim()).unwrap();
    assert!(j["error"]["message"].as_str().unwrap().contains("'--chi'"), "{err}");
}

/// `scan --out` named like its `--instrument` file (the same path, a hard link, a symlink)
/// wrote the plan over the instrument file with exit 0, and `--products` naming an input file
/// was taken; both are refused now (exit 2) and the file is unchanged.
#[test]
fn scan_refuses_to_write_its_plan_over_an_input() {
    let d = tempfile::tempdir().unwrap();
    let inst = d.path().join("inst.toml");
    std::fs::copy(common::night::tiny_fors2(), &inst).unwrap();
    let before = std::fs::read(&inst).unwrap();
    let raw = d.path().join("raw");
    std::fs::create_dir(&raw).unwrap();
    // A file the scan leaves out (not FITS): the plan is written, with no unit.
    std::fs::write(raw.join("x.fits"), "not FITS\n").unwrap();
    let hard = d.path().join("hard.toml");
    std::fs::hard_link(&inst, &hard).unwrap();
    let soft = d.path().join("soft.toml");
    std::os::unix::fs::symlink(&inst, &soft).unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_string();
    for (flag, out) in [("--out", &inst), ("--out", &hard), ("--out", &soft), ("--products", &inst)] {
        let mut a = vec!["scan".to_string(), s(&raw), "--instrument".into(), s(&inst)];
        if flag != "--out" {
            a.extend(["--out".to_string(), s(&d.path().join("plan.toml"))]);
        }
        a.extend([flag.to_string(), s(out)]);
        let (code, _, err) = common::run(&a);
        assert_eq!(code, 2, "{flag} {}: {err}", out.display());
        assert!(err.contains("refusing to write over an input"), "{err}");
        assert_eq!(std::fs::read(&inst).unwrap(), before, "{flag} {}: the instrument file changed", out.display());
    }
}

/// `zero-angle --measured FILE` with no frames took a `--bias`, `--flat`, `--hwp-angles` or
/// `--assembled` it never used, a broken master included, with exit 0; such an option is now
/// refused naming itself, as `calibrate --map` does.
#[test]
fn zero_angle_without_frames_refuses_frame_options() {
    let d = tempfile::tempdir().unwrap();
    let m = d.path().join("measured.csv");
    std::fs::write(
        &m,
        "label,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg\nA,31.2,0.3,30.0,0.2\n",
    )
    .unwrap();
    let broken = d.path().join("broken.fits");
    std::fs::write(&broken, "not a master\n").unwrap();
    let m = m.to_str().unwrap();
    let (code, _, err) = common::run(&["zero-angle", "--measured", m, "--filter", "V"]);
    assert_eq!(code, 0, "control: {err}");
    for extra in [&["--bias", broken.to_str().unwrap()][..], &["--flat", broken.to_str().unwrap()], &["--assembled"]] {
        let mut a = vec!["zero-angle", "--measured", m, "--filter", "V"];
        a.extend_from_slice(extra);
        let (code, _, err) = common::run(&a);
        assert_eq!(code, 2, "{extra:?}: {err}");
        assert!(err.contains(extra[0]) && err.contains("applies to frames"), "{extra:?}: {err}");
    }
}

/// An ECSV table in astropy's form whose columns are `names` with declared `units` ("" for
/// none) and rows `rows` (values as written).
fn ecsv(names: &[&str], units: &[&str], rows: &[&[&str]]) -> String {
    let mut t = String::from("# %ECSV 1.0\n# ---\n# datatype:\n");
    for (n, u) in names.iter().zip(units) {
        let ty = if *n == "label" || *n == "star" || *n == "filter" { "string" } else { "float64" };
        let unit = if u.is_empty() { String::new() } else { format!(" unit: '{u}',") };
        t += &format!("# - {{name: {n},{unit} datatype: {ty}}}\n");
    }
    t += "# schema: astropy-2.0\n";
    t += &names.join(" ");
    t.push('\n');
    for r in rows {
        t += &r.join(" ");
        t.push('\n');
    }
    t
}

/// Declared units were ignored by the readers that took a table's numbers as written:
/// `zero-angle --measured` read angles in rad as degrees, `fit-standards` q, u and their errors
/// in % as fractions, `scan --sky-table` a percentage declared in pix. One rule now (the column's name
/// says its unit, `skyfield::table::Table::numbers`): a declared unit is converted or refused
/// naming the column.
#[test]
fn declared_units_are_honoured_or_refused_by_every_table_reader() {
    let d = tempfile::tempdir().unwrap();
    let put = |name: &str, text: &str| {
        let p = d.path().join(name);
        std::fs::write(&p, text).unwrap();
        p.to_str().unwrap().to_string()
    };
    // One standard: measured 31.2 +- 0.3 deg, catalogued 30.0 +- 0.2 deg, in deg and in rad.
    let names = ["label", "chi_measured_deg", "sigma_chi_measured_deg", "chi_catalogue_deg", "sigma_chi_catalogue_deg"];
    let deg =
        put("deg.ecsv", &ecsv(&names, &["", "deg", "deg", "deg", "deg"], &[&["A", "31.2", "0.3", "30.0", "0.2"]]));
    let r = |x: f64| x.to_radians().to_string();
    let (a, b, c, e) = (r(31.2), r(0.3), r(30.0), r(0.2));
    let rad = put("rad.ecsv", &ecsv(&names, &["", "rad", "rad", "rad", "rad"], &[&["A", &a, &b, &c, &e]]));
    let offset = |table: &str| {
        let j = common::run_json("zero-angle", &["--measured", table, "--filter", "V"]);
        (j["zero_angle_deg"].as_f64().unwrap(), j["sigma_zero_angle_deg"].as_f64().unwrap())
    };
    let (o_deg, s_deg) = offset(&deg);
    // The closed form for one standard: catalogued less measured, the errors in quadrature.
    assert!((o_deg.abs() - 1.2).abs() < 1e-9, "{o_deg}");
    assert!((s_deg - 0.3f64.hypot(0.2)).abs() < 1e-9, "{s_deg}");
    let (o_rad, s_rad) = offset(&rad);
    assert!((o_rad - o_deg).abs() < 1e-9 && (s_rad - s_deg).abs() < 1e-9, "rad: {o_rad} +- {s_rad}");
    let pct = put("pct.ecsv", &ecsv(&names, &["", "%", "deg", "deg", "deg"], &[&["A", "31.2", "0.3", "30.0", "0.2"]]));
    let (code, _, err) = common::run(&["zero-angle", "--measured", &pct, "--filter", "V"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("column 'chi_measured_deg'") && err.contains("'%'"), "{err}");

    // Standards behind a mirror: q, u and their errors in % give the fit of the fractions.
    let cols = ["star", "parallactic_deg", "q", "sigma_q", "u", "sigma_u", "wavelength_um", "filter"];
    let rows: Vec<Vec<String>> = (0..8)
        .map(|k| {
            let pa = -150.0 + 37.0 * k as f64;
            let t = 2.0 * (40f64 - pa).to_radians();
            [
                format!("S{k}"),
                pa.to_string(),
                (0.035 * t.cos()).to_string(),
                "0.0002".into(),
                (-0.035 * t.sin()).to_string(),
                "0.0002".into(),
                "0.55".into(),
                "V".into(),
            ]
            .to_vec()
        })
        .collect();
    let table = |units: &[&str], scale: f64| {
        let rows: Vec<Vec<String>> = rows
            .iter()
            .map(|r| {
                let mut r = r.clone();
                for i in [2, 3, 4, 5] {
                    r[i] = (r[i].parse::<f64>().unwrap() * scale).to_string();
                }
                r
            })
            .collect();
        let refs: Vec<Vec<&str>> = rows.iter().map(|r| r.iter().map(|s| s.as_str()).collect()).collect();
        let refs: Vec<&[&str]> = refs.iter().map(|r| r.as_slice()).collect();
        ecsv(&cols, units, &refs)
    };
    let plain = put("plain.ecsv", &table(&["", "deg", "", "", "", "", "", ""], 1.0));
    let percent = put("percent.ecsv", &table(&["", "deg", "%", "%", "%", "%", "", ""], 100.0));
    let fit = |f: &str| common::run_json("fit-standards", &[f, "--model", "wiersema"]);
    let (jp, jc) = (fit(&plain), fit(&percent));
    // The fitted parameters and their errors (the errors scale with sigma_q, sigma_u).
    let params = |j: &serde_json::Value| -> Vec<f64> {
        j[0]["params"]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|p| [p["value"].as_f64().unwrap(), p["sigma_value"].as_f64().unwrap()])
            .collect()
    };
    let (pp, pc) = (params(&jp), params(&jc));
    assert_eq!(pp.len(), 4, "{jp}");
    for (a, b) in pp.iter().zip(&pc) {
        assert!((a - b).abs() <= 1e-6 * a.abs(), "sigma in %: {pc:?} against {pp:?}");
    }
    let pix = put("pix.ecsv", &table(&["", "pix", "", "", "", "", "", ""], 1.0));
    let (code, _, err) = common::run(&["fit-standards", &pix, "--model", "wiersema"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("column 'parallactic_deg'"), "{err}");
}

/// `mc --p0 50` (a percentage for the fraction P0, documented 0..1) was refused as "P0 = 50 is
/// invalid" without the option's name; every engine input the options set is named now.
#[test]
fn mc_names_the_option_it_refuses() {
    for (flag, value) in [("--p0", "50"), ("--snr", "0.5"), ("--n-hwp", "1"), ("--sky", "-1")] {
        let (code, _, err) = common::run(&["mc", "--trials", "100", flag, value]);
        assert_eq!(code, 2, "{flag} {value}: {err}");
        assert!(err.contains(flag), "{flag} {value}: {err}");
    }
}

/// `plan` with a target beyond reach (1e-300 %) or met by no light at all (1e300 %, or a sky
/// rate of 1e308 e-/px/s) planned exposures of inf or 0 s, and drawing them with `--plot` never
/// ended (killed after 20 s). Such a plan is refused now, naming the exposure, within a second.
#[test]
fn plan_refuses_an_exposure_that_cannot_be_observed() {
    let d = tempfile::tempdir().unwrap();
    let plot = d.path().join("plan.svg");
    for (target, rate) in [("1e-300", "2"), ("1e300", "2"), ("0.05", "1e308"), ("0.05", "1e-308")] {
        let a = ["plan", "--target-percent", target, "--sky-rate", rate, "--bin", "200"];
        let mut child = common::instpol()
            .args(a)
            .args(["--candidate", "6.45:68.4", "--candidate", "4:10", "--plot", plot.to_str().unwrap()])
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let t0 = std::time::Instant::now();
        let status = loop {
            if let Some(s) = child.try_wait().unwrap() {
                break s;
            }
            if t0.elapsed().as_secs() > 20 {
                child.kill().unwrap();
                panic!("{target} {rate}: still running after 20 s");
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        };
        let mut err = String::new();
        std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
        assert_eq!(status.code(), Some(2), "{target} {rate}: {err}");
        assert!(err.contains("needs an exposure of"), "{target} {rate}: {err}");
        assert!(!plot.exists());
    }
}

/// An SVG figure under 8 KB on a full disk became an empty file with exit 0 (`plan --plot
/// X.svg`): plotters' file target dropped the error of its last flush. Needs a real full disk
/// (a 64 KiB tmpfs, mounted as root); says so and returns elsewhere.
#[test]
fn a_small_svg_on_a_full_disk_fails_and_leaves_nothing() {
    let mnt = tempfile::tempdir().unwrap();
    let m = mnt.path().to_str().unwrap();
    let st = std::process::Command::new("mount").args(["-t", "tmpfs", "-o", "size=64k", "tmpfs", m]).output();
    if !matches!(&st, Ok(o) if o.status.success()) {
        eprintln!("note: cannot mount a tmpfs here (not root?): the full-disk SVG case is not tried");
        return;
    }
    struct Umount(std::path::PathBuf);
    impl Drop for Umount {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount").arg(&self.0).status();
        }
    }
    let _guard = Umount(mnt.path().to_path_buf());
    let mut fill = std::fs::File::create(mnt.path().join("filler")).unwrap();
    use std::io::Write;
    while fill.write_all(&[0u8; 4096]).and_then(|_| fill.sync_all()).is_ok() {}
    drop(fill);
    let plot = mnt.path().join("plan.svg");
    let (code, _, err) = common::run(&[&common::QUICK_PLAN[..], &["--plot", plot.to_str().unwrap()]].concat());
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("No space left on device"), "{err}");
    assert_eq!(common::listing(mnt.path()), ["filler"]);
}

/// `scan` wrote its plan through a writer of its own (workflow's `write_atomic`), which a
/// failing fsync did not reach: with the fsync failing (`skyfield::durable`'s injection, a
/// full disk's error at the last moment) it exited 0. It writes through the durable writer
/// now: exit 2, no plan, no temporary.
#[test]
fn scan_writes_its_plan_through_the_durable_writer() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("raw");
    std::fs::create_dir(&raw).unwrap();
    std::fs::write(raw.join("x.fits"), "not FITS\n").unwrap();
    let out = d.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let plan = out.join("plan.toml");
    let inst = common::night::tiny_fors2();
    let o = common::instpol()
        .args(["scan", raw.to_str().unwrap(), "--instrument", inst.to_str().unwrap(), "--out", plan.to_str().unwrap()])
        .env(skyfield::durable::FAIL_SYNC_ENV, "1")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("No space left on device"), "{err}");
    assert!(common::listing(&out).is_empty(), "{:?}", common::listing(&out));
}
