//! Aperture photometry of a point source in both beams at every HWP angle, with the local
//! background measured in an annulus and subtracted *beam by beam, before* `F_i`: the
//! background's polarization is then removed vectorially (section `sec:background`), and the
//! result feeds the one reduction of the `stokes` crate (`stokes::Measurement`).
//!
//! Pixels are in electrons (bias removed, times the gain). The o aperture sits at the source
//! (re-centred in each frame on the star's centroid by default, since real frames move by a
//! pixel or two between HWP positions), the e aperture where the beam layout puts the e image
//! of that point ([`BeamGeometry::e_position`]: a whole-pixel throw for FORS strips, a 2-D
//! sub-pixel vector for a maskless calcite). Edge pixels weigh by the exact fraction of their
//! area inside the circle ([`crate::aperture`]), so that both beams get the same aperture at
//! any sub-pixel phase. The annulus `[r_in, r_out)` (whole pixels of the same beam) gives the
//! background per pixel as a sigma-clipped mean (so neighbouring stars and cosmic rays do not
//! bias it). Errors per beam: photon noise of the aperture counts, read noise, and the error of
//! the background mean times the aperture area.

use crate::aperture::{centroid, weights, Weighting};
use crate::beams::{BeamGeometry, PixelKind};
use crate::bin::{with_clipped, ClipConfig, ClipHint};
use crate::frame::Conversion;
use crate::layout::{layout_of_image, oe_offset_of_image};
use crate::reduce::FrameSet;
use crate::Error;
use instrument::{Instrument, Layout};
use std::path::{Path, PathBuf};

/// Aperture and background annulus (px).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Aperture {
    pub radius_px: f64,
    /// `(r_in, r_out)`; `None`: no background subtraction (the section-background combined
    /// values).
    pub annulus: Option<(f64, f64)>,
}

/// How the apertures are placed and weighed.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PhotOptions {
    /// Exact pixel-area weights (default) or whole pixels by their centre.
    pub weighting: Weighting,
    /// Re-centre the o aperture on the star's centroid in every frame (default), searching
    /// within the aperture radius of the given position.
    pub recentre: bool,
    /// The Wollaston imbalance: as measured (default), a known kappa, or estimated from the
    /// star's own `F_i` and applied in the same run.
    pub kappa: stokes::KappaCorrection,
}

impl Default for PhotOptions {
    fn default() -> Self {
        Self { weighting: Weighting::Exact, recentre: true, kappa: stokes::KappaCorrection::None }
    }
}

/// The photometry of one source and its reduction.
#[derive(Debug, Clone)]
pub struct StarPhotometry {
    /// Source position as given (px, o coordinates).
    pub x: f64,
    pub y: f64,
    pub hwp_deg: Vec<f64>,
    /// Aperture centres per HWP angle: `[x_o, y_o, x_e, y_e]` (px).
    pub centres: Vec<[f64; 4]>,
    /// Background-subtracted fluxes (e-) and their errors, per HWP angle.
    pub f_o: Vec<f64>,
    pub f_e: Vec<f64>,
    pub sigma_o: Vec<f64>,
    pub sigma_e: Vec<f64>,
    /// Background per pixel (e-) in each beam, per HWP angle (0 without annulus).
    pub bg_o: Vec<f64>,
    pub bg_e: Vec<f64>,
    /// Aperture area (px, the sum of the weights) and annulus pixels kept.
    pub n_aperture: usize,
    pub aperture_area_px: f64,
    pub n_annulus: usize,
    pub reduction: stokes::Reduction,
    /// The kappa applied to the fluxes before `reduction` (`f_o`, `f_e` above are as measured).
    pub kappa_applied: Option<f64>,
}

/// Measure the source at `(x, y)` (0-based px, o coordinates) in every frame of `set`, with
/// the default options (exact weights, re-centring) and the instrument's own layout.
pub fn photometry(set: &FrameSet, inst: &Instrument, x: f64, y: f64, ap: &Aperture) -> Result<StarPhotometry, Error> {
    let g = layout_for(set, inst)?;
    photometry_with(set, &g, x, y, ap, &PhotOptions::default())
}

/// The instrument's layout for these frames: for a maskless layout without a given o/e
/// offset, the offset measured from the frames' stars ([`measure_oe_offset`]).
pub fn layout_for(set: &FrameSet, inst: &Instrument) -> Result<BeamGeometry, Error> {
    let img = set.data.first().ok_or(Error::NoFrames)?;
    layout_of_image(img, set.nx, set.ny, &set.files[0][0], &inst.for_filter(&set.filter))
}

/// Check the aperture and annulus radii.
fn check_aperture(ap: &Aperture) -> Result<(), Error> {
    if !(ap.radius_px > 0.0 && ap.radius_px.is_finite()) {
        return Err(Error::Invalid(format!("aperture radius {} px must be positive", ap.radius_px)));
    }
    if let Some((a, b)) = ap.annulus {
        if !(a >= ap.radius_px && b > a && b.is_finite()) {
            return Err(Error::Invalid(format!(
                "annulus ({a}, {b}) px must lie outside the aperture (radius {}) with r_in < r_out",
                ap.radius_px
            )));
        }
    }
    Ok(())
}

/// [`photometry`] with a given layout `g` (e.g. with a measured maskless offset) and options.
pub fn photometry_with(
    set: &FrameSet,
    g: &BeamGeometry,
    x: f64,
    y: f64,
    ap: &Aperture,
    opts: &PhotOptions,
) -> Result<StarPhotometry, Error> {
    let out = measure_fluxes(set, g, x, y, ap, opts)?;
    finish(out, &set.files, x, y, opts)
}

