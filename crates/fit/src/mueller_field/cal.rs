//! The Mueller field in a calibration file, and the exact correction of
//! polarized targets with it.
//!
//! # File layout
//!
//! The specification is `docs/calibration-file.md` ("Mueller-field calibrations"). In short:
//! the primary HDU says `HIERARCH IP MODEL = 'MUELLER'` (with the format version, instrument,
//! filter, valid region, the field coordinates' pixel grid and the provenance); the binary
//! table `MUELLER` holds one row per coefficient (`PARAM`: index of the parameter in the
//! model's full vector; `PX`, `PY`: powers of `x / scale`, `y / scale`; `COEFF`, `SIGMA`) and
//! in its header the model as vocabulary words (`MU MODEL`, `MU FREE`), the degree, scale,
//! fit statistics, box and the sky fields used; the image `MUELLER_COV` is the coefficients'
//! covariance; the optional table `MUELLER_BINS` is the per-bin fit. [`crate::files::calfile::Calibration::load`]
//! refuses such a file by name (it is not a partial polarizer), so every consumer of today's
//! calibrations keeps reading exactly what it read before.
//!
//! # The correction
//!
//! [`MuellerCal::correct`] inverts the fitted linear block exactly at the target's position
//! ([`MuellerField::correct`], the one inverse [`mueller::linear::LinearBlock::invert`]),
//! propagating the measurement's covariance and the model's coefficient covariance through
//! the inversion's Jacobian. The frame is the sky frame, as for a `p, phi` calibration
//! (`crate::correction::correct` module docs): `instpol calibrate-mueller` turns each map by the HWP zero
//! angle it records (`HWPZERO`, [`skyfield::StokesMap::hwp_zero_angle_deg`]) before the fit,
//! and the file's `HWP CHI OFFSET DEG` ([`MuellerCal::hwp_chi_offset_deg`]) says by how much,
//! so that `correct` turns a measurement at the plate by it first. Maps that record none (and
//! files written before the format had this keyword) are fitted as they are, in the maps'
//! frame, and hold 0: a zero angle is then a rotation of the polarization plane, fitted only
//! when `rotation` is free (and `explain` would read it as a physical rotation). Positions
//! outside the fitted box are refused unless extrapolation is allowed, then the same rule as
//! the `p, phi` path: the correction itself is trusted to a fraction `f`
//! ([`CorrectOptions::extrapolation_rel_error`]), `(f |v0 - m|)^2` added to each variance.

use crate::correction::correct::{self, CorrectOptions, Corrected, Measurement};
use crate::files::calfile::{PixelGrid, Provenance};
use crate::files::keys::{fits_err, open_versioned, save_fits_atomically, KeyReader, KeyWriter, FORMAT_VERSION};
use crate::mueller_field::smooth;
use crate::mueller_field::{monomial_powers, BinFit, Kind, MuellerField, Smooth};
use crate::{Error, Result};
use field::{FieldCoords, FieldModel};
use fitsio::images::{ImageDescription, ImageType};
use fitsio::tables::{ColumnDataType, ColumnDescription};
use fitsio::FitsFile;
use std::path::Path;

/// The `HIERARCH IP MODEL` of this kind of file.
pub use crate::files::keys::MUELLER_MODEL as MODEL_KIND;
/// The coefficient table.
pub const HDU: &str = "MUELLER";
/// The coefficients' covariance (image).
pub const COV_HDU: &str = "MUELLER_COV";
/// The per-bin fits (table, optional).
pub const BINS_HDU: &str = "MUELLER_BINS";

/// One sky field the Mueller field was fitted to: its name (file) and declared polarization.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SkyField {
    pub name: String,
    /// Degree of the sky's polarization (fraction), its angle (deg) and the 1-sigma
    /// uncertainty of each of the sky's q, u (fraction).
    pub p: f64,
    pub chi_deg: f64,
    pub sigma: f64,
}

/// A Mueller-field calibration: the fitted field and what it was fitted to.
#[derive(Debug, Clone, PartialEq)]
pub struct MuellerCal {
    pub instrument: String,
    pub filter: String,
    pub field: MuellerField,
    /// The detector pixel grid of the field coordinates (for catalogs in pixels).
    pub coords: Option<FieldCoords>,
    pub skies: Vec<SkyField>,
    /// The per-bin fits, when they were made (each a degree-0 field).
    pub per_bin: Vec<BinFit>,
    pub provenance: Provenance,
    /// The HWP zero angle (deg) the maps were turned by into the sky frame before the fit
    /// (module docs): what `correct` applies to a measurement at the plate first.
    pub hwp_chi_offset_deg: f64,
}

