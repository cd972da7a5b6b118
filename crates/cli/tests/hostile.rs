//! A generator of hostile inputs: cases are produced by code, not listed by hand, so
//! that the next few hundred inputs someone tries have already been tried.
//!
//! - every command x every numeric flag x edge values (0, -0, negative, NaN, inf, 1e308,
//!   1e-308, subnormal, huge counts, text, empty); the numeric flags are read from the CLI's
//!   own definition (`instpol cli-spec`), so a flag added to a command is tried without being
//!   listed here, and a command with no valid invocation below fails the test unless it is
//!   listed in [`NOT_YET`] with the reason;
//! - every file-reading argument x file variants (empty, text, truncated FITS, binary garbage,
//!   a directory, missing, a symlink loop, /dev/null) and, for commands that write, the input
//!   given as the output;
//! - every numeric key of a scene file x edge values (TOML nan, inf, 1e308, text, ...).
//!
//! Each case runs the built binary with a timeout (killed after [`TIMEOUT`]) and must: not
//! panic ("panicked at", exit 101, or a signal such as SIGABRT/SIGSEGV), not hang, exit 0, 1 or
//! 2, leave its input files byte-identical, and on failure leave no file under the final output
//! name and no temporary. Cases run on all cores; the inputs are tiny (a 96 x 96 px instrument).
//! The results table (cases per command) is printed; `HOSTILE_TABLE=path` also writes it.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// A case that has not ended by then is a hang.
const TIMEOUT: Duration = Duration::from_secs(20);

/// Numeric edge values given to every numeric flag.
const EDGES: &[&str] = &[
    "0",
    "-0",
    "-1",
    "-30",
    "NaN",
    "inf",
    "-inf",
    "1e308",
    "-1e308",
    "1e-308",
    "5e-324",
    "18446744073709551616",
    "99999999999",
    "abc",
    "",
];

/// Values given to every text option (a number or a list the command parses itself:
/// `--aperture 2.5fwhm`, `--annulus 12,20`, `--parang 10,20`, `--sky EMPTY:1.7:-53`).
const TEXT_EDGES: &[&str] = &["", "NaN", "inf,inf", "-1", "1e308", "abc", ",", "1,2,3,4,5,6", "0:0:0", "\u{1F600}"];

/// TOML literals given to every numeric key of a scene.
const TOML_EDGES: &[&str] = &["0", "-0.0", "-1", "nan", "inf", "-inf", "1e308", "1e-308", "1e12", "\"text\""];

/// Commands without a valid invocation in [`templates`] yet, with the reason: their numeric
/// flags and files are not tried here (each has its own bad-input tests in its test file).
const NOT_YET: &[(&str, &str)] = &[
    ("demo", "the whole chain: minutes per case"),
    ("scan", "needs a night of raw chip files (crates/cli/tests/night.rs tries its bad inputs)"),
    ("run", "needs a scanned night (night.rs)"),
    ("trend", "needs run nights (night.rs)"),
    ("calibrate-stars", "needs catalogs of dithered pointings (calibrate_stars.rs)"),
    ("calibrate-mueller", "needs Mueller maps (calibrate_mueller.rs)"),
    ("explain", "needs a Mueller-field calibration (explain.rs)"),
    ("plan", "needs an instrument with a Mueller model; slow per case (plot_publication.rs)"),
    ("import-map", "needs an imported map file (import_map.rs)"),
];

/// Every command's arguments and their kinds, from the binary's own definition
/// (`instpol cli-spec`).
fn spec() -> serde_json::Value {
    let (code, out, err) = common::run(&["cli-spec"]);
    assert_eq!(code, 0, "cli-spec: {err}");
    serde_json::from_str(&out).unwrap()
}

/// The long flags of `kind` (`number`, `text`, `path`) of every command of `spec`.
fn flags_of_kind(spec: &serde_json::Value, kind: &str) -> BTreeMap<String, Vec<String>> {
    spec.as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let flags = c["args"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|a| a["kind"] == kind)
                .filter_map(|a| a["long"].as_str().map(str::to_string))
                .collect();
            (c["name"].as_str().unwrap().to_string(), flags)
        })
        .collect()
}

/// The valid inputs every case starts from, made by the binary itself.
struct Fixture {
    dir: tempfile::TempDir,
}

