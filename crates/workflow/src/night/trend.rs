//! Instrument monitoring over many nights: the quantities the nights' plans measured, against
//! date, and a step in each where one stands out of the errors.
//!
//! From each plan ([`super::plan::Plan`], as `instpol scan` wrote and `instpol run` ran it) are
//! read, for every unit that finished (its output exists):
//!
//! - `zero_angle_deg`: a `zero-angle` unit's HWP zero angle (deg) and its error, per filter, one
//!   point per polarized standard (`instpol zero-angle --json`): its measured chi against the
//!   catalogued one;
//! - `p_minus_catalogue`: the same unit's measured `P` less the catalogued `P` of the star in
//!   the filter's band (fractions; the standards list its command names, else the built-in
//!   one), the errors of both combined;
//! - `q_unpolarized`, `u_unpolarized`, `p_unpolarized`: a `photometry` unit's `q`, `u`, `P`
//!   (fractions, in the plate's frame) and their errors, per filter, one point per unpolarized
//!   standard (`instpol photometry --json`): the instrument's own polarization where the star
//!   sits (`q`, `u` carry no bias; `P` does, near zero);
//! - `p_field_edge`: a `calibrate` unit's instrumental `P` at the edge of the field (fraction),
//!   per filter, one point per sky-field calibration (`fit::Calibration::p_at_edge`);
//! - `telescope_<parameter>[_<unit>]` (`telescope_factor`, `telescope_offset_deg`): a
//!   `fit-standards` unit's fitted parameters with their errors, per filter, one point per
//!   night (`instpol fit-standards --json`).
//!
//! A photometry unit of a polarized standard (a point of the telescope fit: its output gives
//! `p_true`) is not the instrument's own polarization and is not read as such.
//!
//! A night's combined zero angle (a `zero-angle` unit without a standard) repeats its
//! standards' points and is not read.
//!
//! Each point is dated by its set's first exposure (`mjd` of the unit). A series (a quantity in
//! one filter) is searched for one step ([`find_step`]): every split into an earlier and a later
//! part of at least two points each, the two weighted means compared; the split of largest
//! significance is reported, and flagged when it exceeds the threshold (5 sigma by default:
//! the search over splits is a look-elsewhere of about `n` trials).

use super::plan::Plan;
use super::Error;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use stokes::stats::circular::{self, Period};

/// The step significance (sigma) above which a step is flagged unless told otherwise: the
/// search over splits is a look-elsewhere of about as many trials as nights (module docs).
pub const DEFAULT_THRESHOLD_SIGMA: f64 = 5.0;

/// One measured value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// `zero_angle_deg`, `p_minus_catalogue`, `q_unpolarized`, `u_unpolarized`, `p_unpolarized`,
    /// `p_field_edge` or
    /// `telescope_<parameter>[_<unit>]` (module docs).
    pub quantity: String,
    pub filter: String,
    /// The standard measured (empty for `p_field_edge` and the telescope's parameters).
    pub star: String,
    /// Start of its set (MJD).
    pub mjd: f64,
    pub value: f64,
    pub sigma: f64,
    /// The file the value was read from.
    pub source: PathBuf,
}

/// The most significant step of one series ([`find_step`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Step {
    pub quantity: String,
    pub filter: String,
    /// The last point before the step and the first after it (MJD).
    pub last_before_mjd: f64,
    pub first_after_mjd: f64,
    /// Weighted means before and after, their difference and its error (the errors scaled by
    /// each part's sqrt(chi^2/dof) where that exceeds 1).
    pub before: f64,
    pub after: f64,
    pub delta: f64,
    pub sigma_delta: f64,
    /// `|delta| / sigma_delta`.
    pub significance: f64,
    /// Significance above the threshold.
    pub flagged: bool,
    pub n_before: usize,
    pub n_after: usize,
}

/// Every point of the nights and each series' step.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Trend {
    pub points: Vec<Point>,
    pub steps: Vec<Step>,
    pub threshold_sigma: f64,
    /// What the points are of ([`plans_product`]): the nights' instrument, the BLAKE3 of its
    /// definition when every plan recorded the same one, its plate, the plans' BLAKE3, and
    /// what differed when plans of several instruments were allowed together.
    #[serde(default)]
    pub product: skyfield::provenance::Product,
}

