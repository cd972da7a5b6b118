//! The HWP zero angle from polarized standards: the angle to add to a measured `chi`
//! (`eq:polang`) so that it becomes the star's catalogued one (the chromatic zero angle of a
//! super-achromatic HWP and the instrument's rotation, section `sec:HWP`), and the sense of
//! the angle (whether the instrument measures `chi` counter-clockwise on the sky, as the IAU
//! does, or mirrored).
//!
//! Angles of linear polarization live on a circle of period 180 deg, so offsets are averaged as
//! the directions `2 d`, weighted by `1 / sigma^2`; the error of the mean is `1 / sqrt(sum w)`.
//! With two or more standards of different `chi`, the sense is the one with the smaller
//! chi^2 (`chi_true = offset + chi_meas` for the IAU sense, `offset - chi_meas` mirrored); with
//! one standard, or standards of one `chi`, it cannot be told and is reported so.
//!
//! With several standards the scatter is checked: the chi^2 of the offsets about their mean,
//! each star's pull against the weighted circular mean of the OTHERS (leave-one-out: its
//! residual over `sqrt(sigma_i^2 + 1 / sum_{k != i} w_k)`, so a grossly wrong star cannot hide
//! by dragging the mean toward itself), a scatter-based error (the propagated one times
//! `sqrt(chi^2 / dof)`, the Birge ratio) beside the propagated one, and the star that disagrees
//! (the largest pull beyond [`OUTLIER_PULL`], with three or more stars: with two, either could
//! be the wrong one). Such a star is left out and the mean, the sense, the errors and the
//! pulls are found again from the rest, as long as more than half the stars remain: a star
//! catalogued 80 deg off (a misidentification) is named and does not move the result.

/// One standard: measured and catalogued `chi` (rad) with their 1-sigma errors (rad).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StandardChi {
    pub chi_measured: f64,
    pub sigma_measured: f64,
    pub chi_catalogue: f64,
    pub sigma_catalogue: f64,
}

/// The sense of the instrument's angle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sense {
    /// `chi_true = offset + chi_measured` fits better (counter-clockwise, as the IAU).
    Iau,
    /// `chi_true = offset - chi_measured` fits better: the instrument's angles are mirrored.
    Mirrored,
    /// One standard, or standards sharing one `chi`: the sense cannot be told.
    Undetermined,
}

/// The zero angle from a set of standards.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ZeroAngle {
    /// The angle to add to a measured `chi` (rad, in (-pi/2, pi/2]), for the IAU sense (or the
    /// mirrored one when `sense` says so).
    pub offset: f64,
    pub sigma: f64,
    /// chi^2 of the offsets about their mean and its degrees of freedom.
    pub chi2: f64,
    pub dof: usize,
    pub sense: Sense,
    /// chi^2 of the other sense (for the record), when the sense was decided.
    pub chi2_other_sense: Option<f64>,
    /// Each standard's own offset (rad).
    pub offsets: Vec<f64>,
    /// Each standard's residual about the mean over its error (0 for a single star).
    pub pulls: Vec<f64>,
    /// The propagated error scaled by `sqrt(chi2 / dof)` (rad), with two or more standards.
    pub sigma_scatter: Option<f64>,
    /// Index (into the standards given) of the star whose pull exceeds [`OUTLIER_PULL`], the
    /// largest one, with three or more standards (the first of `excluded`).
    pub outlier: Option<usize>,
    /// Indices (into the standards given) of the stars left out of the mean, worst first; the
    /// offset, errors, chi^2 and sense are those of the others. `offsets` and `pulls` still
    /// hold every star (an excluded star's pull is against the mean of the kept ones).
    pub excluded: Vec<usize>,
}

/// A standard whose offset lies further than this (in sigma of its residual) from the mean of
/// the others is named as an outlier.
pub const OUTLIER_PULL: f64 = 3.0;

pub use mueller::wrap_half_pi;

/// Weighted circular mean (period pi) of offsets `d` with weights `w`, and its chi^2
/// (`stokes::stats::circular::direction`: offsets spread evenly round the half turn give a
/// direction that means nothing, which their chi^2 says, as the sums' atan2 always did).
fn mean_offset(d: &[f64], w: &[f64]) -> (f64, f64) {
    use stokes::stats::circular::{direction, Period};
    direction(d, w, Period::HalfTurn).map_or((f64::NAN, f64::NAN), |m| (m.mean, m.chi2))
}

/// One sense's offsets `d` (all usable stars) with weights `w`, the worst disagreeing star left
/// out at a time (leave-one-out pull beyond [`OUTLIER_PULL`], while three or more remain and
/// more than half would stay).
struct Clipped {
    kept: Vec<usize>,
    excluded: Vec<usize>,
    mean: f64,
    chi2: f64,
    pulls: Vec<f64>,
}

fn clip(d: &[f64], w: &[f64]) -> Clipped {
    let mut kept: Vec<usize> = (0..d.len()).collect();
    let mut excluded = Vec::new();
    loop {
        let (mean, chi2) = mean_offset(
            &kept.iter().map(|&k| d[k]).collect::<Vec<f64>>(),
            &kept.iter().map(|&k| w[k]).collect::<Vec<f64>>(),
        );
        let pulls = loo_pulls(&kept, d, w);
        if kept.len() >= 3 && 2 * (kept.len() - 1) > d.len() {
            let (k, worst) =
                kept.iter().map(|&k| (k, pulls[k].abs())).fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
            if worst > OUTLIER_PULL {
                kept.retain(|&j| j != k);
                excluded.push(k);
                continue;
            }
        }
        return Clipped { kept, excluded, mean, chi2, pulls };
    }
}

/// Leave-one-out pulls: each star's offset against the weighted circular mean of the kept
/// stars other than itself, over `sqrt(1/w_i + 1/sum_{kept, k != i} w_k)` (0 with no other).
fn loo_pulls(kept: &[usize], d: &[f64], w: &[f64]) -> Vec<f64> {
    (0..d.len())
        .map(|i| {
            let others: Vec<usize> = kept.iter().copied().filter(|&k| k != i).collect();
            if others.is_empty() {
                return 0.0;
            }
            let wo: Vec<f64> = others.iter().map(|&k| w[k]).collect();
            let (m, _) = mean_offset(&others.iter().map(|&k| d[k]).collect::<Vec<f64>>(), &wo);
            let v = 1.0 / w[i] + 1.0 / wo.iter().sum::<f64>();
            wrap_half_pi(d[i] - m) / v.sqrt()
        })
        .collect()
}