/// Whether `path` is a Mueller-field calibration (primary `HIERARCH IP MODEL = 'MUELLER'`).
/// Files that are not FITS, or have no such keyword, are not (their own readers say why).
pub fn is_mueller(path: &Path) -> bool {
    let Ok(mut f) = FitsFile::open(path) else { return false };
    let Ok(hdu) = f.primary_hdu() else { return false };
    let mut r = KeyReader { f: &mut f, hdu: &hdu, path };
    r.opt_str("MODEL").as_deref() == Some(MODEL_KIND)
}

/// The Mueller field of a file that is either a calibration (FITS, [`MuellerCal::load`]) or
/// the JSON of `calibrate-mueller --out X.json` ([`MuellerField::from_json`]), told apart by
/// content (a FITS file begins with `SIMPLE  =`), with the per-bin fits when the file has them.
/// A FITS file that is not a Mueller-field calibration (a `p, phi` calibration, a Stokes map)
/// is refused naming its `HIERARCH IP MODEL`.
pub fn load_field(path: &Path) -> Result<LoadedField> {
    use std::io::Read;
    let what = path.display().to_string();
    let mut head = [0u8; 9];
    let n = std::fs::File::open(path)
        .and_then(|mut f| f.read(&mut head))
        .map_err(|e| Error::Input(format!("{what}: cannot read: {e}")))?;
    if n == 9 && &head == b"SIMPLE  =" {
        if !is_mueller(path) {
            let model = FitsFile::open(path).ok().and_then(|mut f| {
                let hdu = f.primary_hdu().ok()?;
                KeyReader { f: &mut f, hdu: &hdu, path }.opt_str("MODEL")
            });
            return Err(Error::BadFile {
                path: path.into(),
                what: match model {
                    Some(m) => format!(
                        "HIERARCH IP MODEL = '{m}': a partial-polarizer (p, phi) calibration, not a Mueller field ('{MODEL_KIND}', written by instpol calibrate-mueller)"
                    ),
                    None => format!(
                        "a FITS file without HIERARCH IP MODEL: not a Mueller-field calibration ('{MODEL_KIND}', written by instpol calibrate-mueller)"
                    ),
                },
            });
        }
        let cal = MuellerCal::load(path)?;
        return Ok(LoadedField { field: cal.field, per_bin: cal.per_bin, of: Some((cal.instrument, cal.filter)) });
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::Input(format!("{what}: cannot read as text: {e}")))?;
    Ok(LoadedField { field: MuellerField::from_json(&text, &what)?, per_bin: vec![], of: None })
}

/// A Mueller field as [`load_field`] read it.
pub struct LoadedField {
    pub field: MuellerField,
    /// The per-bin fits, when the file keeps them.
    pub per_bin: Vec<BinFit>,
    /// The instrument and filter the calibration records (the FITS form records them; the
    /// JSON form does not).
    pub of: Option<(String, String)>,
}

impl LoadedField {
    /// Refuse to use the field as one of instrument `inst` in filter `band` when the file
    /// records another instrument or filter (the filter compared through `inst`'s names and
    /// aliases, [`crate::correction::setup::same_filter`]); `what` names the file in the message.
    pub fn check_for(&self, inst: &instrument::Instrument, band: &str, what: &str) -> Result<()> {
        let Some((i, f)) = &self.of else { return Ok(()) };
        if !crate::correction::setup::same_instrument(i, &inst.name) {
            return Err(Error::Input(format!(
                "{what} is a Mueller field of instrument {i}, not of {} (--instrument): explain it with its own instrument",
                inst.name
            )));
        }
        if !crate::correction::setup::same_filter(Some(inst), f, band) {
            return Err(Error::Input(format!(
                "{what} is a Mueller field of filter {f}, not of {band} (--band): explain it in its own filter"
            )));
        }
        Ok(())
    }
}

impl MuellerCal {
    /// The pixel grid of the field coordinates, in the form the catalog readers take.
    pub fn pixel(&self) -> Option<PixelGrid> {
        // Binned pixel x_b is unbinned b x_b + (b - 1) / 2 (FieldCoords): the same positions
        // as a grid of b-times-larger pixels about the origin in binned pixels.
        self.coords.map(|c| {
            let b = c.binning as f64;
            let o = |v: f64| (v - 0.5 * (b - 1.0)) / b;
            PixelGrid { scale_arcsec: c.scale_arcsec * b, origin_px: [o(c.origin_px[0]), o(c.origin_px[1])] }
        })
    }

