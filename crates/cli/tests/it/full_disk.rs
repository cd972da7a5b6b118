//! A full disk at every writer: a write error that shows only at flush, close or fsync must
//! fail the command (exit 2, an error naming the output) and leave neither a partial file under
//! the final name nor a temporary.
//!
//! The writers are read from the CLI's own definition (`instpol cli-spec`): every output
//! argument of every command (`--out`, `--plot`, `--plots`, `--field-out`, `--output`, ...),
//! each tried alone from the command's valid invocation (`common::invocations`, shared with the
//! hostile-input generator), all outputs in one fresh folder. An output argument that cannot be
//! tried must be listed in [`NOT_TRIED`] with the reason, so that a new writer cannot pass
//! untried.
//!
//! Two ways: (1) always, an injected fsync failure (`INSTPOL_TEST_FAIL_SYNC`, see
//! `skyfield::durable`), which every writer must pass through before its rename; (2) where
//! mounting is possible (root), a real 64 KiB tmpfs that the outputs do not fit in, so the
//! error comes from the kernel at write, flush or close.

use crate::common;

use common::invocations::{self, fill, Fixture};
use std::path::{Path, PathBuf};
use std::process::Command;

/// Output arguments not tried here, with the reason (command, flag, why).
const NOT_TRIED: &[(&str, &str, &str)] = &[
    ("scan", "--products", "names a folder the plan's units write into later (instpol run), not scan"),
    (
        "fit-standards",
        "--output-dir",
        "a folder of calibration files per band; tried through --output, the same writer",
    ),
];

/// Output arguments that write only with another option (command, flag, what it needs).
const NEEDS: &[(&str, &str, &[&str])] = &[("mc", "--plot", &["--accuracy-report"])];

/// The file (or folder) name an output argument gets in the case's folder.
fn output_name(flag: &str) -> &'static str {
    match flag {
        "--plot" => "plot.png",
        "--field-out" => "field.json",
        "--output" => "telescope.fits",
        _ => "outputs",
    }
}

/// One writer: its label, the arguments with `{DIR}` for the folder all its outputs go to.
struct Writer {
    label: String,
    args: Vec<String>,
}

/// Every output argument of every command with a valid invocation, each set in that
/// invocation (the invocation's own output moved into the folder too).
fn writers(f: &Fixture) -> Vec<Writer> {
    let defs = invocations::args_by_command(&invocations::spec());
    let templates = invocations::templates(f);
    // An output argument some invocation names is tried there (every such invocation); one
    // that none names is added to the command's first invocation.
    let named = |cmd: &str, flag: &str| templates.iter().any(|t| t.name() == cmd && t.args.iter().any(|x| x == flag));
    let mut out = vec![];
    let mut added = std::collections::BTreeSet::new();
    for t in &templates {
        for a in defs[t.name()].iter().filter(|a| a["role"] == "output") {
            let flag = a["long"].as_str().unwrap();
            if NOT_TRIED.iter().any(|(c, fl, _)| *c == t.name() && *fl == flag) {
                continue;
            }
            let mut args = fill(&t.args, Path::new("{DIR}"), t.out_name);
            if !t.args.iter().any(|x| x == flag) {
                if named(t.name(), flag) || !added.insert((t.name().to_string(), flag.to_string())) {
                    continue;
                }
                args.extend([flag.to_string(), format!("{{DIR}}/{}", output_name(flag))]);
                if let Some((_, _, more)) = NEEDS.iter().find(|(c, fl, _)| *c == t.name() && *fl == flag) {
                    args.extend(more.iter().map(|m| m.to_string()));
                }
            }
            out.push(Writer { label: format!("{} {flag}", t.command), args });
        }
    }
    out
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

fn in_dir(args: &[String], dir: &Path) -> Vec<String> {
    args.iter().map(|a| a.replace("{DIR}", dir.to_str().unwrap())).collect()
}

fn check_fails_cleanly(name: &str, args: &[String], out: &Path, env: Option<(&str, &str)>, expect: &[&str]) {
    let args = in_dir(args, out);
    let mut c = Command::new(common::bin());
    c.args(&args).current_dir(out);
    if let Some((k, v)) = env {
        c.env(k, v);
    }
    let o = c.output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("panicked"), "{name}: panic: {err}");
    assert_eq!(o.status.code(), Some(2), "{name}: a full disk must fail the command: {err}");
    assert!(err.contains("error"), "{name}: {err}");
    for e in expect {
        assert!(err.contains(e), "{name}: the message should say '{e}': {err}");
    }
    // No partial file under a final name, no temporary: nothing at all but what was there.
    let left: Vec<String> = files(out).into_iter().filter(|f| !f.starts_with("filler")).collect();
    assert!(left.is_empty(), "{name}: left {left:?} in {}", out.display());
}

