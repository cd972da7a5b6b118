//! The beam layout a frame's stars tell when the instrument file leaves it out: a maskless
//! layout's o/e offset and a two-camera instrument's camera transform, measured from the bright
//! stars of one frame. What photometry, catalog and the reduction (whose two-camera maps need
//! the transform) all ask, in a file of its own that uses neither of them.

use crate::aperture::centroid;
use crate::beams::BeamGeometry;
use crate::Error;
use instrument::{Instrument, Layout};
use std::path::Path;
use stokes::stats::robust::{median, Middle, MAD_TO_SIGMA};

/// The instrument's layout for a frame (`img`, `nx` x `ny`, read from `file`), as
/// [`crate::photometry::layout_for`] gives it for a frame set: for a maskless layout without a
/// given o/e offset, the offset measured from the frame's stars; for two cameras without a
/// transform, the transform measured from its star pairs.
pub(crate) fn layout_of_image(
    img: &[f64],
    nx: usize,
    ny: usize,
    file: &Path,
    inst: &Instrument,
) -> Result<BeamGeometry, Error> {
    let g = BeamGeometry::new(inst);
    if g.layout == Layout::Maskless && g.oe_offset.is_none() {
        let (dx, dy, _) = oe_offset_of_image(img, nx, ny, file, inst)?;
        return Ok(g.with_oe_offset(dx, dy));
    }
    if let Some(c) = g.cameras.as_ref().filter(|c| c.transform.is_none()) {
        let bound = inst.polarimetry.cameras.as_ref().map_or(0.5, |c| c.max_residual_px);
        let (t, rms, n) = camera_transform_of_image(img, nx, ny, file, inst, c, bound)?;
        return Ok(g.with_camera_transform(t, rms, n));
    }
    Ok(g)
}