/// The zero angle and sense from `stds` (see the module docs). `None` when no standard has a
/// finite, positive error.
///
/// Each sense is fitted with its own outliers left out (a wrong star can make the wrong sense
/// look better while it is in); the sense is the one whose kept stars scatter less (reduced
/// chi^2), decided only when the kept stars' catalogued angles differ by more than five times
/// their largest error. `chi2_other_sense` is the other sense's chi^2 over its own kept stars.
pub fn zero_angle(stds: &[StandardChi]) -> Option<ZeroAngle> {
    // Indices (into `stds`) of the usable standards.
    let idx: Vec<usize> = stds
        .iter()
        .enumerate()
        .filter(|(_, s)| {
            let v = s.sigma_measured.powi(2) + s.sigma_catalogue.powi(2);
            s.chi_measured.is_finite() && s.chi_catalogue.is_finite() && v.is_finite() && v > 0.0
        })
        .map(|(i, _)| i)
        .collect();
    if idx.is_empty() {
        return None;
    }
    let ok: Vec<&StandardChi> = idx.iter().map(|&i| &stds[i]).collect();
    let w: Vec<f64> = ok.iter().map(|s| 1.0 / (s.sigma_measured.powi(2) + s.sigma_catalogue.powi(2))).collect();
    let iau: Vec<f64> = ok.iter().map(|s| wrap_half_pi(s.chi_catalogue - s.chi_measured)).collect();
    let mir: Vec<f64> = ok.iter().map(|s| wrap_half_pi(s.chi_catalogue + s.chi_measured)).collect();
    let (ci, cm) = (clip(&iau, &w), clip(&mir, &w));
    // The sense can be told only when the kept stars' catalogued angles differ.
    let decidable = |c: &Clipped| {
        let c0 = ok[c.kept[0]].chi_catalogue;
        let spread = c.kept.iter().map(|&k| wrap_half_pi(ok[k].chi_catalogue - c0).abs()).fold(0.0, f64::max);
        let sig_max = c.kept.iter().map(|&k| ok[k].sigma_catalogue.max(ok[k].sigma_measured)).fold(0.0, f64::max);
        c.kept.len() >= 2 && spread > 5.0 * sig_max
    };
    let reduced = |c: &Clipped| c.chi2 / (c.kept.len().max(2) - 1) as f64;
    let (sense, best, offsets, other) = if !decidable(&ci) {
        (Sense::Undetermined, ci, iau, None)
    } else if !decidable(&cm) || reduced(&ci) <= reduced(&cm) {
        let o = cm.chi2;
        (Sense::Iau, ci, iau, Some(o))
    } else {
        let o = ci.chi2;
        (Sense::Mirrored, cm, mir, Some(o))
    };
    let sw: f64 = best.kept.iter().map(|&k| w[k]).sum();
    let sigma = 1.0 / sw.sqrt();
    let dof = best.kept.len() - 1;
    let sigma_scatter = (dof > 0).then(|| sigma * (best.chi2 / dof as f64).sqrt());
    let excluded: Vec<usize> = best.excluded.iter().map(|&k| idx[k]).collect();
    Some(ZeroAngle {
        offset: best.mean,
        sigma,
        chi2: best.chi2,
        dof,
        sense,
        chi2_other_sense: other,
        offsets,
        pulls: best.pulls,
        sigma_scatter,
        outlier: excluded.first().copied(),
        excluded,
    })
}

/// The least `P / sigma_P` of a standard whose angle is measured: below it `chi` is not
/// determined (`eq:sigchi`: `sigma_chi = sigma_P / (2 P)` rad, 9.5 deg at 3 sigma, and the
/// distribution of the measured angle departs from a Gaussian below that).
pub const MIN_P_SNR: f64 = 3.0;

/// Why standards could not give a zero angle; each names the star or the rows at fault.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("standard {label} at ({x}, {y}) has P = {:.3} +- {:.3} %: too little polarization to measure an angle (need P > {MIN_P_SNR} sigma)", 100.0 * .p, 100.0 * .sigma_p)]
    TooLittlePolarization { label: String, x: f64, y: f64, p: f64, sigma_p: f64 },
    #[error("the angles have no finite error")]
    NoFiniteError,
    #[error("some standards' angles have no finite error: cannot combine them")]
    SomeNoFiniteError,
}

/// One standard's measured and catalogued angle (deg), from frames or a file of earlier
/// measurements ([`read_measured`]): a row of the zero-angle report.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MeasuredStandard {
    /// The star's name, or its catalogued angle when given by number.
    pub label: String,
    /// Position (px; `None` for a row of a table without one).
    pub x: Option<f64>,
    pub y: Option<f64>,
    pub chi_measured_deg: f64,
    pub sigma_chi_measured_deg: f64,
    pub chi_catalogue_deg: f64,
    pub sigma_chi_catalogue_deg: f64,
    pub p_measured: Option<f64>,
    pub sigma_p_measured: Option<f64>,
    /// The catalogued `P` (fraction) and its error, when known (a named standard of the list,
    /// or a file's `p_catalogue` column): the polarimetric efficiency is `p_measured` over it
    /// ([`efficiency`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub p_catalogue: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_p_catalogue: Option<f64>,
    /// Where the measurement came from: "frames" or the file.
    #[serde(skip)]
    pub source: String,
}

