//! The telescope model in a calibration file, and the correction through the whole chain
//! (telescope, then field: `docs/architecture.md`, "The optical chain").
//!
//! # File layout
//!
//! A binary-table HDU `TELESCOPE`, one row per band: `WAVELENGTH_UM`, `N`, `K` (the metal's
//! tabulated index there), `FACTOR` (on `n, k`), `THICKNESS_NM` (alumina over-layer),
//! `OFFSET_DEG`, `Q0`, `U0` (fractions). Its header: `HIERARCH IP TEL MODEL` (`wiersema` /
//! `oxide`), `TEL JOINT`, `TEL BAND<k>` (band names, 1-based), `TEL NPAR`, `TEL PAR<k> NAME`,
//! `TEL PAR<k>`, `TEL PAR<k> ERR` (angles in rad as fitted), `TEL COV <i> <j>` (upper triangle,
//! 0-based, scaled as `TEL ERR SCALING` says, by `TEL ERR FACTOR`), `TEL CHI2`, `TEL DOF`,
//! `TEL CHI2 DOF`, `TEL RMS Q`, `TEL RMS U`, `TEL N USED`, `TEL METAL`, `TEL ROTATOR` (1: the
//! standards carried rotator angles, so `offset` is the angle zero at rotator 0; 0 or absent:
//! `offset` holds whatever fixed rotator angle the standards were taken at).
//!
//! The HDU sits beside a field model (after the field calibration's HDUs, written by
//! [`save_with_field`] through [`Calibration::save_with`]) or alone (a file whose primary HDU
//! says `HIERARCH IP MODEL = 'TELESCOPE'`, [`save_alone`]). [`crate::files::calibration::load`] reads either;
//! [`Calibration::load`] refuses a telescope-only file by name.
//!
//! # The chain and its inversion
//!
//! Light meets the telescope first, then the instrument: the measured normalized Stokes
//! parameters are `m = M_I(x, y) [T(track) S_sky]` with `T` the telescope model of the band
//! averaged over the exposure's parallactic-angle track ([`crate::telescope::Track`]) and
//! `M_I` the field's partial polarizer (`eq:instpol`). [`correct_chain`] undoes them in reverse:
//! the field first ([`Corrector`], with its covariance), then the telescope
//! ([`TelescopeFit::correct_cov`], with the measurement-plus-field covariance and the telescope
//! parameters' covariance). With a field model the telescope's constant `(q0, u0)` is left out
//! (the field model is the instrument's own polarization; counting both would remove it twice).
//!
//! # One frame: the sky frame
//!
//! Both models live in the sky frame, the frame in which chi has the instrument's HWP zero
//! angle added (`crate::correction::correct` module docs): the field because the sky-field solution is
//! made there (`crate::models::pipeline`), the telescope because its standards' `q, u` are there (what
//! `instpol photometry`, `catalog` and `zero-angle` report, and what published standards are).
//! So the chain first brings the measurement into that frame from the frame it says it is in
//! ([`mueller::Frame`]: a Stokes map or a star measured by `validate` is at the plate and needs
//! the whole zero angle; a catalog of `instpol catalog` already carries it), with the
//! covariance turned alike; the field corrector it is given lives in the same frame, so it
//! turns nothing more.
//! The exposures' demodulations take each plate angle in that frame too
//! ([`telescope_exposures`]). Without this turn a plate-frame measurement would be corrected
//! by models turned by the zero angle against it, off by about `2 sin(z) P` (9e-3 for the
//! 3.6 % an unpolarized star shows through the test's M3 with `z` = 7 deg, an estimate); with
//! it such a star comes back to 1e-16
//! (`crates/cli/tests/it/telescope_frames.rs`, `the_chain_undoes_the_telescope_through_a_hwp_zero_angle`).

use crate::correction::correct::{Corrected, Corrector, Measurement};
use crate::files::calfile::Provenance;
use crate::files::keys::{fits_err, KeyReader, KeyWriter};
use crate::models::model::{FieldModel, InstPol};
use crate::models::radial::ErrorScaling;
use crate::telescope::{BandModel, ModelKind, Param, Seen, TelescopeFit, Track};
use crate::{Calibration, Error, Result};
use fitsio::tables::{ColumnDataType, ColumnDescription};
use fitsio::FitsFile;
use mueller::C64;
use std::path::Path;

/// The `HIERARCH IP MODEL` of this kind of file.
pub use crate::files::keys::TELESCOPE_MODEL as MODEL_KIND;
/// The HDU name.
pub const HDU: &str = "TELESCOPE";

