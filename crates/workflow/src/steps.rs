//! The steps from frames to products, each one library call that the CLI (`instpol reduce`,
//! `catalog`, `master-bias`, `master-flat`, `calibrate --map`), the Python package
//! (`instpol.reduce`, `instpol.catalog`) and a night's units run in process
//! (`workflow::night::call`) make alike: what a step composes (the reduction, the exposures'
//! telescope angles recorded, the correction in the same run, the file written) is composed
//! here once, and the faces only parse, print and plot.

use fit::correction::catalog_correct::{correct_catalog_loaded, CorrectedCatalog, TelescopeUsed};
use fit::correction::correct::CorrectOptions;
use fit::files::calibration::CalibrationFile;
use instrument::Instrument;
use skyfield::calib::ReadOptions;
use skyfield::catalog::{Catalog, CatalogConfig};
use skyfield::reduce::{PlateReduced, ReduceConfig};
use std::path::{Path, PathBuf};

/// The defaults of the steps' options, one place for the CLI's `--help` and a night's units
/// read back in process ([`crate::night::call`]): a master's clipping threshold (robust
/// sigma), a map's bin (px), a catalog's star FWHM (px) and aperture radius (px).
pub const DEFAULT_MASTER_NSIGMA: f64 = 3.0;
pub const DEFAULT_BIN_PX: usize = 30;
pub const DEFAULT_FWHM_PX: f64 = 4.0;
pub const DEFAULT_APERTURE: &str = "8";
/// Frames to a Stokes map (`instpol reduce`, `instpol.reduce`): the instrument's plate decides
/// the map (`skyfield::reduce::reduce_for_plate`: `Q/I`, `U/I`, or `V/I` through a quarter-wave
/// plate); a linear map records the exposures' telescope angles when the headers have them
/// (`fit::telescope::cal::record_telescope_angles`, what `instpol correct` needs to remove a
/// telescope model from it); written to `out` when given. `on_read` is told of every frame read.
pub fn reduce(
    frames: &[PathBuf],
    inst: &Instrument,
    cfg: &ReduceConfig,
    read: &ReadOptions,
    out: Option<&Path>,
    on_read: &(dyn Fn() + Sync),
) -> Result<PlateReduced, skyfield::Error> {
    let mut r = skyfield::reduce::reduce_for_plate(frames, inst, cfg, read, on_read)?;
    match &mut r {
        PlateReduced::Linear(r) => {
            fit::telescope::cal::record_telescope_angles(&mut r.map, &r.exposures, frames, inst);
            if let Some(out) = out {
                r.map.write_fits(out)?;
            }
        }
        PlateReduced::Circular(r) => {
            if let Some(out) = out {
                r.map.write_fits(out)?;
            }
        }
    }
    Ok(r)
}

/// A catalog measured, corrected when a calibration is given, and written: what
/// [`catalog`] returns.
pub struct CatalogRun {
    pub catalog: Catalog,
    pub warnings: Vec<skyfield::Warning>,
    /// The correction in the same run (`instpol catalog --cal`), with the telescope model it
    /// undid, if any.
    pub corrected: Option<(CorrectedCatalog, Option<TelescopeUsed>)>,
}

/// Why [`catalog`] failed, by the part that failed: the faces word each (the CLI names
/// `--cal` for a correction's refusal, Python `cal`).
#[derive(Debug, thiserror::Error)]
pub enum CatalogError {
    /// Measuring the frames.
    #[error(transparent)]
    Frames(skyfield::Error),
    /// Correcting the catalog with the calibration.
    #[error(transparent)]
    Correction(fit::correction::catalog_correct::Error),
    /// Writing the table.
    #[error(transparent)]
    Output(skyfield::Error),
}

