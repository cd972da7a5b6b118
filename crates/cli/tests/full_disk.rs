//! A full disk at every writer: a write error that shows only at flush, close or
//! fsync must fail the command (exit 2, an error naming the output) and leave neither a partial
//! file under the final name nor a temporary.
//!
//! Two ways: (1) always, an injected fsync failure (`INSTPOL_TEST_FAIL_SYNC`, see
//! `skyfield::durable`), which every writer must pass through before its rename; (2) where
//! mounting is possible (root), a real 64 KiB tmpfs that the outputs do not fit in, so the
//! error comes from the kernel at write, flush or close.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

struct Fx {
    dir: tempfile::TempDir,
}

impl Fx {
    fn s(&self, n: &str) -> String {
        self.dir.path().join(n).to_str().unwrap().to_string()
    }
}

const SCENE: &str = "instrument = \"mini.toml\"\nfilter = \"V\"\n[sky]\nbrightness_e = 20000\np = 0.02\n";

fn ok(args: &[String]) {
    let (code, _, err) = common::run(args);
    assert_eq!(code, 0, "fixture {args:?}: {err}");
}

fn fixture() -> Fx {
    let f = Fx { dir: tempfile::tempdir().unwrap() };
    std::fs::write(f.s("mini.toml"), common::MINI.toml()).unwrap();
    std::fs::write(f.s("scene.toml"), SCENE).unwrap();
    std::fs::write(
        f.s("f.csv"),
        "hwp_deg,f_o,f_e\n0,505000,495000\n22.5,508660,491340\n45,495000,505000\n67.5,491340,508660\n",
    )
    .unwrap();
    std::fs::write(f.s("cat.csv"), "x,y,q,u,sigma_q,sigma_u\n0.5,0.5,0.01,0,0.001,0.001\n").unwrap();
    let v = |a: &[&str]| a.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    ok(&v(&["simulate", &f.s("scene.toml"), "--out", &f.s("frames")]));
    let mut r = v(&["reduce", "--instrument", &f.s("mini.toml"), "--bin", "8", "--out", &f.s("map.fits")]);
    r.extend(common::fits_in(&f.dir.path().join("frames")).iter().map(|p| p.to_str().unwrap().to_string()));
    ok(&r);
    ok(&v(&[
        "calibrate",
        "--map",
        &f.s("map.fits"),
        "--instrument",
        &f.s("mini.toml"),
        "--sky-p",
        "2",
        "--sky-chi",
        "30",
        "--out",
        &f.s("cal.fits"),
    ]));
    let field = fit::RadialModel::new(1, vec![1e-4, 4e-4, 0.0], [0.0, 0.0]);
    fit::synth::write_qu_cubes(
        &f.dir.path().join("q.fits"),
        &f.dir.path().join("u.fits"),
        &field,
        96,
        96,
        4.0,
        8,
        1e-4,
    )
    .unwrap();
    f
}

/// Every writer: the arguments with `{OUT}` for the output (a file name, or a folder for the
/// commands that write several), and the files a success would create there.
fn writers(f: &Fx) -> Vec<(&'static str, Vec<String>, Vec<&'static str>)> {
    let frames: Vec<String> =
        common::fits_in(&f.dir.path().join("frames")).iter().map(|p| p.to_str().unwrap().to_string()).collect();
    let v = |a: &[&str]| a.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let mut reduce = v(&["reduce", "--instrument", &f.s("mini.toml"), "--bin", "8", "--out", "{OUT}/map.fits"]);
    reduce.extend(frames.iter().cloned());
    let mut calf = v(&[
        "calibrate",
        "--instrument",
        &f.s("mini.toml"),
        "--bin",
        "8",
        "--sky-p",
        "2",
        "--sky-chi",
        "30",
        "--out",
        "{OUT}/cal.fits",
    ]);
    calf.extend(frames.iter().cloned());
    vec![
        (
            "stokes --plot (PNG)",
            v(&["stokes", "--input", &f.s("f.csv"), "--plot", "{OUT}/fourier.png"]),
            vec!["fourier.png"],
        ),
        ("reduce (Stokes map)", reduce, vec!["map.fits"]),
        ("calibrate (frames)", calf, vec!["cal.fits"]),
        (
            "calibrate --map --plots",
            v(&[
                "calibrate",
                "--map",
                &f.s("map.fits"),
                "--instrument",
                &f.s("mini.toml"),
                "--sky-p",
                "2",
                "--sky-chi",
                "30",
                "--out",
                "{OUT}/cal.fits",
                "--plots",
                "{OUT}",
            ]),
            vec!["cal.fits"],
        ),
        ("fit --out", v(&["fit", &f.s("cal.fits"), "--out", "{OUT}/refit.fits"]), vec!["refit.fits"]),
        (
            "import-map",
            v(&[
                "import-map",
                "--q",
                &f.s("q.fits"),
                "--u",
                &f.s("u.fits"),
                "--pixel-scale",
                "4",
                "--bin",
                "8",
                "--filter",
                "V",
                "--out",
                "{OUT}/imp.fits",
            ]),
            vec!["imp.fits"],
        ),
        (
            "correct (catalog)",
            v(&["correct", "--cal", &f.s("cal.fits"), "--in", &f.s("cat.csv"), "--out", "{OUT}/cat.csv"]),
            vec!["cat.csv"],
        ),
        (
            "correct (map)",
            v(&["correct", "--cal", &f.s("cal.fits"), "--in", &f.s("map.fits"), "--out", "{OUT}/map.fits"]),
            vec!["map.fits"],
        ),
        ("plot", v(&["plot", &f.s("cal.fits"), "--out", "{OUT}"]), vec![]),
        ("simulate (frames)", v(&["simulate", &f.s("scene.toml"), "--out", "{OUT}"]), vec![]),
        (
            "raytrace --plot --field-out",
            v(&["raytrace", "--instrument", "fors1", "--plot", "{OUT}/rt.png", "--field-out", "{OUT}/rt.json"]),
            vec!["rt.png", "rt.json"],
        ),
    ]
}