/// What a plan's products are of: the product it recorded ([`Plan::product`]), else its
/// instrument as the commands were given it, loaded (a built-in name, or a file as given or
/// beside the plan), else that name alone.
fn plan_product(plan: &Plan, path: &Path) -> skyfield::provenance::Product {
    use skyfield::provenance::Product;
    if let Some(p) = &plan.product {
        return p.clone();
    }
    let beside = path.parent().map(|d| d.join(&plan.instrument));
    let loaded = instrument::Instrument::load(&plan.instrument)
        .ok()
        .or_else(|| beside.and_then(|b| instrument::Instrument::from_file(&b).ok()));
    match loaded {
        Some(i) => Product::of_instrument_alone(&i),
        None => Product { instrument: Some(plan.instrument.clone()), ..Product::default() },
    }
}

/// The one product of the nights' plans (`(path, product)` each, in order): one instrument
/// (`fit::correction::setup::same_instrument`), or, with `allow_mismatch`, several with what differed
/// recorded (`MISMATCH`); otherwise an error naming two plans and their instruments. A
/// trend compares one instrument's nights: a step between two instruments is no step.
pub fn plans_product(
    plans: &[(PathBuf, skyfield::provenance::Product)],
    allow_mismatch: bool,
) -> Result<skyfield::provenance::Product, Error> {
    let name = |p: &skyfield::provenance::Product| p.instrument.clone().unwrap_or_else(|| "(unnamed)".into());
    let Some((first_path, first)) = plans.first() else { return Err(Error::Option("no plan given".into())) };
    let mut out = first.clone();
    for (path, p) in &plans[1..] {
        if !fit::correction::setup::same_instrument(&name(p), &name(first)) {
            if !allow_mismatch {
                return Err(Error::Option(format!(
                    "{} is a plan of instrument {}, {} of {}: a trend follows one instrument's nights (give each instrument's plans on their own, or --allow-mismatch to put them together)",
                    path.display(),
                    name(p),
                    first_path.display(),
                    name(first)
                )));
            }
            out.mismatch_allowed.get_or_insert_with(|| format!("plans of {} and {}", name(first), name(p)));
        }
        if p.instrument_hash != out.instrument_hash {
            out.instrument_hash = None;
        }
        if p.plate != out.plate {
            out.plate = None;
        }
    }
    out.inputs = plans
        .iter()
        .filter_map(|(path, _)| std::fs::read(path).ok())
        .map(|b| skyfield::provenance::hash_hex(&b))
        .collect();
    Ok(out)
}

/// Weighted mean, its error scaled by sqrt(chi^2/dof) when above 1, of `(value, sigma)`.
fn weighted(v: &[(f64, f64)]) -> (f64, f64) {
    let w: f64 = v.iter().map(|(_, s)| 1.0 / (s * s)).sum();
    let m = v.iter().map(|(x, s)| x / (s * s)).sum::<f64>() / w;
    let chi2: f64 = v.iter().map(|(x, s)| ((x - m) / s).powi(2)).sum();
    let scale = if v.len() > 1 { (chi2 / (v.len() - 1) as f64).max(1.0).sqrt() } else { 1.0 };
    (m, scale / w.sqrt())
}

/// [`weighted`] of angles in degrees of `period`: the circular weighted mean
/// (`stokes::stats::circular`), on the branch of the first value, its chi^2 on the wrapped
/// differences; `None` when the angles have no mean (spread round the circle).
fn weighted_angles(v: &[(f64, f64)], period: Period) -> Option<(f64, f64)> {
    let a: Vec<f64> = v.iter().map(|(x, _)| x.to_radians()).collect();
    let w: Vec<f64> = v.iter().map(|(_, s)| 1.0 / (s.to_radians() * s.to_radians())).collect();
    let m = circular::weighted_mean(&a, &w, period)?;
    let scale = if v.len() > 1 { (m.chi2 / (v.len() - 1) as f64).max(1.0).sqrt() } else { 1.0 };
    let near_first = a[0] + circular::difference(m.mean, a[0], period);
    Some((near_first.to_degrees(), (scale / w.iter().sum::<f64>().sqrt()).to_degrees()))
}

