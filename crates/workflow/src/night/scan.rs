//! What each file of a night is, from its headers alone, and the plan of work that makes the
//! night's products from them.
//!
//! Rules, in the order they are applied:
//!
//! 1. **A file**: its cards ([`super::header`]) name the instrument (`[headers]
//!    instrument_keyword`), its role (the role string, [`instrument::Headers::role_of`]), its
//!    chip (the `[format]` chips' match keyword), filter, HWP angle, exposure time, binning,
//!    exposure number, target, pointing and start (MJD). A file that is not FITS, truncated,
//!    of another instrument, of a role the instrument file does not know, or without a keyword
//!    its role needs is left out with that reason.
//! 2. **An exposure**: the chip files sharing the `[format] exposure_keywords` values (one
//!    file per exposure when the format has no chips); an exposure lacking a chip is left out
//!    naming it.
//! 3. **A night**: exposures are sorted by start; a night runs from noon to noon UT
//!    (`floor(MJD - 0.5)`, assumed: ESO's Chilean nights fall within it).
//! 4. **Masters**: one master bias per night and binning, one master flat per night, binning
//!    and filter (bias-subtracted with the bias of its night and binning).
//! 5. **Sets**: polarimetric exposures following each other in time with the same role,
//!    target, filter and binning, pointing within `pointing_tol_arcsec` of the set's first and
//!    started within `max_gap_min` of the previous exposure. A set must hold the optimal set
//!    of HWP angles that its angles belong to (`skyfield::reduce::plate_set_gap`, the
//!    reduction's rule) the same number of times (complete repeated cycles); exposures beyond
//!    the last complete cycle are left out, and a set that lacks an angle is left out naming
//!    the missing angles.
//! 6. **Standards**: a set whose target matches a star of the standards list
//!    (`fit::standards::Standards`) by name, or by position within `pointing_tol_arcsec` of
//!    the pointing, is that standard whatever its role string says; a set the headers call a
//!    standard but the list does not know is measured as a target, with a note.
//! 7. **Units**: every set is reduced to a map and (but a sky field) catalogued, each with the masters of its
//!    night, binning and filter (the nearest night's when its own has none); a set whose target
//!    is a sky field given with a known polarization is calibrated from its map
//!    (`instpol calibrate --map`); each polarized standard's set measures the HWP zero angle
//!    (`instpol zero-angle --json`) and each unpolarized standard's set the instrument's own
//!    polarization at the star (`instpol photometry --json`), the star's pixel from its
//!    catalogued position against the pointing (north up, east left and the pointing on the
//!    detector centre, assumed). Each unit of a set records the set's start, filter and
//!    standard, for `trend`.
//! 8. **A night's checks**: every standard's set with a calibration of its filter in the plan
//!    (the sky field's set nearest in time) is validated against it (`instpol validate
//!    --json`, a polarized standard by name, an unpolarized one as expected at zero; a check unit: a star off its prediction is a result, kept and reported, not a
//!    failure); the zero-angle measurements of a night and filter, two or more, are combined
//!    into one (`instpol zero-angle --measured ... --json`, the weighted mean on the circle),
//!    the value to put in the instrument file; behind a Nasmyth telescope whose headers give
//!    the parallactic angle, every standard (polarized ones too) is measured by photometry
//!    with its name, and the telescope model is fitted per night and filter to two or more of
//!    them (`instpol fit-standards --model wiersema --json`).

