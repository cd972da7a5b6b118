//! `instpol`: the command-line tool. It parses arguments, prints tables and JSON, draws plots
//! and shows progress; all science lives in the library crates (`mueller`, `stokes`,
//! `skyfield`, `fit`, `sim`).

use clap::{CommandFactory, FromArgMatches, Subcommand};

/// `println!` for the CLI's tables: a reader that closes the pipe (`| head`) ends the printing,
/// not the command (which still writes its files); see [`util::write_stdout`].
macro_rules! outln {
    () => { $crate::util::write_stdout(b"\n") };
    ($($t:tt)*) => { $crate::util::write_stdout(format!("{}\n", format_args!($($t)*)).as_bytes()) };
}

/// `print!` with [`outln!`]'s handling of a closed pipe.
macro_rules! out {
    ($($t:tt)*) => { $crate::util::write_stdout(format!($($t)*).as_bytes()) };
}

mod cmd;
mod plot;
mod util;

/// Find, model and remove the instrumental polarization of dual-beam imaging polarimeters
/// (half-wave plate + Wollaston prism, e.g. VLT FORS1/FORS2), following Patat & Romaniello
/// 2006, PASP 118, 146.
///
/// Every command takes --json for scripts (keys: docs/guide/formats.md, schemas/).
/// Polarization degrees are fractions in JSON and percent (labelled) in tables; angles are
/// degrees at the edges. Errors in the input exit with code 2 and a message that names the
/// input; with --json the error is one JSON object on stderr:
/// {"error": {"message", "kind": "input" | "io" | "check", "exit_code"}}.
#[derive(clap::Parser)]
#[command(name = "instpol", version, long_version = long_version(), about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// What `instpol --version` prints: the version, then how to cite the tool and the paper
/// (`skyfield::provenance::citation`, the one text of it, also the Python package's
/// `__citation__`); `-V` prints the version alone.
fn long_version() -> &'static str {
    static TEXT: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    TEXT.get_or_init(|| format!("{}\n\n{}", env!("CARGO_PKG_VERSION"), skyfield::provenance::citation().trim_end()))
}

