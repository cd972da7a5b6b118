//! The CLI's CSV reader and reduction (`instpol stokes`, crates/cli/src/cmd/stokes.rs,
//! compiled in here as it is, because the CLI has no library) on the input written to a
//! file: header and column lookup, the numbers of each row, then `stokes::Measurement` +
//! `reduce` and the JSON and table output (stdout is closed by run.sh with
//! -close_fd_mask=1), without and with a kappa correction. The plot is not drawn.
#![no_main]
use clap::Parser;
use libfuzzer_sys::fuzz_target;

mod util {
    /// The CLI's `util::print_json`, all that stokes.rs takes from `crate::util`.
    pub fn print_json<T: serde::Serialize>(v: &T) -> anyhow::Result<()> {
        println!("{}", serde_json::to_string_pretty(v)?);
        Ok(())
    }
}

#[path = "../../crates/cli/src/cmd/stokes_plot/data.rs"]
pub mod stokes_plot_data;

/// `super::stokes_plot` as stokes.rs sees it: the plot's numbers (pure), no drawing.
mod stokes_plot {
    pub use super::stokes_plot_data as data;
    pub fn fourier_png(_: &std::path::Path, _: &data::FourierPlot) -> anyhow::Result<()> {
        unreachable!("the fuzz target passes no --plot")
    }
}

#[allow(dead_code)]
#[path = "../../crates/cli/src/cmd/stokes.rs"]
mod stokes_cmd;

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    args: stokes_cmd::Args,
}

fuzz_target!(|data: &[u8]| {
    let p = instpol_fuzz::write_input("input.csv", data);
    let p = p.to_str().expect("scratch paths are UTF-8");
    for extra in [&["--json"][..], &["--kappa", "0.03"][..]] {
        let mut argv = vec!["stokes", "--input", p];
        argv.extend_from_slice(extra);
        let _ = stokes_cmd::run(Cli::parse_from(argv).args);
    }
});
