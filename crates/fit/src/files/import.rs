//! Import of instrumental-polarization maps made by other tools: a pair of FITS cubes of
//! `Q/I` and `U/I` (plane 1 value, plane 2 its 1-sigma error, NaN outside the mapped area), each
//! map pixel covering `bin x bin` detector pixels, as the public FORS2 maps of
//! Gonzalez-Gaitan et al. (2020). The result is a calibration whose model is the map itself.

use crate::files::calfile::{Calibration, Model, PixelGrid, Provenance, FORMAT_VERSION};
use crate::gridmap::GridMap;
use crate::models::bins::Bin;
use crate::models::region::FieldRegion;
use crate::{Error, Result};
use fitsio::FitsFile;
use std::path::Path;

/// How the map lies on the detector.
#[derive(Debug, Clone, PartialEq)]
pub struct ImportOptions {
    /// Detector pixel scale (arcsec per detector pixel, as binned on chip).
    pub pixel_scale_arcsec: f64,
    /// Detector pixels per map pixel along each axis.
    pub bin: usize,
    pub instrument: String,
    pub filter: String,
    pub lambda_nm: f64,
    /// 0-based detector pixel taken as the field origin (0, 0) arcmin; default the centre of
    /// the area the map covers.
    pub origin_px: Option<[f64; 2]>,
    /// The HWP zero angle (deg, added to a measured chi) of the frame the maps' `Q/I`, `U/I`
    /// are in, recorded as the calibration's own: a correction turns rows from their frame
    /// into this one ([`mueller::Frame::turn_to`]). [`ImportOptions::for_instrument`] takes
    /// the instrument file's for the filter, the frame its catalogs are written in.
    pub hwp_chi_offset_deg: f64,
}

impl ImportOptions {
    /// The options for maps of `filter` on `inst` (a loaded instrument file, or `None` with
    /// `instrument` naming an instrument this tool has no file for), of `bin` detector pixels
    /// of `pixel_scale_arcsec` per map pixel, the origin at the map's centre: the wavelength and the HWP
    /// zero angle are the given ones, else the instrument file's for the filter, else NaN (no
    /// wavelength law) and 0 (the plate's frame). Taking the file's zero angle puts the maps in
    /// the frame `instpol catalog` writes the same instrument's catalogs in; recording 0 there
    /// turned every corrected chi by the whole zero angle.
    pub fn for_instrument(
        inst: Option<&instrument::Instrument>,
        instrument: &str,
        filter: &str,
        (pixel_scale_arcsec, bin): (f64, usize),
        lambda_nm: Option<f64>,
        zero_angle_deg: Option<f64>,
    ) -> Self {
        let f = inst.and_then(|i| i.filter(filter).ok());
        Self {
            pixel_scale_arcsec,
            bin,
            instrument: inst.map_or_else(|| instrument.to_string(), |i| i.name.clone()),
            filter: filter.to_string(),
            lambda_nm: lambda_nm.or(f.map(|f| f.lambda_eff_nm)).unwrap_or(f64::NAN),
            origin_px: None,
            hwp_chi_offset_deg: zero_angle_deg.or(f.and_then(|f| f.hwp_chi_offset_deg)).unwrap_or(0.0),
        }
    }
}

/// A `(2, ny, nx)` cube: value plane and error plane, row-major.
struct Cube {
    nx: usize,
    ny: usize,
    value: Vec<f64>,
    error: Vec<f64>,
}

fn read_cube(path: &Path, what: &str) -> Result<Cube> {
    let e = |doing: &str, m: String| Error::Fits { path: path.into(), doing: doing.into(), message: m };
    if !path.is_file() {
        return Err(Error::Io {
            path: path.into(),
            err: std::io::Error::new(std::io::ErrorKind::NotFound, format!("no such {what} map")),
        });
    }
    let mut f = FitsFile::open(path).map_err(|x| e("opening", x.to_string()))?;
    let hdu = f.primary_hdu().map_err(|x| e("reading the primary HDU", x.to_string()))?;
    let shape = match &hdu.info {
        fitsio::hdu::HduInfo::ImageInfo { shape, .. } => shape.clone(),
        _ => return Err(Error::BadFile { path: path.into(), what: "primary HDU is not an image".into() }),
    };
    if shape.len() != 3 || shape[0] != 2 {
        return Err(Error::BadFile {
            path: path.into(),
            what: format!(
                "{what} map has shape {shape:?} (numpy order); expected (2, NY, NX): plane 1 the value, plane 2 its error"
            ),
        });
    }
    crate::files::keys::check_claimed_size(path, &format!("the {what} map"), &shape)?;
    let data: Vec<f64> = hdu.read_image(&mut f).map_err(|x| e("reading the image", x.to_string()))?;
    let (ny, nx) = (shape[1], shape[2]);
    let n = nx * ny;
    Ok(Cube { nx, ny, value: data[..n].to_vec(), error: data[n..2 * n].to_vec() })
}