impl MeasuredStandard {
    /// A standard measured in frames at `(x, y)` px with `P`, `chi` (rad, at the plate) and
    /// their errors, catalogued at `chi_catalogue_deg +- sigma_catalogue_deg`: refused when
    /// `P <= MIN_P_SNR sigma_P` (its angle is not measured). On a rotator `sky_pa_deg` is the
    /// frames' position angle on the sky (`skyfield::sky_angle::of_set`), added to the measured
    /// `chi` so that the zero angle found is the plate's alone, as catalogs of the instrument
    /// add both (a catalogued angle is north through east).
    #[allow(clippy::too_many_arguments)]
    pub fn from_frames(
        label: String,
        (x, y): (f64, f64),
        (p, sigma_p): (f64, f64),
        (chi, sigma_chi): (f64, f64),
        chi_catalogue_deg: f64,
        sigma_catalogue_deg: f64,
        sky_pa_deg: Option<f64>,
    ) -> Result<Self, Error> {
        if !(p > MIN_P_SNR * sigma_p) {
            return Err(Error::TooLittlePolarization { label, x, y, p, sigma_p });
        }
        let chi_measured_deg = match sky_pa_deg {
            Some(pa) => mueller::fold_pi(chi + pa.to_radians()).to_degrees(),
            None => chi.to_degrees(),
        };
        Ok(Self {
            label,
            x: Some(x),
            y: Some(y),
            chi_measured_deg,
            sigma_chi_measured_deg: sigma_chi.to_degrees(),
            chi_catalogue_deg,
            sigma_chi_catalogue_deg: sigma_catalogue_deg,
            p_measured: Some(p),
            sigma_p_measured: Some(sigma_p),
            p_catalogue: None,
            sigma_p_catalogue: None,
            source: "frames".into(),
        })
    }

    /// Check the angles: finite, errors in (0, 90) deg (measured) and [0, 90) deg (catalogue);
    /// `at` names the row in the error.
    fn check(&self, path: &Path, at: &str) -> crate::Result<()> {
        let bad = |what: String| crate::Error::BadFile { path: path.to_path_buf(), what: format!("{at}: {what}") };
        let (cm, sm, cc, sc) =
            (self.chi_measured_deg, self.sigma_chi_measured_deg, self.chi_catalogue_deg, self.sigma_chi_catalogue_deg);
        if !(cm.is_finite() && cc.is_finite() && sm.is_finite() && sc.is_finite()) {
            return Err(bad(format!("chi and its errors must be numbers (got chi_measured_deg {cm}, sigma_chi_measured_deg {sm}, chi_catalogue_deg {cc}, sigma_chi_catalogue_deg {sc})")));
        }
        if !(sm > 0.0 && sm < 90.0 && (0.0..90.0).contains(&sc)) {
            return Err(bad(format!(
                "errors must lie in (0, 90) deg (measured) and [0, 90) deg (catalogue), got {sm} and {sc}"
            )));
        }
        Ok(())
    }

    /// The angles in rad, as [`zero_angle`] takes them.
    pub fn chi(&self) -> StandardChi {
        StandardChi {
            chi_measured: self.chi_measured_deg.to_radians(),
            sigma_measured: self.sigma_chi_measured_deg.to_radians(),
            chi_catalogue: self.chi_catalogue_deg.to_radians(),
            sigma_catalogue: self.sigma_chi_catalogue_deg.to_radians(),
        }
    }
}

use std::path::Path;

/// The name a standard's measurements are merged by ([`merge_repeats`]).
fn key_of(m: &MeasuredStandard) -> String {
    m.label.trim().to_ascii_lowercase()
}

/// The polarimetric efficiency from polarized standards: the measured `P` over the catalogued
/// one, `eta = P_measured / P_catalogue`, averaged with weights `1 / sigma_eta^2`, where
/// `sigma_eta^2 = (sigma_P_measured / P_cat)^2 + (eta sigma_P_cat / P_cat)^2`; its error is
/// `1 / sqrt(sum w)`. Measurements of one star (one name and one catalogued `P`) are first
/// averaged (weights `1 / sigma_P^2`), so that the catalogue's error enters once, as
/// [`merge_repeats`] does for the angle. The measured `P` is not corrected for its bias: the
/// standards are measured at a signal-to-noise ratio where it is negligible (the bias is
/// `sigma_P^2 / (2 P)`, `sec:bias`). `None` when no row has a measured and a positive
/// catalogued `P` with finite errors.
pub fn efficiency(rows: &[MeasuredStandard]) -> Option<Efficiency> {
    // Each star: catalogued P and its error, sum of weights and of weighted P.
    let mut stars: Vec<(String, f64, f64, f64, f64)> = Vec::new();
    for m in rows {
        let (Some(p), Some(sp), Some(pc), Some(spc)) =
            (m.p_measured, m.sigma_p_measured, m.p_catalogue, m.sigma_p_catalogue)
        else {
            continue;
        };
        if !(p.is_finite() && sp.is_finite() && sp > 0.0 && pc.is_finite() && pc > 0.0 && spc.is_finite() && spc >= 0.0)
        {
            continue;
        }
        let w = sp.powi(-2);
        match stars.iter_mut().find(|s| s.0 == key_of(m) && s.1 == pc && m.label.trim().parse::<f64>().is_err()) {
            Some(s) => {
                s.3 += w;
                s.4 += w * p;
            }
            None => stars.push((key_of(m), pc, spc, w, w * p)),
        }
    }
    if stars.is_empty() {
        return None;
    }
    let (ratios, weights): (Vec<f64>, Vec<f64>) = stars
        .iter()
        .map(|&(_, pc, spc, sw, swp)| {
            let eta = swp / sw / pc;
            (eta, 1.0 / (1.0 / (sw * pc * pc) + (eta * spc / pc).powi(2)))
        })
        .unzip();
    let sw: f64 = weights.iter().sum();
    let eta = ratios.iter().zip(&weights).map(|(r, w)| r * w).sum::<f64>() / sw;
    let chi2: f64 = ratios.iter().zip(&weights).map(|(r, w)| w * (r - eta).powi(2)).sum();
    let dof = ratios.len() - 1;
    Some(Efficiency {
        efficiency: eta,
        sigma_efficiency: sw.sqrt().recip(),
        chi2_dof: (dof > 0).then(|| chi2 / dof as f64),
        n_standards: ratios.len(),
    })
}

