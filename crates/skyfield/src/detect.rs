//! Point sources in a frame: background and noise, detection, centroids, FWHM, flags, and
//! the pairing of each source's ordinary image with its extraordinary one through the beam
//! layout ([`crate::beams`]).
//!
//! The background is a mesh of sigma-clipped medians (boxes of `box_px`, over the pixels the
//! layout illuminates), interpolated bilinearly between box centres; the noise is the robust
//! standard deviation of the background-subtracted illuminated pixels. Sources are the local
//! maxima of the image smoothed with a Gaussian of the expected FWHM (a matched filter) that
//! rise `threshold_sigma` above the smoothed noise; each is re-centred on its flux-weighted
//! centroid ([`crate::aperture::centroid`]) and measured for its FWHM (second moments) and
//! peak. Pairing asks the layout where each source's e image should fall and takes the nearest
//! source within `pair_tol_px` there.

use crate::aperture::centroid;
use crate::beams::{BeamGeometry, PixelKind};
use crate::bin::{clipped_stats, clipped_stats_hinted};
use instrument::Layout;
use rayon::prelude::*;
use stokes::stats::robust::{median, Middle};

/// Detection settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DetectConfig {
    /// Expected FWHM of the stars (px): the matched filter's width.
    pub fwhm_px: f64,
    /// Detection threshold in units of the smoothed image's noise.
    pub threshold_sigma: f64,
    /// Background mesh box (px).
    pub box_px: usize,
    /// Largest distance (px) between where the layout predicts a source's e image and a
    /// detected source, for the two to pair.
    pub pair_tol_px: f64,
    /// Saturation level of the image's values (same units as the image).
    pub saturation: f64,
}

impl Default for DetectConfig {
    fn default() -> Self {
        Self { fwhm_px: 4.0, threshold_sigma: 5.0, box_px: 64, pair_tol_px: 1.5, saturation: f64::INFINITY }
    }
}

/// A detected source (one beam's image of a star).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Source {
    pub x: f64,
    pub y: f64,
    /// Peak value above the background.
    pub peak: f64,
    /// FWHM from the second moments (px).
    pub fwhm_px: f64,
    /// Which image the layout says the pixel belongs to.
    #[serde(skip)]
    pub kind: PixelKind,
    /// A pixel near the centre reaches the saturation level.
    pub saturated: bool,
}

/// The background and noise of an image.
#[derive(Debug, Clone)]
pub struct Background {
    /// Background per pixel (row-major), NaN where nothing is illuminated nearby.
    pub level: Vec<f64>,
    /// Robust rms of the background-subtracted illuminated pixels.
    pub sigma: f64,
}

fn usable(g: &BeamGeometry, x: usize, y: usize) -> bool {
    !matches!(g.kind(x, y), PixelKind::Masked)
}

/// Background mesh and noise of `img` over the pixels the layout illuminates.
pub fn background(img: &[f64], g: &BeamGeometry, box_px: usize) -> Background {
    let level = background_level(img, g, box_px, Vec::new());
    let sigma = background_noise(img, &level, g);
    Background { level, sigma }
}

/// The background mesh of [`background`], interpolated to every pixel.
fn background_level(img: &[f64], g: &BeamGeometry, box_px: usize, mut level: Vec<f64>) -> Vec<f64> {
    let (nx, ny) = (g.nx, g.ny);
    let b = box_px.max(8);
    let (mx, my) = (nx.div_ceil(b), ny.div_ceil(b));
    // Rows of boxes are independent: measured in parallel (the mesh was most of a detection's
    // time); along a row each box's clipping starts where its neighbour's ended.
    let mut mesh = vec![f64::NAN; mx * my];
    mesh.par_chunks_mut(mx.max(1)).enumerate().for_each(|(j, row)| {
        let mut hint = None;
        let mut v = Vec::with_capacity(b * b);
        for (i, m) in row.iter_mut().enumerate() {
            v.clear();
            for y in j * b..((j + 1) * b).min(ny) {
                for x in i * b..((i + 1) * b).min(nx) {
                    if usable(g, x, y) {
                        v.push(img[y * nx + x]);
                    }
                }
            }
            if v.len() >= 16 {
                *m = clipped_stats_hinted(&v, &mut hint).map_or(f64::NAN, |s| s.0);
            }
        }
    });
    // Empty boxes (behind the mask) take the median of the filled ones: the bilinear
    // interpolation then never reaches for a NaN.
    let mut filled: Vec<f64> = mesh.iter().copied().filter(|v| v.is_finite()).collect();
    let fill = if filled.is_empty() { 0.0 } else { median(&mut filled, Middle::Mean) };
    for v in mesh.iter_mut().filter(|v| !v.is_finite()) {
        *v = fill;
    }
    // Bilinear between box centres, clamped at the edges; the column part of the weights and
    // indices is the same on every row, so it is worked out once.
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    let cols: Vec<(usize, usize, f64)> = (0..nx)
        .map(|x| {
            let fx = (x as f64 + 0.5) / b as f64 - 0.5;
            let (i0, tx) = (fx.floor() as isize, fx - fx.floor());
            (clamp(i0, mx), clamp(i0 + 1, mx), tx)
        })
        .collect();
    level.clear();
    crate::par_resize(&mut level, nx * ny, f64::NAN);
    level.par_chunks_mut(nx.max(1)).enumerate().for_each(|(y, row)| {
        let fy = (y as f64 + 0.5) / b as f64 - 0.5;
        let (j0, ty) = (fy.floor() as isize, fy - fy.floor());
        let (r0, r1) = (&mesh[clamp(j0, my) * mx..][..mx], &mesh[clamp(j0 + 1, my) * mx..][..mx]);
        for (l, &(ia, ib, tx)) in row.iter_mut().zip(&cols) {
            *l = (1.0 - ty) * ((1.0 - tx) * r0[ia] + tx * r0[ib]) + ty * ((1.0 - tx) * r1[ia] + tx * r1[ib]);
        }
    });
    level
}

