//! A generator of hostile inputs: cases are produced by code, not listed by hand, so that the
//! next few hundred inputs someone tries have already been tried. Every command of the CLI
//! (read from its own definition, `instpol cli-spec`) has a valid invocation
//! (`common::invocations::templates`), and each case changes one thing in it. The cases come
//! in classes, each with its properties:
//!
//! - `numeric`: every numeric flag x edge values (0, -0, negative, NaN, inf, -inf, 1e300,
//!   -1e300, 1e-300, 1e308, subnormal, huge counts, text, empty);
//! - `range`: a fraction option given a percentage (50 for 0.5) must be refused (exit 2) naming
//!   the flag; an angle option in degrees given radians (0.785) and a percent option given a
//!   fraction (0.5) are tried (nothing more is decidable without knowing the intent);
//! - `turn`: every orientation option ([`ORIENTATIONS`]: a polarization angle, plate angles, a
//!   zero angle, a sector) given a value and the same value a full turn (360 deg) further: the
//!   command prints the same numbers (but for the echoed angle, a whole number of turns off) or
//!   refuses the turned value naming the flag. An option read in radians fails it (360 rad is
//!   not a whole number of turns); every angle option in degrees is in [`ORIENTATIONS`] or in
//!   [`NOT_ORIENTATIONS`] with its reason;
//! - `text`: every text option (`--aperture 2.5fwhm`, `--annulus 12,20`, `--parang`, ...) x text
//!   edges (empty, NaN, "1e999", "-1", "2,", ",", "inf,inf", 5000 characters, non-UTF-8);
//! - `file`: every input-file argument of the invocation, and every input-file option the
//!   command has but the invocation does not use, x file variants (empty, text, truncated,
//!   binary garbage, a directory, missing, a symlink loop, /dev/null): a file that is not one
//!   (all but the truncation) is never accepted with exit 0;
//! - `output over input`: every output argument named like every input (the same path, a hard
//!   link, a symlink) must be refused (exit 2) with the input byte-identical;
//! - `output name`: an output in a missing folder, one that is a folder, one in /proc;
//! - `duplicate input`: every input-file argument of the invocation that takes a list (frames,
//!   catalogs, tables, calibrations, plans, folders) given its first file a second time, after
//!   it, under another name (the same path, a copy, a hard link, a symlink; a folder by its
//!   path and a symlink). The command refuses it (exit 2) naming both names, or uses it once
//!   and names both (a warning, or the plan's list of what it left out) with the numbers of
//!   the valid invocation (its `--json`), never counting it twice. (A single input has no
//!   second place in its role; the same bytes in two roles, a Q and a U map both zero, are two
//!   inputs);
//! - `another product`: in every command that combines two inputs that say which instrument
//!   and filter they are of (a calibration file, a Stokes map, a catalog with its keywords,
//!   frames), each of them in turn replaced by a copy that says another filter, then another
//!   instrument: refused (exit 2) naming it, or, where the command combines them on purpose
//!   ([`PRODUCT_ON_PURPOSE`]), warned naming it; never a number with exit 0;
//! - `units`: every table a command reads, with one column at a time declaring a unit (ECSV,
//!   FITS, VOTable: %, deg, rad, arcmin, arcsec, pix) and its values converted: the command
//!   honours it (the numbers it prints equal those of the plain table) or refuses it (exit 2)
//!   naming the column;
//! - `scene keys`: every numeric key of a scene file x TOML edges (nan, inf, 1e308, text, ...);
//! - `collapsed`: every CSV table a command reads (all of a list at once) with its positions
//!   collapsed onto a point or onto the line `y = 0.5 x + 0.2`, or its angles onto one
//!   ([`POSITION_PAIRS`], [`ANGLE_COLUMNS`]): a fitting command ([`FITTERS`]) must refuse
//!   (exit 2) saying what the data do not determine, wherever the collapse leaves a parameter
//!   free (a point; a line under a plane; one parallactic angle under the oxide model);
//! - `plate set`: every list of frames (the positional argument taking several; calibrate
//!   given frames in place of its map) with one frame dropped, a set missing a plate angle:
//!   refused (exit 2) or reduced (exit 0), either way naming the missing angle ("missing [");
//! - `edited input` (in `hostile_edited.rs`, which runs `instpol run` over one-unit plans): every
//!   command a night's unit may run, its command line's files edited one at a time after a run:
//!   the unit is never called up to date.
//!
//! Every case runs the built binary with a timeout (killed after [`TIMEOUT`]) and must: not
//! panic ("panicked at", exit 101, or a signal such as SIGABRT/SIGSEGV), not hang, exit 0, 1
//! or 2, leave its input files byte-identical, and on failure leave no file under the final
//! output name and no temporary. Cases run on all cores; the inputs are tiny. The results table
//! (cases per command and class, and failures) is printed; `HOSTILE_TABLE=path` also writes it.
//!
//! The generator (with full_disk.rs, which tries every output argument of the definition on a
//! full disk) must fail when a class is broken in any one command. Checked by hand (a switch in
//! release code for a test is not wanted): break one command on a scratch commit, run
//! `cargo test --no-fail-fast -p instpol --test it -- hostile:: full_disk::`, and see it fail;
//! then drop the commit. Done once each, with these mutations:
//!
//! 1. an input check removed: the two `util::check_output` calls of `instpol scan`
//!    (crates/cli/src/cmd/night.rs) taken out. 12 `output over input` cases of scan fail, e.g.
//!    "scan [output over input]: --out = --instrument (same path) -> input
//!    .../input_tiny_fors2.toml modified; exit 0, not refused (exit 2)";
//! 2. a broken writer: `stokes --plot` drawn straight onto its final name
//!    (`BitMapBackend::new(path)` in crates/cli/src/cmd/stokes_plot.rs instead of
//!    `plot::save_image`). full_disk.rs fails: "stokes --plot --plot: a full disk must fail the
//!    command" (exit 0 under the injected fsync failure), and on a real full tmpfs "stokes --plot
//!    --plot: left [\"fourier.png\"]".
//! 3. an angle read in radians: `bias --chi` and `mc --chi0` passed on without `to_radians()`
//!    (crates/cli/src/cmd/bias.rs, mc.rs). The `turn` class fails for both: "bias [turn]: --chi
//!    390 (a turn further) -> exit 0 with other numbers than a full turn back: the angle is not
//!    read in degrees", and the same for mc.
//! 4. the same input counted twice: in `instpol fit-standards`, the definition's duplicate
//!    check skipped (`util::guard_arguments`) and the repeated measurements found but kept
//!    (crates/cli/src/cmd/fit_standards.rs). The `duplicate input` class fails for its four
//!    names: "fit-standards [duplicate input]: files twice (copy) -> exit 0 with other numbers
//!    than the input once: counted twice", the same for the same path, a hard link and a
//!    symlink. (With the check skipped alone nothing fails: the repeated rows are then used
//!    once, naming both files, with the numbers of the table once, which the property allows.)
//! 5. a combination not checked: a catalog's rows corrected without what its table says it is
//!    (`data: None` in `fit::correction::columns::TableAngles::request`). The `another product` class
//!    fails four cases of `correct (catalog)`, e.g. "correct (catalog) [another product]:
//!    cat.csv of another filter -> exit 0, not refused (exit 2)".
//! 6. a fit the data do not determine: the conditioning judge's call taken out of the
//!    polynomial field's solve (crates/fit/src/models/poly.rs). The `collapsed` class fails:
//!    "calibrate-stars [collapsed]: x_arcmin,y_arcmin onto a line, a plane -> refused without
//!    naming do not determine" (the failed inverse's words, where it refuses at all).
//! 7. a plate-angle set reduced silently: `instpol photometry` grouping its frames without the
//!    completeness check and not printing the note that names the gap
//!    (crates/cli/src/cmd/photometry.rs). The `plate set` class fails: "photometry [plate set]:
//!    frames without frame_01_hwp022.5.fits -> exit 0 without naming the missing plate angle".

use crate::common;

use common::invocations::{self, fill, Fixture, Template};
use std::collections::BTreeMap;
use std::ffi::OsString;
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
    "1e300",
    "-1e300",
    "1e-300",
    "1e308",
    "-1e308",
    "1e-308",
    "5e-324",
    "18446744073709551616",
    "99999999999",
    "abc",
    "",
];

/// Stands for a value that is not UTF-8 (the bytes FF FE), which a `String` cannot hold.
const NON_UTF8: &str = "\u{0}non-utf8";