    /// Correct one measurement exactly (module docs): the source's `(q0, u0)` with the
    /// measurement's and the model's covariance propagated; `inst` is the field's
    /// instrumental polarization of unpolarized light there. The measurement is first turned
    /// from its frame into the sky frame of the HWP zero angle of `opts` (the file's
    /// [`MuellerCal::hwp_chi_offset_deg`]), as in [`correct::Corrector`].
    pub fn correct(&self, m: &Measurement, opts: &CorrectOptions) -> std::result::Result<Corrected, correct::Error> {
        correct::check_measurement(m)?;
        let inside = self.field.contains(m.x, m.y);
        if !inside && !opts.allow_extrapolation {
            return Err(correct::Error::OutsideField { x: m.x, y: m.y });
        }
        let m1 = m.frame.to_sky(&m.qu, opts.zero_angle_deg);
        let (q1, u1) = (m1.q, m1.u);
        let var1 = [m1.var_q, m1.cov_qu, m1.var_u];
        let ((q0, u0), mut cov) =
            self.field.correct(m.x, m.y, q1, u1, var1).map_err(|e| correct::Error::Mueller(e.to_string()))?;
        if !inside {
            let f = opts.extrapolation_rel_error;
            let add = f * f * ((q0 - q1).powi(2) + (u0 - u1).powi(2));
            cov[0] += add;
            cov[2] += add;
        }
        if !(cov.iter().all(|v| v.is_finite()) && q0.is_finite() && u0.is_finite()) {
            return Err(correct::Error::Mueller(format!(
                "the Mueller field at ({}, {}) arcmin gives no finite correction",
                m.x, m.y
            )));
        }
        Ok(Corrected::of(mueller::Qu::new(q0, u0, cov[0], cov[2], cov[1]), self.field.eval(m.x, m.y), !inside))
    }

    /// Write the calibration to `path` atomically (a temporary file beside it, renamed when
    /// complete and synced).
    pub fn save(&self, path: &Path) -> Result<()> {
        save_fits_atomically(path, |f| self.write_to(f, path))
    }

    /// [`Self::save`] of a file whose field elements are `order`, in the order light meets
    /// them, this Mueller field among them ([`crate::files::elements::Element::Model`]); `extra`
    /// writes further HDUs as in [`Self::save_with`]. An empty order writes the field alone.
    pub fn save_with_elements(
        &self,
        path: &Path,
        order: &[crate::files::elements::Element],
        extra: impl FnOnce(&mut FitsFile, &Path) -> Result<()>,
    ) -> Result<()> {
        self.save_with(path, crate::files::elements::writing_then(order, extra)?)
    }

    /// [`Self::save`], with `extra` writing further HDUs into the same temporary file before it
    /// is renamed: a telescope model beside the field (`crate::telescope::cal::write_hdu`).
    pub fn save_with(&self, path: &Path, extra: impl FnOnce(&mut FitsFile, &Path) -> Result<()>) -> Result<()> {
        save_fits_atomically(path, |f| {
            self.write_to(f, path)?;
            extra(f, path)
        })
    }

