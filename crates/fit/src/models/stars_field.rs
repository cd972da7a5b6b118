//! The instrumental field from field stars: many stars of a dense field, in one or several
//! dithered pointings, taken as unpolarized or sharing one interstellar polarization, give the
//! field's instrumental `(q, u)` where no polarized sky of known polarization is at hand.
//!
//! The model of a measurement `m` of star `s` at field position `x_m` is, to first order in the
//! polarizations (`eq:approx`: a partial polarizer adds its `(q, u)` to a weakly polarized
//! beam's),
//!
//! ```text
//! (q, u)_m = F(x_m) + (q_is, u_is) + e_m
//! ```
//!
//! with `F` the instrumental field (the radial model of section `sec:fors1`, fixed or free
//! centre, optionally with the interpolant of its residuals, or a polynomial in x, y such as a
//! plane, [`crate::models::poly`]: the sky-field calibration's own models and fitter,
//! [`crate::models::pipeline::calibrate_bins`]; a polynomial's constant term needs the interstellar
//! term fixed, the two being the same at every position), `(q_is, u_is)` one interstellar
//! polarization common to every star (free, zero or given) and `e_m` the measurement's error.
//! A star seen in several pointings is one star (matched by its sky position: field position
//! plus the pointing's offset), so its intrinsic polarization is common to its measurements
//! while the instrumental part changes with its detector position.
//!
//! The fit alternates (backfitting, exact at convergence for the linear parameters): the field
//! fitted to the measurements minus the interstellar term, then the interstellar term as the
//! weighted mean of the measurements minus the field, until the interstellar term moves by less
//! than a ten-thousandth of its error. The covariance of the field's coefficients is then the joint
//! one, `(J^T W J)^-1` over the field's parameters and the interstellar pair together, scaled as
//! the radial fit scales its own: the interstellar term's uncertainty is in the coefficients'
//! errors.
//!
//! Stars polarized in themselves are rejected by their residual chi^2 across their
//! measurements (`2 n` degrees of freedom for `n` measurements; the errors scaled as the fit
//! scales its covariance, by `max(1, chi2_red)` by default, with the fitted model's and the
//! interstellar term's uncertainty added): a star whose chi^2 has an upper
//! tail probability below `reject_alpha` is left out and the field refitted, until the set of
//! rejected stars no longer changes (a star can come back). For an unpolarized star with right
//! errors the tail probability is uniform, so the expected false-rejection rate is
//! `reject_alpha` per star (default 1e-3: 0.3 of 300 stars), slightly less because the fitted
//! parameters absorb part of each residual.

use crate::files::calfile::Provenance;
use crate::models::pipeline::{calibrate_bins, CalibrateOptions, CalibrationMeta, CalibrationRun};
use crate::models::polar::chi2_even_sf;
use crate::{Bin, Error, Result};
use mueller::Qu;
use nalgebra::DMatrix;
use serde::Serialize;
use skyfield::table::Table;
use std::path::Path;

/// One star's measurement in one pointing: field position (arcmin from the detector centre) and
/// the measured `(q, u)` in the sky frame (the HWP zero angle added, [`catalog_rows`]) with
/// their errors (no covariance: a catalog's `q, u` errors are taken as independent).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StarRow {
    /// The pointing (catalog) it was measured in, 0-based.
    pub pointing: usize,
    /// Its row in that catalog, 0-based (for messages and reports).
    pub row: usize,
    pub x: f64,
    pub y: f64,
    pub qu: Qu,
}

/// The interstellar polarization common to the stars.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum Interstellar {
    /// Fitted with the field.
    Free,
    /// None: the stars are taken as unpolarized.
    Zero,
    /// Known `(q, u)` (fractions, sky frame).
    Given { q: f64, u: f64 },
}

/// How to fit the field from stars.
#[derive(Debug, Clone, PartialEq)]
pub struct StarsOptions {
    /// The field model and its fit (the sky-field calibration's options).
    pub calibrate: CalibrateOptions,
    pub interstellar: Interstellar,
    /// Offsets of the pointings (arcmin, along the detector axes): a star seen at field
    /// position `(x, y)` in pointing `k` is at `(x + dx_k, y + dy_k)` in the first pointing's
    /// field coordinates. `None`: measured from the stars ([`measure_offsets`]).
    pub offsets: Option<Vec<[f64; 2]>>,
    /// Two measurements closer than this on the sky (arcmin) are one star (default 1 arcsec).
    pub match_radius_arcmin: f64,
    /// A star whose residual chi^2 has an upper-tail probability below this is rejected
    /// (default 1e-3): the expected false-rejection rate per unpolarized star.
    pub reject_alpha: f64,
}

impl Default for StarsOptions {
    fn default() -> Self {
        StarsOptions {
            calibrate: CalibrateOptions::default(),
            interstellar: Interstellar::Free,
            offsets: None,
            match_radius_arcmin: 1.0 / 60.0,
            reject_alpha: 1e-3,
        }
    }
}