use super::header::{read_cards, Cards};
use super::plan::{LeftOut, Plan, Unit};
use super::Error;
use instrument::{Instrument, Role};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A sky field whose polarization is known (an empty field for `instpol calibrate`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SkyField {
    /// The target name as the headers write it (case and spaces aside).
    pub target: String,
    /// Sky polarization degree (percent, as `calibrate --sky-p`) and angle (deg).
    pub p_percent: f64,
    pub chi_deg: f64,
}

impl SkyField {
    /// A sky field from `TARGET:P_PERCENT:CHI_DEG` (the target may hold colons), checked.
    pub fn parse(spec: &str) -> Result<SkyField, Error> {
        let bad =
            || Error::Option(format!("sky field '{spec}': expected TARGET:P_PERCENT:CHI_DEG, e.g. EMPTY-V:1.74:-53.8"));
        let parts: Vec<&str> = spec.rsplitn(3, ':').collect();
        let [chi, p, target] = parts.as_slice() else { return Err(bad()) };
        let (Ok(p), Ok(chi)) = (p.trim().parse::<f64>(), chi.trim().parse::<f64>()) else { return Err(bad()) };
        let f = SkyField { target: target.trim().into(), p_percent: p, chi_deg: chi };
        f.check()?;
        Ok(f)
    }

    /// Sky fields from a table (CSV, ECSV, FITS or VOTable by the extension) with the columns
    /// `target`, `p_percent` and `chi_deg`, each row checked; errors name the file and row.
    pub fn read_table(path: &Path) -> Result<Vec<SkyField>, Error> {
        use skyfield::table::{Data, Table};
        let bad = |why: String| Error::Input { path: path.into(), why };
        let t = Table::read(path, None).map_err(|e| bad(e.to_string()))?;
        let col = |name: &str| {
            t.column(name)
                .ok_or_else(|| bad(format!("no column '{name}' (a sky-field table has target, p_percent, chi_deg)")))
        };
        // The one reading of a numeric column: declared units honoured (p_percent in %,
        // chi_deg in deg or rad, ...) or refused naming the column.
        let numbers = |name: &str| -> Result<Vec<f64>, Error> {
            if let Data::Str(_) = &col(name)?.data {
                return Err(bad(format!("column {name} must hold numbers")));
            }
            t.numbers(name, path).map_err(|e| bad(e.to_string()))
        };
        let (ps, chis) = (numbers("p_percent")?, numbers("chi_deg")?);
        let Data::Str(targets) = &col("target")?.data else {
            return Err(bad("column target must hold names".into()));
        };
        let mut out = Vec::new();
        for (i, ((target, &p_percent), &chi_deg)) in targets.iter().zip(&ps).zip(&chis).enumerate() {
            let f = SkyField { target: target.trim().into(), p_percent, chi_deg };
            f.check().map_err(|e| bad(format!("{}: {e}", t.row_label(i))))?;
            out.push(f);
        }
        if out.is_empty() {
            return Err(bad("no sky field in the table".into()));
        }
        Ok(out)
    }

    /// A named target, a degree of polarization in [0, 100) percent and a finite angle.
    pub fn check(&self) -> Result<(), Error> {
        if self.target.trim().is_empty() {
            return Err(Error::Option("a sky field without a target name".into()));
        }
        if !(self.p_percent.is_finite() && (0.0..100.0).contains(&self.p_percent) && self.chi_deg.is_finite()) {
            return Err(Error::Option(format!(
                "sky field {}: P {} % and chi {} deg: P must be a percentage in [0, 100), chi a finite angle",
                self.target, self.p_percent, self.chi_deg
            )));
        }
        Ok(())
    }
}

/// How to sort and plan.
#[derive(Debug, Clone)]
pub struct ScanOptions {
    /// The instrument as named on the command line (built-in name or file).
    pub instrument: String,
    /// Where the products go (masters/, maps/, catalogs/, calibrations/, zero-angle/, and
    /// the run's records in .instpol-run/).
    pub products: PathBuf,
    /// Sky fields with a known polarization, calibrated from their maps.
    pub sky_fields: Vec<SkyField>,
    /// A standard-star file; `None`: the built-in list.
    pub standards: Option<PathBuf>,
    /// Largest distance (arcsec) of a set's pointings, and of a standard from the pointing.
    pub pointing_tol_arcsec: f64,
    /// Largest gap (minutes) between the starts of two exposures of one set.
    pub max_gap_min: f64,
    /// Bin side (px) of the maps (`reduce --bin`, `calibrate --bin`).
    pub bin_px: usize,
    /// Expected FWHM (px) of the stars (`catalog --fwhm`).
    pub fwhm_px: f64,
    /// Aperture radius (px) of the catalogs and the standards (`--aperture`).
    pub aperture_px: f64,
}

impl ScanOptions {
    pub fn new(instrument: &str, products: &Path) -> Self {
        ScanOptions {
            instrument: instrument.into(),
            products: products.into(),
            sky_fields: vec![],
            standards: None,
            pointing_tol_arcsec: 60.0,
            max_gap_min: 60.0,
            bin_px: 30,
            fwhm_px: 4.0,
            aperture_px: 8.0,
        }
    }
}

/// One usable file, as its headers describe it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileInfo {
    pub path: PathBuf,
    pub role: Role,
    /// The chip (`[format]` chip name) this file holds, for a chip instrument.
    pub chip: Option<String>,
    /// The instrument's name of the filter.
    pub filter: Option<String>,
    pub hwp_deg: Option<f64>,
    /// The plate angle (deg) a turning plate swept during the exposure (`hwp_deg` its range's
    /// middle); 0 for a fixed plate.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub hwp_sweep_deg: f64,
    pub exptime_s: Option<f64>,
    pub binning: [u32; 2],
    /// The `exposure_keywords` values, joined by `/` (empty: the file is its own exposure).
    pub exposure: String,
    pub target: String,
    pub ra_deg: Option<f64>,
    pub dec_deg: Option<f64>,
    pub mjd: f64,
}

/// The sorting of a folder: every usable file, and the left-out ones with the reason.
#[derive(Debug, Clone, Default)]
pub struct Sorted {
    pub files: Vec<FileInfo>,
    pub left_out: Vec<LeftOut>,
}

/// Every `.fits`/`.fit`/`.fts` file (any case, `.gz` not) under `dirs` (recursively), and any
/// file given directly, sorted by path. A folder that holds none is an error naming it. A
/// folder is entered once, however many links lead to it: a symlink loop (`raw/loop -> ..`)
/// ends there, and the second value names each folder not entered again.
pub fn list_files(dirs: &[PathBuf]) -> Result<(Vec<PathBuf>, Vec<LeftOut>), Error> {
    let mut out = Vec::new();
    let mut again = Vec::new();
    let mut entered: std::collections::HashMap<(u64, u64), PathBuf> = std::collections::HashMap::new();
    for d in dirs {
        if d.is_file() {
            out.push(d.clone());
            continue;
        }
        let before = out.len();
        let mut stack = vec![d.clone()];
        let mut others = 0usize;
        while let Some(dir) = stack.pop() {
            if let Some(id) = skyfield::durable::file_id(&dir) {
                if let Some(first) = entered.get(&id) {
                    let why = format!(
                        "the folder {} again (a symlink loop or a second link to it): its files are read once",
                        first.display()
                    );
                    again.push(LeftOut { files: vec![dir], why });
                    continue;
                }
                entered.insert(id, dir.clone());
            }
            let rd = std::fs::read_dir(&dir).map_err(|e| Error::Input { path: dir.clone(), why: e.to_string() })?;
            for e in rd {
                let e = e.map_err(|e| Error::Input { path: dir.clone(), why: e.to_string() })?;
                let p = e.path();
                let name = e.file_name().to_string_lossy().to_ascii_lowercase();
                if name.starts_with('.') {
                    continue;
                }
                // The entry's own type needs no second look at the disk; a link is followed.
                let is_dir = e.file_type().is_ok_and(|t| t.is_dir() || (t.is_symlink() && p.is_dir()));
                if is_dir {
                    stack.push(p);
                } else if [".fits", ".fit", ".fts"].iter().any(|x| name.ends_with(x)) {
                    out.push(p);
                } else {
                    others += 1;
                }
            }
        }
        if out.len() == before {
            return Err(Error::Input {
                path: d.clone(),
                why: if others > 0 {
                    format!("no FITS file (.fits, .fit, .fts) among its {others} files")
                } else {
                    "an empty folder: no FITS file".into()
                },
            });
        }
    }
    out.sort();
    out.dedup();
    Ok((out, again))
}