/// Values given to every text option (a number or a list the command parses itself:
/// `--aperture 2.5fwhm`, `--annulus 12,20`, `--parang 10,20`, `--sky EMPTY:1.7:-53`).
fn text_edges() -> Vec<String> {
    let mut v: Vec<String> =
        ["", "NaN", "inf,inf", "-1", "1e308", "1e999", "abc", ",", "2,", "1,2,3,4,5,6", "0:0:0", "\u{1F600}", NON_UTF8]
            .map(String::from)
            .to_vec();
    v.push("9".repeat(5000));
    v
}

/// TOML literals given to every numeric key of a scene.
const TOML_EDGES: &[&str] = &["0", "-0.0", "-1", "nan", "inf", "-inf", "1e308", "1e-308", "1e12", "\"text\""];

/// File arguments that take anything by design, listing what is not what they want with the
/// reason and going on (command, argument, why): not held to "a file that is not one is never
/// accepted with exit 0".
const LEFT_OUT_BY_DESIGN: &[(&str, &str, &str)] =
    &[("scan", "dirs", "a night's folder holds other files: scan lists each unusable one with the reason")];

/// Defects the generator finds that are not fixed yet (command, class, case, what is wrong): each
/// is reported, none fails the test, and one that no longer fails does (take it off the list).
/// Anything else that fails is new and fails the test.
const KNOWN: &[(&str, &str, &str, &str)] = &[];

/// What a case must show beyond the properties every case has.
#[derive(Clone)]
enum Expect {
    Nothing,
    /// A file that is not one: never exit 0.
    NotAccepted,
    /// Exit 2, the message naming one of these.
    Refused(Vec<String>),
    /// Exit 2 naming `word`, or exit 0 or 1 with a warning naming it (a combination a command
    /// makes on purpose, such as `validate` showing a calibration of another filter fail).
    RefusedOrWarned(String),
    /// Exit 0 with the numbers of the valid invocation (case index), or exit 2 naming the column.
    SameOrRefused {
        reference: usize,
        column: String,
    },
    /// The case `reference` must exit 0; this one, its orientation a full turn further, exits 0
    /// with its numbers (each the same, or a whole number of turns off) or 2 naming `flag`.
    SameTurned {
        reference: usize,
        flag: String,
    },
    /// An input under two names: exit 2 naming both `names`, or exit 0 naming both with the
    /// numbers of the valid invocation (case index `reference`).
    Once {
        reference: usize,
        names: Vec<String>,
    },
    /// A set of plate angles with one dropped: refused (exit 2) or reduced (exit 0), either way
    /// with the missing angle named ("missing" in the messages); never a silent number.
    MissingNamed,
}

/// How an orientation option's value is turned a full turn further: every number in it (a
/// single angle, a list of plate angles, a sector `sector:FROM:TO`), the number after its last
/// `:` (`P_PERCENT:CHI_DEG`, `MAP:P_PERCENT:CHI_DEG`), or the one after its `,` (`P,CHI`).
#[derive(Clone, Copy)]
enum Turn {
    Every,
    AfterLastColon,
    AfterComma,
}

/// Orientation options in degrees, by template (`Template::command`): the flag, the value tried
/// (`None`: the template's own), how it turns, and arguments added to both cases where the
/// template's own do not let the angle matter (`bias --chi` acts with unequal errors only). Moved by a full turn they name the same
/// orientation (a polarization angle repeats every 180 deg, a plate angle every 90, a sector
/// every 360).
const ORIENTATIONS: &[(&str, &str, Option<&str>, Turn, &[&str])] = &[
    ("calibrate", "--sky-chi", None, Turn::Every, &[]),
    ("calibrate", "--exclude", Some("sector:10:80"), Turn::Every, &[]),
    ("calibrate-stars", "--exclude", Some("sector:10:80"), Turn::Every, &[]),
    ("calibrate-stars", "--interstellar", Some("0.5,30"), Turn::AfterComma, &[]),
    ("calibrate-mueller", "--field", None, Turn::AfterLastColon, &[]),
    ("fit", "--exclude", Some("sector:10:80"), Turn::Every, &[]),
    ("plan", "--candidate", None, Turn::AfterLastColon, &[]),
    ("reduce", "--hwp-angles", Some("0,22.5,45,67.5"), Turn::Every, &[]),
    ("photometry", "--hwp-angles", Some("0,22.5,45,67.5"), Turn::Every, &[]),
    ("catalog", "--hwp-angles", Some("0,22.5,45,67.5"), Turn::Every, &[]),
    ("zero-angle", "--hwp-angles", Some("0,22.5,45,67.5"), Turn::Every, &[]),
    ("zero-angle", "--chi-deg", None, Turn::Every, &[]),
    ("validate", "--hwp-angles", Some("0,22.5,45,67.5"), Turn::Every, &[]),
    ("explain", "--hwp-angles", Some("0,22.5,45,67.5"), Turn::Every, &[]),
    ("import-map", "--zero-angle", Some("2.5"), Turn::Every, &[]),
    ("bias", "--chi", Some("30"), Turn::Every, &["--sigma-q", "0.002", "--sigma-u", "0.004"]),
    ("mc", "--chi0", Some("30"), Turn::Every, &[]),
];

/// Options in degrees (or that speak of angles) that are not orientations, or that the
/// fixture's invocations cannot exercise, with why (by command name).
const NOT_ORIENTATIONS: &[(&str, &str, &str)] = &[
    ("fresnel", "--aoi-deg", "an angle of incidence in [0, 90), not periodic"),
    ("mc", "--n-hwp", "a number of plate angles"),
    ("zero-angle", "--sigma-chi-deg", "an error, not an orientation"),
    (
        "zero-angle",
        "--standard",
        "X,Y:CHI_DEG+-SIGMA_DEG names the stars --x, --y and --chi-deg name (tried) and replaces them; its angle is read by the same parser",
    ),
    (
        "calibrate",
        "--hwp-angles",
        "applies to frames; the fixture calibrates from a reduced map (refused beside it); the frames' --hwp-angles is tried in reduce, photometry, catalog, zero-angle and validate",
    ),
    ("scan", "--sky", "the fixture's night takes its skies from a table (skies.csv); TARGET:P:CHI is the --field form of calibrate-mueller, tried"),
    (
        "correct",
        "--parang",
        "needs a telescope model, which the fixture's calibration has not (refused); a parallactic track a turn further is checked by crates/cli/tests/it/telescope_frames.rs",
    ),
    (
        "correct",
        "--rotator",
        "needs a telescope model fitted with rotator angles, which the fixture's calibration has not (refused)",
    ),
    ("validate", "--parang", "needs a telescope calibration, which the fixture's calibration has not (refused)"),
];

/// Whether an option of the CLI's definition takes an angle in degrees: its help speaks of an
/// angle (or chi) and of degrees.
fn is_angle_in_degrees(a: &serde_json::Value) -> bool {
    let h = a["help"].as_str().unwrap_or("").to_ascii_lowercase();
    ["number", "text"].contains(&a["kind"].as_str().unwrap_or(""))
        && (h.contains("angle") || h.contains("chi"))
        && (h.contains("deg") || h.contains("degree"))
}

/// `value` a full turn (360 deg) further, as `how` says: `30` -> `390`, `sector:10:80` ->
/// `sector:370:440`, `6.45:68.4` -> `6.45:428.4`, `0.5,30` -> `0.5,390`.
fn turned(value: &str, how: Turn) -> String {
    let tok = |t: &str| t.parse::<f64>().map_or(t.to_string(), |v| format!("{}", v + 360.0));
    match how {
        Turn::Every => {
            value.split(',').map(|p| p.split(':').map(tok).collect::<Vec<_>>().join(":")).collect::<Vec<_>>().join(",")
        }
        Turn::AfterLastColon => match value.rsplit_once(':') {
            Some((head, last)) => format!("{head}:{}", tok(last)),
            None => value.to_string(),
        },
        Turn::AfterComma => match value.split_once(',') {
            Some((head, last)) => format!("{head},{}", tok(last)),
            None => value.to_string(),
        },
    }
}

/// One generated case.
struct Case {
    command: &'static str,
    class: &'static str,
    what: String,
    args: Vec<String>,
    /// Final output names: must not exist after a failure.
    outputs: Vec<PathBuf>,
    /// Files whose bytes must not change.
    inputs: Vec<PathBuf>,
    /// The case's own folder (outputs, hostile input variants).
    dir: PathBuf,
    expect: Expect,
}

/// An input file argument of a valid invocation: its position and a label (the flag, or the
/// positional argument's name in the CLI's definition).
struct FileArg {
    index: usize,
    label: String,
}