const COLS: [&str; 8] = ["WAVELENGTH_UM", "N", "K", "FACTOR", "THICKNESS_NM", "OFFSET_DEG", "Q0", "U0"];

/// Write the `TELESCOPE` HDU of `fit` (fitted with the metal `metal`) into an open file.
pub fn write_hdu(f: &mut FitsFile, path: &Path, fit: &TelescopeFit, metal: &str) -> Result<()> {
    let e = |doing: &str| fits_err(path, doing);
    let mut descs = vec![];
    for c in COLS {
        descs.push(
            ColumnDescription::new(c).with_type(ColumnDataType::Double).create().map_err(e("describing TELESCOPE"))?,
        );
    }
    let h = f.create_table(HDU, &descs).map_err(e("creating table TELESCOPE"))?;
    let b = &fit.bands;
    let col = |g: &dyn Fn(&BandModel) -> f64| b.iter().map(|(_, m)| g(m)).collect::<Vec<f64>>();
    let columns: [(&str, Vec<f64>); 8] = [
        ("WAVELENGTH_UM", col(&|m| m.wavelength_um)),
        ("N", col(&|m| m.index.re)),
        ("K", col(&|m| m.index.im)),
        ("FACTOR", col(&|m| m.factor)),
        ("THICKNESS_NM", col(&|m| m.thickness_nm)),
        ("OFFSET_DEG", col(&|m| m.offset.to_degrees())),
        ("Q0", col(&|m| m.q0)),
        ("U0", col(&|m| m.u0)),
    ];
    for (name, v) in &columns {
        h.write_col(f, *name, v).map_err(e(&format!("writing TELESCOPE column {name}")))?;
    }
    let mut w = KeyWriter { f, hdu: &h, path };
    w.str("TEL MODEL", fit.model.name())?;
    w.int("TEL JOINT", (b.len() > 1) as i64)?;
    w.str("TEL METAL", metal)?;
    w.int("TEL NBAND", b.len() as i64)?;
    for (k, (name, _)) in b.iter().enumerate() {
        w.str(&format!("TEL BAND{}", k + 1), name)?;
    }
    w.int("TEL NPAR", fit.params.len() as i64)?;
    for (k, p) in fit.params.iter().enumerate() {
        w.str(&format!("TEL PAR{} NAME", k + 1), &p.name)?;
        w.real(&format!("TEL PAR{}", k + 1), p.value)?;
        w.real(&format!("TEL PAR{} ERR", k + 1), p.sigma)?;
    }
    for i in 0..fit.params.len() {
        for j in i..fit.params.len() {
            w.real(&format!("TEL COV {i} {j}"), fit.covariance[i][j])?;
        }
    }
    w.str("TEL ERR SCALING", fit.error_scaling.name())?;
    w.real("TEL ERR FACTOR", fit.error_factor)?;
    w.real("TEL CHI2", fit.chi2)?;
    w.int("TEL DOF", fit.dof as i64)?;
    w.real("TEL CHI2 DOF", fit.chi2_reduced)?;
    w.real("TEL RMS Q", fit.rms_q)?;
    w.real("TEL RMS U", fit.rms_u)?;
    w.int("TEL N USED", fit.n_used() as i64)?;
    w.int("TEL ROTATOR", fit.with_rotator as i64)?;
    Ok(())
}

/// A band or model name as part of a file name: every character but ASCII letters, digits and
/// dots made `_`, so that a name cannot reach another folder.
pub fn safe_name(s: &str) -> String {
    s.chars().map(|c| if c.is_ascii_alphanumeric() || c == '.' { c } else { '_' }).collect()
}

/// The file name of band `band`'s telescope model in a folder of them (`fit-standards
/// --output-dir`): `telescope_<band>.fits` ([`safe_name`]).
pub fn band_file_name(band: &str) -> String {
    format!("telescope_{}.fits", safe_name(band))
}

/// Write a calibration file holding only the telescope model of `instrument` (atomically:
/// a temporary file beside `path`, renamed when complete), with what it is (`product`: the
/// instrument file's hash, the plate, the detector, the inputs' hashes) when known.
pub fn save_alone(
    path: &Path,
    instrument: &str,
    fit: &TelescopeFit,
    metal: &str,
    inputs: &[String],
    product: Option<&skyfield::provenance::Product>,
) -> Result<()> {
    crate::files::keys::write_fits_atomically(path, |f| {
        let hdu = f.primary_hdu().map_err(fits_err(path, "opening the primary HDU"))?;
        let mut w = KeyWriter { f, hdu: &hdu, path };
        w.int("FORMAT VERSION", crate::files::keys::FORMAT_VERSION)?;
        w.str("INSTRUMENT", instrument)?;
        w.str("MODEL", MODEL_KIND)?;
        let pv = Provenance { product: product.cloned(), ..Provenance::now("instpol fit-standards", inputs.to_vec()) };
        pv.write_common(&mut w)?;
        w.int("NINPUT", inputs.len() as i64)?;
        for (k, name) in inputs.iter().enumerate() {
            w.str(&format!("INPUT{}", k + 1), name)?;
        }
        write_hdu(f, path, fit, metal)
    })
}

