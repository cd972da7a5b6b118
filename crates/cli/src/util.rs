//! Small helpers shared by the commands: JSON printing and atomic file writes.

use anyhow::{bail, Context, Result};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The files the running command reads, registered by [`inputs`]: every output is checked
/// against them ([`check_output`], also inside [`write_via_temp`]), so that no command ever
/// writes over one of its own inputs, whatever the name it is given by.
static INPUTS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// The arguments of any command that name files it WRITES (a file or a folder of outputs).
/// Every other path argument, and `--instrument` when it names a file, is an input
/// ([`guard_arguments`]). A new output argument must be listed here: the test
/// `path_arguments_are_inputs_or_listed_outputs` reads every command's definition.
pub const OUTPUT_ARGUMENTS: [&str; 9] =
    ["out", "output", "output_dir", "plot", "plots", "plot_dir", "field_out", "products", "night"];

/// Guard every file a command line names as an input against being written over, whatever
/// the command (the one registry of inputs: a command's own [`inputs`] call still hashes them
/// for the provenance, but a file it forgot there, such as a master bias passed with `--bias`,
/// is guarded here), and refuse the same data named twice among the files of one argument
/// (the frames, the catalogs, the tables: [`skyfield::same::distinct_files`] by content, the
/// same path, a link or a copy): it would be counted twice. `def` is the subcommand's
/// definition and `m` its matches.
pub fn guard_arguments(def: &clap::Command, m: &clap::ArgMatches) -> Result<()> {
    let guarded = input_arguments(def, m);
    INPUTS.lock().unwrap_or_else(|e| e.into_inner()).extend(guarded.iter().cloned());
    for arg in def.get_arguments().filter(|a| a.get_value_parser().type_id() == std::any::TypeId::of::<PathBuf>()) {
        if let Ok(Some(v)) = m.try_get_many::<PathBuf>(arg.get_id().as_str()) {
            refuse_duplicates(&v.collect::<Vec<_>>(), skyfield::same::By::Content)?;
        }
    }
    Ok(())
}

/// Every file a command line names as an input, by the roles of the command's definition:
/// every path argument but the outputs ([`OUTPUT_ARGUMENTS`]), and `--instrument` when it names
/// a file.
pub fn input_arguments(def: &clap::Command, m: &clap::ArgMatches) -> Vec<PathBuf> {
    let mut guarded = vec![];
    for arg in def.get_arguments() {
        let id = arg.get_id().as_str();
        if OUTPUT_ARGUMENTS.contains(&id) {
            continue;
        }
        if arg.get_value_parser().type_id() == std::any::TypeId::of::<PathBuf>() {
            if let Ok(Some(v)) = m.try_get_many::<PathBuf>(id) {
                guarded.extend(v.cloned());
            }
        } else if id == "instrument" {
            if let Ok(Some(v)) = m.try_get_one::<String>(id) {
                guarded.extend(file_arg(v).map(Path::to_path_buf));
            }
        }
    }
    guarded
}

/// Refuse (exit 2) input files that are the same data under two names, naming both
/// ([`skyfield::same::distinct_files`] decides, `by` identity or content).
pub fn refuse_duplicates<P: AsRef<Path>>(paths: &[P], by: skyfield::same::By) -> Result<()> {
    let d = skyfield::same::distinct_files(paths, by);
    if let Some(first) = d.duplicates.first() {
        let more = match d.duplicates.len() {
            1 => String::new(),
            n => format!(" ({} such pairs in all)", n),
        };
        bail!("{first}{more}: each input may be given once (the same data twice would be counted twice)");
    }
    Ok(())
}

/// Register the files this command reads, after refusing one passed twice (it would be summed
/// with itself, doubling its weight without a word). Files that do not exist are registered
/// too (their reader reports them).
pub fn inputs<'a>(paths: impl IntoIterator<Item = &'a Path>) -> Result<()> {
    let paths: Vec<&Path> = paths.into_iter().collect();
    register_inputs(&paths)?;
    skyfield::provenance::add_inputs(&paths);
    Ok(())
}

/// [`inputs`] where the command reads `streamed` whole and in order itself (the catalog's
/// frames): their provenance hashes are taken as they are read
/// (`skyfield::provenance::add_inputs_read_in_order`); `others` are hashed as by [`inputs`].
pub fn inputs_read_in_order<'a>(streamed: &[&'a Path], others: impl IntoIterator<Item = &'a Path>) -> Result<()> {
    let others: Vec<&Path> = others.into_iter().collect();
    let all: Vec<&Path> = streamed.iter().copied().chain(others.iter().copied()).collect();
    register_inputs(&all)?;
    skyfield::provenance::add_inputs_read_in_order(streamed);
    skyfield::provenance::add_inputs(&others);
    Ok(())
}