/// What one file is (rule 1 of the module docs).
pub fn classify(path: &Path, inst: &Instrument) -> Result<FileInfo, String> {
    let h = inst
        .headers
        .as_ref()
        .ok_or_else(|| format!("instrument {} has no [headers] table to sort files by", inst.name))?;
    let c: Cards = read_cards(path).map_err(|p| p.to_string())?;
    let got = c.text(&h.instrument_keyword).unwrap_or_default();
    if !h.is_instrument(&got) {
        return Err(if got.is_empty() {
            format!("another instrument: no {} keyword", h.instrument_keyword)
        } else {
            format!("another instrument: {} = '{got}'", h.instrument_keyword)
        });
    }
    let role_string = h.role_keywords.iter().map(|k| c.text(k).unwrap_or_default()).collect::<Vec<_>>().join("/");
    let role = h.role_of(&role_string).ok_or_else(|| {
        format!("a mode the instrument file does not know: {} = '{role_string}'", h.role_keywords.join("/"))
    })?;
    let need_num = |k: &str| c.number(k).ok_or_else(|| format!("no number in keyword {k}"));
    let mjd = need_num(&h.mjd_keyword)?;
    let fmt = &inst.format;
    let chip = if fmt.chips.is_empty() {
        None
    } else {
        let found = fmt.chips.iter().find(|ch| match (&ch.match_keyword, &ch.match_value) {
            (Some(k), Some(v)) => c.text(k).is_some_and(|x| x.trim().eq_ignore_ascii_case(v.trim())),
            _ => fmt.chips.len() == 1,
        });
        Some(found.map(|ch| ch.name.clone()).ok_or("no chip of the instrument's [format] matches its headers")?)
    };
    let binning = if fmt.binning_keywords.len() == 2 {
        let bx = need_num(&fmt.binning_keywords[0])?;
        let by = need_num(&fmt.binning_keywords[1])?;
        [bx as u32, by as u32]
    } else {
        [fmt.binning.first().copied().unwrap_or(1), fmt.binning.get(1).copied().unwrap_or(1)]
    };
    let exposure = fmt.exposure_keywords.iter().map(|k| c.text(k).unwrap_or_default()).collect::<Vec<_>>().join("/");
    let pol = &inst.polarimetry;
    let filter = match c.text(&pol.filter_keyword) {
        Some(f) => Some(
            inst.filter(&f)
                .map_err(|_| {
                    format!(
                        "filter {} = '{f}' is not one of the instrument's ({})",
                        pol.filter_keyword,
                        inst.filters.iter().map(|x| x.name.as_str()).collect::<Vec<_>>().join(", ")
                    )
                })?
                .name
                .clone(),
        ),
        None if matches!(role, Role::Bias) => None,
        None => return Err(format!("no filter keyword {}", pol.filter_keyword)),
    };
    let mut hwp_deg = std::iter::once(&pol.hwp_angle_keyword)
        .chain(&pol.hwp_angle_fallback_keywords)
        .filter(|k| !k.is_empty())
        .find_map(|k| c.number(k));
    // A turning plate: the middle and the width of the range the exposure swept, as the
    // reduction reads them (instrument::HwpRotation).
    let mut hwp_sweep_deg = 0.0;
    if let Some(r) = &pol.rotation {
        let range = if r.by_position() {
            match c.number(&r.position_keyword) {
                Some(pos) if pos.fract() == 0.0 && pos.abs() <= 1e9 => Some(r.position_range(pos as i64)?),
                Some(pos) => return Err(format!("{} = {pos}: not a rotor position (an integer)", r.position_keyword)),
                None => None,
            }
        } else {
            match (c.number(&r.begin_keyword), c.number(&r.end_keyword)) {
                (Some(b), Some(e)) => Some(instrument::HwpRotation::range(b, e)),
                _ => None,
            }
        };
        if let Some((mid, sweep)) = range {
            (hwp_deg, hwp_sweep_deg) = (Some(mid), sweep);
        }
    }
    if matches!(role, Role::Polarimetry | Role::Standard) && hwp_deg.is_none() && !pol.hwp_angle_keyword.is_empty() {
        return Err(format!("a polarimetric exposure without its HWP angle ({})", pol.hwp_angle_keyword));
    }
    Ok(FileInfo {
        path: path.into(),
        role,
        chip,
        filter,
        hwp_deg,
        hwp_sweep_deg,
        exptime_s: c.number(&pol.exptime_keyword),
        binning,
        exposure,
        target: c.text(&h.target_keyword).unwrap_or_default().trim().to_string(),
        ra_deg: c.number(&h.ra_keyword),
        dec_deg: c.number(&h.dec_keyword),
        mjd,
    })
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// Classify every file (in parallel; headers only).
pub fn sort_files(paths: &[PathBuf], inst: &Instrument) -> Sorted {
    let results: Vec<Result<FileInfo, LeftOut>> =
        paths.par_iter().map(|p| classify(p, inst).map_err(|why| LeftOut { files: vec![p.clone()], why })).collect();
    let mut s = Sorted::default();
    for r in results {
        match r {
            Ok(f) => s.files.push(f),
            Err(l) => s.left_out.push(l),
        }
    }
    s
}

/// One exposure: its files in chip order and what they share.
#[derive(Debug, Clone)]
struct Exposure {
    files: Vec<PathBuf>,
    info: FileInfo,
}

fn night_of(mjd: f64) -> i64 {
    (mjd - 0.5).floor() as i64
}

/// Calendar date (YYYYMMDD) of the noon that starts night `n` (an MJD day number; MJD 40587
/// is 1970-01-01).
fn night_label(n: i64) -> String {
    skyfield::provenance::iso_utc((n - 40_587) * 86_400)[..10].replace('-', "")
}

fn slug(s: &str) -> String {
    let t: String = s.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' { c } else { '_' }).collect();
    let t = t.trim_matches('_').to_string();
    if t.is_empty() {
        "unnamed".into()
    } else {
        t
    }
}

fn norm_name(s: &str) -> String {
    s.chars().filter(|c| !c.is_whitespace() && *c != '_').flat_map(|c| c.to_lowercase()).collect()
}

/// Angular distance (arcsec) of two positions (deg).
fn sep_arcsec(ra1: f64, dec1: f64, ra2: f64, dec2: f64) -> f64 {
    let (a1, d1, a2, d2) = (ra1.to_radians(), dec1.to_radians(), ra2.to_radians(), dec2.to_radians());
    let h = ((d2 - d1) / 2.0).sin().powi(2) + d1.cos() * d2.cos() * ((a2 - a1) / 2.0).sin().powi(2);
    2.0 * h.sqrt().min(1.0).asin().to_degrees() * 3600.0
}

fn fmt_deg(a: &[f64]) -> String {
    a.iter().map(|x| format!("{x}")).collect::<Vec<_>>().join(", ")
}

/// Where a standard star sits on the detector (0-based px): its catalogued position against
/// the pointing, north up and east left with the pointing on the detector centre (assumed;
/// module docs). `None` without a catalogued position or a pointing.
fn star_pixel(inst: &Instrument, st: &fit::standards::Star, ra: Option<f64>, dec: Option<f64>) -> Option<(f64, f64)> {
    let ((sra, sdec), ra, dec) = (st.position_deg()?, ra?, dec?);
    let scale = inst.detector.pixel_scale_arcsec;
    let dx = -((sra - ra + 540.0).rem_euclid(360.0) - 180.0) * dec.to_radians().cos() * 3600.0 / scale;
    let dy = (sdec - dec) * 3600.0 / scale;
    Some((0.5 * (inst.detector.nx as f64 - 1.0) + dx, 0.5 * (inst.detector.ny as f64 - 1.0) + dy))
}

/// Rule 2: chip files into exposures.
fn exposures(files: Vec<FileInfo>, inst: &Instrument, left: &mut Vec<LeftOut>) -> Vec<Exposure> {
    let chips: Vec<String> = inst.format.chips.iter().map(|c| c.name.clone()).collect();
    let mut groups: BTreeMap<(String, String), Vec<FileInfo>> = BTreeMap::new();
    let mut out = Vec::new();
    for f in files {
        if chips.is_empty() || f.exposure.is_empty() {
            out.push(Exposure { files: vec![f.path.clone()], info: f });
        } else {
            groups.entry((f.exposure.clone(), format!("{:?}", f.role))).or_default().push(f);
        }
    }
    for ((exp, _), mut fs) in groups {
        fs.sort_by_key(|f| chips.iter().position(|c| Some(c) == f.chip.as_ref()));
        let have: Vec<&str> = fs.iter().filter_map(|f| f.chip.as_deref()).collect();
        let missing: Vec<&str> = chips.iter().map(|c| c.as_str()).filter(|c| !have.contains(c)).collect();
        let files: Vec<PathBuf> = fs.iter().map(|f| f.path.clone()).collect();
        if !missing.is_empty() || have.len() != chips.len() {
            left.push(LeftOut {
                files,
                why: if missing.is_empty() {
                    format!("exposure {exp}: {} files for {} chips ({})", have.len(), chips.len(), have.join(", "))
                } else {
                    format!("exposure {exp}: chip file(s) {} missing", missing.join(", "))
                },
            });
            continue;
        }
        let first = &fs[0];
        if fs.iter().any(|f| f.filter != first.filter || f.hwp_deg != first.hwp_deg || f.target != first.target) {
            left.push(LeftOut {
                files,
                why: format!("exposure {exp}: its chip files disagree on filter, HWP angle or target"),
            });
            continue;
        }
        out.push(Exposure { files, info: first.clone() });
    }
    out.sort_by(|a, b| a.info.mjd.total_cmp(&b.info.mjd).then_with(|| a.files.cmp(&b.files)));
    out
}

/// A master's unit id and output.
#[derive(Debug, Clone)]
/// A standard's set, as the night's checks (rule 8) use it.
struct StandardSet {
    set_id: String,
    night: i64,
    filter: String,
    mjd: f64,
    star: String,
    polarized: bool,
    /// The star's pixel, formatted as the set's units give it.
    xy: [String; 2],
    /// The units' frame arguments, master flags, inputs and dependencies.
    frame_args: Vec<String>,
    masters_args: Vec<String>,
    inputs: Vec<PathBuf>,
    after: Vec<String>,
}

impl StandardSet {
    /// The id and output of its unit of `kind` (`zero-angle` or `photometry`).
    fn unit(&self, kind: &str, products: &Path) -> (String, PathBuf) {
        let dir = if kind == "zero-angle" { "zero-angle" } else { "standards" };
        (format!("{kind}-{}", self.set_id), products.join(dir).join(format!("{}.json", self.set_id)))
    }
    /// Whether it has a unit of `kind` (rule 6).
    fn has(&self, kind: &str, nasmyth: bool) -> bool {
        match kind {
            "zero-angle" => self.polarized,
            _ => !self.polarized || nasmyth,
        }
    }
}

/// Rule 6's units of a standard's set: a polarized standard's zero angle; the photometry of an
/// unpolarized one (the instrument's own polarization where it sits), and of a polarized one
/// too behind a Nasmyth telescope (a point of the telescope fit), the star named so that its
/// output records it ([`fit::telescope::StandardRecord`]).
fn standard_units(set: &StandardSet, nasmyth: bool, opts: &ScanOptions) -> Vec<Unit> {
    let mut units = Vec::new();
    for kind in ["zero-angle", "photometry"].into_iter().filter(|k| set.has(k, nasmyth)) {
        let (id, out) = set.unit(kind, &opts.products);
        let mut args = vec![kind.to_string()];
        args.extend(set.frame_args.iter().cloned());
        args.extend(["--instrument".into(), opts.instrument.clone()]);
        args.extend(["--x".into(), set.xy[0].clone(), "--y".into(), set.xy[1].clone()]);
        args.extend(["--aperture".into(), opts.aperture_px.to_string(), "--star".into(), set.star.clone()]);
        if let Some(sp) = &opts.standards {
            args.extend(["--standards".into(), s(sp)]);
        }
        args.extend(set.masters_args.iter().cloned());
        args.push("--json".into());
        let mut u = Unit::new(&id, kind, set.inputs.clone(), vec![out], args, set.after.clone());
        u.stdout = true;
        u.standard = Some(set.star.clone());
        units.push(u);
    }
    units
}

/// A calibration made from a sky field's set.
struct SkyCalibration {
    unit: String,
    out: PathBuf,
    filter: String,
    mjd: f64,
}

struct Master {
    id: String,
    out: PathBuf,
    night: i64,
    binning: [u32; 2],
    filter: Option<String>,
}

/// The master of `masters` for a set of `night`, `binning` and `filter`: the same night's, else
/// the nearest night's.
fn nearest<'a>(masters: &'a [Master], night: i64, binning: [u32; 2], filter: Option<&String>) -> Option<&'a Master> {
    masters
        .iter()
        .filter(|m| m.binning == binning && (filter.is_none() || m.filter.as_ref() == filter))
        .min_by_key(|m| ((m.night - night).abs(), m.night))
}