/// The noise of [`background`]: the robust rms of `img - level` over the illuminated pixels.
fn background_noise(img: &[f64], level: &[f64], g: &BeamGeometry) -> f64 {
    let (nx, ny) = (g.nx, g.ny);
    // The noise from at most ~250 000 illuminated pixels spread over the frame: plenty for a
    // robust rms, and it keeps the clipping's selections off the whole 4-Mpixel frame.
    let step = (nx * ny / 250_000).max(1);
    let resid: Vec<f64> =
        (0..nx * ny).step_by(step).filter(|&k| usable(g, k % nx, k / nx)).map(|k| img[k] - level[k]).collect();
    clipped_stats(&resid).map_or(0.0, |s| s.1)
}

/// Detect the sources of `img` (one frame, or a sum of frames, in any linear unit).
pub fn detect(img: &[f64], g: &BeamGeometry, cfg: &DetectConfig) -> Vec<Source> {
    detect_reusing(img, g, cfg, &mut Vec::new())
}

/// [`detect`] with its three frame-sized work images taken from `spare` where it holds them,
/// and left there afterwards, for the caller's next frames: a catalog's measuring pass then
/// reads its frames into memory the detection already faulted in (fresh 32 MB buffers, cleared
/// by the kernel page by page, were a fifth of a catalog's CPU time).
pub fn detect_reusing(img: &[f64], g: &BeamGeometry, cfg: &DetectConfig, spare: &mut Vec<Vec<f64>>) -> Vec<Source> {
    let (nx, ny) = (g.nx, g.ny);
    let level = background_level(img, g, cfg.box_px, spare.pop().unwrap_or_default());
    // Background-subtracted image, zero where nothing is illuminated or the value is bad.
    let mut sub = spare.pop().unwrap_or_default();
    sub.clear();
    crate::par_resize(&mut sub, nx * ny, 0.0);
    sub.par_chunks_mut(nx.max(1)).enumerate().for_each(|(y, row)| {
        // One answer per row where the layout gives one.
        let whole_row = g.row_kind(y).map(|k| k != PixelKind::Masked);
        if whole_row == Some(false) {
            return;
        }
        for (x, o) in row.iter_mut().enumerate() {
            let k = y * nx + x;
            let v = img[k] - level[k];
            if whole_row.unwrap_or_else(|| usable(g, x, y)) && v.is_finite() {
                *o = v;
            }
        }
    });
    // Separable Gaussian matched filter, normalized to unit sum.
    let s = (cfg.fwhm_px / 2.3548).max(0.5);
    let r = (3.0 * s).ceil() as isize;
    let mut k: Vec<f64> = (-r..=r).map(|i| (-0.5 * (i as f64 / s).powi(2)).exp()).collect();
    let ks: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= ks);
    // Each output pixel sums its taps in kernel order, the taps off the detector left out; the
    // sums are accumulated a whole row at a time (tap by tap, as row-wide multiply-adds the
    // compiler vectorizes), which gives the same sums in the same order as a pixel-by-pixel
    // loop at a fraction of its time.
    // `out` is written before it is read: zero-filled memory from the allocator (pages the
    // kernel maps to its shared zero page) read then written costs a copy-on-write fault and
    // a TLB flush on every core per page, which was an eighth of a catalog's time.
    let conv = |src: &[f64], along_x: bool, mut out: Vec<f64>| -> Vec<f64> {
        out.clear();
        crate::par_resize(&mut out, nx * ny, 0.0);
        out.par_chunks_mut(nx.max(1)).enumerate().for_each(|(y, row)| {
            for (t, &w) in k.iter().enumerate() {
                let d = t as isize - r;
                if along_x {
                    // Outputs x with x + d on the detector.
                    let (x0, x1) = ((-d).max(0) as usize, (nx as isize - d.max(0)).max(0) as usize);
                    if x0 >= x1 {
                        continue;
                    }
                    let s = &src[y * nx..(y + 1) * nx];
                    let from = &s[(x0 as isize + d) as usize..(x1 as isize + d) as usize];
                    for (o, v) in row[x0..x1].iter_mut().zip(from) {
                        *o += w * v;
                    }
                } else {
                    let yy = y as isize + d;
                    if yy < 0 || yy >= ny as isize {
                        continue;
                    }
                    let from = &src[yy as usize * nx..(yy as usize + 1) * nx];
                    for (o, v) in row.iter_mut().zip(from) {
                        *o += w * v;
                    }
                }
            }
        });
        out
    };
    // The background's noise (a clipping of 250 000 values on one thread) is found while the
    // other threads filter along x; the background map's buffer then takes the pass along y.
    let across = spare.pop().unwrap_or_default();
    let (sigma, across) = rayon::join(|| background_noise(img, &level, g), || conv(&sub, true, across));
    let sm = conv(&across, false, level);
    // Noise of the smoothed image: sigma times the kernel's 2-D norm.
    let k2: f64 = k.iter().map(|v| v * v).sum::<f64>();
    let thr = cfg.threshold_sigma * sigma * k2;
    let rc = (1.5 * cfg.fwhm_px).max(3.0);
    // The local maxima above the threshold, in row-major order (rows scanned in parallel).
    let maxima: Vec<(usize, usize)> = (1..ny.saturating_sub(1))
        .into_par_iter()
        .flat_map_iter(|y| {
            let (sm, thr) = (&sm, thr);
            (1..nx.saturating_sub(1))
                .filter(move |&x| {
                    let v = sm[y * nx + x];
                    v > thr
                        && usable(g, x, y)
                        && (y - 1..=y + 1)
                            .all(|yy| (x - 1..=x + 1).all(|xx| (xx, yy) == (x, y) || sm[yy * nx + xx] < v))
                })
                .map(move |x| (x, y))
        })
        .collect();
    // Each maximum centred and measured on its own (in parallel, order kept).
    let measured: Vec<Option<Source>> = maxima
        .par_iter()
        .map(|&(x, y)| {
            let kind = g.kind(x, y);
            let same = |px: usize, py: usize| g.kind(px, py) == kind;
            let (cx, cy) = centroid(&sub, nx, ny, x as f64, y as f64, rc, same)?;
            // FWHM from the second moments inside the centroid radius, and the peak.
            let (mut sw, mut s2, mut peak, mut sat) = (0.0, 0.0, 0.0f64, false);
            let (xa, xb) = ((cx - rc).floor().max(0.0) as usize, ((cx + rc).ceil() as usize).min(nx - 1));
            let (ya, yb) = ((cy - rc).floor().max(0.0) as usize, ((cy + rc).ceil() as usize).min(ny - 1));
            for py in ya..=yb {
                for px in xa..=xb {
                    let d2 = (px as f64 - cx).powi(2) + (py as f64 - cy).powi(2);
                    if d2 > rc * rc || !same(px, py) {
                        continue;
                    }
                    let w = sub[py * nx + px];
                    if d2 <= 4.0 {
                        peak = peak.max(w);
                        sat |= img[py * nx + px] >= cfg.saturation;
                    }
                    if w > 0.0 {
                        sw += w;
                        s2 += w * d2;
                    }
                }
            }
            let fwhm = if sw > 0.0 { 2.3548 * (s2 / (2.0 * sw)).sqrt() } else { f64::NAN };
            Some(Source { x: cx, y: cy, peak, fwhm_px: fwhm, kind, saturated: sat })
        })
        .collect();
    // A maximum whose centroid lands on an earlier source's is the same source (taken in the
    // scan order, as one pass would).
    let mut found: Vec<Source> = Vec::new();
    for s in measured.into_iter().flatten() {
        let near =
            |f: &Source| (f.x - s.x).abs() < 1.5 && (f.y - s.y).abs() < 1.5 && (f.x - s.x).hypot(f.y - s.y) < 1.5;
        if !found.iter().any(near) {
            found.push(s);
        }
    }
    found.sort_by(|a, b| b.peak.total_cmp(&a.peak));
    spare.extend([sm, across, sub]);
    found
}

