//! Byte-mutation fuzzing of the input readers (bad input must be refused, never panic). Not
//! part of the default test run: every target is `#[ignore]`; `fuzz/run.sh` runs them with a
//! time budget
//! (`FUZZ_SECS`, default 20 s per target) and a seed (`FUZZ_SEED`).
//!
//! Nightly cargo-fuzz is not used: a seeded mutator (bit flips, byte replacement with
//! interesting bytes, block deletion, duplication and splicing of lines, token insertion)
//! applied to valid seed inputs, which is enough to reach the parsers' error paths. Library
//! readers (instrument TOML, scene TOML) run in-process under `catch_unwind`; readers that go
//! through CFITSIO or the CLI (the `instpol stokes` CSV reader, the calibration-file reader)
//! run the binary, so that memory corruption shows as a signal instead of killing the harness.
//!
//! A finding is a panic, a signal, an exit code other than 0 and 2, or a missing `error:`
//! message. Findings are written to `fuzz/findings/<target>/` (the input) and counted;
//! distinct first error lines are counted as the corpus of behaviours reached. A summary line
//! per target is appended to `$FUZZ_REPORT` when set.

use crate::common;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        // xorshift64*
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

const TOKENS: &[&[u8]] = &[
    b"NaN",
    b"nan",
    b"inf",
    b"-inf",
    b"-1",
    b"0",
    b"1e308",
    b"-0.0",
    b"\"\"",
    b"[",
    b"]",
    b"{",
    b"}",
    b"=",
    b",",
    b"\n",
    b"\"",
    b"#",
    b"[[filters]]",
    b"1e-320",
    b"18446744073709551616",
    b"\xff\xfe",
    b"\0",
    b"'",
    b"true",
    b"SIMPLE  =                    T",
    b"END",
    b"NAXIS   =                    0",
    b"BITPIX  =                  -64",
];

fn mutate(rng: &mut Rng, seed: &[u8]) -> Vec<u8> {
    let mut v = seed.to_vec();
    for _ in 0..1 + rng.below(4) {
        let n = v.len().max(1);
        match rng.below(7) {
            0 if !v.is_empty() => {
                let i = rng.below(n);
                v[i] ^= 1 << rng.below(8);
            }
            1 if !v.is_empty() => {
                let i = rng.below(n);
                v[i] = [0u8, 0xff, b'9', b'-', b'.', b'e', b'"', b'\n', b'='][rng.below(9)];
            }
            2 if !v.is_empty() => {
                let i = rng.below(n);
                let len = 1 + rng.below(64.min(n - i).max(1));
                v.drain(i..(i + len).min(v.len()));
            }
            3 => {
                let i = rng.below(n + 1).min(v.len());
                let t = TOKENS[rng.below(TOKENS.len())];
                v.splice(i..i, t.iter().copied());
            }
            4 if !v.is_empty() => {
                // Duplicate a block.
                let i = rng.below(n);
                let len = 1 + rng.below(200.min(n - i).max(1));
                let block: Vec<u8> = v[i..(i + len).min(v.len())].to_vec();
                let j = rng.below(v.len() + 1);
                v.splice(j..j, block);
            }
            5 if !v.is_empty() => {
                // Replace a number-looking run of digits by another.
                let i = rng.below(n);
                if v[i].is_ascii_digit() {
                    let mut j = i;
                    while j < v.len() && (v[j].is_ascii_digit() || v[j] == b'.') {
                        j += 1;
                    }
                    let t = TOKENS[rng.below(TOKENS.len())];
                    v.splice(i..j, t.iter().copied());
                }
            }
            _ => {
                // Truncate.
                let keep = rng.below(n + 1);
                v.truncate(keep);
            }
        }
    }
    v
}

/// Byte ranges of the FITS header blocks of `b` (from a SIMPLE/XTENSION block to its END card).
fn header_ranges(b: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i + 2880 <= b.len() {
        if b[i..].starts_with(b"SIMPLE  =") || b[i..].starts_with(b"XTENSION=") {
            let start = i;
            loop {
                let blk = &b[i..(i + 2880).min(b.len())];
                i += 2880;
                if blk.chunks(80).any(|c| c.starts_with(b"END     ") || c == b"END") || i + 2880 > b.len() {
                    break;
                }
            }
            out.push((start, i.min(b.len())));
        } else {
            i += 2880;
        }
    }
    out
}