/// Read the `Q/I` and `U/I` cubes into a calibration holding the map as its model; every
/// measured map pixel becomes a bin (so the map can be refitted with a radial model).
pub fn import_map(q_path: &Path, u_path: &Path, opts: &ImportOptions) -> Result<Calibration> {
    if !(opts.pixel_scale_arcsec.is_finite() && opts.pixel_scale_arcsec > 0.0) {
        return Err(Error::Input(format!("pixel scale {} arcsec is not positive", opts.pixel_scale_arcsec)));
    }
    if opts.bin == 0 {
        return Err(Error::Input("--bin must be at least 1 detector pixel per map pixel".into()));
    }
    let q = read_cube(q_path, "Q")?;
    let u = read_cube(u_path, "U")?;
    if (q.nx, q.ny) != (u.nx, u.ny) {
        return Err(Error::Input(format!(
            "the Q map {} is {} x {} but the U map {} is {} x {}",
            q_path.display(),
            q.nx,
            q.ny,
            u_path.display(),
            u.nx,
            u.ny
        )));
    }
    let b = opts.bin as f64;
    // Map pixel (i, j) covers detector pixels [b i, b i + b): its centre is at b i + (b - 1)/2.
    let origin = opts.origin_px.unwrap_or([0.5 * (q.nx as f64 * b - 1.0), 0.5 * (q.ny as f64 * b - 1.0)]);
    let coords = field::FieldCoords::with_origin(origin, opts.pixel_scale_arcsec);
    let n = q.nx * q.ny;
    let mut grid = GridMap::on_pixels(&coords.binned(opts.bin), q.nx, q.ny, q.value, u.value, q.error, u.error);
    // A pixel counts as measured only when Q, U and both errors are.
    for k in 0..n {
        let ok = grid.q[k].is_finite()
            && grid.u[k].is_finite()
            && grid.sigma_q[k].is_finite()
            && grid.sigma_u[k].is_finite();
        if !ok {
            grid.q[k] = f64::NAN;
            grid.u[k] = f64::NAN;
        }
    }
    // Physically impossible values are refused, naming the file and the map pixel: an error
    // cannot be negative, and a polarization degree cannot exceed 1 (these maps are fractions).
    for j in 0..grid.ny {
        for i in 0..grid.nx {
            let k = j * grid.nx + i;
            if !grid.q[k].is_finite() {
                continue;
            }
            for (path, name, s) in [(q_path, "Q", grid.sigma_q[k]), (u_path, "U", grid.sigma_u[k])] {
                if s < 0.0 {
                    return Err(Error::Input(format!(
                        "{}: the {name} error map (plane 2) is {s} at map pixel ({i}, {j}): an error cannot be negative",
                        path.display()
                    )));
                }
            }
            let p = grid.q[k].hypot(grid.u[k]);
            if p > 1.0 {
                return Err(Error::Input(format!(
                    "{} and {}: at map pixel ({i}, {j}) Q/I = {}, U/I = {} give P = {p}, above 1: are the maps in \
                     percent? (they must be fractions)",
                    q_path.display(),
                    u_path.display(),
                    grid.q[k],
                    grid.u[k]
                )));
            }
        }
    }
    let mut bins = vec![];
    for j in 0..grid.ny {
        for i in 0..grid.nx {
            if grid.is_finite_at(i, j) {
                let k = j * grid.nx + i;
                let (x, y) = grid.pixel_centre(i, j);
                bins.push(Bin::new(x, y, grid.q[k], grid.u[k], grid.sigma_q[k], grid.sigma_u[k]));
            }
        }
    }
    if bins.is_empty() {
        return Err(Error::Input(format!(
            "the maps {} and {} have no finite pixel",
            q_path.display(),
            u_path.display()
        )));
    }
    let region = FieldRegion::bounding(bins.iter().map(|b| (b.x, b.y)), 0.5 * grid.dx)
        .ok_or_else(|| Error::Input("no finite pixel positions".into()))?;
    let n_used = bins.len();
    Ok(Calibration {
        format_version: FORMAT_VERSION,
        instrument: opts.instrument.clone(),
        filter: opts.filter.clone(),
        lambda_nm: opts.lambda_nm,
        hwp_chi_offset_deg: opts.hwp_chi_offset_deg,
        model: Model::Map(grid.clone()),
        region,
        rms_residual: f64::NAN,
        n_bins_used: n_used,
        polar_angle: None,
        exclusions: vec![],
        robust: String::new(),
        pixel: Some(PixelGrid { scale_arcsec: opts.pixel_scale_arcsec, origin_px: origin }),
        // What the maps say they are: the instrument and filter given (the detector and the
        // plate are not known from a pair of maps, and are not claimed).
        provenance: Provenance::now("imported map", vec![q_path.display().to_string(), u_path.display().to_string()])
            .with_product(skyfield::provenance::Product {
                instrument: Some(opts.instrument.clone()),
                filter: Some(opts.filter.clone()),
                wavelength_um: Some(opts.lambda_nm / 1000.0).filter(|w| w.is_finite()),
                ..Default::default()
            }),
        bins,
        grid: Some(grid),
    })
}