/// Why a field calibration may not go into one file beside a telescope model
/// ([`check_field_beside`]); each face names the file and its option.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FieldBesideError {
    /// The field calibration is of another instrument, plate or detector than the standards'
    /// (the one compatibility check, the filter apart).
    #[error("{0}: the field and the telescope model must be of one instrument")]
    Mismatch(crate::correction::setup::Mismatch),
    /// The field calibration's filter is no band of the telescope model.
    #[error(
        "it is for filter {filter}, but the telescope model has band(s) {bands} (name the bands by a 'filter' column)"
    )]
    Band { filter: String, bands: String },
}

/// Whether the field calibration `field` goes into one file beside the telescope model `fit`
/// of standards measured with `inst` (`None`: no instrument said, nothing to compare): one
/// instrument, plate and detector by the one check
/// ([`crate::correction::setup::check_same_instrument`]), and its filter one of the model's
/// bands. `Ok(Some(words))`: a field that names no instrument, taken unchecked, said.
pub fn check_field_beside(
    field: &Calibration,
    fit: &TelescopeFit,
    inst: Option<&instrument::Instrument>,
) -> std::result::Result<Option<String>, FieldBesideError> {
    use crate::correction::setup::{check_same_instrument, is_known, Setup};
    let mut said = None;
    if let Some(inst) = inst {
        let theirs = Setup::named(&field.instrument, &field.filter).with_product(field.provenance.product.as_ref());
        if is_known(field.instrument.trim()) {
            check_same_instrument(&Setup::of_instrument(inst, ""), &theirs).map_err(FieldBesideError::Mismatch)?;
        } else {
            said = Some(format!(
                "it does not say its instrument ('{}'): taken as {} unchecked",
                field.instrument.trim(),
                inst.name
            ));
        }
    }
    if fit.band(&field.filter).is_none() {
        let bands = fit.bands.iter().map(|b| b.0.as_str()).collect::<Vec<_>>().join(", ");
        return Err(FieldBesideError::Band { filter: field.filter.clone(), bands });
    }
    Ok(said)
}

/// Write the field calibration `cal` with the telescope model beside it.
pub fn save_with_field(path: &Path, cal: &Calibration, fit: &TelescopeFit, metal: &str) -> Result<()> {
    cal.save_with(path, |f, p| write_hdu(f, p, fit, metal))
}

