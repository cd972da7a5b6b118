//! Exit codes and flags a script can trust, outputs that never replace inputs,
//! resource bounds and unit traps, each checked on the built binary.

use crate::common;

use common::run;
use std::path::{Path, PathBuf};

const GOOD: &str =
    "hwp_deg,f_o,f_e\n0,505000,495000\n22.5,508660.25,491339.75\n45,495000,505000\n67.5,491339.75,508660.25\n";

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

fn json(out: &str) -> serde_json::Value {
    serde_json::from_str(out).unwrap_or_else(|e| panic!("not JSON ({e}): {out}"))
}

/// Frames and a Stokes map of the tiny instrument, made by the binary.
fn frames(dir: &Path) -> (PathBuf, Vec<String>, PathBuf) {
    let ins = dir.join("mini.toml");
    std::fs::write(&ins, common::MINI.toml()).unwrap();
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, "instrument = \"mini.toml\"\nfilter = \"V\"\n[sky]\nbrightness_e = 20000\np = 0.02\n")
        .unwrap();
    let (c, _, e) = run(&["simulate", &s(&scene), "--out", &s(&dir.join("frames"))]);
    assert_eq!(c, 0, "{e}");
    let fr: Vec<String> = common::fits_in(&dir.join("frames")).iter().map(|p| s(p)).collect();
    let map = dir.join("map.fits");
    let mut a = vec!["reduce".to_string(), "--instrument".into(), s(&ins), "--bin".into(), "8".into()];
    a.extend(["--out".into(), s(&map)]);
    a.extend(fr.iter().cloned());
    let (c, _, e) = run(&a);
    assert_eq!(c, 0, "{e}");
    (ins, fr, map)
}

/// A calibration of the tiny instrument's map (`instpol calibrate --map`, a 2 % sky at 30 deg).
fn calibrate_map(ins: &Path, map: &Path, cal: &Path) {
    let (c, _, e) = run(&[
        "calibrate",
        "--map",
        &s(map),
        "--instrument",
        &s(ins),
        "--sky-p",
        "2",
        "--sky-chi",
        "30",
        "--out",
        &s(cal),
    ]);
    assert_eq!(c, 0, "{e}");
}

/// Negative numbers are values in every command (`--chi -30`, `--kappa -1e-3`, `--x -30`),
/// not flags: the same result as the `--chi=-30` form, which always worked.
#[test]
fn negative_numbers_are_values_everywhere() {
    let (c1, o1, e1) = run(&["bias", "--p", "0.01", "--sigma", "0.003", "--chi", "-30", "--json"]);
    let (c2, o2, _) = run(&["bias", "--p", "0.01", "--sigma", "0.003", "--chi=-30", "--json"]);
    assert_eq!((c1, c2), (0, 0), "{e1}");
    // The same result; only the provenance (the command line as typed) differs.
    let strip = |o: &str| {
        let mut v: serde_json::Value = serde_json::from_str(o).unwrap();
        v.as_object_mut().unwrap().remove("provenance");
        v
    };
    assert_eq!(strip(&o1), strip(&o2));
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("f.csv");
    std::fs::write(&f, GOOD).unwrap();
    let (c, o, e) = run(&["stokes", "--input", &s(&f), "--kappa", "-1e-3", "--json"]);
    assert_eq!(c, 0, "{e}");
    assert_eq!(json(&o)["kappa_correction"], -1e-3);
    let (c, _, e) = run(&["mc", "--chi0", "-30", "--trials", "1000", "--json"]);
    assert_eq!(c, 0, "{e}");
    // A position at x = -30 px is refused for what it is, not as an unknown flag '-3'.
    let (ins, fr, _) = frames(d.path());
    let mut a = vec!["photometry".to_string(), "--instrument".into(), s(&ins), "--x".into(), "-30".into()];
    a.extend(["--y".into(), "24".into()]);
    a.extend(fr);
    let (c, _, e) = run(&a);
    assert_eq!(c, 2, "{e}");
    assert!(!e.contains("unexpected argument") && !e.contains("Usage"), "{e}");
}