/// The bright local maxima of `img` inside the detector rectangle `[x0, x1) x [y0, y1)` (above
/// the rectangle's median by 10 robust sigma; the brightest 300, brightest first) and that
/// median: `(value, x, y)`.
fn bright_peaks(
    img: &[f64],
    nx: usize,
    (x0, y0, x1, y1): (usize, usize, usize, usize),
) -> Option<(f64, Vec<(f64, usize, usize)>)> {
    let mut vals: Vec<f64> =
        (y0..y1).flat_map(|y| (x0..x1).map(move |x| img[y * nx + x])).filter(|v| v.is_finite()).collect();
    if vals.len() < 9 {
        return None;
    }
    // Upper middles: the level is one of the pixels.
    let med = median(&mut vals, Middle::Upper);
    let mut dev: Vec<f64> = vals.iter().map(|v| (v - med).abs()).collect();
    let sigma = (MAD_TO_SIGMA * median(&mut dev, Middle::Upper)).max(1e-9 * med.abs().max(1.0));
    let thr = med + 10.0 * sigma;
    let mut peaks: Vec<(f64, usize, usize)> = Vec::new();
    for y in y0 + 2..y1.saturating_sub(2) {
        for x in x0 + 2..x1.saturating_sub(2) {
            let v = img[y * nx + x];
            if !(v > thr) {
                continue;
            }
            let is_max =
                (y - 2..=y + 2).all(|yy| (x - 2..=x + 2).all(|xx| (xx, yy) == (x, y) || !(img[yy * nx + xx] >= v)));
            if is_max {
                peaks.push((v, x, y));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0));
    peaks.truncate(300);
    Some((med, peaks))
}

/// The camera transform of a two-camera instrument measured from the stars of one frame: the
/// bright peaks of each camera, the e camera's turned by its orientation, matched by the
/// translation most pairs of about equal brightness agree on (within a pixel), centroided, and
/// the affine map `(x', y') = (a x + b y + c, d x + e y + f)` fitted to the pairs by least
/// squares. Returns the map, its RMS residual (px) and the number of pairs; refused, with what
/// to do, when fewer than 3 pairs match or the residual exceeds `bound` px.
fn camera_transform_of_image(
    img: &[f64],
    nx: usize,
    ny: usize,
    file: &Path,
    inst: &Instrument,
    c: &crate::beams::CameraMap,
    bound: f64,
) -> Result<([f64; 6], f64, usize), Error> {
    let rect = |(x0, y0): (usize, usize), (w, h): (usize, usize)| (x0, y0, (x0 + w).min(nx), (y0 + h).min(ny));
    let refuse = |why: String| {
        Error::Invalid(format!(
            "cannot measure the camera transform of instrument {} from {}: {why}; give [polarimetry.cameras] transform in the instrument file",
            inst.name,
            file.display()
        ))
    };
    let (Some((mo, po)), Some((me, pe))) =
        (bright_peaks(img, nx, rect(c.o_origin, c.o_size)), bright_peaks(img, nx, rect(c.e_origin, c.e_size)))
    else {
        return Err(refuse("a camera has no finite pixels".into()));
    };
    let pe: Vec<(f64, f64, f64)> = pe
        .iter()
        .map(|&(v, x, y)| {
            let (u, w) = c.turned_e(x as f64, y as f64);
            (v - me, u, w)
        })
        .collect();
    let mut votes: std::collections::HashMap<(i64, i64), usize> = std::collections::HashMap::new();
    for a in &po {
        let fa = a.0 - mo;
        for b in &pe {
            // The two images of one star are about equally bright (a gain or flat difference
            // of a few per cent and (1 + F) / (1 - F) aside); two different stars seldom are.
            if fa < 1.6 * b.0 && b.0 < 1.6 * fa {
                let d = (
                    (b.1 - a.1 as f64 + c.o_origin.0 as f64).round() as i64,
                    (b.2 - a.2 as f64 + c.o_origin.1 as f64).round() as i64,
                );
                *votes.entry(d).or_default() += 1;
            }
        }
    }
    let score = |v: &(i64, i64)| -> usize {
        (-1..=1)
            .flat_map(|i| (-1..=1).map(move |j| (i, j)))
            .map(|(i, j)| votes.get(&(v.0 + i, v.1 + j)).copied().unwrap_or(0))
            .sum()
    };
    let best = votes.keys().max_by_key(|v| (score(v), votes[v], std::cmp::Reverse(**v))).copied();
    let Some(best) = best.filter(|v| score(v) >= 3) else {
        return Err(refuse(format!(
            "fewer than 3 star pairs agree on one shift between the cameras ({} and {} bright peaks)",
            po.len(),
            pe.len()
        )));
    };
    // Pairs through the best shift, fitted; then matched again through that first fit (a
    // camera map's turn and scale move the far corners' stars beyond the shift's reach) and
    // fitted again.
    let shift = [1.0, 0.0, best.0 as f64, 0.0, 1.0, best.1 as f64];
    let pairs = camera_pairs(img, nx, ny, c, &po, &pe, &shift);
    let first = fit_affine(&pairs).map_err(refuse)?;
    let again = camera_pairs(img, nx, ny, c, &po, &pe, &first);
    let pairs = if again.len() >= pairs.len() { again } else { pairs };
    let t = fit_affine(&pairs).map_err(refuse)?;
    let [a, b, cc, d, e, f] = t;
    let n = pairs.len() as f64;
    let ss: f64 =
        pairs.iter().map(|((u, v), (x, y))| (a * u + b * v + cc - x).powi(2) + (d * u + e * v + f - y).powi(2)).sum();
    let rms = (ss / n).sqrt();
    if !(rms <= bound) {
        return Err(refuse(format!(
            "the affine map fitted to {} star pairs leaves an RMS residual of {rms:.3} px, beyond the bound of {bound} px (max_residual_px)",
            pairs.len()
        )));
    }
    Ok((t, rms, pairs.len()))
}

/// The o peaks `po` (value, x, y in the detector frame) matched to the turned e peaks `pe`
/// (value, local turned x, y) within 1.5 px of where the map `t` (o camera local px -> turned e
/// px) puts them, each pair centred in the image: `((o local x, y), (turned e x, y))`.
fn camera_pairs(
    img: &[f64],
    nx: usize,
    ny: usize,
    c: &crate::beams::CameraMap,
    po: &[(f64, usize, usize)],
    pe: &[(f64, f64, f64)],
    t: &[f64; 6],
) -> Vec<((f64, f64), (f64, f64))> {
    let r = 3.0;
    let (ex0, ey0) = c.e_origin;
    let e_pixel = |px: usize, py: usize| px >= ex0 && py >= ey0 && px < ex0 + c.e_size.0 && py < ey0 + c.e_size.1;
    let mut pairs: Vec<((f64, f64), (f64, f64))> = Vec::new();
    for a in po {
        let (ua, va) = (a.1 as f64 - c.o_origin.0 as f64, a.2 as f64 - c.o_origin.1 as f64);
        let (tu, tv) = (t[0] * ua + t[1] * va + t[2], t[3] * ua + t[4] * va + t[5]);
        let Some(b) = pe.iter().find(|b| (b.1 - tu).abs() <= 1.5 && (b.2 - tv).abs() <= 1.5) else { continue };
        // The e peak's detector pixel: back through the orientation.
        let (ex, ey) = c.e_of_local(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0], b.1, b.2);
        if let (Some(ca), Some(cb)) = (
            centroid(img, nx, ny, a.1 as f64, a.2 as f64, r, |_, _| true),
            centroid(img, nx, ny, ex.round(), ey.round(), r, e_pixel),
        ) {
            let o = (ca.0 - c.o_origin.0 as f64, ca.1 - c.o_origin.1 as f64);
            pairs.push((o, c.turned_e(cb.0, cb.1)));
        }
    }
    pairs
}