/// The polarimetric efficiency of [`efficiency`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Efficiency {
    /// Measured `P` over catalogued `P` (fraction; 1: nothing lost).
    pub efficiency: f64,
    pub sigma_efficiency: f64,
    /// Reduced chi^2 of the stars' ratios about the mean; `None` with one star.
    pub chi2_dof: Option<f64>,
    /// Stars in the mean (measurements of one star counted once).
    pub n_standards: usize,
}

/// Measurements of one standard merged into one row, each star once: rows with the same name
/// (a name, not a catalogued angle given by number) and the same catalogued angle. Their
/// measured angles share the catalogue's error, so counting them as independent stars made the
/// zero angle's error too small by up to sqrt(n). The merged angle is the circular mean
/// (period 180 deg, `stokes::stats::circular`) of the measured ones weighted by
/// `1 / sigma^2`, whichever comes first; its error `1 / sqrt(sum w)`; the catalogue error then
/// enters once, which is the generalized least-squares combination of measurements that share
/// one error term. The merged row's source lists the sources; its position and P are the first
/// measurement's. A star measured once keeps its row bit for bit.
pub fn merge_repeats(rows: Vec<MeasuredStandard>) -> Vec<MeasuredStandard> {
    use stokes::stats::circular::{difference, direction, Period};
    let key = key_of;
    // Each star: its first row, and its rows' measured angles (rad) and weights.
    let mut out: Vec<(MeasuredStandard, Vec<f64>, Vec<f64>)> = Vec::with_capacity(rows.len());
    for m in rows {
        let w = m.sigma_chi_measured_deg.powi(-2);
        let same = out.iter().position(|(o, ..)| {
            key(o) == key(&m) && m.label.trim().parse::<f64>().is_err() && o.chi_catalogue_deg == m.chi_catalogue_deg
        });
        match same {
            Some(k) => {
                let (o, angles, weights) = &mut out[k];
                angles.push(m.chi_measured_deg.to_radians());
                weights.push(w);
                if !o.source.split(" + ").any(|s| s == m.source) {
                    o.source = format!("{} + {}", o.source, m.source);
                }
            }
            None => {
                let a = m.chi_measured_deg.to_radians();
                out.push((m, vec![a], vec![w]));
            }
        }
    }
    out.into_iter()
        .map(|(mut o, angles, weights)| {
            if angles.len() > 1 {
                // The rows were checked on reading (finite angles, errors in (0, 90) deg), so
                // the weights are finite and positive and a direction exists.
                // The mean is written on the first row's branch (170 deg stays near 170, not -10).
                if let Some(mean) = direction(&angles, &weights, Period::HalfTurn) {
                    o.chi_measured_deg += difference(mean.mean, angles[0], Period::HalfTurn).to_degrees();
                }
                o.sigma_chi_measured_deg = weights.iter().sum::<f64>().sqrt().recip();
            }
            o
        })
        .collect()
}

/// The standards of a file of earlier measurements and the filter it names (if any): the
/// `--json` output of `instpol zero-angle` (`.json`: its `filter` and `standards` array) or a
/// table in any format `skyfield::table` reads, with columns `label` (or `name`),
/// `chi_measured_deg`, `sigma_chi_measured_deg`, `chi_catalogue_deg`,
/// `sigma_chi_catalogue_deg`, and optionally `filter` (one for all rows), `x`, `y`,
/// `p_measured`, `sigma_p_measured`, `p_catalogue`, `sigma_p_catalogue`. The measured angles are at the plate; a table whose
/// zero-angle column (`hwp_chi_offset_deg`) says they carry a zero angle already
/// (`skyfield::table::Table::frame`) has it taken off ([`mueller::Frame::turn_to`]), or the
/// zero angle found would be what was left of it. Every row is checked (finite angles, errors
/// in (0, 90) deg, a catalogue error of 0 allowed) and named in errors; a row without a label
/// is called by the file and its row number.
pub fn read_measured(path: &Path) -> crate::Result<(Option<String>, Vec<MeasuredStandard>)> {
    let src = path.display().to_string();
    let bad = |what: String| crate::Error::BadFile { path: path.to_path_buf(), what };
    let is_json = path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("json"));
    let mut rows = Vec::new();
    let filter;
    if is_json {
        let text = std::fs::read_to_string(path).map_err(|err| crate::Error::Io { path: path.to_path_buf(), err })?;
        let v: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| bad(format!("not JSON ({e}): give a zero-angle --json output or a table")))?;
        let stars = v.get("standards").and_then(|s| s.as_array()).ok_or_else(|| {
            bad("no 'standards' array (expected the --json output of instpol zero-angle)".to_string())
        })?;
        filter = v.get("filter").and_then(|f| f.as_str()).map(str::to_string);
        for (i, s) in stars.iter().enumerate() {
            let at = format!("standards[{i}]");
            let num = |k: &str| -> crate::Result<f64> {
                s.get(k).and_then(|x| x.as_f64()).ok_or_else(|| bad(format!("{at}: no number '{k}'")))
            };
            let opt = |k: &str| s.get(k).and_then(|x| x.as_f64());
            let m = MeasuredStandard {
                label: s.get("label").and_then(|l| l.as_str()).unwrap_or("").to_string(),
                x: opt("x"),
                y: opt("y"),
                chi_measured_deg: num("chi_measured_deg")?,
                sigma_chi_measured_deg: num("sigma_chi_measured_deg")?,
                chi_catalogue_deg: num("chi_catalogue_deg")?,
                sigma_chi_catalogue_deg: num("sigma_chi_catalogue_deg")?,
                p_measured: opt("p_measured"),
                sigma_p_measured: opt("sigma_p_measured"),
                p_catalogue: opt("p_catalogue"),
                sigma_p_catalogue: opt("sigma_p_catalogue"),
                source: src.clone(),
            };
            m.check(path, &at)?;
            rows.push(m);
        }
    } else {
        let t = skyfield::table::Table::read(path, None)?;
        let num = |k: &str| t.numbers(k, path);
        let opt = |k: &str| -> crate::Result<Option<Vec<f64>>> {
            if t.column(k).is_some() {
                Ok(Some(num(k)?))
            } else {
                Ok(None)
            }
        };
        let text = |k: &str| -> Option<Vec<String>> {
            t.column(k).map(|c| match &c.data {
                skyfield::table::Data::Str(v) => v.iter().map(|s| s.trim().to_string()).collect(),
                skyfield::table::Data::F64(v) => v.iter().map(|x| x.to_string()).collect(),
                skyfield::table::Data::I64(v) => v.iter().map(|x| x.to_string()).collect(),
            })
        };
        // Back to the plate from the frame the table says (0 for one at the plate).
        let to_plate = t.frame(path)?.turn_to(0.0);
        let (cm, sm, cc, sc) = (
            num("chi_measured_deg")?.into_iter().map(|c| c + to_plate).collect::<Vec<_>>(),
            num("sigma_chi_measured_deg")?,
            num("chi_catalogue_deg")?,
            num("sigma_chi_catalogue_deg")?,
        );
        let (xs, ys, ps, sps) = (opt("x")?, opt("y")?, opt("p_measured")?, opt("sigma_p_measured")?);
        let (pcs, spcs) = (opt("p_catalogue")?, opt("sigma_p_catalogue")?);
        let labels = text("label").or_else(|| text("name"));
        let filters = text("filter");
        filter = match &filters {
            Some(f) => {
                let first = f.first().cloned().unwrap_or_default();
                if let Some(i) = f.iter().position(|x| !x.eq_ignore_ascii_case(&first)) {
                    return Err(bad(format!(
                        "{}: filter '{}' differs from the first row's '{first}': one filter per run",
                        t.row_label(i),
                        f[i]
                    )));
                }
                Some(first)
            }
            None => None,
        };
        let pick = |v: &Option<Vec<f64>>, i: usize| v.as_ref().map(|v| v[i]).filter(|x| x.is_finite());
        for i in 0..t.n_rows() {
            let m = MeasuredStandard {
                label: labels.as_ref().map(|l| l[i].clone()).unwrap_or_default(),
                x: pick(&xs, i),
                y: pick(&ys, i),
                chi_measured_deg: cm[i],
                sigma_chi_measured_deg: sm[i],
                chi_catalogue_deg: cc[i],
                sigma_chi_catalogue_deg: sc[i],
                p_measured: pick(&ps, i),
                sigma_p_measured: pick(&sps, i),
                p_catalogue: pick(&pcs, i),
                sigma_p_catalogue: pick(&spcs, i),
                source: src.clone(),
            };
            m.check(path, &t.row_label(i))?;
            rows.push(m);
        }
    }
    if rows.is_empty() {
        return Err(bad("no standards in the file".to_string()));
    }
    for (i, m) in rows.iter_mut().enumerate() {
        if m.label.is_empty() {
            m.label = format!("{src} row {}", i + 1);
        }
    }
    Ok((filter, rows))
}

