//! `instpol stokes`: reduce one source's dual-beam fluxes.

use anyhow::Result;

/// Reduce the ordinary/extraordinary fluxes of one source at N half-wave-plate angles to
/// Q/I, U/I, P, chi with errors, Fourier harmonics and the Wollaston kappa.
#[derive(clap::Args)]
pub struct Args {
    /// CSV with columns hwp_deg,f_o,f_e[,sigma_o,sigma_e].
    #[arg(long)]
    pub input: std::path::PathBuf,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(_a: Args) -> Result<()> {
    anyhow::bail!("not yet implemented")
}