/// The affine map `[a, b, c, d, e, f]` of least squares through `pairs` (`(u, v) -> (x, y)`),
/// solved about the pairs' mean (well conditioned); `Err` with the reason when fewer than 3
/// pairs or all on a line.
fn fit_affine(pairs: &[((f64, f64), (f64, f64))]) -> Result<[f64; 6], String> {
    if pairs.len() < 3 {
        return Err(format!("only {} star pairs could be matched and centred (3 needed)", pairs.len()));
    }
    let n = pairs.len() as f64;
    let (mu, mv) = (pairs.iter().map(|p| p.0 .0).sum::<f64>() / n, pairs.iter().map(|p| p.0 .1).sum::<f64>() / n);
    let (mut suu, mut suv, mut svv) = (0.0, 0.0, 0.0);
    let (mut sx, mut sy) = ([0.0; 3], [0.0; 3]);
    for ((u, v), (x, y)) in pairs {
        let (du, dv) = (u - mu, v - mv);
        suu += du * du;
        suv += du * dv;
        svv += dv * dv;
        sx[0] += du * x;
        sx[1] += dv * x;
        sx[2] += x;
        sy[0] += du * y;
        sy[1] += dv * y;
        sy[2] += y;
    }
    let det = suu * svv - suv * suv;
    if !(det > 1e-9 * (suu + svv).powi(2) && det > 0.0) {
        return Err(format!("the {} matched stars lie on a line: the map is not determined", pairs.len()));
    }
    let solve = |s: [f64; 3]| {
        let a = (svv * s[0] - suv * s[1]) / det;
        let b = (suu * s[1] - suv * s[0]) / det;
        (a, b, s[2] / n - a * mu - b * mv)
    };
    let ((a, b, c), (d, e, f)) = (solve(sx), solve(sy));
    Ok([a, b, c, d, e, f])
}

/// [`crate::photometry::measure_oe_offset`] from one frame (`img`, `nx` x `ny`, read from `file`).
pub(crate) fn oe_offset_of_image(
    img: &[f64],
    nx: usize,
    ny: usize,
    file: &Path,
    inst: &Instrument,
) -> Result<(f64, f64, usize), Error> {
    let Some((med, peaks)) = bright_peaks(img, nx, (0, 0, nx, ny)) else {
        return Err(Error::Invalid("cannot measure the o/e offset: the frame has no finite pixels".into()));
    };
    let mut votes: std::collections::HashMap<(i64, i64), usize> = std::collections::HashMap::new();
    for a in &peaks {
        for b in &peaks {
            let (dx, dy) = (b.1 as i64 - a.1 as i64, b.2 as i64 - a.2 as i64);
            // The two images of one star are about equally bright (their ratio is
            // (1 + F) / (1 - F), near 1 unless the star is strongly polarized); two different
            // stars seldom are, so only such pairs vote.
            let (fa, fb) = (a.0 - med, b.0 - med);
            let similar = fa < 1.6 * fb && fb < 1.6 * fa;
            if similar && (dx > 0 || (dx == 0 && dy > 0)) && dx * dx + dy * dy >= 4 {
                *votes.entry((dx, dy)).or_default() += 1;
            }
        }
    }
    // Votes of a vector and its 8 neighbours (a sub-pixel offset splits its pairs).
    let score = |v: &(i64, i64)| -> usize {
        (-1..=1)
            .flat_map(|i| (-1..=1).map(move |j| (i, j)))
            .map(|(i, j)| votes.get(&(v.0 + i, v.1 + j)).copied().unwrap_or(0))
            .sum()
    };
    let best = votes.keys().max_by_key(|v| (score(v), votes[v])).copied();
    let Some(best) = best.filter(|v| score(v) >= 3) else {
        return Err(Error::Invalid(format!(
            "cannot measure the o/e offset of instrument {}: fewer than three star pairs share one separation in {} ({} bright peaks); give [polarimetry] oe_offset_px in the instrument file",
            inst.name,
            file.display(),
            peaks.len()
        )));
    };
    let r = 3.0;
    let mut dxs = Vec::new();
    let mut dys = Vec::new();
    for a in &peaks {
        let t = (a.1 as i64 + best.0, a.2 as i64 + best.1);
        if let Some(b) = peaks.iter().find(|b| (b.1 as i64 - t.0).abs() <= 1 && (b.2 as i64 - t.1).abs() <= 1) {
            if let (Some(ca), Some(cb)) = (
                centroid(img, nx, ny, a.1 as f64, a.2 as f64, r, |_, _| true),
                centroid(img, nx, ny, b.1 as f64, b.2 as f64, r, |_, _| true),
            ) {
                dxs.push(cb.0 - ca.0);
                dys.push(cb.1 - ca.1);
            }
        }
    }
    if dxs.len() < 3 {
        return Err(Error::Invalid(format!(
            "cannot measure the o/e offset of instrument {}: only {} star pairs could be centred; give [polarimetry] oe_offset_px",
            inst.name,
            dxs.len()
        )));
    }
    let npairs = dxs.len();
    Ok((median(&mut dxs, Middle::Mean), median(&mut dys, Middle::Mean), npairs))
}