    fn write_to(&self, f: &mut FitsFile, path: &Path) -> Result<()> {
        let e = |doing: &str| fits_err(path, doing);
        let mf = &self.field;
        let b = mf.bounds;
        let hdu = f.primary_hdu().map_err(e("opening the primary HDU"))?;
        let mut w = KeyWriter { f, hdu: &hdu, path };
        w.int("FORMAT VERSION", FORMAT_VERSION)?;
        w.str("INSTRUMENT", &self.instrument)?;
        w.str("FILTER", &self.filter)?;
        w.str("MODEL", MODEL_KIND)?;
        w.real("HWP CHI OFFSET DEG", self.hwp_chi_offset_deg)?;
        w.str("UNITS", "fractions; arcmin from detector centre; degrees")?;
        for (k, v) in ["REGION XMIN", "REGION XMAX", "REGION YMIN", "REGION YMAX"].iter().zip(b) {
            w.real(k, v)?;
        }
        if let Some(c) = &self.coords {
            w.real("PIX SCALE ARCSEC", c.scale_arcsec)?;
            w.real("PIX ORIGIN X", c.origin_px[0])?;
            w.real("PIX ORIGIN Y", c.origin_px[1])?;
            w.int("PIX BINNING", c.binning as i64)?;
        }
        let pv = &self.provenance;
        pv.write_common(&mut w)?;
        w.int("NINPUT", pv.inputs.len() as i64)?;
        for (k, name) in pv.inputs.iter().enumerate() {
            w.str(&format!("INPUT{}", k + 1), name)?;
        }

        // The coefficients, one row each.
        let rows = coeff_rows(mf.kind, mf.smooth.name(), mf.deg)
            .map_err(|m| Error::Input(format!("{}: {m}", path.display())))?;
        let n = mf.coeffs.len();
        if rows.len() != n || mf.cov.len() != n * n {
            return Err(Error::Input(format!("{}: the field's coefficients do not match its model", path.display())));
        }
        if matches!(mf.smooth, Smooth::Interp(_)) && self.per_bin.is_empty() {
            return Err(Error::Input(format!(
                "{}: the interpolant form is stored as its per-bin fits, and there are none",
                path.display()
            )));
        }
        let mut descs = vec![];
        for (c, t) in [
            ("PARAM", ColumnDataType::Int),
            ("PX", ColumnDataType::Int),
            ("PY", ColumnDataType::Int),
            ("COEFF", ColumnDataType::Double),
            ("SIGMA", ColumnDataType::Double),
        ] {
            descs.push(ColumnDescription::new(c).with_type(t).create().map_err(e("describing MUELLER"))?);
        }
        let h = f.create_table(HDU, &descs).map_err(e("creating table MUELLER"))?;
        let param: Vec<i32> = rows.iter().map(|r| r.0 as i32).collect();
        let px: Vec<i32> = rows.iter().map(|r| r.1 as i32).collect();
        let py: Vec<i32> = rows.iter().map(|r| r.2 as i32).collect();
        let sigma: Vec<f64> = (0..n).map(|r| mf.cov[r * n + r].max(0.0).sqrt()).collect();
        if n > 0 {
            for (c, v) in [("PARAM", &param), ("PX", &px), ("PY", &py)] {
                h.write_col(f, c, v).map_err(e(&format!("writing MUELLER column {c}")))?;
            }
            h.write_col(f, "COEFF", &mf.coeffs).map_err(e("writing MUELLER column COEFF"))?;
            h.write_col(f, "SIGMA", &sigma).map_err(e("writing MUELLER column SIGMA"))?;
        }
        let mut w = KeyWriter { f, hdu: &h, path };
        w.str("MU SMOOTH", &mf.smooth.name().to_ascii_uppercase())?;
        w.str("MU MODEL", mf.kind.model_name())?;
        w.str("MU FREE", &mf.kind.free_words().join(","))?;
        w.int("MU DEG", mf.deg as i64)?;
        w.real("MU SCALE ARCMIN", mf.scale_arcmin)?;
        w.int("MU NCOEF", n as i64)?;
        w.real("MU CHI2 DOF", mf.chi2_dof)?;
        w.int("MU NOBS", mf.n_obs as i64)?;
        w.real("MU CONDITION", mf.condition)?;
        for (k, v) in ["MU XMIN", "MU XMAX", "MU YMIN", "MU YMAX"].iter().zip(b) {
            w.real(k, v)?;
        }
        w.int("MU NFIELD", self.skies.len() as i64)?;
        for (k, s) in self.skies.iter().enumerate() {
            w.str(&format!("MU FIELD{}", k + 1), &s.name)?;
            w.real(&format!("MU FIELD{} P", k + 1), s.p)?;
            w.real(&format!("MU FIELD{} CHI DEG", k + 1), s.chi_deg)?;
            w.real(&format!("MU FIELD{} SIGMA", k + 1), s.sigma)?;
        }
        w.int("MU NWARN", mf.warnings.len() as i64)?;
        for (k, t) in mf.warnings.iter().enumerate() {
            w.str(&format!("MU WARN{}", k + 1), t)?;
        }

        // The covariance (the interpolant has no coefficients: its errors are the bins').
        if n > 0 {
            let desc = ImageDescription { data_type: ImageType::Double, dimensions: &[n, n] };
            let h = f.create_image(COV_HDU, &desc).map_err(e("creating image MUELLER_COV"))?;
            h.write_image(f, &mf.cov).map_err(e("writing image MUELLER_COV"))?;
        }

        if !self.per_bin.is_empty() {
            self.write_bins(f, path)?;
        }
        Ok(())
    }