/// One standard of a [`ZeroAngleReport`]: its measurement, its own offset (deg, in the sense
/// found) and its pull about the mean of the other (kept) stars.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StandardOffset {
    #[serde(flatten)]
    pub measured: MeasuredStandard,
    pub offset_deg: f64,
    pub pull: f64,
    /// Left out of the mean (it disagrees with the others).
    pub excluded: bool,
    /// Where the measurement came from: "frames" or the file.
    pub source: String,
}

/// The zero angle of a filter from its standards ([`zero_angle`]), in degrees, with every
/// star's offset: the report `instpol zero-angle --json` prints.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ZeroAngleReport {
    pub filter: String,
    pub zero_angle_deg: f64,
    pub sigma_zero_angle_deg: f64,
    pub sigma_scatter_zero_angle_deg: Option<f64>,
    pub chi2_dof: Option<f64>,
    /// Standards in the mean.
    pub n_standards: usize,
    pub sense: Sense,
    pub outlier: Option<String>,
    /// Labels of the standards left out of the mean, worst first.
    pub excluded: Vec<String>,
    pub standards: Vec<StandardOffset>,
    /// The line to put in the instrument file's filter entry.
    pub instrument_file_line: String,
    /// The polarimetric efficiency beside the zero angle, when the standards' catalogued `P`
    /// is known ([`efficiency`]; the stars left out of the zero angle left out of it too).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub efficiency: Option<Efficiency>,
    /// What the standards were measured in ([`ZeroAngleReport::with_product`]): the frames'
    /// instrument file, filter, plate and detector, the run's inputs; with tables alone, the
    /// filter and the inputs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub product: Option<skyfield::provenance::Product>,
}

/// Every filter a zero angle's inputs name must be one: a zero angle is a filter's.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    /// Nothing names a filter (tables without one, and no frames).
    #[error("no input names a filter")]
    None,
    /// Two inputs name different filters: each `(filter, where it is named)`.
    #[error("{} is in filter '{}', {} in '{}': a zero angle is per filter, combine one filter at a time", .other.1, .other.0, .first.1, .first.0)]
    Differ { first: (String, String), other: (String, String) },
}

/// The one filter of a zero angle's inputs: each `(filter, where it is named)` (frames,
/// tables, an option), compared as `inst` names its filters (aliases; without an
/// instrument, by name in any case). The first named is the one.
pub fn one_filter(named: &[(String, String)], inst: Option<&instrument::Instrument>) -> Result<String, FilterError> {
    let first = named.first().ok_or(FilterError::None)?;
    match named.iter().find(|(f, _)| !crate::correction::setup::same_filter(inst, f, &first.0)) {
        Some(other) => Err(FilterError::Differ { first: first.clone(), other: other.clone() }),
        None => Ok(first.0.clone()),
    }
}

impl ZeroAngleReport {
    /// The report with its product: of the frames' instrument `inst` in the report's filter,
    /// or, for tables alone (`None`), the filter; the run's inputs either way.
    pub fn with_product(self, inst: Option<&instrument::Instrument>) -> Self {
        let product = match inst {
            Some(i) => skyfield::provenance::Product::of_instrument(i, &self.filter, None),
            None => skyfield::provenance::Product { filter: Some(self.filter.clone()), ..Default::default() },
        };
        ZeroAngleReport { product: Some(product.with_run_inputs()), ..self }
    }