/// The photometry of one source through a quarter-wave plate and its `V/I`
/// (`stokes::circular`): the same apertures, backgrounds and errors as [`StarPhotometry`], the
/// fluxes demodulated by [`stokes::CircularSolver`] at the plate's axis angles (the frames'
/// plate angles plus the filter's `qwp_zero_angle_deg`). `P` and `chi` are not given: the
/// 2- and 4-position sets (-45, 45, 135, 225 deg) do not determine `q` and `u`.
#[derive(Debug, Clone)]
pub struct CircularPhotometry {
    /// Source position as given (px, o coordinates).
    pub x: f64,
    pub y: f64,
    /// The frames' plate angles (deg, as the headers or `--hwp-angles` give them).
    pub hwp_deg: Vec<f64>,
    /// The zero angle the demodulation added to them (deg).
    pub zero_angle_deg: f64,
    /// Aperture centres per plate angle: `[x_o, y_o, x_e, y_e]` (px).
    pub centres: Vec<[f64; 4]>,
    /// Background-subtracted fluxes (e-) and their errors, per plate angle.
    pub f_o: Vec<f64>,
    pub f_e: Vec<f64>,
    pub sigma_o: Vec<f64>,
    pub sigma_e: Vec<f64>,
    /// `V/I` and its variance.
    pub circular: stokes::Circular,
}

/// Measure the source at `(x, y)` (0-based px, o coordinates) in every frame of `set` taken
/// through a quarter-wave plate whose fast axis sits at the frames' angles plus
/// `zero_angle_deg`, with layout `g` and options `opts` (its `kappa` is not used: the
/// demodulation's offset term takes the beams' ratio). Errors as [`photometry_with`], and the
/// angle sets that do not determine `V` (`stokes::Error::CircularUndetermined`).
pub fn circular_with(
    set: &FrameSet,
    g: &BeamGeometry,
    x: f64,
    y: f64,
    ap: &Aperture,
    opts: &PhotOptions,
    zero_angle_deg: f64,
) -> Result<CircularPhotometry, Error> {
    if set.hwp_sweep_deg != 0.0 {
        return Err(Error::Invalid(format!(
            "the frames' plate swept {} deg during each exposure: a turning quarter-wave plate is not modelled",
            set.hwp_sweep_deg
        )));
    }
    let solver = circular_solver(&set.angles_deg, zero_angle_deg)?;
    let out = measure_fluxes(set, g, x, y, ap, opts)?;
    finish_circular(out, &set.files, x, y, &solver, zero_angle_deg)
}

pub use crate::reduce::circular_solver;

/// [`finish`] through a quarter-wave plate: refused where `f_O + f_E` is not positive, else
/// `V/I` by `solver`.
pub(crate) fn finish_circular(
    out: Partial,
    files: &[Vec<PathBuf>],
    x: f64,
    y: f64,
    solver: &stokes::CircularSolver,
    zero_angle_deg: f64,
) -> Result<CircularPhotometry, Error> {
    if let Some(i) = (0..out.hwp_deg.len()).find(|&i| !(out.f_o[i] + out.f_e[i] > 0.0)) {
        return Err(Error::Invalid(format!(
            "no source at ({x:.1}, {y:.1}) px: the background-subtracted flux f_O + f_E = {:.1} e- at plate angle {} deg ({}) is not positive",
            out.f_o[i] + out.f_e[i],
            out.hwp_deg[i],
            files[i].iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" + ")
        )));
    }
    let circular = solver.solve_fluxes(&out.f_o, &out.f_e, &out.sigma_o, &out.sigma_e)?;
    Ok(CircularPhotometry {
        x,
        y,
        hwp_deg: out.hwp_deg,
        zero_angle_deg,
        centres: out.centres,
        f_o: out.f_o,
        f_e: out.f_e,
        sigma_o: out.sigma_o,
        sigma_e: out.sigma_e,
        circular,
    })
}

/// [`circular_with`] with the default options, the instrument's own layout and its filter's
/// quarter-wave zero angle (`qwp_zero_angle_deg`; 0 for a filter the instrument does not know).
pub fn circular(set: &FrameSet, inst: &Instrument, x: f64, y: f64, ap: &Aperture) -> Result<CircularPhotometry, Error> {
    let g = layout_for(set, inst)?;
    let zero = inst.filter(&set.filter).map_or(0.0, |f| f.qwp_zero_angle_deg());
    circular_with(set, &g, x, y, ap, &PhotOptions::default(), zero)
}

/// The reduction of a source's fluxes in every frame (`files`: each angle's exposures, for
/// messages): refused where `f_O + f_E` is not positive (no source there), else the one
/// Stokes solver with the kappa correction `opts` asks for.
pub(crate) fn finish(
    out: Partial,
    files: &[Vec<PathBuf>],
    x: f64,
    y: f64,
    opts: &PhotOptions,
) -> Result<StarPhotometry, Error> {
    let n = out.hwp_deg.len();
    if let Some(i) = (0..n).find(|&i| !(out.f_o[i] + out.f_e[i] > 0.0)) {
        return Err(Error::Invalid(format!(
            "no source at ({x:.1}, {y:.1}) px: the background-subtracted flux f_O + f_E = {:.1} e- at HWP angle {} deg ({}) is not positive",
            out.f_o[i] + out.f_e[i],
            out.hwp_deg[i],
            files[i].iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" + ")
        )));
    }
    let theta: Vec<f64> = out.hwp_deg.iter().map(|a| a.to_radians()).collect();
    let m = stokes::Measurement::with_errors(
        theta,
        out.f_o.clone(),
        out.f_e.clone(),
        out.sigma_o.clone(),
        out.sigma_e.clone(),
    )?;
    // A turning plate: every exposure swept the same range, demodulated with its efficiency.
    let m = if out.hwp_sweep_deg == 0.0 { m } else { m.with_sweeps(vec![out.hwp_sweep_deg.to_radians(); n])? };
    let (reduction, kappa_applied) = m.reduce_with(opts.kappa)?;
    let Partial {
        hwp_deg,
        hwp_sweep_deg: _,
        centres,
        f_o,
        f_e,
        sigma_o,
        sigma_e,
        bg_o,
        bg_e,
        n_aperture,
        aperture_area_px,
        n_annulus,
    } = out;
    Ok(StarPhotometry {
        x,
        y,
        hwp_deg,
        centres,
        f_o,
        f_e,
        sigma_o,
        sigma_e,
        bg_o,
        bg_e,
        n_aperture,
        aperture_area_px,
        n_annulus,
        reduction,
        kappa_applied,
    })
}