/// The input-file arguments of `t`, found through the CLI's definition: the value of every
/// option whose role is `input` when it names an existing path, and the first of every run of
/// positional values that name existing paths (one of a list of frames stands for all).
fn file_args(t: &Template, defs: &[serde_json::Value]) -> Vec<FileArg> {
    let def_of = |flag: &str| defs.iter().find(|a| a["long"] == flag);
    let positional =
        defs.iter().find(|a| a["long"].is_null() && a["role"] == "input").and_then(|a| a["id"].as_str()).unwrap_or("");
    let mut out = vec![];
    let mut prev_positional = false;
    let mut i = 1;
    while i < t.args.len() {
        let a = &t.args[i];
        if let Some(d) = a.starts_with("--").then(|| def_of(a)).flatten() {
            let takes_value = d["kind"] != "flag";
            if takes_value && d["role"] == "input" && Path::new(&t.args[i + 1]).exists() {
                out.push(FileArg { index: i + 1, label: a.clone() });
            }
            i += if takes_value { 2 } else { 1 };
            prev_positional = false;
            continue;
        }
        if Path::new(a).exists() && !prev_positional {
            out.push(FileArg { index: i, label: positional.to_string() });
        }
        prev_positional = true;
        i += 1;
    }
    out
}

/// Set `flag` to `value` (replacing the value after it, or appending both).
fn set_flag(args: &mut Vec<String>, flag: &str, value: &str) {
    match args.iter().position(|a| a == flag) {
        Some(i) => args[i + 1] = value.to_string(),
        None => args.extend([flag.to_string(), value.to_string()]),
    }
}

/// Where an input file says which instrument and filter it is of.
#[derive(Clone, Copy, Debug)]
enum Said {
    /// A calibration file: `HIERARCH IP INSTRUMENT`, `HIERARCH IP FILTER`.
    Calibration,
    /// A Stokes map: `INSTRUME`, `FILTER`.
    Map,
    /// Frames of the tests' instrument: `INSTRUME` and its filter keyword.
    Frames,
    /// A table with its product keywords (`# INSTRUME = ...` lines of a CSV).
    Table,
}

/// Combinations a command makes on purpose, with why: these warn instead of refusing.
const PRODUCT_ON_PURPOSE: &[(&str, &str, &str)] = &[
    ("validate", "filter", "a calibration of another filter is how a wrong calibration is shown to fail: warned"),
    ("wavelength-law", "filter", "it takes calibrations of several filters: that is its input"),
];

/// What `p` says it is, by its bytes: `None` for a file that says nothing.
fn said(p: &Path) -> Option<Said> {
    let b = std::fs::read(p).ok()?;
    let has = |k: &str| b.windows(k.len()).any(|w| w == k.as_bytes());
    if b.starts_with(b"SIMPLE") {
        if has("IP INSTRUMENT") {
            Some(Said::Calibration)
        } else if has("INSTRUME=") && has("FILTER  =") {
            Some(Said::Map)
        } else if has("INSTRUME=") && has("FILT1 NAME") {
            Some(Said::Frames)
        } else {
            None
        }
    } else {
        (has("# INSTRUME = ") && has("# FILTER = ")).then_some(Said::Table)
    }
}

/// Whether `p` records its detector (the product keyword `DETSIZE`, FITS card or CSV line).
fn says_detector(p: &Path) -> bool {
    let b = std::fs::read(p).unwrap_or_default();
    ["DETSIZE =", "# DETSIZE = "].iter().any(|k| b.windows(k.len()).any(|w| w == k.as_bytes()))
}

/// The files of an argument: the one at `index`, or the run of files it starts (frames).
fn run_of_files(args: &[String], index: usize) -> Vec<PathBuf> {
    args[index..].iter().map(PathBuf::from).take_while(|p| p.is_file()).collect()
}

/// Copies of `files` in `dir` saying another `what` (`filter`: R, which no file of the
/// fixture is of; `instrument`: OTHERCAM; `detector`: 1000x1000 px, which no fixture's is).
fn relabelled(files: &[PathBuf], how: Said, what: &str, dir: &Path) -> Vec<PathBuf> {
    let (key, value) = match (how, what) {
        (Said::Calibration | Said::Map, "detector") => ("DETSIZE =", "'1000x1000'"),
        (Said::Table, "detector") => ("# DETSIZE = ", "1000x1000"),
        (Said::Frames, "detector") => unreachable!("frames say no detector: the instrument file does"),
        (Said::Calibration, "filter") => ("IP FILTER", "'R'"),
        (Said::Calibration, _) => ("IP INSTRUMENT", "'OTHERCAM'"),
        (Said::Map, "filter") => ("FILTER  =", "'R'"),
        (Said::Frames, "filter") => ("FILT1 NAME", "'R'"),
        (Said::Map | Said::Frames, _) => ("INSTRUME=", "'OTHERCAM'"),
        (Said::Table, "filter") => ("# FILTER = ", "R"),
        (Said::Table, _) => ("# INSTRUME = ", "OTHERCAM"),
    };
    let copies: Vec<PathBuf> = files.iter().map(|f| dir.join(f.file_name().unwrap())).collect();
    for (f, c) in files.iter().zip(&copies) {
        std::fs::copy(f, c).unwrap();
        match how {
            Said::Table => {
                let text = std::fs::read_to_string(c).unwrap();
                let out: Vec<String> = text
                    .lines()
                    .map(|l| if l.starts_with(key) { format!("{key}{value}") } else { l.to_string() })
                    .collect();
                std::fs::write(c, out.join("\n") + "\n").unwrap();
            }
            _ => common::invocations::patch_card(c, key, value),
        }
    }
    copies
}

