//! The calibration file: one multi-extension FITS per instrument and filter, readable by
//! astropy with no help (specified in `docs/calibration-file.md`).
//!
//! Layout (format version [`FORMAT_VERSION`]):
//! - primary HDU, no data; `HIERARCH IP ...` keywords: format version, instrument, filter,
//!   wavelength, HWP chi offset, model kind, centre (arcmin, and pixels when there is a pixel
//!   grid), radial coefficients (fractions, r in arcmin) with errors and full covariance, how the
//!   covariance was scaled (`ERR SCALING` = conservative / scaled / absolute, `CHI2 RED`,
//!   `ERR CHI2 FACTOR`, and `ERR CORR INFL` when inflated for correlated errors; files written
//!   before these keywords used `scaled`), RMS of the residuals, polar-angle test, valid field region, exclusions, provenance (sky values,
//!   tool version, date, number of input files);
//! - `QMAP`, `UMAP`, `QERR`, `UERR`: images of the instrumental `Q/I`, `U/I` and their errors on
//!   a regular grid (linear WCS in arcmin from the detector centre: `CRVALn` is the centre of
//!   pixel `CRPIXn = 1`, `CDELTn` the step); for an imported map these images are the model;
//! - `BINS`: binary table of the binned measurements (positions in arcmin, instrumental `q`,
//!   `u` of the exact sky-field solution with errors, `p`, `phi`, the approximate `eq:approx`
//!   solution, `MODEL_Q/U` = the radial (or map) model at the bin, `RES_Q/U` = data minus that
//!   model, which is what the residual interpolant of a RADIAL+RESIDUAL model passes through,
//!   and `USED` = 1 for bins the fit used);
//! - `INPUTS`: binary table of input file names (present when there were input files).
//!
//! Files are written to a temporary file in the destination folder and renamed, so a failed
//! write never leaves a half-written calibration. A reader refuses files of a newer format.

use crate::files::keys::{check_claimed_size, fits_err, open_versioned, save_fits_atomically, KeyReader, KeyWriter};
use crate::gridmap::GridMap;
use crate::models::bins::Bin;
use crate::models::model::{FieldModel, InstPol};
use crate::models::polar::PolarAngleTest;
use crate::models::radial::{CovarianceScaling, ErrorScaling, RadialModel};
use crate::models::region::{Exclusion, FieldRegion};
use crate::models::residual::{ResidualMap, ResidualPoint};
use crate::{Error, Result};
use fitsio::images::{ImageDescription, ImageType};
use fitsio::tables::{ColumnDataType, ColumnDescription};
use fitsio::FitsFile;
use serde::{Deserialize, Serialize};
use std::path::Path;

pub use crate::files::keys::{utc_now_iso, FORMAT_VERSION};

/// The model a calibration holds.
#[derive(Debug, Clone, PartialEq)]
pub enum Model {
    /// A radial polynomial about an optical-axis centre.
    Radial(RadialModel),
    /// A radial polynomial plus the natural-neighbour interpolant of its residuals (fields that
    /// are not radial, such as the paper's B band).
    RadialResidual { radial: RadialModel, residual: ResidualMap },
    /// A gridded map (e.g. imported from another tool), bilinearly interpolated.
    Map(GridMap),
    /// A polynomial in x, y for `q` and for `u` (a field without an optical axis: a plane, a
    /// tilt; [`crate::models::poly`]).
    Poly(crate::models::poly::PolyModel),
}

impl Model {
    /// Keyword value naming the model kind.
    pub fn kind(&self) -> &'static str {
        match self {
            Model::Radial(_) => "RADIAL",
            Model::RadialResidual { .. } => "RADIAL+RESIDUAL",
            Model::Map(_) => "MAP",
            Model::Poly(_) => "POLY",
        }
    }

    /// The radial part, if any.
    pub fn radial(&self) -> Option<&RadialModel> {
        match self {
            Model::Radial(r) | Model::RadialResidual { radial: r, .. } => Some(r),
            Model::Map(_) | Model::Poly(_) => None,
        }
    }
}

/// Where a calibration came from.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Provenance {
    /// Input files (frames, or the imported maps).
    pub inputs: Vec<String>,
    /// Sky polarization assumed by the sky-field solution (fraction, degrees), if any.
    pub sky_p: Option<f64>,
    pub sky_chi_deg: Option<f64>,
    /// "sky-field", "imported map", "simulation", ...
    pub source: String,
    pub tool_version: String,
    /// UTC, ISO 8601.
    pub date: String,
    /// What the calibration is: the instrument file's BLAKE3, the filter and its wavelength,
    /// the plate, the detector, the inputs' BLAKE3 (`skyfield::provenance::Product`, written
    /// as the product keywords every table and map carries); `None` for a file that does not
    /// say (written before products were recorded, or made without an instrument file).
    #[serde(default)]
    pub product: Option<skyfield::provenance::Product>,
}

impl Provenance {
    /// Provenance stamped with this tool's version and the current UTC date.
    pub fn now(source: &str, inputs: Vec<String>) -> Self {
        Provenance {
            inputs,
            sky_p: None,
            sky_chi_deg: None,
            source: source.into(),
            tool_version: format!("instpol {}", env!("CARGO_PKG_VERSION")),
            date: utc_now_iso(),
            product: None,
        }
    }