/// HWP angles that are evidently radians are refused unless --angles-in-radians, which then
/// gives the result of the same angles in degrees.
#[test]
fn radian_hwp_angles_refused_unless_declared() {
    let d = tempfile::tempdir().unwrap();
    let deg = d.path().join("deg.csv");
    std::fs::write(&deg, GOOD).unwrap();
    let rad = d.path().join("rad.csv");
    let text: String = GOOD
        .lines()
        .enumerate()
        .map(|(i, l)| {
            if i == 0 {
                return format!("{l}\n");
            }
            let (a, rest) = l.split_once(',').unwrap();
            format!("{:.17},{rest}\n", a.parse::<f64>().unwrap().to_radians())
        })
        .collect();
    std::fs::write(&rad, text).unwrap();
    let (c, _, e) = run(&["stokes", "--input", &s(&rad), "--json"]);
    assert_eq!(c, 2);
    assert!(e.contains("rad.csv") && e.contains("look like radians") && e.contains("--angles-in-radians"), "{e}");
    let (c, o, e) = run(&["stokes", "--input", &s(&rad), "--angles-in-radians", "--json"]);
    assert_eq!(c, 0, "{e}");
    let (_, od, _) = run(&["stokes", "--input", &s(&deg), "--json"]);
    let (r, g) = (json(&o), json(&od));
    assert!((r["p"].as_f64().unwrap() - g["p"].as_f64().unwrap()).abs() < 1e-12, "{r} {g}");
    assert!((g["p"].as_f64().unwrap() - 0.02).abs() < 1e-6);
}

/// sigma_chi has one rule in `stokes` and `photometry`: null when chi is undetermined (P far
/// below its error: the linear propagation would give thousands of degrees), a number below
/// 52 deg (the spread of a uniform angle) otherwise.
#[test]
fn sigma_chi_is_null_when_chi_is_undetermined() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("weak.csv");
    // 100 counts per angle, P ~ 1e-4: sigma_P ~ 0.07, sigma_chi far beyond 52 deg.
    std::fs::write(&f, "hwp_deg,f_o,f_e\n0,50.005,49.995\n22.5,50,50\n45,49.995,50.005\n67.5,50,50\n").unwrap();
    let (c, o, e) = run(&["stokes", "--input", &s(&f), "--json"]);
    assert_eq!(c, 0, "{e}");
    assert!(json(&o)["sigma_chi_deg"].is_null(), "{o}");
    let (c, o, _) = run(&["stokes", "--input", &s(&f)]);
    assert_eq!(c, 0);
    assert!(o.contains("undetermined"), "{o}");
    let g = d.path().join("good.csv");
    std::fs::write(&g, GOOD).unwrap();
    let (_, o, _) = run(&["stokes", "--input", &s(&g), "--json"]);
    let sc = json(&o)["sigma_chi_deg"].as_f64().unwrap();
    // eq:sigchi: sigma_P / (2 P) in rad, sigma_P = 1/(sqrt(2) 1000) for 1e6 counts, N = 4.
    let want = (1e-3 / 2f64.sqrt() / (2.0 * 0.02)).to_degrees();
    assert!((sc - want).abs() < 0.01 * want, "{sc} vs {want}");
}