/// One star after the fit.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StarFit {
    /// Star number, 0-based, in the order of first appearance.
    pub id: usize,
    /// Sky position: field position in the first pointing's coordinates (arcmin), the mean of
    /// its measurements'.
    pub x_sky: f64,
    pub y_sky: f64,
    /// Its measurements: indices into the rows given.
    pub rows: Vec<usize>,
    /// Residual chi^2 against field + interstellar over its measurements, `2 n` degrees of
    /// freedom, and the chi^2's upper-tail probability.
    pub chi2: f64,
    pub dof: usize,
    pub p_value: f64,
    /// Mean residual `(q, u)` (its own polarization beyond the interstellar term), its `P`
    /// (fraction) and its distance from zero in sigma (the model's and the interstellar
    /// term's errors counted).
    pub residual_q: f64,
    pub residual_u: f64,
    pub residual_p: f64,
    pub residual_p_sigma: f64,
    pub rejected: bool,
}

/// What the fit from stars found.
#[derive(Debug, Clone)]
pub struct StarsRun {
    /// The calibration (the same file as the sky-field calibration's: `IP SOURCE` = "field
    /// stars"), the field's fit with the joint covariance, and the polar-angle test.
    pub run: CalibrationRun,
    /// The interstellar `(q, u)` with its covariance (zero covariance when not fitted).
    pub interstellar: mueller::Qu,
    pub interstellar_mode: Interstellar,
    /// Pointing offsets used (arcmin) and whether they were measured from the stars.
    pub offsets: Vec<[f64; 2]>,
    pub offsets_measured: bool,
    pub stars: Vec<StarFit>,
    /// Rejection rounds run (fits with a new rejected set).
    pub rounds: usize,
    pub n_rows: usize,
    /// What the fit ran despite (a pointing that shares no star with the others).
    pub warnings: Vec<String>,
}

impl StarsRun {
    /// The rejected stars, worst first.
    pub fn rejected(&self) -> Vec<&StarFit> {
        let mut r: Vec<&StarFit> = self.stars.iter().filter(|s| s.rejected).collect();
        r.sort_by(|a, b| a.p_value.total_cmp(&b.p_value));
        r
    }
}

/// The rows of one catalog written by `instpol catalog` (any table format): field positions
/// `x_arcmin, y_arcmin`, `q, u, sigma_q, sigma_u` (fractions, or % as declared) and the HWP zero
/// angle column ([`skyfield::table::ZERO_ANGLE_COLUMN`]) that says the `q, u` are in the sky
/// frame. Rows not measured (a value not finite, or a flag other than `outlier_exposure`) are
/// skipped. Returns the rows (with `pointing`) and the zero angle they carry.
pub fn catalog_rows(table: &Table, path: &Path, pointing: usize) -> Result<(Vec<StarRow>, f64)> {
    let bad = |what: String| Error::Input(format!("{}: {what}", path.display()));
    let z = table.frame(path)?.zero_angle_deg().ok_or_else(|| {
        bad(format!(
            "no column '{}': the field from stars needs q, u in the sky frame, with the HWP zero angle they carry \
             (the catalogs of `instpol catalog` have it)",
            skyfield::table::ZERO_ANGLE_COLUMN
        ))
    })?;
    let x = table.numbers("x_arcmin", path)?;
    let y = table.numbers("y_arcmin", path)?;
    let (v, _) = table.fractions(&["q", "u", "sigma_q", "sigma_u"], path)?;
    let flags: Option<Vec<String>> = table.column("flags").map(|c| match &c.data {
        skyfield::table::Data::Str(s) => s.clone(),
        _ => vec![String::new(); table.n_rows()],
    });
    let mut rows = vec![];
    for i in 0..table.n_rows() {
        let flagged = flags
            .as_ref()
            .is_some_and(|f| f[i].split('|').map(str::trim).any(|g| !g.is_empty() && g != "outlier_exposure"));
        let qu = Qu::from_sigmas(v[0][i], v[1][i], v[2][i], v[3][i], 0.0);
        let r = StarRow { pointing, row: i, x: x[i], y: y[i], qu };
        let ok = [r.x, r.y, qu.q, qu.u].iter().all(|a| a.is_finite())
            && [v[2][i], v[3][i]].iter().all(|s| s.is_finite() && *s > 0.0)
            && qu.var_q.is_finite()
            && qu.var_u.is_finite();
        if ok && !flagged {
            rows.push(r);
        }
    }
    Ok((rows, z))
}

/// The rows of the catalogs `paths`, one pointing each in their order ([`catalog_rows`]), and
/// the HWP zero angle their `q, u` carry: one for all (a calibration has one), else refused
/// naming the two catalogs that differ. A measurement written twice (a row whose position and
/// `q, u` with their errors repeat an earlier row's, in the same catalog or another:
/// `skyfield::same::repeated_rows`) is used once, and the third value says so naming both.
/// `expect`: the instrument and filter of the calibration asked for; a catalog that says it is
/// of another ([`crate::correction::setup::check_compatible`], its product keywords) is refused naming
/// both (`None`: a mismatch allowed).
pub fn read_catalogs(
    paths: &[std::path::PathBuf],
    expect: Option<(&str, &str)>,
) -> Result<(Vec<StarRow>, f64, Vec<String>)> {
    let mut rows = vec![];
    let mut zero: Option<(f64, &std::path::PathBuf)> = None;
    for (k, path) in paths.iter().enumerate() {
        let table = Table::read(path, None)?;
        if let (Some(setup), Some(e)) =
            (table.product.as_ref().and_then(crate::correction::setup::Setup::of_product), expect)
        {
            crate::correction::setup::check_compatible(&setup, Some(&crate::correction::setup::Setup::named(e.0, e.1)))
                .map_err(|m| {
                    Error::Input(format!(
                        "{} and the calibration asked for ({} {}): {m}: give the catalogs' instrument and filter",
                        path.display(),
                        e.0,
                        e.1
                    ))
                })?;
        }
        let (r, z) = catalog_rows(&table, path, k)?;
        match zero {
            Some((z0, p0)) if (z - z0).abs() > 1e-9 => {
                return Err(Error::Input(format!(
                "{}: its q, u carry the HWP zero angle {z} deg, {} carries {z0} deg: the catalogs of one calibration \
                     share one",
                path.display(),
                p0.display()
            )))
            }
            None => zero = Some((z, path)),
            _ => {}
        }
        rows.extend(r);
    }
    let (rows, notes) = distinct_rows(rows, paths);
    Ok((rows, zero.map_or(0.0, |z| z.0), notes))
}