impl Fixture {
    fn p(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
    fn s(&self, name: &str) -> String {
        self.p(name).to_str().unwrap().to_string()
    }
    fn frames(&self) -> Vec<String> {
        common::fits_in(&self.p("frames")).iter().map(|p| p.to_str().unwrap().to_string()).collect()
    }
}

const SCENE: &str = r#"instrument = "mini.toml"
filter = "V"
seed = 3
exposure_s = 10.0
[sky]
brightness_e = 20000
p = 0.02
[[stars]]
x = 48
y = 24
coords = "pixel"
flux_e = 200000
p = 0.0
fwhm_arcsec = 8.0
[[stars]]
x = 20
y = 24
coords = "pixel"
flux_e = 200000
p = 0.05
chi_deg = 30
fwhm_arcsec = 8.0
[effects]
photon_noise = true
read_noise_e = 3.0
cosmic_rays = { rate_per_frame = 2 }
"#;

const STOKES_CSV: &str =
    "hwp_deg,f_o,f_e\n0,505000,495000\n22.5,508660.25,491339.75\n45,495000,505000\n67.5,491339.75,508660.25\n";

fn must(args: &[&str]) {
    let (code, _, err) = common::run(args);
    assert_eq!(code, 0, "fixture step {args:?} failed: {err}");
}

fn fixture() -> Fixture {
    let f = Fixture { dir: tempfile::tempdir().unwrap() };
    std::fs::write(f.p("mini.toml"), common::MINI.toml()).unwrap();
    std::fs::write(f.p("scene.toml"), SCENE).unwrap();
    std::fs::write(f.p("f.csv"), STOKES_CSV).unwrap();
    std::fs::write(f.p("cat.csv"), "x,y,q,u,sigma_q,sigma_u\n0.5,0.5,0.01,0,0.001,0.001\n-1,1,0,0.01,0.001,0.001\n")
        .unwrap();
    must(&["simulate", &f.s("scene.toml"), "--out", &f.s("frames"), "--json"]);
    // The truth file is not an input of anything.
    std::fs::remove_file(f.p("frames/truth.json")).unwrap();
    let mut a = vec!["reduce".to_string()];
    a.extend(f.frames());
    a.extend(["--instrument", &f.s("mini.toml"), "--bin", "8", "--out", &f.s("map.fits"), "--json"].map(String::from));
    must(&a.iter().map(|s| s.as_str()).collect::<Vec<_>>());
    must(&[
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
        "--json",
    ]);
    // Raw chip files of the shrunk FORS2 (bias and flats) for the masters.
    std::fs::create_dir_all(f.p("raw")).unwrap();
    std::fs::write(f.p("fors2_tiny.toml"), common::raw::fors2_tiny_text()).unwrap();
    let raw = common::raw::write_raw_set(&f.p("raw"), &common::raw::fors2_tiny());
    let list = |v: &[PathBuf]| v.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join("\n");
    std::fs::write(f.p("raw/bias.list"), list(&raw.bias)).unwrap();
    std::fs::write(f.p("raw/flats.list"), list(&raw.flats)).unwrap();
    // Standards through an aluminium M3 (factor 0.86, offset 40 deg: Wiersema et al. 2018's
    // model), q, u = 3.5 % turned by the parallactic angle, at twelve angles.
    let mut t = String::from("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter\n");
    for k in 0..12 {
        let pa = -160.0 + 29.0 * k as f64;
        let a = 2.0 * (40f64 - pa).to_radians();
        t += &format!("S{k},{pa},{},0.0002,{},0.0002,0.55,V\n", 0.035 * a.cos(), -0.035 * a.sin());
    }
    std::fs::write(f.p("standards.csv"), t).unwrap();
    // A second filter for the wavelength law: the same calibration relabelled B at 440 nm.
    std::fs::copy(f.p("cal.fits"), f.p("cal2.fits")).unwrap();
    patch_card(&f.p("cal2.fits"), "IP FILTER", "'B'");
    patch_card(&f.p("cal2.fits"), "IP LAMBDA NM", "440.0");
    f
}

/// Replace the value of the header card holding `key` (the comment dropped).
fn patch_card(path: &Path, key: &str, value: &str) {
    let mut b = std::fs::read(path).unwrap();
    let pos = b.windows(key.len()).position(|w| w == key.as_bytes()).unwrap_or_else(|| panic!("no card {key}"));
    let card = pos - pos % 80;
    let eq = card + b[card..card + 80].iter().position(|&c| c == b'=').unwrap();
    let mut field = format!(" {value}");
    while field.len() < 80 - (eq + 1 - card) {
        field.push(' ');
    }
    b[eq + 1..card + 80].copy_from_slice(&field.as_bytes()[..card + 80 - eq - 1]);
    std::fs::write(path, b).unwrap();
}

/// One generated case.
struct Case {
    command: &'static str,
    what: String,
    args: Vec<String>,
    /// Final output names: must not exist after a failure.
    outputs: Vec<PathBuf>,
    /// Files whose bytes must not change.
    inputs: Vec<PathBuf>,
    /// The case's own folder (outputs, hostile input variants).
    dir: PathBuf,
}

/// A command's valid invocation: `{OUT}` stands for the case's output file (named `out_name`),
/// and the files it reads are listed for the hash check.
struct Template {
    command: &'static str,
    args: Vec<String>,
    /// Numeric flags (`--x`), each set to every edge value.
    numeric: Vec<&'static str>,
    /// Flags that name a file (or the index of a positional argument) to replace by variants.
    files: Vec<FileArg>,
    out_name: Option<&'static str>,
}

#[derive(Clone)]
enum FileArg {
    Flag(&'static str),
    Positional(usize),
}

fn templates(f: &Fixture) -> Vec<Template> {
    let fr = f.frames();
    let ins = f.s("mini.toml");
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
    let with_frames = |mut v: Vec<String>| {
        v.extend(fr.iter().cloned());
        v
    };
    let star = ["--instrument", &ins, "--x", "48", "--y", "24", "--aperture", "3", "--annulus", "4,6"];
    let lines = |name: &str| -> Vec<String> {
        std::fs::read_to_string(f.p(name)).unwrap().lines().map(str::to_string).collect()
    };
    let (bias, flats) = (lines("raw/bias.list"), lines("raw/flats.list"));
    let tiny = f.s("fors2_tiny.toml");
    vec![
        Template {
            command: "master-bias",
            args: [s(&["master-bias", "--instrument", &tiny, "--out", "{OUT}", "--json"]), bias.clone()].concat(),
            numeric: vec![],
            files: vec![FileArg::Positional(6), FileArg::Flag("--instrument")],
            out_name: Some("bias.fits"),
        },
        Template {
            command: "master-flat",
            args: [s(&["master-flat", "--instrument", &tiny, "--out", "{OUT}", "--json"]), flats].concat(),
            numeric: vec![],
            files: vec![FileArg::Positional(6), FileArg::Flag("--instrument")],
            out_name: Some("flat.fits"),
        },
        Template {
            command: "zero-angle",
            args: with_frames(s(&[
                "zero-angle",
                "--instrument",
                &ins,
                "--x",
                "20",
                "--y",
                "24",
                "--chi-deg",
                "30",
                "--aperture",
                "3",
                "--annulus",
                "4,6",
                "--json",
            ])),
            numeric: vec![],
            files: vec![FileArg::Positional(14), FileArg::Flag("--instrument")],
            out_name: None,
        },
        Template {
            command: "fit-standards",
            args: s(&["fit-standards", &f.s("standards.csv"), "--model", "wiersema", "--json"]),
            numeric: vec![],
            files: vec![FileArg::Positional(1)],
            out_name: None,
        },
        Template {
            command: "stokes",
            args: s(&["stokes", "--input", &f.s("f.csv"), "--json"]),
            numeric: vec!["--kappa"],
            files: vec![FileArg::Flag("--input")],
            out_name: None,
        },
        Template {
            command: "stokes --plot",
            args: s(&["stokes", "--input", &f.s("f.csv"), "--plot", "{OUT}"]),
            numeric: vec![],
            files: vec![FileArg::Flag("--input")],
            out_name: Some("fourier.png"),
        },
        Template {
            command: "bias",
            args: s(&["bias", "--p", "0.01", "--sigma", "0.003", "--json"]),
            numeric: vec!["--p", "--sigma", "--cl", "--chi", "--sigma-q", "--sigma-u"],
            files: vec![],
            out_name: None,
        },
        Template {
            command: "mc",
            args: s(&["mc", "--trials", "2000", "--json"]),
            numeric: vec![
                "--n-hwp",
                "--snr",
                "--p0",
                "--chi0",
                "--trials",
                "--seed",
                "--threads",
                "--sky",
                "--read-noise",
            ],
            files: vec![],
            out_name: None,
        },
        Template {
            command: "fresnel",
            args: s(&["fresnel", "--n-real", "1.5", "--aoi-deg", "10", "--json"]),
            numeric: vec!["--n-real", "--n-imag", "--aoi-deg", "--wavelength-nm", "--n-incident"],
            files: vec![],
            out_name: None,
        },
        Template {
            command: "raytrace",
            args: s(&["raytrace", "--instrument", "fors1", "--json"]),
            numeric: vec!["--wavelength-nm", "--field-points", "--pupil-rays"],
            files: vec![],
            out_name: None,
        },
        Template {
            command: "reduce",
            args: with_frames(s(&["reduce", "--instrument", &ins, "--bin", "8", "--out", "{OUT}", "--json"])),
            numeric: vec!["--bin", "--nsigma"],
            files: vec![FileArg::Positional(8), FileArg::Flag("--instrument")],
            out_name: Some("map.fits"),
        },
        Template {
            command: "catalog",
            args: with_frames(s(&[
                "catalog",
                "--instrument",
                &ins,
                "--fwhm",
                "3",
                "--aperture",
                "3",
                "--annulus",
                "4,6",
                "--out",
                "{OUT}",
                "--json",
            ])),
            numeric: vec!["--fwhm", "--threshold", "--pair-tol", "--aperture"],
            files: vec![FileArg::Positional(12), FileArg::Flag("--instrument")],
            out_name: Some("cat.csv"),
        },
        Template {
            command: "photometry",
            args: with_frames(s(&[&["photometry"][..], &star[..], &["--json"]].concat())),
            numeric: vec!["--x", "--y", "--aperture"],
            files: vec![FileArg::Positional(12), FileArg::Flag("--instrument")],
            out_name: None,
        },
        Template {
            command: "calibrate",
            args: s(&[
                "calibrate",
                "--map",
                &f.s("map.fits"),
                "--instrument",
                &ins,
                "--sky-p",
                "2",
                "--sky-chi",
                "30",
                "--out",
                "{OUT}",
                "--json",
            ]),
            numeric: vec!["--sky-p", "--sky-chi", "--bin"],
            files: vec![FileArg::Flag("--map"), FileArg::Flag("--instrument")],
            out_name: Some("cal.fits"),
        },
        Template {
            command: "fit",
            args: s(&["fit", &f.s("cal.fits"), "--out", "{OUT}", "--json"]),
            numeric: vec![],
            files: vec![FileArg::Positional(1)],
            out_name: Some("refit.fits"),
        },
        Template {
            command: "plot",
            args: s(&["plot", &f.s("cal.fits"), "--out", "{OUT}", "--json"]),
            numeric: vec![],
            files: vec![FileArg::Positional(1)],
            out_name: None,
        },
        Template {
            command: "correct (catalog)",
            args: s(&["correct", "--cal", &f.s("cal.fits"), "--in", &f.s("cat.csv"), "--out", "{OUT}", "--json"]),
            numeric: vec!["--extrapolation-error"],
            files: vec![FileArg::Flag("--cal"), FileArg::Flag("--in")],
            out_name: Some("cat_out.csv"),
        },
        Template {
            command: "correct (map)",
            args: s(&["correct", "--cal", &f.s("cal.fits"), "--in", &f.s("map.fits"), "--out", "{OUT}", "--json"]),
            numeric: vec![],
            files: vec![FileArg::Flag("--in")],
            out_name: Some("map_out.fits"),
        },
        Template {
            command: "validate",
            args: with_frames(s(&[&["validate", "--cal", &f.s("cal.fits")][..], &star[..], &["--json"]].concat())),
            numeric: vec!["--x", "--y", "--aperture", "--threshold"],
            files: vec![FileArg::Flag("--cal"), FileArg::Positional(14), FileArg::Flag("--instrument")],
            out_name: None,
        },
        Template {
            command: "wavelength-law",
            args: s(&["wavelength-law", &f.s("cal.fits"), &f.s("cal2.fits"), "--json"]),
            numeric: vec!["--r-min", "--r-max"],
            files: vec![FileArg::Positional(1)],
            out_name: None,
        },
        Template {
            command: "simulate",
            args: s(&["simulate", &f.s("scene.toml"), "--out", "{OUT}", "--json"]),
            numeric: vec![],
            files: vec![FileArg::Positional(1)],
            out_name: None,
        },
    ]
}

/// Set `flag` to `value` (replacing the value after it, or appending both).
fn set_flag(args: &mut Vec<String>, flag: &str, value: &str) {
    match args.iter().position(|a| a == flag) {
        Some(i) => args[i + 1] = value.to_string(),
        None => args.extend([flag.to_string(), value.to_string()]),
    }
}

fn file_index(args: &[String], fa: &FileArg) -> usize {
    match fa {
        FileArg::Flag(f) => args.iter().position(|a| a == f).unwrap() + 1,
        FileArg::Positional(i) => *i,
    }
}

/// A hostile stand-in for the input file `orig`, made in `dir`; None for variants that need
/// no file (missing).
fn variant(kind: &str, orig: &Path, dir: &Path) -> PathBuf {
    let ext = orig.extension().map(|e| e.to_string_lossy().to_string()).unwrap_or_default();
    let p = dir.join(format!("hostile_{kind}.{ext}"));
    match kind {
        "empty" => std::fs::write(&p, b"").unwrap(),
        "text" => std::fs::write(&p, b"this is not the file you are looking for\n").unwrap(),
        "truncated" => {
            let b = std::fs::read(orig).unwrap();
            let n = if b.len() > 3000 { 3000 } else { b.len() / 2 };
            std::fs::write(&p, &b[..n]).unwrap();
        }
        "garbage" => {
            let b: Vec<u8> = (0..5000u32).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8).collect();
            std::fs::write(&p, b).unwrap();
        }
        "directory" => std::fs::create_dir_all(&p).unwrap(),
        "missing" => {}
        "symlink-loop" => {
            let q = dir.join(format!("hostile_loop2.{ext}"));
            std::os::unix::fs::symlink(&q, &p).unwrap();
            std::os::unix::fs::symlink(&p, &q).unwrap();
        }
        "dev-null" => return PathBuf::from("/dev/null"),
        _ => unreachable!(),
    }
    p
}

const FILE_VARIANTS: &[&str] =
    &["empty", "text", "truncated", "garbage", "directory", "missing", "symlink-loop", "dev-null"];

/// The files of the fixture (for the hash check) named in `args`.
fn files_in(args: &[String]) -> Vec<PathBuf> {
    args.iter().map(PathBuf::from).filter(|p| p.is_file()).collect()
}

fn cases(f: &Fixture, root: &Path) -> Vec<Case> {
    let mut out = vec![];
    let spec = spec();
    let (numbers, texts, paths) =
        (flags_of_kind(&spec, "number"), flags_of_kind(&spec, "text"), flags_of_kind(&spec, "path"));
    let n = AtomicUsize::new(0);
    let new_dir = || {
        let d = root.join(format!("c{:04}", n.fetch_add(1, Ordering::Relaxed)));
        std::fs::create_dir_all(&d).unwrap();
        d
    };
    for t in templates(f) {
        let fill = |args: &[String], dir: &Path| -> (Vec<String>, Vec<PathBuf>) {
            let o = t.out_name.map(|n| dir.join(n)).unwrap_or_else(|| dir.join("plots"));
            let a =
                args.iter().map(|x| if x == "{OUT}" { o.to_str().unwrap().to_string() } else { x.clone() }).collect();
            (a, t.out_name.map(|_| vec![o]).unwrap_or_default())
        };
        // The valid invocation itself (a control: it must not fail for a reason of its own).
        {
            let dir = new_dir();
            let (args, outputs) = fill(&t.args, &dir);
            out.push(Case { command: t.command, what: "valid".into(), inputs: files_in(&args), args, outputs, dir });
        }
        // The valid invocation with `flag` set to `value`, in the case's folder `dir`.
        let with_flag = |flag: &str, value: &str, what: String, dir: PathBuf| {
            let mut a = t.args.clone();
            set_flag(&mut a, flag, value);
            let (args, outputs) = fill(&a, &dir);
            Case { command: t.command, what, inputs: files_in(&args), args, outputs, dir }
        };
        // Every input-file option the command has but its valid invocation does not use
        // (`--bias`, `--flat`, `--standards`, ...), given each hostile variant; outputs are
        // named by the convention the CLI's own test checks (out*, plot*, *-out, *-dir).
        let is_output = |f: &str| {
            f.starts_with("--out")
                || f.starts_with("--plot")
                || f.ends_with("-out")
                || f.ends_with("-dir")
                || f == "--products"
        };
        for flag in paths.get(&t.args[0]).into_iter().flatten() {
            if is_output(flag) || t.args.contains(flag) {
                continue;
            }
            for kind in FILE_VARIANTS {
                let dir = new_dir();
                let v = variant(kind, &f.p("map.fits"), &dir);
                out.push(with_flag(flag, v.to_str().unwrap(), format!("{flag} {kind}"), dir));
            }
        }
        // Every text option at its edges (the instrument's name is a file argument's business).
        let texts = texts.get(&t.args[0]).into_iter().flatten().filter(|f| *f != "--instrument");
        // Every numeric flag of the command, those listed and those its definition has.
        let defined = numbers.get(&t.args[0]).into_iter().flatten().filter(|f| !t.numeric.contains(&f.as_str()));
        let numeric = t.numeric.iter().map(|f| f.to_string()).chain(defined.cloned());
        let edges = texts.map(|f| (f.clone(), TEXT_EDGES)).chain(numeric.map(|f| (f, EDGES)));
        for (flag, values) in edges {
            for v in values {
                out.push(with_flag(&flag, v, format!("{flag} {v:?}"), new_dir()));
            }
        }
        for fa in &t.files {
            let label = match fa {
                FileArg::Flag(fl) => fl.to_string(),
                FileArg::Positional(i) => format!("arg {i}"),
            };
            for kind in FILE_VARIANTS {
                let dir = new_dir();
                let mut a = t.args.clone();
                let i = file_index(&a, fa);
                a[i] = variant(kind, Path::new(&a[i]), &dir).to_str().unwrap().to_string();
                let (args, outputs) = fill(&a, &dir);
                out.push(Case {
                    command: t.command,
                    what: format!("{label} {kind}"),
                    inputs: files_in(&args),
                    args,
                    outputs,
                    dir,
                });
            }
            // The input given as the output (a copy, so the fixture stays intact): refused,
            // and the file unchanged.
            if t.out_name.is_some() {
                let dir = new_dir();
                let mut a = t.args.clone();
                let i = file_index(&a, fa);
                let copy = dir.join(Path::new(&a[i]).file_name().unwrap());
                std::fs::copy(&a[i], &copy).unwrap();
                a[i] = copy.to_str().unwrap().to_string();
                let o = a.iter().position(|x| x == "{OUT}").unwrap();
                a[o] = a[i].clone();
                let inputs = files_in(&a);
                out.push(Case {
                    command: t.command,
                    what: format!("{label} same as --out"),
                    args: a,
                    outputs: vec![],
                    inputs,
                    dir,
                });
            }
        }
        // Hostile output names: a symlink to an input (refused, input unchanged), a folder
        // that does not exist, an existing folder, a name in /proc (not writable).
        if let Some(name) = t.out_name {
            for kind in ["symlink-to-input", "missing-folder", "is-a-folder", "proc"] {
                let dir = new_dir();
                let o = match kind {
                    "symlink-to-input" => {
                        let i = file_index(&t.args, &t.files[0]);
                        let copy = dir.join(format!(
                            "input_copy_{}",
                            Path::new(&t.args[i]).file_name().unwrap().to_string_lossy()
                        ));
                        std::fs::copy(&t.args[i], &copy).unwrap();
                        let link = dir.join(name);
                        std::os::unix::fs::symlink(&copy, &link).unwrap();
                        let mut a = t.args.clone();
                        a[i] = copy.to_str().unwrap().to_string();
                        let o = a.iter().position(|x| x == "{OUT}").unwrap();
                        a[o] = link.to_str().unwrap().to_string();
                        let inputs = files_in(&a);
                        out.push(Case {
                            command: t.command,
                            what: format!("--out {kind}"),
                            args: a,
                            outputs: vec![],
                            inputs,
                            dir,
                        });
                        continue;
                    }
                    "missing-folder" => dir.join("no/such/folder").join(name),
                    "is-a-folder" => {
                        std::fs::create_dir_all(dir.join(name)).unwrap();
                        dir.join(name)
                    }
                    _ => PathBuf::from("/proc/instpol_hostile").join(name),
                };
                let a: Vec<String> = t
                    .args
                    .iter()
                    .map(|x| if x == "{OUT}" { o.to_str().unwrap().to_string() } else { x.clone() })
                    .collect();
                let outputs = if kind == "is-a-folder" { vec![] } else { vec![o.clone()] };
                out.push(Case {
                    command: t.command,
                    what: format!("--out {kind}"),
                    inputs: files_in(&a),
                    args: a,
                    outputs,
                    dir,
                });
            }
        }
        // The same input file twice (frames): refused, naming it.
        if let Some(FileArg::Positional(i)) = t.files.iter().find(|fa| matches!(fa, FileArg::Positional(_))) {
            if t.command != "fit" && t.command != "plot" && t.command != "simulate" {
                let dir = new_dir();
                let mut a = t.args.clone();
                a[i + 1] = a[*i].clone();
                let (args, outputs) = fill(&a, &dir);
                out.push(Case {
                    command: t.command,
                    what: format!("arg {i} twice"),
                    inputs: files_in(&args),
                    args,
                    outputs,
                    dir,
                });
            }
        }
    }
    // Scene keys at their edges.
    let keys: &[(&str, &str)] = &[
        ("exposure_s = 10.0", "exposure_s = {}"),
        ("seed = 3", "seed = {}"),
        ("brightness_e = 20000", "brightness_e = {}"),
        ("p = 0.02", "p = {}"),
        ("x = 48", "x = {}"),
        ("flux_e = 200000", "flux_e = {}"),
        ("fwhm_arcsec = 8.0", "fwhm_arcsec = {}"),
        ("read_noise_e = 3.0", "read_noise_e = {}"),
        ("rate_per_frame = 2", "rate_per_frame = {}"),
    ];
    for (orig, pat) in keys {
        for v in TOML_EDGES {
            let dir = new_dir();
            let scene = dir.join("scene.toml");
            let text = SCENE
                .replacen(orig, &pat.replace("{}", v), 1)
                .replace("\"mini.toml\"", &format!("{:?}", f.s("mini.toml")));
            std::fs::write(&scene, text).unwrap();
            let args = ["simulate", scene.to_str().unwrap(), "--out", dir.join("frames").to_str().unwrap(), "--json"]
                .map(String::from)
                .to_vec();
            out.push(Case {
                command: "simulate (scene keys)",
                what: format!("{orig} -> {v}"),
                inputs: files_in(&args),
                args,
                outputs: vec![],
                dir,
            });
        }
    }
    out
}

fn hash(p: &Path) -> Option<u64> {
    use std::hash::{Hash, Hasher};
    let b = std::fs::read(p).ok()?;
    let mut h = std::collections::hash_map::DefaultHasher::new();
    b.hash(&mut h);
    Some(h.finish())
}

/// Every file below `dir` (for the whole-fixture check), with its hash.
fn tree(dir: &Path) -> BTreeMap<PathBuf, Option<u64>> {
    let mut m = BTreeMap::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            m.extend(tree(&p));
        } else {
            let h = hash(&p);
            m.insert(p, h);
        }
    }
    m
}