    /// [`Provenance::now`] of a calibration of `inst` in `filter`, with its product
    /// (`skyfield::provenance::Product::of_instrument`; the inputs' hashes are the run's).
    pub fn of_instrument(source: &str, inputs: Vec<String>, inst: &instrument::Instrument, filter: &str) -> Self {
        let product = skyfield::provenance::Product::of_instrument(inst, filter, None);
        Provenance { product: Some(product), ..Provenance::now(source, inputs) }
    }

    /// `self` recording what the calibration is (`product`).
    pub fn with_product(self, product: skyfield::provenance::Product) -> Self {
        Provenance { product: Some(product), ..self }
    }

    /// The keywords every calibration file writes of where it came from (`IP SOURCE`, `IP
    /// TOOL`, `IP DATE`) and the product keywords of what it is; the inputs are each format's.
    pub(crate) fn write_common(&self, w: &mut KeyWriter) -> Result<()> {
        w.str("SOURCE", &self.source)?;
        w.str("TOOL", &self.tool_version)?;
        w.str("DATE", &self.date)?;
        crate::files::keys::write_product(w, self.product.as_ref())
    }

    /// What [`Provenance::write_common`] wrote, read back (no inputs: each format reads its
    /// own); a product keyword that does not parse is an error naming it.
    pub(crate) fn read_common(r: &mut KeyReader) -> Result<Self> {
        Ok(Provenance {
            inputs: vec![],
            sky_p: None,
            sky_chi_deg: None,
            source: r.opt_str("SOURCE").unwrap_or_default(),
            tool_version: r.opt_str("TOOL").unwrap_or_default(),
            date: r.opt_str("DATE").unwrap_or_default(),
            product: crate::files::keys::read_product(r)?,
        })
    }
}

/// The detector pixel grid behind the field coordinates: field position `(0, 0)` arcmin is
/// 0-based pixel `origin_px`, and one pixel is `scale_arcsec`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PixelGrid {
    pub scale_arcsec: f64,
    pub origin_px: [f64; 2],
}

impl PixelGrid {
    /// The grid of a detector: field origin at its centre.
    pub fn of_instrument(inst: &instrument::Instrument) -> Self {
        let c = inst.field_coords();
        PixelGrid { scale_arcsec: c.scale_arcsec, origin_px: c.origin_px }
    }

    /// The field coordinates of this grid (unbinned pixels).
    pub fn coords(&self) -> field::FieldCoords {
        field::FieldCoords::with_origin(self.origin_px, self.scale_arcsec)
    }

    /// 0-based pixel of field position `(x, y)` arcmin.
    pub fn to_px(&self, x: f64, y: f64) -> [f64; 2] {
        let (px, py) = self.coords().arcmin_to_pixel(x, y);
        [px, py]
    }

    /// Field position (arcmin) of 0-based pixel `(x, y)`.
    pub fn to_arcmin(&self, x: f64, y: f64) -> (f64, f64) {
        self.coords().pixel_to_arcmin(x, y)
    }
}

/// Summary of the polar-angle test kept in the file.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PolarAngleSummary {
    pub slope: f64,
    pub slope_err: f64,
    pub intercept_deg: f64,
    pub intercept_err_deg: f64,
}

impl From<&PolarAngleTest> for PolarAngleSummary {
    fn from(t: &PolarAngleTest) -> Self {
        PolarAngleSummary {
            slope: t.slope,
            slope_err: t.slope_err,
            intercept_deg: t.intercept_deg,
            intercept_err_deg: t.intercept_err_deg,
        }
    }
}

/// A calibration of the instrumental polarization of one instrument in one filter.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    pub format_version: i64,
    pub instrument: String,
    pub filter: String,
    /// Effective wavelength (nm), NaN when unknown.
    pub lambda_nm: f64,
    /// HWP chromatic zero angle added to measured chi (deg), as in the instrument file.
    pub hwp_chi_offset_deg: f64,
    pub model: Model,
    /// Where the model is valid (arcmin from the detector centre).
    pub region: FieldRegion,
    /// RMS per component of the fit residuals (fraction), NaN when there was no fit.
    pub rms_residual: f64,
    pub n_bins_used: usize,
    pub polar_angle: Option<PolarAngleSummary>,
    pub exclusions: Vec<Exclusion>,
    /// Robust loss of the fit ("huber:1.345", "none", ...).
    pub robust: String,
    pub pixel: Option<PixelGrid>,
    pub provenance: Provenance,
    /// The binned measurements (the BINS table).
    pub bins: Vec<Bin>,
    /// The gridded images. For a [`Model::Map`] they are the model itself; for the other models
    /// the model evaluated on a grid, for people and other tools.
    pub grid: Option<GridMap>,
}

impl Calibration {
    /// The optical-axis centre (arcmin): the radial model's, else the detector centre.
    pub fn centre_arcmin(&self) -> [f64; 2] {
        self.model.radial().map(|r| r.centre).unwrap_or([0.0, 0.0])
    }

    /// The centre in 0-based detector pixels, when the field has a pixel grid.
    pub fn centre_px(&self) -> Option<[f64; 2]> {
        let c = self.centre_arcmin();
        self.pixel.map(|g| g.to_px(c[0], c[1]))
    }