/// Every paired star of a frame set (`instpol catalog`, `instpol.catalog`):
/// `skyfield::catalog::catalog_files`, then, with a calibration `cal`, the correction in the
/// same run (`fit::correction::catalog_correct::correct_catalog_loaded`), and, with `out`, the
/// table written with the exposures' telescope angles (`fit::telescope::cal::recorded_angles`,
/// for `instpol correct`) and the corrected columns of `instpol correct`
/// (`fit::correction::columns::Outputs`, NaN for a star not measured).
pub fn catalog(
    frames: &[PathBuf],
    inst: &Instrument,
    read: &ReadOptions,
    cfg: &CatalogConfig,
    cal: Option<(&CalibrationFile, CorrectOptions)>,
    out: Option<&Path>,
    on_read: Box<dyn Fn() + Send + Sync>,
) -> Result<CatalogRun, CatalogError> {
    let (catalog, warnings) =
        skyfield::catalog::catalog_files(frames, inst, read, cfg, on_read).map_err(CatalogError::Frames)?;
    let corrected = match cal {
        None => None,
        Some((loaded, opts)) => {
            Some(correct_catalog_loaded(&catalog, inst, frames, loaded, opts).map_err(CatalogError::Correction)?)
        }
    };
    if let Some(out) = out {
        let mut t = catalog.to_table();
        // ECSV, FITS and VOTable carry the angles; CSV has no place for them.
        if let Some(angles) = fit::telescope::cal::recorded_angles(&catalog.frames, frames, inst) {
            t.meta = angles.to_meta();
        }
        if let Some((c, _)) = &corrected {
            t.columns.extend(fit::correction::columns::Outputs::of_rows(&c.rows).into_table_columns());
        }
        t.write(out).map_err(CatalogError::Output)?;
    }
    Ok(CatalogRun { catalog, warnings, corrected })
}

/// A master bias (`instpol master-bias`): `skyfield::calib::master_bias`, written to `out`;
/// returns the master.
pub fn master_bias(
    frames: &[PathBuf],
    inst: &Instrument,
    nsigma: f64,
    out: &Path,
) -> Result<skyfield::calib::Master, skyfield::Error> {
    let m = skyfield::calib::master_bias(frames, inst, nsigma)?;
    m.write(out, inst)?;
    Ok(m)
}

/// A master flat (`instpol master-flat`): `skyfield::calib::master_flat`, written to `out`;
/// returns the master.
pub fn master_flat(
    frames: &[PathBuf],
    inst: &Instrument,
    bias: Option<&Path>,
    nsigma: f64,
    out: &Path,
) -> Result<skyfield::calib::Master, skyfield::Error> {
    let m = skyfield::calib::master_flat(frames, inst, bias, nsigma)?;
    m.write(out, inst)?;
    Ok(m)
}

/// A sky-field calibration from a Stokes map (`instpol calibrate --map`): the map read
/// (`skyfield::StokesMap::read_uncorrected`), the sky-field fit
/// (`fit::models::pipeline::calibrate_sky_field`) and the calibration saved to `out` when given.
/// Returns the run and, when the map's recorded zero angle is not the instrument's, a warning
/// (`fit::correction::setup::zero_angle_disagreement`).
pub fn calibrate_map(
    map_path: &Path,
    sky: &skyfield::solve::SkyPolarization,
    inst: &Instrument,
    opts: &fit::models::pipeline::CalibrateOptions,
    out: Option<&Path>,
) -> Result<(fit::models::pipeline::CalibrationRun, Option<String>), fit::Error> {
    let map = skyfield::StokesMap::read_uncorrected(map_path)?;
    calibrate_read_map(&map, vec![map_path.display().to_string()], sky, inst, opts, out)
}

/// [`calibrate_map`] of a map already in memory (reduced from frames in the same run), with
/// the `inputs` its calibration records.
pub fn calibrate_read_map(
    map: &skyfield::StokesMap,
    inputs: Vec<String>,
    sky: &skyfield::solve::SkyPolarization,
    inst: &Instrument,
    opts: &fit::models::pipeline::CalibrateOptions,
    out: Option<&Path>,
) -> Result<(fit::models::pipeline::CalibrationRun, Option<String>), fit::Error> {
    let warning = fit::correction::setup::zero_angle_disagreement(map, inst);
    let run = fit::models::pipeline::calibrate_sky_field(map, sky, inst, inputs, opts)?;
    if let Some(out) = out {
        run.calibration.save(out)?;
    }
    Ok((run, warning))
}