fn temporaries(dir: &Path) -> Vec<String> {
    let mut v = vec![];
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            if name.starts_with(".instpol-") {
                v.push(e.path().display().to_string());
            } else if e.path().is_dir() && !e.path().is_symlink() {
                v.extend(temporaries(&e.path()));
            }
        }
    }
    v
}

/// Run one case; returns (exit code or -signal, a failure description if any).
fn run_case(c: &Case) -> (i32, Option<String>) {
    let before: Vec<Option<u64>> = c.inputs.iter().map(|p| hash(p)).collect();
    let (so, se) = (c.dir.join("stdout.txt"), c.dir.join("stderr.txt"));
    let mut child = Command::new(common::bin())
        .args(&c.args)
        .current_dir(&c.dir)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&so).unwrap())
        .stderr(std::fs::File::create(&se).unwrap())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break Some(s);
        }
        if t0.elapsed() > TIMEOUT {
            child.kill().ok();
            child.wait().ok();
            break None;
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let err = std::fs::read_to_string(&se).unwrap_or_default();
    let mut problems = vec![];
    let code = match status {
        None => {
            problems.push(format!("hang: killed after {TIMEOUT:?}"));
            -999
        }
        Some(s) => {
            use std::os::unix::process::ExitStatusExt;
            match (s.code(), s.signal()) {
                (Some(k), _) => k,
                (None, Some(sig)) => -sig,
                _ => -998,
            }
        }
    };
    if err.contains("panicked at") || code == 101 {
        problems.push("panic".into());
    }
    if code < 0 && code != -999 {
        problems.push(format!("killed by signal {}", -code));
    }
    if code >= 0 && ![0, 1, 2].contains(&code) {
        problems.push(format!("exit code {code}"));
    }
    for (p, h) in c.inputs.iter().zip(&before) {
        if hash(p) != *h {
            problems.push(format!("input {} modified", p.display()));
        }
    }
    if code != 0 {
        for o in &c.outputs {
            if o.exists() {
                problems.push(format!("failed (exit {code}) but left {}", o.display()));
            }
        }
    }
    let t = temporaries(&c.dir);
    if !t.is_empty() {
        problems.push(format!("temporaries left: {t:?}"));
    }
    if problems.is_empty() {
        (code, None)
    } else {
        let last = err.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("").chars().take(300).collect::<String>();
        (code, Some(format!("{}: {} -> {} [stderr: {last}]", c.command, c.what, problems.join("; "))))
    }
}