    /// The instrumental `P` (`eq:poldeg`) at the edge of the field, the number an instrument's
    /// monitoring follows over nights (`workflow::night::trend`): the mean of the model's `P`
    /// at the midpoints of the four sides of its region, with the mean of their errors (the
    /// four share the model's parameters, so their errors are taken as fully correlated: the
    /// error of the mean is then their mean). `None` when the model is undefined at one of
    /// them (an interpolant with a hole there).
    ///
    /// A radial pattern `P(r) = c r^2` about the centre of a region of half-sides `a`, `b`
    /// gives `c (a^2 + b^2) / 2` (`crates/fit/tests/it/request.rs` checks an off-centre case).
    pub fn p_at_edge(&self) -> Option<(f64, f64)> {
        let r = &self.region;
        let (xc, yc) = (0.5 * (r.x_min + r.x_max), 0.5 * (r.y_min + r.y_max));
        let sides = [(r.x_min, yc), (r.x_max, yc), (xc, r.y_min), (xc, r.y_max)];
        let mut sum = (0.0, 0.0);
        for (x, y) in sides {
            if !self.contains(x, y) {
                return None;
            }
            let e = self.eval(x, y).p_chi_with_errors();
            if !(e.p.is_finite() && e.sigma_p.is_finite()) {
                return None;
            }
            sum = (sum.0 + e.p, sum.1 + e.sigma_p);
        }
        Some((sum.0 / 4.0, sum.1 / 4.0))
    }

    /// Evaluate the model on a regular grid of `step` arcmin over the region, for the images.
    pub fn gridded(&self, step: f64) -> GridMap {
        let r = &self.region;
        let nx = (((r.x_max - r.x_min) / step).floor() as usize + 1).max(2);
        let ny = (((r.y_max - r.y_min) / step).floor() as usize + 1).max(2);
        let mut g = GridMap {
            nx,
            ny,
            x0: r.x_min,
            y0: r.y_min,
            dx: step,
            dy: step,
            q: vec![f64::NAN; nx * ny],
            u: vec![f64::NAN; nx * ny],
            sigma_q: vec![f64::NAN; nx * ny],
            sigma_u: vec![f64::NAN; nx * ny],
        };
        for j in 0..ny {
            for i in 0..nx {
                let (x, y) = g.pixel_centre(i, j);
                if !self.contains(x, y) {
                    continue;
                }
                let v = self.eval(x, y);
                let k = j * nx + i;
                g.q[k] = v.q;
                g.u[k] = v.u;
                g.sigma_q[k] = v.var_q.sqrt();
                g.sigma_u[k] = v.var_u.sqrt();
            }
        }
        g
    }

    /// Write the calibration to `path` atomically (temporary file in the same folder, then
    /// rename). Non-map models get their images from [`Self::gridded`] when `grid` is None.
    pub fn save(&self, path: &Path) -> Result<()> {
        self.save_with(path, |_, _| Ok(()))
    }

    /// [`Self::save`], with `extra` writing further HDUs (e.g. the telescope model,
    /// [`crate::telescope::cal`]) into the same temporary file before it is renamed.
    pub fn save_with(&self, path: &Path, extra: impl FnOnce(&mut FitsFile, &Path) -> Result<()>) -> Result<()> {
        save_fits_atomically(path, |f| {
            self.write_to(f, path)?;
            extra(f, path)
        })
    }

    /// [`Self::save`] of a file whose field elements are `order`, in the order light meets
    /// them, this calibration's model among them ([`crate::files::elements::Element::Model`]);
    /// `extra` writes further HDUs as in [`Self::save_with`] (a telescope model). An empty
    /// order writes the model alone, as [`Self::save_with`] does.
    pub fn save_with_elements(
        &self,
        path: &Path,
        order: &[crate::files::elements::Element],
        extra: impl FnOnce(&mut FitsFile, &Path) -> Result<()>,
    ) -> Result<()> {
        self.save_with(path, crate::files::elements::writing_then(order, extra)?)
    }

    fn write_to(&self, f: &mut FitsFile, path: &Path) -> Result<()> {
        self.write_primary(f, path)?;
        self.write_images(f, path)?;
        self.write_bins(f, path)?;
        if !self.provenance.inputs.is_empty() {
            write_inputs(f, path, &self.provenance.inputs)?;
        }
        Ok(())
    }