/// The beams' background-subtracted fluxes and errors of the source at `(x, y)` in every
/// frame of `set` (the measuring half of [`photometry_with`], shared with
/// [`exposure_checks`]): the placement checked once, then each frame measured.
fn measure_fluxes(
    set: &FrameSet,
    g: &BeamGeometry,
    x: f64,
    y: f64,
    ap: &Aperture,
    opts: &PhotOptions,
) -> Result<Partial, Error> {
    check_placement(g, x, y, ap, opts)?;
    let m = (0..set.data.len())
        .map(|i| measure_frame(&set.data[i], g, x, y, ap, opts, &FrameFacts::of(set, i)))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Partial::from_frames(&set.angles_deg, set.hwp_sweep_deg, &m))
}

/// What the measurement of one frame needs besides its pixels: how its values become
/// electrons, how many exposures it sums, and its file and HWP angle for messages.
#[derive(Debug, Clone)]
pub(crate) struct FrameFacts<'a> {
    pub conversion: Conversion,
    pub nexp: usize,
    pub file: &'a Path,
    pub hwp_deg: f64,
    /// The chip files of the exposure with their places (empty for a plain frame).
    pub chips: &'a [crate::frame::ChipPlace],
}

impl<'a> FrameFacts<'a> {
    /// Angle `i` of `set`.
    pub(crate) fn of(set: &'a FrameSet, i: usize) -> Self {
        Self {
            conversion: set.conversion,
            nexp: set.files[i].len(),
            file: &set.files[i][0],
            hwp_deg: set.angles_deg[i],
            chips: set.chips.get(i).map_or(&[], |c| c.as_slice()),
        }
    }
}

/// One frame's measurement of a source: the aperture centres `[x_o, y_o, x_e, y_e]`, each
/// beam's background-subtracted flux, its error and the background per pixel (e-), and the
/// aperture's size.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FrameFluxes {
    pub centre: [f64; 4],
    pub f_o: f64,
    pub f_e: f64,
    pub sigma_o: f64,
    pub sigma_e: f64,
    pub bg_o: f64,
    pub bg_e: f64,
    pub n_aperture: usize,
    pub aperture_area_px: f64,
    pub n_annulus: usize,
}

/// The aperture weights about `(cx, cy)` as the o image's weights `w` about `o` (both of
/// radius `r`), when both centres sit at the same sub-pixel phase and neither aperture's
/// window meets the detector's edge; `None` otherwise. Then every pixel offset from the centre
/// is the same number to the bit (a pixel's offset from a centre is the exact difference of
/// a whole number and the centre's fraction, rounded once), so the weights are too: a whole-
/// pixel o/e throw (FORS) needs the circle-pixel areas once per frame, not twice.
fn shifted_weights(
    w: &[(usize, usize, f64)],
    o: (f64, f64),
    (cx, cy): (f64, f64),
    r: f64,
    nx: usize,
    ny: usize,
) -> Option<Vec<(usize, usize, f64)>> {
    let phase = |v: f64| v - v.floor();
    if phase(cx).to_bits() != phase(o.0).to_bits() || phase(cy).to_bits() != phase(o.1).to_bits() {
        return None;
    }
    let inside = |x: f64, y: f64| {
        x - r - 2.0 >= 0.0 && y - r - 2.0 >= 0.0 && x + r + 2.0 <= nx as f64 - 1.0 && y + r + 2.0 <= ny as f64 - 1.0
    };
    if !(inside(o.0, o.1) && inside(cx, cy) && o.0 >= 1.0 && o.1 >= 1.0) {
        return None;
    }
    let (sx, sy) = (cx.floor() - o.0.floor(), cy.floor() - o.1.floor());
    Some(w.iter().map(|&(x, y, v)| ((x as f64 + sx) as usize, (y as f64 + sy) as usize, v)).collect())
}

/// An aperture of radius `r` at `at` reaching pixel `px` behind the mask (before centring, by
/// [`check_placement`]; after, in either beam, by [`measure_frame`]).
fn behind_mask(r: f64, at: (f64, f64), px: (usize, usize)) -> Error {
    Error::mask_edge(format!(
        "aperture of radius {r} px at ({:.1}, {:.1}) reaches pixel ({}, {}) behind the mask; use a smaller aperture",
        at.0, at.1, px.0, px.1
    ))
}