/// Every command of the CLI has a valid invocation in [`templates`] or is in [`NOT_YET`] with
/// its reason, and nothing is listed that the CLI does not have: a new command cannot pass
/// untried without a word.
#[test]
fn every_command_is_tried_or_says_why_not() {
    let f = fixture();
    let tried: std::collections::BTreeSet<String> = templates(&f).iter().map(|t| t.args[0].clone()).collect();
    let spec = flags_of_kind(&spec(), "number");
    let mut wrong = vec![];
    for name in spec.keys() {
        let listed = NOT_YET.iter().any(|(n, _)| n == name);
        match (tried.contains(name), listed) {
            (false, false) => wrong.push(format!("{name}: no valid invocation in templates() and not in NOT_YET")),
            (true, true) => wrong.push(format!("{name}: tried and also listed in NOT_YET")),
            _ => {}
        }
    }
    for (n, _) in NOT_YET {
        if !spec.contains_key(*n) {
            wrong.push(format!("{n}: listed in NOT_YET but the CLI has no such command"));
        }
    }
    assert!(spec.len() >= 28, "{} commands", spec.len());
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

#[test]
fn hostile_inputs() {
    let t0 = Instant::now();
    let f = fixture();
    let fixture_before = tree(f.dir.path());
    let root = tempfile::tempdir().unwrap();
    let cases = cases(&f, root.path());
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, i32, Option<String>)>> = Mutex::new(vec![]);
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2).clamp(2, 8);
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                let Some(c) = cases.get(k) else { break };
                let (code, fail) = run_case(c);
                results.lock().unwrap().push((k, code, fail));
            });
        }
    });
    let mut results = results.into_inner().unwrap();
    results.sort_by_key(|r| r.0);
    let mut failures: Vec<String> = results.iter().filter_map(|r| r.2.clone()).collect();
    // A file that is not what its argument takes (empty, text, garbage, a folder, missing, a
    // loop, /dev/null) is never accepted with exit 0, even by an option the run did not need.
    // (A truncated text file can be a valid shorter one: not counted.)
    for (k, code, _) in &results {
        let c = &cases[*k];
        let hostile_file =
            FILE_VARIANTS.iter().filter(|v| **v != "truncated").any(|v| c.what.ends_with(&format!(" {v}")));
        if hostile_file && *code == 0 && c.command != "simulate (scene keys)" {
            failures.push(format!("{}: {} -> exit 0: a file that is not one was accepted", c.command, c.what));
        }
    }
    // The valid invocations must succeed (exit 0), or the cases test nothing.
    for (k, code, _) in &results {
        if cases[*k].what == "valid" && *code != 0 {
            let err = std::fs::read_to_string(cases[*k].dir.join("stderr.txt")).unwrap_or_default();
            failures.push(format!("{}: the valid control exits {code}: {err}", cases[*k].command));
        }
    }
    // Nothing in the shared fixture changed (each case also checks its own inputs).
    if tree(f.dir.path()) != fixture_before {
        failures.push("the fixture folder changed".into());
    }
    let mut table: BTreeMap<&str, [usize; 5]> = BTreeMap::new();
    for (k, code, fail) in &results {
        let row = table.entry(cases[*k].command).or_default();
        row[0] += 1;
        match code {
            0 => row[1] += 1,
            1 => row[2] += 1,
            2 => row[3] += 1,
            _ => {}
        }
        if fail.is_some() {
            row[4] += 1;
        }
    }
    let mut text =
        String::from("| command | cases | exit 0 | exit 1 | exit 2 | failures |\n|---|---|---|---|---|---|\n");
    let mut tot = [0usize; 5];
    for (cmd, r) in &table {
        text += &format!("| {cmd} | {} | {} | {} | {} | {} |\n", r[0], r[1], r[2], r[3], r[4]);
        for i in 0..5 {
            tot[i] += r[i];
        }
    }
    text += &format!("| **all** | {} | {} | {} | {} | {} |\n", tot[0], tot[1], tot[2], tot[3], tot[4]);
    println!("{text}");
    if std::env::var_os("HOSTILE_ZERO").is_some() {
        for (k, code, _) in &results {
            if *code == 0 && cases[*k].what != "valid" {
                println!("exit0: {} {}", cases[*k].command, cases[*k].what);
            }
        }
    }
    println!("{} cases on {threads} threads in {:.1} s", results.len(), t0.elapsed().as_secs_f64());
    if let Ok(p) = std::env::var("HOSTILE_TABLE") {
        std::fs::write(p, &text).unwrap();
    }
    assert!(results.len() >= 500, "only {} cases", results.len());
    assert!(failures.is_empty(), "{} failures:\n{}", failures.len(), failures.join("\n"));
}
