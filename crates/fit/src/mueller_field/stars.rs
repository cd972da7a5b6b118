//! The steps of a Mueller-field calibration around the fit ([`crate::mueller_field`]):
//! polarized standards read from a table as calibration inputs of their own known
//! polarization, turned into the sky frame of the maps they join, and the fitted field summed
//! up over its positions (what `instpol calibrate-mueller` reports).

use crate::correction::correct::Measurement;
use crate::mueller_field::{Kind, MuellerField};
use crate::{Error, Result};

/// The polarized standards of a star table (any format `skyfield::table` reads), each a
/// calibration "field" of one position whose known input polarization is the star's, named
/// "FILE row N (line L)": columns `x`, `y` (or `x_arcmin`, `y_arcmin`; arcmin from the detector
/// centre), `q`, `u`, `sigma_q`, `sigma_u` (measured, fractions), `p_true` (fraction),
/// `chi_true_deg` (or `chi_true`, deg) and optionally `sigma_true` (1-sigma of the true q, u).
/// The measured q, u are turned from the table's frame (the zero angle its column
/// `hwp_chi_offset_deg` carries, as `instpol catalog` writes it; at the plate without it:
/// `skyfield::table::Table::frame`) into the maps' sky frame of zero angle `zero_angle_deg`,
/// with their covariance ([`Measurement::in_sky`]). Rows with a non-finite value, an error <= 0,
/// or a `p_true` or measured P outside [0, 1) (percent given for a fraction) are refused, and so
/// is a star outside the detector the maps cover (`half_field`: its half width and half height
/// in arcmin, when known): a polynomial field fitted to it would be an extrapolation.
pub fn read_star_fields(
    path: &std::path::Path,
    zero_angle_deg: f64,
    half_field: Option<(f64, f64)>,
) -> Result<Vec<crate::mueller_field::CalField>> {
    use crate::mueller_field::{CalField, Observation};
    let t = skyfield::table::Table::read(path, None)?;
    let frame = t.frame(path)?;
    let bad = |what: String| Error::BadFile { path: path.to_path_buf(), what };
    let pick = |names: &[&str]| -> Result<Vec<f64>> {
        for n in names {
            if t.column(n).is_some() {
                return Ok(t.numbers(n, path)?);
            }
        }
        Err(bad(format!(
            "no column {} (columns: {}); need x, y (or x_arcmin, y_arcmin), q, u, sigma_q, sigma_u, p_true, chi_true_deg",
            names.join(" or "),
            t.names().join(", ")
        )))
    };
    let (x, y) = (pick(&["x_arcmin", "x"])?, pick(&["y_arcmin", "y"])?);
    let (q, u, sq, su) = (pick(&["q"])?, pick(&["u"])?, pick(&["sigma_q"])?, pick(&["sigma_u"])?);
    let (pt, ct) = (pick(&["p_true"])?, pick(&["chi_true_deg", "chi_true"])?);
    let st = if t.column("sigma_true").is_some() { t.numbers("sigma_true", path)? } else { vec![0.0; x.len()] };
    if x.is_empty() {
        return Err(bad("the star table has no data rows".into()));
    }
    let mut out = Vec::with_capacity(x.len());
    for i in 0..x.len() {
        let at = format!("{} {}", path.display(), t.row_label(i));
        let vals = [x[i], y[i], q[i], u[i], sq[i], su[i], pt[i], ct[i], st[i]];
        // Every row here calibrates through its catalogued polarization: an angle without a
        // degree (an unpolarized star written as a polarized one) is named as such.
        if pt[i].is_nan() && ct[i].is_finite() {
            let what = format!(
                "chi_true_deg = {} but p_true is empty: every star of the table needs its catalogued P (a fraction) and chi",
                ct[i]
            );
            return Err(Error::Row { at, what });
        }
        if !(vals.iter().all(|v| v.is_finite()) && sq[i] > 0.0 && su[i] > 0.0) || st[i] < 0.0 {
            let what = format!("x, y, q, u, sigma_q, sigma_u, p_true, chi_true_deg, sigma_true = {vals:?}: need finite values and errors > 0");
            return Err(Error::Row { at, what });
        }
        if !(0.0..1.0).contains(&pt[i]) || q[i].hypot(u[i]) >= 1.0 {
            let what = format!(
                "p_true = {} and the measured P = {} must be fractions in [0, 1) (not percent)",
                pt[i],
                q[i].hypot(u[i])
            );
            return Err(Error::Row { at, what });
        }
        if let Some((hx, hy)) = half_field.filter(|&(hx, hy)| x[i].abs() > 1.001 * hx || y[i].abs() > 1.001 * hy) {
            let what = format!(
                "x, y = ({}, {}) arcmin lies outside the maps' detector (+-{hx:.3} x +-{hy:.3} arcmin about its centre): a star the fields do not cover cannot calibrate them (positions are arcmin from the detector centre, not pixels)",
                x[i], y[i]
            );
            return Err(Error::Row { at, what });
        }
        let m = Measurement::at(x[i], y[i], mueller::Qu::from_sigmas(q[i], u[i], sq[i], su[i], 0.0), frame)
            .in_sky(zero_angle_deg);
        let obs = Observation::new(x[i], y[i], m.qu.q, m.qu.u, m.qu.var_q, m.qu.var_u, m.qu.cov_qu);
        out.push(CalField::from_p_chi(&at, pt[i], ct[i].to_radians(), st[i], vec![obs]));
    }
    Ok(out)
}