#[derive(Subcommand)]
enum Command {
    #[command(about = "Run the whole chain on the paper's FORS1 empty fields (the main job; start here)")]
    Demo(cmd::demo::Args),
    #[command(
        about = "Sort a folder of raw files by their headers into a plan of units of work (masters, maps, catalogs, calibrations)"
    )]
    Scan(cmd::night::ScanArgs),
    #[command(
        about = "Run a plan from `instpol scan`: dependency order, finished units skipped, one unit for a job array"
    )]
    Run(cmd::night::RunArgs),
    #[command(
        about = "The standards' zero angle and instrumental polarization of many nights against date, steps flagged"
    )]
    Trend(cmd::trend::Args),
    #[command(
        about = "A static HTML report of nights' plans and products and of their trend: one folder, SVG figures, no network"
    )]
    Report(cmd::report::Args),
    #[command(about = "Simulate raw-like dual-beam FITS frames of a scene (only the effects it lists)")]
    Simulate(cmd::simulate::Args),
    #[command(about = "Reduce frames to a binned, sigma-clipped Stokes map")]
    Reduce(cmd::reduce::Args),
    #[command(about = "Combine bias frames into a master bias (sigma-clipped, overscan-corrected)")]
    MasterBias(cmd::master::BiasArgs),
    #[command(about = "Combine flat-field frames into a normalized master flat (sigma-clipped)")]
    MasterFlat(cmd::master::FlatArgs),
    #[command(about = "Measure a star's Q, U, P, chi in frames, background removed vectorially")]
    Photometry(cmd::photometry::Args),
    #[command(about = "Find, pair and measure every star in frames: Q, U, P, chi with errors and flags")]
    Catalog(cmd::catalog::Args),
    #[command(about = "Measure the instrumental polarization on an empty field of known sky polarization")]
    Calibrate(cmd::calibrate::Args),
    #[command(
        about = "Measure the instrumental polarization from field stars of dithered pointings (polarized ones rejected)"
    )]
    CalibrateStars(cmd::calibrate_stars::Args),
    #[command(about = "Fit the Mueller field (diattenuation, retardance, ...) jointly to several sky fields")]
    CalibrateMueller(cmd::calibrate_mueller::Args),
    #[command(about = "Which physics explains a fitted Mueller field: ray trace, stressed lens, HWP defects")]
    Explain(cmd::explain::Args),
    #[command(about = "Plan a Mueller-field calibration: fields and exposure for a target accuracy")]
    Plan(cmd::plan::Args),
    #[command(about = "Refit a calibration file (radial model, free centre, exclusions, residual map)")]
    Fit(cmd::fit::Args),
    #[command(about = "Turn third-party Q/I, U/I maps into a calibration file")]
    ImportMap(cmd::import_map::Args),
    #[command(about = "Fit p(lambda)/p(550 nm) = a + b lambda across filters' calibrations")]
    WavelengthLaw(cmd::wavelength_law::Args),
    #[command(about = "Draw a calibration's map, radial profile, polar-angle test and residual map")]
    Plot(cmd::plot::Args),
    #[command(about = "Remove the instrumental polarization from a catalog or a Stokes map")]
    Correct(cmd::correct::Args),
    #[command(about = "HWP zero angle of a filter from a polarized standard star in frames")]
    ZeroAngle(cmd::zero_angle::Args),
    #[command(
        about = "The instrument's (q0, u0), efficiency and angle offset from standards in catalogs, as a calibration file"
    )]
    Efficiency(cmd::efficiency::Args),
    #[command(about = "Check a calibration against a standard star in frames")]
    Validate(cmd::validate::Args),
    #[command(about = "Reduce one source's dual-beam fluxes: Q, U, P, chi, errors, harmonics, kappa")]
    Stokes(cmd::stokes::Args),
    #[command(about = "Estimate the true polarization P0 from a measured P and sigma, with an interval")]
    Bias(cmd::bias::Args),
    #[command(about = "Monte Carlo of dual-beam polarimetry; paper figures; accuracy against time")]
    Mc(cmd::mc::Args),
    #[command(
        about = "Fresnel and thin films: transmission diattenuation and retardance, reflection from metals with coatings"
    )]
    Fresnel(cmd::fresnel::Args),
    #[command(about = "Polarization ray trace of the collimator: p(r), phi, per surface, wavelength law")]
    Raytrace(cmd::raytrace::Args),
    #[command(about = "Fit a telescope M3 Mueller model to standard stars against the parallactic angle")]
    FitStandards(cmd::fit_standards::Args),
    #[command(hide = true, about = "Every command's arguments and their kinds, as JSON (for tests and scripts)")]
    CliSpec(cmd::cli_spec::Args),
}