    /// The primary HDU's keywords: the calibration, its model's parameters, its pixel grid
    /// and where it came from.
    fn write_primary(&self, f: &mut FitsFile, path: &Path) -> Result<()> {
        let e = |doing: &str| fits_err(path, doing);
        let hdu = f.primary_hdu().map_err(e("opening the primary HDU"))?;
        let mut w = KeyWriter { f, hdu: &hdu, path };
        w.int("FORMAT VERSION", FORMAT_VERSION)?;
        w.str("INSTRUMENT", &self.instrument)?;
        w.str("FILTER", &self.filter)?;
        w.real("LAMBDA NM", self.lambda_nm)?;
        w.real("HWP CHI OFFSET DEG", self.hwp_chi_offset_deg)?;
        w.str("MODEL", self.model.kind())?;
        w.str("UNITS", "fractions; arcmin from detector centre; degrees")?;
        w.real("RMS RESID", self.rms_residual)?;
        w.int("NBINS USED", self.n_bins_used as i64)?;
        w.str("ROBUST", &self.robust)?;
        w.real("REGION XMIN", self.region.x_min)?;
        w.real("REGION XMAX", self.region.x_max)?;
        w.real("REGION YMIN", self.region.y_min)?;
        w.real("REGION YMAX", self.region.y_max)?;
        w.int("NEXCL", self.exclusions.len() as i64)?;
        for (k, ex) in self.exclusions.iter().enumerate() {
            w.str(&format!("EXCL{}", k + 1), &ex.spec())?;
        }
        let c = self.centre_arcmin();
        w.real("CENTRE X", c[0])?;
        w.real("CENTRE Y", c[1])?;
        if let Some(r) = self.model.radial() {
            let ce = r.centre_errors();
            w.int("CENTRE FREE", r.centre_free as i64)?;
            w.real("CENTRE X ERR", ce[0])?;
            w.real("CENTRE Y ERR", ce[1])?;
            w.int("RADIAL FIRST POWER", r.first_power as i64)?;
            w.int("RADIAL DEGREE", r.degree() as i64)?;
            let errs = r.coefficient_errors();
            for (i, (cv, ev)) in r.coeffs.iter().zip(&errs).enumerate() {
                let k = r.first_power + i;
                w.real(&format!("RADIAL C{k}"), *cv)?;
                w.real(&format!("RADIAL C{k} ERR"), *ev)?;
            }
            let np = r.n_params();
            for i in 0..np {
                for j in i..np {
                    w.real(&format!("COV {i} {j}"), r.cov_at(i, j))?;
                }
            }
            if let Some(sc) = &r.scaling {
                w.str("ERR SCALING", sc.mode.name())?;
                w.real("CHI2 RED", sc.chi2_reduced)?;
                w.real("ERR CHI2 FACTOR", sc.chi2_factor)?;
                if let Some(t) = sc.correlation_inflation {
                    w.real("ERR CORR INFL", t)?;
                }
            }
        }
        if let Model::Poly(m) = &self.model {
            w.int("POLY DEGREE", m.degree as i64)?;
            let errs = m.coefficient_errors();
            let nt = m.q.len();
            for (k, (i, j)) in crate::models::poly::PolyModel::powers(m.degree).into_iter().enumerate() {
                w.real(&format!("POLY Q X{i}Y{j}"), m.q[k])?;
                w.real(&format!("POLY Q X{i}Y{j} ERR"), errs[k])?;
                w.real(&format!("POLY U X{i}Y{j}"), m.u[k])?;
                w.real(&format!("POLY U X{i}Y{j} ERR"), errs[nt + k])?;
            }
            let np = 2 * nt;
            for i in 0..np {
                for j in i..np {
                    w.real(&format!("COV {i} {j}"), m.cov[i * np + j])?;
                }
            }
            if let Some(sc) = &m.scaling {
                w.str("ERR SCALING", sc.mode.name())?;
                w.real("CHI2 RED", sc.chi2_reduced)?;
                w.real("ERR CHI2 FACTOR", sc.chi2_factor)?;
            }
        }
        if let Model::RadialResidual { residual, .. } = &self.model {
            w.real("RESID LOO RMS Q", residual.loo_rms_q)?;
            w.real("RESID LOO RMS U", residual.loo_rms_u)?;
        }
        if let Some(pa) = &self.polar_angle {
            w.real("POLANG SLOPE", pa.slope)?;
            w.real("POLANG SLOPE ERR", pa.slope_err)?;
            w.real("POLANG ICPT DEG", pa.intercept_deg)?;
            w.real("POLANG ICPT ERR", pa.intercept_err_deg)?;
        }
        if let Some(g) = &self.pixel {
            w.real("PIX SCALE ARCSEC", g.scale_arcsec)?;
            w.real("PIX ORIGIN X", g.origin_px[0])?;
            w.real("PIX ORIGIN Y", g.origin_px[1])?;
            let cp = g.to_px(c[0], c[1]);
            w.real("PIX CENTRE X", cp[0])?;
            w.real("PIX CENTRE Y", cp[1])?;
        }
        let pv = &self.provenance;
        if let Some(p) = pv.sky_p {
            w.real("SKY P", p)?;
        }
        if let Some(chi) = pv.sky_chi_deg {
            w.real("SKY CHI DEG", chi)?;
        }
        pv.write_common(&mut w)?;
        w.int("NINPUT", pv.inputs.len() as i64)?;
        Ok(())
    }

    /// The `QMAP`, `UMAP`, `QERR`, `UERR` images: the model on a grid (a map: itself).
    fn write_images(&self, f: &mut FitsFile, path: &Path) -> Result<()> {
        let e = |doing: &str| fits_err(path, doing);
        // Images.
        let grid = match (&self.model, &self.grid) {
            (Model::Map(g), _) => g.clone(),
            (_, Some(g)) => g.clone(),
            _ => self.gridded(0.1),
        };
        for (name, data, what) in [
            ("QMAP", &grid.q, "instrumental Q/I"),
            ("UMAP", &grid.u, "instrumental U/I"),
            ("QERR", &grid.sigma_q, "1-sigma error of Q/I"),
            ("UERR", &grid.sigma_u, "1-sigma error of U/I"),
        ] {
            let desc = ImageDescription { data_type: ImageType::Double, dimensions: &[grid.ny, grid.nx] };
            let h = f.create_image(name, &desc).map_err(e(&format!("creating image {name}")))?;
            h.write_image(f, data).map_err(e(&format!("writing image {name}")))?;
            let mut w = KeyWriter { f, hdu: &h, path };
            // '' = dimensionless for astropy (CCDData reads it); 'fraction' is not a unit.
            w.plain_with_comment("BUNIT", "", "dimensionless fraction")?;
            w.plain("COMMENT1", what)?;
            w.plain("CTYPE1", "X-ARCMIN")?;
            w.plain("CTYPE2", "Y-ARCMIN")?;
            w.plain("CUNIT1", "arcmin")?;
            w.plain("CUNIT2", "arcmin")?;
            w.plain_real("CRPIX1", 1.0)?;
            w.plain_real("CRPIX2", 1.0)?;
            w.plain_real("CRVAL1", grid.x0)?;
            w.plain_real("CRVAL2", grid.y0)?;
            w.plain_real("CDELT1", grid.dx)?;
            w.plain_real("CDELT2", grid.dy)?;
        }
        Ok(())
    }