/// FITS-aware mutation: half the time edit header cards in place (value fields replaced by
/// hostile tokens, bytes flipped, cards blanked or swapped; the file keeps its length, so
/// CFITSIO gets past the block structure), else a generic byte mutation.
fn mutate_fits(rng: &mut Rng, seed: &[u8]) -> Vec<u8> {
    let hr = header_ranges(seed);
    if hr.is_empty() || rng.below(2) == 0 {
        return mutate(rng, seed);
    }
    let mut v = seed.to_vec();
    const VALUES: &[&str] = &[
        "-1",
        "0",
        "99999999999",
        "NaN",
        "'abc'",
        "T",
        "-64",
        "1e400",
        "3",
        "'V       '",
        "''",
        "-2147483649",
        "8",
        "999",
        "1.5",
        "' '",
    ];
    for _ in 0..1 + rng.below(3) {
        let (a, b) = hr[rng.below(hr.len())];
        let ncards = (b - a) / 80;
        let c = a + 80 * rng.below(ncards);
        match rng.below(4) {
            0 => {
                if v[c + 8] == b'=' {
                    let t = VALUES[rng.below(VALUES.len())];
                    let field = format!("{t:>20}");
                    v[c + 10..c + 30].copy_from_slice(&field.as_bytes()[..20]);
                }
            }
            1 => {
                let i = c + rng.below(80);
                v[i] ^= 1 << rng.below(7);
            }
            2 => v[c..c + 80].fill(b' '),
            _ => {
                let d = a + 80 * rng.below(ncards);
                let card: Vec<u8> = v[c..c + 80].to_vec();
                let other: Vec<u8> = v[d..d + 80].to_vec();
                v[c..c + 80].copy_from_slice(&other);
                v[d..d + 80].copy_from_slice(&card);
            }
        }
    }
    v
}