/// How the instrument of a calibration from catalogs was chosen ([`catalogs_instrument`]).
#[derive(Debug, Clone, PartialEq)]
pub enum InstrumentChoice {
    /// Given by the caller.
    Given,
    /// The built-in one that writes the value the catalogs record (`INSTRUME`).
    Recorded(String),
    /// The catalogs say none: [`ASSUMED_INSTRUMENT`], which the faces warn of.
    Assumed,
}

/// The instrument of catalogs that say none.
pub const ASSUMED_INSTRUMENT: &str = "fors1";

/// The instrument a calibration from the catalogs `paths` is of: `given`, else the built-in one
/// the catalogs say they are of ([`recorded_instrument`], `instrument::builtin_for_keyword`;
/// an instrument that is no built-in one is refused, its file to be given), else
/// [`ASSUMED_INSTRUMENT`]. The one rule of `instpol calibrate-stars` and Python's
/// `calibrate_stars`.
pub fn catalogs_instrument(given: Option<&str>, paths: &[std::path::PathBuf]) -> Result<(String, InstrumentChoice)> {
    if let Some(g) = given {
        return Ok((g.to_string(), InstrumentChoice::Given));
    }
    match recorded_instrument(paths)? {
        Some(i) => match instrument::builtin_for_keyword(&i) {
            Some(b) => Ok((b.to_string(), InstrumentChoice::Recorded(i))),
            None => Err(Error::Input(format!(
                "the catalogs are of instrument {i}, no built-in one: give its instrument file"
            ))),
        },
        None => Ok((ASSUMED_INSTRUMENT.to_string(), InstrumentChoice::Assumed)),
    }
}

/// The instrument the catalogs `paths` say they are of (their product keywords, `INSTRUME`):
/// `None` when none says; refused naming two catalogs that say different ones.
pub fn recorded_instrument(paths: &[std::path::PathBuf]) -> Result<Option<String>> {
    let mut found: Option<(String, &std::path::PathBuf)> = None;
    for path in paths {
        let Some(i) = Table::read(path, None)?.product.and_then(|p| p.instrument) else { continue };
        match &found {
            Some((j, q)) if !j.eq_ignore_ascii_case(&i) => {
                return Err(Error::Input(format!(
                    "{} is a catalog of instrument {i}, {} of {j}: one calibration is of one instrument",
                    path.display(),
                    q.display()
                )))
            }
            Some(_) => {}
            None => found = Some((i, path)),
        }
    }
    Ok(found.map(|f| f.0))
}

/// `rows` with every repeated measurement (`skyfield::same::repeated_rows` over position and
/// `q, u` with their variances) left out, and a note naming the repeats (catalog and data row,
/// from 1) when there were any.
fn distinct_rows(rows: Vec<StarRow>, paths: &[std::path::PathBuf]) -> (Vec<StarRow>, Vec<String>) {
    let values: Vec<[f64; 7]> =
        rows.iter().map(|r| [r.x, r.y, r.qu.q, r.qu.u, r.qu.var_q, r.qu.var_u, r.qu.cov_qu]).collect();
    let repeats = skyfield::same::repeated_rows(&values);
    if repeats.is_empty() {
        return (rows, vec![]);
    }
    let name = |i: usize| {
        let r = &rows[i];
        format!("{} row {}", paths.get(r.pointing).map_or(String::new(), |p| p.display().to_string()), r.row + 1)
    };
    let note = format!(
        "{} measurements repeat earlier ones value for value (the same data written twice) and are used once: {}",
        repeats.len(),
        skyfield::same::describe_repeated(&repeats, &name, 3)
    );
    let again: std::collections::HashSet<usize> = repeats.iter().map(|r| r.again).collect();
    let kept = rows.into_iter().enumerate().filter(|(i, _)| !again.contains(i)).map(|(_, r)| r).collect();
    (kept, vec![note])
}

impl Interstellar {
    /// A given interstellar polarization from `P` in percent and `chi` in degrees (sky frame).
    pub fn from_percent_deg(p_percent: f64, chi_deg: f64) -> Result<Self> {
        if !(p_percent.is_finite() && (0.0..100.0).contains(&p_percent) && chi_deg.is_finite()) {
            return Err(Error::Input(format!(
                "interstellar polarization {p_percent} % at {chi_deg} deg: P must be in [0, 100) % and chi finite"
            )));
        }
        let (s2, c2) = (2.0 * chi_deg.to_radians()).sin_cos();
        Ok(Interstellar::Given { q: p_percent / 100.0 * c2, u: p_percent / 100.0 * s2 })
    }
}