/// Read the `TELESCOPE` HDU of a file, `None` when it has none.
pub fn read_hdu(path: &Path) -> Result<Option<TelescopeFit>> {
    let e = |doing: &str| fits_err(path, doing);
    let mut f = FitsFile::open(path).map_err(e("opening"))?;
    let Ok(h) = f.hdu(HDU) else { return Ok(None) };
    let bad = |what: String| Error::BadFile { path: path.into(), what: format!("{HDU} HDU: {what}") };
    let nrows = match &h.info {
        fitsio::hdu::HduInfo::TableInfo { num_rows, .. } => *num_rows,
        _ => return Err(bad("is not a table".into())),
    };
    let mut cols = Vec::new();
    for c in COLS {
        cols.push(h.read_col::<f64>(&mut f, c).map_err(e(&format!("reading {HDU} column {c}")))?);
    }
    let mut r = KeyReader { f: &mut f, hdu: &h, path };
    let model = match r.str("TEL MODEL")?.as_str() {
        "wiersema" => ModelKind::Wiersema,
        "oxide" => ModelKind::Oxide,
        other => return Err(bad(format!("keyword HIERARCH IP TEL MODEL = '{other}': not wiersema or oxide"))),
    };
    let nband = r.int("TEL NBAND")?;
    if nband < 1 || nband as usize != nrows {
        return Err(bad(format!("HIERARCH IP TEL NBAND = {nband} but the table has {nrows} rows")));
    }
    let mut bands = Vec::new();
    for k in 0..nrows {
        let v: Vec<f64> = cols.iter().map(|c| c[k]).collect();
        let name = r.str(&format!("TEL BAND{}", k + 1))?;
        let ok = v.iter().all(|x| x.is_finite())
            && v[0] > 0.0
            && v[1] > 0.0
            && v[2] >= 0.0
            && v[3] > 0.0
            && v[4] >= 0.0
            && v[6].abs() < 1.0
            && v[7].abs() < 1.0;
        if !ok {
            return Err(bad(format!(
                "row {} (band {name}): {} = {:?}: need finite values, wavelength, n, factor > 0, k, thickness >= 0, |q0|, |u0| < 1",
                k + 1,
                COLS.join(", "),
                v
            )));
        }
        bands.push((
            name,
            BandModel {
                wavelength_um: v[0],
                index: C64::new(v[1], v[2]),
                factor: v[3],
                thickness_nm: v[4],
                offset: v[5].to_radians(),
                q0: v[6],
                u0: v[7],
            },
        ));
    }
    let npar = r.int("TEL NPAR")?;
    let per_band = match model {
        ModelKind::Wiersema => 1,
        ModelKind::Oxide => 3,
    };
    if npar < 1 || npar as usize != 1 + per_band * nrows {
        return Err(bad(format!(
            "HIERARCH IP TEL NPAR = {npar}: the {} model of {nrows} band(s) has {}",
            model.name(),
            1 + per_band * nrows
        )));
    }
    let np = npar as usize;
    let mut params = Vec::new();
    for k in 1..=np {
        params.push(Param {
            name: r.str(&format!("TEL PAR{k} NAME"))?,
            value: r.real(&format!("TEL PAR{k}"))?,
            sigma: r.real(&format!("TEL PAR{k} ERR"))?,
        });
    }
    let mut cov = vec![vec![0.0; np]; np];
    #[allow(clippy::needless_range_loop)] // symmetric fill by keyword indices
    for i in 0..np {
        for j in i..np {
            let v = r.real(&format!("TEL COV {i} {j}"))?;
            cov[i][j] = v;
            cov[j][i] = v;
        }
    }
    for i in 0..np {
        if !(cov[i][i].is_finite() && cov[i][i] >= 0.0) {
            return Err(bad(format!("keyword HIERARCH IP TEL COV {i} {i} = {} is not a variance", cov[i][i])));
        }
        for j in 0..i {
            if !cov[j][i].is_finite() || cov[j][i] * cov[j][i] > cov[i][i] * cov[j][j] * (1.0 + 1e-9) {
                return Err(bad(format!(
                    "keyword HIERARCH IP TEL COV {j} {i} = {} is not a covariance of variances {} and {} (|correlation| > 1)",
                    cov[j][i], cov[j][j], cov[i][i]
                )));
            }
        }
    }
    let error_scaling = r
        .opt_str("TEL ERR SCALING")
        .map(|s| s.parse::<ErrorScaling>())
        .transpose()
        .map_err(|err| bad(format!("keyword HIERARCH IP TEL ERR SCALING: {err}")))?
        .unwrap_or(ErrorScaling::Conservative);
    Ok(Some(TelescopeFit {
        model,
        bands,
        params,
        covariance: cov,
        chi2: r.opt_real("TEL CHI2").unwrap_or(f64::NAN),
        dof: r.opt_int("TEL DOF").unwrap_or(0).max(0) as usize,
        chi2_reduced: r.opt_real("TEL CHI2 DOF").unwrap_or(f64::NAN),
        error_scaling,
        error_factor: r.opt_real("TEL ERR FACTOR").unwrap_or(f64::NAN),
        rms_q: r.opt_real("TEL RMS Q").unwrap_or(f64::NAN),
        rms_u: r.opt_real("TEL RMS U").unwrap_or(f64::NAN),
        with_rotator: r.opt_int("TEL ROTATOR").unwrap_or(0) != 0,
        minima: Vec::new(),
        points: Vec::new(),
    }))
}

/// One measurement corrected through the chain.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChainCorrected {
    /// The sky's polarization with its covariance; `inst` is the field's part (zero without a
    /// field model).
    pub corrected: Corrected,
    /// What the telescope alone makes of an unpolarized star over this track (instrument
    /// frame, without `q0, u0` when a field model is given).
    pub q_tel: f64,
    pub u_tel: f64,
}

impl ChainCorrected {
    /// The correction with `inst` holding the field's and the telescope's instrumental
    /// polarization together (their sum: first order), as catalogs and maps report it.
    pub fn with_telescope_in_inst(&self) -> Corrected {
        let mut c = self.corrected;
        c.inst.q += self.q_tel;
        c.inst.u += self.u_tel;
        c
    }
}