fn budget() -> Duration {
    Duration::from_secs_f64(std::env::var("FUZZ_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(20.0))
}
fn seed() -> u64 {
    std::env::var("FUZZ_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or(0x9E37_79B9_7F4A_7C15)
}
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

struct Stats {
    target: &'static str,
    runs: usize,
    findings: Vec<String>,
    behaviours: BTreeSet<String>,
}

impl Stats {
    fn new(target: &'static str) -> Self {
        Stats { target, runs: 0, findings: Vec::new(), behaviours: BTreeSet::new() }
    }
    fn finding(&mut self, input: &[u8], ext: &str, why: String) {
        let dir = root().join("fuzz/findings").join(self.target);
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(format!("{:04}.{ext}", self.findings.len()));
        std::fs::write(&p, input).unwrap();
        self.findings.push(format!("{}: {why}", p.file_name().unwrap().to_string_lossy()));
    }
    fn report(&self) {
        let line = format!(
            "{} | {} runs | {} distinct outcomes | {} findings{}",
            self.target,
            self.runs,
            self.behaviours.len(),
            self.findings.len(),
            if self.findings.is_empty() { String::new() } else { format!(": {}", self.findings.join("; ")) }
        );
        eprintln!("{line}");
        if let Ok(p) = std::env::var("FUZZ_REPORT") {
            use std::io::Write;
            let mut f = std::fs::OpenOptions::new().create(true).append(true).open(p).unwrap();
            writeln!(f, "{line}").unwrap();
        }
    }
}

/// Normalize an error message to a behaviour class (drop numbers and paths).
fn class(msg: &str) -> String {
    let first = msg.lines().next().unwrap_or("");
    first.chars().filter(|c| !c.is_ascii_digit()).take(90).collect()
}

/// In-process target: `f` must return Ok or Err, never panic.
fn fuzz_lib(
    target: &'static str,
    seeds: &[Vec<u8>],
    f: impl Fn(&str) -> Result<(), String> + std::panic::RefUnwindSafe,
) {
    let mut st = Stats::new(target);
    let mut rng = Rng(seed());
    let t0 = Instant::now();
    std::panic::set_hook(Box::new(|_| {}));
    while t0.elapsed() < budget() {
        let s = &seeds[rng.below(seeds.len())];
        let input = mutate(&mut rng, s);
        let text = String::from_utf8_lossy(&input).into_owned();
        st.runs += 1;
        match std::panic::catch_unwind(|| f(&text)) {
            Ok(Ok(())) => {
                st.behaviours.insert("ok".into());
            }
            Ok(Err(e)) => {
                st.behaviours.insert(class(&e));
            }
            Err(p) => {
                let msg =
                    p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()));
                st.finding(&input, "toml", format!("panic: {}", msg.unwrap_or_default()));
            }
        }
    }
    let _ = std::panic::take_hook();
    st.report();
    assert!(st.findings.is_empty(), "{target}: {} findings, see fuzz/findings/{target}", st.findings.len());
}

/// Binary target: `args(path)` runs instpol on the mutated file.
fn fuzz_bin(
    target: &'static str,
    ext: &str,
    seeds: &[Vec<u8>],
    mutator: fn(&mut Rng, &[u8]) -> Vec<u8>,
    args: impl Fn(&str, &str) -> Vec<String>,
) {
    let mut st = Stats::new(target);
    let mut rng = Rng(seed());
    let dir = tempfile::tempdir().unwrap();
    let t0 = Instant::now();
    while t0.elapsed() < budget() {
        let s = &seeds[rng.below(seeds.len())];
        let input = mutator(&mut rng, s);
        let p = dir.path().join(format!("input.{ext}"));
        std::fs::write(&p, &input).unwrap();
        let out = dir.path().join(format!("out.{ext}"));
        let _ = std::fs::remove_file(&out);
        let o = common::instpol().args(args(p.to_str().unwrap(), out.to_str().unwrap())).output().unwrap();
        st.runs += 1;
        let err = String::from_utf8_lossy(&o.stderr);
        match o.status.code() {
            Some(0) => {
                st.behaviours.insert("ok".into());
            }
            Some(2) if err.contains("error: ") && !err.contains("panicked") => {
                st.behaviours.insert(class(err.split("error: ").nth(1).unwrap_or("")));
                if out.exists() {
                    st.finding(&input, ext, "exit 2 but an output file was written".into());
                }
            }
            code => {
                let why = format!("exit {code:?}: {}", err.lines().next().unwrap_or("(killed by a signal)"));
                st.finding(&input, ext, why);
            }
        }
    }
    st.report();
    assert!(st.findings.is_empty(), "{target}: {} findings, see fuzz/findings/{target}", st.findings.len());
}

#[test]
#[ignore = "fuzzing: run fuzz/run.sh"]
fn fuzz_instrument_toml() {
    let seed = std::fs::read(root().join("instruments/fors1.toml")).unwrap();
    fuzz_lib("instrument_toml", &[seed], |text| {
        let inst = instrument::Instrument::from_toml_str(text, Path::new("fuzz.toml")).map_err(|e| e.to_string())?;
        // A loaded instrument must be usable without panics.
        let _ = inst.strips();
        let (x, y) = inst.pixel_to_arcmin(0.0, 0.0);
        let _ = inst.arcmin_to_pixel(x, y);
        for f in &inst.filters {
            inst.filter(&f.name).map_err(|e| e.to_string())?;
        }
        Ok(())
    });
}

#[test]
#[ignore = "fuzzing: run fuzz/run.sh"]
fn fuzz_scene_toml() {
    let dir = root().join("instruments/scenes");
    let seeds: Vec<Vec<u8>> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.path().extension().is_some_and(|x| x == "toml"))
        .map(|e| std::fs::read(e.path()).unwrap())
        .collect();
    assert!(!seeds.is_empty());
    let label = dir.join("fuzz.toml");
    fuzz_lib("scene_toml", &seeds, move |text| {
        sim::scene::Scene::from_toml_str(text, &label).map(|_| ()).map_err(|e| e.to_string())
    });
}

