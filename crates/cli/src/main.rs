//! `instpol`: the command-line tool. It parses arguments, prints tables and JSON, draws plots
//! and shows progress; all science lives in the library crates (`mueller`, `stokes`,
//! `skyfield`, `fit`, `sim`).

use clap::{Parser, Subcommand};

mod cmd;
mod plot;
mod util;

/// Find, model and remove the instrumental polarization of dual-beam imaging polarimeters
/// (half-wave plate + Wollaston prism, e.g. VLT FORS1/FORS2), following Patat & Romaniello
/// 2006, PASP 118, 146.
///
/// Every command that prints numbers takes --json for scripts. Polarization degrees are
/// fractions in JSON and percent (labelled) in tables; angles are degrees at the edges.
/// Errors in the input exit with code 2 and a message that names the input.
#[derive(Parser)]
#[command(name = "instpol", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    Simulate(cmd::simulate::Args),
    Reduce(cmd::reduce::Args),
    Photometry(cmd::photometry::Args),
    Validate(cmd::validate::Args),
    Bias(cmd::bias::Args),
    Mc(cmd::mc::Args),
    Correct(cmd::correct::Args),
    Stokes(cmd::stokes::Args),
    Fresnel(cmd::fresnel::Args),
    Raytrace(cmd::raytrace::Args),
    Calibrate(cmd::calibrate::Args),
    Fit(cmd::fit::Args),
    ImportMap(cmd::import_map::Args),
    WavelengthLaw(cmd::wavelength_law::Args),
    Plot(cmd::plot::Args),
    Demo(cmd::demo::Args),
}

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Simulate(a) => cmd::simulate::run(a),
        Command::Reduce(a) => cmd::reduce::run(a),
        Command::Photometry(a) => cmd::photometry::run(a),
        Command::Validate(a) => cmd::validate::run(a),
        Command::Bias(a) => cmd::bias::run(a),
        Command::Mc(a) => cmd::mc::run(a),
        Command::Correct(a) => cmd::correct::run(a),
        Command::Stokes(a) => cmd::stokes::run(a),
        Command::Fresnel(a) => cmd::fresnel::run(a),
        Command::Raytrace(a) => cmd::raytrace::run(a),
        Command::Calibrate(a) => cmd::calibrate::run(a),
        Command::Fit(a) => cmd::fit::run(a),
        Command::ImportMap(a) => cmd::import_map::run(a),
        Command::WavelengthLaw(a) => cmd::wavelength_law::run(a),
        Command::Plot(a) => cmd::plot::run(a),
        Command::Demo(a) => cmd::demo::run(a),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(2);
    }
}