/// `--plot x.svg` writes SVG, `.png` PNG, anything else is refused before anything is
/// written; plots drawn only as PNG refuse `.svg` before their (long) computation.
#[test]
fn plot_format_follows_the_extension() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("f.csv");
    std::fs::write(&f, GOOD).unwrap();
    let svg = d.path().join("x.svg");
    let (c, _, e) = run(&["stokes", "--input", &s(&f), "--plot", &s(&svg)]);
    assert_eq!(c, 0, "{e}");
    let b = std::fs::read(&svg).unwrap();
    assert!(b.starts_with(b"<svg"), "{:?}", &b[..20.min(b.len())]);
    let png = d.path().join("x.png");
    run(&["stokes", "--input", &s(&f), "--plot", &s(&png)]);
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
    let jpg = d.path().join("x.jpg");
    let (c, _, e) = run(&["stokes", "--input", &s(&f), "--plot", &s(&jpg)]);
    assert_eq!(c, 2);
    assert!(e.contains("x.jpg") && e.contains(".png and .svg"), "{e}");
    assert!(!jpg.exists());
    // raytrace draws through the same two backends (it wrote PNG only, refusing .svg).
    let rt = d.path().join("rt.svg");
    let (c, _, e) = run(&["raytrace", "--instrument", "fors1", "--filter", "V", "--plot", &s(&rt)]);
    assert_eq!(c, 0, "{e}");
    assert!(std::fs::read(&rt).unwrap().starts_with(b"<svg"));
    let t0 = std::time::Instant::now();
    let (c, _, e) =
        run(&["raytrace", "--instrument", "fors1", "--filter", "V", "--plot", &s(&d.path().join("rt.pdf"))]);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("PDF is not supported") && t0.elapsed().as_secs() < 5, "{e}");
}

/// No command writes over one of its inputs, whatever name the output is given by: the same
/// path, a symlink to it, a hard link (same inode); the message names both; the input is
/// unchanged. The same input given twice is refused, naming it.
#[test]
fn outputs_never_replace_inputs() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("f.csv");
    std::fs::write(&f, GOOD).unwrap();
    let link = d.path().join("link.png");
    std::os::unix::fs::symlink(&f, &link).unwrap();
    let hard = d.path().join("hard.png");
    std::fs::hard_link(&f, &hard).unwrap();
    for out in [&f, &link, &hard] {
        let (c, _, e) = run(&["stokes", "--input", &s(&f), "--plot", &s(out)]);
        assert_eq!(c, 2, "{e}");
        assert!(e.contains("is the input") && e.contains("f.csv"), "{e}");
        assert_eq!(std::fs::read_to_string(&f).unwrap(), GOOD);
    }
    let (ins, fr, map) = frames(d.path());
    let before = std::fs::read(&fr[0]).unwrap();
    let mut a = vec!["reduce".to_string(), "--instrument".into(), s(&ins), "--bin".into(), "8".into()];
    a.extend(["--out".into(), fr[0].clone()]);
    a.extend(fr.iter().cloned());
    let (c, _, e) = run(&a);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("is the input"), "{e}");
    assert_eq!(std::fs::read(&fr[0]).unwrap(), before);
    // The same frame twice (it would be summed with itself).
    let mut a =
        vec!["reduce".to_string(), "--instrument".into(), s(&ins), "--out".into(), s(&d.path().join("m2.fits"))];
    a.extend(fr.iter().cloned());
    a.push(fr[1].clone());
    let (c, _, e) = run(&a);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("given twice") && e.contains(Path::new(&fr[1]).file_name().unwrap().to_str().unwrap()), "{e}");
    // correct: the map given as its own output.
    let cal = d.path().join("cal.fits");
    calibrate_map(&ins, &map, &cal);
    let mb = std::fs::read(&map).unwrap();
    let (c, _, e) = run(&["correct", "--cal", &s(&cal), "--in", &s(&map), "--out", &s(&map)]);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("map.fits"), "{e}");
    assert_eq!(std::fs::read(&map).unwrap(), mb);
    // A full-circle sector exclusion is refused, not silently ignored.
    let (c, _, e) = run(&["fit", &s(&cal), "--exclude", "sector:0:360"]);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("full circle"), "{e}");
    // --sky-p in percent: a fraction-looking value is warned about loudly.
    let (c, _, e) = run(&[
        "calibrate",
        "--map",
        &s(&map),
        "--instrument",
        &s(&ins),
        "--sky-p",
        "0.02",
        "--sky-chi",
        "30",
        "--out",
        &s(&d.path().join("cal3.fits")),
    ]);
    assert!(c == 0 || c == 2, "{e}");
    assert!(e.contains("warning: --sky-p 0.02 is in PERCENT") && e.contains("--sky-p 2.00"), "{e}");
}

