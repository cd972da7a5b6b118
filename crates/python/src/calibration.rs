//! A calibration file loaded (`instpol.Calibration`): its model evaluated and rows corrected,
//! as `instpol correct` reads and applies it.

use crate::convert::*;
use crate::errors::*;
use crate::maps::map_dict;
use fit::correction::columns::{Inputs, Units};
use fit::correction::correct::Method;
use numpy::PyReadonlyArray1;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rayon::prelude::*;
use std::borrow::Cow;
use std::path::PathBuf;
use stokes::stats::Estimator;

/// The field model a calibration file holds: a partial polarizer p, phi (`instpol calibrate`,
/// `import-map`, `fit`) or a Mueller field (`instpol calibrate-mueller --out CAL.fits`); or
/// none, in a telescope-only file (`instpol fit-standards --output`), named by its instrument
/// and its telescope model's only band ("" with several).
pub(crate) enum Field<'a> {
    PPhi(&'a fit::Calibration),
    Mueller(&'a fit::mueller_field::cal::MuellerCal),
    TelescopeOnly {
        instrument: &'a str,
        filter: &'a str,
    },
    /// An instrument's constant response from standards (`instpol efficiency`).
    Response(&'a fit::response::cal::ResponseCal),
}

/// A calibration file as `fit::files::calibration::load` reads it (`instpol correct`'s reader): a
/// partial polarizer (`fit::Calibration`) or a Mueller field (`fit::mueller_field::cal::MuellerCal`),
/// with the telescope model stored beside the field one or alone (`instpol fit-standards
/// --output`), applied after the field with each row's parallactic angle.
#[pyclass(module = "instpol._instpol", frozen)]
pub(crate) struct _Calibration {
    file: fit::files::calibration::CalibrationFile,
    path: PathBuf,
}

impl _Calibration {
    /// The file's field model, or what names a telescope-only file.
    fn field(&self) -> Field<'_> {
        if let Some(r) = &self.file.response {
            return Field::Response(r);
        }
        match (&self.file.field, &self.file.mueller, &self.file.telescope) {
            (Some(c), _, _) => Field::PPhi(c),
            (None, Some(m), _) => Field::Mueller(m),
            (None, None, t) => Field::TelescopeOnly {
                instrument: &self.file.instrument,
                filter: t.as_ref().filter(|t| t.bands.len() == 1).map_or("", |t| t.bands[0].0.as_str()),
            },
        }
    }

    fn instrument_filter(&self) -> (&str, &str) {
        match self.field() {
            Field::PPhi(c) => (&c.instrument, &c.filter),
            Field::Mueller(m) => (&m.instrument, &m.filter),
            Field::TelescopeOnly { instrument, filter } => (instrument, filter),
            Field::Response(r) => (&r.instrument, &r.filter),
        }
    }

    fn pixel(&self) -> Option<fit::files::calfile::PixelGrid> {
        fit::correction::columns::pixel_grid(&self.file)
    }

    /// A telescope model's band that cannot be chosen, in this package's words.
    fn band_error(&self, e: fit::telescope::BandChoiceError) -> PyErr {
        use fit::telescope::{BandChoiceError, BandSource};
        let path = self.path.display();
        input_err(match e {
            BandChoiceError::Missing { band, source: BandSource::Asked, bands } => {
                format!("band '{band}': the telescope model of {path} has bands {}: choose one with band=", bands.join(", "))
            }
            BandChoiceError::Missing { band, source: BandSource::FieldCalibration, bands } => format!(
                "{path}: the field calibration is for filter {band}, a band the telescope model does not have (it has {}): choose one with band=",
                bands.join(", ")
            ),
            BandChoiceError::Ambiguous { bands } => {
                format!("the telescope model of {path} has bands {}: choose one with band=", bands.join(", "))
            }
        })
    }

    /// A refusal of `fit::correction::request::plan_map` in this package's words.
    fn map_error(&self, e: fit::correction::request::Refusal, input: &std::path::Path) -> PyErr {
        use fit::correction::request::Refusal as E;
        let (cal_path, input) = (self.path.display(), input.display());
        input_err(match e {
            E::TelescopeOptions { mueller } => format!(
                "parang_deg, rotator_deg and band are for calibrations with a telescope model; {cal_path} holds {}",
                if mueller { "a Mueller field" } else { "none" }
            ),
            E::Mismatch { mismatch: fit::correction::setup::Mismatch::Setup { data, calibration }, .. } => format!(
                "{input} is a {} {} map but {cal_path} calibrates {} {} (instrument, filter): use the calibration of the map's instrument and filter (or allow_mismatch=True)",
                data.0, data.1, calibration.0, calibration.1
            ),
            E::BandMismatch { map_filter, band } => format!(
                "{input} is a {map_filter} map but the telescope model's band is {band}: use the band of the map's filter (band=), or allow_mismatch=True"
            ),
            E::NoParallactic => format!(
                "{input}: the map needs the parallactic angle of its exposures for the telescope model of {cal_path}: give parang_deg=(START, END) (deg: the first frame's start, the last frame's end; instpol reduce records it when the instrument's [telescope] section names the header keywords)"
            ),
            E::NoRotator { .. } => format!(
                "the telescope model of {cal_path} was fitted with rotator angles: give the exposures' with rotator_deg="
            ),
            E::Band(b) => return self.band_error(b),
            e => return self.rows_error(e, false),
        })
    }

    /// A note of `fit::correction::request` on a map's correction, in this package's words.
    fn note_text(&self, n: &fit::correction::request::Note, input: &std::path::Path) -> String {
        use fit::correction::request::Note;
        let (cal_path, input) = (self.path.display(), input.display());
        match n {
            Note::TrackReplaced { recorded: (s, e) } => format!(
                "parang_deg replaces the parallactic angle {input} recorded ({:.3} to {:.3} deg)",
                s.to_degrees(),
                e.to_degrees()
            ),
            Note::RotatorIgnored => format!(
                "rotator_deg is ignored: the telescope model of {cal_path} was fitted without rotator angles (its offset holds the rotator's)"
            ),
            Note::ZeroAngleUnknown(w) => w.clone(),
            Note::InstrumentFileDiffers { data, calibration } => format!(
                "{input} and {cal_path} are of one instrument but were made with two different instrument files ({data} and {calibration}, BLAKE3): corrected; if the file's geometry, strips or zero angles changed between them, remake the calibration"
            ),
            Note::MismatchAllowed(m) => format!(
                "allow_mismatch: {input} and {cal_path} do not fit together ({m}); corrected all the same"
            ),
            Note::CarriedZeroAngle { carried, calibration, applied } => format!(
                "q, u carry the HWP zero angle {carried} deg but {cal_path} records {calibration} deg: the rows are turned by the difference, {applied} deg, into the calibration's frame (every chi0 moves by it)"
            ),
            Note::AnglesWithoutTelescope => format!(
                "{cal_path} holds no telescope model: the telescope's polarization is NOT removed"
            ),

        }
    }

    /// A refusal of `fit::correction::request` in this package's words (`per_row`: parang_deg was given).
    fn rows_error(&self, e: fit::correction::request::Refusal, per_row: bool) -> PyErr {
        use fit::correction::request::Refusal as E;
        let path = self.path.display();
        match e {
            E::TelescopeOptions { mueller: true } => input_err(format!(
                "parang_deg, parang_end_deg and band are for calibrations with a telescope model; {path} holds a Mueller field"
            )),
            E::TelescopeOptions { mueller: false } if per_row => input_err(format!(
                "parang_deg given but {path} holds no telescope model: the telescope's polarization would NOT be removed (fit one with instpol fit-standards --output --field-cal)"
            )),
            E::TelescopeOptions { mueller: false } => input_err(format!(
                "band or recorded given but {path} holds no telescope model: the telescope's polarization would NOT be removed"
            )),
            E::MuellerFirstOrder => input_err(format!(
                "method \"first-order\": {path} holds a Mueller field, which is inverted exactly (eq:approx is the p, phi model's first order)"
            )),
            E::NoParallactic => input_err(format!(
                "{path} holds a telescope model ({}): give each row's parallactic angle, parang_deg= (deg, as the standards were fitted with), as `instpol correct` reads it from the column parang_deg",
                self.file.telescope.as_ref().map_or("", |t| t.model.name())
            )),
            E::TwoTracks => input_err("give parang_deg (each row's track) or recorded (the catalog's exposures), not both"),
            E::NoRotator { per_row: false } => {
                input_err("recorded: the telescope model was fitted with rotator angles and the catalog recorded none")
            }
            E::NoRotator { per_row: true } => input_err(format!(
                "the telescope model of {path} was fitted with rotator angles, which correct() does not take: correct the catalog with instpol correct (column rotator_deg, or --rotator)"
            )),
            E::Band(b) => self.band_error(b),
            E::Exposures(m) => input_err(format!("recorded: {m}")),
            E::Mismatch { mismatch, .. } => input_err(format!(
                "{mismatch}: give the calibration of the rows' instrument and filter (instrument=, filter= are the rows'), or allow_mismatch=True"
            )),
            E::FrameUnstated { .. } => input_err(format!(
                "{e}: give sky_pa_deg= (catalog()['product']['sky_pa_deg']) or product=catalog()['product'], or sky_pa_deg=0 (with hwp_chi_offset_deg=) for rows in the instrument's own frame"
            )),
            e => input_err(e.to_string()),
        }
    }

    /// Positions in arcmin from the detector centre, from `units` "px" (0-based pixels of the
    /// calibration's grid) or "arcmin" (`fit::correction::columns::arcmin_positions`).
    fn arcmin<'a>(&self, x: &'a [f64], y: &'a [f64], units: &str) -> PyResult<(Cow<'a, [f64]>, Cow<'a, [f64]>)> {
        let units = match units {
            "arcmin" => Units::Arcmin,
            "px" | "pixel" => Units::Pixel,
            u => return Err(input_err(format!("units '{u}': expected \"px\" or \"arcmin\""))),
        };
        fit::correction::columns::arcmin_positions(x, y, units, self.pixel()).map_err(|_| {
            input_err("the calibration has no pixel grid: give the positions in arcmin (units=\"arcmin\")")
        })
    }
}