    /// Combine the standards of `filter` ([`zero_angle`]); every star must have a finite error.
    /// Measurements of one standard (the same name and catalogued angle) are first merged into
    /// one ([`merge_repeats`]): they share its catalogue error, so they are not independent.
    pub fn combine(filter: String, rows: Vec<MeasuredStandard>) -> Result<(Self, ZeroAngle), Error> {
        let all = rows.clone();
        let rows = merge_repeats(rows);
        let chis: Vec<StandardChi> = rows.iter().map(MeasuredStandard::chi).collect();
        let z = zero_angle(&chis).ok_or(Error::NoFiniteError)?;
        if z.offsets.len() != rows.len() {
            return Err(Error::SomeNoFiniteError);
        }
        let zd = z.offset.to_degrees();
        let instrument_file_line = format!("hwp_chi_offset_deg = {zd:.2}   # filter {filter}");
        let label = |k: usize| rows[k].label.clone();
        let left_out: Vec<String> = z.excluded.iter().map(|&k| key_of(&rows[k])).collect();
        let kept: Vec<MeasuredStandard> = all.into_iter().filter(|m| !left_out.contains(&key_of(m))).collect();
        let r = ZeroAngleReport {
            product: None,
            efficiency: efficiency(&kept),
            zero_angle_deg: zd,
            sigma_zero_angle_deg: z.sigma.to_degrees(),
            sigma_scatter_zero_angle_deg: z.sigma_scatter.map(f64::to_degrees),
            chi2_dof: (z.dof > 0).then(|| z.chi2 / z.dof as f64),
            n_standards: rows.len() - z.excluded.len(),
            sense: z.sense,
            outlier: z.outlier.map(label),
            excluded: z.excluded.iter().map(|&k| label(k)).collect(),
            filter,
            instrument_file_line,
            standards: rows
                .into_iter()
                .enumerate()
                .zip(z.offsets.iter().zip(&z.pulls))
                .map(|((k, m), (d, p))| StandardOffset {
                    source: m.source.clone(),
                    measured: m,
                    offset_deg: d.to_degrees(),
                    pull: *p,
                    excluded: z.excluded.contains(&k),
                })
                .collect(),
        };
        Ok((r, z))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn d(x: f64) -> f64 {
        x.to_radians()
    }

    /// Offsets that straddle the 180-deg wrap average to the right angle (a naive mean of
    /// 89 and -89 deg would give 0), and the weights and error are the textbook ones.
    #[test]
    fn offsets_across_the_wrap() {
        let s = [
            StandardChi {
                chi_measured: d(10.0),
                sigma_measured: d(0.5),
                chi_catalogue: d(99.0),
                sigma_catalogue: d(0.1),
            },
            StandardChi {
                chi_measured: d(10.0),
                sigma_measured: d(0.5),
                chi_catalogue: d(101.0),
                sigma_catalogue: d(0.1),
            },
        ];
        let z = zero_angle(&s).unwrap();
        assert!((z.offset.to_degrees().abs() - 90.0).abs() < 1e-9, "{}", z.offset.to_degrees());
        let sig1 = (0.5f64.powi(2) + 0.1f64.powi(2)).sqrt();
        assert!((z.sigma.to_degrees() - sig1 / 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(z.sense, Sense::Undetermined);
    }

    /// Three standards of different chi seen through a mirrored instrument with a 41.3 deg
    /// zero angle: the mirrored sense wins by a wide chi^2 margin and the offset comes back.
    #[test]
    fn mirrored_sense_is_recognized() {
        let off = 41.3;
        let s: Vec<StandardChi> = [12.0, 77.0, 140.0]
            .iter()
            .map(|&c: &f64| StandardChi {
                chi_measured: d(wrap_half_pi(d(off - c)).to_degrees().rem_euclid(180.0)),
                sigma_measured: d(0.3),
                chi_catalogue: d(c),
                sigma_catalogue: d(0.2),
            })
            .collect();
        let z = zero_angle(&s).unwrap();
        assert_eq!(z.sense, Sense::Mirrored);
        assert!((z.offset.to_degrees() - off).abs() < 1e-9);
        assert!(z.chi2 < 1e-12 && z.chi2_other_sense.unwrap() > 100.0);
        assert!(z.outlier.is_none() && z.sigma_scatter.unwrap() < 1e-9);
    }

    /// Four standards, one catalogued 3 deg off: its leave-one-out pull is the textbook
    /// `(d - mean of the others) / sqrt(sigma^2 + sigma^2 / 3)` (the three others agree
    /// exactly: residual 3 deg), it is named and left out, the others are not, and the result
    /// is the three others' (offset exact, chi^2 0, error sigma / sqrt 3).
    #[test]
    fn a_discrepant_standard_is_named() {
        let off = 10.0;
        let chis = [20.0, 60.0, 100.0, 150.0];
        let s: Vec<StandardChi> = chis
            .iter()
            .enumerate()
            .map(|(k, &c): (usize, &f64)| StandardChi {
                chi_measured: d(c - off),
                sigma_measured: d(0.3),
                chi_catalogue: d(c + if k == 2 { 3.0 } else { 0.0 }),
                sigma_catalogue: d(0.4),
            })
            .collect();
        let z = zero_angle(&s).unwrap();
        assert_eq!(z.sense, Sense::Iau);
        assert_eq!(z.outlier, Some(2));
        assert_eq!(z.excluded, vec![2]);
        let sig = 0.5f64; // hypot(0.3, 0.4)
        let want = 3.0 / (sig * (1.0 + 1.0 / 3.0f64).sqrt());
        assert!((z.pulls[2] - want).abs() < 1e-9, "{} vs {want}", z.pulls[2]);
        assert!(z.pulls.iter().enumerate().all(|(k, p)| k == 2 || p.abs() < 1e-9), "{:?}", z.pulls);
        assert!((z.offset.to_degrees() - off).abs() < 1e-9);
        assert!(z.chi2 < 1e-18 && z.dof == 2);
        assert!((z.sigma.to_degrees() - sig / 3f64.sqrt()).abs() < 1e-12);
        assert!(z.sigma_scatter.unwrap() < 1e-9);
    }

    /// Three good standards (offset 41.3 deg, errors 0.3 deg, one measured 0.2 deg off so the
    /// mean is not exact) and one catalogued 80 deg off: the bad one is named and left out,
    /// and the offset is the three good ones' weighted mean (written out here), within its
    /// error of the truth. A plain mean with the bad star would be ~10 deg away and would
    /// make the good stars the outliers.
    #[test]
    fn a_star_80_deg_off_does_not_drag_the_mean() {
        let off = 41.3;
        let rows = [(15.0, 0.0, 0.0), (70.0, 0.2, 0.0), (125.0, 0.0, 0.0), (160.0, 0.0, 80.0)];
        let s: Vec<StandardChi> = rows
            .iter()
            .map(|&(c, dm, dc): &(f64, f64, f64)| StandardChi {
                chi_measured: d((c - off + dm).rem_euclid(180.0)),
                sigma_measured: d(0.3),
                chi_catalogue: d((c + dc).rem_euclid(180.0)),
                sigma_catalogue: d(0.1),
            })
            .collect();
        let z = zero_angle(&s).unwrap();
        assert_eq!(z.outlier, Some(3), "{z:?}");
        assert_eq!(z.excluded, vec![3]);
        assert_eq!(z.sense, Sense::Iau);
        let mean = off - 0.2 / 3.0; // equal weights, small angles: the arithmetic mean
        assert!((z.offset.to_degrees() - mean).abs() < 1e-4, "{} vs {mean}", z.offset.to_degrees());
        assert!((z.offset.to_degrees() - off).abs() < 3.0 * z.sigma.to_degrees());
        assert!(z.pulls[3].abs() > 100.0 && z.pulls[..3].iter().all(|p| p.abs() < 1.0), "{:?}", z.pulls);
        // With two stars nothing is left out: either could be the wrong one.
        let z2 = zero_angle(&s[2..]).unwrap();
        assert!(z2.excluded.is_empty() && z2.outlier.is_none());
    }

    /// A star is measured only above P = 3 sigma_P; two rows of a table of earlier measurements
    /// (catalogue errors 0) give the mean of their offsets, 20 and 22 deg, weighted equally:
    /// 21 deg, the instrument-file line with it; a row with a measured error of 0 is refused
    /// naming the file and the row.
    #[test]
    fn measured_standards_selected_read_and_combined() {
        let at =
            |p: f64| MeasuredStandard::from_frames("s".into(), (1.0, 2.0), (p, 0.001), (0.1, 0.01), 30.0, 0.1, None);
        assert!(matches!(at(0.003), Err(Error::TooLittlePolarization { .. })));
        let m = at(0.0031).unwrap();
        assert_eq!(
            (m.chi_measured_deg, m.p_measured, m.source.as_str()),
            (0.1f64.to_degrees(), Some(0.0031), "frames")
        );
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.csv");
        let head = "label,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg,filter\n";
        std::fs::write(&path, format!("{head}a,10,0.5,30,0,V\nb,50,0.5,72,0,V\n")).unwrap();
        let (filter, rows) = read_measured(&path).unwrap();
        assert_eq!(filter.as_deref(), Some("V"));
        let (r, _) = ZeroAngleReport::combine("V".into(), rows).unwrap();
        assert!((r.zero_angle_deg - 21.0).abs() < 1e-9, "{r:?}");
        assert!((r.sigma_zero_angle_deg - 0.5 / 2f64.sqrt()).abs() < 1e-9, "{r:?}");
        assert_eq!(r.instrument_file_line, "hwp_chi_offset_deg = 21.00   # filter V");
        assert_eq!(r.standards[1].measured.label, "b");
        // The same measurements in the sky frame of a zero angle of 2.89 deg, saying so in the
        // column catalogs carry: the same zero angle.
        let sky = "label,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg,filter,hwp_chi_offset_deg\n";
        std::fs::write(&path, format!("{sky}a,12.89,0.5,30,0,V,2.89\nb,52.89,0.5,72,0,V,2.89\n")).unwrap();
        let (r2, _) = ZeroAngleReport::combine("V".into(), read_measured(&path).unwrap().1).unwrap();
        assert!((r2.zero_angle_deg - 21.0).abs() < 1e-9, "{r2:?}");
        std::fs::write(&path, format!("{head}a,10,0,30,0,V\n")).unwrap();
        let e = read_measured(&path).unwrap_err().to_string();
        assert!(e.contains("m.csv") && e.contains("row 1") && e.contains("(0, 90)"), "{e}");
    }

    /// Two measurements of one standard share its catalogue error: the zero angle is the
    /// generalized least-squares one, written out here by hand (the star's measurements
    /// averaged with weights 1/sigma^2, its catalogue variance added once, then the stars
    /// averaged), not the mean of three independent rows (which gave an error sqrt(3/2)
    /// too small for this set).
    #[test]
    fn repeated_measurements_of_a_standard_are_one_star() {
        let row = |label: &str, chi: f64, cat: f64, source: &str| MeasuredStandard {
            label: label.into(),
            x: None,
            y: None,
            chi_measured_deg: chi,
            sigma_chi_measured_deg: 1.0,
            chi_catalogue_deg: cat,
            sigma_chi_catalogue_deg: 0.5,
            p_measured: None,
            sigma_p_measured: None,
            p_catalogue: None,
            sigma_p_catalogue: None,
            source: source.into(),
        };
        let rows = vec![
            row("Vela1 95", 10.0, 40.0, "frames"),
            row("HD 154445", 70.0, 100.5, "frames"),
            row("vela1 95 ", 12.0, 40.0, "earlier.json"),
        ];
        let (r, _) = ZeroAngleReport::combine("V".into(), rows).unwrap();
        // Star A: measured 11 +- 1/sqrt(2), offset 29 with variance 1/2 + 1/4; star B: offset
        // 30.5 with variance 1 + 1/4.
        let (va, vb): (f64, f64) = (0.75, 1.25);
        // The mean of angles modulo 180 deg: the weighted mean of the doubled angles' vectors.
        let (sn, cs) = [(29.0f64, va), (30.5, vb)].iter().fold((0.0, 0.0), |(s, c), (o, v)| {
            (s + (2.0 * o.to_radians()).sin() / v, c + (2.0 * o.to_radians()).cos() / v)
        });
        let want = (0.5 * sn.atan2(cs)).to_degrees();
        let sigma = (1.0 / va + 1.0 / vb).powf(-0.5);
        assert!((r.zero_angle_deg - want).abs() < 1e-9, "{} vs {want}", r.zero_angle_deg);
        assert!((r.sigma_zero_angle_deg - sigma).abs() < 1e-9, "{} vs {sigma}", r.sigma_zero_angle_deg);
        assert_eq!(r.standards.len(), 2);
        assert_eq!(r.standards[0].source, "frames + earlier.json");
        // Different stars that share a catalogued angle given by number stay apart.
        let rows = vec![row("40", 10.0, 40.0, "a"), row("40", 12.0, 40.0, "b")];
        assert_eq!(merge_repeats(rows).len(), 2);
    }

    #[test]
    fn repeats_are_averaged_as_angles_whichever_comes_first() {
        let row = |chi: f64, sigma: f64| MeasuredStandard {
            label: "Vela1 95".into(),
            x: None,
            y: None,
            chi_measured_deg: chi,
            sigma_chi_measured_deg: sigma,
            chi_catalogue_deg: 40.0,
            sigma_chi_catalogue_deg: 0.5,
            p_measured: None,
            sigma_p_measured: None,
            p_catalogue: None,
            sigma_p_catalogue: None,
            source: "frames".into(),
        };
        // The closed form: the direction of the weighted sum of the doubled angles' unit
        // vectors, halved; compared modulo 180 deg.
        let truth = |chis: &[(f64, f64)]| {
            let (s, c) = chis.iter().fold((0.0, 0.0), |(s, c), (chi, sg)| {
                let a = 2.0 * chi.to_radians();
                (s + a.sin() / (sg * sg), c + a.cos() / (sg * sg))
            });
            (0.5 * s.atan2(c)).to_degrees()
        };
        let near = |a: f64, b: f64| ((a - b + 90.0).rem_euclid(180.0) - 90.0).abs() < 1e-9;
        // Across the wrap: 179 and 1 deg average to 0 deg, in either order, and the merged
        // angle stays on the first row's branch.
        for (a, b) in [(179.0, 1.0), (1.0, 179.0)] {
            let m = merge_repeats(vec![row(a, 1.0), row(b, 1.0)]);
            assert_eq!(m.len(), 1);
            assert!(near(m[0].chi_measured_deg, 0.0), "{a}, {b}: {}", m[0].chi_measured_deg);
            assert!((m[0].chi_measured_deg - a).abs() <= 1.0 + 1e-9, "{}", m[0].chi_measured_deg);
            assert!((m[0].sigma_chi_measured_deg - 0.5f64.sqrt()).abs() < 1e-12);
        }
        // Widely spread repeats: the mean does not depend on which row came first (a mean of
        // wrapped differences about the first row did: 59.3 deg from 0 first, 88.0 from 89).
        let chis = [(0.0, 1.0), (89.0, 1.0), (89.0, 1.0)];
        let want = truth(&chis);
        for order in [[0, 1, 2], [1, 0, 2], [1, 2, 0]] {
            let m = merge_repeats(order.iter().map(|&k| row(chis[k].0, chis[k].1)).collect());
            assert!(near(m[0].chi_measured_deg, want), "{order:?}: {} vs {want}", m[0].chi_measured_deg);
        }
        // Unequal weights.
        let chis = [(30.0, 1.0), (36.0, 2.0)];
        let m = merge_repeats(chis.iter().map(|&(c, s)| row(c, s)).collect());
        assert!(near(m[0].chi_measured_deg, truth(&chis)));
        assert!((m[0].sigma_chi_measured_deg - 1.25f64.recip().sqrt()).abs() < 1e-12);
    }

    /// The efficiency of two measurements of one star (P 3.60 and 3.64 % +- 0.04 %, catalogued
    /// 4.00 +- 0.02 %) and one of another (4.5 +- 0.05 % against 5.0 +- 0.03 %), written out:
    /// the first star's measurements averaged (equal weights), each star's ratio with the
    /// catalogue's error entered once, the ratios averaged with weights 1 / variance; a row
    /// without a catalogued P does not count, and none with one gives no efficiency.
    #[test]
    fn the_efficiency_of_standards_written_out() {
        let row = |label: &str, p: f64, sp: f64, pc: Option<f64>, spc: f64| MeasuredStandard {
            label: label.into(),
            x: None,
            y: None,
            chi_measured_deg: 10.0,
            sigma_chi_measured_deg: 1.0,
            chi_catalogue_deg: 12.0,
            sigma_chi_catalogue_deg: 0.5,
            p_measured: Some(p),
            sigma_p_measured: Some(sp),
            p_catalogue: pc,
            sigma_p_catalogue: Some(spc),
            source: "frames".into(),
        };
        let rows = vec![
            row("A", 0.0360, 0.0004, Some(0.04), 0.0002),
            row("B", 0.045, 0.0005, Some(0.05), 0.0003),
            row("a ", 0.0364, 0.0004, Some(0.04), 0.0002),
            row("C", 0.02, 0.0004, None, 0.0),
        ];
        let e = efficiency(&rows).unwrap();
        let (ea, va) =
            (0.0362 / 0.04, 0.0004f64.powi(2) / 2.0 / 0.04f64.powi(2) + (0.0362f64 / 0.04 * 0.0002 / 0.04).powi(2));
        let (eb, vb) = (0.9, (0.0005f64 / 0.05).powi(2) + (0.9 * 0.0003f64 / 0.05).powi(2));
        let want = (ea / va + eb / vb) / (1.0 / va + 1.0 / vb);
        assert!((e.efficiency - want).abs() < 1e-12, "{e:?} vs {want}");
        assert!((e.sigma_efficiency - (1.0 / va + 1.0 / vb).powf(-0.5)).abs() < 1e-12, "{e:?}");
        let chi2 = (ea - want).powi(2) / va + (eb - want).powi(2) / vb;
        assert!((e.chi2_dof.unwrap() - chi2).abs() < 1e-9 && e.n_standards == 2, "{e:?}");
        assert!(efficiency(&rows[3..]).is_none());
    }
}