fn main() {
    // Negative numbers are values everywhere (`--chi -30`, `--kappa -1e-3`, `--x -30`), in
    // every subcommand, not only where an argument remembered to say so. clap's own test for
    // a negative number knows no exponent (`-1e-3` was read as the flags -1, -e, ...), so the
    // numeric options take any value that starts with '-' and their parser judges it.
    let numeric = util::is_numeric_arg;
    let parsed = Cli::command()
        .mut_subcommands(|s| {
            s.allow_negative_numbers(true).mut_args(|a| {
                if !a.is_positional() && numeric(&a) {
                    a.allow_hyphen_values(true)
                } else {
                    a
                }
            })
        })
        .try_get_matches();
    // A script that asked for --json gets its usage errors as JSON too (the flag is looked for
    // in the raw arguments: the parse that would find it is the one that failed).
    let json_arg = std::env::args_os().skip(1).any(|a| a == "--json");
    let matches = match parsed {
        Ok(m) => m,
        Err(e) => clap_error(e, json_arg),
    };
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| clap_error(e, json_arg));
    let json =
        matches.subcommand().and_then(|(_, m)| m.try_get_one::<bool>("json").ok().flatten().copied()).unwrap_or(false);
    if let Some((name, m)) = matches.subcommand() {
        if let Some(def) = Cli::command().find_subcommand(name) {
            if let Err(e) = util::guard_arguments(def, m) {
                exit_with(e, json);
            }
            if let Err(message) = util::check_finite_options(def, m) {
                clap_error(clap::Error::raw(clap::error::ErrorKind::ValueValidation, message), json_arg);
            }
        }
    }
    util::start_provenance();
    // Commands that write several files and read none of them back write all or none
    // (`skyfield::durable::stage`): a failure after the first file left the others' files.
    // (Commands that write one file need no staging: their one write is atomic already.)
    let staged = matches!(
        cli.command,
        Command::FitStandards(_)
            | Command::Calibrate(_)
            | Command::CalibrateStars(_)
            | Command::Fit(_)
            | Command::Plot(_)
            | Command::CalibrateMueller(_)
            | Command::Raytrace(_)
    );
    let run = move || match cli.command {
        Command::Demo(a) => cmd::demo::run(a),
        Command::CliSpec(a) => cmd::cli_spec::run(a),
        Command::Scan(a) => cmd::night::run_scan(a),
        Command::Run(a) => cmd::night::run_run(a),
        Command::Trend(a) => cmd::trend::run(a),
        Command::Report(a) => cmd::report::run(a),
        Command::Simulate(a) => cmd::simulate::run(a),
        Command::Reduce(a) => cmd::reduce::run(a),
        Command::MasterBias(a) => cmd::master::run_bias(a),
        Command::MasterFlat(a) => cmd::master::run_flat(a),
        Command::Photometry(a) => cmd::photometry::run(a),
        Command::Catalog(a) => cmd::catalog::run(a),
        Command::Calibrate(a) => cmd::calibrate::run(a),
        Command::CalibrateStars(a) => cmd::calibrate_stars::run(a),
        Command::CalibrateMueller(a) => cmd::calibrate_mueller::run(a),
        Command::Explain(a) => cmd::explain::run(a),
        Command::Plan(a) => cmd::plan::run(a),
        Command::Fit(a) => cmd::fit::run(a),
        Command::ImportMap(a) => cmd::import_map::run(a),
        Command::WavelengthLaw(a) => cmd::wavelength_law::run(a),
        Command::Plot(a) => cmd::plot::run(a),
        Command::Correct(a) => cmd::correct::run(a),
        Command::ZeroAngle(a) => cmd::zero_angle::run(a),
        Command::Efficiency(a) => cmd::efficiency::run(a),
        Command::Validate(a) => cmd::validate::run(a),
        Command::Stokes(a) => cmd::stokes::run(a),
        Command::Bias(a) => cmd::bias::run(a),
        Command::Mc(a) => cmd::mc::run(a),
        Command::Fresnel(a) => cmd::fresnel::run(a),
        Command::Raytrace(a) => cmd::raytrace::run(a),
        Command::FitStandards(a) => cmd::fit_standards::run(a),
    };
    let result = if staged { skyfield::durable::stage(run) } else { run() };
    // Output the reader could not take for another reason than closing the pipe (a full
    // disk behind `> file`): the command's files are written, but the printed result is lost.
    let result = result.and_then(|()| util::stdout_status());
    let check_ran = result.as_ref().err().is_some_and(|e| e.downcast_ref::<util::CheckFailed>().is_some());
    if result.is_ok() || check_ran {
        util::report_input_hashes();
    }
    if let Err(e) = result {
        exit_with(e, json);
    }
}

