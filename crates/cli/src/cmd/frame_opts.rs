//! Options every command that reads frames shares: calibration frames and HWP angles.

use anyhow::{bail, Result};
use std::path::PathBuf;

/// Calibration frames and HWP angles for reading raw frames.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct FrameOpts {
    /// Master bias (from `instpol master-bias`), subtracted from every frame after its
    /// overscan level.
    #[arg(long, value_name = "BIAS.fits")]
    pub bias: Option<PathBuf>,
    /// Master flat (from `instpol master-flat`): every frame is divided by it.
    #[arg(long, value_name = "FLAT.fits")]
    pub flat: Option<PathBuf>,
    /// HWP angles in degrees, one per exposure in the order of the frames (for headers without
    /// an HWP-angle keyword), e.g. 0,22.5,45,67.5.
    #[arg(long, value_name = "DEG,DEG,...", allow_hyphen_values = true)]
    pub hwp_angles: Option<String>,
    /// The frames are already trimmed and assembled into the detector frame (another
    /// pipeline's products, bias-subtracted), for an instrument whose raw frames are chip
    /// files (FORS2, EFOSC2): each is read as one image of the detector's size in ADU, with no
    /// overscan; --bias and --flat still apply when given.
    #[arg(long)]
    pub assembled: bool,
    /// Apply --bias and --flat even when the instrument file declares its frames already bias
    /// or flat corrected ([format] already_corrected, e.g. MOPTOP's level-1 frames); without
    /// it such a master is refused.
    #[arg(long)]
    pub correct_again: bool,
}

impl FrameOpts {
    /// The first frame-reading option given (`--bias`, `--flat`, `--hwp-angles`,
    /// `--assembled`, `--correct-again`), for a command that was given no frames to apply it to.
    pub fn first_given(&self) -> Option<&'static str> {
        [
            (self.bias.is_some(), "--bias"),
            (self.flat.is_some(), "--flat"),
            (self.hwp_angles.is_some(), "--hwp-angles"),
            (self.assembled, "--assembled"),
            (self.correct_again, "--correct-again"),
        ]
        .into_iter()
        .find_map(|(given, name)| given.then_some(name))
    }

    /// The library's reading options.
    pub fn read_options(&self) -> Result<skyfield::calib::ReadOptions> {
        let hwp_angles_deg = match &self.hwp_angles {
            None => None,
            Some(s) => {
                // Parsed here; the rule (some angles, each finite) is the library's.
                let v: Option<Vec<f64>> = s.split(',').map(|t| t.trim().parse::<f64>().ok()).collect();
                match v {
                    Some(v) if skyfield::calib::ReadOptions::check_hwp_angles(&v).is_ok() => Some(v),
                    _ => {
                        bail!("--hwp-angles '{s}': expected angles in degrees separated by commas, e.g. 0,22.5,45,67.5")
                    }
                }
            }
        };
        Ok(skyfield::calib::ReadOptions {
            bias: self.bias.clone(),
            flat: self.flat.clone(),
            hwp_angles_deg,
            assembled: self.assembled,
            correct_again: self.correct_again,
        })
    }
}

/// The Wollaston imbalance kappa: a known value, or estimated from the data and applied in the
/// same run (paper, sec:wollaston, eq:kappa2).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct KappaOpts {
    /// Known Wollaston imbalance kappa = (t - s)/(t + s), dimensionless in (-1, 1): the fluxes
    /// are corrected (f_o / (1 + kappa), f_e / (1 - kappa)) before the reduction. Default: no
    /// correction.
    #[arg(long, value_name = "K", allow_negative_numbers = true, conflicts_with = "kappa_from_data")]
    pub kappa: Option<f64>,
    /// Estimate kappa from the data (the mean kappa_j of eq:kappa2, from HWP positions 45 deg
    /// apart: needs N >= 4) and apply it in the same run; the output states the kappa applied.
    #[arg(long)]
    pub kappa_from_data: bool,
}

impl KappaOpts {
    /// The library's setting.
    pub fn correction(&self) -> Result<stokes::KappaCorrection> {
        match (self.kappa, self.kappa_from_data) {
            // The library's rule (stokes::KappaCorrection::known), worded for the option.
            (Some(k), _) => stokes::KappaCorrection::known(k).map_err(|e| anyhow::anyhow!("--kappa {k}: {e}")),
            (None, true) => Ok(stokes::KappaCorrection::FromData),
            (None, false) => Ok(stokes::KappaCorrection::None),
        }
    }
}