/// Correct `m` for the field (when `field` is given, its corrector in the same sky frame) and
/// then the telescope of `band` over `track`, after bringing `m` from its frame into the sky
/// frame of the HWP zero angle `zero_angle_deg` (`None`: `m`'s own frame; see the module docs
/// for the frame, the order and what each step uses).
pub fn correct_chain<M: FieldModel + ?Sized>(
    field: Option<&Corrector<M>>,
    tel: &TelescopeFit,
    band: &str,
    m: &Measurement,
    track: Track,
    zero_angle_deg: Option<f64>,
) -> Result<ChainCorrected> {
    correct_chain_seen(field, tel, band, m, Seen::Track(track), zero_angle_deg)
}

/// [`correct_chain`] for a measurement that saw the telescope as `seen` says; `q_tel, u_tel`
/// are then what the telescope makes of an unpolarized sky as these data saw it (sky frame).
pub fn correct_chain_seen<M: FieldModel + ?Sized>(
    field: Option<&Corrector<M>>,
    tel: &TelescopeFit,
    band: &str,
    m: &Measurement,
    seen: Seen<'_>,
    zero_angle_deg: Option<f64>,
) -> Result<ChainCorrected> {
    if let Some(c) = field.filter(|c| zero_angle_deg != Some(c.options().zero_angle_deg)) {
        // The field and the telescope are undone in one sky frame (module docs).
        return Err(Error::Input(format!(
            "the chain's field model lives in the sky frame of HWP zero angle {} deg, the chain in {}",
            c.options().zero_angle_deg,
            zero_angle_deg.map_or("the data's own frame".to_string(), |z| format!("that of {z} deg"))
        )));
    }
    let tracks: Vec<Track> = match seen {
        Seen::Track(t) => vec![t],
        Seen::Exposures { whole, exposures } => {
            std::iter::once(whole).chain(exposures.iter().map(|e| e.track)).collect()
        }
        Seen::Prepared(_) => vec![],
    };
    for t in &tracks {
        for (what, v) in [("parallactic angle (start)", t.start), ("parallactic angle (end)", t.end)] {
            if !v.is_finite() {
                return Err(Error::Input(format!("{what} = {v} is not a finite number")));
            }
        }
    }
    // Checked as given (turning would hide a negative error), then brought into the sky frame.
    // The errors are held as variances, a negative error as a negative variance
    // (`Qu::from_sigmas`): the error's own value is given back in the message.
    let sigma = |v: f64| if v < 0.0 { -(-v).sqrt() } else { v.sqrt() };
    for (what, v) in [("q", m.qu.q), ("u", m.qu.u), ("sigma_q", sigma(m.qu.var_q)), ("sigma_u", sigma(m.qu.var_u))] {
        if !v.is_finite() || (what.starts_with("sigma") && v < 0.0) {
            return Err(Error::Input(format!("{what} = {v} is not a finite number (>= 0 for errors)")));
        }
    }
    if let Some(z) = zero_angle_deg.filter(|z| !z.is_finite()) {
        return Err(Error::Input(format!("HWP zero angle {z} deg is not a finite number")));
    }
    // Without a field's zero angle the data are taken in their own frame, as the instrument
    // saw them (a celestial row turned back by its position angle).
    let m = &zero_angle_deg.map_or(m.in_instrument(), |z| m.in_sky(z));
    let (q1, u1, cov, inst, extrapolated) = match field {
        Some(c) => {
            let r = c.correct(m).map_err(|e| Error::Input(e.to_string()))?;
            (r.q0, r.u0, [r.var_q0, r.var_u0, r.cov_qu0], r.inst, r.extrapolated)
        }
        None => (m.qu.q, m.qu.u, [m.qu.var_q, m.qu.var_u, m.qu.cov_qu], InstPol::default(), false),
    };
    let constant = field.is_none();
    let [q0, u0, vq, vu, cv] = tel.correct_cov_seen(band, q1, u1, cov, seen, constant)?;
    let b = tel.band(band).ok_or_else(|| Error::Input(format!("band '{band}' was not fitted")))?;
    let model_err = |e: mueller::Error| Error::FitFailed(format!("telescope model: {e}"));
    let (mut q_tel, mut u_tel) = match seen {
        Seen::Track(track) => {
            let mt = b.matrix_track(track).map_err(model_err)?;
            (mt[(1, 0)] / mt[(0, 0)], mt[(2, 0)] / mt[(0, 0)])
        }
        Seen::Exposures { exposures, .. } => b.demodulation(exposures).map_err(model_err)?.forward(0.0, 0.0),
        Seen::Prepared(p) => p.base().forward(0.0, 0.0),
    };
    if constant {
        q_tel += b.q0;
        u_tel += b.u0;
    }
    Ok(ChainCorrected {
        corrected: Corrected::of(mueller::Qu::new(q0, u0, vq, vu, cv), inst, extrapolated),
        q_tel,
        u_tel,
    })
}