#[pymethods]
impl _Calibration {
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        // The reader `instpol correct` uses: a Mueller field, or a field model and a telescope
        // model when the file holds one (ignoring it would return the telescope's polarization
        // as the sky's).
        // A telescope-only file (instpol fit-standards --output): correct() applies the
        // telescope alone, as `instpol correct` does.
        let file = py.detach(|| fit::files::calibration::load(&path)).map_err(|e| load_err(&path, e))?;
        Ok(Self { file, path })
    }

    #[getter]
    fn path(&self) -> PathBuf {
        self.path.clone()
    }
    #[getter]
    fn instrument(&self) -> String {
        self.instrument_filter().0.to_string()
    }
    #[getter]
    fn filter(&self) -> String {
        self.instrument_filter().1.to_string()
    }
    #[getter]
    fn lambda_nm(&self) -> f64 {
        match self.field() {
            Field::PPhi(c) => c.lambda_nm,
            Field::Mueller(_) | Field::TelescopeOnly { .. } | Field::Response(_) => f64::NAN,
        }
    }
    #[getter]
    fn hwp_chi_offset_deg(&self) -> f64 {
        match self.field() {
            Field::PPhi(c) => c.hwp_chi_offset_deg,
            // A Mueller field: the zero angle its maps were turned by (fit::mueller_field::cal); a
            // telescope model alone records none (its frame: fit::telescope::cal).
            Field::Mueller(m) => m.hwp_chi_offset_deg,
            Field::TelescopeOnly { .. } => 0.0,
            // A constant response: the zero angle of the sky frame it lives in.
            Field::Response(r) => r.hwp_chi_offset_deg,
        }
    }
    #[getter]
    fn model(&self) -> &'static str {
        match self.field() {
            Field::PPhi(c) => c.model.kind(),
            Field::Mueller(_) => "MUELLER",
            Field::TelescopeOnly { .. } => "TELESCOPE",
            Field::Response(_) => fit::response::cal::RESPONSE_MODEL,
        }
    }
    /// A Mueller field's model in words (`physical`, `general`), as `instpol correct --json`
    /// says it; None for a p, phi calibration.
    #[getter]
    fn mueller_model(&self) -> Option<&'static str> {
        match self.field() {
            Field::Mueller(m) => Some(m.field.kind.model_name()),
            Field::PPhi(_) | Field::TelescopeOnly { .. } | Field::Response(_) => None,
        }
    }
    /// A Mueller field's free effects (`diattenuation`, `retardance`, ...); empty otherwise.
    #[getter]
    fn mueller_free(&self) -> Vec<&'static str> {
        match self.field() {
            Field::Mueller(m) => m.field.kind.free_words(),
            Field::PPhi(_) | Field::TelescopeOnly { .. } | Field::Response(_) => vec![],
        }
    }
    #[getter]
    fn rms_residual(&self) -> f64 {
        match self.field() {
            Field::PPhi(c) => c.rms_residual,
            Field::Mueller(_) | Field::TelescopeOnly { .. } | Field::Response(_) => f64::NAN,
        }
    }
    #[getter]
    fn centre_arcmin(&self) -> (f64, f64) {
        match self.field() {
            Field::PPhi(c) => {
                let c = c.centre_arcmin();
                (c[0], c[1])
            }
            Field::Mueller(_) | Field::TelescopeOnly { .. } | Field::Response(_) => (f64::NAN, f64::NAN),
        }
    }
    #[getter]
    fn has_pixel_grid(&self) -> bool {
        self.pixel().is_some()
    }
    /// The bands of the telescope model stored in the file (empty without one).
    #[getter]
    fn telescope_bands(&self) -> Vec<String> {
        self.file.telescope.as_ref().map_or(vec![], |t| t.bands.iter().map(|b| b.0.clone()).collect())
    }

    /// Instrumental `(q, u)` with the calibration's covariance at flat arrays `x`, `y`, and
    /// whether each position lies inside the calibrated field.
    fn _evaluate<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArray1<'py, f64>,
        y: PyReadonlyArray1<'py, f64>,
        units: &str,
    ) -> PyResult<Bound<'py, PyDict>> {
        use field::FieldModel;
        let (x, y) = (slice(&x, "x")?, slice(&y, "y")?);
        if x.len() != y.len() {
            return Err(input_err("x and y must have one shape (after broadcasting)"));
        }
        if let Field::TelescopeOnly { .. } = self.field() {
            return Err(input_err(format!(
                "{} holds only a telescope model: it has no field to evaluate (correct() applies it with parang_deg=)",
                self.path.display()
            )));
        }
        let (x, y) = self.arcmin(x, y, units)?;
        let (x, y) = (x.as_ref(), y.as_ref());
        fn at<M: FieldModel + Sync>(m: &M, x: &[f64], y: &[f64]) -> Vec<(fit::models::model::InstPol, bool)> {
            x.par_iter().zip(y).map(|(&x, &y)| (m.eval(x, y), m.contains(x, y))).collect()
        }
        let v = py.detach(|| match self.field() {
            Field::PPhi(c) => at(c, x, y),
            Field::Mueller(m) => at(&m.field, x, y),
            Field::TelescopeOnly { .. } => vec![],
            // The same everywhere: (q0, u0) with the file's covariance.
            Field::Response(r) => {
                let (q0, u0, c) = (r.response.q0, r.response.u0, &r.covariance);
                vec![(mueller::Qu::new(q0, u0, c[0][0], c[1][1], c[0][1]), true); x.len()]
            }
        });
        let d = PyDict::new(py);
        d.set_item("q", arr1(py, v.iter().map(|a| a.0.q).collect()))?;
        d.set_item("u", arr1(py, v.iter().map(|a| a.0.u).collect()))?;
        d.set_item("sigma_q", arr1(py, v.iter().map(|a| a.0.var_q.sqrt()).collect()))?;
        d.set_item("sigma_u", arr1(py, v.iter().map(|a| a.0.var_u.sqrt()).collect()))?;
        d.set_item("cov_qu", arr1(py, v.iter().map(|a| a.0.cov_qu).collect()))?;
        d.set_item("inside", bools(py, v.iter().map(|a| a.1).collect()))?;
        Ok(d)
    }

    /// `instpol correct` on flat arrays: exact inversion of `eq:instpol` (or `eq:approx`), the
    /// HWP zero angle first, errors propagated; `estimator`: also the bias-corrected `P0`.
    #[pyo3(signature = (x, y, q, u, sigma_q, sigma_u, cov_qu, units, method, allow_extrapolation, extrapolation_error, estimator, parang_deg, parang_end_deg, band, recorded, carried_deg, setup, allow_mismatch, sky_pa_deg=None, product=None))]
    #[allow(clippy::too_many_arguments)]
    fn _correct<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArray1<'py, f64>,
        y: PyReadonlyArray1<'py, f64>,
        q: PyReadonlyArray1<'py, f64>,
        u: PyReadonlyArray1<'py, f64>,
        sigma_q: PyReadonlyArray1<'py, f64>,
        sigma_u: PyReadonlyArray1<'py, f64>,
        cov_qu: Option<PyReadonlyArray1<'py, f64>>,
        units: &str,
        method: &str,
        allow_extrapolation: bool,
        extrapolation_error: f64,
        estimator: Option<&str>,
        parang_deg: Option<PyReadonlyArray1<'py, f64>>,
        parang_end_deg: Option<PyReadonlyArray1<'py, f64>>,
        band: Option<String>,
        recorded: Option<Recorded>,
        carried_deg: Option<f64>,
        setup: Option<(String, String, Option<String>)>,
        allow_mismatch: bool,
        sky_pa_deg: Option<f64>,
        product: Option<Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let base = request(method, allow_extrapolation, extrapolation_error, band.as_deref(), allow_mismatch)?;
        // What the rows are (instrument, filter, plate, and what else catalog()'s product
        // records: instrument file, detector), checked against the calibration as a table's
        // keywords are.
        let product = product_of_dict(product.as_ref())?;
        let setup = setup.map(|(instrument, filter, plate)| {
            fit::correction::setup::Setup { plate, ..fit::correction::setup::Setup::named(&instrument, &filter) }
                .with_product(product.as_ref())
        });
        // The zero angle q, u already carry (catalog()'s do): given, else what `recorded`
        // says, else none (q, u at the plate); the calibration's less it is applied, as
        // `instpol correct` takes a table's hwp_chi_offset_deg column.
        if carried_deg.is_some_and(|z| !mueller::plausible_degrees(z)) {
            return Err(input_err("hwp_chi_offset_deg must be finite degrees"));
        }
        let carried = carried_deg.or_else(|| recorded.as_ref().and_then(|r| r.zero_angle_deg));
        if sky_pa_deg.is_some_and(|z| !mueller::plausible_degrees(z)) {
            return Err(input_err("sky_pa_deg must be finite degrees"));
        }
        let frame = mueller::Frame::carrying_on_sky(carried, sky_pa_deg).ok_or_else(|| {
            input_err("sky_pa_deg without hwp_chi_offset_deg: give the zero angle the rows carry too (catalog()'s chi_offset_deg)")
        })?;
        let est: Option<Estimator> =
            estimator.map(|e| e.parse().map_err(|e| input_err(format!("estimator: {e}")))).transpose()?;
        let (x, y, q, u) = (slice(&x, "x")?, slice(&y, "y")?, slice(&q, "q")?, slice(&u, "u")?);
        let (sq, su) = (slice(&sigma_q, "sigma_q")?, slice(&sigma_u, "sigma_u")?);
        let cov = cov_qu.as_ref().map(|c| slice(c, "cov_qu")).transpose()?;
        let n = x.len();
        if [y.len(), q.len(), u.len(), sq.len(), su.len(), cov.map_or(n, |c| c.len())].iter().any(|&l| l != n) {
            return Err(input_err("x, y, q, u, sigma_q, sigma_u and cov_qu must have one shape (after broadcasting)"));
        }
        let pa = parang_deg.as_ref().map(|c| slice(c, "parang_deg")).transpose()?;
        let pa_end = parang_end_deg.as_ref().map(|c| slice(c, "parang_end_deg")).transpose()?;
        if [pa.map_or(n, |c| c.len()), pa_end.map_or(n, |c| c.len())].iter().any(|&l| l != n) {
            return Err(input_err("parang_deg and parang_end_deg must have the shape of x (after broadcasting)"));
        }
        if pa_end.is_some() && pa.is_none() {
            return Err(input_err("parang_end_deg needs parang_deg (each row's start)"));
        }
        // The one rule set of `instpol correct`'s tables (fit::correction::request).
        let request = fit::correction::request::Request {
            frame,
            per_row: pa.map(|start_deg| fit::correction::request::PerRowAngles {
                start_deg,
                end_deg: pa_end,
                rotator_deg: None,
            }),
            recorded: recorded.as_ref().map(|r| &r.angles),
            data: setup.as_ref(),
            frame_unstated: sky_pa_deg.is_none(),
            ..base
        };
        let plan = fit::correction::request::plan_rows(&self.file, &request, n)
            .map_err(|e| self.rows_error(e, pa.is_some()))?;
        let (x, y) = self.arcmin(x, y, units)?;
        let input = Inputs { frame: request.frame, x: &x, y: &y, q, u, sigma_q: sq, sigma_u: su, cov_qu: cov };
        let out =
            py.detach(|| fit::correction::columns::correct_columns(&input, est, &|_| {}, |k, m| plan.correct(k, m)));
        let out = out.map_err(|(row, e)| input_err(format!("index {row}: {e}")))?;
        let d = PyDict::new(py);
        for (name, c) in out.names.iter().zip(out.values) {
            d.set_item(name, arr1(py, c))?;
        }
        // What the correction decided and a person should know (a mismatch allowed, two
        // instrument files, a carried zero angle): warned by `Calibration.correct`.
        let rows = std::path::Path::new("the rows");
        d.set_item("warnings", plan.notes.iter().map(|n| self.note_text(n, rows)).collect::<Vec<String>>())?;
        d.set_item(fit::correction::correct::EXTRAPOLATED_COLUMN, bools(py, out.extrapolated))?;
        d.set_item("n_extrapolated", out.n_extrapolated)?;
        d.set_item("n_unmeasured", out.n_unmeasured)?;
        if let Some(t) = &plan.telescope {
            d.set_item("telescope_model", t.fit.model.name())?;
            d.set_item("telescope_band", t.band.as_str())?;
            d.set_item("telescope_exposures", recorded.as_ref().map(|r| r.angles.exposure_tracks.len()))?;
        }
        Ok(d)
    }

    /// `instpol correct` on a Stokes map file (from `instpol reduce` or `reduce(output=)`): the
    /// calibration's field, Mueller field or telescope chain over every valid bin
    /// (`fit::correction::request::MapPlan::correct`), the map's instrument and filter checked, the
    /// telescope's band and track by the CLI's rules; `output`: the corrected map, written with
    /// the correction's record (`INSTCORR`, ...). Returns the corrected map as `_reduce` does,
    /// with the correction's summary.
    #[pyo3(signature = (input, output, method, allow_extrapolation, extrapolation_error, parang_deg, rotator_deg, band, allow_mismatch))]
    #[allow(clippy::too_many_arguments)]
    fn _correct_map<'py>(
        &self,
        py: Python<'py>,
        input: PathBuf,
        output: Option<PathBuf>,
        method: &str,
        allow_extrapolation: bool,
        extrapolation_error: f64,
        parang_deg: Option<Vec<f64>>,
        rotator_deg: Option<f64>,
        band: Option<String>,
        allow_mismatch: bool,
    ) -> PyResult<Bound<'py, PyDict>> {
        use fit::telescope::{angle_from_deg, track_from_deg, TrackDegError};
        let base = request(method, allow_extrapolation, extrapolation_error, band.as_deref(), allow_mismatch)?;
        let bad = |name: &str, x: f64| input_err(format!("{name} {x}: not an angle in degrees (-360 to 360)"));
        let given = parang_deg.as_deref().map(track_from_deg).transpose().map_err(|e| match e {
            TrackDegError::NotAnAngle(x) => bad("parang_deg", x),
            TrackDegError::Count(_) => input_err("parang_deg: expected START or (START, END) in degrees"),
        })?;
        let rotator = rotator_deg.map(|r| angle_from_deg(r).ok_or_else(|| bad("rotator_deg", r))).transpose()?;
        refuse_overwrite(output.as_deref(), [&input, &self.path])?;
        let map = py
            .detach(|| skyfield::StokesMap::read_uncorrected(&input))
            .map_err(|e| input_err(format!("Stokes map {}: {e}", input.display())))?;
        // The one rule set of `instpol correct` on a map (fit::correction::request::plan_map).
        let request = fit::correction::request::Request { parang: given, rotator, ..base };
        let plan =
            fit::correction::request::plan_map(&self.file, &request, &map).map_err(|e| self.map_error(e, &input))?;
        let notes: Vec<String> = plan.notes.iter().map(|n| self.note_text(n, &input)).collect();
        let name = self.path.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
        let (c, stamp) = py
            .detach(|| {
                let r = plan.correct(&map, &name);
                let (c, stamp) = r.map_err(|e| format!("{} {e}", input.display()))?;
                if let Some(out) = &output {
                    c.map.write_corrected_fits(out, &stamp).map_err(|e| e.to_string())?;
                }
                Ok::<_, String>((c, stamp))
            })
            .map_err(input_err)?;
        let d = map_dict(py, &c.map, notes)?;
        let r = PyDict::new(py);
        r.set_item("calibration", &stamp.calibration)?;
        r.set_item("method", &stamp.method)?;
        r.set_item("hwp_chi_offset_deg", stamp.hwp_chi_offset_deg)?;
        r.set_item("n_bins", c.n_bins)?;
        r.set_item("n_extrapolated", c.n_extrapolated)?;
        if let Some(t) = &stamp.telescope {
            r.set_item("telescope_model", &t.model)?;
            r.set_item("telescope_band", &t.band)?;
            r.set_item("rotator_deg", t.rotator_deg)?;
        }
        if let Some((a, b)) = c.map.parallactic_rad {
            r.set_item("parang_deg", (a.to_degrees(), b.to_degrees()))?;
        }
        d.set_item("correction", r)?;
        Ok(d)
    }
}