/// The inputs a command reads through options are guarded as its positional ones are: a
/// master bias or flat named as `reduce --out` or `calibrate --out`, the calibration named as
/// `catalog --out`, a standards file named as `validate --plot`. Each is refused, naming both,
/// and the file is unchanged. (The guard is built once from every command's definition, see
/// `util::guard_arguments`, so these cases stand for every option of every command.)
#[test]
fn outputs_never_replace_masters_or_calibrations() {
    let d = tempfile::tempdir().unwrap();
    let (ins, fr, map) = frames(d.path());
    let master = d.path().join("master.fits");
    std::fs::copy(&fr[0], &master).unwrap();
    let before = std::fs::read(&master).unwrap();
    for opt in ["--bias", "--flat"] {
        for cmd in ["reduce", "calibrate"] {
            let mut a = vec![cmd.to_string(), "--instrument".into(), s(&ins), opt.into(), s(&master)];
            if cmd == "calibrate" {
                a.extend(["--sky-p".into(), "2".into(), "--sky-chi".into(), "30".into()]);
            }
            a.extend(fr.iter().cloned());
            a.extend(["--out".into(), s(&master)]);
            let (c, _, e) = run(&a);
            assert_eq!(c, 2, "{cmd} {opt}: {e}");
            assert!(e.contains("is the input") && e.contains("master.fits"), "{cmd} {opt}: {e}");
            assert_eq!(std::fs::read(&master).unwrap(), before, "{cmd} {opt} changed the master");
        }
    }
    let cal = d.path().join("cal.fits");
    calibrate_map(&ins, &map, &cal);
    let cb = std::fs::read(&cal).unwrap();
    let mut a = vec!["catalog".to_string(), "--instrument".into(), s(&ins), "--cal".into(), s(&cal)];
    a.extend(["--out".into(), s(&cal)]);
    a.extend(fr.iter().cloned());
    let (c, _, e) = run(&a);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("is the input") && e.contains("cal.fits"), "{e}");
    assert_eq!(std::fs::read(&cal).unwrap(), cb);
}

/// Resource bounds of `plan`: `--bin 1` on FORS1 (2048 x 2048 bins, three candidate fields)
/// would grow past 4 GB; it is refused before any fitting, with the estimate (4,194,304
/// bins x 3 fields x 500 B = 6.3 GB, the bins counted here from the detector's size) and the
/// ways out named. A plan within the limits runs.
#[test]
fn plan_resource_bounds() {
    let t0 = std::time::Instant::now();
    let base = ["plan", "--instrument", "fors1", "--target-percent", "0.02", "--sky-rate", "2"];
    let cands = ["--candidate", "6.45:68.4", "--candidate", "4:10", "--candidate", "8:130"];
    let mut a: Vec<&str> = base.to_vec();
    a.extend(cands);
    a.extend(["--bin", "1"]);
    let (c, _, e) = run(&a);
    assert_eq!(c, 2, "{e}");
    let gb = 2048.0 * 2048.0 * 3.0 * 500.0 / 1e9;
    assert!(e.contains("--bin 1") && e.contains("4194304 bins") && e.contains(&format!("{gb:.1} GB")), "{e}");
    assert!(e.contains("--force"), "{e}");
    assert!(t0.elapsed().as_secs() < 60, "refused only after {:?}", t0.elapsed());
    let mut a: Vec<&str> = base.to_vec();
    a.extend(cands);
    a.extend(["--bin", "256", "--json"]);
    let (c, out, e) = run(&a);
    assert_eq!(c, 0, "{e}");
    assert_eq!(json(&out)["n_bins"].as_u64(), Some(64), "{out}");
}