/// End the command with its error: exit 2 for bad input or an unusable file, 1 for a check
/// that ran and failed; the message on stderr (as JSON under `--json`).
fn exit_with(e: anyhow::Error, json: bool) -> ! {
    // Exit codes: 0 success, 1 a check that ran and failed, 2 bad input.
    let (kind, code, message) = match e.downcast_ref::<util::CheckFailed>() {
        Some(f) => (ErrorKind::Check, 1, f.to_string()),
        None if is_io(&e) => (ErrorKind::Io, 2, format!("{e:#}")),
        None => (ErrorKind::Input, 2, format!("{e:#}")),
    };
    if json {
        eprintln!("{}", error_json(kind, code, &message));
    } else if kind == ErrorKind::Check {
        eprintln!("{message}");
    } else {
        eprintln!("error: {message}");
    }
    std::process::exit(code);
}

/// What went wrong, for the `kind` of a `--json` error: the input (a bad value, file content or
/// argument), the file system (an unreadable input, an unwritable output), or a check that ran
/// and failed (a standard star off its prediction).
#[derive(Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
enum ErrorKind {
    Input,
    Io,
    Check,
}

/// An error of the file system (a file that cannot be read or written), wherever in the chain:
/// a `std::io::Error`, or a library error that carries one as a field rather than a source.
fn is_io(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.is::<std::io::Error>()
            || matches!(c.downcast_ref::<fit::Error>(), Some(fit::Error::Io { .. }))
            || matches!(c.downcast_ref::<skyfield::Error>(), Some(skyfield::Error::Write { .. }))
            || matches!(c.downcast_ref::<instrument::Error>(), Some(instrument::Error::Io { .. }))
            || matches!(
                c.downcast_ref::<sim::Error>(),
                Some(
                    sim::Error::Frames(skyfield::Error::Write { .. })
                        | sim::Error::Instrument(instrument::Error::Io { .. })
                )
            )
    })
}

/// The one JSON form of an error on stderr under `--json` (schemas/error.schema.json):
/// `{"error": {"message", "kind", "exit_code"}}`, one line.
fn error_json(kind: ErrorKind, exit_code: i32, message: &str) -> String {
    #[derive(serde::Serialize)]
    struct Inner<'a> {
        message: &'a str,
        kind: ErrorKind,
        exit_code: i32,
    }
    #[derive(serde::Serialize)]
    struct Outer<'a> {
        error: Inner<'a>,
    }
    serde_json::to_string(&Outer { error: Inner { message, kind, exit_code } })
        .unwrap_or_else(|_| r#"{"error":{"message":"unprintable error","kind":"input","exit_code":2}}"#.into())
}