/// A summary's typical value: the upper middle of the finite values (always one of the
/// positions' values), NaN when none is finite.
fn typical(v: Vec<f64>) -> f64 {
    stokes::stats::robust::finite_median(v, stokes::stats::robust::Middle::Upper).unwrap_or(f64::NAN)
}

/// One free parameter of a Mueller field over the observed positions.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ParamSummary {
    pub name: &'static str,
    pub median_value: f64,
    pub rms_value: f64,
    pub median_sigma: f64,
}

/// A Mueller field summed up over the positions it was fitted at: each free parameter's median
/// and RMS and the median of its error, and the physical diattenuation and retardance
/// (`MuellerField::physical_at`): their median and largest values.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldSummary {
    pub parameters: Vec<ParamSummary>,
    pub median_p: Option<f64>,
    pub max_p: Option<f64>,
    /// When the retardance is free.
    pub median_retardance_deg: Option<f64>,
    pub max_retardance_deg: Option<f64>,
}

impl FieldSummary {
    /// The summary of `mf` (of model `kind`) at `positions` (arcmin).
    pub fn new(mf: &MuellerField, kind: Kind, positions: &[(f64, f64)]) -> Self {
        let nf = mf.free.len();
        let mut parameters = Vec::new();
        for (k, &i) in mf.free.iter().enumerate() {
            let (mut vals, mut sig) = (Vec::new(), Vec::new());
            for &(x, y) in positions {
                let (v, c) = mf.params_at(x, y);
                vals.push(v[k]);
                sig.push(c[k * nf + k].max(0.0).sqrt());
            }
            let rms = (vals.iter().map(|v| v * v).sum::<f64>() / vals.len() as f64).sqrt();
            parameters.push(ParamSummary {
                name: kind.name(i),
                median_value: typical(vals),
                rms_value: rms,
                median_sigma: typical(sig),
            });
        }
        let phys: Vec<_> = positions.iter().filter_map(|&(x, y)| mf.physical_at(x, y)).collect();
        let has_ret = mf.free.contains(&2);
        let (median_p, max_p) = if phys.is_empty() {
            (None, None)
        } else {
            (Some(typical(phys.iter().map(|p| p.p).collect())), Some(phys.iter().map(|p| p.p).fold(0.0, f64::max)))
        };
        let (median_retardance_deg, max_retardance_deg) = if has_ret && !phys.is_empty() {
            let d: Vec<f64> = phys.iter().map(|p| p.retardance.to_degrees()).collect();
            (Some(typical(d.clone())), Some(d.iter().cloned().fold(0.0, f64::max)))
        } else {
            (None, None)
        };
        FieldSummary { parameters, median_p, max_p, median_retardance_deg, max_retardance_deg }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A star measured at the plate (q = 1 %, u = 0, no carried zero angle) is turned by the
    /// maps' zero angle of 10 deg: (q, u) = 1 % (cos 20 deg, sin 20 deg), its sky the catalogued
    /// p, chi; a row carrying the 10 deg already is not turned; P in percent is refused naming
    /// the row.
    #[test]
    fn star_table_rows_turned_into_the_maps_frame() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("stars.csv");
        let head = "x,y,q,u,sigma_q,sigma_u,p_true,chi_true_deg";
        std::fs::write(&path, format!("{head}\n1,2,0.01,0,1e-4,1e-4,0.02,30\n")).unwrap();
        let f = read_star_fields(&path, 10.0, None).unwrap();
        let o = &f[0].obs[0];
        let t = 20f64.to_radians();
        assert!((o.qu.q - 0.01 * t.cos()).abs() < 1e-15 && (o.qu.u - 0.01 * t.sin()).abs() < 1e-15, "{o:?}");
        assert!((o.x_arcmin, o.y_arcmin) == (1.0, 2.0) && (o.qu.var_q - 1e-8).abs() < 1e-20);
        let c = 60f64.to_radians();
        assert!((f[0].sky_q - 0.02 * c.cos()).abs() < 1e-15 && (f[0].sky_u - 0.02 * c.sin()).abs() < 1e-15);
        assert!(f[0].name.ends_with("stars.csv row 1 (line 2)"), "{}", f[0].name);
        std::fs::write(&path, format!("{head},hwp_chi_offset_deg\n1,2,0.01,0,1e-4,1e-4,0.02,30,10\n")).unwrap();
        assert_eq!(read_star_fields(&path, 10.0, None).unwrap()[0].obs[0].qu.q, 0.01);
        std::fs::write(&path, format!("{head}\n1,2,0.01,0,1e-4,1e-4,2,30\n")).unwrap();
        let e = read_star_fields(&path, 0.0, None).unwrap_err().to_string();
        assert!(e.contains("stars.csv row 1") && e.contains("p_true"), "{e}");
        // An angle without its degree is named as what it is.
        std::fs::write(&path, format!("{head}\n1,2,0.01,0,1e-4,1e-4,0.02,30\n1,2,0.01,0,1e-4,1e-4,,30\n")).unwrap();
        let e = read_star_fields(&path, 0.0, None).unwrap_err().to_string();
        assert!(e.contains("stars.csv row 2") && e.contains("p_true is empty"), "{e}");
    }

    /// The summary's median is the upper middle of the finite values.
    #[test]
    fn median_is_the_upper_middle_of_the_finite() {
        assert_eq!(typical(vec![4.0, f64::NAN, 1.0, 3.0, 2.0]), 3.0);
        assert_eq!(typical(vec![2.0, 1.0, 3.0]), 2.0);
        assert!(typical(vec![f64::NAN]).is_nan());
    }
}