/// The period of a series' values: angles (a quantity in degrees: zero angles, the telescope's
/// offsets) repeat every half turn; other quantities are not angles.
pub fn period_of(quantity: &str) -> Option<Period> {
    quantity.ends_with("_deg").then_some(Period::HalfTurn)
}

/// The most significant single step of a series `(mjd, value, sigma)` (module docs); `None`
/// with fewer than four points. The points need not be sorted.
pub fn find_step(points: &[(f64, f64, f64)], threshold_sigma: f64) -> Option<Step> {
    find_step_of(points, threshold_sigma, None)
}

/// [`find_step`] of a series whose values are angles in degrees of `period` (`None`: not
/// angles): the means of each part are circular, and the step their wrapped difference.
pub fn find_step_of(points: &[(f64, f64, f64)], threshold_sigma: f64, period: Option<Period>) -> Option<Step> {
    let mut p: Vec<(f64, f64, f64)> = points
        .iter()
        .copied()
        .filter(|(t, v, s)| t.is_finite() && v.is_finite() && s.is_finite() && *s > 0.0)
        .collect();
    p.sort_by(|a, b| a.0.total_cmp(&b.0));
    if p.len() < 4 {
        return None;
    }
    let mut best: Option<Step> = None;
    for k in 2..=p.len() - 2 {
        // A split between two points of the same date is no split.
        if p[k].0 == p[k - 1].0 {
            continue;
        }
        let a: Vec<(f64, f64)> = p[..k].iter().map(|x| (x.1, x.2)).collect();
        let b: Vec<(f64, f64)> = p[k..].iter().map(|x| (x.1, x.2)).collect();
        let ((m1, e1), (m2, e2), d) = match period {
            None => {
                let ((m1, e1), (m2, e2)) = (weighted(&a), weighted(&b));
                ((m1, e1), (m2, e2), m2 - m1)
            }
            Some(per) => {
                let (Some(x), Some(y)) = (weighted_angles(&a, per), weighted_angles(&b, per)) else { continue };
                let d = circular::difference(y.0.to_radians(), x.0.to_radians(), per).to_degrees();
                (x, y, d)
            }
        };
        let sd = e1.hypot(e2);
        let z = d.abs() / sd;
        if best.as_ref().is_none_or(|s| z > s.significance) {
            best = Some(Step {
                quantity: String::new(),
                filter: String::new(),
                last_before_mjd: p[k - 1].0,
                first_after_mjd: p[k].0,
                before: m1,
                after: m2,
                delta: d,
                sigma_delta: sd,
                significance: z,
                flagged: z > threshold_sigma,
                n_before: k,
                n_after: p.len() - k,
            });
        }
    }
    best
}

/// A unit's JSON output, or an error naming the file.
pub(crate) fn read_json(path: &Path) -> Result<serde_json::Value, Error> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::Input { path: path.into(), why: e.to_string() })?;
    serde_json::from_str(&text).map_err(|e| Error::Input { path: path.into(), why: format!("not JSON: {e}") })
}

/// The finite number under `key` of a JSON output, or an error naming the file and key.
pub(crate) fn number(v: &serde_json::Value, key: &str, path: &Path) -> Result<f64, Error> {
    v.get(key)
        .and_then(|x| x.as_f64())
        .filter(|x| x.is_finite())
        .ok_or_else(|| Error::Input { path: path.into(), why: format!("no number '{key}'") })
}

/// The `p_field_edge` point of a `calibrate` unit's output (module docs); none when the model
/// is undefined at the edge.
fn edge_point(u: &super::plan::Unit, out: &Path, mjd: f64) -> Result<Option<Point>, Error> {
    let cal = fit::Calibration::load(out).map_err(|e| Error::Input { path: out.into(), why: e.to_string() })?;
    Ok(cal.p_at_edge().map(|(value, sigma)| Point {
        quantity: "p_field_edge".into(),
        filter: u.filter.clone().unwrap_or_default(),
        star: String::new(),
        mjd,
        value,
        sigma,
        source: out.into(),
    }))
}