/// The checks of [`inputs`] (no file twice) and the registration against overwriting.
fn register_inputs(paths: &[&Path]) -> Result<()> {
    refuse_duplicates(paths, skyfield::same::By::Identity)?;
    INPUTS.lock().unwrap_or_else(|e| e.into_inner()).extend(paths.iter().map(|p| p.to_path_buf()));
    Ok(())
}

/// The instrument a command that reads files reads them as: `--instrument` when given, else
/// the built-in one the first file's `INSTRUME` names (said on stderr, and recorded in the
/// run's provenance), else an error asking for `--instrument` (`skyfield::io::instrument_from_headers`).
pub fn instrument_of(given: &Option<String>, first: Option<&Path>) -> Result<String> {
    if let Some(g) = given {
        return Ok(g.clone());
    }
    let Some(first) = first else {
        bail!("no input file says which instrument it is of: give --instrument NAME or FILE")
    };
    let (name, how) =
        skyfield::io::instrument_from_headers(first).map_err(|e| anyhow::anyhow!("{e} (--instrument)"))?;
    eprintln!("note: {how}; give --instrument to read them as another");
    if let Some(text) = instrument::builtin_source(&name) {
        skyfield::provenance::set_instrument(&name, text.as_bytes());
    }
    Ok(name)
}

/// Start the run's provenance (`skyfield::provenance`): the command line, and the instrument
/// named by `--instrument` (a file, hashed as read, or a built-in definition). Inputs are added
/// by [`inputs`]; every FITS output and every `--json` object then carries it.
pub fn start_provenance() {
    let args: Vec<String> = std::env::args().collect();
    skyfield::provenance::set_session(skyfield::provenance::Provenance::of_command(&args));
}

/// For `instpol run` (`workflow::night::run`, "Hashes read once" and "Up to date"): when the
/// environment names a file in `INPUT_HASHES_ENV`, every file the command read is written
/// there with its hash: the run's provenance inputs with the hashes computed while reading
/// them, and every other file its arguments name as inputs ([`guard_arguments`]: an instrument
/// file, a master, a calibration), hashed now. A file that cannot be written is no error of
/// the command: the runner then hashes the plan's inputs itself.
pub fn report_input_hashes() {
    let Some(path) = std::env::var_os(workflow::night::run::INPUT_HASHES_ENV) else { return };
    let mut read = skyfield::provenance::current().inputs;
    let named: Vec<PathBuf> = INPUTS.lock().unwrap_or_else(|e| e.into_inner()).clone();
    for p in named.iter().filter(|p| p.is_file()) {
        let name = p.display().to_string();
        if !read.iter().any(|i| i.path == name) {
            if let Ok(hash) = skyfield::provenance::hash_file(p) {
                read.push(skyfield::provenance::InputFile { path: name, hash });
            }
        }
    }
    if let Ok(text) = serde_json::to_string(&read) {
        let _ = std::fs::write(path, text);
    }
}

/// Whether an argument takes a number (a float or an integer type): such an option takes a
/// value that starts with '-' (`main`), its help must name a unit, and the hostile-input
/// generator gives it the numeric edge values (`instpol cli-spec`).
pub fn is_numeric_arg(a: &clap::Arg) -> bool {
    use std::any::TypeId;
    let t = a.get_value_parser().type_id();
    [TypeId::of::<f64>(), TypeId::of::<usize>(), TypeId::of::<u64>(), TypeId::of::<u32>(), TypeId::of::<i64>()]
        .iter()
        .any(|id| t == *id)
}

/// Every floating-point option of a command line is a finite number: a NaN or an infinity
/// reached the commands as a value (an imported map's zero angle of NaN, a clipping level or a
/// star's FWHM of inf, accepted with exit 0 when the run did not use it) and no option means
/// anything by one. The message names the option and its value. `def` is the subcommand's
/// definition and `m` its matches.
pub fn check_finite_options(def: &clap::Command, m: &clap::ArgMatches) -> std::result::Result<(), String> {
    for arg in def.get_arguments() {
        if arg.get_value_parser().type_id() != std::any::TypeId::of::<f64>() {
            continue;
        }
        let id = arg.get_id().as_str();
        let Ok(Some(values)) = m.try_get_many::<f64>(id) else { continue };
        if let Some(v) = values.copied().find(|v| !v.is_finite()) {
            let name = arg.get_long().map_or_else(|| id.to_string(), |l| format!("--{l}"));
            return Err(format!("invalid value '{v}' for '{name}': not a finite number (every number given to an option must be finite)\n"));
        }
    }
    Ok(())
}