    /// The `BINS` table: the binned measurements with the model and the residuals at each.
    fn write_bins(&self, f: &mut FitsFile, path: &Path) -> Result<()> {
        let e = |doing: &str| fits_err(path, doing);
        // The binned measurements.
        let model_qu: Vec<(f64, f64)> = self
            .bins
            .iter()
            .map(|b| match &self.model {
                Model::Radial(r) | Model::RadialResidual { radial: r, .. } => r.qu(b.x, b.y),
                Model::Map(g) => g.interpolate(b.x, b.y).map(|v| (v.q, v.u)).unwrap_or((f64::NAN, f64::NAN)),
                Model::Poly(m) => m.qu(b.x, b.y),
            })
            .collect();
        let dcols = [
            "X_ARCMIN",
            "Y_ARCMIN",
            "Q",
            "U",
            "SIGMA_Q",
            "SIGMA_U",
            "P",
            "PHI_DEG",
            "P_APPROX",
            "PHI_APPROX_DEG",
            "MODEL_Q",
            "MODEL_U",
            "RES_Q",
            "RES_U",
        ];
        let mut descs = vec![];
        for c in dcols {
            descs.push(
                ColumnDescription::new(c).with_type(ColumnDataType::Double).create().map_err(e("describing BINS"))?,
            );
        }
        descs.push(
            ColumnDescription::new("USED").with_type(ColumnDataType::Int).create().map_err(e("describing BINS"))?,
        );
        let h = f.create_table("BINS", &descs).map_err(e("creating table BINS"))?;
        let col = |g: &dyn Fn(usize) -> f64| (0..self.bins.len()).map(g).collect::<Vec<f64>>();
        let b = &self.bins;
        let columns: Vec<(&str, Vec<f64>)> = vec![
            ("X_ARCMIN", col(&|i| b[i].x)),
            ("Y_ARCMIN", col(&|i| b[i].y)),
            ("Q", col(&|i| b[i].qu.q)),
            ("U", col(&|i| b[i].qu.u)),
            ("SIGMA_Q", col(&|i| b[i].sigma_q())),
            ("SIGMA_U", col(&|i| b[i].sigma_u())),
            ("P", col(&|i| b[i].p_phi().0)),
            ("PHI_DEG", col(&|i| b[i].p_phi().1.to_degrees())),
            ("P_APPROX", col(&|i| b[i].p_approx)),
            ("PHI_APPROX_DEG", col(&|i| b[i].phi_approx.to_degrees())),
            ("MODEL_Q", col(&|i| model_qu[i].0)),
            ("MODEL_U", col(&|i| model_qu[i].1)),
            ("RES_Q", col(&|i| b[i].qu.q - model_qu[i].0)),
            ("RES_U", col(&|i| b[i].qu.u - model_qu[i].1)),
        ];
        // Units (FITS/astropy strings) of the columns that have one; q, u, p are dimensionless.
        for (k, c) in dcols.iter().enumerate() {
            let unit = match *c {
                "X_ARCMIN" | "Y_ARCMIN" => "arcmin",
                "PHI_DEG" | "PHI_APPROX_DEG" => "deg",
                _ => continue,
            };
            h.write_key(f, &format!("TUNIT{}", k + 1), unit).map_err(e("writing BINS units"))?;
        }
        if !b.is_empty() {
            for (name, v) in &columns {
                h.write_col(f, *name, v).map_err(e(&format!("writing column {name}")))?;
            }
            let used: Vec<i32> = b.iter().map(|x| x.used as i32).collect();
            h.write_col(f, "USED", &used).map_err(e("writing column USED"))?;
        }
        Ok(())
    }