/// The `p_minus_catalogue` point of a polarized standard's `zero-angle` unit (module docs);
/// none when the output has no measured `P` or the list no `P` in the band.
fn p_against_catalogue(
    u: &super::plan::Unit,
    v: &serde_json::Value,
    out: &Path,
    mjd: f64,
) -> Result<Option<Point>, Error> {
    let (Some(star), Some(filter)) = (&u.standard, &u.filter) else { return Ok(None) };
    let Some((p, sp)) = measured_p(v) else { return Ok(None) };
    let Some((pc, spc)) = catalogue_p(u, out)? else { return Ok(None) };
    Ok(Some(Point {
        quantity: "p_minus_catalogue".into(),
        filter: filter.clone(),
        star: star.clone(),
        mjd,
        value: p - pc,
        sigma: sp.hypot(spc),
        source: out.into(),
    }))
}

/// A `zero-angle` output's measured `P` of its (first) standard and its error (fractions).
pub(crate) fn measured_p(v: &serde_json::Value) -> Option<(f64, f64)> {
    let row = &v["standards"][0];
    Some((row["p_measured"].as_f64()?, row["sigma_p_measured"].as_f64()?))
}

/// The catalogued `P` and its error (fractions) of a unit's standard in its filter's band, from
/// the standards list its command names (`--standards`), else the built-in one; none when the
/// list has no `P` in the band. `out` names the unit's output in the error of a list that
/// cannot be read.
pub(crate) fn catalogue_p(u: &super::plan::Unit, out: &Path) -> Result<Option<(f64, f64)>, Error> {
    let (Some(star), Some(filter)) = (&u.standard, &u.filter) else { return Ok(None) };
    let file = u.command.windows(2).find(|w| w[0] == "--standards").map(|w| PathBuf::from(&w[1]));
    let list = match &file {
        Some(f) => fit::standards::Standards::load(f),
        None => fit::standards::Standards::builtin(),
    }
    .map_err(|e| Error::Input { path: file.clone().unwrap_or_else(|| out.into()), why: e.to_string() })?;
    let Ok(band) = list.star(star).and_then(|s| s.band(filter).cloned()) else { return Ok(None) };
    Ok(Some((band.p_percent / 100.0, band.sigma_p_percent / 100.0)))
}

/// The `telescope_*` points of a `fit-standards` unit's output (module docs): every parameter
/// of every band's fit.
fn telescope_points(u: &super::plan::Unit, out: &Path, mjd: f64) -> Result<Vec<Point>, Error> {
    let v = read_json(out)?;
    let bad = |why: &str| Error::Input { path: out.into(), why: why.into() };
    let fits = v.as_array().ok_or_else(|| bad("not the --json output of instpol fit-standards (an array of fits)"))?;
    let mut points = Vec::new();
    for fit in fits {
        let params = fit["params"].as_array().ok_or_else(|| bad("a fit without 'params'"))?;
        for par in params {
            let name = par["name"].as_str().ok_or_else(|| bad("a parameter without a name"))?;
            let unit = par["unit"].as_str().unwrap_or("");
            points.push(Point {
                quantity: if unit.is_empty() {
                    format!("telescope_{name}")
                } else {
                    format!("telescope_{name}_{unit}")
                },
                filter: u.filter.clone().unwrap_or_default(),
                star: String::new(),
                mjd,
                value: number(par, "value", out)?,
                sigma: number(par, "sigma_value", out)?,
                source: out.into(),
            });
        }
    }
    Ok(points)
}