fn bin_label(b: [u32; 2]) -> String {
    format!("{}x{}", b[0], b[1])
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// Scan `dirs` and plan the night(s): the one library call of `instpol scan` and
/// `instpol.scan`.
///
/// The plan holds absolute paths (the folders, the products, a standards file and an
/// instrument given as a file are made absolute here), so that it runs from any folder and on
/// any worker that sees the same file system.
pub fn scan(dirs: &[PathBuf], opts: &ScanOptions) -> Result<Plan, Error> {
    let abs = |p: &Path| std::path::absolute(p).map_err(|e| Error::Input { path: p.into(), why: e.to_string() });
    let dirs: Vec<PathBuf> = dirs.iter().map(|d| abs(d)).collect::<Result<_, _>>()?;
    let mut opts = opts.clone();
    opts.products = abs(&opts.products)?;
    opts.standards = opts.standards.as_deref().map(abs).transpose()?;
    if Path::new(&opts.instrument).is_file() {
        opts.instrument = abs(Path::new(&opts.instrument))?.display().to_string();
    }
    let opts = &opts;
    let inst = Instrument::load(&opts.instrument).map_err(|e| Error::Instrument(e.to_string()))?;
    if inst.headers.is_none() {
        return Err(Error::Instrument(format!(
            "instrument {} has no [headers] table: it does not say how its headers name bias, flat and polarimetric files",
            opts.instrument
        )));
    }
    if !(opts.pointing_tol_arcsec.is_finite() && opts.pointing_tol_arcsec > 0.0) {
        return Err(Error::Option(format!("pointing tolerance {} arcsec: must be positive", opts.pointing_tol_arcsec)));
    }
    if !(opts.max_gap_min.is_finite() && opts.max_gap_min > 0.0) {
        return Err(Error::Option(format!("largest gap {} min: must be positive", opts.max_gap_min)));
    }
    skyfield::reduce::check_bin(opts.bin_px, &inst).map_err(|e| Error::Option(e.to_string()))?;
    for (what, v) in [("FWHM", opts.fwhm_px), ("aperture radius", opts.aperture_px)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(Error::Option(format!("{what} {v} px: must be a positive number of pixels")));
        }
    }
    for f in &opts.sky_fields {
        f.check()?;
    }
    let standards = match &opts.standards {
        Some(p) => fit::standards::Standards::load(p),
        None => fit::standards::Standards::builtin(),
    }
    .map_err(|e| Error::Option(e.to_string()))?;
    let (mut paths, again) = list_files(&dirs)?;
    // Of a file's names, the one reached through no symlink is kept, else the first by path.
    paths.sort_by_cached_key(|p| (std::fs::canonicalize(p).ok().as_deref() != Some(p.as_path()), p.clone()));
    let distinct = skyfield::same::distinct_files(&paths, skyfield::same::By::Content);
    let mut files = distinct.files.clone();
    files.sort();
    let mut sorted = sort_files(&files, &inst);
    sorted.left_out.extend(again);
    sorted.left_out.extend(distinct.duplicates.iter().map(|d| LeftOut {
        files: vec![d.again.clone(), d.first.clone()],
        why: format!("{d}: used once, as {}", d.first.display()),
    }));
    plan_sorted(sorted, &inst, &standards, opts)
}