    /// Column names of the per-bin table for the free parameters of `kind` (`free`).
    fn bin_columns(kind: Kind, free: &[usize]) -> (Vec<String>, Vec<String>, Vec<(usize, usize, String)>) {
        let names: Vec<String> = free.iter().map(|&i| kind.name(i).to_ascii_uppercase()).collect();
        let sig = names.iter().map(|n| format!("SIGMA_{n}")).collect();
        let mut cov = vec![];
        for k in 0..free.len() {
            for l in k + 1..free.len() {
                cov.push((k, l, format!("COV_{}_{}", names[k], names[l])));
            }
        }
        (names, sig, cov)
    }

    fn write_bins(&self, f: &mut FitsFile, path: &Path) -> Result<()> {
        let e = |doing: &str| fits_err(path, doing);
        let mf = &self.field;
        let nf = mf.free.len();
        let (names, sig, cov) = Self::bin_columns(mf.kind, &mf.free);
        let mut cols: Vec<(String, Vec<f64>)> = vec![
            ("X_ARCMIN".into(), self.per_bin.iter().map(|b| b.x_arcmin).collect()),
            ("Y_ARCMIN".into(), self.per_bin.iter().map(|b| b.y_arcmin).collect()),
            ("CHI2_DOF".into(), self.per_bin.iter().map(|b| b.field.chi2_dof).collect()),
            ("N_OBS".into(), self.per_bin.iter().map(|b| b.field.n_obs as f64).collect()),
        ];
        for k in 0..nf {
            cols.push((names[k].clone(), self.per_bin.iter().map(|b| b.field.coeffs[k]).collect()));
            cols.push((sig[k].clone(), self.per_bin.iter().map(|b| b.field.cov[k * nf + k].max(0.0).sqrt()).collect()));
        }
        for (k, l, name) in &cov {
            cols.push((name.clone(), self.per_bin.iter().map(|b| b.field.cov[k * nf + l]).collect()));
        }
        let mut descs = vec![];
        for (c, _) in &cols {
            descs.push(
                ColumnDescription::new(c)
                    .with_type(ColumnDataType::Double)
                    .create()
                    .map_err(e("describing MUELLER_BINS"))?,
            );
        }
        let h = f.create_table(BINS_HDU, &descs).map_err(e("creating table MUELLER_BINS"))?;
        for (c, v) in &cols {
            h.write_col(f, c, v).map_err(e(&format!("writing MUELLER_BINS column {c}")))?;
        }
        for (k, unit) in [(1, "arcmin"), (2, "arcmin")] {
            h.write_key(f, &format!("TUNIT{k}"), unit).map_err(e("writing MUELLER_BINS units"))?;
        }
        Ok(())
    }