/// A hostile stand-in for the input file `orig`, made in `dir`.
fn variant(kind: &str, orig: &Path, dir: &Path) -> PathBuf {
    let ext = orig.extension().map(|e| e.to_string_lossy().to_string()).unwrap_or_default();
    let p = dir.join(format!("hostile_{kind}.{ext}"));
    match kind {
        "empty" => std::fs::write(&p, b"").unwrap(),
        "text" => std::fs::write(&p, b"this is not the file you are looking for\n").unwrap(),
        "truncated" => {
            let b = if orig.is_file() { std::fs::read(orig).unwrap() } else { b"SIMPLE  =".to_vec() };
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

/// A second name of the input `orig` in `dir`: the same path, a copy, a hard link or a
/// symlink (`None` where a folder has no such name: a copy or a hard link of a folder).
fn second_name(orig: &Path, how: &str, dir: &Path) -> Option<PathBuf> {
    let name = dir.join(format!("again_{}", orig.file_name()?.to_string_lossy()));
    match how {
        "same path" => return Some(orig.to_path_buf()),
        "symlink" => std::os::unix::fs::symlink(orig, &name).unwrap(),
        _ if orig.is_dir() => return None,
        "copy" => {
            std::fs::copy(orig, &name).unwrap();
        }
        "hard link" => std::fs::hard_link(orig, &name).unwrap(),
        _ => unreachable!(),
    }
    Some(name)
}

const FILE_VARIANTS: &[&str] =
    &["empty", "text", "truncated", "garbage", "directory", "missing", "symlink-loop", "dev-null"];

/// The files named in `args` (for the hash check).
fn files_in(args: &[String]) -> Vec<PathBuf> {
    args.iter().map(PathBuf::from).filter(|p| p.is_file()).collect()
}

/// The unit variants of a table column, by its name: (unit, factor from the plain column's
/// value). Fractions in %, angles in degrees as rad or arcmin, offsets in arcmin as arcsec or
/// deg; a unit of the wrong kind (a fraction in deg, a position in %) has no factor: it can
/// only be refused.
fn unit_variants(column: &str) -> Vec<(&'static str, Option<f64>)> {
    let c = column.to_ascii_lowercase();
    let fraction = ["q", "u", "sigma_q", "sigma_u", "p_true", "sigma_true", "p_measured", "sigma_p_measured", "p"];
    if fraction.contains(&c.as_str()) {
        vec![("%", Some(100.0)), ("deg", None)]
    } else if c.ends_with("_deg") || c == "chi" {
        vec![("rad", Some(std::f64::consts::PI / 180.0)), ("arcmin", Some(60.0)), ("%", None)]
    } else if c.ends_with("_arcmin") {
        vec![("arcsec", Some(60.0)), ("deg", Some(1.0 / 60.0)), ("%", None)]
    } else if c == "x" || c == "y" {
        vec![("%", None)]
    } else if c == "p_percent" {
        vec![("%", Some(1.0)), ("pix", None)]
    } else {
        vec![]
    }
}

/// Write `plain` (a CSV table) as `out` (format by extension) with `column` declaring `unit`
/// and its values times `factor` (1 when it has none).
fn table_with_unit(plain: &Path, out: &Path, column: &str, unit: &str, factor: Option<f64>) {
    use skyfield::table::{Data, Table};
    let mut t = Table::read(plain, None).unwrap();
    let c = t.columns.iter_mut().find(|c| c.name == column).unwrap();
    c.unit = Some(unit.to_string());
    let k = factor.unwrap_or(1.0);
    c.data = match &c.data {
        Data::F64(v) => Data::F64(v.iter().map(|x| x * k).collect()),
        Data::I64(v) => Data::F64(v.iter().map(|&x| x as f64 * k).collect()),
        Data::Str(v) => Data::Str(v.clone()),
    };
    t.write(out).unwrap();
}

/// The numeric columns of a CSV table.
fn numeric_columns(plain: &Path) -> Vec<String> {
    use skyfield::table::{Data, Table};
    let Ok(t) = Table::read(plain, None) else { return vec![] };
    t.columns.iter().filter(|c| !matches!(c.data, Data::Str(_))).map(|c| c.name.clone()).collect()
}

/// The `duplicate input` cases of template `t` (module docs): the first file of every list
/// input `used` under a second name after it; each (what, arguments, folder, expectation).
fn duplicate_inputs(
    t: &Template,
    defs: &[serde_json::Value],
    used: &[FileArg],
    control: usize,
    new_dir: &dyn Fn() -> PathBuf,
) -> Vec<(String, Vec<String>, PathBuf, Expect)> {
    let mut out = vec![];
    for fa in used {
        let label = fa.label.as_str();
        let def = defs.iter().find(|a| a["id"] == label || a["long"] == label);
        if !def.is_some_and(|a| a["multiple"] == true) {
            continue;
        }
        let orig = PathBuf::from(&t.args[fa.index]);
        for how in ["same path", "copy", "hard link", "symlink"] {
            let dir = new_dir();
            let Some(second) = second_name(&orig, how, &dir) else { continue };
            let second = second.to_str().unwrap().to_string();
            let mut a = t.args.clone();
            if label.starts_with("--") {
                a.extend([label.to_string(), second.clone()]);
            } else {
                a.insert(fa.index + 1, second.clone());
            }
            let names = vec![orig.to_str().unwrap().to_string(), second];
            out.push((format!("{label} twice ({how})"), a, dir, Expect::Once { reference: control, names }));
        }
    }
    out
}

fn cases(f: &Fixture, root: &Path) -> Vec<Case> {
    let mut out: Vec<Case> = vec![];
    let spec = invocations::spec();
    let defs = invocations::args_by_command(&spec);
    let n = AtomicUsize::new(0);
    let new_dir = || {
        let d = root.join(format!("c{:05}", n.fetch_add(1, Ordering::Relaxed)));
        std::fs::create_dir_all(&d).unwrap();
        d
    };
    for t in invocations::templates(f) {
        let defs = &defs[t.name()];
        let outputs_of = |dir: &Path| t.out_name.map(|n| vec![dir.join(n)]).unwrap_or_default();
        let case = |class: &'static str, what: String, args: Vec<String>, dir: PathBuf, expect: Expect| {
            let a = fill(&args, &dir, t.out_name);
            Case {
                command: t.command,
                class,
                what,
                inputs: files_in(&a),
                outputs: outputs_of(&dir),
                args: a,
                dir,
                expect,
            }
        };
        // The valid invocation itself (a control: it must succeed, or the cases test nothing).
        let control = out.len();
        out.push(case("control", "valid".into(), t.args.clone(), new_dir(), Expect::Nothing));
        let with_flag = |flag: &str, value: &str| {
            let mut a = t.args.clone();
            set_flag(&mut a, flag, value);
            a
        };
        let flags = |pred: &dyn Fn(&serde_json::Value) -> bool| -> Vec<serde_json::Value> {
            defs.iter().filter(|a| a["long"].is_string() && pred(a)).cloned().collect()
        };
        let long = |a: &serde_json::Value| a["long"].as_str().unwrap().to_string();
        // Every numeric flag at its edges, and given a value in the wrong unit.
        for a in flags(&|a| a["kind"] == "number") {
            let flag = long(&a);
            for v in EDGES {
                // No option means anything by a NaN or an infinity: refused naming the flag (or,
                // for a flag that needs another, by the usage error naming that one).
                let e = if ["NaN", "inf", "-inf"].contains(v) {
                    Expect::Refused(vec![flag.clone(), "required arguments were not provided".into()])
                } else {
                    Expect::Nothing
                };
                out.push(case("numeric", format!("{flag} {v:?}"), with_flag(&flag, v), new_dir(), e));
            }
            let help = a["help"].as_str().unwrap_or("").to_ascii_lowercase();
            if help.contains("fraction") && (help.contains("0..1") || help.contains("[0, 1]")) {
                let e = Expect::Refused(vec![flag.clone()]);
                out.push(case(
                    "range",
                    format!("{flag} 50 (percent for a fraction)"),
                    with_flag(&flag, "50"),
                    new_dir(),
                    e,
                ));
            }
            if help.contains("percent") || help.contains('%') {
                let what = format!("{flag} 0.5 (a fraction for percent)");
                out.push(case("range", what, with_flag(&flag, "0.5"), new_dir(), Expect::Nothing));
            }
            if help.contains("deg") {
                let what = format!("{flag} 0.785 (radians for degrees)");
                out.push(case("range", what, with_flag(&flag, "0.785"), new_dir(), Expect::Nothing));
            }
        }
        // Every orientation option, and the same a full turn further.
        for (_, flag, base, how, extra) in ORIENTATIONS.iter().filter(|(c, ..)| *c == t.command) {
            let own = t.args.iter().position(|a| a == flag).map(|i| t.args[i + 1].clone());
            let base = base.map(str::to_string).or(own).expect("an orientation without a value");
            let with = |v: &str| {
                let mut a = with_flag(flag, v);
                a.extend(extra.iter().map(|x| x.to_string()));
                a
            };
            let reference = out.len();
            out.push(case("turn", format!("{flag} {base}"), with(&base), new_dir(), Expect::Nothing));
            let (turn, e) = (turned(&base, *how), Expect::SameTurned { reference, flag: flag.to_string() });
            out.push(case("turn", format!("{flag} {turn} (a turn further)"), with(&turn), new_dir(), e));
        }
        // Every text option at its edges (the instrument's name is a file argument's business).
        for a in flags(&|a| a["kind"] == "text" && a["long"] != "--instrument") {
            let flag = long(&a);
            for v in text_edges() {
                let what = format!("{flag} {:?}", v.chars().take(12).collect::<String>());
                out.push(case("text", what, with_flag(&flag, &v), new_dir(), Expect::Nothing));
            }
        }
        // Every input file of the invocation, and every input-file option the command has but
        // the invocation does not use (`--bias`, `--flat`, `--standards`, ...), given each
        // hostile variant.
        let used = file_args(&t, defs);
        let unused = flags(&|a| a["kind"] == "path" && a["role"] == "input" && !t.args.contains(&long(a)));
        let mut slots: Vec<(String, Option<usize>, PathBuf)> =
            used.iter().map(|fa| (fa.label.clone(), Some(fa.index), PathBuf::from(&t.args[fa.index]))).collect();
        slots.extend(unused.iter().map(|a| (long(a), None, f.p("map.fits"))));
        for (label, index, orig) in &slots {
            for kind in FILE_VARIANTS {
                let dir = new_dir();
                let v = variant(kind, orig, &dir).to_str().unwrap().to_string();
                let mut a = t.args.clone();
                match index {
                    Some(i) => a[*i] = v,
                    None => set_flag(&mut a, label, &v),
                }
                let by_design = LEFT_OUT_BY_DESIGN.iter().any(|(c, l, _)| *c == t.command && l == label);
                let e = if *kind == "truncated" || by_design { Expect::Nothing } else { Expect::NotAccepted };
                out.push(case("file", format!("{label} {kind}"), a, dir, e));
            }
        }
        let outputs: Vec<String> = flags(&|a| a["role"] == "output").iter().map(long).collect();
        out.extend(output_cases(&t, &outputs, &used, &new_dir, &case));
        // Every input file under a second name.
        for (what, a, dir, e) in duplicate_inputs(&t, defs, &used, control, &new_dir) {
            out.push(case("duplicate input", what, a, dir, e));
        }
        // Another product: every input that says which instrument and filter it is of
        // (calibration files, Stokes maps, catalogs with their keywords, frames' filter), in a
        // command that combines it with another such input, replaced by one of another filter
        // or instrument: refused naming it (or warned where the command combines them on
        // purpose, PRODUCT_ON_PURPOSE), never a number with exit 0.
        let sides: Vec<(usize, Vec<PathBuf>, Said)> = used
            .iter()
            .filter_map(|fa| {
                let files = run_of_files(&t.args, fa.index);
                said(files.first()?).map(|s| (fa.index, files, s))
            })
            .collect();
        if sides.len() >= 2 {
            // (each side against the others; one file of a run against the rest is below)
            for (index, files, how) in &sides {
                for what in ["filter", "instrument", "detector"] {
                    // A detector is said by the products that record one (DETSIZE), frames
                    // by their instrument file; a mismatch needs another side that says one.
                    let other_says = sides
                        .iter()
                        .any(|(i, fs, h)| i != index && (matches!(h, Said::Frames) || says_detector(&fs[0])));
                    if what == "detector" && !(says_detector(&files[0]) && other_says) {
                        continue;
                    }
                    let dir = new_dir();
                    let copies = relabelled(files, *how, what, &dir);
                    let mut a = t.args.clone();
                    a.splice(*index..*index + files.len(), copies.iter().map(|p| p.display().to_string()));
                    let label = format!("{} of another {what}", t.args[*index].rsplit('/').next().unwrap_or(""));
                    let e = match PRODUCT_ON_PURPOSE.iter().find(|(c, w, _)| *c == t.command && *w == what) {
                        Some(_) => Expect::RefusedOrWarned(what.to_string()),
                        None => Expect::Refused(vec![what.to_string()]),
                    };
                    out.push(case("another product", label, a, dir, e));
                }
            }
        }
        // One of several files of one argument (calibrations of several filters, catalogs of
        // several pointings) replaced by one of another instrument or detector (and filter,
        // where the command does not combine filters on purpose): refused naming it.
        for (index, files, how) in sides.iter().filter(|(_, fs, h)| fs.len() >= 2 && !matches!(h, Said::Frames)) {
            let last = files.len() - 1;
            for what in ["filter", "instrument", "detector"] {
                let on_purpose = PRODUCT_ON_PURPOSE.iter().any(|(c, w, _)| *c == t.command && *w == what);
                let detector_unsaid = what == "detector" && !files.iter().all(|f| says_detector(f));
                if on_purpose || detector_unsaid {
                    continue;
                }
                let dir = new_dir();
                let copy = relabelled(&files[last..], *how, what, &dir);
                let mut a = t.args.clone();
                a[index + last] = copy[0].display().to_string();
                let label = format!(
                    "{} of another {what} among {}",
                    t.args[index + last].rsplit('/').next().unwrap_or(""),
                    files.len()
                );
                out.push(case("another product", label, a, dir, Expect::Refused(vec![what.to_string()])));
            }
        }
        // Tables with units: each numeric column of each CSV input declaring a unit, its values
        // converted, in three formats.
        for fa in used.iter().filter(|fa| t.args[fa.index].ends_with(".csv")) {
            let plain = PathBuf::from(&t.args[fa.index]);
            for column in numeric_columns(&plain) {
                for (k, (unit, factor)) in unit_variants(&column).into_iter().enumerate() {
                    let formats: &[&str] = if k == 0 { &["ecsv", "fits", "vot"] } else { &["ecsv"] };
                    for ext in formats {
                        let dir = new_dir();
                        let table = dir.join(format!("{}.{ext}", plain.file_stem().unwrap().to_string_lossy()));
                        table_with_unit(&plain, &table, &column, unit, factor);
                        let mut a = t.args.clone();
                        a[fa.index] = table.to_str().unwrap().to_string();
                        let what = format!("{} {column} in {unit} ({ext})", fa.label);
                        let e = match factor {
                            Some(_) => Expect::SameOrRefused { reference: control, column: column.clone() },
                            None => Expect::Refused(vec![column.clone()]),
                        };
                        out.push(case("units", what, a, dir, e));
                    }
                }
            }
        }
    }
    // Fits given inputs collapsed onto a point or a line, and plate-angle sets missing one.
    for t in invocations::templates(f) {
        out.extend(collapsed_cases(&t, &new_dir));
        out.extend(dropped_angle_cases(&t, &defs[t.name()], &f.frames(), &new_dir));
    }
    out.extend(scene_key_cases(f, &new_dir));
    out
}

/// The `output over input` and `output name` cases of template `t`: every output argument
/// (`outputs`) named like every input file `used`, and hostile output names; `case` makes each.
fn output_cases(
    t: &Template,
    outputs: &[String],
    used: &[FileArg],
    new_dir: &dyn Fn() -> PathBuf,
    case: &dyn Fn(&'static str, String, Vec<String>, PathBuf, Expect) -> Case,
) -> Vec<Case> {
    let mut out = vec![];
    // Every output argument named like every input file (a copy, so that the fixture
    // stays intact): the same path, a hard link, a symlink. Refused, the input unchanged.
    for oflag in outputs {
        for fa in used {
            for how in ["same path", "hard link", "symlink"] {
                let dir = new_dir();
                let orig = Path::new(&t.args[fa.index]);
                if !orig.is_file() {
                    continue;
                }
                let copy = dir.join(format!("input_{}", orig.file_name().unwrap().to_string_lossy()));
                std::fs::copy(orig, &copy).unwrap();
                let name = match how {
                    "same path" => copy.clone(),
                    "hard link" => {
                        let l = dir.join("hardlink_out");
                        std::fs::hard_link(&copy, &l).unwrap();
                        l
                    }
                    _ => {
                        let l = dir.join("symlink_out");
                        std::os::unix::fs::symlink(&copy, &l).unwrap();
                        l
                    }
                };
                let mut a = t.args.clone();
                a[fa.index] = copy.to_str().unwrap().to_string();
                set_flag(&mut a, oflag, name.to_str().unwrap());
                let what = format!("{oflag} = {} ({how})", fa.label);
                let mut c = case("output over input", what, a, dir, Expect::Refused(vec![]));
                c.outputs.clear();
                out.push(c);
            }
        }
    }
    // Hostile output names: a folder that does not exist, an existing folder, a name in
    // /proc (not writable).
    if let Some(name) = t.out_name {
        for kind in ["missing-folder", "is-a-folder", "proc"] {
            let dir = new_dir();
            let o = match kind {
                "missing-folder" => dir.join("no/such/folder").join(name),
                "is-a-folder" => {
                    std::fs::create_dir_all(dir.join(name)).unwrap();
                    dir.join(name)
                }
                _ => PathBuf::from("/proc/instpol_hostile").join(name),
            };
            let a: Vec<String> = t.args.iter().map(|x| x.replace("{OUT}", o.to_str().unwrap())).collect();
            let mut c = case("output name", format!("--out {kind}"), a, dir, Expect::Nothing);
            c.outputs = if kind == "is-a-folder" { vec![] } else { vec![o] };
            out.push(c);
        }
    }
    out
}

/// Every numeric key of a scene at its TOML edges (the `scene keys` class).
fn scene_key_cases(f: &Fixture, new_dir: &dyn Fn() -> PathBuf) -> Vec<Case> {
    let mut out = vec![];
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
            let text = invocations::SCENE
                .replacen(orig, &pat.replace("{}", v), 1)
                .replace("\"mini.toml\"", &format!("{:?}", f.s("mini.toml")));
            std::fs::write(&scene, text).unwrap();
            let args = ["simulate", scene.to_str().unwrap(), "--out", dir.join("frames").to_str().unwrap(), "--json"]
                .map(String::from)
                .to_vec();
            out.push(Case {
                command: "simulate",
                class: "scene keys",
                what: format!("{orig} -> {v}"),
                inputs: files_in(&args),
                args,
                outputs: vec![],
                dir,
                expect: Expect::Nothing,
            });
        }
    }
    out
}

/// Columns the `collapsed` class collapses: position pairs (onto the first row's point, or onto
/// the line `y = 0.5 x + 0.2`) and angles (every row at the first row's).
const POSITION_PAIRS: &[(&str, &str)] =
    &[("x_arcmin", "y_arcmin"), ("x", "y"), ("x_px", "y_px"), ("ra_deg", "dec_deg")];
const ANGLE_COLUMNS: &[&str] = &["parallactic_deg", "rotator_deg", "hwp_deg", "hwp_angle_deg"];

/// Commands that fit a model to their tables: a collapse leaves a parameter free, refused
/// (exit 2) naming what the data do not determine, or the collapsed input. Other commands'
/// tables are collapsed too, with the properties every case has.
/// (calibrate-mueller fits its field to the --field maps; its --stars table only adds stars to
/// them, and is collapsed with the properties every case has.)
const FITTERS: &[&str] = &["calibrate-stars", "fit-standards"];

/// Commands whose frame lists are not sets of plate angles (the `plate set` class leaves them
/// out), with the reason.
const NOT_ANGLE_SETS: &[(&str, &str)] = &[
    ("master-bias", "bias frames: no plate angles"),
    ("master-flat", "flat frames are combined whatever their plate angles"),
    ("wavelength-law", "its list is calibration files of several filters, not frames"),
];

/// How a table's rows are collapsed.
#[derive(Clone, Copy)]
enum Collapse<'a> {
    Point(&'a str, &'a str),
    Line(&'a str, &'a str),
    Angle(&'a str),
}

/// `src` (CSV) written to `dst` with its rows collapsed as `how` says; `false` when the table
/// has not the columns.
fn collapse_table(src: &Path, dst: &Path, how: Collapse) -> bool {
    let text = std::fs::read_to_string(src).unwrap_or_default();
    let mut lines = text.lines();
    let Some(head) = lines.next() else { return false };
    let cols: Vec<&str> = head.split(',').map(str::trim).collect();
    let at = |c: &str| cols.iter().position(|h| *h == c);
    let (a, b) = match how {
        Collapse::Point(x, y) | Collapse::Line(x, y) => match (at(x), at(y)) {
            (Some(i), Some(j)) => (i, Some(j)),
            _ => return false,
        },
        Collapse::Angle(c) => match at(c) {
            Some(i) => (i, None),
            None => return false,
        },
    };
    let rows: Vec<Vec<String>> = lines.map(|l| l.split(',').map(String::from).collect()).collect();
    let Some(first) = rows.first().cloned() else { return false };
    let mut out = format!("{head}\n");
    for mut r in rows {
        match (how, b) {
            (Collapse::Point(..), Some(j)) => (r[a], r[j]) = (first[a].clone(), first[j].clone()),
            (Collapse::Line(..), Some(j)) => {
                let x: f64 = r[a].trim().parse().unwrap_or(0.0);
                r[j] = format!("{}", 0.5 * x + 0.2);
            }
            _ => r[a] = first[a].clone(),
        }
        out += &format!("{}\n", r.join(","));
    }
    std::fs::write(dst, out).unwrap();
    true
}

/// The `collapsed` class of template `t`: every CSV table it reads (all of them at once, a
/// list of catalogs included) with its positions collapsed onto a point or a line, or its
/// angles onto one. A fitting command ([`FITTERS`]) must refuse a point or one angle naming
/// what is left free; a line is refused by a plane (`--model plane`, tried for every fitter
/// with a `--model` option), while a radial profile is still determined along it.
fn collapsed_cases(t: &Template, new_dir: &dyn Fn() -> PathBuf) -> Vec<Case> {
    // Dithered catalogs placed by their --offset are each at their own place: collapsed, they
    // are one catalog without offsets.
    let mut base = t.args.clone();
    if let Some(k) = base.iter().position(|a| a == "--offset") {
        let first = base.iter().position(|a| a.ends_with(".csv")).unwrap_or(k);
        base = base
            .iter()
            .enumerate()
            .filter(|(i, a)| !(*i > first && a.ends_with(".csv")))
            .map(|(_, a)| a.clone())
            .collect();
        while let Some(k) = base.iter().position(|a| a == "--offset") {
            base.drain(k..k + 2);
        }
    }
    let tables: Vec<usize> =
        (0..base.len()).filter(|&i| base[i].ends_with(".csv") && Path::new(&base[i]).is_file()).collect();
    let fitter = FITTERS.contains(&t.name());
    // What a collapse leaves to a fit: (what, how, options added, refused by a fitter).
    let mut kinds: Vec<(String, Collapse, &[&str], bool)> = vec![];
    for (x, y) in POSITION_PAIRS {
        kinds.push((format!("{x},{y} onto a point"), Collapse::Point(x, y), &[], true));
        kinds.push((format!("{x},{y} onto a line"), Collapse::Line(x, y), &[], false));
        if t.name() == "calibrate-stars" {
            let plane: &[&str] = &["--model", "plane", "--interstellar", "zero"];
            kinds.push((format!("{x},{y} onto a line, a plane"), Collapse::Line(x, y), plane, true));
        }
    }
    for c in ANGLE_COLUMNS {
        // One parallactic angle gives the Wiersema model's two numbers one (q, u) each: a
        // fit of its two parameters; the oxide model's four are not determined.
        let refused = t.name() != "fit-standards";
        kinds.push((format!("{c} onto one angle"), Collapse::Angle(c), &[], refused));
        if t.name() == "fit-standards" {
            kinds.push((format!("{c} onto one angle, oxide"), Collapse::Angle(c), &["--model", "oxide"], true));
        }
    }
    let mut out = vec![];
    for (what, how, extra, refusing) in kinds {
        let dir = new_dir();
        let mut args = base.clone();
        let mut any = false;
        for &i in &tables {
            let dst = dir.join(format!("collapsed{i}.csv"));
            if collapse_table(Path::new(&base[i]), &dst, how) {
                args[i] = dst.to_str().unwrap().to_string();
                any = true;
            }
        }
        if !any {
            std::fs::remove_dir_all(&dir).ok();
            continue;
        }
        for pair in extra.chunks(2) {
            set_flag(&mut args, pair[0], pair[1]);
        }
        let refused = fitter && refusing;
        let expect = if refused { Expect::Refused(vec!["do not determine".into()]) } else { Expect::Nothing };
        let a = fill(&args, &dir, t.out_name);
        out.push(Case {
            command: t.command,
            class: "collapsed",
            what,
            inputs: files_in(&a),
            outputs: t.out_name.map(|n| vec![dir.join(n)]).unwrap_or_default(),
            args: a,
            dir,
            expect,
        });
    }
    out
}

/// The `plate set` class of template `t`: its list of frames (the positional argument taking
/// several, [`NOT_ANGLE_SETS`] left out) with the second frame dropped, a set missing one plate
/// angle: refused or reduced with the missing angle named ([`Expect::MissingNamed`]). A
/// command whose invocation reads a map but that also takes frames (calibrate) is given the
/// fixture's frames, one dropped, in place of the map.
fn dropped_angle_cases(
    t: &Template,
    defs: &[serde_json::Value],
    frames: &[String],
    new_dir: &dyn Fn() -> PathBuf,
) -> Vec<Case> {
    if NOT_ANGLE_SETS.iter().any(|(c, _)| *c == t.name()) {
        return vec![];
    }
    let takes_frames = defs.iter().any(|a| a["long"].is_null() && a["role"] == "input" && a["multiple"] == true);
    if let (true, Some(k)) = (takes_frames, t.args.iter().position(|a| a == "--map")) {
        let mut args = t.args.clone();
        args.drain(k..k + 2);
        args.extend(frames.iter().enumerate().filter(|(i, _)| *i != 1).map(|(_, f)| f.clone()));
        let dir = new_dir();
        let a = fill(&args, &dir, t.out_name);
        return vec![Case {
            command: t.command,
            class: "plate set",
            what: format!("frames in place of --map, without {}", frames.get(1).map_or("", |f| f.as_str())),
            inputs: files_in(&a),
            outputs: t.out_name.map(|n| vec![dir.join(n)]).unwrap_or_default(),
            args: a,
            dir,
            expect: Expect::MissingNamed,
        }];
    }
    let Some(fa) = file_args(t, defs).into_iter().find(|fa| !fa.label.starts_with("--")) else { return vec![] };
    let many = defs.iter().any(|a| a["id"] == fa.label.as_str() && a["multiple"] == true);
    let i = fa.index;
    let frames = |k: usize| t.args.get(k).is_some_and(|a| a.ends_with(".fits") && Path::new(a).is_file());
    if !(many && frames(i) && frames(i + 1)) {
        return vec![];
    }
    let mut args = t.args.clone();
    let dropped = args.remove(i + 1);
    let dir = new_dir();
    let a = fill(&args, &dir, t.out_name);
    vec![Case {
        command: t.command,
        class: "plate set",
        what: format!("{} without {}", fa.label, Path::new(&dropped).file_name().unwrap().to_string_lossy()),
        inputs: files_in(&a),
        outputs: t.out_name.map(|n| vec![dir.join(n)]).unwrap_or_default(),
        args: a,
        dir,
        expect: Expect::MissingNamed,
    }]
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

/// The argument as the OS gets it ([`NON_UTF8`] made into bytes that are not UTF-8).
fn os_arg(a: &str) -> OsString {
    use std::os::unix::ffi::OsStringExt;
    if a == NON_UTF8 {
        OsString::from_vec(vec![0xff, 0xfe, b'x'])
    } else {
        OsString::from(a)
    }
}

/// Run one case; returns (exit code or -signal, a failure description if any).
fn run_case(c: &Case) -> (i32, Option<String>) {
    let before: Vec<Option<u64>> = c.inputs.iter().map(|p| hash(p)).collect();
    let (so, se) = (c.dir.join("stdout.txt"), c.dir.join("stderr.txt"));
    let mut child = Command::new(common::bin())
        .args(c.args.iter().map(|a| os_arg(a)))
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
    match &c.expect {
        Expect::Nothing | Expect::SameOrRefused { .. } | Expect::SameTurned { .. } | Expect::Once { .. } => {}
        Expect::NotAccepted => {
            if code == 0 {
                problems.push("exit 0: a file that is not one was accepted".into());
            }
        }
        Expect::RefusedOrWarned(word) => {
            let warned = err.lines().any(|l| l.starts_with("warning") && l.contains(word.as_str()));
            if !(code == 2 && err.contains(word.as_str()) || (code == 0 || code == 1) && warned) {
                problems.push(format!("exit {code}, neither refused nor warned naming the {word}"));
            }
        }
        Expect::MissingNamed => {
            if ![0, 2].contains(&code) || !err.contains("missing [") {
                problems.push(format!("exit {code} without naming the missing plate angle"));
            }
        }
        Expect::Refused(names) => {
            if code != 2 {
                problems.push(format!("exit {code}, not refused (exit 2)"));
            } else if !names.is_empty() && !names.iter().any(|n| err.contains(n.as_str())) {
                problems.push(format!("refused without naming {}", names.join(" or ")));
            }
        }
    }
    if problems.is_empty() {
        (code, None)
    } else {
        (code, Some(failure(c, &problems.join("; "))))
    }
}

fn failure(c: &Case, problem: &str) -> String {
    let err = std::fs::read_to_string(c.dir.join("stderr.txt")).unwrap_or_default();
    let last = err.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("").chars().take(300).collect::<String>();
    format!("{} [{}]: {} -> {problem} [stderr: {last}]", c.command, c.class, c.what)
}

/// The numbers of a JSON value (not its provenance, nor a run time), in order.
fn numbers(v: &serde_json::Value, out: &mut Vec<f64>) {
    match v {
        serde_json::Value::Number(n) => out.push(n.as_f64().unwrap()),
        serde_json::Value::Array(a) => a.iter().for_each(|x| numbers(x, out)),
        serde_json::Value::Object(o) => {
            for (k, x) in o {
                if k != "provenance" && !k.contains("seconds") && !k.contains("per_second") && !k.ends_with("_s") {
                    numbers(x, out);
                }
            }
        }
        _ => {}
    }
}

/// The numbers a case printed (its --json output).
fn printed_numbers(c: &Case) -> Option<Vec<f64>> {
    let text = std::fs::read_to_string(c.dir.join("stdout.txt")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    let mut out = vec![];
    numbers(&v, &mut out);
    Some(out)
}

/// The `units` property: exit 0 with the valid invocation's numbers (to 1e-6 relative; a unit
/// ignored is a factor of 60 or more), or
/// exit 2 naming the column.
fn check_units(c: &Case, code: i32, cases: &[Case]) -> Option<String> {
    let Expect::SameOrRefused { reference, column } = &c.expect else { return None };
    let err = std::fs::read_to_string(c.dir.join("stderr.txt")).unwrap_or_default();
    match code {
        2 if err.contains(column.as_str()) => None,
        2 => Some(failure(c, &format!("refused without naming the column '{column}'"))),
        0 => {
            let (got, want) = (printed_numbers(c), printed_numbers(&cases[*reference]));
            let same = matches!((&got, &want), (Some(g), Some(w)) if g.len() == w.len()
                && g.iter().zip(w).all(|(a, b)| a == b || (a - b).abs() <= 1e-6 * a.abs().max(b.abs()) + 1e-12));
            (!same).then(|| failure(c, "exit 0 with other numbers than the plain table's: the unit was ignored"))
        }
        _ => None,
    }
}

/// The `turn` property: the reference (the option at its value) exits 0, and the case (a full
/// turn further) exits 0 with each printed number the reference's (to 1e-6 relative) or a whole
/// number of turns off it (the angle echoed), or exits 2 naming the flag.
fn check_turned(c: &Case, code: i32, cases: &[Case], codes: &[i32]) -> Option<String> {
    let Expect::SameTurned { reference, flag } = &c.expect else { return None };
    if codes[*reference] != 0 {
        return Some(failure(
            &cases[*reference],
            "the orientation's value is not taken: the turned case tests nothing",
        ));
    }
    let err = std::fs::read_to_string(c.dir.join("stderr.txt")).unwrap_or_default();
    match code {
        2 if err.contains(flag.as_str()) => None,
        2 => Some(failure(c, &format!("refused without naming {flag}"))),
        0 => {
            let (got, want) = (printed_numbers(c), printed_numbers(&cases[*reference]));
            let turns = |d: f64| (d / 360.0).round() != 0.0 && (d - 360.0 * (d / 360.0).round()).abs() < 1e-6;
            let same = matches!((&got, &want), (Some(g), Some(w)) if g.len() == w.len()
                && g.iter().zip(w).all(|(a, b)| a == b || (a - b).abs() <= 1e-6 * a.abs().max(b.abs()) + 1e-12 || turns(a - b)));
            (!same).then(|| {
                failure(c, "exit 0 with other numbers than a full turn back: the angle is not read in degrees")
            })
        }
        _ => Some(failure(c, &format!("exit {code}: a full turn further is neither taken nor refused"))),
    }
}

/// The `duplicate input` property: exit 2 naming both names, or exit 0 naming both (a warning,
/// or the printed plan's list of what it left out) with each printed number the valid
/// invocation's (to 1e-9 relative: an input counted twice moves its errors by sqrt(2)).
fn check_once(c: &Case, code: i32, cases: &[Case]) -> Option<String> {
    let Expect::Once { reference, names } = &c.expect else { return None };
    let err = std::fs::read_to_string(c.dir.join("stderr.txt")).unwrap_or_default();
    let said = |text: &str| names.iter().all(|n| text.contains(n.as_str()));
    match code {
        2 if said(&err) => None,
        2 => Some(failure(c, &format!("refused without naming both {}", names.join(" and ")))),
        0 => {
            let out = std::fs::read_to_string(c.dir.join("stdout.txt")).unwrap_or_default();
            if !said(&format!("{err}{out}")) {
                return Some(failure(c, &format!("exit 0 without naming both {}", names.join(" and "))));
            }
            let (got, want) = (printed_numbers(c), printed_numbers(&cases[*reference]));
            let same = match (&got, &want) {
                (Some(g), Some(w)) => {
                    g.len() == w.len()
                        && g.iter().zip(w).all(|(a, b)| a == b || (a - b).abs() <= 1e-9 * a.abs().max(b.abs()))
                }
                (None, None) => true,
                _ => false,
            };
            (!same).then(|| failure(c, "exit 0 with other numbers than the input once: counted twice"))
        }
        _ => Some(failure(c, &format!("exit {code}: the same input twice neither refused nor used once"))),
    }
}

/// Every angle option in degrees of the CLI's definition is tried a full turn further
/// ([`ORIENTATIONS`]) or says why not ([`NOT_ORIENTATIONS`]), and both lists name options the
/// CLI has: a new angle option cannot pass untried without a word.
#[test]
fn every_angle_option_is_tried_a_turn_further() {
    let defs = invocations::args_by_command(&invocations::spec());
    let mut wrong = vec![];
    for (command, args) in &defs {
        for a in args.iter().filter(|a| a["long"].is_string() && is_angle_in_degrees(a)) {
            let flag = a["long"].as_str().unwrap();
            let name = |label: &str| label.split(' ').next().unwrap().to_string();
            let listed = ORIENTATIONS.iter().any(|(c, f, ..)| name(c) == *command && *f == flag)
                || NOT_ORIENTATIONS.iter().any(|(c, f, _)| c == command && *f == flag);
            if !listed {
                wrong.push(format!(
                    "{command} {flag}: an angle in degrees, in neither ORIENTATIONS nor NOT_ORIENTATIONS"
                ));
            }
        }
    }
    let labels = ORIENTATIONS.iter().map(|(c, f, ..)| (c.split(' ').next().unwrap(), *f));
    for (c, f) in labels.chain(NOT_ORIENTATIONS.iter().map(|(c, f, _)| (*c, *f))) {
        let has = defs.get(c).is_some_and(|args| args.iter().any(|a| a["long"] == f));
        if !has {
            wrong.push(format!("{c} {f}: listed, but the CLI has no such option"));
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    assert_eq!(turned("sector:10:80", Turn::Every), "sector:370:440");
    assert_eq!(turned("0,22.5", Turn::Every), "360,382.5");
    assert_eq!(turned("m.fits:6.45:68.4", Turn::AfterLastColon), "m.fits:6.45:428.4");
    assert_eq!(turned("0.5,30", Turn::AfterComma), "0.5,390");
    // Every template an orientation names exists.
    let f = invocations::fixture();
    let names: Vec<&str> = invocations::templates(&f).iter().map(|t| t.command).collect();
    for (c, ..) in ORIENTATIONS {
        assert!(names.contains(c), "ORIENTATIONS names {c}, which is no template");
    }
}

/// Every command of the CLI has a valid invocation or is in `NOT_YET` with its reason, and
/// nothing is listed that the CLI does not have: a new command cannot pass untried without a
/// word.
#[test]
fn every_command_is_tried_or_says_why_not() {
    let f = invocations::fixture();
    let tried: std::collections::BTreeSet<String> =
        invocations::templates(&f).iter().map(|t| t.name().to_string()).collect();
    let spec = invocations::args_by_command(&invocations::spec());
    let mut wrong = vec![];
    for name in spec.keys() {
        let listed = invocations::NOT_YET.iter().any(|(n, _)| n == name);
        match (tried.contains(name), listed) {
            (false, false) => wrong.push(format!("{name}: no valid invocation in templates() and not in NOT_YET")),
            (true, true) => wrong.push(format!("{name}: tried and also listed in NOT_YET")),
            _ => {}
        }
    }
    for (n, _) in invocations::NOT_YET {
        if !spec.contains_key(*n) {
            wrong.push(format!("{n}: listed in NOT_YET but the CLI has no such command"));
        }
    }
    assert!(spec.len() >= 28, "{} commands", spec.len());
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// The input-file arguments are found from the CLI's definition: a positional list of frames
/// counts once, an option's value by its flag, an output never.
#[test]
fn file_arguments_come_from_the_definition() {
    let f = invocations::fixture();
    let defs = invocations::args_by_command(&invocations::spec());
    let labels = |command: &str| -> Vec<String> {
        let t = invocations::templates(&f).into_iter().find(|t| t.command == command).unwrap();
        file_args(&t, &defs[t.name()]).into_iter().map(|fa| fa.label).collect()
    };
    assert_eq!(labels("validate"), ["--cal", "--instrument", "frames"]);
    assert_eq!(labels("correct (catalog)"), ["--cal", "--in"]);
    assert_eq!(labels("import-map"), ["--q", "--u"]);
    assert_eq!(labels("wavelength-law"), ["calibrations"]);
    assert_eq!(labels("calibrate-mueller"), ["--stars"]);
}

#[test]
fn hostile_inputs() {
    let t0 = Instant::now();
    let f = invocations::fixture();
    let t_fixture = t0.elapsed().as_secs_f64();
    let fixture_before = tree(f.dir.path());
    let root = tempfile::tempdir().unwrap();
    let cases = cases(&f, root.path());
    // HOSTILE_CLASS=NAME runs only the controls and the cases of one class (a quick look while
    // working on it; the full run is the test): the others are left out of the results.
    let only = std::env::var("HOSTILE_CLASS").ok();
    let wanted = |c: &Case| only.as_deref().is_none_or(|o| c.class == "control" || c.class == o);
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, i32, Option<String>)>> = Mutex::new(vec![]);
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2).clamp(2, 8);
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                let Some(c) = cases.get(k) else { break };
                if !wanted(c) {
                    continue;
                }
                let (code, fail) = run_case(c);
                results.lock().unwrap().push((k, code, fail));
            });
        }
    });
    let mut results = results.into_inner().unwrap();
    results.sort_by_key(|r| r.0);
    let mut codes: Vec<i32> = vec![-1; cases.len()];
    for r in &results {
        codes[r.0] = r.1;
    }
    for r in results.iter_mut() {
        if r.2.is_none() {
            r.2 = check_units(&cases[r.0], r.1, &cases)
                .or_else(|| check_turned(&cases[r.0], r.1, &cases, &codes))
                .or_else(|| check_once(&cases[r.0], r.1, &cases));
        }
    }
    let is_known =
        |c: &Case| KNOWN.iter().any(|(cmd, class, what, _)| *cmd == c.command && *class == c.class && *what == c.what);
    let mut failures: Vec<String> =
        results.iter().filter(|r| !is_known(&cases[r.0])).filter_map(|r| r.2.clone()).collect();
    let known: Vec<String> = results.iter().filter(|r| is_known(&cases[r.0])).filter_map(|r| r.2.clone()).collect();
    for (cmd, class, what, why) in KNOWN {
        let found = results.iter().any(|r| {
            let c = &cases[r.0];
            r.2.is_some() && c.command == *cmd && c.class == *class && c.what == *what
        });
        if !found {
            failures.push(format!("{cmd} [{class}]: {what}: listed in KNOWN ({why}) but no longer fails: take it off"));
        }
    }
    // The valid invocations must succeed (exit 0), or the cases test nothing.
    for (k, code, _) in &results {
        if cases[*k].class == "control" && *code != 0 {
            let err = std::fs::read_to_string(cases[*k].dir.join("stderr.txt")).unwrap_or_default();
            failures.push(format!("{}: the valid control exits {code}: {err}", cases[*k].command));
        }
    }
    // Nothing in the shared fixture changed (each case also checks its own inputs).
    if tree(f.dir.path()) != fixture_before {
        failures.push("the fixture folder changed".into());
    }
    let text = table(&cases, &results);
    println!("{text}");
    println!("{} known defects (KNOWN), not failing the test:", known.len());
    for k in &known {
        println!("  known: {k}");
    }
    if std::env::var_os("HOSTILE_ZERO").is_some() {
        for (k, code, _) in &results {
            let c = &cases[*k];
            if *code == 0 && c.class != "control" {
                println!("exit0: {} [{}] {}", c.command, c.class, c.what);
            }
        }
    }
    println!(
        "{} cases on {threads} threads in {:.1} s (the fixture {t_fixture:.1} s)",
        results.len(),
        t0.elapsed().as_secs_f64()
    );
    if let Ok(p) = std::env::var("HOSTILE_TABLE") {
        std::fs::write(p, &text).unwrap();
    }
    assert!(only.is_some() || results.len() >= 3000, "only {} cases", results.len());
    assert!(failures.is_empty(), "{} failures:\n{}", failures.len(), failures.join("\n"));
}