/// Rules 2 to 7 over classified files.
pub fn plan_sorted(
    sorted: Sorted,
    inst: &Instrument,
    standards: &fit::standards::Standards,
    opts: &ScanOptions,
) -> Result<Plan, Error> {
    let mut left = sorted.left_out;
    let files_seen: Vec<(PathBuf, String)> =
        sorted.files.iter().map(|f| (f.path.clone(), f.role.name().to_string())).collect();
    let exps = exposures(sorted.files, inst, &mut left);
    let mut units: Vec<Unit> = Vec::new();
    let (biases, flats) = master_units(&exps, opts, &mut left, &mut units);
    // A telescope whose mirrors polarize (a Nasmyth fold) and whose headers give the
    // parallactic angle: its standards are fitted for a telescope model.
    let nasmyth = inst
        .telescope
        .as_ref()
        .is_some_and(|t| t.focus == instrument::telescope::Focus::Nasmyth && !t.parang_start_keyword.is_empty());
    let mut sets = SetPlanner {
        inst,
        standards,
        opts,
        biases,
        flats,
        nasmyth,
        units,
        left,
        set_names: BTreeMap::new(),
        standard_sets: Vec::new(),
        calibrations: Vec::new(),
    };
    for q in sequences(&exps, opts) {
        sets.plan_set(&q);
    }
    let SetPlanner { mut units, left, standard_sets, calibrations, .. } = sets;
    units.extend(night_checks(&standard_sets, &calibrations, nasmyth, opts));
    let files = files_seen.into_iter().map(|(path, role)| super::plan::FileRole { path, role }).collect();
    Plan::checked((&opts.instrument, inst), &opts.products, units, files, left)
}

