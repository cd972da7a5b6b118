//! A simulated archive night, end to end: `instpol scan` sorts it (every role, set, master and
//! problem), `instpol run` makes the same products as the units' commands run by hand in
//! order, byte for byte but for the provenance (its date, and the hashes of the products a
//! product was made from, which carry theirs); a run killed with SIGKILL at three
//! points and started again redoes no finished unit; `--jobs 2`, `--unit K` over every K and
//! GNU parallel give the same products; bad folders and nonsense plans are refused by name.
//!
//! The frames are written by `instpol simulate` (archive-like names, ESO DPR keywords through
//! the scene's `[output]`) for a FORS2 shrunk to 160 x 216 px (instruments/tiny_fors2.toml), so the
//! night of ~100 exposures is written and run in seconds.

use crate::common;

use common::night::{simulate_scene, Spec};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_instpol")
}

fn inst() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/tiny_fors2.toml")
}

fn instpol(args: &[&str]) -> std::process::Output {
    Command::new(bin()).args(args).output().expect("run instpol")
}

/// The instrument's radial pattern (percent, powers 0 to 3 of r in arcmin) in every frame.
use sim::night::PATTERN_PERCENT as PATTERN;

fn simulate(root: &Path, s: &Spec) {
    simulate_with(root, s, PATTERN)
}

fn simulate_with(root: &Path, s: &Spec, pattern: [f64; 4]) {
    simulate_scene(root, s, &inst(), pattern, "")
}

use sim::night::{HD110984, HD14069, HD64299, NIGHT_MJD as NIGHT, Q4};

/// The night of `sim::night::archive_night` (5 bias, 5 flats in each of 2 filters, 2 empty
/// fields per filter, 2 polarized and 2 unpolarized standards, a target at 16 angles observed
/// twice, an aborted set, another instrument's frames), the other instrument's cut to one
/// exposure, and a truncated file, a text file named .fits and a text file.
fn make_night(root: &Path) -> PathBuf {
    let specs = sim::night::archive_night();
    for s in &specs {
        simulate(root, s);
    }
    let raw = root.join("raw");
    // One exposure of the other instrument (its two chip files).
    let mut hawki: Vec<PathBuf> = std::fs::read_dir(raw.join("hawki"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "fits"))
        .collect();
    hawki.sort();
    for p in &hawki[2..] {
        std::fs::remove_file(p).unwrap();
    }
    // A truncated file: a bias chip file cut inside its data, under an archive name of its own.
    let b = std::fs::read(raw.join("bias/FORS2.2019-03-04T19:12:00.000_CHIP1.fits")).unwrap();
    std::fs::write(raw.join("FORS2.2019-03-04T23:59:00.000.fits"), &b[..b.len() / 2]).unwrap();
    std::fs::write(raw.join("README.fits"), "not a FITS file\n").unwrap();
    std::fs::write(raw.join("notes.txt"), "observing log\n").unwrap();
    raw
}

/// A product without its provenance (who made it when, from inputs with which hashes: a
/// product made from a master carries the master's hash, and the master its date), so that two
/// runs compare equal when every pixel, table value and other keyword is. FITS: every 80-byte
/// card `HISTORY` (the provenance's block, skyfield::provenance) or holding a date or a hash
/// (a product's `INHASHn`, its inputs' hashes) left out; JSON: the
/// `provenance` object left out; text: the lines naming a hash or a date left out.
fn unprovenanced(b: Vec<u8>) -> Vec<u8> {
    let dated = |l: &[u8]| {
        l.windows(7).any(|w| w == b"blake3:")
            || l.windows(6).any(|w| w == b"INHASH")
            || l.windows(19).any(|w| {
                w[4] == b'-' && w[7] == b'-' && w[10] == b'T' && w[13] == b':' && w[..4].iter().all(u8::is_ascii_digit)
            })
    };
    if b.starts_with(b"SIMPLE  =") {
        // Blank cards too: the header's padding to its 2880-byte block grows with the HISTORY
        // lines, whose count follows the length of the command line (the binary's full path
        // by hand, `instpol` for a unit run in process).
        let blank = |c: &[u8]| c.iter().all(|&x| x == b' ');
        return b
            .chunks(80)
            .filter(|c| !(c.starts_with(b"HISTORY ") || dated(c) || blank(c)))
            .flatten()
            .copied()
            .collect();
    }
    if let Ok(mut v) = serde_json::from_slice::<Value>(&b) {
        if let Some(o) = v.as_object_mut() {
            o.remove("provenance");
            // The inputs' hashes: of files stamped with their date (a calibration), each
            // compared above without its stamps.
            if let Some(p) = o.get_mut("product").and_then(Value::as_object_mut) {
                p.remove("inputs");
            }
        }
        return serde_json::to_vec(&v).unwrap();
    }
    b.split(|c| *c == b'\n').filter(|l| !dated(l)).flat_map(|l| l.iter().copied().chain([b'\n'])).collect()
}

fn outputs(plan: &Value) -> Vec<PathBuf> {
    plan["units"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|u| u["outputs"].as_array().unwrap().iter().map(|o| PathBuf::from(o.as_str().unwrap())))
        .collect()
}

/// Every output of the plan equals the reference copy in `hand` (paths under `products`).
fn same_as_hand(plan: &Value, products: &Path, hand: &Path, what: &str) {
    for o in outputs(plan) {
        let rel = o.strip_prefix(products).unwrap();
        let got = std::fs::read(&o).unwrap_or_else(|e| panic!("{what}: {} missing: {e}", o.display()));
        let want = std::fs::read(hand.join(rel)).unwrap();
        let (got, want) = (unprovenanced(got), unprovenanced(want));
        if got != want {
            let at = got.iter().zip(&want).position(|(a, b)| a != b).unwrap_or(got.len().min(want.len()));
            let show =
                |b: &[u8]| String::from_utf8_lossy(&b[at.saturating_sub(160)..(at + 80).min(b.len())]).to_string();
            panic!(
                "{what}: {} differs from the command run by hand at byte {at}:\n{}\n---\n{}",
                rel.display(),
                show(&got),
                show(&want)
            );
        }
    }
}

/// `instpol scan RAW --instrument INSTRUMENT --out PLAN` with the tiny FORS2's sizes: 8 px
/// bins, stars of 3 px FWHM measured in 4 px apertures.
fn scan_args(raw: &Path, instrument: &Path, plan: &Path) -> Vec<String> {
    let paths = [raw, instrument, plan].map(|p| p.to_str().unwrap().to_string());
    let [raw, instrument, plan] = paths;
    ["scan", &raw, "--instrument", &instrument, "--out", &plan, "--bin", "8", "--fwhm", "3", "--aperture", "4"]
        .map(String::from)
        .to_vec()
}

fn run_json(plan: &Path, extra: &[&str]) -> (bool, Value) {
    let mut args = vec!["run", plan.to_str().unwrap(), "--json"];
    args.extend(extra);
    let o = instpol(&args);
    let v: Value =
        serde_json::from_slice(&o.stdout).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&o.stderr)));
    (o.status.success(), v)
}