/// A command line clap refuses: as clap prints it, or under `--json` as the JSON error (exit 2,
/// clap's own code for usage errors). `--help` and `--version` print as usual.
fn clap_error(e: clap::Error, json: bool) -> ! {
    use clap::error::ErrorKind as K;
    if !json || matches!(e.kind(), K::DisplayHelp | K::DisplayVersion | K::DisplayHelpOnMissingArgumentOrSubcommand) {
        e.exit()
    }
    let text = e.render().to_string();
    // clap's message without its "error: " prefix and usage footer: the first paragraph.
    let first = text.trim_start_matches("error: ").split("\n\n").next().unwrap_or("").trim().to_string();
    eprintln!("{}", error_json(ErrorKind::Input, 2, &first));
    std::process::exit(2)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--version` gives the version and then the citation (the paper's reference and the
    /// BibTeX entries); `-V` the version line alone.
    #[test]
    fn long_version_cites_the_tool_and_the_paper() {
        let long = Cli::command().render_long_version();
        assert!(long.starts_with(&format!("instpol {}\n", env!("CARGO_PKG_VERSION"))), "{long}");
        assert!(long.contains("PASP 118, 146") && long.contains("@article{") && long.contains("@software{"), "{long}");
        assert!(long.trim_end().ends_with(skyfield::provenance::citation().trim_end()));
        assert_eq!(Cli::command().render_version(), format!("instpol {}\n", env!("CARGO_PKG_VERSION")));
    }

    /// Every path argument of every command is either a listed output
    /// ([`util::OUTPUT_ARGUMENTS`]) or guarded as an input ([`util::guard_arguments`]). The
    /// outputs are named by convention (`out`, `output`, `plot`, `..._out`, `..._dir`): a path
    /// argument named so but not listed would be guarded as an input, and a listed name that
    /// no command has is a stale entry. (An output named otherwise and not listed is refused on
    /// its first use, as the input it is taken for, so that mistake cannot pass its own test.)
    #[test]
    fn path_arguments_are_inputs_or_listed_outputs() {
        let (mut inputs, mut seen, mut wrong) = (0, std::collections::BTreeSet::new(), vec![]);
        let cli = Cli::command();
        for sub in cli.get_subcommands() {
            for arg in sub.get_arguments() {
                if arg.get_value_parser().type_id() != std::any::TypeId::of::<std::path::PathBuf>() {
                    continue;
                }
                let id = arg.get_id().as_str();
                let named_output =
                    id.starts_with("out") || id.starts_with("plot") || id.ends_with("_out") || id.ends_with("_dir");
                if util::OUTPUT_ARGUMENTS.contains(&id) {
                    seen.insert(id);
                } else if named_output {
                    wrong.push(format!("{} --{id} is named as an output but not listed", sub.get_name()));
                } else {
                    inputs += 1;
                }
            }
        }
        for id in util::OUTPUT_ARGUMENTS {
            if !seen.contains(id) {
                wrong.push(format!("--{id} is listed as an output but no command has it"));
            }
        }
        assert!(wrong.is_empty(), "{}", wrong.join("\n"));
        assert!(inputs > 25, "only {inputs} input path arguments found");
    }
}

/// `--help` teaches: every command's help shows an example command line, and every option that
/// takes a number says its unit (or that it is a count, a ratio, a seed), so that nobody has to
/// guess whether `--sky-p` is percent or a fraction.
#[cfg(test)]
mod help_tests {
    use super::Cli;
    use clap::CommandFactory;

    /// Words that state a number's unit or kind in a help text (matched in lower case).
    #[rustfmt::skip]
    const UNIT_WORDS: [&str; 32] = [
        "px", "pixel", "arcmin", "arcsec", "deg", "rad", "nm", "micron", "percent", "%", "fraction", "sigma", "e-",
        "electron", "adu", "second", " s ", " s)", " s,", " s.", "count", "number of", "seed", "ratio", "dimensionless",
        "index", "threads", "trials", "times", "ppm", "chi^2", "minute",
    ];

    use crate::util::is_numeric_arg as is_numeric;

    #[test]
    fn every_command_help_has_an_example_and_units_for_its_numbers() {
        // Unwrapped, so that an example command line is one line of text.
        let mut cli = Cli::command().term_width(0);
        cli.build();
        let mut missing = vec![];
        let mut n_commands = 0;
        for sub in cli.get_subcommands_mut() {
            let name = sub.get_name().to_string();
            if name == "help" {
                continue; // clap's own
            }
            n_commands += 1;
            let help = sub.render_long_help().to_string();
            let example = format!("instpol {name} ");
            if !(help.to_lowercase().contains("example") && help.contains(&example)) {
                missing.push(format!("{name}: no example ('Example: {example}...') in --help"));
            }
            for a in sub.get_arguments().filter(|a| is_numeric(a)) {
                let text = format!(
                    "{} {}",
                    a.get_help().map(|h| h.to_string()).unwrap_or_default(),
                    a.get_long_help().map(|h| h.to_string()).unwrap_or_default()
                )
                .to_lowercase();
                if !UNIT_WORDS.iter().any(|w| text.contains(w)) {
                    missing.push(format!("{name} --{}: takes a number but its help names no unit", a.get_id()));
                }
            }
        }
        assert!(n_commands >= 24, "{n_commands} commands");
        assert!(missing.is_empty(), "{} help text(s) to complete:\n{}", missing.len(), missing.join("\n"));
    }
}