/// `--bin` must be a number of pixels that fits the detector (1 ..= its longer side): a bin of
/// 1e11 px overflowed the bin-count arithmetic (a panic) before it was checked.
pub fn check_bin(bin: usize, inst: &instrument::Instrument) -> Result<()> {
    skyfield::reduce::check_bin(bin, inst).map_err(|e| anyhow::anyhow!("--bin {bin}: {e}"))
}

/// An `--instrument` value as an input path when it names a file (built-in names do not).
pub fn file_arg(s: &str) -> Option<&Path> {
    let p = Path::new(s);
    p.is_file().then_some(p)
}

/// The message for a telescope band that cannot be chosen
/// (`fit::telescope::TelescopeFit::choose_band`), for calibration `cal` and the frames' filter.
pub fn band_choice_error(e: fit::telescope::BandChoiceError, cal: &Path, frames_filter: Option<&str>) -> anyhow::Error {
    use fit::telescope::{BandChoiceError, BandSource};
    match e {
        BandChoiceError::Missing { band, source: BandSource::Asked, bands } => {
            anyhow::anyhow!("--band {band}: the telescope model of {} has bands {}", cal.display(), bands.join(", "))
        }
        BandChoiceError::Missing { band, source: BandSource::FieldCalibration, bands } => anyhow::anyhow!(
            "{}: the field calibration is for filter {band}, a band the telescope model does not have (it has {}): choose one with --band",
            cal.display(),
            bands.join(", ")
        ),
        BandChoiceError::Ambiguous { bands } => anyhow::anyhow!(
            "{}: the telescope model has bands {}{}: choose one with --band",
            cal.display(),
            bands.join(", "),
            frames_filter.map_or(String::new(), |f| format!(" and the frames' filter is {f}"))
        ),
    }
}

/// Refuse an output that resolves to one of the registered inputs (same path after resolving
/// symlinks and `..`, or same device and inode), naming both.
pub fn check_output(out: &Path) -> Result<()> {
    let ins = INPUTS.lock().unwrap_or_else(|e| e.into_inner()).clone();
    skyfield::durable::refuse_overwrite(out, ins.iter().map(PathBuf::as_path)).map_err(anyhow::Error::msg)
}

/// A check that ran and failed (a standard star that does not match its prediction): the
/// command's report is already printed; `main` prints this line and exits with code 1, which
/// scripts tell apart from 0 (passed) and 2 (bad input, nothing checked).
#[derive(Debug)]
pub struct CheckFailed(pub String);

impl std::fmt::Display for CheckFailed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for CheckFailed {}

/// Every JSON object a command prints carries the run's provenance as its last key,
/// `provenance` (spliced into the text so that the command's own key order is kept; a list
/// stays a list).
fn with_provenance(s: String) -> Result<String> {
    let body = s.trim_end();
    if !(body.starts_with('{') && body.ends_with('}')) || body.contains("\n  \"provenance\": ") {
        return Ok(s);
    }
    let p = serde_json::to_string_pretty(&skyfield::provenance::current())?.replace('\n', "\n  ");
    let inner = body[1..body.len() - 1].trim_end();
    Ok(if inner.trim().is_empty() {
        format!("{{\n  \"provenance\": {p}\n}}")
    } else {
        format!("{{{inner},\n  \"provenance\": {p}\n}}")
    })
}

/// Print a value as pretty JSON on stdout.
pub fn print_json<T: serde::Serialize>(v: &T) -> Result<()> {
    let mut s = with_provenance(serde_json::to_string_pretty(v)?)?;
    s.push('\n');
    write_stdout(s.as_bytes());
    Ok(())
}

/// The first error met writing stdout that was not a closed pipe.
static STDOUT_ERROR: std::sync::OnceLock<String> = std::sync::OnceLock::new();

/// Write to stdout, the one way the CLI prints results (`outln!`, `out!`, [`print_json`]).
/// A closed pipe (`instpol bias ... | head -3`) is the reader's choice: the rest of the output
/// is dropped and the command goes on to write its files and exit normally (`println!` would
/// panic, and a panic would leave those files unwritten). Any other error (a full disk behind
/// `> file`) is remembered and fails the command at its end ([`stdout_status`]).
pub fn write_stdout(bytes: &[u8]) {
    static CLOSED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    if CLOSED.load(std::sync::atomic::Ordering::Relaxed) {
        return;
    }
    let mut out = std::io::stdout().lock();
    if let Err(e) = out.write_all(bytes).and_then(|()| out.flush()) {
        CLOSED.store(true, std::sync::atomic::Ordering::Relaxed);
        if e.kind() != std::io::ErrorKind::BrokenPipe {
            let _ = STDOUT_ERROR.set(e.to_string());
        }
    }
}