    /// Read a Mueller-field calibration; every malformed part is refused naming the file and
    /// the keyword, column or row (a newer format version too).
    pub fn load(path: &Path) -> Result<Self> {
        let e = |doing: &str| fits_err(path, doing);
        let bad = |what: String| Error::BadFile { path: path.into(), what };
        let mut f = open_versioned(path)?;
        let hdu = f.primary_hdu().map_err(e("reading the primary HDU"))?;
        let mut r = KeyReader { f: &mut f, hdu: &hdu, path };
        let model = r.str("MODEL")?;
        if model != MODEL_KIND {
            return Err(bad(format!("MODEL = '{model}': not a Mueller-field calibration ('{MODEL_KIND}')")));
        }
        let instrument = r.str("INSTRUMENT")?;
        let filter = r.str("FILTER")?;
        let hwp_chi_offset_deg = r.opt_real("HWP CHI OFFSET DEG").unwrap_or(0.0);
        if !hwp_chi_offset_deg.is_finite() {
            return Err(bad(format!("HWP CHI OFFSET DEG = {hwp_chi_offset_deg}: not a finite angle")));
        }
        let coords = read_coords(&mut r, path)?;
        let mut provenance = Provenance::read_common(&mut r)?;
        let ninput = r.opt_int("NINPUT").unwrap_or(0).clamp(0, 10_000);
        for k in 1..=ninput {
            provenance.inputs.push(r.opt_str(&format!("INPUT{k}")).unwrap_or_default());
        }

        let h = f.hdu(HDU).map_err(e("finding table MUELLER"))?;
        let nrows = match &h.info {
            fitsio::hdu::HduInfo::TableInfo { num_rows, .. } => *num_rows,
            _ => return Err(bad("MUELLER is not a table".into())),
        };
        let (param, px, py, coeffs) = if nrows == 0 {
            (vec![], vec![], vec![], vec![])
        } else {
            let mut ints = |c: &str| -> Result<Vec<i32>> {
                h.read_col::<i32>(&mut f, c).map_err(e(&format!("reading MUELLER column {c}")))
            };
            let (a, b, c) = (ints("PARAM")?, ints("PX")?, ints("PY")?);
            let d: Vec<f64> = h.read_col(&mut f, "COEFF").map_err(e("reading MUELLER column COEFF"))?;
            (a, b, c, d)
        };
        let mut r = KeyReader { f: &mut f, hdu: &h, path };
        // Files written before the smooth forms hold the polynomial.
        let smooth_word = r.opt_str("MU SMOOTH").unwrap_or_else(|| "POLY".into()).to_ascii_lowercase();
        let model_word = r.str("MU MODEL")?;
        let free_words = r.str("MU FREE")?;
        let words: Vec<&str> = free_words.split(',').map(str::trim).filter(|w| !w.is_empty()).collect();
        let kind = Kind::from_words(&model_word, &words).map_err(|m| {
            bad(format!("keywords HIERARCH IP MU MODEL / MU FREE ('{model_word}', '{free_words}'): {m}"))
        })?;
        let deg = r.int("MU DEG")?;
        if !(0..=12).contains(&deg) {
            return Err(bad(format!("keyword HIERARCH IP MU DEG = {deg}: must be 0..12")));
        }
        let deg = deg as usize;
        let scale_arcmin = r.real("MU SCALE ARCMIN")?;
        if !(scale_arcmin > 0.0 && scale_arcmin.is_finite()) {
            return Err(bad(format!("keyword HIERARCH IP MU SCALE ARCMIN = {scale_arcmin}: must be positive")));
        }
        let free = kind.free();
        let rows = coeff_rows(kind, &smooth_word, deg)
            .map_err(|m| bad(format!("keyword HIERARCH IP MU SMOOTH = '{smooth_word}': {m}")))?;
        let n = rows.len();
        if nrows != n || coeffs.len() != n {
            return Err(bad(format!(
                "MUELLER has {nrows} rows; the {} model ({}) in the {smooth_word} form of degree {deg} has {n} coefficients",
                kind.model_name(),
                kind.free_words().join(", ")
            )));
        }
        check_rows(&rows, (&param, &px, &py, &coeffs)).map_err(bad)?;
        let mut bounds = [0.0; 4];
        for (k, name) in ["MU XMIN", "MU XMAX", "MU YMIN", "MU YMAX"].iter().enumerate() {
            bounds[k] = r.real(name)?;
        }
        if !bounds.iter().all(|v| v.is_finite()) || bounds[0] > bounds[1] || bounds[2] > bounds[3] {
            return Err(bad(format!("keywords HIERARCH IP MU XMIN..YMAX = {bounds:?} are not a box")));
        }
        let chi2_dof = r.opt_real("MU CHI2 DOF").unwrap_or(f64::NAN);
        let n_obs = r.opt_int("MU NOBS").unwrap_or(0).max(0) as usize;
        let condition = r.opt_real("MU CONDITION").unwrap_or(f64::NAN);
        let skies = read_skies(&mut r)?;
        let nwarn = r.opt_int("MU NWARN").unwrap_or(0).clamp(0, 1000);
        let warnings = (1..=nwarn).filter_map(|k| r.opt_str(&format!("MU WARN{k}"))).collect();

        let cov = if n == 0 { vec![] } else { read_cov(&mut f, path, n)? };

        let mut field = MuellerField {
            kind,
            deg,
            scale_arcmin,
            free: free.clone(),
            coeffs,
            cov,
            chi2_dof,
            n_obs,
            condition,
            bounds,
            warnings,
            smooth: Smooth::Poly,
        };
        let per_bin = match f.hdu(BINS_HDU) {
            Err(_) => vec![],
            Ok(h) => read_bins(&mut f, &h, path, kind, &free)?,
        };
        field.smooth = match smooth_word.as_str() {
            "radial" => Smooth::Radial(
                smooth::radial_form_of(kind, deg, &field.coeffs, &field.cov)
                    .map_err(|m| bad(format!("table MUELLER: {m}")))?,
            ),
            "interp" => {
                if per_bin.len() < 3 {
                    return Err(bad(format!(
                        "the interpolant form (MU SMOOTH = 'INTERP') is read from table MUELLER_BINS, which holds {} rows (>= 3 needed)",
                        per_bin.len()
                    )));
                }
                let built = smooth::interp_field(&per_bin).map_err(|e| bad(format!("table MUELLER_BINS: {e}")))?;
                built.smooth
            }
            _ => Smooth::Poly,
        };
        Ok(MuellerCal { instrument, filter, field, coords, skies, per_bin, provenance, hwp_chi_offset_deg })
    }
}

