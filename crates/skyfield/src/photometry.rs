//! Aperture photometry of a point source in both beams at every HWP angle, with the local
//! background measured in an annulus and subtracted *beam by beam, before* `F_i`: the
//! background's polarization is then removed vectorially (section `sec:background`), and the
//! result feeds the one reduction of the `stokes` crate (`stokes::Measurement`).
//!
//! Pixels are in electrons (bias removed, times the gain). A pixel belongs to the aperture when
//! its centre lies within `radius_px` of the source; the annulus `[r_in, r_out)` gives the
//! background per pixel as a sigma-clipped mean (so neighbouring stars and cosmic rays do not
//! bias it). Errors per beam: photon noise of the aperture counts, read noise, and the error of
//! the background mean times the aperture area.

use crate::beams::BeamGeometry;
use crate::bin::{sigma_clip_columns, ClipConfig};
use crate::reduce::FrameSet;
use crate::Error;
use instrument::Instrument;

/// Aperture and background annulus (px).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Aperture {
    pub radius_px: f64,
    /// `(r_in, r_out)`; `None`: no background subtraction (the section-background combined
    /// values).
    pub annulus: Option<(f64, f64)>,
}

/// The photometry of one source and its reduction.
#[derive(Debug, Clone)]
pub struct StarPhotometry {
    /// Source position (px, o coordinates).
    pub x: f64,
    pub y: f64,
    pub hwp_deg: Vec<f64>,
    /// Background-subtracted fluxes (e-) and their errors, per HWP angle.
    pub f_o: Vec<f64>,
    pub f_e: Vec<f64>,
    pub sigma_o: Vec<f64>,
    pub sigma_e: Vec<f64>,
    /// Background per pixel (e-) in each beam, per HWP angle (0 without annulus).
    pub bg_o: Vec<f64>,
    pub bg_e: Vec<f64>,
    pub n_aperture: usize,
    pub n_annulus: usize,
    pub reduction: stokes::Reduction,
}