/// The checks of a source's placement that need no pixels: the aperture and annulus radii,
/// the position on the detector and, for strip layouts, on sky the mask lets through with
/// the whole aperture.
pub(crate) fn check_placement(
    g: &BeamGeometry,
    x: f64,
    y: f64,
    ap: &Aperture,
    opts: &PhotOptions,
) -> Result<(), Error> {
    check_aperture(ap)?;
    if !(x.is_finite() && y.is_finite()) || x < 0.0 || y < 0.0 || x >= g.nx as f64 || y >= g.ny as f64 {
        return Err(Error::Invalid(format!(
            "source position ({x}, {y}) px is outside the {} x {} detector",
            g.nx, g.ny
        )));
    }
    if g.layout == Layout::Strips && g.strip_of_sky(x.round() as usize, y.round() as usize).is_none() {
        return Err(Error::mask_edge(format!(
                "source position ({x:.1}, {y:.1}) px is behind the focal-plane mask: the sky there is not imaged (sky bands: {:?})",
                g.sky_bands()
            )));
    }
    if g.layout == Layout::Strips {
        // The aperture at the given position must see sky only: say so before any centring.
        let k = g.strip_of_sky(x.round() as usize, y.round() as usize);
        for (px, py, _) in weights(x, y, ap.radius_px, g.nx, g.ny, opts.weighting) {
            if !matches!(g.kind(px, py), PixelKind::Ordinary(s) if Some(s) == k) {
                return Err(behind_mask(ap.radius_px, (x, y), (px, py)));
            }
        }
    }
    Ok(())
}

/// Measure the source at `(x, y)` in one frame (`data`, row-major, values as `facts` says):
/// the o aperture re-centred on the star (if `opts` says so), the e aperture where the layout
/// puts the e image, exact pixel weights, the annulus background removed in each beam. Call
/// [`check_placement`] first.
pub(crate) fn measure_frame(
    data: &[f64],
    g: &BeamGeometry,
    x: f64,
    y: f64,
    ap: &Aperture,
    opts: &PhotOptions,
    facts: &FrameFacts,
) -> Result<FrameFluxes, Error> {
    // The frames' own conversion: the instrument's ADU, or electrons for calibrated frames.
    let (bias, gain, sat, rn2) = facts.conversion.det();
    let nexp = facts.nexp as f64;
    // Each pixel's own file: a chip file of an assembled exposure (the one decision).
    let file_of = |px: usize, py: usize| crate::frame::file_of(facts.chips, facts.file, px, py).display();
    let file_at = |x: f64, y: f64| file_of(x.round().max(0.0) as usize, y.round().max(0.0) as usize);
    let to_e = |v: f64| (v - bias * nexp) * gain;
    let strip0 = g.strip_of_sky(x.round() as usize, y.round() as usize);
    let o_pixel = |px: usize, py: usize| match g.kind(px, py) {
        PixelKind::Both => true,
        PixelKind::Ordinary(k) => Some(k) == strip0,
        _ => false,
    };
    let (xo, yo) = if opts.recentre {
        centroid(data, g.nx, g.ny, x, y, ap.radius_px, o_pixel).ok_or_else(|| {
            Error::Invalid(format!(
                "no source at ({x:.1}, {y:.1}) px in {} (HWP angle {} deg): nothing rises above the local background within the aperture radius {} px, so the aperture cannot be centred (turn re-centring off to measure a fixed position)",
                file_at(x, y), facts.hwp_deg, ap.radius_px
            ))
        })?
    } else {
        (x, y)
    };
    let (xe, ye) = g.e_position(xo, yo).ok_or_else(|| {
        Error::mask_edge(format!(
            "the e image of ({xo:.1}, {yo:.1}) px falls behind the mask or off the detector ({})",
            file_at(xo, yo)
        ))
    })?;
    let strip = g.strip_of_sky(xo.round().max(0.0) as usize, yo.round().max(0.0) as usize);
    let mut beam = [(0.0, 0.0, 0.0); 2];
    let (mut n_aperture, mut area_o, mut n_annulus) = (0, 0.0, 0);
    let mut o_weights: Option<(f64, f64, Vec<(usize, usize, f64)>)> = None;
    for (b, (cx, cy)) in [(xo, yo), (xe, ye)].into_iter().enumerate() {
        let name = if b == 0 { "o" } else { "e" };
        // Pixels of this beam's image of the strip (strips), or any pixel (maskless).
        let in_beam = |px: usize, py: usize| match (g.kind(px, py), strip) {
            (PixelKind::Both, _) => true,
            (PixelKind::Ordinary(k), Some(s)) => b == 0 && k == s,
            (PixelKind::Extraordinary(k), Some(s)) => b == 1 && k == s,
            _ => false,
        };
        let w = match &o_weights {
            Some((ox, oy, ow)) if b == 1 => shifted_weights(ow, (*ox, *oy), (cx, cy), ap.radius_px, g.nx, g.ny)
                .unwrap_or_else(|| weights(cx, cy, ap.radius_px, g.nx, g.ny, opts.weighting)),
            _ => weights(cx, cy, ap.radius_px, g.nx, g.ny, opts.weighting),
        };
        let r = ap.radius_px;
        let covered = cx - r >= -0.5 && cy - r >= -0.5 && cx + r <= g.nx as f64 - 0.5 && cy + r <= g.ny as f64 - 0.5;
        if !covered {
            return Err(Error::mask_edge(format!(
                "the {name} aperture of radius {r} px at ({cx:.1}, {cy:.1}) reaches off the {} x {} detector",
                g.nx, g.ny
            )));
        }
        let (mut s, mut v, mut area) = (0.0, 0.0, 0.0);
        for &(px, py, wt) in &w {
            if !in_beam(px, py) {
                return Err(behind_mask(r, (cx, cy), (px, py)));
            }
            let val = data[py * g.nx + px];
            if val <= crate::frame::GAP_LIMIT {
                return Err(Error::mask_edge(format!(
                        "aperture pixel ({px}, {py}) of the {name} beam lies in the gap between the chips; photometry needs clean aperture pixels"
                    )));
            }
            if !val.is_finite() {
                return Err(Error::Invalid(format!(
                    "aperture pixel ({px}, {py}) of the {name} beam in {} is {val}; photometry needs clean aperture pixels",
                    file_of(px, py)
                )));
            }
            if val >= sat * nexp {
                return Err(Error::saturated(format!(
                        "aperture pixel ({px}, {py}) of the {name} beam in {} is saturated; photometry needs clean aperture pixels",
                        file_of(px, py)
                    )));
            }
            let e = to_e(val);
            s += wt * e;
            // Photon (e-) and read-noise variance of the weighted sum.
            v += wt * wt * (e.max(0.0) + nexp * rn2);
            area += wt;
        }
        if b == 0 {
            n_aperture = w.len();
            area_o = area;
            o_weights = Some((cx, cy, w));
        }
        let (mut bg, mut vbg) = (0.0, 0.0);
        if let Some((ra, rb)) = ap.annulus {
            let mut vals = Vec::new();
            let (xa, xb) = ((cx - rb).floor().max(0.0) as usize, ((cx + rb).ceil() as usize).min(g.nx - 1));
            let (ya, yb) = ((cy - rb).floor().max(0.0) as usize, ((cy + rb).ceil() as usize).min(g.ny - 1));
            for py in ya..=yb {
                for px in xa..=xb {
                    let r2 = (px as f64 - cx).powi(2) + (py as f64 - cy).powi(2);
                    if r2 >= ra * ra && r2 < rb * rb && in_beam(px, py) {
                        let val = data[py * g.nx + px];
                        if val.is_finite() && val < sat * nexp && val > crate::frame::GAP_LIMIT {
                            vals.push(to_e(val));
                        }
                    }
                }
            }
            if vals.len() < 5 {
                return Err(Error::Invalid(format!(
                    "background annulus of the {name} beam at ({cx:.1}, {cy:.1}) has {} usable sky pixels (need 5): move it or widen it",
                    vals.len()
                )));
            }
            let (m, vm, kept) = clipped_mean(&vals);
            if b == 0 {
                n_annulus = kept;
            }
            (bg, vbg) = (m, vm);
        }
        beam[b] = (s - area * bg, v + area * area * vbg, bg);
    }
    Ok(FrameFluxes {
        centre: [xo, yo, xe, ye],
        f_o: beam[0].0,
        f_e: beam[1].0,
        sigma_o: beam[0].1.sqrt(),
        sigma_e: beam[1].1.sqrt(),
        bg_o: beam[0].2,
        bg_e: beam[1].2,
        n_aperture,
        aperture_area_px: area_o,
        n_annulus,
    })
}