/// The field coordinates of the maps (`IP PIX SCALE ARCSEC`, `PIX ORIGIN X/Y`, `PIX BINNING`),
/// none when the file gives no pixel scale; an unusable grid is refused naming the keywords.
fn read_coords(r: &mut KeyReader, path: &Path) -> Result<Option<FieldCoords>> {
    let bad = |what: String| Error::BadFile { path: path.into(), what };
    Ok(match r.opt_real("PIX SCALE ARCSEC") {
        None => None,
        Some(scale) => {
            let origin = [r.real("PIX ORIGIN X")?, r.real("PIX ORIGIN Y")?];
            let binning = r.opt_int("PIX BINNING").unwrap_or(1);
            let valid =
                scale > 0.0 && scale.is_finite() && origin.iter().all(|v| v.is_finite()) && (1..=64).contains(&binning);
            if !valid {
                return Err(bad(format!(
                    "pixel grid PIX SCALE ARCSEC = {scale}, PIX ORIGIN = {origin:?}, PIX BINNING = {binning} is not valid"
                )));
            }
            Some(FieldCoords::with_origin(origin, scale).binned(binning as usize))
        }
    })
}

/// Each row of table MUELLER as the form expects it (`rows`: its `(PARAM, PX, PY)`) with a
/// finite coefficient; the first that is not, named.
fn check_rows(
    rows: &[(usize, usize, usize)],
    (param, px, py, coeffs): (&[i32], &[i32], &[i32], &[f64]),
) -> std::result::Result<(), String> {
    let n = rows.len();
    for row in 0..n {
        let want = (rows[row].0 as i32, rows[row].1 as i32, rows[row].2 as i32);
        if (param[row], px[row], py[row]) != want || !coeffs[row].is_finite() {
            return Err(format!(
                "MUELLER row {}: PARAM, PX, PY, COEFF = {}, {}, {}, {}: expected {}, {}, {} and a finite coefficient",
                row + 1,
                param[row],
                px[row],
                py[row],
                coeffs[row],
                want.0,
                want.1,
                want.2
            ));
        }
    }
    Ok(())
}

/// The sky fields the Mueller field was fitted to (`IP MU NFIELD`, `IP MU FIELD<k>` ..).
fn read_skies(r: &mut KeyReader) -> Result<Vec<SkyField>> {
    let nfield = r.opt_int("MU NFIELD").unwrap_or(0).clamp(0, 10_000);
    let mut skies = vec![];
    for k in 1..=nfield {
        skies.push(SkyField {
            name: r.opt_str(&format!("MU FIELD{k}")).unwrap_or_default(),
            p: r.real(&format!("MU FIELD{k} P"))?,
            chi_deg: r.real(&format!("MU FIELD{k} CHI DEG"))?,
            sigma: r.opt_real(&format!("MU FIELD{k} SIGMA")).unwrap_or(0.0),
        });
    }
    Ok(skies)
}

/// The `n x n` covariance of the coefficients (image MUELLER_COV), checked.
fn read_cov(f: &mut FitsFile, path: &Path, n: usize) -> Result<Vec<f64>> {
    let e = |doing: &str| fits_err(path, doing);
    let bad = |what: String| Error::BadFile { path: path.into(), what };
    let h = f.hdu(COV_HDU).map_err(e("finding image MUELLER_COV"))?;
    match &h.info {
        fitsio::hdu::HduInfo::ImageInfo { shape, .. } if shape.as_slice() == [n, n] => {}
        fitsio::hdu::HduInfo::ImageInfo { shape, .. } => {
            return Err(bad(format!("MUELLER_COV is {shape:?}, not the {n} x {n} covariance of the coefficients")))
        }
        _ => return Err(bad("MUELLER_COV is not an image".into())),
    }
    let cov: Vec<f64> = h.read_image(f).map_err(e("reading image MUELLER_COV"))?;
    check_covariance(&cov, n).map_err(|m| bad(format!("MUELLER_COV {m}")))?;
    Ok(cov)
}