    /// Read a calibration file. Files of a newer format version are refused with an error
    /// that says so; missing keywords are named.
    pub fn load(path: &Path) -> Result<Self> {
        let e = |doing: &str| fits_err(path, doing);
        let mut f = open_versioned(path)?;
        let hdu = f.primary_hdu().map_err(e("reading the primary HDU"))?;
        let mut r = KeyReader { f: &mut f, hdu: &hdu, path };
        let version = r.int("FORMAT VERSION")?;
        refuse_other_kind(path, r.opt_str("MODEL").as_deref())?;
        let instrument = r.str("INSTRUMENT")?;
        let filter = r.str("FILTER")?;
        let lambda_nm = r.opt_real("LAMBDA NM").unwrap_or(f64::NAN);
        let hwp_chi_offset_deg = r.opt_real("HWP CHI OFFSET DEG").unwrap_or(0.0);
        let kind = r.str("MODEL")?;
        let rms_residual = r.opt_real("RMS RESID").unwrap_or(f64::NAN);
        let n_bins_used = r.opt_int("NBINS USED").unwrap_or(0).max(0) as usize;
        let robust = r.opt_str("ROBUST").unwrap_or_default();
        let region = FieldRegion {
            x_min: r.real("REGION XMIN")?,
            x_max: r.real("REGION XMAX")?,
            y_min: r.real("REGION YMIN")?,
            y_max: r.real("REGION YMAX")?,
        };
        let nexcl = r.opt_int("NEXCL").unwrap_or(0);
        let mut exclusions = vec![];
        for k in 1..=nexcl {
            let s = r.str(&format!("EXCL{k}"))?;
            exclusions.push(s.parse::<Exclusion>().map_err(|err| Error::BadFile {
                path: path.into(),
                what: format!("keyword HIERARCH IP EXCL{k}: {err}"),
            })?);
        }
        let radial = if kind == "RADIAL" || kind == "RADIAL+RESIDUAL" {
            let first_power = r.int("RADIAL FIRST POWER")?;
            let degree = r.int("RADIAL DEGREE")?;
            if !(0..=1).contains(&first_power) || degree < first_power || degree > 20 {
                return Err(Error::BadFile {
                    path: path.into(),
                    what: format!("radial powers {first_power}..{degree} are not valid"),
                });
            }
            let coeffs =
                (first_power..=degree).map(|k| r.real(&format!("RADIAL C{k}"))).collect::<Result<Vec<f64>>>()?;
            let cov = read_covariance(&mut r, coeffs.len() + 2, path)?;
            let scaling = read_scaling(&mut r, path)?;
            Some(RadialModel {
                first_power: first_power as usize,
                coeffs,
                centre: [r.real("CENTRE X")?, r.real("CENTRE Y")?],
                centre_free: r.opt_int("CENTRE FREE").unwrap_or(0) != 0,
                cov,
                scaling,
            })
        } else if kind == "MAP" || kind == "POLY" {
            None
        } else {
            return Err(Error::BadFile { path: path.into(), what: format!("unknown model kind MODEL = '{kind}'") });
        };
        let poly = if kind == "POLY" { Some(read_poly(&mut r, path)?) } else { None };
        let polar_angle = r.opt_real("POLANG SLOPE").map(|slope| PolarAngleSummary {
            slope,
            slope_err: r.opt_real("POLANG SLOPE ERR").unwrap_or(f64::NAN),
            intercept_deg: r.opt_real("POLANG ICPT DEG").unwrap_or(f64::NAN),
            intercept_err_deg: r.opt_real("POLANG ICPT ERR").unwrap_or(f64::NAN),
        });
        let pixel = r.opt_real("PIX SCALE ARCSEC").map(|scale_arcsec| PixelGrid {
            scale_arcsec,
            origin_px: [r.opt_real("PIX ORIGIN X").unwrap_or(0.0), r.opt_real("PIX ORIGIN Y").unwrap_or(0.0)],
        });
        let mut provenance = Provenance {
            sky_p: r.opt_real("SKY P"),
            sky_chi_deg: r.opt_real("SKY CHI DEG"),
            ..Provenance::read_common(&mut r)?
        };
        let ninput = r.opt_int("NINPUT").unwrap_or(0);

        let grid = read_grid(&mut f, path)?;
        let bins = read_bins(&mut f, path)?;
        if ninput > 0 {
            provenance.inputs = read_inputs(&mut f, path, ninput as usize)?;
        }

        let model = match (kind.as_str(), radial, poly) {
            (_, _, Some(p)) => Model::Poly(p),
            ("RADIAL", Some(r), _) => Model::Radial(r),
            ("RADIAL+RESIDUAL", Some(r), _) => {
                let residual = residual_from_bins(&r, &bins)?;
                Model::RadialResidual { radial: r, residual }
            }
            _ => Model::Map(grid.clone()),
        };
        Ok(Calibration {
            format_version: version,
            instrument,
            filter,
            lambda_nm,
            hwp_chi_offset_deg,
            model,
            region,
            rms_residual,
            n_bins_used,
            polar_angle,
            exclusions,
            robust,
            pixel,
            provenance,
            bins,
            grid: Some(grid),
        })
    }
}

/// The `QMAP`, `UMAP`, `QERR`, `UERR` images as a grid: each 2-D, of a plausible size, the
/// grid from `QMAP`'s `CRVAL`, `CDELT` and `CRPIX`.
fn read_grid(f: &mut FitsFile, path: &Path) -> Result<GridMap> {
    let e = |doing: &str| fits_err(path, doing);
    let mut planes = vec![];
    let (mut nx, mut ny, mut x0, mut y0, mut dx, mut dy) = (0, 0, 0.0, 0.0, 1.0, 1.0);
    for name in ["QMAP", "UMAP", "QERR", "UERR"] {
        let h = f.hdu(name).map_err(e(&format!("finding image extension {name}")))?;
        if let fitsio::hdu::HduInfo::ImageInfo { shape, .. } = &h.info {
            if shape.len() != 2 {
                return Err(Error::BadFile { path: path.into(), what: format!("{name} is not a 2-D image") });
            }
            ny = shape[0];
            nx = shape[1];
        } else {
            return Err(Error::BadFile { path: path.into(), what: format!("{name} is not an image") });
        }
        check_claimed_size(path, name, &[ny, nx])?;
        let data: Vec<f64> = h.read_image(f).map_err(e(&format!("reading image {name}")))?;
        if name == "QMAP" {
            let mut r = KeyReader { f, hdu: &h, path };
            x0 = r.plain_real("CRVAL1")?;
            y0 = r.plain_real("CRVAL2")?;
            dx = r.plain_real("CDELT1")?;
            dy = r.plain_real("CDELT2")?;
            let (p1, p2) = (r.plain_real("CRPIX1")?, r.plain_real("CRPIX2")?);
            x0 -= (p1 - 1.0) * dx;
            y0 -= (p2 - 1.0) * dy;
        }
        planes.push(data);
    }
    Ok(GridMap {
        nx,
        ny,
        x0,
        y0,
        dx,
        dy,
        sigma_u: planes.pop().unwrap_or_default(),
        sigma_q: planes.pop().unwrap_or_default(),
        u: planes.pop().unwrap_or_default(),
        q: planes.pop().unwrap_or_default(),
    })
}