/// Gather the points of `plans` (plan files) and find each series' step (module docs). A plan
/// whose units have not run (no output) contributes nothing from those units; a plan that
/// cannot be read, or an output that does not hold what its kind writes, is an error naming
/// the file.
pub fn gather(plans: &[PathBuf], threshold_sigma: f64, allow_mismatch: bool) -> Result<Trend, Error> {
    if !(threshold_sigma.is_finite() && threshold_sigma > 0.0) {
        return Err(Error::Option(format!("step threshold {threshold_sigma} sigma: must be positive")));
    }
    if plans.is_empty() {
        return Err(Error::Option("no plan given".into()));
    }
    let loaded: Vec<Plan> = plans.iter().map(|p| Plan::load(p)).collect::<Result<_, _>>()?;
    let products: Vec<_> =
        plans.iter().zip(&loaded).map(|(path, plan)| (path.clone(), plan_product(plan, path))).collect();
    let product = plans_product(&products, allow_mismatch)?;
    let mut points = Vec::new();
    for plan in &loaded {
        for u in &plan.units {
            let (Some(out), Some(mjd)) = (u.outputs.first(), u.mjd) else { continue };
            if !out.is_file() {
                continue;
            }
            if u.kind == "calibrate" {
                points.extend(edge_point(u, out, mjd)?);
                continue;
            }
            if u.kind == "fit-standards" {
                points.extend(telescope_points(u, out, mjd)?);
                continue;
            }
            if !matches!(u.kind.as_str(), "zero-angle" | "photometry") || u.standard.is_none() {
                continue;
            }
            let v = read_json(out)?;
            if v.get("p_true").is_some_and(|p| !p.is_null()) {
                continue;
            }
            if u.kind == "zero-angle" {
                points.extend(p_against_catalogue(u, &v, out, mjd)?);
            }
            let read: Vec<(&str, &str, &str)> = if u.kind == "zero-angle" {
                vec![("zero_angle_deg", "zero_angle_deg", "sigma_zero_angle_deg")]
            } else {
                vec![
                    ("q_unpolarized", "q", "sigma_q"),
                    ("u_unpolarized", "u", "sigma_u"),
                    ("p_unpolarized", "p", "sigma_p"),
                ]
            };
            for (quantity, key, sigma) in read {
                points.push(Point {
                    quantity: quantity.into(),
                    filter: u.filter.clone().unwrap_or_default(),
                    star: u.standard.clone().unwrap_or_default(),
                    mjd,
                    value: number(&v, key, out)?,
                    sigma: number(&v, sigma, out)?,
                    source: out.clone(),
                });
            }
        }
    }
    points.sort_by(|a, b| {
        (a.quantity.as_str(), a.filter.as_str())
            .cmp(&(b.quantity.as_str(), b.filter.as_str()))
            .then(a.mjd.total_cmp(&b.mjd))
    });
    let mut series: Vec<(String, String)> = points.iter().map(|p| (p.quantity.clone(), p.filter.clone())).collect();
    series.dedup();
    let steps = series
        .into_iter()
        .filter_map(|(q, f)| {
            let s: Vec<(f64, f64, f64)> =
                points.iter().filter(|p| p.quantity == q && p.filter == f).map(|p| (p.mjd, p.value, p.sigma)).collect();
            find_step_of(&s, threshold_sigma, period_of(&q)).map(|st| Step { quantity: q, filter: f, ..st })
        })
        .collect();
    Ok(Trend { points, steps, threshold_sigma, product })
}