/// One frame's telescope angles as its header gives them (deg, the header's own sense).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaderAngles {
    pub parang_start_deg: f64,
    pub parang_end_deg: Option<f64>,
    pub rotator_deg: Option<f64>,
}

/// Read the parallactic angle at the start (and end, when the instrument names an end
/// keyword) and the rotator angle (when it names one) from a frame's header, under the
/// keywords of the instrument's `[telescope]` section: the primary header, else the first
/// extension's. Errors name the frame and the missing or unreadable keyword.
pub fn header_angles(path: &Path, tel: &instrument::Telescope) -> Result<HeaderAngles> {
    if tel.parang_start_keyword.is_empty() {
        return Err(Error::Input(format!(
            "{}: the instrument's [telescope] section names no parang_start_keyword: give the angle by hand",
            path.display()
        )));
    }
    let mut f = FitsFile::open(path).map_err(fits_err(path, "opening the frame"))?;
    let mut read = |key: &str| -> Result<Option<f64>> {
        let mut value = None;
        for i in 0..2usize {
            let Ok(h) = f.hdu(i) else { break };
            if let Ok(s) = skyfield::fits::read_key_str(&mut f, &h, key) {
                value = Some(s);
                break;
            }
        }
        let Some(s) = value else { return Ok(None) };
        let v: f64 = s.trim().trim_matches('\'').trim().replace(['D', 'd'], "E").parse().map_err(|_| {
            Error::BadFile { path: path.into(), what: format!("keyword {key} = '{s}' is not a number (deg)") }
        })?;
        if !v.is_finite() {
            return Err(Error::BadFile { path: path.into(), what: format!("keyword {key} = {v} is not finite") });
        }
        Ok(Some(v))
    };
    let start = read(&tel.parang_start_keyword)?.ok_or_else(|| Error::BadFile {
        path: path.into(),
        what: format!(
            "no keyword {} (the parallactic angle at the exposure's start, named by the instrument's [telescope] parang_start_keyword)",
            tel.parang_start_keyword
        ),
    })?;
    let end = if tel.parang_end_keyword.is_empty() { None } else { read(&tel.parang_end_keyword)? };
    let rotator = if tel.rotator_keyword.is_empty() { None } else { read(&tel.rotator_keyword)? };
    Ok(HeaderAngles { parang_start_deg: start, parang_end_deg: end, rotator_deg: rotator })
}

/// The [`crate::telescope::StandardRecord`] of a standard measured in `frames` through
/// `filter` (the instrument's filter name): the filter's wavelength, the star's catalogued
/// polarization in that band when it is a polarized standard, and the middle of the frames'
/// parallactic-angle track ([`frames_track`]: the demodulated set's `(q, u)` averages the
/// telescope's turn over the track, which its middle represents to second order in the
/// turn) with their rotator angle, when the instrument's `[telescope]` names the keywords.
pub fn standard_record(
    frames: &[std::path::PathBuf],
    inst: &instrument::Instrument,
    filter: &str,
    star: Option<&crate::standards::Star>,
) -> Result<crate::telescope::StandardRecord> {
    let tel = inst.telescope.as_ref().filter(|t| !t.parang_start_keyword.is_empty());
    let track = tel.map(|t| frames_track(frames, t)).transpose()?;
    let (p_true, chi_true_deg) = match star.filter(|s| s.kind == crate::standards::Kind::Polarized) {
        Some(s) => {
            let b = s.band(filter).map_err(|e| Error::Input(e.to_string()))?;
            (Some(b.p_percent / 100.0), b.chi_deg)
        }
        None => (None, None),
    };
    Ok(crate::telescope::StandardRecord {
        filter: filter.to_string(),
        wavelength_um: inst.filter(filter).ok().map(|f| f.lambda_eff_nm / 1000.0).filter(|w| w.is_finite() && *w > 0.0),
        star: star.map(|s| s.name.clone()),
        p_true,
        chi_true_deg,
        parallactic_deg: track.map(|t| (0.5 * (t.start + t.end)).to_degrees()),
        rotator_deg: track.map(|t| t.rotator.to_degrees()),
    })
}