/// The `BINS` table's rows, refused by row when an error is negative or `P` above 1.
fn read_bins(f: &mut FitsFile, path: &Path) -> Result<Vec<Bin>> {
    let e = |doing: &str| fits_err(path, doing);
    let h = f.hdu("BINS").map_err(e("finding table BINS"))?;
    let nrows = match &h.info {
        fitsio::hdu::HduInfo::TableInfo { num_rows, .. } => *num_rows,
        _ => return Err(Error::BadFile { path: path.into(), what: "BINS is not a table".into() }),
    };
    let mut bins = vec![];
    if nrows > 0 {
        let mut get =
            |c: &str| -> Result<Vec<f64>> { h.read_col::<f64>(f, c).map_err(e(&format!("reading BINS column {c}"))) };
        let (x, y, q, u, sq, su, pa, pha) = (
            get("X_ARCMIN")?,
            get("Y_ARCMIN")?,
            get("Q")?,
            get("U")?,
            get("SIGMA_Q")?,
            get("SIGMA_U")?,
            get("P_APPROX")?,
            get("PHI_APPROX_DEG")?,
        );
        let used: Vec<i32> = h.read_col(f, "USED").map_err(e("reading BINS column USED"))?;
        for i in 0..nrows {
            bins.push(Bin {
                p_approx: pa[i],
                phi_approx: pha[i].to_radians(),
                used: used[i] != 0,
                ..Bin::new(x[i], y[i], q[i], u[i], sq[i], su[i])
            });
        }
        if let Some((i, b)) = bins.iter().enumerate().find(|(_, b)| {
            b.qu.var_q < 0.0
                || b.qu.var_u < 0.0
                || (b.qu.q.is_finite() && b.qu.u.is_finite() && b.qu.q.hypot(b.qu.u) > 1.0)
        }) {
            return Err(Error::BadFile {
                path: path.into(),
                what: format!(
                    "BINS row {}: Q, U = {}, {} with errors {}, {}: errors must be >= 0 and P = hypot(Q, U) at most 1",
                    i + 1,
                    b.qu.q,
                    b.qu.u,
                    sq[i],
                    su[i]
                ),
            });
        }
    }
    Ok(bins)
}

/// The `INPUTS` table's `n` names (from `FILE_BYTES`).
fn read_inputs(f: &mut FitsFile, path: &Path, n: usize) -> Result<Vec<String>> {
    let e = |doing: &str| fits_err(path, doing);
    let h = f.hdu("INPUTS").map_err(e("finding table INPUTS"))?;
    let bytes: Vec<u8> = h.read_col(f, "FILE_BYTES").map_err(e("reading INPUTS column FILE_BYTES"))?;
    if n == 0 || bytes.is_empty() || !bytes.len().is_multiple_of(n) {
        return Err(Error::BadFile {
            path: path.into(),
            what: format!("INPUTS holds {} bytes, not a whole number of {n} names", bytes.len()),
        });
    }
    let width = bytes.len() / n;
    Ok(bytes
        .chunks(width)
        .map(|c| String::from_utf8_lossy(&c[..c.iter().position(|&b| b == 0).unwrap_or(c.len())]).into_owned())
        .collect())
}

/// The residual interpolant of a radial model: the residuals `q - q_model`, `u - u_model` of
/// the used bins, interpolated by natural neighbours.
pub fn residual_from_bins(radial: &RadialModel, bins: &[Bin]) -> Result<ResidualMap> {
    let pts = bins
        .iter()
        .filter(|b| b.used && b.is_valid())
        .map(|b| {
            let (q, u) = radial.qu(b.x, b.y);
            ResidualPoint { x: b.x, y: b.y, dq: b.qu.q - q, du: b.qu.u - u }
        })
        .collect();
    ResidualMap::new(pts)
}

/// The covariance `COV i j` (upper triangle) of a model's `np` parameters, checked: a negative
/// variance or a correlation beyond 1 would give imaginary or understated errors downstream,
/// and is refused by name.
fn read_covariance(r: &mut KeyReader, np: usize, path: &Path) -> Result<Vec<f64>> {
    let mut cov = vec![0.0; np * np];
    for i in 0..np {
        for j in i..np {
            let v = r.opt_real(&format!("COV {i} {j}")).unwrap_or(0.0);
            cov[i * np + j] = v;
            cov[j * np + i] = v;
        }
    }
    for i in 0..np {
        let cii = cov[i * np + i];
        if !(cii.is_finite() && cii >= 0.0) {
            return Err(Error::BadFile {
                path: path.into(),
                what: format!("keyword HIERARCH IP COV {i} {i} = {cii} is not a variance (finite, >= 0)"),
            });
        }
        for j in 0..i {
            let c = cov[i * np + j];
            if !(c.is_finite() && c * c <= cii * cov[j * np + j] * (1.0 + 1e-9)) {
                return Err(Error::BadFile {
                    path: path.into(),
                    what: format!(
                        "keyword HIERARCH IP COV {j} {i} = {c} is not a covariance of variances {} and {cii} (|correlation| > 1)",
                        cov[j * np + j]
                    ),
                });
            }
        }
    }
    Ok(cov)
}