/// Files in `dir` (recursively), names relative to it.
fn files(dir: &Path) -> Vec<String> {
    let mut v = vec![];
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                v.extend(files(&p));
            } else {
                v.push(p.strip_prefix(dir).unwrap_or(&p).display().to_string());
            }
        }
    }
    v.sort();
    v
}

fn check_fails_cleanly(name: &str, args: &[String], out: &Path, env: Option<(&str, &str)>, expect: &[&str]) {
    let args: Vec<String> = args.iter().map(|a| a.replace("{OUT}", out.to_str().unwrap())).collect();
    let mut c = Command::new(common::bin());
    c.args(&args);
    if let Some((k, v)) = env {
        c.env(k, v);
    }
    let o = c.output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("panicked"), "{name}: panic: {err}");
    assert_eq!(o.status.code(), Some(2), "{name}: a full disk must fail the command: {err}");
    assert!(err.contains("error:"), "{name}: {err}");
    for e in expect {
        assert!(err.contains(e), "{name}: the message should say '{e}': {err}");
    }
    // No partial file under a final name, no temporary: nothing at all but what was there.
    let left: Vec<String> = files(out).into_iter().filter(|f| !f.starts_with("filler")).collect();
    assert!(left.is_empty(), "{name}: left {left:?} in {}", out.display());
}

#[test]
fn injected_fsync_failure_fails_every_writer_and_leaves_nothing() {
    let f = fixture();
    for (name, args, made) in writers(&f) {
        // Control: without the injection the writer succeeds and makes its files.
        let good = tempfile::tempdir().unwrap();
        let a: Vec<String> = args.iter().map(|a| a.replace("{OUT}", good.path().to_str().unwrap())).collect();
        let (code, _, err) = common::run(&a);
        assert_eq!(code, 0, "{name} control: {err}");
        for m in &made {
            assert!(good.path().join(m).is_file(), "{name} control made no {m}");
        }
        assert!(!files(good.path()).is_empty(), "{name} control wrote nothing");
        let bad = tempfile::tempdir().unwrap();
        check_fails_cleanly(
            name,
            &args,
            bad.path(),
            Some((skyfield::durable::FAIL_SYNC_ENV, "1")),
            &["No space left on device"],
        );
    }
}

/// A real full disk: a 64 KiB tmpfs (mounting needs root; elsewhere the injected test above
/// is the proof, and this one says so and returns).
#[test]
fn real_full_tmpfs_fails_every_writer_and_leaves_nothing() {
    let f = fixture();
    let mnt = tempfile::tempdir().unwrap();
    let m = mnt.path().to_str().unwrap();
    let st = Command::new("mount").args(["-t", "tmpfs", "-o", "size=64k", "tmpfs", m]).output();
    if !matches!(&st, Ok(o) if o.status.success()) {
        eprintln!("note: cannot mount a tmpfs here (not root?); the injected-failure test covers the writers");
        return;
    }
    struct Umount(PathBuf);
    impl Drop for Umount {
        fn drop(&mut self) {
            let _ = Command::new("umount").arg(&self.0).status();
        }
    }
    let _guard = Umount(mnt.path().to_path_buf());
    let mut tested = 0;
    for (name, args, _) in writers(&f) {
        let out = mnt.path().join(format!("w{tested}"));
        std::fs::create_dir(&out).unwrap();
        // Fill the tmpfs completely (a one-row CSV fits in any space left over).
        let filler = out.join("filler");
        let mut fill = std::fs::File::create(&filler).unwrap();
        let chunk = vec![0u8; 4096];
        use std::io::Write;
        while fill.write_all(&chunk).and_then(|_| fill.sync_all()).is_ok() {}
        drop(fill);
        check_fails_cleanly(name, &args, &out, None, &[]);
        std::fs::remove_dir_all(&out).unwrap();
        tested += 1;
    }
    assert_eq!(tested, writers(&f).len());
}