fn statuses(report: &Value) -> Vec<(String, String)> {
    report["outcomes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| (o["id"].as_str().unwrap().to_string(), o["status"].as_str().unwrap().to_string()))
        .collect()
}

#[test]
fn a_simulated_night_scanned_and_run() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let raw = make_night(root);
    let plan_path = root.join("night.toml");
    let products = root.join("products");
    let inst = inst();
    let mut args = scan_args(&raw, &inst, &plan_path);
    args.push("--json".into());
    for sky in ["EMPTY-V1:1.74:-53.8", "EMPTY-V2:1.74:-53.8", "EMPTY-I1:1.74:-53.8", "EMPTY-I2:1.74:-53.8"] {
        args.extend(["--sky".to_string(), sky.to_string()]);
    }
    let o = Command::new(bin()).args(&args).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let plan: Value = serde_json::from_slice(&o.stdout).unwrap();
    // The sky fields from a table instead: the same plan.
    let table = root.join("skies.csv");
    std::fs::write(
        &table,
        "target,p_percent,chi_deg\nEMPTY-V1,1.74,-53.8\nEMPTY-V2,1.74,-53.8\nEMPTY-I1,1.74,-53.8\nEMPTY-I2,1.74,-53.8\n",
    )
    .unwrap();
    let mut targs: Vec<String> = args.iter().take_while(|a| *a != "--sky").cloned().collect();
    targs.extend(["--sky-table".into(), table.display().to_string()]);
    let alt = root.join("alt.toml");
    let at = targs.iter().position(|a| a == "--out").unwrap() + 1;
    targs[at] = alt.display().to_string();
    let o = Command::new(bin()).args(&targs).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let from_table: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(from_table["units"], plan["units"]);
    std::fs::remove_file(&alt).unwrap();

    // Every role.
    let mut roles = std::collections::BTreeMap::<String, usize>::new();
    for f in plan["files"].as_array().unwrap() {
        *roles.entry(f["role"].as_str().unwrap().into()).or_default() += 1;
    }
    // Files (two chips each): 5 bias, 10 flats, 16 + 64 + 3 empty-field, target and aborted
    // exposures, 16 standard exposures.
    assert_eq!(roles.get("bias"), Some(&10));
    assert_eq!(roles.get("flat"), Some(&20));
    assert_eq!(roles.get("polarimetry"), Some(&(2 * (16 + 32 + 3))));
    assert_eq!(roles.get("standard"), Some(&32));
    // Every problem, named.
    let left: Vec<(Vec<String>, String)> = plan["left_out"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| {
            (
                l["files"].as_array().unwrap().iter().map(|f| f.as_str().unwrap().to_string()).collect(),
                l["why"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    let why_of = |name: &str| {
        left.iter()
            .find(|(f, _)| f.iter().any(|p| p.ends_with(name)))
            .map(|(_, w)| w.clone())
            .unwrap_or_else(|| panic!("{name} not left out: {left:?}"))
    };
    assert!(why_of("FORS2.2019-03-04T23:59:00.000.fits").starts_with("truncated"), "{}", why_of("T23:59:00.000.fits"));
    assert!(why_of("README.fits").contains("not a FITS file"));
    let hawki: Vec<_> = left.iter().filter(|(_, w)| w.contains("another instrument: INSTRUME = 'HAWKI'")).collect();
    assert_eq!(hawki.len(), 2, "{left:?}");
    let aborted = left.iter().find(|(_, w)| w.contains("NGC 5678")).expect("the aborted set");
    assert!(aborted.1.contains("incomplete") && aborted.1.contains("67.5 missing"), "{}", aborted.1);
    assert_eq!(aborted.0.len(), 6);
    assert!(!left.iter().any(|(f, _)| f.iter().any(|p| p.contains("notes.txt"))));

    // Every set and unit, with the right masters.
    let units = plan["units"].as_array().unwrap();
    let ids: Vec<&str> = units.iter().map(|u| u["id"].as_str().unwrap()).collect();
    let count = |k: &str| units.iter().filter(|u| u["kind"] == k).count();
    assert_eq!(
        (
            count("master-bias"),
            count("master-flat"),
            count("reduce"),
            count("catalog"),
            count("calibrate"),
            count("zero-angle"),
            count("validate")
        ),
        (1, 2, 9, 5, 4, 3, 4),
        "{ids:?}"
    );
    let unit = |id: &str| units.iter().find(|u| u["id"] == id).unwrap_or_else(|| panic!("no unit {id} in {ids:?}"));
    let target = unit("reduce-20190304-NGC_1234-v_HIGH");
    let cmd: Vec<&str> = target["command"].as_array().unwrap().iter().map(|c| c.as_str().unwrap()).collect();
    assert_eq!(
        cmd.iter().filter(|c| c.ends_with(".fits") && c.contains("/raw/")).count(),
        64,
        "two cycles of 16 angles, two chips each"
    );
    let flag = |c: &[&str], f: &str| c.iter().position(|x| *x == f).map(|i| c[i + 1].to_string());
    assert!(flag(&cmd, "--bias").unwrap().ends_with("masters/bias-20190304-2x2.fits"));
    assert!(flag(&cmd, "--flat").unwrap().ends_with("masters/flat-20190304-v_HIGH-2x2.fits"));
    let ei = unit("reduce-20190304-EMPTY-I1-I_BESS");
    let c: Vec<&str> = ei["command"].as_array().unwrap().iter().map(|c| c.as_str().unwrap()).collect();
    assert!(flag(&c, "--flat").unwrap().ends_with("masters/flat-20190304-I_BESS-2x2.fits"));
    assert_eq!(unit("calibrate-20190304-EMPTY-I1-I_BESS")["after"][0], "reduce-20190304-EMPTY-I1-I_BESS");
    // Standards by name and by position; the star's pixel from its position.
    let za: Vec<&str> = unit("zero-angle-20190304-STD-2-v_HIGH")["command"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_str().unwrap())
        .collect();
    assert_eq!(flag(&za, "--star").as_deref(), Some("HD 161056"));
    assert_eq!((flag(&za, "--x").as_deref(), flag(&za, "--y").as_deref()), (Some("79.50"), Some("57.50")));
    assert!(ids.contains(&"zero-angle-20190304-HD110984-v_HIGH"));
    assert!(ids.contains(&"catalog-20190304-HD_14069-v_HIGH") && ids.contains(&"catalog-20190304-HD64299-I_BESS"));
    assert!(!ids.iter().any(|i| i.contains("zero-angle") && i.contains("HD") && i.contains("14069")));
    // The night's checks: each standard against its filter's calibration nearest in time
    // (the second empty field of each filter was taken closer to the standards), and the
    // zero angle of the night in v_HIGH from its two polarized standards.
    let words = |id: &str| -> Vec<String> {
        unit(id)["command"].as_array().unwrap().iter().map(|c| c.as_str().unwrap().to_string()).collect()
    };
    for (set, cal) in [
        ("HD110984-v_HIGH", "EMPTY-V2-v_HIGH"),
        ("STD-2-v_HIGH", "EMPTY-V2-v_HIGH"),
        ("HD_14069-v_HIGH", "EMPTY-V2-v_HIGH"),
        ("HD64299-I_BESS", "EMPTY-I2-I_BESS"),
    ] {
        let id = format!("validate-20190304-{set}");
        let v = words(&id);
        let v: Vec<&str> = v.iter().map(|x| x.as_str()).collect();
        assert!(flag(&v, "--cal").unwrap().ends_with(&format!("calibrations/20190304-{cal}.fits")), "{id}: {v:?}");
        assert_eq!(unit(&id)["check"], true);
        assert!(unit(&id)["after"].as_array().unwrap().iter().any(|a| a == &format!("calibrate-20190304-{cal}")));
    }
    let night_za = words("zero-angle-20190304-v_HIGH-night");
    let measured: Vec<&String> = night_za.windows(2).filter(|w| w[0] == "--measured").map(|w| &w[1]).collect();
    assert_eq!(measured.len(), 2, "{night_za:?}");
    assert!(measured.iter().all(|m| m.contains("/zero-angle/20190304-")), "{night_za:?}");

    // The commands by hand, in the plan's order, into products; kept as the reference.
    let hand = root.join("hand");
    for u in units {
        let c: Vec<&str> = u["command"].as_array().unwrap().iter().map(|c| c.as_str().unwrap()).collect();
        for o in u["outputs"].as_array().unwrap() {
            std::fs::create_dir_all(Path::new(o.as_str().unwrap()).parent().unwrap()).unwrap();
        }
        let o = instpol(&c);
        // A check unit's exit status 1 is its check not passing: a result (run reports it).
        let check_ran = u["check"] == true && o.status.code() == Some(1);
        assert!(o.status.success() || check_ran, "{}: {}", u["id"], String::from_utf8_lossy(&o.stderr));
        if u["stdout"] == true {
            std::fs::write(u["outputs"][0].as_str().unwrap(), &o.stdout).unwrap();
        }
    }
    std::fs::rename(&products, &hand).unwrap();

    // run --jobs 2: the same products; a second run does nothing.
    let t0 = std::time::Instant::now();
    let (ok, report) = run_json(&plan_path, &["--jobs", "2"]);
    let full = t0.elapsed();
    assert!(ok, "{report}");
    assert!(statuses(&report).iter().all(|(_, s)| s == "done"), "{report}");
    same_as_hand(&plan, &products, &hand, "run --jobs 2");
    let (ok, report) = run_json(&plan_path, &[]);
    assert!(ok && statuses(&report).iter().all(|(_, s)| s == "up_to_date"), "{report}");
    // Every record's hashes are the files' BLAKE3 hashes, whether the command reported them
    // (the inputs it read) or the runner computed them.
    let mut n_checked = 0;
    for rec in std::fs::read_dir(products.join(".instpol-run")).unwrap() {
        let rec = rec.unwrap().path();
        if rec.extension().is_none_or(|e| e != "json") {
            continue;
        }
        let r: Value = serde_json::from_slice(&std::fs::read(&rec).unwrap()).unwrap();
        // What the unit's products are of: the night's instrument (its definition's BLAKE3)
        // in the unit's filter.
        let id = rec.file_stem().unwrap().to_string_lossy().into_owned();
        let unit = plan["units"].as_array().unwrap().iter().find(|u| u["id"] == id.as_str()).unwrap();
        assert_eq!(r["product"]["instrument"], plan["product"]["instrument"], "{id}");
        let def = format!("blake3:{}", blake3::hash(&std::fs::read(&inst).unwrap()).to_hex());
        assert_eq!(r["product"]["instrument_hash"], def.as_str(), "{id}");
        assert_eq!(r["product"]["filter"], unit.get("filter").cloned().unwrap_or(Value::Null), "{id}");
        for pair in r["inputs"].as_array().unwrap().iter().chain(r["outputs"].as_array().unwrap()) {
            let (path, hash) = (pair[0].as_str().unwrap(), pair[1].as_str().unwrap());
            let bytes = std::fs::read(path).unwrap();
            assert_eq!(hash, format!("blake3:{}", blake3::hash(&bytes).to_hex()), "{}: {path}", rec.display());
            n_checked += 1;
        }
    }
    assert!(n_checked > 200, "{n_checked}");
    // A frame touched (its time changed, its bytes not) is hashed again and still up to date;
    // a frame changed in place runs what reads it.
    let frame = PathBuf::from(target["inputs"][0].as_str().unwrap());
    let t = std::fs::metadata(&frame).unwrap().modified().unwrap();
    std::fs::File::options()
        .write(true)
        .open(&frame)
        .unwrap()
        .set_modified(t + std::time::Duration::from_secs(5))
        .unwrap();
    let (ok, report) = run_json(&plan_path, &["--dry-run"]);
    assert!(ok && statuses(&report).iter().all(|(_, s)| s == "up_to_date"), "{report}");
    let original = std::fs::read(&frame).unwrap();
    let mut changed = original.clone();
    let last = changed.len() - 1;
    changed[last] ^= 1;
    std::fs::write(&frame, &changed).unwrap();
    let (_, report) = run_json(&plan_path, &["--dry-run"]);
    for u in units {
        let reads = u["inputs"].as_array().unwrap().iter().any(|i| i.as_str() == frame.to_str());
        let st = statuses(&report).into_iter().find(|(i, _)| u["id"] == i.as_str()).unwrap().1;
        assert_eq!(st, if reads { "would_run" } else { "up_to_date" }, "{}", u["id"]);
    }
    std::fs::write(&frame, &original).unwrap();

    // Killed (SIGKILL) at three points, after 1, a third and two thirds of the units had
    // finished, then started again: no finished unit is redone.
    let records = products.join(".instpol-run");
    // A unit's record is `<id>.json`; a running unit's input-hash report sits beside them as a
    // hidden `.<id>.hashes-<pid>.json` until it finishes (counted once as a record: the run
    // was killed with 19 of 20 units done).
    let is_record = |n: &str| n.ends_with(".json") && !n.starts_with('.');
    let n_records = || {
        std::fs::read_dir(&records).map_or(0, |rd| {
            rd.filter(|e| e.as_ref().is_ok_and(|e| is_record(&e.file_name().to_string_lossy()))).count()
        })
    };
    for at in [1, units.len() / 3, 2 * units.len() / 3] {
        let frac = format!("{at} unit(s)");
        std::fs::remove_dir_all(&products).unwrap();
        let mut child = Command::new(bin())
            .args(["run", plan_path.to_str().unwrap()])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let t = std::time::Instant::now();
        while n_records() < at && t.elapsed() < full * 20 {
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        assert!(n_records() >= at, "{} units finished, waiting for {at}", n_records());
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        let finished: Vec<String> = std::fs::read_dir(&records)
            .map(|rd| {
                rd.filter_map(|e| {
                    let n = e.unwrap().file_name().to_string_lossy().to_string();
                    is_record(&n).then(|| n.strip_suffix(".json").unwrap_or(&n).to_string())
                })
                .collect()
            })
            .unwrap_or_default();
        let (ok, report) = run_json(&plan_path, &[]);
        assert!(ok, "{report}");
        for (id, s) in statuses(&report) {
            if finished.contains(&id) {
                assert_eq!(s, "up_to_date", "killed after {frac}: {id} finished before the kill but was run again");
            } else {
                assert_eq!(s, "done", "killed after {frac}: {id}");
            }
        }
        assert!(
            finished.len() >= at && finished.len() < units.len(),
            "killed after {frac}: {} of {} units had finished",
            finished.len(),
            units.len()
        );
        same_as_hand(&plan, &products, &hand, &format!("killed after {frac} and run again"));
    }

    // --unit K over every K, one after another.
    std::fs::remove_dir_all(&products).unwrap();
    for id in &ids {
        let (ok, report) = run_json(&plan_path, &["--unit", id]);
        assert!(ok, "{report}");
        let st = statuses(&report);
        assert_eq!(st.last().map(|(i, s)| (i.as_str(), s.as_str())), Some((*id, "done")), "{report}");
    }
    same_as_hand(&plan, &products, &hand, "--unit K over every K");

    // GNU parallel over the plan's units.
    std::fs::remove_dir_all(&products).unwrap();
    let sh = format!("{b} run {p} --list | parallel -j 3 {b} run {p} --unit {{}}", b = bin(), p = plan_path.display());
    let o = Command::new("sh").args(["-c", &sh]).output().expect("sh");
    assert!(o.status.success(), "GNU parallel (Debian package parallel): {}", String::from_utf8_lossy(&o.stderr));
    same_as_hand(&plan, &products, &hand, "GNU parallel");

    // A plan as JSON is the same plan.
    let json_plan = root.join("night.json");
    let o = instpol(&["run", plan_path.to_str().unwrap(), "--list"]);
    assert!(o.status.success());
    let text = std::fs::read_to_string(&plan_path).unwrap();
    let as_value: toml::Value = toml::from_str(&text).unwrap();
    std::fs::write(&json_plan, serde_json::to_string(&as_value).unwrap()).unwrap();
    let (ok, report) = run_json(&json_plan, &["--dry-run"]);
    assert!(ok && statuses(&report).iter().all(|(_, s)| s == "up_to_date"), "{report}");

    // The standards passed their checks; a check made impossible (a threshold of 0.01 sigma)
    // does not pass: its output is kept, the run says so with exit status 1, and a second run
    // skips it and says so again.
    for u in units.iter().filter(|u| u["kind"] == "validate") {
        let v: Value = serde_json::from_slice(&std::fs::read(u["outputs"][0].as_str().unwrap()).unwrap()).unwrap();
        assert_eq!(v["pass"], true, "{}: {v}", u["id"]);
    }
    let mut strict = serde_json::to_value(&as_value).unwrap();
    let id = "validate-20190304-HD110984-v_HIGH";
    let vu = strict["units"].as_array_mut().unwrap().iter_mut().find(|u| u["id"] == id).unwrap();
    vu["command"].as_array_mut().unwrap().extend(["--threshold".into(), "0.01".into()]);
    let strict_plan = root.join("strict.json");
    std::fs::write(&strict_plan, serde_json::to_string(&strict).unwrap()).unwrap();
    for pass in ["ran", "recorded"] {
        let (ok, report) = run_json(&strict_plan, &["--unit", id]);
        assert!(!ok, "{pass}: a check that did not pass exits with 1: {report}");
        let last = report["outcomes"].as_array().unwrap().last().unwrap().clone();
        assert_eq!(
            (last["id"].as_str(), last["status"].as_str()),
            (Some(id), Some("check_failed")),
            "{pass}: {report}"
        );
        let out = vu_output(&strict, id);
        let v: Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
        assert_eq!(v["pass"], false, "{pass}: {v}");
    }
    // A Cassegrain instrument's standard gives no parallactic angle: not a point of the
    // telescope fit, refused naming the file.
    let phot = vu_output(&strict, "photometry-20190304-HD_14069-v_HIGH");
    let o = instpol(&["fit-standards", phot.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("HD_14069-v_HIGH.json") && err.contains("no parallactic angle"), "{err}");
}

fn vu_output(plan: &Value, id: &str) -> PathBuf {
    let u = plan["units"].as_array().unwrap().iter().find(|u| u["id"] == id).unwrap();
    PathBuf::from(u["outputs"][0].as_str().unwrap())
}

#[test]
fn bad_folders_and_nonsense_plans_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let inst = inst();
    let scan = |folder: &Path, out: &Path| {
        instpol(&[
            "scan",
            folder.to_str().unwrap(),
            "--instrument",
            inst.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
    };
    let plan = d.join("p.toml");
    let empty = d.join("empty");
    std::fs::create_dir(&empty).unwrap();
    let o = scan(&empty, &plan);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2));
    assert!(e.contains("empty") && e.contains("no FITS file"), "{e}");
    let texts = d.join("texts");
    std::fs::create_dir(&texts).unwrap();
    std::fs::write(texts.join("a.txt"), "x").unwrap();
    std::fs::write(texts.join("b.csv"), "x").unwrap();
    let o = scan(&texts, &plan);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("texts") && e.contains("no FITS file") && e.contains("2 files"), "{e}");
    assert!(!plan.exists());
    // A sky field with a negative degree of polarization, given or in a table.
    let o = instpol(&[
        "scan",
        texts.to_str().unwrap(),
        "--instrument",
        inst.to_str().unwrap(),
        "--out",
        plan.to_str().unwrap(),
        "--sky",
        "EMPTY:-1.74:30",
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(2) && e.contains("sky field EMPTY") && e.contains("[0, 100)"), "{e}");
    let skies = d.join("skies.csv");
    std::fs::write(&skies, "target,p_percent,chi_deg\nA,1.0,10\nB,150,10\n").unwrap();
    let o = instpol(&[
        "scan",
        texts.to_str().unwrap(),
        "--instrument",
        inst.to_str().unwrap(),
        "--out",
        plan.to_str().unwrap(),
        "--sky-table",
        skies.to_str().unwrap(),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(2) && e.contains("skies.csv") && e.contains("sky field B"), "{e}");
    assert!(!plan.exists());
    // An unreadable file (a link to nothing: root reads any file) is left out with its reason.
    let odd = d.join("odd");
    std::fs::create_dir(&odd).unwrap();
    std::os::unix::fs::symlink(d.join("nowhere.fits"), odd.join("gone.fits")).unwrap();
    std::fs::write(odd.join("text.fits"), "SIMPLE = nonsense").unwrap();
    let o = instpol(&[
        "scan",
        odd.to_str().unwrap(),
        "--instrument",
        inst.to_str().unwrap(),
        "--out",
        plan.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: Value = serde_json::from_slice(&o.stdout).unwrap();
    let whys: Vec<&str> = v["left_out"].as_array().unwrap().iter().map(|l| l["why"].as_str().unwrap()).collect();
    assert!(whys.iter().any(|w| w.starts_with("unreadable")), "{whys:?}");
    assert!(whys.iter().any(|w| w.contains("not a FITS file")), "{whys:?}");
    // An instrument without [headers].
    let o = instpol(&["scan", odd.to_str().unwrap(), "--instrument", "fors1", "--out", plan.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("[headers]"));

    // Nonsense plans: refused naming the unit and the file, nothing written.
    let frame = d.join("frame.fits");
    std::fs::write(&frame, "raw").unwrap();
    let products = d.join("products");
    let unit = |id: &str, kind: &str, input: &Path, out: &Path, after: &str| {
        format!(
            "[[units]]\nid = {id:?}\nkind = {kind:?}\ninputs = [{:?}]\noutputs = [{:?}]\ncommand = [{kind:?}, {:?}, \"--out\", {:?}]\nafter = [{after}]\n",
            input.display().to_string(),
            out.display().to_string(),
            input.display().to_string(),
            out.display().to_string()
        )
    };
    let head = format!(
        "version = 1\ninstrument = \"fors2\"\nrecords = {:?}\n",
        products.join(".instpol-run").display().to_string()
    );
    let a = products.join("a.fits");
    let b = products.join("b.fits");
    // The frame under other names: spelled otherwise, and a hard link; a file a command names
    // (an instrument file) that is no unit's listed input.
    std::fs::create_dir_all(d.join("sub")).unwrap();
    let spelled = d.join("sub").join("..").join("frame.fits");
    let linked = d.join("linked.fits");
    std::fs::hard_link(&frame, &linked).unwrap();
    let inst_file = d.join("inst.toml");
    std::fs::write(&inst_file, "not read").unwrap();
    // Unit A's command names the instrument file besides its listed input.
    let inst_arg = format!("\"--instrument\", {:?}, \"--out\"", inst_file.display().to_string());
    let names_inst = unit("A", "reduce", &frame, &a, "").replace("\"--out\"", &inst_arg);
    let over_inst = names_inst + &unit("B", "reduce", &frame, &inst_file, "");
    let cases = [
        (
            "a cycle",
            format!("{head}{}{}", unit("A", "reduce", &b, &a, "\"B\""), unit("B", "reduce", &a, &b, "\"A\"")),
            "cycle",
        ),
        (
            "a missing input",
            format!("{head}{}", unit("A", "reduce", &d.join("nothing.fits"), &a, "")),
            "nothing.fits does not exist",
        ),
        (
            "an unknown kind",
            format!("{head}{}", unit("A", "transmogrify", &frame, &a, "")),
            "unknown kind 'transmogrify'",
        ),
        (
            "output over its input",
            format!("{head}{}", unit("A", "reduce", &frame, &frame, "")),
            "refusing to write over an input",
        ),
        (
            "output over another's input",
            format!("{head}{}{}", unit("A", "reduce", &frame, &a, ""), unit("B", "reduce", &a, &frame, "\"A\"")),
            "refusing to write over an input",
        ),
        (
            "output over its input spelled otherwise",
            format!("{head}{}", unit("A", "reduce", &frame, &spelled, "")),
            "under another name",
        ),
        (
            "output over a hard link of an input",
            format!("{head}{}", unit("A", "reduce", &frame, &linked, "")),
            "under another name",
        ),
        ("output over a file a command names", format!("{head}{over_inst}"), "inst.toml is"),
    ];
    for (what, text, says) in cases {
        let p = d.join("bad.toml");
        std::fs::write(&p, &text).unwrap();
        let o = instpol(&["run", p.to_str().unwrap()]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{what}: {e}");
        assert!(e.contains("bad.toml") && e.contains("unit ") && e.contains(says), "{what}: {e}");
        assert!(!products.exists(), "{what}: something was written");
        assert_eq!(std::fs::read_to_string(&frame).unwrap(), "raw");
        assert_eq!(std::fs::read_to_string(&inst_file).unwrap(), "not read");
    }
    let o = instpol(&["run", d.join("none.toml").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    let p = d.join("bad.toml");
    std::fs::write(&p, "version = 1\nunits = 3\n").unwrap();
    let o = instpol(&["run", p.to_str().unwrap()]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("bad.toml"));
}

/// Twelve monthly nights (bias, flats, the polarized standard HD 110984 at 4 angles, the
/// unpolarized HD 14069 at 16 angles twice, an empty field of known sky polarization),
/// scanned and run; with `steps`, from the seventh month on the zero angle moves by 1.5 deg
/// (the star's angle turned), the unpolarized standard shows 0.1 % along q (an instrumental
/// polarization) and the empty field's instrumental pattern is 20 % stronger (only its frames
/// carry the change, so that each series has one step of its own). The plans, in month order.
fn twelve_months(root: &Path, steps: bool, seed: u64) -> Vec<PathBuf> {
    let mut plans = Vec::new();
    for m in 0..12u64 {
        let dir = root.join(format!("m{m:02}"));
        std::fs::create_dir_all(&dir).unwrap();
        let night = NIGHT + 30.0 * m as f64;
        let after = steps && m >= 6;
        let s = seed + 100 * m;
        let std = |(ra, dec): (f64, f64)| (ra, dec + 50.0 / 3600.0);
        let a16: Vec<f64> = (0..16).map(|i| i as f64 * 22.5).collect();
        let unpol = vec![(79.5, 57.5, 6e5, if after { 0.001 } else { 0.0 }, 0.0)];
        let specs = vec![
            Spec::bias(vec![0.0, 22.5, 45.0, 67.5, 90.0], night + 0.80, s + 1),
            Spec::sky_flat("flat", "v_HIGH", Q4.to_vec(), night + 0.81, 11, s + 2),
            Spec {
                dir: "pol",
                filter: "v_HIGH",
                angles: Q4.to_vec(),
                start_mjd: night + 0.85,
                first_exp: 21,
                dpr: ["CALIB", "STD", "POLARIMETRY"],
                target: "HD110984",
                ra_dec: std(HD110984),
                sky: Some((100.0, 0.0, 0.0)),
                stars: vec![(79.5, 57.5, 6e5, 0.057, 91.65 + if after { 1.5 } else { 0.0 })],
                instrume: None,
                seed: s + 3,
            },
            Spec {
                dir: "unpol1",
                filter: "v_HIGH",
                angles: a16.clone(),
                start_mjd: night + 0.87,
                first_exp: 31,
                dpr: ["CALIB", "STD", "POLARIMETRY"],
                target: "HD 14069",
                ra_dec: std(HD14069),
                sky: Some((100.0, 0.0, 0.0)),
                stars: unpol.clone(),
                instrume: None,
                seed: s + 4,
            },
            Spec {
                dir: "unpol2",
                filter: "v_HIGH",
                angles: a16,
                start_mjd: night + 0.882,
                first_exp: 51,
                dpr: ["CALIB", "STD", "POLARIMETRY"],
                target: "HD 14069",
                ra_dec: std(HD14069),
                sky: Some((100.0, 0.0, 0.0)),
                stars: unpol,
                instrume: None,
                seed: s + 5,
            },
        ];
        for sp in &specs {
            simulate(&dir, sp);
        }
        let empty = Spec {
            dir: "empty",
            filter: "v_HIGH",
            angles: Q4.to_vec(),
            start_mjd: night + 0.83,
            first_exp: 71,
            dpr: ["SCIENCE", "OBJECT", "POLARIMETRY"],
            target: "EMPTY-V",
            ra_dec: (150.0, -30.0),
            sky: Some((3000.0, 0.0174, -53.8)),
            stars: vec![],
            instrume: None,
            seed: s + 6,
        };
        simulate_with(&dir, &empty, if after { PATTERN.map(|c| 1.2 * c) } else { PATTERN });
        let plan = dir.join("night.toml");
        let mut args = scan_args(&dir.join("raw"), &inst(), &plan);
        args.extend(["--sky".into(), "EMPTY-V:1.74:-53.8".into()]);
        let o = Command::new(bin()).args(&args).output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let (ok, report) = run_json(&plan, &["--jobs", "2"]);
        assert!(ok, "month {m}: {report}");
        plans.push(plan);
    }
    plans
}

fn trend_json(root: &Path, plans: &[PathBuf]) -> Value {
    let out = root.join("trend.ecsv");
    let png = root.join("trend.png");
    let mut args = vec!["trend".to_string()];
    args.extend(plans.iter().map(|p| p.display().to_string()));
    args.extend(["--out", out.to_str().unwrap(), "--plot", png.to_str().unwrap(), "--json"].map(String::from));
    let o = Command::new(bin()).args(&args).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.is_file() && png.is_file());
    serde_json::from_slice(&o.stdout).unwrap()
}

#[test]
fn trend_over_twelve_months_finds_the_steps_and_only_them() {
    let dir = tempfile::tempdir().unwrap();
    let with = dir.path().join("with");
    let plans = twelve_months(&with, true, 7);
    let t = trend_json(&with, &plans);
    let step = |q: &str| {
        t["steps"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["quantity"] == q)
            .unwrap_or_else(|| panic!("no {q} series: {t}"))
            .clone()
    };
    let month7 = NIGHT + 180.0;
    // The pattern's P at the edge: the mean over the sides' midpoints of the tiny FORS2
    // (2.6667' x 3.6': r = 1.3333' and 1.8') of 0.1 r + 0.3 r^2 + 0.05 r^3 percent, times 0.2.
    let pat = |r: f64| (PATTERN[1] * r + PATTERN[2] * r * r + PATTERN[3] * r * r * r) / 100.0;
    let edge_step = 0.2 * (pat(2.6667 / 2.0) + pat(1.8)) / 2.0;
    for (q, size) in [("zero_angle_deg", 1.5), ("q_unpolarized", 0.001), ("p_field_edge", edge_step)] {
        let s = step(q);
        assert_eq!(s["flagged"], true, "{q}: {s}");
        assert!(
            s["first_after_mjd"].as_f64().unwrap() > month7 && s["first_after_mjd"].as_f64().unwrap() < month7 + 1.0,
            "{q}: {s}"
        );
        assert_eq!((s["n_before"].as_u64(), s["n_after"].as_u64()), (Some(6), Some(6)), "{q}: {s}");
        let (d, sd) = (s["delta"].as_f64().unwrap(), s["sigma_delta"].as_f64().unwrap());
        assert!((d.abs() - size).abs() < 3.0 * sd + 0.1 * size, "{q}: delta {d} +- {sd}, expected {size} in size");
    }
    // u saw nothing, nor the polarized standard's P against its catalogued value (only its
    // angle moved).
    assert_eq!(step("u_unpolarized")["flagged"], false, "{t}");
    assert_eq!(step("p_minus_catalogue")["flagged"], false, "{t}");
    // The star was simulated at its catalogued V value, 5.70 %: what the measurement adds is the
    // instrument's pattern where it sits, 50" below the centre (0.1 r + 0.3 r^2 + 0.05 r^3 % at
    // r = 0.833': 0.32 %) and the noise, so every point lies within 0.32 % and 4 sigma of it.
    for p in t["points"].as_array().unwrap().iter().filter(|p| p["quantity"] == "p_minus_catalogue") {
        let (v, e) = (p["value"].as_f64().unwrap(), p["sigma"].as_f64().unwrap());
        assert!(v.abs() < 0.0032 + 4.0 * e, "{p}");
    }
    assert_eq!(t["points"].as_array().unwrap().len(), 12 * 6);
    // The report of the twelve nights: the three simulated steps flagged in four series (the
    // unpolarized standard's P moves with its q), as trend flags them, and no other.
    let out = with.join("report");
    let mut args = vec!["report".to_string()];
    args.extend(plans.iter().map(|p| p.display().to_string()));
    args.extend(["--out", out.to_str().unwrap(), "--json"].map(String::from));
    let o = Command::new(bin()).args(&args).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    let flagged = t["steps"].as_array().unwrap().iter().filter(|s| s["flagged"] == true).count();
    assert_eq!(step("p_unpolarized")["flagged"], true, "{t}");
    assert_eq!((r["nights"].as_u64(), r["trend_flagged"].as_u64()), (Some(12), Some(4)), "{r}");
    assert_eq!(flagged, 4, "{t}");
    crate::report::check_static(&out);
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    assert_eq!(html.matches(" flagged</td>").count(), 4, "the page shows the four steps flagged");

    let without = dir.path().join("without");
    let plans = twelve_months(&without, false, 11);
    let t = trend_json(&without, &plans);
    for s in t["steps"].as_array().unwrap() {
        assert_eq!(s["flagged"], false, "a step where none was simulated: {s}");
    }
}

/// The night of [`a_simulated_night_scanned_and_run`] written into `$INSTPOL_NIGHT_DIR/raw`
/// for `bench/run_plan.sh` (run only on demand: `--ignored`).
#[test]
#[ignore]
fn write_night_for_bench() {
    let dir = PathBuf::from(std::env::var("INSTPOL_NIGHT_DIR").expect("set INSTPOL_NIGHT_DIR"));
    std::fs::create_dir_all(&dir).unwrap();
    make_night(&dir);
}

/// Behind a Nasmyth telescope (the tiny FORS2 given EFOSC2's `[telescope]`: an aluminium M3
/// at 45 deg, parallactic angles in the headers), the plan measures every standard, polarized
/// ones too, by photometry with its name and fits the telescope model to them per night and
/// filter; the fit finds the simulated mirror (Wiersema et al. 2018's model: factor 0.86 on
/// aluminium's n, k, offset 40 deg) within its errors, and `trend` reads its parameters.
#[test]
fn a_nasmyth_night_fits_its_telescope_model() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let efosc2 = include_str!("../../../../instruments/efosc2.toml");
    let tel = &efosc2[efosc2.find("[telescope]").unwrap()..efosc2.find("# How the headers say").unwrap()];
    let nasmyth = root.join("tiny_nasmyth.toml");
    std::fs::write(&nasmyth, std::fs::read_to_string(inst()).unwrap() + "\n" + tel).unwrap();
    let std_at = |(ra, dec): (f64, f64)| (ra, dec + 50.0 / 3600.0);
    // Two unpolarized standards at two hour angles each, and a polarized one (its V values):
    // sets 72 min apart, each its own.
    let stars: [(&str, (f64, f64), f64, f64, f64); 5] = [
        ("HD 14069", HD14069, 0.0, 0.0, -50.0),
        ("HD 14069", HD14069, 0.0, 0.0, 40.0),
        ("HD64299", HD64299, 0.0, 0.0, -30.0),
        ("HD64299", HD64299, 0.0, 0.0, 25.0),
        ("HD110984", HD110984, 0.057, 91.65, 10.0),
    ];
    for (k, (name, pos, p, chi, ha)) in stars.iter().enumerate() {
        let spec = Spec {
            dir: ["s0", "s1", "s2", "s3", "s4"][k],
            filter: "v_HIGH",
            angles: Q4.to_vec(),
            start_mjd: NIGHT + 0.80 + 0.05 * k as f64,
            first_exp: 1 + 10 * k as i64,
            dpr: ["CALIB", "STD", "POLARIMETRY"],
            target: name,
            ra_dec: std_at(*pos),
            sky: Some((100.0, 0.0, 0.0)),
            stars: vec![(79.5, 57.5, 6e5, *p, *chi)],
            instrume: None,
            seed: 60 + k as u64,
        };
        // The plate's zero angle of v_HIGH (an [effects] key: the text follows that table),
        // which photometry adds back to reach the sky frame of the telescope model.
        let telescope = format!(
            "hwp_chi_offset_from_filter = true\n[telescope]\nmetal = \"aluminium\"\nfactor = 0.86\noffset_deg = 40\ndec_deg = {}\nha_start_deg = {ha}\n",
            pos.1
        );
        simulate_scene(root, &spec, &nasmyth, [0.0; 4], &telescope);
    }
    let plan_path = root.join("night.json");
    let o = Command::new(bin()).args(scan_args(&root.join("raw"), &nasmyth, &plan_path)).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let plan: Value = serde_json::from_slice(&std::fs::read(&plan_path).unwrap()).unwrap();
    let units = plan["units"].as_array().unwrap();
    let of = |k: &str| units.iter().filter(|u| u["kind"] == k).collect::<Vec<_>>();
    assert_eq!((of("photometry").len(), of("zero-angle").len(), of("fit-standards").len()), (5, 1, 1), "{plan}");
    let fs = of("fit-standards")[0];
    assert_eq!(fs["id"], "fit-standards-20190304-v_HIGH-night");
    assert_eq!(fs["inputs"].as_array().unwrap().len(), 5);
    let (ok, report) = run_json(&plan_path, &["--jobs", "2"]);
    assert!(ok, "{report}");

    // Each photometry output records its star and the middle of its parallactic track.
    for u in of("photometry") {
        let v: Value = serde_json::from_slice(&std::fs::read(u["outputs"][0].as_str().unwrap()).unwrap()).unwrap();
        assert_eq!(v["star"], u["standard"], "{v}");
        assert!(v["parallactic_deg"].as_f64().is_some_and(f64::is_finite), "{v}");
    }
    let fits: Value = serde_json::from_slice(&std::fs::read(fs["outputs"][0].as_str().unwrap()).unwrap()).unwrap();
    let par = |name: &str| {
        let p = fits[0]["params"].as_array().unwrap().iter().find(|p| p["name"] == name).unwrap().clone();
        (p["value"].as_f64().unwrap(), p["sigma_value"].as_f64().unwrap())
    };
    for (name, truth) in [("factor", 0.86), ("offset", 40.0)] {
        let (v, e) = par(name);
        assert!((v - truth).abs() < 3.0 * e + 1e-6, "{name}: {v} +- {e}, simulated {truth}: {fits}");
    }
    let t = trend_json(root, &[plan_path]);
    let points = t["points"].as_array().unwrap();
    for q in ["telescope_factor", "telescope_offset_deg"] {
        assert_eq!(points.iter().filter(|p| p["quantity"] == q).count(), 1, "{q}: {t}");
    }
    // The polarized standard's photometry is no point of the instrument's own polarization.
    assert_eq!(points.iter().filter(|p| p["quantity"] == "q_unpolarized").count(), 4, "{t}");
}

/// A small night of the shrunk FORS2 (biases, sky flats, an empty field of known sky
/// polarization at four angles) simulated through the instrument file `instrument` into
/// `root/raw`, its sky field in `root/skies.csv`.
fn small_night(root: &Path, instrument: &Path) {
    let specs = [
        Spec::bias(vec![0.0, 22.5, 45.0], NIGHT + 0.80, 1),
        Spec::sky_flat("flat", "v_HIGH", Q4.to_vec(), NIGHT + 0.81, 11, 2),
        Spec {
            dir: "empty",
            filter: "v_HIGH",
            angles: Q4.to_vec(),
            start_mjd: NIGHT + 0.83,
            first_exp: 21,
            dpr: ["SCIENCE", "OBJECT", "POLARIMETRY"],
            target: "EMPTY-V",
            ra_dec: (150.0, -30.0),
            sky: Some((3000.0, 0.0174, -53.8)),
            stars: vec![],
            instrume: None,
            seed: 3,
        },
    ];
    for s in &specs {
        simulate_scene(root, s, instrument, PATTERN, "");
    }
    std::fs::write(root.join("skies.csv"), "target,p_percent,chi_deg\nEMPTY-V,1.74,-53.8\n").unwrap();
}

/// `scan_args` with the small night's sky table; the plan as JSON.
fn scan_small(root: &Path, instrument: &Path, plan: &Path) -> Value {
    let mut a = scan_args(&root.join("raw"), instrument, plan);
    a.extend(["--sky-table".to_string(), root.join("skies.csv").display().to_string()]);
    let a: Vec<&str> = a.iter().map(String::as_str).collect();
    let o = instpol(&a);
    assert!(o.status.success(), "scan: {}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_str(&std::fs::read_to_string(plan).unwrap()).unwrap()
}

/// A file reached under several names (a copy, a hard link, a symlink, a folder linked twice, a
/// symlink loop back to the night's root) is one file to `scan`: the plan's units are those of
/// the night without the extra names, and every extra name is listed as left out naming the
/// file it repeats.
#[test]
fn scan_reads_a_file_once_whatever_its_names() {
    let d = tempfile::tempdir().unwrap();
    let root = d.path();
    small_night(root, &inst());
    // Each unit's id and command, a file of the raw folder by its content (of two names of one
    // file, either may be the one kept).
    let raw = root.join("raw");
    let units = |plan: &Value| -> Vec<(String, Vec<String>)> {
        let arg = |a: &Value| {
            let a = a.as_str().unwrap();
            let p = Path::new(a);
            if p.starts_with(&raw) && p.is_file() {
                blake3::hash(&std::fs::read(p).unwrap()).to_hex().to_string()
            } else {
                a.to_string()
            }
        };
        let units = plan["units"].as_array().unwrap().iter();
        units
            .map(|u| (u["id"].as_str().unwrap().into(), u["command"].as_array().unwrap().iter().map(arg).collect()))
            .collect()
    };
    let control = scan_small(root, &inst(), &root.join("control.json"));
    assert!(units(&control).len() >= 4, "{control}");
    let mut frames: Vec<PathBuf> =
        std::fs::read_dir(root.join("raw/empty")).unwrap().map(|e| e.unwrap().path()).collect();
    frames.sort();
    let again = root.join("raw/again");
    std::fs::create_dir_all(&again).unwrap();
    std::fs::copy(&frames[0], again.join("copy.fits")).unwrap();
    std::fs::hard_link(&frames[1], again.join("link.fits")).unwrap();
    std::os::unix::fs::symlink(&frames[2], again.join("sym.fits")).unwrap();
    std::os::unix::fs::symlink(root.join("raw/flat"), root.join("raw/flat_again")).unwrap();
    std::os::unix::fs::symlink(root, root.join("raw/loop")).unwrap();
    let plan = scan_small(root, &inst(), &root.join("plan.json"));
    assert_eq!(units(&plan), units(&control), "the units of the night with the extra names");
    let left = serde_json::to_string(&plan["left_out"]).unwrap();
    for (name, orig) in [("copy.fits", &frames[0]), ("link.fits", &frames[1]), ("sym.fits", &frames[2])] {
        let entry = plan["left_out"].as_array().unwrap().iter().find(|l| l.to_string().contains(name));
        let entry = entry.unwrap_or_else(|| panic!("{name} not named: {left}"));
        assert!(entry.to_string().contains(orig.to_str().unwrap()), "{name} without {}: {entry}", orig.display());
    }
    assert!(left.contains("raw/loop") && left.contains("again (a symlink loop"), "{left}");
}

/// An instrument file edited after a run re-runs every unit whose command reads it, with the
/// new file's numbers (the calibration's HWP zero angle is the edited one); a run after that
/// has nothing to do. Temporaries a killed run left, tagged with a unit's id, are removed by
/// that unit's next run.
#[test]
fn run_reruns_the_units_of_an_edited_instrument_file() {
    let d = tempfile::tempdir().unwrap();
    let root = d.path();
    let own = root.join("inst.toml");
    std::fs::copy(inst(), &own).unwrap();
    small_night(root, &own);
    let plan_path = root.join("plan.json");
    let plan = scan_small(root, &own, &plan_path);
    let (ok, first) = run_json(&plan_path, &[]);
    assert!(ok, "{first}");
    let (ok, second) = run_json(&plan_path, &[]);
    assert!(ok && statuses(&second).iter().all(|(_, s)| s == "up_to_date"), "{second}");
    let cal_unit =
        plan["units"].as_array().unwrap().iter().find(|u| u["kind"] == "calibrate").expect("a calibrate unit");
    let cal = PathBuf::from(cal_unit["outputs"][0].as_str().unwrap());
    assert_eq!(fit::Calibration::load(&cal).unwrap().hwp_chi_offset_deg, -1.80);
    let text = std::fs::read_to_string(&own).unwrap();
    assert!(text.contains("hwp_chi_offset_deg = -1.80"));
    std::fs::write(&own, text.replacen("hwp_chi_offset_deg = -1.80", "hwp_chi_offset_deg = 25.0", 1)).unwrap();
    // What a run killed in the calibrate unit would have left: its command's temporary beside
    // its output and its hash report beside its record.
    let id = cal_unit["id"].as_str().unwrap();
    let tmp = cal.with_file_name(format!(".instpol-{id}.abc123.fits.tmp"));
    std::fs::write(&tmp, b"half a file").unwrap();
    let records = PathBuf::from(plan["records"].as_str().unwrap());
    let report = records.join(format!(".{id}.hashes-4242.json"));
    std::fs::write(&report, b"[").unwrap();
    let (ok, third) = run_json(&plan_path, &[]);
    assert!(ok, "{third}");
    let reads_it = |u: &Value| u["command"].as_array().unwrap().iter().any(|a| a.as_str() == own.to_str());
    for u in plan["units"].as_array().unwrap().iter().filter(|u| reads_it(u)) {
        let s = statuses(&third).into_iter().find(|(i, _)| u["id"] == i.as_str()).unwrap().1;
        assert_eq!(s, "done", "{} reads the edited instrument file: {third}", u["id"]);
    }
    assert_eq!(fit::Calibration::load(&cal).unwrap().hwp_chi_offset_deg, 25.0);
    assert!(!tmp.exists() && !report.exists(), "leftovers of a killed run kept");
    let (ok, fourth) = run_json(&plan_path, &[]);
    assert!(ok && statuses(&fourth).iter().all(|(_, s)| s == "up_to_date"), "{fourth}");
}

/// A turning plate's night: the shrunk FORS2 with a rotor of 16 positions (MOPRPOS), one set
/// of all 16 and one with position 3 (56.25 deg, the middle of 45 .. 67.5) missing. scan
/// keeps the whole set and leaves the other out naming the missing range's middle, by the
/// reduction's rule for a turning plate (it had no plate angle for a rotor's frames).
#[test]
fn scan_names_the_missing_position_of_a_turning_plate() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(inst()).unwrap().replace(
        "hwp_angle_keyword = \"HIERARCH ESO INS RETA2 POSANG\"",
        "rotation = { position_keyword = \"MOPRPOS\", positions_per_turn = 16, first_position = 1, zero_deg = 0.0 }",
    );
    let turning = dir.path().join("turning.toml");
    std::fs::write(&turning, text).unwrap();
    let mids: Vec<f64> = (0..16).map(|k| 11.25 + 22.5 * k as f64).collect();
    let set = |name: &'static str, target: &'static str, angles: Vec<f64>, start: f64, first: i64| Spec {
        dir: name,
        filter: "v_HIGH",
        angles,
        start_mjd: start,
        first_exp: first,
        dpr: ["SCIENCE", "OBJECT", "POLARIMETRY"],
        target,
        ra_dec: (150.0, -30.0),
        sky: Some((3000.0, 0.02, 30.0)),
        stars: vec![],
        instrume: None,
        seed: 5,
    };
    let sweep = "[hwp_motion]\nsweep_deg = 22.5\n";
    simulate_scene(dir.path(), &set("whole", "WHOLE", mids.clone(), NIGHT + 0.1, 10), &turning, PATTERN, sweep);
    let short: Vec<f64> = mids.iter().enumerate().filter(|(k, _)| *k != 2).map(|(_, a)| *a).collect();
    simulate_scene(dir.path(), &set("short", "SHORT", short, NIGHT + 0.3, 40), &turning, PATTERN, sweep);
    let plan = dir.path().join("night.json");
    let mut args = scan_args(&dir.path().join("raw"), &turning, &plan);
    args.push("--json".into());
    let o = Command::new(bin()).args(&args).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let plan: Value = serde_json::from_str(&std::fs::read_to_string(&plan).unwrap()).unwrap();
    let left: Vec<String> =
        plan["left_out"].as_array().unwrap().iter().map(|l| l["why"].as_str().unwrap().to_string()).collect();
    let short_why = left.iter().find(|w| w.contains("SHORT")).unwrap_or_else(|| panic!("{left:?}"));
    assert!(short_why.contains("incomplete") && short_why.contains("56.25 missing"), "{short_why}");
    assert!(!left.iter().any(|w| w.contains("WHOLE")), "{left:?}");
}