/// Err when printing failed for another reason than a closed pipe.
pub fn stdout_status() -> Result<()> {
    match STDOUT_ERROR.get() {
        Some(e) => anyhow::bail!("cannot write the results to standard output: {e}"),
        None => Ok(()),
    }
}

/// The one way the CLI writes a file: `write` fills a temporary file (named `.instpol-*SUFFIX`)
/// in the destination folder, which is then renamed onto `path`; on any error the temporary
/// is removed, so an interrupted or failed run never leaves a half-written file.
pub fn write_via_temp(path: &Path, suffix: &str, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    check_output(path)?;
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let tmp = skyfield::fits::temp_beside(path, suffix)
        .with_context(|| format!("cannot create a temporary file in {}", dir.display()))?;
    // The closure writes by name (plotters, CFITSIO open their own handle); it must close
    // what it opened and return every error (FITS: through `skyfield::durable::close_fits`).
    write(tmp.path())?;
    // fsync then rename: a deferred write error (full disk) fails the command here and the
    // temporary is deleted, instead of a truncated file under the final name and exit 0.
    skyfield::durable::finish(tmp.into_temp_path(), path)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// Write `bytes` to `path` through [`write_via_temp`].
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_via_temp(path, ".tmp", |tmp| {
        std::fs::File::create(tmp)
            .and_then(|mut f| {
                f.write_all(bytes)?;
                f.flush()
            })
            .with_context(|| format!("cannot write {}", path.display()))
    })
}

/// A duration for a person: seconds, minutes, hours or days.
pub fn human_seconds(s: f64) -> String {
    if s < 120.0 {
        format!("{s:.0} s")
    } else if s < 7200.0 {
        format!("{:.0} min", s / 60.0)
    } else if s < 2.0 * 86400.0 {
        format!("{:.1} h", s / 3600.0)
    } else {
        format!("{:.1} days", s / 86400.0)
    }
}

/// `--annulus R_IN,R_OUT` (px): the one parser of photometry, catalog and zero-angle.
pub fn parse_radii(s: &str) -> Result<(f64, f64)> {
    let parsed: Option<Vec<f64>> = s.split(',').map(|t| t.trim().parse().ok()).collect();
    match parsed.as_deref() {
        Some([r1, r2]) => Ok((*r1, *r2)),
        _ => bail!("--annulus '{s}': expected two radii in px, e.g. 12,20"),
    }
}

/// `--aperture`: `8` (px), `2.5fwhm` (a multiple of the star's FWHM) or `best` (the radius of
/// best S/N on the star's curve of growth).
pub fn parse_aperture(s: &str) -> Result<skyfield::photometry::ApertureRadius> {
    use skyfield::photometry::ApertureRadius;
    match ApertureRadius::parse(s) {
        Some(ApertureRadius::Px(r)) if !(r > 0.0 && r < 1000.0) => {
            anyhow::bail!("--aperture {s}: expected a radius between 0 and 1000 px")
        }
        Some(ApertureRadius::FwhmMultiple(k)) if !(k > 0.0 && k <= 20.0) => {
            anyhow::bail!("--aperture {s}: expected a multiple of the FWHM between 0 and 20")
        }
        Some(r) => Ok(r),
        None => anyhow::bail!(
            "--aperture '{s}': expected a radius in px (8), a multiple of the FWHM (2.5fwhm) or 'best' (best S/N on the curve of growth)"
        ),
    }
}

/// `--parang START[,END]` (deg) as a track (rad), each angle by `fit::telescope::angle_from_deg`.
pub fn parse_parang(s: &str) -> Result<fit::telescope::Track> {
    let v: Vec<&str> = s.split(',').collect();
    let num = |t: &str| -> Result<f64> {
        let x: f64 = t.trim().parse().map_err(|_| anyhow::anyhow!("--parang '{s}': '{t}' is not a number (deg)"))?;
        fit::telescope::angle_from_deg(x)
            .ok_or_else(|| anyhow::anyhow!("--parang '{s}': {x} is not an angle in degrees (-360 to 360)"))
    };
    match v.as_slice() {
        [a] => Ok(fit::telescope::Track::at(num(a)?)),
        [a, b] => Ok(fit::telescope::Track::new(num(a)?, Some(num(b)?))),
        _ => bail!("--parang '{s}': expected START or START,END in degrees"),
    }
}

/// `--rotator DEG` (the rotator / adapter angle, deg) in radians (`fit::telescope::angle_from_deg`).
pub fn parse_rotator(x: f64) -> Result<f64> {
    fit::telescope::angle_from_deg(x)
        .ok_or_else(|| anyhow::anyhow!("--rotator {x}: not an angle in degrees (-360 to 360)"))
}