/// The results table: cases per command and class, the exit codes, and the failures.
fn table(cases: &[Case], results: &[(usize, i32, Option<String>)]) -> String {
    let mut classes: Vec<&str> = cases.iter().map(|c| c.class).collect();
    classes.sort();
    classes.dedup();
    let mut rows: BTreeMap<&str, (BTreeMap<&str, usize>, [usize; 4])> = BTreeMap::new();
    for (k, code, fail) in results {
        let c = &cases[*k];
        let row = rows.entry(c.command).or_default();
        *row.0.entry(c.class).or_default() += 1;
        match code {
            0 => row.1[0] += 1,
            1 => row.1[1] += 1,
            2 => row.1[2] += 1,
            _ => {}
        }
        if fail.is_some() {
            row.1[3] += 1;
        }
    }
    let mut text = format!("| command | {} | all | exit 0 | exit 1 | exit 2 | failures |\n", classes.join(" | "));
    text += &format!("|---{}|---|---|---|---|---|\n", "|---".repeat(classes.len()));
    let (mut by_class, mut tot) = (BTreeMap::<&str, usize>::new(), [0usize; 5]);
    for (cmd, (per, r)) in &rows {
        let counts: Vec<String> = classes.iter().map(|k| per.get(k).copied().unwrap_or(0).to_string()).collect();
        let all: usize = per.values().sum();
        text += &format!("| {cmd} | {} | {all} | {} | {} | {} | {} |\n", counts.join(" | "), r[0], r[1], r[2], r[3]);
        for (k, v) in per {
            *by_class.entry(k).or_default() += v;
        }
        tot[0] += all;
        for i in 0..4 {
            tot[i + 1] += r[i];
        }
    }
    let counts: Vec<String> = classes.iter().map(|k| by_class.get(k).copied().unwrap_or(0).to_string()).collect();
    text += &format!(
        "| **all** | {} | {} | {} | {} | {} | {} |\n",
        counts.join(" | "),
        tot[0],
        tot[1],
        tot[2],
        tot[3],
        tot[4]
    );
    text
}