/// Rule 4: a master bias of each night and binning, and a master flat of each night, binning
/// and filter (after its night's nearest bias), each of at least 3 exposures (fewer are left
/// out, with why). Returns the biases and the flats.
fn master_units(
    exps: &[Exposure],
    opts: &ScanOptions,
    left: &mut Vec<LeftOut>,
    units: &mut Vec<Unit>,
) -> (Vec<Master>, Vec<Master>) {
    let p = &opts.products;
    let inst_arg = &opts.instrument;
    let mut bias_groups: BTreeMap<(i64, [u32; 2]), Vec<&Exposure>> = BTreeMap::new();
    let mut flat_groups: BTreeMap<(i64, [u32; 2], String), Vec<&Exposure>> = BTreeMap::new();
    for e in exps {
        let n = night_of(e.info.mjd);
        match e.info.role {
            Role::Bias => bias_groups.entry((n, e.info.binning)).or_default().push(e),
            Role::Flat => match &e.info.filter {
                Some(f) => flat_groups.entry((n, e.info.binning, f.clone())).or_default().push(e),
                None => left.push(LeftOut { files: e.files.clone(), why: "a flat without a filter".into() }),
            },
            _ => {}
        }
    }
    let mut biases = Vec::new();
    for ((n, b), es) in &bias_groups {
        if es.len() < 3 {
            left.push(LeftOut {
                files: es.iter().flat_map(|e| e.files.clone()).collect(),
                why: format!(
                    "{} bias exposure(s) of night {} binning {}: a master needs at least 3",
                    es.len(),
                    night_label(*n),
                    bin_label(*b)
                ),
            });
            continue;
        }
        let id = format!("bias-{}-{}", night_label(*n), bin_label(*b));
        let out = p.join("masters").join(format!("{id}.fits"));
        let inputs: Vec<PathBuf> = es.iter().flat_map(|e| e.files.clone()).collect();
        let mut args = vec!["master-bias".to_string()];
        args.extend(inputs.iter().map(|x| s(x)));
        args.extend(["--instrument".into(), inst_arg.clone(), "--out".into(), s(&out)]);
        units.push(Unit::new(&id, "master-bias", inputs, vec![out.clone()], args, vec![]));
        biases.push(Master { id, out, night: *n, binning: *b, filter: None });
    }
    let mut flats = Vec::new();
    for ((n, b, f), es) in &flat_groups {
        if es.len() < 3 {
            left.push(LeftOut {
                files: es.iter().flat_map(|e| e.files.clone()).collect(),
                why: format!(
                    "{} flat exposure(s) in {f} of night {}: a master needs at least 3",
                    es.len(),
                    night_label(*n)
                ),
            });
            continue;
        }
        let id = format!("flat-{}-{}-{}", night_label(*n), slug(f), bin_label(*b));
        let out = p.join("masters").join(format!("{id}.fits"));
        let mut inputs: Vec<PathBuf> = es.iter().flat_map(|e| e.files.clone()).collect();
        let mut args = vec!["master-flat".to_string()];
        args.extend(inputs.iter().map(|x| s(x)));
        args.extend(["--instrument".into(), inst_arg.clone()]);
        let mut after = vec![];
        if let Some(m) = nearest(&biases, *n, *b, None) {
            args.extend(["--bias".into(), s(&m.out)]);
            inputs.push(m.out.clone());
            after.push(m.id.clone());
        }
        args.extend(["--out".into(), s(&out)]);
        units.push(Unit::new(&id, "master-flat", inputs, vec![out.clone()], args, after));
        flats.push(Master { id, out, night: *n, binning: *b, filter: Some(f.clone()) });
    }
    (biases, flats)
}

/// Rule 5: the polarimetric and standard exposures in sequences, an exposure joining the last
/// sequence when it has the same role, target, filter and binning, points within the
/// tolerance of its first exposure and starts within the largest gap of its last.
fn sequences<'a>(exps: &'a [Exposure], opts: &ScanOptions) -> Vec<Vec<&'a Exposure>> {
    let tol = opts.pointing_tol_arcsec;
    let mut seqs: Vec<Vec<&Exposure>> = Vec::new();
    for e in exps.iter().filter(|e| matches!(e.info.role, Role::Polarimetry | Role::Standard)) {
        let joins = seqs.last().is_some_and(|q: &Vec<&Exposure>| {
            let (first, last) = (&q[0].info, &q[q.len() - 1].info);
            let i = &e.info;
            let near = match (first.ra_deg, first.dec_deg, i.ra_deg, i.dec_deg) {
                (Some(a), Some(b), Some(c), Some(d)) => sep_arcsec(a, b, c, d) <= tol,
                (None, None, None, None) => true,
                _ => false,
            };
            first.role == i.role
                && norm_name(&first.target) == norm_name(&i.target)
                && first.filter == i.filter
                && first.binning == i.binning
                && near
                && (i.mjd - last.mjd) * 1440.0 <= opts.max_gap_min
        });
        if joins {
            if let Some(q) = seqs.last_mut() {
                q.push(e);
            }
        } else {
            seqs.push(vec![e]);
        }
    }
    seqs
}

/// A sequence's complete cycles of plate angles, in time order; `None` (the sequence left out,
/// with why) when an exposure has no angle or the angles are not a complete set. Exposures
/// beyond the complete cycles are left out.
fn complete_cycles<'a>(q: &[&'a Exposure], label: &str, left: &mut Vec<LeftOut>) -> Option<Vec<&'a Exposure>> {
    let info = &q[0].info;
    let all_files: Vec<PathBuf> = q.iter().flat_map(|e| e.files.clone()).collect();
    // Angles and their counts.
    let mut angles: Vec<(f64, Vec<&Exposure>)> = Vec::new();
    for e in q {
        let a = e.info.hwp_deg.unwrap_or(f64::NAN);
        match angles.iter_mut().find(|(b, _)| (a - *b).abs() < 0.05) {
            Some((_, v)) => v.push(e),
            None => angles.push((a, vec![e])),
        }
    }
    let distinct: Vec<f64> = angles.iter().map(|(a, _)| *a).collect();
    if distinct.iter().any(|a| !a.is_finite()) {
        left.push(LeftOut { files: all_files, why: format!("set {label}: an exposure without an HWP angle") });
        return None;
    }
    // The one completeness rule of the reduction, for a fixed or a turning plate.
    if let Some(g) = skyfield::reduce::plate_set_gap(&distinct, info.hwp_sweep_deg) {
        left.push(LeftOut {
            files: all_files,
            why: format!(
                "set {label}: incomplete, HWP angle(s) {} missing from the N = {} set ({}); has {}",
                fmt_deg(&g.missing_deg),
                g.n,
                fmt_deg(&g.expected_deg),
                fmt_deg(&distinct)
            ),
        });
        return None;
    }
    let cycles = angles.iter().map(|(_, v)| v.len()).min().unwrap_or(0);
    let mut keep: Vec<&Exposure> = Vec::new();
    let mut extra: Vec<PathBuf> = Vec::new();
    for (_, v) in &angles {
        keep.extend(v.iter().take(cycles));
        extra.extend(v.iter().skip(cycles).flat_map(|e| e.files.clone()));
    }
    if !extra.is_empty() {
        left.push(LeftOut {
            files: extra,
            why: format!("set {label}: exposures beyond its {cycles} complete cycle(s) of {} angles", distinct.len()),
        });
    }
    keep.sort_by(|a, b| a.info.mjd.total_cmp(&b.info.mjd));
    Some(keep)
}