/// The offset of each pointing from the first (arcmin, see [`StarsOptions::offsets`]),
/// measured from the stars: the shift that brings the most of pointing `k`'s stars within
/// `radius` of one of pointing 0's (a vote over every pair's difference on a grid of `radius`
/// cells, then the median of the pairs that agree with the best cell). A pointing that shares
/// fewer than three stars, or than a tenth of the smaller catalog, with the first is refused,
/// naming it.
pub fn measure_offsets(rows: &[StarRow], n_pointings: usize, radius: f64) -> Result<Vec<[f64; 2]>> {
    let of = |k: usize| rows.iter().filter(|r| r.pointing == k).map(|r| (r.x, r.y)).collect::<Vec<_>>();
    let first = of(0);
    let mut out = vec![[0.0, 0.0]];
    for k in 1..n_pointings {
        let other = of(k);
        let mut votes: std::collections::HashMap<(i64, i64), usize> = std::collections::HashMap::new();
        for a in &first {
            for b in &other {
                let (dx, dy) = (a.0 - b.0, a.1 - b.1);
                *votes.entry(((dx / radius).floor() as i64, (dy / radius).floor() as i64)).or_default() += 1;
            }
        }
        // The best 2 x 2 block of cells (a true offset near a cell's edge splits its votes).
        let best = votes
            .keys()
            .map(|&(i, j)| {
                let n: usize =
                    (0..2).flat_map(|a| (0..2).map(move |b| (i + a, j + b))).filter_map(|c| votes.get(&c)).sum();
                (n, (i, j))
            })
            .max();
        let Some((_, (i, j))) = best else {
            return Err(Error::Input(format!("pointing {}: no stars to match with the first pointing's", k + 1)));
        };
        let centre = ((i as f64 + 1.0) * radius, (j as f64 + 1.0) * radius);
        let mut pairs = vec![];
        for a in &first {
            for b in &other {
                let (dx, dy) = (a.0 - b.0, a.1 - b.1);
                if (dx - centre.0).abs() <= 1.5 * radius && (dy - centre.1).abs() <= 1.5 * radius {
                    pairs.push((dx, dy));
                }
            }
        }
        if pairs.len() < 3 {
            return Err(Error::Input(format!(
                "pointing {}: only {} of its stars match the first pointing's at any one offset (need 3): the pointings \
                 do not overlap, or give their offsets",
                k + 1,
                pairs.len()
            )));
        }
        // The median of the pairs near the best cell (chance pairs of two different stars fall
        // anywhere in it), then of those within half the radius of that.
        let median = |v: Vec<f64>| {
            let mut v = v;
            stokes::stats::robust::median(&mut v, stokes::stats::robust::Middle::Mean)
        };
        let mut at = [median(pairs.iter().map(|p| p.0).collect()), median(pairs.iter().map(|p| p.1).collect())];
        let near: Vec<&(f64, f64)> =
            pairs.iter().filter(|p| (p.0 - at[0]).hypot(p.1 - at[1]) <= 0.5 * radius).collect();
        if !near.is_empty() {
            at = [median(near.iter().map(|p| p.0).collect()), median(near.iter().map(|p| p.1).collect())];
        }
        // Chance pairs of two different stars crowd some cell too (a few among 10^5 pairs):
        // an offset is the pointings' only when a tenth of the smaller catalog, and at least
        // three stars, agree on it.
        let agree = pairs.iter().filter(|p| (p.0 - at[0]).hypot(p.1 - at[1]) <= radius).count();
        let need = 3.max(first.len().min(other.len()).div_ceil(10));
        if agree < need {
            return Err(Error::Input(format!(
                "pointing {}: only {agree} of its stars match the first pointing's at any one offset (need {need}): the \
                 pointings do not overlap, or give their offsets",
                k + 1
            )));
        }
        out.push(at);
    }
    Ok(out)
}