/// The parallactic-angle track of a set of frames (the exposures of one measurement, e.g. the
/// HWP angles of a polarimetric set) from their headers ([`header_angles`]), the instrument's
/// senses applied: the span of every frame's start and end angle (each unwrapped to within
/// half a turn of the first frame's start, so a set may cross +-180 deg), from the earliest
/// to the latest in the sense the angle moves (the sense of the frames' own start-to-end
/// motion, or of the frames' order when they give no end angle). For frames given in time
/// order that is the first frame's start to the last frame's end; frames in any other order
/// (sorted by HWP angle, say) give the same track, the headers holding no time to sort them
/// by. With the rotator angle of the first frame (frames whose rotator angles differ by more
/// than 0.5 deg are refused: they are not one measurement of the model). Counting the gaps
/// between exposures as exposing is second order in the set's turn.
pub fn frames_track(frames: &[std::path::PathBuf], tel: &instrument::Telescope) -> Result<Track> {
    let angles: Vec<HeaderAngles> = frames.iter().map(|p| header_angles(p, tel)).collect::<Result<_>>()?;
    track_of_headers(frames, &angles, tel)
}

/// [`frames_track`] from the frames' header angles already read (`angles[i]` of `frames[i]`).
fn track_of_headers(
    frames: &[std::path::PathBuf],
    angles: &[HeaderAngles],
    tel: &instrument::Telescope,
) -> Result<Track> {
    if frames.is_empty() {
        return Err(Error::Input("no frames for the parallactic angle".into()));
    }
    let (mut first, mut lo, mut hi) = (None::<f64>, f64::INFINITY, f64::NEG_INFINITY);
    // The sense of the motion: the frames' own start-to-end turns, else the order's.
    let (mut own, mut by_order, mut last_start) = (0.0, 0.0, None::<f64>);
    let mut rot = None::<(f64, &Path)>;
    for (p, h) in frames.iter().zip(angles) {
        let (s, e) = tel.parallactic_rad(h.parang_start_deg, h.parang_end_deg);
        let f0 = *first.get_or_insert(s);
        let unwrap = |a: f64| f0 + 2.0 * mueller::wrap_half_pi(0.5 * (a - f0));
        let s = unwrap(s);
        let e = e.map(unwrap);
        if let Some(e) = e {
            own += e - s;
        }
        if let Some(l) = last_start {
            by_order += s - l;
        }
        last_start = Some(s);
        for a in [Some(s), e].into_iter().flatten() {
            lo = lo.min(a);
            hi = hi.max(a);
        }
        let r = h.rotator_deg.map(|r| tel.rotator_sense as f64 * r.to_radians()).unwrap_or(0.0);
        match rot {
            None => rot = Some((r, p.as_path())),
            Some((r0, p0)) if mueller::wrap_half_pi(0.5 * (r - r0)).abs() * 2.0 > 0.5f64.to_radians() => {
                return Err(Error::Input(format!(
                    "{}: rotator angle {:.3} deg ({}) differs from {:.3} deg in {}: the frames are not one measurement",
                    p.display(),
                    r.to_degrees(),
                    tel.rotator_keyword,
                    r0.to_degrees(),
                    p0.display()
                )))
            }
            _ => {}
        }
    }
    let rising = if own != 0.0 { own > 0.0 } else { by_order >= 0.0 };
    let (start, end) = if rising { (lo, hi) } else { (hi, lo) };
    Ok(Track { start, end, rotator: rot.map(|r| r.0).unwrap_or(0.0) })
}

/// The exposures' telescope angles from their headers (`exposures`: each one's file and HWP
/// angle in deg, as [`skyfield::reduce::Reduced::exposures`] or
/// [`skyfield::reduce::FrameSet::exposures`] list them, angle by angle), each header read
/// once: the set's track ([`frames_track`], with the rotator angle) and each exposure's own
/// track. Both in the order of `frames` (the files as given, taken to be the order they were
/// observed in: the track's sense comes from it when the headers give no end angles).
/// Errors name the frame and the keyword.
pub fn exposure_tracks(
    exposures: &[(std::path::PathBuf, f64)],
    frames: &[std::path::PathBuf],
    tel: &instrument::Telescope,
) -> Result<(Track, Vec<skyfield::ExposureTrack>)> {
    let mut exposures = exposures.to_vec();
    exposures.sort_by_key(|(p, _)| frames.iter().position(|f| f == p).unwrap_or(usize::MAX));
    let files: Vec<std::path::PathBuf> = exposures.iter().map(|e| e.0.clone()).collect();
    let angles = files.iter().map(|p| header_angles(p, tel)).collect::<Result<Vec<_>>>()?;
    let track = track_of_headers(&files, &angles, tel)?;
    let each = exposures
        .iter()
        .zip(&angles)
        .map(|((_, hwp), h)| {
            let (s, e) = tel.parallactic_rad(h.parang_start_deg, h.parang_end_deg);
            skyfield::ExposureTrack { hwp_deg: *hwp, start: s, end: e.unwrap_or(s) }
        })
        .collect();
    Ok((track, each))
}