/// The units of each complete set (rules 5 to 7), and what the night's checks need of them.
struct SetPlanner<'a> {
    inst: &'a Instrument,
    standards: &'a fit::standards::Standards,
    opts: &'a ScanOptions,
    biases: Vec<Master>,
    flats: Vec<Master>,
    nasmyth: bool,
    units: Vec<Unit>,
    left: Vec<LeftOut>,
    /// How many sets have each base name so far (the second is `-2`).
    set_names: BTreeMap<String, usize>,
    standard_sets: Vec<StandardSet>,
    calibrations: Vec<SkyCalibration>,
}

/// A set's frames with the masters that calibrate them, as a unit's inputs and arguments.
struct SetInputs {
    frame_args: Vec<String>,
    masters_args: Vec<String>,
    inputs: Vec<PathBuf>,
    after: Vec<String>,
}

impl<'a> SetPlanner<'a> {
    /// One sequence's units: its map and its catalog (or, for a sky field, its calibration),
    /// and, for a standard star, its standard units.
    fn plan_set(&mut self, q: &[&Exposure]) {
        let opts = self.opts;
        let info = &q[0].info;
        let label = format!(
            "{} {} ({} exposure(s) from MJD {:.5})",
            if info.target.is_empty() { "(no target name)" } else { &info.target },
            info.filter.as_deref().unwrap_or("?"),
            q.len(),
            info.mjd
        );
        let Some(keep) = complete_cycles(q, &label, &mut self.left) else { return };
        let frames: Vec<PathBuf> = keep.iter().flat_map(|e| e.files.clone()).collect();
        let night = night_of(info.mjd);
        let filter = info.filter.clone().unwrap_or_default();
        let star = self.standard_of(info, &label);
        let first_unit = self.units.len();
        let base = format!("{}-{}-{}", night_label(night), slug(&info.target), slug(&filter));
        let k = self.set_names.entry(base.clone()).or_insert(0);
        *k += 1;
        let set_id = if *k == 1 { base } else { format!("{base}-{k}") };
        let set = self.inputs_of(&frames, night, info);
        let sky = opts.sky_fields.iter().find(|f| norm_name(&f.target) == norm_name(&info.target));
        let map = self.map_and_catalog(&set_id, &set, sky.is_none());
        if let Some(sky) = sky {
            let cal = opts.products.join("calibrations").join(format!("{set_id}.fits"));
            let args = vec![
                "calibrate".to_string(),
                "--map".into(),
                s(&map),
                "--instrument".into(),
                opts.instrument.clone(),
                "--sky-p".into(),
                sky.p_percent.to_string(),
                "--sky-chi".into(),
                sky.chi_deg.to_string(),
                "--bin".into(),
                opts.bin_px.to_string(),
                "--out".into(),
                s(&cal),
            ];
            let unit = format!("calibrate-{set_id}");
            self.calibrations.push(SkyCalibration {
                unit: unit.clone(),
                out: cal.clone(),
                filter: filter.clone(),
                mjd: info.mjd,
            });
            self.units.push(Unit::new(
                &unit,
                "calibrate",
                vec![map.clone()],
                vec![cal],
                args,
                vec![format!("reduce-{set_id}")],
            ));
        }
        if let Some(st) = star {
            match star_pixel(self.inst, st, info.ra_deg, info.dec_deg) {
                Some((x, y)) => {
                    let set = StandardSet {
                        set_id: set_id.clone(),
                        night,
                        filter: filter.clone(),
                        mjd: info.mjd,
                        star: st.name.clone(),
                        polarized: st.kind == fit::standards::Kind::Polarized,
                        xy: [format!("{x:.2}"), format!("{y:.2}")],
                        frame_args: set.frame_args,
                        masters_args: set.masters_args,
                        inputs: set.inputs,
                        after: set.after,
                    };
                    self.units.extend(standard_units(&set, self.nasmyth, opts));
                    self.standard_sets.push(set);
                }
                None => self.left.push(LeftOut {
                    files: vec![],
                    why: format!(
                        "set {label}: standard {} without a catalogued position or a pointing: not measured at its position",
                        st.name
                    ),
                }),
            }
        }
        // What each unit of the set measures (module docs of `trend`).
        for u in &mut self.units[first_unit..] {
            u.mjd = Some(info.mjd);
            u.filter = info.filter.clone();
        }
    }

    /// Rule 6: the standard star a set observes, by its target name or within the pointing
    /// tolerance of a catalogued position. A set the headers call a standard that the list
    /// does not know is measured as a target, and the plan says so.
    fn standard_of(&mut self, info: &FileInfo, label: &str) -> Option<&'a fit::standards::Star> {
        let standards = self.standards;
        let tol = self.opts.pointing_tol_arcsec;
        let by_name = standards.star(&info.target).ok();
        let by_pos = match (info.ra_deg, info.dec_deg) {
            (Some(ra), Some(dec)) => standards
                .stars
                .iter()
                .find(|st| st.position_deg().is_some_and(|(sra, sdec)| sep_arcsec(ra, dec, sra, sdec) <= tol)),
            _ => None,
        };
        let star = by_name.or(by_pos);
        if star.is_none() && info.role == Role::Standard {
            self.left.push(LeftOut {
                files: vec![],
                why: format!("set {label}: the headers call it a standard, but the standards list knows no '{}' there: measured as a target", info.target),
            });
        }
        star
    }

    /// A set's frames and the night's nearest master bias and flat of its binning (and filter).
    fn inputs_of(&self, frames: &[PathBuf], night: i64, info: &FileInfo) -> SetInputs {
        let mut masters_args: Vec<String> = vec![];
        let mut masters_in: Vec<PathBuf> = vec![];
        let mut after: Vec<String> = vec![];
        if let Some(m) = nearest(&self.biases, night, info.binning, None) {
            masters_args.extend(["--bias".into(), s(&m.out)]);
            masters_in.push(m.out.clone());
            after.push(m.id.clone());
        }
        if let Some(m) = nearest(&self.flats, night, info.binning, info.filter.as_ref()) {
            masters_args.extend(["--flat".into(), s(&m.out)]);
            masters_in.push(m.out.clone());
            after.push(m.id.clone());
        }
        let inputs: Vec<PathBuf> = frames.iter().cloned().chain(masters_in.iter().cloned()).collect();
        let frame_args: Vec<String> = frames.iter().map(|x| s(x)).collect();
        SetInputs { frame_args, masters_args, inputs, after }
    }

    /// Rule 7: the set's map (`reduce`), and its catalog unless it is a sky field (an empty
    /// field: its stars, if any, are not what it was taken for). Returns the map's path.
    fn map_and_catalog(&mut self, set_id: &str, set: &SetInputs, with_catalog: bool) -> PathBuf {
        let (opts, p, inst_arg) = (self.opts, &self.opts.products, &self.opts.instrument);
        let map = p.join("maps").join(format!("{set_id}.fits"));
        let mut args = vec!["reduce".to_string()];
        args.extend(set.frame_args.iter().cloned());
        args.extend(["--instrument".into(), inst_arg.clone(), "--bin".into(), opts.bin_px.to_string()]);
        args.extend(set.masters_args.iter().cloned());
        args.extend(["--out".into(), s(&map)]);
        self.units.push(Unit::new(
            &format!("reduce-{set_id}"),
            "reduce",
            set.inputs.clone(),
            vec![map.clone()],
            args,
            set.after.clone(),
        ));
        let cat = p.join("catalogs").join(format!("{set_id}.ecsv"));
        let mut args = vec!["catalog".to_string()];
        args.extend(set.frame_args.iter().cloned());
        args.extend(["--instrument".into(), inst_arg.clone(), "--fwhm".into(), opts.fwhm_px.to_string()]);
        args.extend(["--aperture".into(), opts.aperture_px.to_string()]);
        args.extend(set.masters_args.iter().cloned());
        args.extend(["--out".into(), s(&cat)]);
        if with_catalog {
            self.units.push(Unit::new(
                &format!("catalog-{set_id}"),
                "catalog",
                set.inputs.clone(),
                vec![cat],
                args,
                set.after.clone(),
            ));
        }
        map
    }
}