/// How a model's covariance was scaled (`ERR SCALING`, `CHI2 RED`, ...). Absent from files
/// written before the choice existed (their covariance was scaled by chi2_red): None, not a
/// guess.
fn read_scaling(r: &mut KeyReader, path: &Path) -> Result<Option<CovarianceScaling>> {
    Ok(match r.opt_str("ERR SCALING") {
        None => None,
        Some(name) => {
            let mode = name.parse::<ErrorScaling>().map_err(|err| Error::BadFile {
                path: path.into(),
                what: format!("keyword HIERARCH IP ERR SCALING: {err}"),
            })?;
            let chi2_reduced = r.opt_real("CHI2 RED").unwrap_or(f64::NAN);
            Some(CovarianceScaling {
                mode,
                chi2_reduced,
                chi2_factor: r.opt_real("ERR CHI2 FACTOR").unwrap_or_else(|| mode.factor(chi2_reduced)),
                correlation_inflation: r.opt_real("ERR CORR INFL"),
            })
        }
    })
}

/// A polynomial field's degree and coefficients (`POLY DEGREE`, `POLY Q X{i}Y{j}`, ...).
fn read_poly(r: &mut KeyReader, path: &Path) -> Result<crate::models::poly::PolyModel> {
    use crate::models::poly::{PolyModel, MAX_DEGREE};
    let degree = r.int("POLY DEGREE")?;
    if !(1..=MAX_DEGREE as i64).contains(&degree) {
        return Err(Error::BadFile {
            path: path.into(),
            what: format!("keyword HIERARCH IP POLY DEGREE = {degree}: expected 1 to {MAX_DEGREE}"),
        });
    }
    let degree = degree as usize;
    let (mut q, mut u) = (vec![], vec![]);
    for (i, j) in PolyModel::powers(degree) {
        q.push(r.real(&format!("POLY Q X{i}Y{j}"))?);
        u.push(r.real(&format!("POLY U X{i}Y{j}"))?);
    }
    let cov = read_covariance(r, 2 * q.len(), path)?;
    Ok(PolyModel { degree, q, u, cov, scaling: read_scaling(r, path)? })
}

impl FieldModel for Calibration {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        match &self.model {
            Model::Radial(r) => r.eval(x, y),
            Model::RadialResidual { radial, residual } => {
                let mut v = radial.eval(x, y);
                if let Some((dq, du)) = residual.eval(x, y) {
                    v.q += dq;
                    v.u += du;
                    v.var_q += residual.loo_rms_q.powi(2);
                    v.var_u += residual.loo_rms_u.powi(2);
                }
                v
            }
            Model::Map(g) => g.eval(x, y),
            Model::Poly(m) => m.eval(x, y),
        }
    }

    fn contains(&self, x: f64, y: f64) -> bool {
        self.region.contains(x, y)
            && match &self.model {
                Model::Radial(_) | Model::Poly(_) => true,
                Model::RadialResidual { residual, .. } => residual.eval(x, y).is_some(),
                Model::Map(g) => g.contains(x, y),
            }
    }

    fn describe(&self) -> String {
        format!("calibration of {} {}, model {}", self.instrument, self.filter, self.model.kind())
    }
}

/// A file of another kind than a field model, refused by name (`model`: its `MODEL`): a
/// telescope model alone, a Mueller field, a constant response.
fn refuse_other_kind(path: &Path, model: Option<&str>) -> Result<()> {
    let what = match model {
        Some(crate::files::keys::TELESCOPE_MODEL) => "holds only a telescope model (instpol fit-standards), no field model",
        Some(crate::files::keys::MUELLER_MODEL) => "holds a Mueller field (instpol calibrate-mueller), not a partial polarizer p, phi",
        Some(crate::response::cal::RESPONSE_MODEL) => {
            "holds an instrument's constant response from standards (instpol efficiency), not a partial polarizer p, phi"
        }
        _ => return Ok(()),
    };
    Err(Error::BadFile { path: path.into(), what: format!("{what}: read it with fit::files::calibration::load") })
}

/// The `INPUTS` table of the input file names.
fn write_inputs(f: &mut FitsFile, path: &Path, inputs: &[String]) -> Result<()> {
    let e = |doing: &str| fits_err(path, doing);
    // FILE (text, for people and astropy) and FILE_BYTES (the same names as bytes,
    // zero-padded): the reader uses the bytes, because fitsio 0.21's string-column
    // reader writes one byte past its buffer.
    let width = inputs.iter().map(|s| s.len()).max().unwrap_or(1).max(1);
    let d = ColumnDescription::new("FILE")
        .with_type(ColumnDataType::String)
        .that_repeats(width)
        .create()
        .map_err(e("describing INPUTS"))?;
    let db = ColumnDescription::new("FILE_BYTES")
        .with_type(ColumnDataType::Byte)
        .that_repeats(width)
        .create()
        .map_err(e("describing INPUTS"))?;
    let h = f.create_table("INPUTS", &[d, db]).map_err(e("creating table INPUTS"))?;
    h.write_col(f, "FILE", inputs).map_err(e("writing INPUTS"))?;
    let mut bytes = vec![0u8; width * inputs.len()];
    for (k, name) in inputs.iter().enumerate() {
        bytes[k * width..k * width + name.len()].copy_from_slice(name.as_bytes());
    }
    h.write_col(f, "FILE_BYTES", &bytes).map_err(e("writing INPUTS"))?;
    Ok(())
}