/// The exposures' telescope angles as a map or a catalog table records them
/// ([`skyfield::RecordedAngles`]: the set's track, the rotator angle when the instrument names
/// its keyword, each exposure's own track), when the instrument names their header keywords
/// and every exposure's header has them (`exposures` and `frames` as for [`exposure_tracks`]);
/// `None` otherwise, silently: most instruments and uses need no telescope model.
pub fn recorded_angles(
    exposures: &[(std::path::PathBuf, f64)],
    frames: &[std::path::PathBuf],
    inst: &instrument::Instrument,
) -> Option<skyfield::RecordedAngles> {
    let t = inst.telescope.as_ref().filter(|t| !t.parang_start_keyword.is_empty())?;
    let (track, each) = exposure_tracks(exposures, frames, t).ok()?;
    Some(skyfield::RecordedAngles {
        parallactic_rad: Some((track.start, track.end)),
        rotator_rad: (!t.rotator_keyword.is_empty()).then_some(track.rotator),
        exposure_tracks: each,
    })
}

/// The exposures' demodulations for `tel`'s `band`, built once for every measurement that
/// shares them ([`TelescopeFit::prepare_exposures`] of [`telescope_exposures`], over the set's
/// `track` and with its rotator; `zero_angle`: the HWP zero angle (rad) of the plate the
/// exposures were taken through): `None` when no exposures are listed (the data are then
/// undone over `track`).
pub fn prepare_recorded(
    tel: &TelescopeFit,
    band: &str,
    track: Track,
    exposures: &[skyfield::ExposureTrack],
    zero_angle: f64,
) -> Result<Option<crate::telescope::PreparedExposures>> {
    if exposures.is_empty() {
        return Ok(None);
    }
    tel.prepare_exposures(band, track, &telescope_exposures(exposures, track.rotator, zero_angle)).map(Some)
}

/// The exposures of `tracks` as the telescope model takes them (HWP angle in rad, each
/// exposure's parallactic track with the set's `rotator`), in the sky frame of the chain
/// (module docs): a plate of zero angle `zero_angle` (rad) read at `theta` modulates the sky
/// frame's `q, u` as `cos, sin (4 theta + 2 zero_angle)`, so each exposure's plate angle is
/// `theta + zero_angle / 2` there. (With the telescope's polarization changing from exposure
/// to exposure this is not the same as turning the demodulated result: 9e-4 on an
/// unpolarized star through the meridian near the zenith, 7 deg zero angle.)
pub fn telescope_exposures(
    tracks: &[skyfield::ExposureTrack],
    rotator: f64,
    zero_angle: f64,
) -> Vec<mueller::telescope::Exposure> {
    tracks
        .iter()
        .map(|x| mueller::telescope::Exposure {
            hwp: x.hwp_deg.to_radians() + 0.5 * zero_angle,
            track: Track::new(x.start, Some(x.end)).with_rotator(rotator),
        })
        .collect()
}

/// Record in a reduced map the exposures' telescope angles ([`recorded_angles`]; `exposures`:
/// each one's file and HWP angle, [`skyfield::reduce::Reduced::exposures`]; `frames` as
/// given, for their order): the set's track (`PARANG1`, `PARANG2`), the rotator angle, and
/// each exposure's own track ([`skyfield::StokesMap::exposure_tracks`]), which `correct` uses
/// to undo the telescope as the exposures saw it. Frames without the angles leave the map
/// without them, silently. The one recording of `instpol reduce` and the Python package's
/// `reduce`.
pub fn record_telescope_angles(
    map: &mut skyfield::StokesMap,
    exposures: &[(std::path::PathBuf, f64)],
    frames: &[std::path::PathBuf],
    inst: &instrument::Instrument,
) {
    let Some(r) = recorded_angles(exposures, frames, inst) else { return };
    map.parallactic_rad = r.parallactic_rad;
    map.rotator_rad = r.rotator_rad;
    map.exposure_tracks = r.exposure_tracks;
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_band_name_cannot_leave_the_folder() {
        assert_eq!(super::band_file_name("V"), "telescope_V.fits");
        assert_eq!(super::band_file_name("../../etc/x y"), "telescope_.._.._etc_x_y.fits");
        assert!(!super::band_file_name("a/b\\c").contains(['/', '\\']));
    }
}