/// Every output argument of the CLI is tried here or listed in [`NOT_TRIED`], and each listed
/// one exists.
#[test]
fn every_output_argument_is_tried_or_says_why_not() {
    let f = invocations::fixture();
    let tried: Vec<String> = writers(&f).iter().map(|w| w.label.clone()).collect();
    let spec = invocations::spec();
    let mut wrong = vec![];
    for (cmd, args) in invocations::args_by_command(&spec) {
        for a in args.iter().filter(|a| a["role"] == "output") {
            let flag = a["long"].as_str().unwrap();
            let listed = NOT_TRIED.iter().any(|(c, fl, _)| *c == cmd && *fl == flag);
            let is_tried = tried.iter().any(|l| l.split(' ').next() == Some(cmd.as_str()) && l.ends_with(flag));
            if !listed && !is_tried {
                wrong.push(format!("{cmd} {flag}: not tried and not in NOT_TRIED"));
            }
        }
    }
    for (c, fl, _) in NOT_TRIED {
        let exists = invocations::args_by_command(&spec)
            .get(*c)
            .is_some_and(|args| args.iter().any(|a| a["long"] == *fl && a["role"] == "output"));
        if !exists {
            wrong.push(format!("{c} {fl}: listed in NOT_TRIED but not an output argument of the CLI"));
        }
    }
    assert!(tried.len() >= 25, "only {} writers", tried.len());
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

#[test]
fn injected_fsync_failure_fails_every_writer_and_leaves_nothing() {
    let f = invocations::fixture();
    let all = writers(&f);
    println!("{} writers: {}", all.len(), all.iter().map(|w| w.label.as_str()).collect::<Vec<_>>().join(", "));
    for w in all {
        // Control: without the injection the writer succeeds and makes its files.
        let good = tempfile::tempdir().unwrap();
        let o =
            Command::new(common::bin()).args(in_dir(&w.args, good.path())).current_dir(good.path()).output().unwrap();
        assert_eq!(o.status.code(), Some(0), "{} control: {}", w.label, String::from_utf8_lossy(&o.stderr));
        assert!(!files(good.path()).is_empty(), "{} control wrote nothing", w.label);
        let bad = tempfile::tempdir().unwrap();
        check_fails_cleanly(
            &w.label,
            &w.args,
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
    let f = invocations::fixture();
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
    for w in writers(&f) {
        let out = mnt.path().join(format!("w{tested}"));
        std::fs::create_dir(&out).unwrap();
        // Fill the tmpfs completely (a one-row CSV fits in any space left over).
        let filler = out.join("filler");
        let mut fill = std::fs::File::create(&filler).unwrap();
        let chunk = vec![0u8; 4096];
        use std::io::Write;
        while fill.write_all(&chunk).and_then(|_| fill.sync_all()).is_ok() {}
        drop(fill);
        check_fails_cleanly(&w.label, &w.args, &out, None, &[]);
        std::fs::remove_dir_all(&out).unwrap();
        tested += 1;
    }
    assert_eq!(tested, writers(&f).len());
}

/// Bytes free on the file system holding `dir` (`stat -f`: available blocks times their size).
fn free_bytes(dir: &Path) -> u64 {
    let o = Command::new("stat").args(["-f", "-c", "%a %S"]).arg(dir).output().unwrap();
    let s = String::from_utf8_lossy(&o.stdout);
    let v: Vec<u64> = s.split_whitespace().map(|x| x.parse().unwrap()).collect();
    v[0] * v[1]
}

/// The output files of a run in `dir` with their sizes (the filler left out).
fn sizes(dir: &Path) -> Vec<(String, u64)> {
    files(dir)
        .into_iter()
        .filter(|f| !f.starts_with("filler"))
        .map(|f| {
            let n = std::fs::symlink_metadata(dir.join(&f)).map_or(0, |m| m.len());
            (f, n)
        })
        .collect()
}

/// Outputs of up to this many pages are tried at every page ([`tmpfs_filled_to_every_page_of_each_fits_writer`]).
const MAX_PAGES: u64 = 48;

/// A tmpfs filled to every page boundary of each FITS writer: for a writer whose outputs
/// take P pages of 4 KiB, the disk is left with 0, 1, ..., P + 1 pages free, so that it fills
/// in every block the writer writes, the last one included (where CFITSIO's last flush at
/// close lost its error and left a file a partial page short under the final name, exit 0).
/// Each run either succeeds with every output the size of the run with room to spare, or
/// fails (exit 2, an error) leaving nothing. The FITS writers are those of
/// [`writers`] whose outputs hold a FITS file, `import-map --out` and `fit-standards
/// --output` among them. Needs root to mount; elsewhere it says so and returns.
#[test]
fn tmpfs_filled_to_every_page_of_each_fits_writer() {
    let f = invocations::fixture();
    let mnt = tempfile::tempdir().unwrap();
    let m = mnt.path().to_str().unwrap();
    let st = Command::new("mount").args(["-t", "tmpfs", "-o", "size=32m", "tmpfs", m]).output();
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
    let run = |w: &Writer, dir: &Path| {
        let o = Command::new(common::bin()).args(in_dir(&w.args, dir)).current_dir(dir).output().unwrap();
        (o.status.code(), String::from_utf8_lossy(&o.stderr).to_string())
    };
    let mut tried = vec![];
    let mut too_big = vec![];
    for w in writers(&f) {
        let control = tempfile::tempdir().unwrap();
        let (code, err) = run(&w, control.path());
        assert_eq!(code, Some(0), "{} control: {err}", w.label);
        let want = sizes(control.path());
        if !want.iter().any(|(n, _)| n.ends_with(".fits")) {
            continue;
        }
        if want.iter().map(|(_, n)| n).sum::<u64>() > 16 << 20 {
            too_big.push(w.label.clone());
            continue;
        }
        let dir = mnt.path().join("w");
        let pages: u64 = want.iter().map(|(_, n)| n.div_ceil(4096)).sum();
        // Every page of a writer of up to MAX_PAGES; of a larger one, its first and last
        // pages (where headers and the last flush are), each run taking the whole output.
        let frees: Vec<u64> =
            if pages <= MAX_PAGES { (0..=pages + 1).collect() } else { (0..8).chain(pages - 8..=pages + 1).collect() };
        for free in frees {
            std::fs::create_dir(&dir).unwrap();
            let fill = (free_bytes(&dir) / 4096).saturating_sub(free) * 4096;
            std::fs::write(dir.join("filler"), vec![0u8; fill as usize]).unwrap();
            let (code, err) = run(&w, &dir);
            let case = format!("{} with {free} of {pages} pages free", w.label);
            assert!(!err.contains("panicked"), "{case}: panic: {err}");
            match code {
                Some(0) => assert_eq!(sizes(&dir), want, "{case}: exit 0 with outputs unlike the control's"),
                Some(2) => assert!(sizes(&dir).is_empty(), "{case}: failed but left {:?}", sizes(&dir)),
                other => panic!("{case}: exit {other:?}: {err}"),
            }
            std::fs::remove_dir_all(&dir).unwrap();
        }
        tried.push(w.label.clone());
    }
    println!("FITS writers tried at every page: {}", tried.join(", "));
    println!("not tried (outputs over 16 MiB, the real full tmpfs test covers them): {}", too_big.join(", "));
    for named in ["import-map --out", "fit-standards --output"] {
        assert!(tried.iter().any(|t| t == named), "{named} not tried: {tried:?}");
    }
}