/// Measure the source at `(x, y)` (0-based px, o coordinates) in every frame of `set`.
pub fn photometry(set: &FrameSet, inst: &Instrument, x: f64, y: f64, ap: &Aperture) -> Result<StarPhotometry, Error> {
    if !(ap.radius_px > 0.0) {
        return Err(Error::Invalid(format!("aperture radius {} px must be positive", ap.radius_px)));
    }
    if let Some((a, b)) = ap.annulus {
        if !(a >= ap.radius_px && b > a) {
            return Err(Error::Invalid(format!(
                "annulus ({a}, {b}) px must lie outside the aperture (radius {}) with r_in < r_out",
                ap.radius_px
            )));
        }
    }
    let g = BeamGeometry::new(inst);
    if !(x.is_finite() && y.is_finite()) || x < 0.0 || y < 0.0 || x >= g.nx as f64 || y >= g.ny as f64 {
        return Err(Error::Invalid(format!(
            "source position ({x}, {y}) px is outside the {} x {} detector",
            g.nx, g.ny
        )));
    }
    if g.strip_of_sky(x.round() as usize, y.round() as usize).is_none() {
        return Err(Error::Invalid(format!(
            "source position ({x:.1}, {y:.1}) px is behind the focal-plane mask: the sky there is not imaged (sky bands: {:?})",
            g.sky_bands()
        )));
    }
    // The frames' own conversion: the instrument's ADU, or electrons for calibrated frames.
    let (bias, gain, sat, rn2) = set.conversion.det();
    let rmax = ap.annulus.map_or(ap.radius_px, |(_, b)| b);
    let (x0, x1) = ((x - rmax).floor().max(0.0) as usize, ((x + rmax).ceil() as usize).min(g.nx - 1));
    let (y0, y1) = ((y - rmax).floor().max(0.0) as usize, ((y + rmax).ceil() as usize).min(g.ny - 1));
    let mut ap_px = Vec::new();
    let mut ann_px = Vec::new();
    for py in y0..=y1 {
        for px in x0..=x1 {
            let r2 = (px as f64 - x).powi(2) + (py as f64 - y).powi(2);
            let beams = g.beams_of_sky(px, py);
            if r2 <= ap.radius_px * ap.radius_px {
                let Some(b) = beams else {
                    return Err(Error::Invalid(format!(
                        "aperture of radius {} px at ({x:.1}, {y:.1}) reaches pixel ({px}, {py}) behind the mask; use a smaller aperture",
                        ap.radius_px
                    )));
                };
                ap_px.push(b);
            } else if let (Some((a, bo)), Some(b)) = (ap.annulus, beams) {
                if r2 >= a * a && r2 < bo * bo {
                    ann_px.push(b);
                }
            }
        }
    }
    let n = set.angles_deg.len();
    let (mut f_o, mut f_e, mut s_o, mut s_e, mut bg_o, mut bg_e) =
        (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    let mut n_ann = 0;
    for (i, data) in set.data.iter().enumerate() {
        let nexp = set.files[i].len() as f64;
        let to_e = |v: f64| (v - bias * nexp) * gain;
        let (mut so, mut se) = (0.0, 0.0);
        for &(o, e) in &ap_px {
            for (idx, beam) in [(o, "o"), (e, "e")] {
                let v = data[idx];
                if v <= crate::io::GAP_LIMIT {
                    return Err(Error::Invalid(format!(
                        "aperture pixel ({}, {}) of the {beam} beam lies in the gap between the chips; photometry needs clean aperture pixels",
                        idx % g.nx,
                        idx / g.nx
                    )));
                }
                if !v.is_finite() || v >= sat * nexp {
                    return Err(Error::Invalid(format!(
                        "aperture pixel ({}, {}) of the {beam} beam in {} is {}; photometry needs clean aperture pixels",
                        idx % g.nx,
                        idx / g.nx,
                        set.files[i][0].display(),
                        if v.is_finite() { "saturated".to_string() } else { v.to_string() }
                    )));
                }
            }
            so += to_e(data[o]);
            se += to_e(data[e]);
        }
        let na = ap_px.len() as f64;
        let (mut vo, mut ve) = (so.max(0.0) + na * nexp * rn2, se.max(0.0) + na * nexp * rn2);
        if ap.annulus.is_some() {
            let vals_o: Vec<f64> = ann_px.iter().map(|&(o, _)| data[o]).collect();
            let vals_e: Vec<f64> = ann_px.iter().map(|&(_, e)| data[e]).collect();
            let ok: Vec<usize> = (0..ann_px.len())
                .filter(|&k| {
                    vals_o[k].is_finite()
                        && vals_e[k].is_finite()
                        && vals_o[k] < sat * nexp
                        && vals_e[k] < sat * nexp
                        && vals_o[k] > crate::io::GAP_LIMIT
                        && vals_e[k] > crate::io::GAP_LIMIT
                })
                .collect();
            if ok.len() < 5 {
                return Err(Error::Invalid(format!(
                    "background annulus at ({x:.1}, {y:.1}) has {} usable sky pixels (need 5): move it or widen it",
                    ok.len()
                )));
            }
            let eo: Vec<f64> = ok.iter().map(|&k| to_e(vals_o[k])).collect();
            let ee: Vec<f64> = ok.iter().map(|&k| to_e(vals_e[k])).collect();
            let (mo, vmo, ko) = clipped_mean(&eo);
            let (me, vme, _) = clipped_mean(&ee);
            n_ann = ko;
            bg_o[i] = mo;
            bg_e[i] = me;
            so -= na * mo;
            se -= na * me;
            vo += na * na * vmo;
            ve += na * na * vme;
        }
        f_o[i] = so;
        f_e[i] = se;
        s_o[i] = vo.sqrt();
        s_e[i] = ve.sqrt();
    }
    if let Some(i) = (0..n).find(|&i| !(f_o[i] + f_e[i] > 0.0)) {
        return Err(Error::Invalid(format!(
            "no source at ({x:.1}, {y:.1}) px: the background-subtracted flux f_O + f_E = {:.1} e- at HWP angle {} deg ({}) is not positive",
            f_o[i] + f_e[i],
            set.angles_deg[i],
            set.files[i].iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" + ")
        )));
    }
    let theta: Vec<f64> = set.angles_deg.iter().map(|a| a.to_radians()).collect();
    let m = stokes::Measurement::with_errors(theta, f_o.clone(), f_e.clone(), s_o.clone(), s_e.clone())?;
    let reduction = m.reduce()?;
    Ok(StarPhotometry {
        x,
        y,
        hwp_deg: set.angles_deg.clone(),
        f_o,
        f_e,
        sigma_o: s_o,
        sigma_e: s_e,
        bg_o,
        bg_e,
        n_aperture: ap_px.len(),
        n_annulus: n_ann,
        reduction,
    })
}

/// Sigma-clipped mean, the variance of that mean, and the number kept.
fn clipped_mean(v: &[f64]) -> (f64, f64, usize) {
    let keep = sigma_clip_columns(&[v], ClipConfig::default());
    let kept: Vec<f64> = v.iter().zip(&keep).filter(|(_, &k)| k).map(|(x, _)| *x).collect();
    let n = kept.len() as f64;
    let m = kept.iter().sum::<f64>() / n;
    let var = if n > 1.0 { kept.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0) } else { 0.0 };
    (m, var / n, kept.len())
}