/// A star: its o image and, when the layout found it, its e image (indices into the sources).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pair {
    pub o: usize,
    pub e: usize,
}

/// Pair the sources' o images with their e images through the layout `g`: for every source
/// that can be an o image (strips: on an o image of the mask; maskless: any, taken in the order
/// of their position along the offset so that the first image of a star is its o image), the
/// nearest unused source within `tol` px of the predicted e position. Returns the pairs and the
/// sources left unpaired.
pub fn pair(sources: &[Source], g: &BeamGeometry, tol: f64) -> (Vec<Pair>, Vec<usize>) {
    let mut order: Vec<usize> = (0..sources.len()).collect();
    if g.layout == Layout::Maskless {
        let (dx, dy) = g.oe_offset.unwrap_or((1.0, 0.0));
        order.sort_by(|&a, &b| {
            (sources[a].x * dx + sources[a].y * dy).total_cmp(&(sources[b].x * dx + sources[b].y * dy))
        });
    }
    let mut used = vec![false; sources.len()];
    let mut pairs = Vec::new();
    for &i in &order {
        let s = &sources[i];
        if used[i] || matches!(s.kind, PixelKind::Extraordinary(_)) {
            continue;
        }
        let Some((ex, ey)) = g.e_position(s.x, s.y) else { continue };
        let best = (0..sources.len())
            .filter(|&j| j != i && !used[j] && !matches!(sources[j].kind, PixelKind::Ordinary(_)))
            // (The box test is exact and spares the hypot of far sources.)
            .filter(|&j| (sources[j].x - ex).abs() <= tol && (sources[j].y - ey).abs() <= tol)
            .map(|j| (j, (sources[j].x - ex).hypot(sources[j].y - ey)))
            .filter(|&(_, d)| d <= tol)
            .min_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((j, _)) = best {
            used[i] = true;
            used[j] = true;
            pairs.push(Pair { o: i, e: j });
        }
    }
    let unpaired = (0..sources.len()).filter(|&k| !used[k]).collect();
    (pairs, unpaired)
}