#[test]
#[ignore = "fuzzing: run fuzz/run.sh"]
fn fuzz_stokes_csv() {
    let seeds = vec![
        b"hwp_deg,f_o,f_e\n0,505000,495000\n22.5,508660.25,491339.75\n45,495000,505000\n67.5,491339.75,508660.25\n".to_vec(),
        b"# comment\nf_e,hwp_deg,f_o,sigma_o,sigma_e\n495,0,505,22,22\n491,22.5,508,22,22\n505,45,495,22,22\n508,67.5,491,22,22\n505,90,495,22,22\n491,112.5,508,22,22\n505,135,495,22,22\n508,157.5,491,22,22\n".to_vec(),
    ];
    fuzz_bin("stokes_csv", "csv", &seeds, mutate, |p, _| {
        vec!["stokes".to_string(), "--input".to_string(), p.to_string(), "--json".to_string()]
    });
}

/// The calibration-file reader through `instpol correct` (process isolation: a CFITSIO or
/// fitsio memory error is a signal, not a dead harness). The seed is a calibration written
/// by `instpol demo --no-frames` (built once, into the temp folder).
#[test]
#[ignore = "fuzzing: run fuzz/run.sh"]
fn fuzz_calibration_file() {
    let work = tempfile::tempdir().unwrap();
    let demo = work.path().join("demo");
    let o = common::instpol().args(["demo", "--no-frames", "--out", demo.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let seeds: Vec<Vec<u8>> =
        ["cal_V.fits", "cal_B.fits"].iter().map(|n| std::fs::read(demo.join(n)).unwrap()).collect();
    let cat = work.path().join("cat.csv");
    std::fs::write(&cat, "x,y,q,u,sigma_q,sigma_u\n0.5,0.5,0.01,0.002,0.0005,0.0005\n").unwrap();
    let cat = cat.to_str().unwrap().to_string();
    fuzz_bin("calibration_file", "fits", &seeds, mutate_fits, move |p, out| {
        vec!["correct".into(), "--cal".into(), p.into(), "--in".into(), cat.clone(), "--out".into(), out.to_string()]
    });
}

/// 64 x 64 px of 4": four strips of 6 px.
const MINI: common::Mini =
    common::Mini { nx: 64, field_arcmin: 4.27, throw_arcsec: 24.0, strip_count: 4, ..common::MINI };

/// The frame reader (CFITSIO through skyfield::io::read_frame) and the frame-set checks via
/// `instpol reduce`: one of four good 64 x 64 frames is replaced by a mutated copy.
#[test]
#[ignore = "fuzzing: run fuzz/run.sh"]
fn fuzz_frame_fits() {
    use skyfield::fits::{write_frame, Bitpix, KeyValue};
    let work = tempfile::tempdir().unwrap();
    let inst = work.path().join("mini.toml");
    std::fs::write(&inst, MINI.toml()).unwrap();
    let mut frames = Vec::new();
    for (i, a) in [0.0, 22.5, 45.0, 67.5].iter().enumerate() {
        let keys = vec![
            ("HIERARCH ESO INS RETA2 POSANG".to_string(), KeyValue::F64(*a), String::new()),
            ("HIERARCH ESO INS FILT1 NAME".to_string(), KeyValue::Str("V".into()), String::new()),
        ];
        let data: Vec<f64> = (0..64 * 64).map(|k| 1000.0 + (k % 7) as f64).collect();
        let p = work.path().join(format!("f{i}.fits"));
        let bp = if i % 2 == 0 { Bitpix::F32 } else { Bitpix::U16 };
        write_frame(&p, 64, 64, &data, bp, &keys).unwrap();
        frames.push(p.to_str().unwrap().to_string());
    }
    let seeds: Vec<Vec<u8>> = frames.iter().map(|p| std::fs::read(p).unwrap()).collect();
    let inst = inst.to_str().unwrap().to_string();
    fuzz_bin("frame_fits", "fits", &seeds, mutate_fits, move |p, out| {
        let mut a = vec!["reduce".to_string(), "--instrument".into(), inst.clone(), "--bin".into(), "8".into()];
        a.extend(frames[1..].iter().cloned());
        a.push(p.to_string());
        a.push("--out".into());
        a.push(out.to_string());
        a
    });
}