/// A catalog's recorded telescope angles as the package passes them (`catalog()`'s
/// `recorded_angles`: the set's track and rotator in deg, each exposure's HWP angle and track
/// in deg), in radians, and the HWP zero angle (deg) the catalog's q, u carry
/// (`hwp_chi_offset_deg`, as the CLI's tables carry it in a column; `None` when not given).
pub(crate) struct Recorded {
    angles: skyfield::RecordedAngles,
    zero_angle_deg: Option<f64>,
}

impl<'a, 'py> FromPyObject<'a, 'py> for Recorded {
    type Error = PyErr;
    fn extract(ob: pyo3::Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        let bad = || {
            input_err("recorded: expected catalog()['recorded_angles'] (a dict of parang_deg, rotator_deg, exposures)")
        };
        let d = ob.cast::<PyDict>().map_err(|_| bad())?;
        let get = |k: &str| d.get_item(k).ok().flatten().ok_or_else(bad);
        let (s, e): (f64, f64) = get("parang_deg")?.extract().map_err(|_| bad())?;
        let rot: Option<f64> = get("rotator_deg")?.extract().map_err(|_| bad())?;
        let ex: Vec<(f64, f64, f64)> = get("exposures")?.extract().map_err(|_| bad())?;
        let zero_angle_deg: Option<f64> = match d.get_item("hwp_chi_offset_deg").ok().flatten() {
            Some(z) => Some(z.extract().map_err(|_| bad())?),
            None => None,
        };
        let finite = mueller::plausible_degrees;
        if !zero_angle_deg.is_none_or(finite) {
            return Err(input_err("recorded: hwp_chi_offset_deg must be finite degrees"));
        }
        if !(finite(s)
            && finite(e)
            && rot.is_none_or(finite)
            && ex.iter().all(|x| finite(x.0) && finite(x.1) && finite(x.2)))
            || ex.is_empty()
        {
            return Err(input_err("recorded: angles must be finite degrees and list at least one exposure"));
        }
        let angles = skyfield::RecordedAngles {
            parallactic_rad: Some((s.to_radians(), e.to_radians())),
            rotator_rad: rot.map(f64::to_radians),
            exposure_tracks: ex
                .into_iter()
                .map(|(h, a, b)| skyfield::ExposureTrack { hwp_deg: h, start: a.to_radians(), end: b.to_radians() })
                .collect(),
        };
        Ok(Self { angles, zero_angle_deg })
    }
}

/// What the package's corrections ask of `fit::correction::request`, before each adds its angles: `method=`
/// ("exact" or "first-order") and `extrapolation_error=` checked, no angles yet, and any angles
/// given later are the caller's arguments (refused without a telescope model, where a table's
/// columns would only be noted).
pub(crate) fn request<'a>(
    method: &str,
    allow_extrapolation: bool,
    extrapolation_error: f64,
    band: Option<&'a str>,
    allow_mismatch: bool,
) -> PyResult<fit::correction::request::Request<'a>> {
    let method = match method {
        "exact" => Method::Exact,
        "first-order" | "first_order" => Method::FirstOrder,
        m => return Err(input_err(format!("method '{m}': expected \"exact\" or \"first-order\""))),
    };
    fit::correction::request::check_extrapolation_error(extrapolation_error)
        .map_err(|f| input_err(format!("extrapolation_error {f} must be a non-negative number")))?;
    let base = fit::correction::request::Request::new(method, allow_extrapolation, extrapolation_error);
    Ok(fit::correction::request::Request { band, angles_are_arguments: true, allow_mismatch, ..base })
}