/// Why a source found no partner in the other beam ([`pair`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Unpaired {
    /// Its e image would fall off the detector or behind the mask: a star at the field's edge.
    OffDetector,
    /// Nothing was found where its e image should be (within the pairing tolerance): a cosmic
    /// ray, a hot pixel or a noise peak, a star too faint in the e beam, or an o/e offset that
    /// does not fit these frames.
    NoPartner,
    /// A source in the e images whose o image was not found (the o image faint, off the
    /// detector, or the source not a star).
    LoneE,
}

impl Unpaired {
    /// Why each of `unpaired` (source indices, as [`pair`] returns them) has no partner.
    pub fn of(sources: &[Source], g: &BeamGeometry, unpaired: &[usize]) -> Vec<Unpaired> {
        unpaired
            .iter()
            .map(|&k| match (sources[k].kind, g.e_position(sources[k].x, sources[k].y)) {
                (PixelKind::Extraordinary(_), _) => Unpaired::LoneE,
                (_, None) => Unpaired::OffDetector,
                (_, Some(_)) => Unpaired::NoPartner,
            })
            .collect()
    }

    /// The reason in a few words, for a console summary.
    pub fn words(self) -> &'static str {
        match self {
            Unpaired::OffDetector => "whose e image falls off the detector",
            Unpaired::NoPartner => {
                "with nothing where their e image should be (noise peaks, cosmic rays, or stars too faint in one beam)"
            }
            Unpaired::LoneE => "in the e images with no o image",
        }
    }
}