/// Resource bounds of `simulate`: a scene of 1000 HWP angles on FORS1 at BITPIX -64 would
/// write 1000 x 2048 x 2048 x 8 B = 33.6 GB, one frame after another, until the disk filled
/// (3000 angles wrote 1.7 GB in 15 s and went on). It is refused before any frame is written,
/// with the estimate (computed here from the detector's size) and the ways out named.
#[test]
fn simulate_resource_bounds() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let angles: Vec<String> = (0..1000).map(|k| format!("{}", 0.3 * k as f64)).collect();
    let scene = d.join("many.toml");
    std::fs::write(
        &scene,
        format!(
            "instrument = \"fors1\"\nfilter = \"V\"\nhwp_angles_deg = [{}]\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 100\np = 0.01\nchi_deg = 10\n",
            angles.join(", ")
        ),
    )
    .unwrap();
    let t0 = std::time::Instant::now();
    let out = d.join("frames");
    let (c, _, e) = run(&["simulate", scene.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(c, 2, "{e}");
    let gb = 1000.0 * 2048.0 * 2048.0 * 8.0 / 1e9;
    assert!(e.contains("many.toml") && e.contains(&format!("{gb:.1} GB")) && e.contains("--force"), "{e}");
    assert!(t0.elapsed().as_secs() < 60, "refused only after {:?}", t0.elapsed());
    assert!(!out.exists() || std::fs::read_dir(&out).unwrap().next().is_none(), "frames were written");
    // A scene value is quoted short: 1000 repeated angles are named, not listed in full.
    let repeated: Vec<String> = (0..1000).map(|k| format!("{}", 22.5 * (k % 16) as f64)).collect();
    std::fs::write(
        &scene,
        format!("instrument = \"fors1\"\nfilter = \"V\"\nhwp_angles_deg = [{}]\n", repeated.join(", ")),
    )
    .unwrap();
    let (c, _, e) = run(&["simulate", scene.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("hwp_angles_deg") && e.contains("characters)") && e.len() < 600, "{e}");
}

/// Resource bounds of `catalog`: a threshold of 0.5 sigma on the 80-star FORS1 field pairs
/// thousands of noise peaks, and with an annulus of 1000 px their photometry would take about
/// 2 x stars x 4 frames x pi 1000^2 pixel visits (over 100 s before, with no estimate): refused
/// with that estimate (computed here from the star count it names) and the ways out. The same
/// frames at the default threshold are measured.
#[test]
fn catalog_resource_bounds() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = d.join("field.toml");
    std::fs::write(&scene, include_str!("../../../../instruments/scenes/field_stars_V.toml")).unwrap();
    let out = d.join("f");
    let (c, _, e) = run(&["simulate", scene.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(c, 0, "{e}");
    let frames: Vec<String> = common::fits_in(&out).iter().map(|p| p.display().to_string()).collect();
    let cat = |extra: &[&str]| {
        let mut a: Vec<&str> = vec!["catalog", "--instrument", "fors1", "--fwhm", "3", "--json"];
        a.extend(frames.iter().map(String::as_str));
        a.extend(extra);
        run(&a)
    };
    let (c, _, e) = cat(&["--threshold", "0.5", "--annulus", "20,1000"]);
    assert_eq!(c, 2, "{e}");
    // (With --json the error is a JSON object on stderr.)
    let n: f64 = e.split(" stars paired").next().unwrap().rsplit(['"', ' ']).next().unwrap().parse().unwrap();
    assert!(n > 1000.0, "{e}");
    let visits = 2.0 * n * 4.0 * std::f64::consts::PI * 1000.0 * 1000.0;
    assert!(e.contains(&format!("{visits:.1e}")) && e.contains("--force"), "{e}");
    let (c, o, e) = cat(&[]);
    assert_eq!(c, 0, "{e}");
    assert!(json(&o)["rows"].as_array().unwrap().len() >= 40, "{o}");
}

/// Resource bounds of `mc`: threads capped at the cores (with a note; the result does not
/// depend on the thread count), a huge --trials refused with its estimated run time before
/// running, degenerate runs refused with a reason.
#[test]
fn mc_resource_bounds() {
    let (c, o, e) = run(&["mc", "--threads", "100000", "--trials", "5000", "--json"]);
    assert_eq!(c, 0, "{e}");
    assert!(e.contains("capped at the machine's"), "{e}");
    let cores = std::thread::available_parallelism().unwrap().get() as u64;
    assert_eq!(json(&o)["n_threads"].as_u64().unwrap(), cores);
    let t0 = std::time::Instant::now();
    let (c, _, e) = run(&["mc", "--trials", "1000000000000", "--json"]);
    assert_eq!(c, 2, "{e}");
    assert!(e.contains("estimated run time") && e.contains("--force"), "{e}");
    assert!(t0.elapsed().as_secs() < 20);
    for (args, word) in [
        (vec!["--snr", "1e-10"], "SNR"),
        (vec!["--read-noise", "1e200"], "read noise"),
        (vec!["--trials", "0"], "--trials"),
    ] {
        let mut a = vec!["mc"];
        a.extend(args.iter());
        if !a.contains(&"--trials") {
            a.extend(["--trials", "100"]);
        }
        let (c, o, e) = run(&a);
        assert_eq!(c, 2, "{a:?}: {o} {e}");
        assert!(e.contains(word), "{e}");
    }
}

/// `stokes` is n log n in the rows: 2e5 rows (the duplicate-angle check was all pairs, 7 s at
/// 1e5) finish in seconds, and errors near 1e149 with a plot end (sigma >= 1e160 never did).
#[test]
fn stokes_large_inputs_end() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("rows.csv");
    let mut t = String::from("hwp_deg,f_o,f_e\n");
    for i in 0..200_000 {
        t += &format!("{},{},{}\n", 7.0 + i as f64 * 0.0017, 1000 + i % 7, 1000 - i % 5);
    }
    std::fs::write(&f, t).unwrap();
    let t0 = std::time::Instant::now();
    let (c, _, e) = run(&["stokes", "--input", &s(&f), "--json"]);
    assert_eq!(c, 0, "{e}");
    assert!(t0.elapsed().as_secs() < 30, "{:?}", t0.elapsed());
    for (sig, code) in [("1e149", 0), ("1e160", 2)] {
        let g = d.path().join("big.csv");
        let rows: String = [0.0, 22.5, 45.0, 67.5].iter().map(|a| format!("{a},505000,495000,{sig},{sig}\n")).collect();
        std::fs::write(&g, format!("hwp_deg,f_o,f_e,sigma_o,sigma_e\n{rows}")).unwrap();
        let (c, _, e) = run(&["stokes", "--input", &s(&g), "--plot", &s(&d.path().join("big.png"))]);
        assert_eq!(c, code, "{sig}: {e}");
    }
}

/// A reader that closes the pipe (`instpol stokes ... | head -0`) ends the printing, not the
/// command: no "panicked at" message (println! panics on a closed pipe), exit 0, and the plot
/// the command was asked for is still written, with no temporary file left beside it. A
/// stdout that fails otherwise (a full disk: /dev/full) fails the command with exit 2.
#[test]
fn closed_stdout_ends_the_printing_not_the_command() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("good.csv");
    std::fs::write(&f, GOOD).unwrap();
    let png = d.path().join("f.png");
    let cases: [Vec<String>; 3] = [
        ["bias", "--p", "0.01", "--sigma", "0.005"].map(String::from).to_vec(),
        ["bias", "--p", "0.01", "--sigma", "0.005", "--json"].map(String::from).to_vec(),
        vec!["stokes".into(), "--input".into(), s(&f), "--plot".into(), s(&png)],
    ];
    for args in cases {
        // The read end is closed before the child starts, so its first write meets the closed
        // pipe whatever the scheduling (no race with a reader that exits "soon").
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let out = common::instpol().args(&args).stdout(writer).stderr(std::process::Stdio::piped()).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("panicked"), "{args:?}: {err}");
        assert_eq!(out.status.code(), Some(0), "{args:?}: {err}");
        let left: Vec<String> = common::listing(d.path()).into_iter().filter(|n| n.contains(".instpol-")).collect();
        assert!(left.is_empty(), "{args:?} left {left:?}");
    }
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"), "the plot was not written");
    let full = std::fs::OpenOptions::new().write(true).open("/dev/full");
    match full {
        Ok(full) => {
            let out = common::instpol()
                .args(["bias", "--p", "0.01", "--sigma", "0.005"])
                .stdout(full)
                .stderr(std::process::Stdio::piped())
                .output()
                .unwrap();
            let err = String::from_utf8_lossy(&out.stderr);
            assert_eq!(out.status.code(), Some(2), "{err}");
            assert!(err.contains("standard output") && !err.contains("panicked"), "{err}");
        }
        Err(e) => eprintln!("SKIPPED the full-stdout half: /dev/full cannot be opened ({e})"),
    }
}