/// One exposure's own measurement of a star and its agreement with the other exposures
/// (frames summed at a repeated HWP position are also measured one by one).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ExposureCheck {
    /// The frame's file.
    pub file: String,
    pub hwp_deg: f64,
    /// Background-subtracted fluxes (e-) and their errors in this exposure alone.
    pub f_o: f64,
    pub f_e: f64,
    pub sigma_o: f64,
    pub sigma_e: f64,
    /// `f_O + f_E` over the median of all exposures (1: as clear as the typical one) and its
    /// error from this exposure's noise.
    pub transparency: f64,
    pub sigma_transparency: f64,
    /// `F_j` (`eq:F`) about the mean of its repeats over the residual's error
    /// (`stokes::repeats`, the check `instpol stokes` makes); 0 at a position taken once.
    pub pull: f64,
    /// Flagged: `|pull|` beyond the threshold (the exposure's `F_j` itself is off: a cosmic ray
    /// in one beam, a plate out of position), or the star's light off the median by more than
    /// [`TRANSPARENCY_TOL`] and the threshold in sigma (clouds, a shutter fault). Flagged
    /// exposures stay in the sum: a change common to both beams cancels in `F_j`.
    pub outlier: bool,
    /// Why it is flagged (empty when not).
    pub why: String,
}

/// An exposure whose `F_j` lies further than this (in sigma of its residual) from its repeats'
/// mean is flagged (the threshold `instpol stokes` uses: one in 16 000 honest exposures).
pub const EXPOSURE_OUTLIER_SIGMA: f64 = 4.0;

/// A relative change of a star's `f_O + f_E` beyond this (and beyond its noise) flags the
/// exposure: 10 % is more than seeing and guiding change the light in a fixed aperture.
pub const TRANSPARENCY_TOL: f64 = 0.10;

/// Each exposure of `frames` as a one-frame [`FrameSet`] (the conversion and filter of `set`),
/// built once for [`exposure_checks`] (a catalog checks every star in the same exposures).
pub fn single_exposures(frames: &[crate::frame::Frame], set: &FrameSet) -> Vec<FrameSet> {
    frames
        .iter()
        .map(|f| FrameSet {
            filter: set.filter.clone(),
            angles_deg: vec![f.hwp_deg],
            hwp_sweep_deg: f.hwp_sweep_deg,
            data: vec![f.data.clone()],
            files: vec![vec![f.path.clone()]],
            nx: f.nx,
            ny: f.ny,
            warnings: vec![],
            conversion: set.conversion,
            chips: vec![f.chips.clone()],
        })
        .collect()
}