/// Where the unpaired sources' other images sit against the layout's prediction: for each
/// unpaired source outside the e images, the nearest unpaired source outside the o images
/// within `reach` px of where `g` puts its e image. Returns the median residual `(dx, dy)` (px)
/// and how many residuals lie within 1 px of it, or `None` with fewer than three residuals. A
/// shift shared by many sources, beyond the pairing tolerance, says the instrument file's o/e
/// offset does not fit these frames (another filter's throw, a different Wollaston).
pub fn unpaired_shift(
    sources: &[Source],
    unpaired: &[usize],
    g: &BeamGeometry,
    reach: f64,
) -> Option<(f64, f64, usize)> {
    let is = |k: usize, o: bool| match sources[k].kind {
        PixelKind::Ordinary(_) => o,
        PixelKind::Extraordinary(_) => !o,
        _ => true,
    };
    let mut res: Vec<(f64, f64)> = Vec::new();
    for &i in unpaired.iter().filter(|&&i| is(i, true)) {
        let Some((ex, ey)) = g.e_position(sources[i].x, sources[i].y) else { continue };
        let best = unpaired
            .iter()
            .filter(|&&j| j != i && is(j, false))
            .map(|&j| (sources[j].x - ex, sources[j].y - ey))
            .filter(|d| d.0.hypot(d.1) <= reach)
            .min_by(|a, b| a.0.hypot(a.1).total_cmp(&b.0.hypot(b.1)));
        res.extend(best);
    }
    if res.len() < 3 {
        return None;
    }
    let dx = median(&mut res.iter().map(|r| r.0).collect::<Vec<_>>(), Middle::Mean);
    let dy = median(&mut res.iter().map(|r| r.1).collect::<Vec<_>>(), Middle::Mean);
    let n = res.iter().filter(|r| (r.0 - dx).hypot(r.1 - dy) <= 1.0).count();
    Some((dx, dy, n))
}

/// Where an image of the star with images at `o` and `e` is shared with another star's other
/// image, if it is (a maskless layout: stars one o/e offset apart): an unpaired source sits
/// where the layout puts the e image of this star's e image (the star's e image is that
/// source's o image), or the e image of an unpaired source falls on this star's o image.
/// `unpaired_e`: the unpaired sources with their layout e positions. Returns the other star's
/// image's position (px).
pub(crate) fn shared_image(
    g: &BeamGeometry,
    unpaired_e: &[(&Source, Option<(f64, f64)>)],
    o: (f64, f64),
    e: (f64, f64),
    tol_px: f64,
) -> Option<(f64, f64)> {
    let near = |p: Option<(f64, f64)>, x: f64, y: f64| p.is_some_and(|(px, py)| (x - px).hypot(y - py) <= tol_px);
    let e_of_e = g.e_position(e.0, e.1);
    unpaired_e.iter().find(|(u, u_e)| near(e_of_e, u.x, u.y) || near(*u_e, o.0, o.1)).map(|(u, _)| (u.x, u.y))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// Work images taken from a previous detection (holding its values, or junk, and sized for
    /// another frame) change nothing: the same sources, to the bit, as a fresh detection.
    #[test]
    fn reused_work_images_change_nothing() {
        let text = include_str!("../../../instruments/fors1.toml")
            .replace("nx = 2048", "nx = 400")
            .replace("ny = 2048", "ny = 480")
            .replace("strip_count = 9", "strip_count = 2");
        let inst = instrument::Instrument::from_toml_str(&text, std::path::Path::new("small.toml")).unwrap();
        let g = BeamGeometry::new(&inst);
        let (nx, ny) = (g.nx, g.ny);
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let mut frame = |stars: usize| -> Vec<f64> {
            let mut img: Vec<f64> = (0..nx * ny).map(|_| 100.0 + rng.random_range(-8.0..8.0)).collect();
            for _ in 0..stars {
                let (cx, cy, a) =
                    (rng.random_range(10.0..390.0), rng.random_range(30.0..470.0), rng.random_range(200.0..5000.0));
                for y in (cy as usize).saturating_sub(8)..(cy as usize + 9).min(ny) {
                    for x in (cx as usize).saturating_sub(8)..(cx as usize + 9).min(nx) {
                        let r2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
                        img[y * nx + x] += a * (-r2 / 4.5).exp();
                    }
                }
            }
            img
        };
        let (a, b) = (frame(40), frame(25));
        let cfg = DetectConfig::default();
        let fresh = detect(&a, &g, &cfg);
        assert!(fresh.len() >= 10, "{} sources", fresh.len());
        let bits = |s: &[Source]| s.iter().map(|s| [s.x, s.y, s.peak, s.fwhm_px].map(f64::to_bits)).collect::<Vec<_>>();
        // Another frame's work images; then junk of other sizes.
        let mut spare = Vec::new();
        assert_ne!(bits(&detect_reusing(&b, &g, &cfg, &mut spare)), bits(&fresh));
        assert_eq!(spare.len(), 3);
        assert_eq!(bits(&detect_reusing(&a, &g, &cfg, &mut spare)), bits(&fresh));
        let mut junk = vec![vec![f64::NAN; 7], vec![1e300; nx * ny + 5], vec![-3.0; nx * ny]];
        assert_eq!(bits(&detect_reusing(&a, &g, &cfg, &mut junk)), bits(&fresh));
    }
}