impl Trend {
    /// The points as a table (by extension: .ecsv, .csv, .fits, .vot): quantity, filter, star,
    /// mjd, value, sigma, and per point the step of its series it falls after (`after_step`,
    /// 1 when the series' step is flagged and the point lies after it).
    pub fn table(&self) -> skyfield::table::Table {
        use skyfield::table::{Column, Table};
        let after: Vec<i64> = self
            .points
            .iter()
            .map(|p| {
                self.steps.iter().any(|s| {
                    s.flagged && s.quantity == p.quantity && s.filter == p.filter && p.mjd >= s.first_after_mjd
                }) as i64
            })
            .collect();
        let col = |f: fn(&Point) -> f64| self.points.iter().map(f).collect::<Vec<f64>>();
        let mut t = Table::new(vec![
            Column::text(
                "quantity",
                "zero_angle_deg (deg), p_minus_catalogue, q_unpolarized, u_unpolarized, p_unpolarized, p_field_edge (fractions) or telescope_<parameter>[_<unit>]",
                self.points.iter().map(|p| p.quantity.clone()).collect(),
            ),
            Column::text("filter", "filter", self.points.iter().map(|p| p.filter.clone()).collect()),
            Column::text(
                "star",
                "standard star (empty for p_field_edge)",
                self.points.iter().map(|p| p.star.clone()).collect(),
            ),
            Column::f64("mjd", Some("d"), "start of the set (MJD)", col(|p| p.mjd)),
            Column::f64("value", None, "the quantity (deg or fraction, by quantity)", col(|p| p.value)),
            Column::f64("sigma", None, "its 1-sigma error", col(|p| p.sigma)),
            Column::i64("after_step", "1: after its series' flagged step", after),
            Column::text("source", "file read", self.points.iter().map(|p| p.source.display().to_string()).collect()),
        ]);
        t.product = Some(self.product.clone());
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_step_without_noise_is_found_where_it_is() {
        // Six points at 0 and six at 1.5, each +-0.1: the means differ by 1.5 with an error of
        // 0.1 sqrt(1/6 + 1/6) (chi^2 = 0: no scaling), between the sixth and seventh dates.
        let p: Vec<(f64, f64, f64)> =
            (0..12).map(|k| (58000.0 + 30.0 * k as f64, if k < 6 { 0.0 } else { 1.5 }, 0.1)).collect();
        let s = find_step(&p, 5.0).unwrap();
        assert_eq!((s.n_before, s.n_after), (6, 6));
        assert_eq!((s.last_before_mjd, s.first_after_mjd), (58150.0, 58180.0));
        assert!((s.delta - 1.5).abs() < 1e-12);
        assert!((s.sigma_delta - 0.1 * (2.0f64 / 6.0).sqrt()).abs() < 1e-12);
        assert!(s.flagged);
    }

    #[test]
    fn scatter_within_errors_flags_nothing_and_scatter_beyond_them_widens_the_error() {
        // +-1 sigma alternating: every split's means differ by at most 2/k sigma-ish.
        let p: Vec<(f64, f64, f64)> = (0..12).map(|k| (k as f64, if k % 2 == 0 { 0.1 } else { -0.1 }, 0.1)).collect();
        let s = find_step(&p, 5.0).unwrap();
        assert!(!s.flagged && s.significance < 2.0, "{s:?}");
        // The same values with errors ten times too small: chi^2/dof ~ 100 scales the errors
        // back by ~10, so the significance stays what it was.
        let small: Vec<(f64, f64, f64)> = p.iter().map(|&(t, v, _)| (t, v, 0.01)).collect();
        let t = find_step(&small, 5.0).unwrap();
        assert!(!t.flagged, "{t:?}");
        assert!(find_step(&p[..3], 5.0).is_none());
    }

    /// A zero angle that sits at the wrap: -89.5 and +89.7 deg are 0.8 deg apart, not 179.2.
    /// Twelve points of one zero angle, 89.8 deg, the later six written -90.2 deg (another
    /// reduction folds them the other way) flag no step, where a linear mean finds one of 180
    /// deg; a real step of 1 deg across the wrap is found with its size.
    #[test]
    fn angles_step_across_the_wrap_as_angles() {
        let p: Vec<(f64, f64, f64)> = (0..12).map(|k| (k as f64, if k < 6 { 89.8 } else { -90.2 }, 0.1)).collect();
        let lin = find_step(&p, 5.0).unwrap();
        assert!(lin.flagged, "the linear test is fooled: {lin:?}");
        let s = find_step_of(&p, 5.0, period_of("zero_angle_deg")).unwrap();
        assert!(!s.flagged && s.delta.abs() < 1e-9, "{s:?}");
        let q: Vec<(f64, f64, f64)> = (0..12).map(|k| (k as f64, if k < 6 { 89.6 } else { -89.4 }, 0.05)).collect();
        let s = find_step_of(&q, 5.0, Some(Period::HalfTurn)).unwrap();
        assert!(s.flagged && (s.delta - 1.0).abs() < 1e-9 && (s.n_before, s.n_after) == (6, 6), "{s:?}");
        assert_eq!(period_of("p_unpolarized"), None);
    }

    #[test]
    fn weighted_means() {
        let (m, e) = weighted(&[(1.0, 1.0), (3.0, 1.0)]);
        // chi^2 = 2 over 1 dof: the error 1/sqrt(2) scaled by sqrt(2).
        assert_eq!(m, 2.0);
        assert!((e - 1.0).abs() < 1e-15);
    }
}