/// Measure the source at `(x, y)` in each exposure on its own (`singles`, the frames split by
/// [`single_exposures`]; apertures re-centred per exposure as `opts` says, the same aperture
/// machinery as [`photometry_with`]), combine the exposures of each plate position with
/// `stokes::repeats::combine_repeats` and flag outliers at `threshold` sigma (see
/// [`ExposureCheck`]).
pub fn exposure_checks(
    singles: &[FrameSet],
    g: &BeamGeometry,
    x: f64,
    y: f64,
    ap: &Aperture,
    opts: &PhotOptions,
    threshold: f64,
) -> Result<Vec<ExposureCheck>, Error> {
    let mut m = Vec::with_capacity(singles.len());
    for one in singles {
        let p = measure_fluxes(one, g, x, y, ap, opts)?;
        m.push((p.f_o[0], p.f_e[0], p.sigma_o[0], p.sigma_e[0]));
    }
    let theta: Vec<f64> = singles.iter().map(|f| f.angles_deg[0].to_radians()).collect();
    let col = |k: usize| m.iter().map(|t| [t.0, t.1, t.2, t.3][k]).collect::<Vec<f64>>();
    let c = stokes::repeats::combine_repeats(&theta, &col(0), &col(1), &col(2), &col(3), threshold);
    let mut tot: Vec<f64> = m.iter().map(|t| t.0 + t.1).collect();
    let med = stokes::stats::robust::median(&mut tot, stokes::stats::robust::Middle::Mean);
    Ok(singles
        .iter()
        .zip(&m)
        .zip(&c.checks)
        .map(|((f, &(fo, fe, so, se)), chk)| {
            let t = (fo + fe) / med;
            let st = so.hypot(se) / med;
            let mut why = Vec::new();
            if chk.outlier {
                why.push(format!("F = {:.5} lies {:.1} sigma from its repeats' mean", chk.f, chk.pull));
            }
            if (t - 1.0).abs() > TRANSPARENCY_TOL && (t - 1.0).abs() > threshold * st {
                why.push(format!("the star's light is {:.0} % of the median exposure's", 100.0 * t));
            }
            ExposureCheck {
                file: f.files[0][0].display().to_string(),
                hwp_deg: f.angles_deg[0],
                f_o: fo,
                f_e: fe,
                sigma_o: so,
                sigma_e: se,
                transparency: t,
                sigma_transparency: st,
                pull: chk.pull,
                outlier: !why.is_empty(),
                why: why.join("; "),
            }
        })
        .collect())
}

/// How an aperture's radius is chosen: given in pixels, a multiple of the star's
/// FWHM, or the radius of best signal-to-noise on the star's curve of growth.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum ApertureRadius {
    /// A fixed radius (px).
    Px(f64),
    /// `k` times the star's FWHM.
    FwhmMultiple(f64),
    /// The radius, among 0.5, 0.6, ... 4.0 FWHM (and inside the background annulus), that
    /// maximizes the S/N of the star's total flux `sum_i (f_O + f_E)` over all frames, with the
    /// photon, read and background noise [`photometry_with`] propagates.
    BestSnr,
}

impl ApertureRadius {
    /// Parse `8` (px), `2.5fwhm` (a multiple of the FWHM) or `best` (best S/N).
    pub fn parse(s: &str) -> Option<Self> {
        let t = s.trim().to_ascii_lowercase();
        if t == "best" {
            return Some(Self::BestSnr);
        }
        let (num, fwhm) = match t.strip_suffix("fwhm") {
            Some(n) => (n.trim(), true),
            None => (t.strip_suffix("px").unwrap_or(&t).trim(), false),
        };
        // The range is the caller's to judge (with its own words): any finite number parses.
        let v: f64 = num.parse().ok().filter(|v: &f64| v.is_finite())?;
        Some(if fwhm { Self::FwhmMultiple(v) } else { Self::Px(v) })
    }
}

/// The photometry of one source with its aperture radius chosen by `radius` for a star of
/// FWHM `fwhm_px` (px; unused for [`ApertureRadius::Px`]); returns the photometry and the
/// radius used. The background annulus stays as given: a radius that would reach into it is
/// not considered (and is an error for the fixed choices, as in [`photometry_with`]).
///
/// Why the total-flux S/N for [`ApertureRadius::BestSnr`]: the polarization's error is
/// `1/(sqrt(N/2) SNR)` (`eq:sigp`), so the radius of best flux S/N is the radius of smallest
/// `sigma_P`; the choice depends on the propagated variances only, never on the measured
/// polarization, so it does not bias `P`. Radii where the photometry fails (an aperture
/// reaching the mask or the detector's edge) are skipped; if all fail, the smallest radius's
/// error is returned.
#[allow(clippy::too_many_arguments)]
pub fn photometry_sized(
    set: &FrameSet,
    g: &BeamGeometry,
    x: f64,
    y: f64,
    radius: ApertureRadius,
    fwhm_px: f64,
    annulus: Option<(f64, f64)>,
    opts: &PhotOptions,
) -> Result<(StarPhotometry, f64), Error> {
    let tried = candidate_radii(x, y, radius, fwhm_px, annulus)?
        .into_iter()
        .map(|r| (r, photometry_with(set, g, x, y, &Aperture { radius_px: r, annulus }, opts)))
        .collect();
    pick_radius(radius, tried)
}