/// Group the rows into stars by sky position (single linkage within `radius`, rows of one
/// pointing never linked directly): each star's row indices, in the order of first appearance.
/// Two stars closer than `radius` become one, whose measurements then disagree: it is rejected
/// and named, not fitted.
fn match_stars(rows: &[StarRow], offsets: &[[f64; 2]], radius: f64) -> Vec<Vec<usize>> {
    let sky: Vec<(f64, f64)> =
        rows.iter().map(|r| (r.x + offsets[r.pointing][0], r.y + offsets[r.pointing][1])).collect();
    let mut parent: Vec<usize> = (0..rows.len()).collect();
    fn find(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    // Sorted by x, each row meets only its neighbours within the radius in x.
    let mut order: Vec<usize> = (0..rows.len()).collect();
    order.sort_by(|&a, &b| sky[a].0.total_cmp(&sky[b].0));
    for (k, &a) in order.iter().enumerate() {
        for &b in &order[k + 1..] {
            if sky[b].0 - sky[a].0 > radius {
                break;
            }
            if rows[a].pointing != rows[b].pointing && (sky[a].1 - sky[b].1).abs() <= radius {
                let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
                if ra != rb {
                    parent[ra.max(rb)] = ra.min(rb);
                }
            }
        }
    }
    let mut groups: Vec<Vec<usize>> = vec![];
    let mut index = std::collections::HashMap::new();
    for i in 0..rows.len() {
        let r = find(&mut parent, i);
        let g = *index.entry(r).or_insert_with(|| {
            groups.push(vec![]);
            groups.len() - 1
        });
        groups[g].push(i);
    }
    groups
}

/// Fit the instrumental field of `meta`'s instrument and filter from star measurements (module
/// docs). `rows` come from [`catalog_rows`], one pointing per catalog, `n_pointings` of them.
/// Refused: no rows, fewer stars than the model needs, every star rejected, offsets of the
/// wrong number, offsets to measure for a pointing that shares fewer than 3 stars with the
/// first.
pub fn stars_field(
    rows: &[StarRow],
    n_pointings: usize,
    meta: CalibrationMeta,
    opts: &StarsOptions,
) -> Result<StarsRun> {
    if rows.is_empty() {
        return Err(Error::Input("no measured star in the catalogs".into()));
    }
    if !(opts.reject_alpha > 0.0 && opts.reject_alpha < 1.0) {
        return Err(Error::Input(format!("the rejection probability {} must be in (0, 1)", opts.reject_alpha)));
    }
    // A polynomial's constant term is the same at every detector position, as a common
    // interstellar term is at every star: the two cannot be told apart.
    if opts.calibrate.poly_degree.is_some() && opts.interstellar == Interstellar::Free {
        return Err(Error::Input(
            "a polynomial field's constant term and a free interstellar polarization are the same at every position and cannot be told apart: take the stars as unpolarized (interstellar zero) or give the interstellar polarization".into(),
        ));
    }
    if !(opts.match_radius_arcmin > 0.0 && opts.match_radius_arcmin.is_finite()) {
        return Err(Error::Input(format!("the match radius {} arcmin must be positive", opts.match_radius_arcmin)));
    }
    let (offsets, measured) = match &opts.offsets {
        Some(o) if o.len() != n_pointings => {
            return Err(Error::Input(format!(
                "{} pointing offsets for {n_pointings} catalogs: give one per catalog",
                o.len()
            )))
        }
        Some(o) => (o.clone(), false),
        None => (measure_offsets(rows, n_pointings, opts.match_radius_arcmin)?, true),
    };
    let groups = match_stars(rows, &offsets, opts.match_radius_arcmin);
    // A pointing that shares no star with the others has wrong offsets, is another field, or
    // fills the others' gaps (a strip mask's dither by one strip): its stars each count as a
    // star of their own. Said, not refused (the measured offsets refuse it in
    // `measure_offsets`).
    let mut warnings = vec![];
    if n_pointings > 1 {
        for k in 0..n_pointings {
            let shared = groups.iter().filter(|g| g.len() > 1 && g.iter().any(|&i| rows[i].pointing == k)).count();
            let own = rows.iter().filter(|r| r.pointing == k).count();
            if own > 0 && shared < 3 {
                warnings.push(format!(
                    "pointing {} shares {shared} stars with the other pointings: at its offset ({:.4}, {:.4}) arcmin its \
                     {own} measurements are stars of their own (check the offset, or give none to measure it)",
                    k + 1,
                    offsets[k][0],
                    offsets[k][1]
                ));
            }
        }
    }
    // The rejection judges stars against the radial model alone: a residual interpolant passes
    // through every kept measurement, a polarized star's too. The interpolant, when asked for,
    // is made once the rejected set has settled.
    let radial_opts =
        StarsOptions { calibrate: CalibrateOptions { residual_map: false, ..opts.calibrate.clone() }, ..opts.clone() };
    let mut rejected = vec![false; groups.len()];
    let mut rounds = 0;
    let mut state;
    let mut keep;
    loop {
        rounds += 1;
        keep =
            groups.iter().zip(&rejected).filter(|(_, r)| !**r).flat_map(|(g, _)| g.iter().copied()).collect::<Vec<_>>();
        if keep.is_empty() {
            return Err(Error::Input(format!(
                "every one of the {} stars was rejected as polarized (residual chi^2 beyond the {} tail): the field model \
                 does not describe them, or their errors are understated",
                groups.len(),
                opts.reject_alpha
            )));
        }
        state = fit_kept(rows, &keep, &meta, &radial_opts).map_err(|e| match e {
            Error::TooFewBins { used, needed, .. } => Error::Input(format!(
                "too few star measurements for the field model: {used} kept ({} stars of {}, {} rejected), need at least \
                 {needed}",
                groups.len() - rejected.iter().filter(|r| **r).count(),
                groups.len(),
                rejected.iter().filter(|r| **r).count()
            )),
            e => e,
        })?;
        let next: Vec<bool> =
            groups.iter().map(|g| star_chi2(rows, g, &state.0, &state.1).2 < opts.reject_alpha).collect();
        if next == rejected || rounds >= 20 {
            break;
        }
        rejected = next;
    }
    if opts.calibrate.residual_map {
        state = fit_kept(rows, &keep, &meta, opts)?;
    }
    let (run, isp) = state;
    let stars = groups
        .iter()
        .enumerate()
        .map(|(id, g)| {
            let (chi2, dof, p_value, rq, ru, significance) = star_chi2(rows, g, &run, &isp);
            let n = g.len() as f64;
            let rp = rq.hypot(ru);
            StarFit {
                id,
                x_sky: g.iter().map(|&i| rows[i].x + offsets[rows[i].pointing][0]).sum::<f64>() / n,
                y_sky: g.iter().map(|&i| rows[i].y + offsets[rows[i].pointing][1]).sum::<f64>() / n,
                rows: g.clone(),
                chi2,
                dof,
                p_value,
                residual_q: rq,
                residual_u: ru,
                residual_p: rp,
                residual_p_sigma: significance,
                rejected: rejected[id],
            }
        })
        .collect();
    Ok(StarsRun {
        run,
        interstellar: isp,
        interstellar_mode: opts.interstellar,
        offsets,
        offsets_measured: measured,
        stars,
        rounds,
        n_rows: rows.len(),
        warnings,
    })
}

/// A star's residual chi^2 against the field's radial model and the interstellar term, its degrees of
/// freedom and tail probability, its mean residual `(q, u)` and that mean's distance from zero
/// in sigma. The residuals' covariance is the measurements' errors plus what the fitted model
/// does not know: the radial model's covariance carried to each measurement's position
/// (`G C G^T`, correlated between the measurements of one star, which sit at nearby
/// positions) and the interstellar term's (common to all of them), the errors scaled as the
/// fit's covariance is ([`crate::ErrorScaling`]). Without the model's part a star at the
/// field's edge, where the fitted `p(r)` is least certain, is rejected for the model's error.
/// The mean is the generalized least-squares one, `(H^T S^-1 H)^-1 H^T S^-1 r`.
fn star_chi2(
    rows: &[StarRow],
    g: &[usize],
    run: &CalibrationRun,
    isp: &mueller::Qu,
) -> (f64, usize, f64, f64, f64, f64) {
    // The measurements' errors as the fit judged them: scaled as its covariance is (by
    // max(1, chi2_red) by default), so that errors the catalogs understate for every star do
    // not reject stars for the scatter they all share.
    let scale = run.chi2_factor();
    let (_, np) = run.field_params();
    let n = 2 * g.len();
    let mut r = nalgebra::DVector::<f64>::zeros(n);
    let mut jac = DMatrix::<f64>::zeros(n, np);
    let mut s = DMatrix::<f64>::zeros(n, n);
    for (k, &i) in g.iter().enumerate() {
        let m = &rows[i];
        let (fq, fu) = run.field_qu(m.x, m.y);
        r[2 * k] = m.qu.q - fq - isp.q;
        r[2 * k + 1] = m.qu.u - fu - isp.u;
        s[(2 * k, 2 * k)] = scale * m.qu.var_q;
        s[(2 * k + 1, 2 * k + 1)] = scale * m.qu.var_u;
        if let Some((gq, gu)) = run.field_jacobian(m.x, m.y) {
            for p in 0..np {
                jac[(2 * k, p)] = gq[p];
                jac[(2 * k + 1, p)] = gu[p];
            }
        }
    }
    let c = DMatrix::from_row_slice(np, np, run.field_covariance());
    s += &jac * c * jac.transpose();
    for a in 0..g.len() {
        for b in 0..g.len() {
            s[(2 * a, 2 * b)] += isp.var_q;
            s[(2 * a + 1, 2 * b + 1)] += isp.var_u;
            s[(2 * a, 2 * b + 1)] += isp.cov_qu;
            s[(2 * a + 1, 2 * b)] += isp.cov_qu;
        }
    }
    let dof = n;
    let Some(chol) = s.cholesky() else {
        return (f64::INFINITY, dof, 0.0, f64::NAN, f64::NAN, f64::INFINITY);
    };
    let sr = chol.solve(&r);
    let chi2 = r.dot(&sr);
    let mut h = DMatrix::<f64>::zeros(n, 2);
    for k in 0..g.len() {
        h[(2 * k, 0)] = 1.0;
        h[(2 * k + 1, 1)] = 1.0;
    }
    let info = h.transpose() * chol.solve(&h);
    let rhs = h.transpose() * &sr;
    let (mean, sig) = match info.clone().try_inverse() {
        Some(cov) => {
            let m = &cov * &rhs;
            (m.clone(), m.dot(&(&info * &m)).max(0.0).sqrt())
        }
        None => (nalgebra::DVector::from_element(2, f64::NAN), f64::NAN),
    };
    (chi2, dof, chi2_even_sf(chi2, g.len()), mean[0], mean[1], sig)
}

/// The field and interstellar term from the kept rows (module docs: backfitting, then the
/// joint covariance).
fn fit_kept(
    rows: &[StarRow],
    keep: &[usize],
    meta: &CalibrationMeta,
    opts: &StarsOptions,
) -> Result<(CalibrationRun, mueller::Qu)> {
    let (mut iq, mut iu) = match opts.interstellar {
        Interstellar::Given { q, u } => (q, u),
        _ => (0.0, 0.0),
    };
    let free = opts.interstellar == Interstellar::Free;
    // The backfitting runs the radial model alone: a residual interpolant would take up the
    // interstellar term. The final fit adds it when asked.
    let radial_only = CalibrateOptions { residual_map: false, ..opts.calibrate.clone() };
    let bins_for = |iq: f64, iu: f64| -> Vec<Bin> {
        keep.iter()
            .map(|&i| {
                let r = &rows[i];
                Bin::new(r.x, r.y, r.qu.q - iq, r.qu.u - iu, r.qu.sigma_q(), r.qu.sigma_u())
            })
            .collect()
    };
    if free {
        for _ in 0..200 {
            let run = calibrate_bins(bins_for(iq, iu), meta.clone(), &radial_only)?;
            let (mut sq, mut su, mut wq, mut wu) = (0.0, 0.0, 0.0, 0.0);
            for (k, &i) in keep.iter().enumerate() {
                let w = run.weights()[k];
                let r = &rows[i];
                let (fq, fu) = run.field_qu(r.x, r.y);
                sq += w * (r.qu.q - fq) / r.qu.var_q;
                su += w * (r.qu.u - fu) / r.qu.var_u;
                wq += w / r.qu.var_q;
                wu += w / r.qu.var_u;
            }
            let (nq, nu) = (sq / wq, su / wu);
            let step = ((nq - iq).powi(2) * wq + (nu - iu).powi(2) * wu).sqrt();
            iq = nq;
            iu = nu;
            if step < 1e-4 {
                break;
            }
        }
    }
    let mut run = calibrate_bins(bins_for(iq, iu), meta.clone(), &opts.calibrate)?;
    let mut isp = mueller::Qu::new(iq, iu, 0.0, 0.0, 0.0);
    if free {
        let (cov, var) = joint_covariance(rows, keep, &run, true)?;
        run.set_field_covariance(&cov);
        isp.var_q = var[0];
        isp.var_u = var[1];
        isp.cov_qu = var[2];
    }
    Ok((run, isp))
}

/// `(J^T W J)^-1` over the field's free parameters (and the interstellar pair when `with_isp`),
/// with the fit's robust weights and its covariance scaling; returns the field block in the
/// model's parameter layout and the interstellar `(var_q, var_u, cov_qu)`.
fn joint_covariance(
    rows: &[StarRow],
    keep: &[usize],
    run: &CalibrationRun,
    with_isp: bool,
) -> Result<(Vec<f64>, [f64; 3])> {
    let (nf, np) = run.field_params();
    let n = nf + if with_isp { 2 } else { 0 };
    let mut a = DMatrix::<f64>::zeros(n, n);
    let mut gq = vec![0.0; n];
    let mut gu = vec![0.0; n];
    let mut rows_w: Vec<Vec<f64>> = vec![];
    for (k, &i) in keep.iter().enumerate() {
        let w = run.weights()[k];
        if w <= 0.0 {
            continue;
        }
        let r = &rows[i];
        let (jq, ju) =
            run.field_jacobian(r.x, r.y).ok_or_else(|| Error::Degenerate("no Jacobian of the field model".into()))?;
        gq[..nf].copy_from_slice(&jq[..nf]);
        gu[..nf].copy_from_slice(&ju[..nf]);
        if with_isp {
            gq[nf] = 1.0;
            gq[nf + 1] = 0.0;
            gu[nf] = 0.0;
            gu[nf + 1] = 1.0;
        }
        let (wq, wu) = (w / r.qu.var_q, w / r.qu.var_u);
        rows_w.push(gq.iter().map(|g| g * wq.sqrt()).collect());
        rows_w.push(gu.iter().map(|g| g * wu.sqrt()).collect());
        for a_ in 0..n {
            for b in 0..n {
                a[(a_, b)] += wq * gq[a_] * gq[b] + wu * gu[a_] * gu[b];
            }
        }
    }
    let scale = run.covariance_scale();
    let design = DMatrix::from_fn(rows_w.len(), n, |i, k| rows_w[i][k]);
    crate::conditioning::judge(&design, &joint_words(run, nf, with_isp))?;
    let inv = a.try_inverse().ok_or_else(|| {
        Error::Degenerate("the field and the interstellar polarization cannot be told apart by these stars".into())
    })? * scale;
    let mut cov = vec![0.0; np * np];
    for i in 0..nf {
        for j in 0..nf {
            cov[i * np + j] = 0.5 * (inv[(i, j)] + inv[(j, i)]);
        }
    }
    let var = if with_isp { [inv[(nf, nf)], inv[(nf + 1, nf + 1)], inv[(nf, nf + 1)]] } else { [0.0; 3] };
    Ok((cov, var))
}

/// The conditioning judge's words for the joint fit of the field (its first `nf` parameters)
/// and, with `with_isp`, the interstellar polarization.
fn joint_words(run: &CalibrationRun, nf: usize, with_isp: bool) -> crate::conditioning::Words {
    let mut names: Vec<String> = match &run.poly {
        Some(p) => {
            let terms = crate::models::poly::plane_words(p.model.degree).names;
            ["q", "u"].iter().flat_map(|c| terms.iter().map(move |t| format!("{t} of {c}"))).collect()
        }
        None => {
            let m = &run.fit.model;
            let mut v: Vec<String> =
                (0..m.coeffs.len()).map(|k| format!("the r^{} coefficient", k + m.first_power)).collect();
            v.extend(["the centre's x".to_string(), "the centre's y".to_string()]);
            v
        }
    };
    names.truncate(nf);
    if with_isp {
        names.extend(["the interstellar q".to_string(), "the interstellar u".to_string()]);
    }
    crate::conditioning::Words::new(
        names,
        "the interstellar polarization is told apart from the instrument's field only where the field changes \
         over the stars: stars spread over the field of view, at several distances from its centre, or the \
         interstellar polarization given rather than fitted",
    )
}

/// The calibration's description for a fit from stars of `inst` in `filter`, with the HWP
/// zero angle the catalogs' `q, u` carry (`zero_angle_deg`, recorded as the calibration's own,
/// so a correction turns by their difference only) and the catalogs as inputs.
pub fn stars_meta(
    inst: &instrument::Instrument,
    filter: &str,
    zero_angle_deg: f64,
    inputs: Vec<String>,
) -> CalibrationMeta {
    let f = inst.filter(filter).ok();
    CalibrationMeta {
        instrument: inst.name.clone(),
        filter: f.map(|f| f.name.clone()).unwrap_or_else(|| filter.to_string()),
        lambda_nm: f.map(|f| f.lambda_eff_nm).unwrap_or(f64::NAN),
        hwp_chi_offset_deg: zero_angle_deg,
        pixel: Some(crate::files::calfile::PixelGrid::of_instrument(inst)),
        provenance: Provenance::of_instrument(SOURCE, inputs, inst, filter),
    }
}

/// `IP SOURCE` of a calibration from field stars.
pub const SOURCE: &str = "field stars";

/// One rejected star in [`StarsSummary`].
#[derive(Debug, Clone, Serialize)]
pub struct RejectedStar {
    pub id: usize,
    /// Sky position in the first pointing's field coordinates (arcmin).
    pub x_arcmin: f64,
    pub y_arcmin: f64,
    pub n_measurements: usize,
    pub chi2: f64,
    pub dof: usize,
    /// Upper-tail probability of its chi^2 (below the threshold).
    pub p_value: f64,
    /// Its own polarization beyond the interstellar term (fraction), angle (deg) and `P / sigma_P`.
    pub residual_p: f64,
    pub residual_chi_deg: f64,
    pub residual_p_sigma: f64,
    /// Catalog (1-based, in the order given) and 0-based row of each of its measurements.
    pub measurements: Vec<[usize; 2]>,
}

/// The interstellar polarization in [`StarsSummary`] (fractions, deg).
#[derive(Debug, Clone, Serialize)]
pub struct InterstellarSummary {
    /// "free", "zero" or "given".
    pub mode: String,
    pub q: f64,
    pub u: f64,
    pub sigma_q: f64,
    pub sigma_u: f64,
    pub p: f64,
    pub chi_deg: f64,
}

/// The JSON of `instpol calibrate-stars` (field names are a contract): the radial fit's summary
/// as `instpol calibrate` prints it, and what the stars add.
#[derive(Debug, Clone, Serialize)]
pub struct StarsSummary {
    #[serde(flatten)]
    pub fit: crate::models::pipeline::FitSummary,
    pub interstellar: InterstellarSummary,
    pub n_catalogs: usize,
    pub n_measurements: usize,
    pub n_stars: usize,
    /// Stars seen in more than one pointing.
    pub n_stars_repeated: usize,
    /// Pointing offsets (arcmin) and whether they were measured from the stars.
    pub offsets_arcmin: Vec<[f64; 2]>,
    pub offsets_measured: bool,
    pub reject_alpha: f64,
    /// `reject_alpha` times the stars kept: the false rejections expected among them.
    pub expected_false_rejections: f64,
    pub rejection_rounds: usize,
    pub rejected: Vec<RejectedStar>,
    /// What the fit ran despite (a pointing that shares no star with the others).
    pub warnings: Vec<String>,
}

impl StarsSummary {
    pub fn new(run: &StarsRun, rows: &[StarRow], reject_alpha: f64) -> Self {
        let isp = &run.interstellar;
        let rejected: Vec<RejectedStar> = run
            .rejected()
            .into_iter()
            .map(|s| RejectedStar {
                id: s.id,
                x_arcmin: s.x_sky,
                y_arcmin: s.y_sky,
                n_measurements: s.rows.len(),
                chi2: s.chi2,
                dof: s.dof,
                p_value: s.p_value,
                residual_p: s.residual_p,
                residual_chi_deg: mueller::fold_pi(0.5 * s.residual_u.atan2(s.residual_q)).to_degrees(),
                residual_p_sigma: s.residual_p_sigma,
                measurements: s.rows.iter().map(|&i| [rows[i].pointing + 1, rows[i].row]).collect(),
            })
            .collect();
        let kept = run.stars.len() - rejected.len();
        StarsSummary {
            fit: crate::models::pipeline::FitSummary::new(&run.run),
            interstellar: InterstellarSummary {
                mode: match run.interstellar_mode {
                    Interstellar::Free => "free",
                    Interstellar::Zero => "zero",
                    Interstellar::Given { .. } => "given",
                }
                .into(),
                q: isp.q,
                u: isp.u,
                sigma_q: isp.var_q.max(0.0).sqrt(),
                sigma_u: isp.var_u.max(0.0).sqrt(),
                p: isp.q.hypot(isp.u),
                chi_deg: mueller::fold_pi(0.5 * isp.u.atan2(isp.q)).to_degrees(),
            },
            n_catalogs: run.offsets.len(),
            n_measurements: run.n_rows,
            n_stars: run.stars.len(),
            n_stars_repeated: run.stars.iter().filter(|s| s.rows.len() > 1).count(),
            offsets_arcmin: run.offsets.clone(),
            offsets_measured: run.offsets_measured,
            reject_alpha,
            expected_false_rejections: reject_alpha * kept as f64,
            rejection_rounds: run.rounds,
            rejected,
            warnings: run.warnings.clone(),
        }
    }
}
