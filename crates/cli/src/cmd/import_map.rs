//! `instpol import-map`: third-party Q/I, U/I maps to a calibration file.

use anyhow::{bail, Result};
use fit::files::import::{import_map, ImportOptions};
use serde::Serialize;
use std::path::PathBuf;
use stokes::stats::robust::{median, Middle};

/// Turn instrumental Q/I and U/I maps made elsewhere into a calibration file of this tool whose
/// model is the map itself (bilinearly interpolated), so that fitting (`instpol fit`),
/// plotting and correcting treat both alike.
///
/// Each input is a FITS cube of shape (2, NY, NX) (numpy order): plane 1 the value (fraction),
/// plane 2 its 1-sigma error, NaN where unmapped. Map pixel (i, j) covers detector pixels
/// [BIN i, BIN i + BIN) in x and likewise in y.
///
/// Example (the public FORS2 maps, 0.25"/px binned detector, 10 x 10 px per map pixel):
/// instpol import-map --q v_HIGH_inlaQ_bin10.fits --u v_HIGH_inlaU_bin10.fits
/// --pixel-scale 0.25 --bin 10 --filter v_HIGH --instrument FORS2 --out fors2_v.fits
#[derive(clap::Args)]
pub struct Args {
    /// Q/I map cube.
    #[arg(long)]
    pub q: PathBuf,
    /// U/I map cube.
    #[arg(long)]
    pub u: PathBuf,
    /// Detector pixel scale, arcsec per (on-chip binned) pixel.
    #[arg(long)]
    pub pixel_scale: f64,
    /// Detector pixels per map pixel along each axis.
    #[arg(long)]
    pub bin: usize,
    /// Filter name.
    #[arg(long)]
    pub filter: String,
    /// Instrument name, or a built-in instrument / TOML file (then the filter's wavelength is
    /// taken from it).
    #[arg(long, default_value = "unknown")]
    pub instrument: String,
    /// Effective wavelength of the filter in nm (for the wavelength law).
    #[arg(long)]
    pub lambda_nm: Option<f64>,
    /// The HWP zero angle (deg, the angle added to a measured chi) of the frame the maps are
    /// in, recorded in the calibration; default the instrument file's for the filter (the
    /// frame `instpol catalog` writes that instrument's catalogs in), else 0 (the plate's).
    #[arg(long, value_name = "DEG")]
    pub zero_angle: Option<f64>,
    /// Detector pixel (0-based) taken as the field origin, "X,Y"; default the centre of the
    /// area the map covers.
    #[arg(long, value_delimiter = ',', num_args = 2)]
    pub origin_px: Option<Vec<f64>>,
    /// Output calibration file (FITS).
    #[arg(long)]
    pub out: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Summary {
    filter: String,
    instrument: String,
    hwp_chi_offset_deg: f64,
    n_pixels: usize,
    region_arcmin: [f64; 4],
    origin_px: [f64; 2],
    #[serde(rename = "max_p")]
    p_max: f64,
    #[serde(rename = "median_p")]
    p_median: f64,
    #[serde(rename = "output")]
    calibration_file: String,
    /// What the calibration is, as its file records it.
    #[serde(skip_serializing_if = "Option::is_none")]
    product: Option<skyfield::provenance::Product>,
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs([a.q.as_path(), a.u.as_path()].into_iter().chain(crate::util::file_arg(&a.instrument)))?;
    crate::util::check_output(&a.out)?;
    let inst = instrument::Instrument::load(&a.instrument).ok();
    let origin = match &a.origin_px {
        Some(v) if v.len() == 2 => Some([v[0], v[1]]),
        Some(_) => bail!("--origin-px takes two numbers: X,Y"),
        None => None,
    };
    let opts = ImportOptions {
        origin_px: origin,
        ..ImportOptions::for_instrument(
            inst.as_ref(),
            &a.instrument,
            &a.filter,
            (a.pixel_scale, a.bin),
            a.lambda_nm,
            a.zero_angle,
        )
    };
    let cal = import_map(&a.q, &a.u, &opts)?;
    cal.save(&a.out)?;
    let mut p: Vec<f64> = cal.bins.iter().map(|b| b.p_phi().0).collect();
    let p_max = p.iter().copied().max_by(f64::total_cmp).unwrap_or(f64::NAN);
    let r = cal.region;
    let s = Summary {
        filter: cal.filter.clone(),
        instrument: cal.instrument.clone(),
        hwp_chi_offset_deg: cal.hwp_chi_offset_deg,
        n_pixels: cal.bins.len(),
        region_arcmin: [r.x_min, r.x_max, r.y_min, r.y_max],
        origin_px: cal.pixel.map(|g| g.origin_px).unwrap_or([0.0, 0.0]),
        p_max,
        // The upper middle of an even count (NaN for none), as the summary always took it.
        p_median: median(&mut p, Middle::Upper),
        calibration_file: a.out.display().to_string(),
        product: cal.provenance.product.as_ref().map(|p| p.with_run_inputs()),
    };
    if a.json {
        crate::util::print_json(&s)
    } else {
        outln!(
            "{} {}: {} mapped pixels over x {:.2}..{:.2}, y {:.2}..{:.2} arcmin (origin at pixel {:.1}, {:.1})",
            s.instrument,
            s.filter,
            s.n_pixels,
            r.x_min,
            r.x_max,
            r.y_min,
            r.y_max,
            s.origin_px[0],
            s.origin_px[1]
        );
        outln!("p: median {:.3}%, max {:.3}%", 100.0 * s.p_median, 100.0 * s.p_max);
        outln!(
            "HWP zero angle recorded: {:+.2} deg (the frame of the maps' Q/I, U/I; --zero-angle to state another)",
            s.hwp_chi_offset_deg
        );
        outln!(
            "wrote {} (model MAP; refit with: instpol fit {} --free-centre)",
            s.calibration_file,
            s.calibration_file
        );
        Ok(())
    }
}