/// Whether the star at `(x, y)` px (its o image) shares an image with another star, as the
/// catalog flags `overlap` (`detect::shared_image`, maskless layouts): the sources of
/// the first angle's frame are detected (matched filter of `fwhm_px`, 5 sigma) and paired, and
/// an unpaired one sitting on the star's o image's e position chain or the star's e image's is
/// found. A shared image holds two stars' light: measured, the star's P is wrong (3.3 % for a
/// true 5 % beside an unpolarized neighbour). It is refused naming the neighbour's image
/// unless `allow`; then it is a warning.
pub fn check_overlap(
    set: &FrameSet,
    g: &BeamGeometry,
    x: f64,
    y: f64,
    fwhm_px: f64,
    allow: bool,
) -> Result<Option<crate::Warning>, Error> {
    if g.layout != Layout::Maskless || set.data.is_empty() {
        return Ok(None);
    }
    let Some((ex, ey)) = g.e_position(x, y) else { return Ok(None) };
    let cfg = crate::detect::DetectConfig {
        fwhm_px: if fwhm_px.is_finite() && fwhm_px > 0.0 { fwhm_px } else { 4.0 },
        saturation: set.conversion.saturation * set.files[0].len() as f64,
        ..Default::default()
    };
    let sources = crate::detect::detect_reusing(&set.data[0], g, &cfg, &mut Vec::new());
    let (_, unpaired) = crate::detect::pair(&sources, g, cfg.pair_tol_px);
    let unpaired_e: Vec<_> =
        unpaired.iter().map(|&k| (&sources[k], g.e_position(sources[k].x, sources[k].y))).collect();
    let Some((ux, uy)) = crate::detect::shared_image(g, &unpaired_e, (x, y), (ex, ey), cfg.pair_tol_px) else {
        return Ok(None);
    };
    let what = format!(
        "the star at ({x:.1}, {y:.1}) px shares an image with another star (its image at ({ux:.1}, {uy:.1}) px): one beam holds both stars' light, and the star's P is wrong"
    );
    if allow {
        return Ok(Some(crate::Warning { file: None, message: format!("{what} (measured as asked)") }));
    }
    Err(Error::Invalid(format!(
        "{what}; the catalog flags it `overlap` and does not measure it. Measure it anyway with --allow-overlap"
    )))
}

/// [`photometry_sized`] through a quarter-wave plate: [`circular_with`] at the radius
/// `radius` chooses (the same choice: the total flux's S/N, which `sigma_v` follows as
/// `sigma_P` does); returns the photometry and the radius used.
#[allow(clippy::too_many_arguments)]
pub fn circular_sized(
    set: &FrameSet,
    g: &BeamGeometry,
    x: f64,
    y: f64,
    radius: ApertureRadius,
    fwhm_px: f64,
    annulus: Option<(f64, f64)>,
    opts: &PhotOptions,
    zero_angle_deg: f64,
) -> Result<(CircularPhotometry, f64), Error> {
    let tried = candidate_radii(x, y, radius, fwhm_px, annulus)?
        .into_iter()
        .map(|r| (r, circular_with(set, g, x, y, &Aperture { radius_px: r, annulus }, opts, zero_angle_deg)))
        .collect();
    pick_radius(radius, tried)
}

/// The aperture radii [`photometry_sized`] measures a star of FWHM `fwhm_px` with: the one
/// radius of [`ApertureRadius::Px`] or [`ApertureRadius::FwhmMultiple`], or every candidate of
/// [`ApertureRadius::BestSnr`] inside the annulus (refused when there is none, or when the
/// choice needs a FWHM the star lacks).
pub(crate) fn candidate_radii(
    x: f64,
    y: f64,
    radius: ApertureRadius,
    fwhm_px: f64,
    annulus: Option<(f64, f64)>,
) -> Result<Vec<f64>, Error> {
    let need_fwhm = || {
        if fwhm_px.is_finite() && fwhm_px > 0.0 {
            Ok(fwhm_px)
        } else {
            Err(Error::Invalid(format!(
                "the aperture is chosen from the star's FWHM, but the FWHM at ({x:.1}, {y:.1}) px is {fwhm_px}: give the radius in pixels"
            )))
        }
    };
    match radius {
        ApertureRadius::Px(r) => Ok(vec![r]),
        ApertureRadius::FwhmMultiple(k) => Ok(vec![k * need_fwhm()?]),
        ApertureRadius::BestSnr => {
            let fwhm = need_fwhm()?;
            let r_max = annulus.map_or(f64::INFINITY, |(a, _)| a);
            let v: Vec<f64> = (5..=40).map(|i| i as f64 * 0.1 * fwhm).take_while(|&r| r <= r_max).collect();
            if v.is_empty() {
                return Err(Error::Invalid(format!(
                    "no aperture radius between 0.5 and 4 FWHM ({fwhm:.2} px) fits inside the background annulus's inner radius {r_max} px"
                )));
            }
            Ok(v)
        }
    }
}

/// The photometry [`photometry_sized`] keeps of those measured at each candidate radius
/// (`tried`, in [`candidate_radii`]'s order): the one of a fixed radius as it came, or the
/// best S/N of the total flux; when every radius failed, the first failure.
pub(crate) fn pick_radius<T: Fluxes>(
    radius: ApertureRadius,
    tried: Vec<(f64, Result<T, Error>)>,
) -> Result<(T, f64), Error> {
    let mut best: Option<(f64, T, f64)> = None;
    let mut first_err = None;
    for (r, res) in tried {
        match res {
            Ok(ph) if !matches!(radius, ApertureRadius::BestSnr) => return Ok((ph, r)),
            Ok(ph) => {
                let (f_o, f_e, sigma_o, sigma_e) = ph.fluxes();
                let flux: f64 = f_o.iter().zip(f_e).map(|(a, b)| a + b).sum();
                let var: f64 = sigma_o.iter().zip(sigma_e).map(|(a, b)| a * a + b * b).sum();
                let snr = flux / var.sqrt();
                if snr.is_finite() && best.as_ref().is_none_or(|b| snr > b.0) {
                    best = Some((snr, ph, r));
                }
            }
            Err(e) => {
                first_err.get_or_insert(e);
            }
        }
    }
    match (best, first_err) {
        (Some((_, ph, r)), _) => Ok((ph, r)),
        (None, Some(e)) => Err(e),
        (None, None) => Err(Error::Invalid("no aperture radius gave a finite S/N of the star's flux".into())),
    }
}

/// The beams' fluxes and errors per plate angle of a measured source, linear or circular:
/// what [`pick_radius`] weighs.
pub(crate) trait Fluxes {
    fn fluxes(&self) -> (&[f64], &[f64], &[f64], &[f64]);
}

