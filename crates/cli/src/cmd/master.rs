//! `instpol master-bias` and `instpol master-flat`: calibration frames from raw frames.

use anyhow::Result;
use std::path::PathBuf;

/// Combine bias frames into a master bias: each frame is trimmed, its chips placed in the
/// detector frame and its overscan level subtracted (as the instrument's [format] says), then
/// every pixel is the sigma-clipped mean over the frames (median/MAD, --nsigma). Written as a
/// 32-bit float FITS image in ADU with provenance keywords (HIERARCH INSTPOL MASTER = 'BIAS',
/// NCOMBINE, the input files); pixels of the chip gap are NaN.
///
/// Example: instpol master-bias bias/*.fits --instrument efosc2 --out bias.fits
#[derive(clap::Args)]
pub struct BiasArgs {
    /// Bias frames (FITS; for a mosaic, the chip files of each exposure next to each other).
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Instrument: built-in name or path to an instrument TOML.
    /// Default: the built-in instrument the first file's INSTRUME keyword names (said on
    /// stderr); a file without one, or of no built-in instrument, is refused.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Clipping threshold per pixel in robust sigmas.
    #[arg(long, default_value_t = workflow::steps::DEFAULT_MASTER_NSIGMA)]
    pub nsigma: f64,
    /// Output master bias (FITS).
    #[arg(long)]
    pub out: PathBuf,
    /// Print JSON (output, n_frames, nx_px, ny_px; schemas/master-bias.schema.json) instead of
    /// a line of text.
    #[arg(long)]
    pub json: bool,
}

/// Combine flat-field frames into a master flat: each frame is trimmed, overscan- and (with
/// --bias) bias-subtracted, converted to electrons and divided by its own median; every pixel
/// is the sigma-clipped mean over the frames, and the result is normalized to a median of 1
/// over the detector (chip gap excluded, NaN there). Written as a 32-bit float FITS image with
/// provenance keywords (HIERARCH INSTPOL MASTER = 'FLAT').
///
/// Example: instpol master-flat flats/*.fits --instrument fors2 --bias bias.fits --out flat.fits
#[derive(clap::Args)]
pub struct FlatArgs {
    /// Flat-field frames (FITS; for a mosaic, the chip files of each exposure together).
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Instrument: built-in name or path to an instrument TOML.
    /// Default: the built-in instrument the first file's INSTRUME keyword names (said on
    /// stderr); a file without one, or of no built-in instrument, is refused.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Master bias (from `instpol master-bias`).
    #[arg(long, value_name = "BIAS.fits")]
    pub bias: Option<PathBuf>,
    /// Clipping threshold per pixel in robust sigmas.
    #[arg(long, default_value_t = workflow::steps::DEFAULT_MASTER_NSIGMA)]
    pub nsigma: f64,
    /// Output master flat (FITS).
    #[arg(long)]
    pub out: PathBuf,
    /// Print JSON (output, n_frames, nx_px, ny_px; schemas/master-flat.schema.json) instead of
    /// a line of text.
    #[arg(long)]
    pub json: bool,
}

/// The JSON of `master-bias` and `master-flat`.
#[derive(serde::Serialize)]
struct Out {
    output: String,
    n_frames: usize,
    nx_px: usize,
    ny_px: usize,
    /// What the master is of: the instrument file, its filter (a flat's), binning and
    /// detector, the frames' hashes.
    product: skyfield::provenance::Product,
}

/// Print what was written: JSON or one line naming the master.
fn report(
    json: bool,
    out: &std::path::Path,
    what: &str,
    m: &skyfield::calib::Master,
    inst: &instrument::Instrument,
) -> Result<()> {
    let (n_frames, nx, ny) = (m.inputs.len(), m.nx, m.ny);
    if json {
        let product = skyfield::provenance::Product {
            filter: m.filter.clone(),
            binning: m.binning.map(|[x, y]| (x, y)),
            ..skyfield::provenance::Product::of_instrument_alone(inst)
        }
        .with_run_inputs();
        return crate::util::print_json(&Out {
            output: out.display().to_string(),
            n_frames,
            nx_px: nx,
            ny_px: ny,
            product,
        });
    }
    outln!("{}: master {what} of {n_frames} frames ({nx} x {ny} px)", out.display());
    Ok(())
}

pub fn run_bias(a: BiasArgs) -> Result<()> {
    let instrument = crate::util::instrument_of(&a.instrument, a.frames.first().map(|p| p.as_path()))?;
    // Registered: the provenance hashes them, and the output may not be one of them.
    crate::util::inputs(a.frames.iter().map(|p| p.as_path()).chain(crate::util::file_arg(&instrument)))?;
    crate::util::check_output(&a.out)?;
    let inst = instrument::Instrument::load(&instrument)?;
    let m = workflow::steps::master_bias(&a.frames, &inst, a.nsigma, &a.out)?;
    report(a.json, &a.out, "bias", &m, &inst)
}

pub fn run_flat(a: FlatArgs) -> Result<()> {
    let instrument = crate::util::instrument_of(&a.instrument, a.frames.first().map(|p| p.as_path()))?;
    crate::util::inputs(
        a.frames.iter().map(|p| p.as_path()).chain(a.bias.as_deref()).chain(crate::util::file_arg(&instrument)),
    )?;
    crate::util::check_output(&a.out)?;
    let inst = instrument::Instrument::load(&instrument)?;
    let m = workflow::steps::master_flat(&a.frames, &inst, a.bias.as_deref(), a.nsigma, &a.out)?;
    report(a.json, &a.out, "flat", &m, &inst)
}