/// `(PARAM, PX, PY)` of each coefficient row of table MUELLER for a smooth form (`poly`:
/// powers of `x / scale`, `y / scale` per free parameter; `radial`: the pair's first parameter
/// and the power of `r`; `interp`: none, the per-bin table is the form).
fn coeff_rows(kind: Kind, smooth: &str, deg: usize) -> std::result::Result<Vec<(usize, usize, usize)>, String> {
    match smooth {
        "poly" => {
            let powers = monomial_powers(deg);
            Ok(kind.free().into_iter().flat_map(|p| powers.iter().map(move |&(i, j)| (p, i, j))).collect())
        }
        "radial" => smooth::radial_rows(kind, deg),
        "interp" => Ok(vec![]),
        other => Err(format!("unknown smooth form '{other}' (POLY, RADIAL or INTERP)")),
    }
}

/// A symmetric covariance: finite, variances >= 0, correlations within 1 (the message names
/// the element).
fn check_covariance(cov: &[f64], n: usize) -> std::result::Result<(), String> {
    if cov.len() != n * n {
        return Err(format!("holds {} values, not {n} x {n}", cov.len()));
    }
    for i in 0..n {
        let cii = cov[i * n + i];
        if !(cii.is_finite() && cii >= 0.0) {
            return Err(format!("element ({i}, {i}) = {cii} is not a variance (finite, >= 0)"));
        }
        for j in 0..i {
            let (a, b) = (cov[i * n + j], cov[j * n + i]);
            if !(a.is_finite() && (a - b).abs() <= 1e-9 * (a.abs() + b.abs()) + f64::MIN_POSITIVE) {
                return Err(format!("elements ({i}, {j}) = {a} and ({j}, {i}) = {b}: not symmetric"));
            }
            if a * a > cii * cov[j * n + j] * (1.0 + 1e-9) {
                return Err(format!("element ({i}, {j}) = {a}: |correlation| > 1"));
            }
        }
    }
    Ok(())
}

fn read_bins(
    f: &mut FitsFile,
    h: &fitsio::hdu::FitsHdu,
    path: &Path,
    kind: Kind,
    free: &[usize],
) -> Result<Vec<BinFit>> {
    let e = |doing: &str| fits_err(path, doing);
    let nrows = match &h.info {
        fitsio::hdu::HduInfo::TableInfo { num_rows, .. } => *num_rows,
        _ => return Err(Error::BadFile { path: path.into(), what: "MUELLER_BINS is not a table".into() }),
    };
    if nrows == 0 {
        return Ok(vec![]);
    }
    let mut get = |c: &str| -> Result<Vec<f64>> {
        h.read_col::<f64>(f, c).map_err(e(&format!("reading MUELLER_BINS column {c}")))
    };
    let (x, y, chi2, nobs) = (get("X_ARCMIN")?, get("Y_ARCMIN")?, get("CHI2_DOF")?, get("N_OBS")?);
    let (names, sig, covn) = MuellerCal::bin_columns(kind, free);
    let nf = free.len();
    let vals: Vec<Vec<f64>> = names.iter().map(|c| get(c)).collect::<Result<_>>()?;
    let sigs: Vec<Vec<f64>> = sig.iter().map(|c| get(c)).collect::<Result<_>>()?;
    let covs: Vec<Vec<f64>> = covn.iter().map(|(_, _, c)| get(c)).collect::<Result<_>>()?;
    let mut out = Vec::with_capacity(nrows);
    for r in 0..nrows {
        let coeffs: Vec<f64> = vals.iter().map(|v| v[r]).collect();
        let mut cov = vec![0.0; nf * nf];
        for k in 0..nf {
            cov[k * nf + k] = sigs[k][r] * sigs[k][r];
        }
        for (c, (k, l, _)) in covs.iter().zip(&covn) {
            cov[k * nf + l] = c[r];
            cov[l * nf + k] = c[r];
        }
        let ok = x[r].is_finite() && y[r].is_finite() && coeffs.iter().all(|v| v.is_finite());
        if let (false, _) | (_, Err(_)) = (ok, check_covariance(&cov, nf)) {
            return Err(Error::BadFile {
                path: path.into(),
                what: format!("MUELLER_BINS row {}: non-finite position or value, or not a covariance", r + 1),
            });
        }
        out.push(BinFit {
            x_arcmin: x[r],
            y_arcmin: y[r],
            field: MuellerField {
                kind,
                deg: 0,
                scale_arcmin: 1.0,
                free: free.to_vec(),
                coeffs,
                cov,
                chi2_dof: chi2[r],
                n_obs: nobs[r].max(0.0) as usize,
                condition: f64::NAN,
                bounds: [x[r], x[r], y[r], y[r]],
                warnings: vec![],
                smooth: Smooth::Poly,
            },
        });
    }
    Ok(out)
}