/// Rule 8 (module docs): each standard's set validated against its filter's calibration
/// nearest in time, and the zero angle of each night and filter combined from its standards.
fn night_checks(sets: &[StandardSet], calibrations: &[SkyCalibration], nasmyth: bool, opts: &ScanOptions) -> Vec<Unit> {
    let p = &opts.products;
    let mut units = Vec::new();
    for set in sets {
        let Some(cal) = calibrations
            .iter()
            .filter(|c| c.filter == set.filter)
            .min_by(|a, b| (a.mjd - set.mjd).abs().total_cmp(&(b.mjd - set.mjd).abs()))
        else {
            continue;
        };
        let mut args = vec!["validate".to_string()];
        args.extend(set.frame_args.iter().cloned());
        args.extend(["--cal".into(), s(&cal.out), "--instrument".into(), opts.instrument.clone()]);
        args.extend(["--x".into(), set.xy[0].clone(), "--y".into(), set.xy[1].clone()]);
        args.extend(["--aperture".into(), opts.aperture_px.to_string()]);
        // An unpolarized standard is expected at zero, which validate takes without a star; a
        // polarized one at its published value in the filter's band.
        if set.polarized {
            args.extend(["--star".into(), set.star.clone()]);
            if let Some(sp) = &opts.standards {
                args.extend(["--standards".into(), s(sp)]);
            }
        }
        args.extend(set.masters_args.iter().cloned());
        args.push("--json".into());
        let mut inputs = set.inputs.clone();
        inputs.push(cal.out.clone());
        let mut after = set.after.clone();
        after.push(cal.unit.clone());
        let out = p.join("validate").join(format!("{}.json", set.set_id));
        let mut u = Unit::new(&format!("validate-{}", set.set_id), "validate", inputs, vec![out], args, after);
        u.stdout = true;
        u.check = true;
        u.mjd = Some(set.mjd);
        u.filter = Some(set.filter.clone());
        u.standard = Some(set.star.clone());
        units.push(u);
    }
    // Per night and filter: the zero angles combined, and behind a Nasmyth telescope its
    // model fitted to every standard's photometry (two stars at least: the model has two
    // parameters, and each star gives two numbers).
    let mut by_night: BTreeMap<(i64, &str), Vec<&StandardSet>> = BTreeMap::new();
    for set in sets {
        by_night.entry((set.night, set.filter.as_str())).or_default().push(set);
    }
    for ((night, filter), group) in by_night {
        for (kind, from, dir) in
            [("zero-angle", "zero-angle", "zero-angle"), ("fit-standards", "photometry", "telescope")]
        {
            let of: Vec<&&StandardSet> = group.iter().filter(|s| s.has(from, nasmyth)).collect();
            if of.len() < 2 || (kind == "fit-standards" && !nasmyth) {
                continue;
            }
            let name = format!("{}-{}-night", night_label(night), slug(filter));
            let mut args = vec![kind.to_string()];
            let (mut inputs, mut after) = (Vec::new(), Vec::new());
            for set in &of {
                let (id, out) = set.unit(from, p);
                if kind == "zero-angle" {
                    args.push("--measured".into());
                }
                args.push(s(&out));
                inputs.push(out);
                after.push(id);
            }
            if kind == "fit-standards" {
                args.extend(["--instrument".into(), opts.instrument.clone(), "--model".into(), "wiersema".into()]);
            }
            args.push("--json".into());
            let out = p.join(dir).join(format!("{name}.json"));
            let mut u = Unit::new(&format!("{kind}-{name}"), kind, inputs, vec![out], args, after);
            u.stdout = true;
            u.mjd = of.iter().map(|s| s.mjd).reduce(f64::min);
            u.filter = Some(filter.to_string());
            units.push(u);
        }
    }
    units
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn night_labels_are_civil_dates() {
        // MJD 58546 is 2019-03-04 (0h UT); the night starting that noon is labelled by it.
        assert_eq!(night_label(58546), "20190304");
        assert_eq!(night_label(40587), "19700101");
        assert_eq!(night_label(51544), "20000101");
        assert_eq!(night_of(58546.9), 58546);
        assert_eq!(night_of(58547.3), 58546);
    }

    #[test]
    fn separations() {
        assert!((sep_arcsec(10.0, 0.0, 10.0, 1.0 / 3600.0) - 1.0).abs() < 1e-6);
        assert!((sep_arcsec(0.0, 60.0, 1.0 / 3600.0 / 0.5, 60.0) - 1.0).abs() < 1e-3);
    }
}