/// No silent default instrument. Frames of an instrument that is no built-in one (`MINI`),
/// read without `--instrument` by every command that reads frames, are refused naming the
/// file, its `INSTRUME` and `--instrument` (they were read as FORS1 without a word); frames of
/// the built-in FORS1 are read as it, said on stderr, with the same numbers as with
/// `--instrument fors1`; a frame without `INSTRUME` is refused naming the keyword.
#[test]
fn frames_without_an_instrument_are_read_by_their_keyword_or_refused() {
    let d = tempfile::tempdir().unwrap();
    let (_, fr, map) = frames(d.path());
    let commands: Vec<Vec<String>> = vec![
        [&["reduce".to_string()][..], &fr, &["--out".into(), s(&d.path().join("m.fits"))]].concat(),
        [&["catalog".to_string()][..], &fr].concat(),
        [&["photometry".to_string()][..], &fr, &["--x".into(), "40".into(), "--y".into(), "30".into()]].concat(),
        vec![
            "calibrate".into(),
            "--map".into(),
            s(&map),
            "--sky-p".into(),
            "2".into(),
            "--sky-chi".into(),
            "0".into(),
            "--out".into(),
            s(&d.path().join("c.fits")),
        ],
        [&["master-bias".to_string()][..], &fr[..1], &["--out".into(), s(&d.path().join("b.fits"))]].concat(),
    ];
    for args in &commands {
        let (code, _, err) = run(args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(err.contains("INSTRUME = 'MINI'") && err.contains("--instrument"), "{args:?}: {err}");
    }
    // A frame without the keyword.
    let bare = d.path().join("bare.fits");
    {
        let mut f = fitsio::FitsFile::create(&bare).open().unwrap();
        let ph = f.primary_hdu().unwrap();
        ph.write_key(&mut f, "EXPTIME", 1.0).unwrap();
    }
    let (code, _, err) = run(&["catalog".to_string(), s(&bare)]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("no INSTRUME keyword") && err.contains("bare.fits"), "{err}");
    // The built-in FORS1's frames: read as it, said, the same numbers.
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/scenes/standard_V_corner.toml");
    let star = d.path().join("star");
    let (code, _, err) = run(&["simulate".to_string(), s(&scene), "--out".into(), s(&star)]);
    assert_eq!(code, 0, "{err}");
    let frames: Vec<String> = common::fits_in(&star).iter().map(|p| s(p)).collect();
    let cat = |extra: &[&str]| {
        let mut a = [&["catalog".to_string()][..], &frames].concat();
        a.extend(extra.iter().map(|x| x.to_string()));
        a.push("--json".into());
        run(&a)
    };
    let (c1, o1, e1) = cat(&[]);
    assert_eq!(c1, 0, "{e1}");
    assert!(e1.contains("read as the built-in instrument fors1 (INSTRUME = 'FORS1'"), "{e1}");
    let (c2, o2, e2) = cat(&["--instrument", "fors1"]);
    assert_eq!(c2, 0, "{e2}");
    assert!(!e2.contains("read as the built-in"), "{e2}");
    let (j1, j2) = (json(&o1), json(&o2));
    assert_eq!(j1["rows"], j2["rows"], "the same stars and numbers");
    assert_eq!(j1["product"]["instrument"], "FORS1");
}