impl Fluxes for StarPhotometry {
    fn fluxes(&self) -> (&[f64], &[f64], &[f64], &[f64]) {
        (&self.f_o, &self.f_e, &self.sigma_o, &self.sigma_e)
    }
}

impl Fluxes for CircularPhotometry {
    fn fluxes(&self) -> (&[f64], &[f64], &[f64], &[f64]) {
        (&self.f_o, &self.f_e, &self.sigma_o, &self.sigma_e)
    }
}

/// [`StarPhotometry`] while it is being measured.
pub(crate) struct Partial {
    hwp_deg: Vec<f64>,
    hwp_sweep_deg: f64,
    centres: Vec<[f64; 4]>,
    f_o: Vec<f64>,
    f_e: Vec<f64>,
    sigma_o: Vec<f64>,
    sigma_e: Vec<f64>,
    bg_o: Vec<f64>,
    bg_e: Vec<f64>,
    n_aperture: usize,
    aperture_area_px: f64,
    n_annulus: usize,
}

impl Partial {
    /// The frames' measurements in angle order (the aperture's size as the last frame saw it).
    pub(crate) fn from_frames(hwp_deg: &[f64], hwp_sweep_deg: f64, m: &[FrameFluxes]) -> Self {
        let col = |f: fn(&FrameFluxes) -> f64| m.iter().map(f).collect::<Vec<f64>>();
        let last = m.last();
        Self {
            hwp_deg: hwp_deg.to_vec(),
            hwp_sweep_deg,
            centres: m.iter().map(|f| f.centre).collect(),
            f_o: col(|f| f.f_o),
            f_e: col(|f| f.f_e),
            sigma_o: col(|f| f.sigma_o),
            sigma_e: col(|f| f.sigma_e),
            bg_o: col(|f| f.bg_o),
            bg_e: col(|f| f.bg_e),
            n_aperture: last.map_or(0, |f| f.n_aperture),
            aperture_area_px: last.map_or(0.0, |f| f.aperture_area_px),
            n_annulus: last.map_or(0, |f| f.n_annulus),
        }
    }
}

/// Measure the o/e offset `(dx, dy)` (px) of a maskless layout from the stars of the first
/// frame of `set`, and the number of star pairs it rests on. Bright local maxima are found
/// (above the median by 10 robust sigma), every pair of them with about equal peaks votes for
/// its separation vector on a 1-px grid, and the most voted vector, confirmed by at least three pairs, is refined by
/// the centroids of its pairs. Every star has its twin at the offset, so that vector (and its
/// opposite) wins over chance separations. Which image is the ordinary one cannot be told from
/// the frames: the offset is taken with a positive x component (positive y when x is ~0).
pub fn measure_oe_offset(set: &FrameSet, inst: &Instrument) -> Result<(f64, f64, usize), Error> {
    let img = set.data.first().ok_or(Error::NoFrames)?;
    oe_offset_of_image(img, set.nx, set.ny, &set.files[0][0], inst)
}

/// Sigma-clipped mean, the variance of that mean, and the number kept. The clipping starts its
/// median searches where this thread's previous one ended (a neighbouring annulus, or the
/// other beam's: the sky changes little), which changes nothing but speed.
fn clipped_mean(v: &[f64]) -> (f64, f64, usize) {
    thread_local! {
        static HINT: std::cell::Cell<ClipHint> = const { std::cell::Cell::new(None) };
    }
    let mut hint = HINT.get();
    let r = with_clipped(v, ClipConfig::default(), &mut hint, |kept| {
        let n = kept.len() as f64;
        let m = kept.iter().sum::<f64>() / n;
        let var = if n > 1.0 { kept.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0) } else { 0.0 };
        (m, var / n, kept.len())
    });
    HINT.set(hint);
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// The e aperture's weights taken from the o aperture's (a whole-pixel throw) are, pixel
    /// for pixel and bit for bit, the weights computed afresh about the e centre; at another
    /// sub-pixel phase the shortcut declines.
    #[test]
    fn shifted_weights_are_the_weights_to_the_bit() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        let (nx, ny) = (2048, 2048);
        let mut used = 0;
        for _ in 0..2000 {
            let (x, y) = (rng.random_range(10.0..1900.0), rng.random_range(10.0..1900.0));
            let r = rng.random_range(0.7..12.0);
            let (dx, dy) = (rng.random_range(-8..140) as f64, rng.random_range(-8..140) as f64);
            let (xe, ye) = (x + dx, y + dy);
            let w = weights(x, y, r, nx, ny, Weighting::Exact);
            let fresh = weights(xe, ye, r, nx, ny, Weighting::Exact);
            match shifted_weights(&w, (x, y), (xe, ye), r, nx, ny) {
                Some(s) => {
                    used += 1;
                    assert_eq!(s.len(), fresh.len());
                    for (a, b) in s.iter().zip(&fresh) {
                        assert_eq!(
                            (a.0, a.1, a.2.to_bits()),
                            (b.0, b.1, b.2.to_bits()),
                            "centre ({x}, {y}) + ({dx}, {dy}), r {r}"
                        );
                    }
                }
                None => {
                    let p = |v: f64| v - v.floor();
                    assert!(
                        p(x) != p(xe)
                            || p(y) != p(ye)
                            || xe + r + 2.0 > (nx - 1) as f64
                            || ye + r + 2.0 > (ny - 1) as f64
                    );
                }
            }
        }
        // Most integer shifts keep the phase (the sum is exact in the same binade).
        assert!(used > 1000, "{used}");
        let w = weights(100.3, 200.7, 5.0, nx, ny, Weighting::Exact);
        assert!(shifted_weights(&w, (100.3, 200.7), (210.35, 200.7), 5.0, nx, ny).is_none());
    }
}
