//! Circular apertures on a pixel grid: the exact area of each pixel inside a circle, and the
//! re-centring of a point source by its flux-weighted centroid. Used by the photometry of
//! both beams, whose apertures sit at different sub-pixel phases when the o/e offset is not a
//! whole number of pixels (maskless layouts, a throw that varies across the field): weights by
//! the exact overlap area give both beams the same aperture, where whole-pixel apertures would
//! not.

use crate::bin::{from_total_key, total_key};

/// Antiderivative of `sqrt(r^2 - u^2)`: `(u sqrt(r^2 - u^2) + r^2 asin(u / r)) / 2`.
#[inline]
fn seg(u: f64, r: f64) -> f64 {
    let u = u.clamp(-r, r);
    0.5 * (u * (r * r - u * u).max(0.0).sqrt() + r * r * (u / r).asin())
}

/// Area of the intersection of the circle of radius `r` about the origin with the rectangle
/// `[x0, x1] x [y0, y1]`: the integral over `u` of the length of `[y0, y1]` inside the circle's
/// chord at `u`, split where the chord's ends cross `y0` or `y1` so that each piece is a line
/// or an arc (closed forms).
///
/// ```
/// use skyfield::aperture::circle_rect_area;
/// use std::f64::consts::PI;
/// // The whole circle, a quarter of it, and a half: pi r^2, pi r^2 / 4, pi r^2 / 2.
/// assert!((circle_rect_area(3.0, -5.0, 5.0, -5.0, 5.0) - 9.0 * PI).abs() < 1e-12);
/// assert!((circle_rect_area(3.0, 0.0, 5.0, 0.0, 5.0) - 9.0 * PI / 4.0).abs() < 1e-12);
/// assert!((circle_rect_area(3.0, -5.0, 5.0, 0.0, 5.0) - 9.0 * PI / 2.0).abs() < 1e-12);
/// ```
pub fn circle_rect_area(r: f64, x0: f64, x1: f64, y0: f64, y1: f64) -> f64 {
    if !(r > 0.0) || x1 <= x0 || y1 <= y0 {
        return 0.0;
    }
    let (a, b) = (x0.max(-r), x1.min(r));
    if a >= b {
        return 0.0;
    }
    // At most six cuts: on the stack (this runs for every edge pixel of every aperture).
    let (mut cuts, mut n) = ([0.0; 6], 2);
    (cuts[0], cuts[1]) = (a, b);
    for y in [y0, y1] {
        if y.abs() < r {
            let u = (r * r - y * y).sqrt();
            for c in [-u, u] {
                if c > a && c < b {
                    cuts[n] = c;
                    n += 1;
                }
            }
        }
    }
    let cuts = &mut cuts[..n];
    cuts.sort_unstable_by(f64::total_cmp);
    let mut area = 0.0;
    for w in cuts.windows(2) {
        let (p, q) = (w[0], w[1]);
        if q <= p {
            continue;
        }
        let m = 0.5 * (p + q);
        let s = (r * r - m * m).max(0.0).sqrt();
        if y1.min(s) <= y0.max(-s) {
            continue; // the rectangle misses the chord on this piece
        }
        let arc = seg(q, r) - seg(p, r);
        let top = if y1 < s { y1 * (q - p) } else { arc };
        let bottom = if y0 > -s { y0 * (q - p) } else { -arc };
        area += top - bottom;
    }
    area.max(0.0)
}

/// The pixels of an `nx` x `ny` detector that overlap the circle of radius `r` about `(xc, yc)`
/// (0-based pixel centres; pixel `(x, y)` spans `[x - 1/2, x + 1/2]`), with the fraction of
/// each pixel's area inside the circle (`Exact`), or 1 for pixels whose centre lies within `r`
/// (`Centre`). Pixels off the detector are left out (the caller checks coverage).
pub fn weights(xc: f64, yc: f64, r: f64, nx: usize, ny: usize, method: Weighting) -> Vec<(usize, usize, f64)> {
    let mut out = Vec::new();
    if !(xc.is_finite() && yc.is_finite() && r > 0.0) {
        return out;
    }
    let xa = (xc - r - 1.0).floor().max(0.0) as usize;
    let ya = (yc - r - 1.0).floor().max(0.0) as usize;
    let xb = ((xc + r + 1.0).ceil().max(0.0) as usize).min(nx.saturating_sub(1));
    let yb = ((yc + r + 1.0).ceil().max(0.0) as usize).min(ny.saturating_sub(1));
    for y in ya..=yb {
        for x in xa..=xb {
            let (dx, dy) = (x as f64 - xc, y as f64 - yc);
            let w = match method {
                Weighting::Centre => {
                    if dx * dx + dy * dy <= r * r {
                        1.0
                    } else {
                        0.0
                    }
                }
                Weighting::Exact => {
                    // Nearest and farthest points of the pixel from the centre decide the easy
                    // cases (all outside, all inside) without the integral.
                    let nxd = (dx.abs() - 0.5).max(0.0);
                    let nyd = (dy.abs() - 0.5).max(0.0);
                    if nxd * nxd + nyd * nyd >= r * r {
                        0.0
                    } else {
                        let fx = dx.abs() + 0.5;
                        let fy = dy.abs() + 0.5;
                        if fx * fx + fy * fy <= r * r {
                            1.0
                        } else {
                            circle_rect_area(r, dx - 0.5, dx + 0.5, dy - 0.5, dy + 0.5)
                        }
                    }
                }
            };
            if w > 0.0 {
                out.push((x, y, w));
            }
        }
    }
    out
}

/// How an aperture weighs the pixels on its edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Weighting {
    /// The exact fraction of each pixel's area inside the circle (the default).
    #[default]
    Exact,
    /// Whole pixels whose centre lies inside the circle.
    Centre,
}

/// The flux-weighted centroid of the source near `(x, y)` in an image (row-major `nx` x `ny`):
/// the local background (median of the pixels between `r` and `r + 4` px) is removed, pixels
/// within `r` px of the current estimate weigh by their flux above it, iterated until the
/// estimate moves by less than 0.001 px. `None` when no pixel rises above the background or
/// the centroid leaves the search radius of the starting point (no source there). Only pixels
/// for which `usable(x, y)` holds take part (those of one beam's image of a mask strip, say).
pub fn centroid(
    img: &[f64],
    nx: usize,
    ny: usize,
    x: f64,
    y: f64,
    r: f64,
    usable: impl Fn(usize, usize) -> bool,
) -> Option<(f64, f64)> {
    let last_x = nx.checked_sub(1)?;
    let last_y = ny.checked_sub(1)?;
    if !(x.is_finite() && y.is_finite() && r.is_finite() && r > 0.0) {
        return None;
    }
    // The pixels the iterations use are copied into a stamp, NaN where not usable, so the
    // iterations neither call `usable` nor test finiteness twice per pixel (same pixels, same
    // order, same sums as reading the image each time). The stamp reaches 2 px beyond the
    // current estimate's window and is made again about a later estimate whose window leaves
    // it: centroids move by a pixel or less, and a stamp for every place an estimate may go
    // (r + 4 px around each point within r) cost three times the pixels and most of the time.
    const MARGIN: f64 = 2.0;
    let mut stamp: Vec<f64> = Vec::new();
    let (mut sx0, mut sy0, mut sx1, mut sy1) = (1, 1, 0, 0);
    let (mut cx, mut cy) = (x, y);
    let (mut ring, mut inner) = (Vec::new(), Vec::new());
    for _ in 0..30 {
        let xa = (cx - r - 4.0).floor().max(0.0) as usize;
        let ya = (cy - r - 4.0).floor().max(0.0) as usize;
        let xb = ((cx + r + 4.0).ceil().max(0.0) as usize).min(last_x);
        let yb = ((cy + r + 4.0).ceil().max(0.0) as usize).min(last_y);
        if xa > xb || ya > yb {
            return None; // no pixel in the window: the estimate is off the image
        }
        if xa < sx0 || ya < sy0 || xb > sx1 || yb > sy1 {
            sx0 = (cx - r - 4.0 - MARGIN).floor().max(0.0) as usize;
            sy0 = (cy - r - 4.0 - MARGIN).floor().max(0.0) as usize;
            sx1 = ((cx + r + 4.0 + MARGIN).ceil().max(0.0) as usize).min(last_x);
            sy1 = ((cy + r + 4.0 + MARGIN).ceil().max(0.0) as usize).min(last_y);
            stamp.clear();
            for py in sy0..=sy1 {
                for px in sx0..=sx1 {
                    let v = img[py * nx + px];
                    stamp.push(if v.is_finite() && usable(px, py) { v } else { f64::NAN });
                }
            }
        }
        let sw_ = sx1 - sx0 + 1;
        let at = |px: usize, py: usize| stamp[(py - sy0) * sw_ + (px - sx0)];
        // One pass: the ring's values, and the pixels inside r (summed after the ring's
        // median, in the same order as a second pass over the window would sum them).
        ring.clear();
        inner.clear();
        for py in ya..=yb {
            for px in xa..=xb {
                let d2 = (px as f64 - cx).powi(2) + (py as f64 - cy).powi(2);
                let v = at(px, py);
                if d2 > r * r && d2 <= (r + 4.0) * (r + 4.0) && v.is_finite() {
                    ring.push(total_key(v));
                } else if d2 <= r * r && v.is_finite() {
                    inner.push((v, px as f64, py as f64));
                }
            }
        }
        if ring.is_empty() {
            return None;
        }
        let mid = ring.len() / 2;
        // Selected on the integer keys of the total order (the same value as `total_cmp`).
        let bg = from_total_key(*ring.select_nth_unstable(mid).1);
        let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for &(v, px, py) in &inner {
            let v = v - bg;
            if v > 0.0 {
                sw += v;
                sx += v * px;
                sy += v * py;
            }
        }
        if !(sw > 0.0) {
            return None;
        }
        let (nxc, nyc) = (sx / sw, sy / sw);
        if (nxc - x).hypot(nyc - y) > r {
            return None;
        }
        let moved = (nxc - cx).hypot(nyc - cy);
        (cx, cy) = (nxc, nyc);
        if moved < 1e-3 {
            break;
        }
    }
    Some((cx, cy))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The exact weights against an independent estimate: each pixel subdivided 400 x 400 and
    /// the sub-pixel centres inside the circle counted (error ~1/400 of the edge length).
    #[test]
    fn exact_weights_match_fine_subsampling() {
        let (xc, yc, r) = (10.37, 9.81, 3.3);
        let n = 400;
        for (x, y, w) in weights(xc, yc, r, 30, 30, Weighting::Exact) {
            let mut inside = 0usize;
            for i in 0..n {
                for j in 0..n {
                    let u = x as f64 - 0.5 + (i as f64 + 0.5) / n as f64 - xc;
                    let v = y as f64 - 0.5 + (j as f64 + 0.5) / n as f64 - yc;
                    inside += (u * u + v * v <= r * r) as usize;
                }
            }
            let sub = inside as f64 / (n * n) as f64;
            assert!((w - sub).abs() < 3e-3, "pixel ({x}, {y}): exact {w}, subsampled {sub}");
        }
    }

    /// The weights of a circle wholly on the detector add up to pi r^2 (to rounding), at any
    /// sub-pixel phase and radius, including radii below one pixel and 1/sqrt(2), the circle
    /// through the corners of the pixel it is centred on, and 0.7071 just inside them.
    #[test]
    #[allow(clippy::approx_constant)] // 0.7071 is meant to miss 1/sqrt(2)
    fn exact_weights_sum_to_the_circle_area() {
        for &(xc, yc) in &[(20.0, 20.0), (20.5, 20.5), (20.13, 19.77), (19.999, 20.25)] {
            for &r in &[0.2, 0.5, std::f64::consts::FRAC_1_SQRT_2, 0.7071, 1.0, 2.5, 7.3] {
                let s: f64 = weights(xc, yc, r, 64, 64, Weighting::Exact).iter().map(|w| w.2).sum();
                let area = std::f64::consts::PI * r * r;
                assert!((s - area).abs() < 1e-12 * area.max(1.0), "({xc}, {yc}) r = {r}: {s} vs {area}");
            }
        }
    }

    /// Closed forms: a quarter disc (rectangle = one quadrant), a half disc, a square inside.
    #[test]
    fn circle_rect_area_closed_forms() {
        let pi = std::f64::consts::PI;
        let r = 2.0;
        assert!((circle_rect_area(r, 0.0, 5.0, 0.0, 5.0) - pi).abs() < 1e-14);
        assert!((circle_rect_area(r, -5.0, 5.0, 0.0, 5.0) - 2.0 * pi).abs() < 1e-14);
        assert!((circle_rect_area(r, -1.0, 1.0, -1.0, 1.0) - 4.0).abs() < 1e-14);
        assert_eq!(circle_rect_area(r, 3.0, 4.0, 0.0, 1.0), 0.0);
        // A strip |y| < 1 of the disc of radius 2: 2 * (2 sqrt(3) / 2 * 1 + 4 asin(1/2)) ...
        // = integral of 2 sqrt(4 - y^2) over [-1, 1] = 2 sqrt(3) + 8 pi / 6 (swap the axes).
        let strip = circle_rect_area(r, -5.0, 5.0, -1.0, 1.0);
        assert!((strip - (2.0 * 3f64.sqrt() + 8.0 * pi / 6.0)).abs() < 1e-13, "{strip}");
    }

    /// A Gaussian star at a sub-pixel position is found to 0.01 px on a flat background.
    #[test]
    fn centroid_of_a_gaussian() {
        let (nx, ny) = (40, 40);
        let (x0, y0, s) = (17.3, 21.8, 1.6);
        let img: Vec<f64> = (0..nx * ny)
            .map(|k| {
                let (x, y) = ((k % nx) as f64, (k / nx) as f64);
                100.0 + 5000.0 * (-((x - x0).powi(2) + (y - y0).powi(2)) / (2.0 * s * s)).exp()
            })
            .collect();
        let (cx, cy) = centroid(&img, nx, ny, 16.0, 23.0, 6.0, |_, _| true).unwrap();
        assert!((cx - x0).abs() < 0.01 && (cy - y0).abs() < 0.01, "({cx}, {cy})");
        assert!(centroid(&vec![100.0; nx * ny], nx, ny, 16.0, 23.0, 6.0, |_, _| true).is_none());
    }

    /// The centroid's iterations as documented, written plainly: every window read from the
    /// image itself (NaN and unusable pixels skipped), the ring's median by a full sort.
    fn centroid_plain(
        img: &[f64],
        nx: usize,
        ny: usize,
        (x, y): (f64, f64),
        r: f64,
        usable: impl Fn(usize, usize) -> bool,
    ) -> Option<(f64, f64)> {
        let (mut cx, mut cy) = (x, y);
        for _ in 0..30 {
            let xa = (cx - r - 4.0).floor().max(0.0) as usize;
            let ya = (cy - r - 4.0).floor().max(0.0) as usize;
            let xb = ((cx + r + 4.0).ceil().max(0.0) as usize).min(nx - 1);
            let yb = ((cy + r + 4.0).ceil().max(0.0) as usize).min(ny - 1);
            let ok = |px: usize, py: usize| img[py * nx + px].is_finite() && usable(px, py);
            let d2 = |px: usize, py: usize| (px as f64 - cx).powi(2) + (py as f64 - cy).powi(2);
            let mut ring = Vec::new();
            for py in ya..=yb {
                for px in xa..=xb {
                    if ok(px, py) && d2(px, py) > r * r && d2(px, py) <= (r + 4.0) * (r + 4.0) {
                        ring.push(img[py * nx + px]);
                    }
                }
            }
            if ring.is_empty() {
                return None;
            }
            let bg = stokes::stats::robust::median(&mut ring, stokes::stats::robust::Middle::Upper);
            let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
            for py in ya..=yb {
                for px in xa..=xb {
                    let v = img[py * nx + px] - bg;
                    if ok(px, py) && d2(px, py) <= r * r && v > 0.0 {
                        sw += v;
                        sx += v * px as f64;
                        sy += v * py as f64;
                    }
                }
            }
            if !(sw > 0.0) {
                return None;
            }
            let (nxc, nyc) = (sx / sw, sy / sw);
            if (nxc - x).hypot(nyc - y) > r {
                return None;
            }
            let moved = (nxc - cx).hypot(nyc - cy);
            (cx, cy) = (nxc, nyc);
            if moved < 1e-3 {
                break;
            }
        }
        Some((cx, cy))
    }

    /// The centroid with its stamp of copied pixels (made again when an estimate wanders) is
    /// the plain iteration to the bit: starts 0 to 5 px off (estimates crossing the stamp's
    /// 2 px margin), next to the image's edges, with NaN pixels and a strip of unusable rows,
    /// and where nothing is found.
    #[test]
    fn centroid_is_the_plain_iteration_to_the_bit() {
        let (nx, ny) = (48, 44);
        let stars = [(20.3, 21.7), (2.2, 40.9), (45.6, 1.4)];
        let mut img: Vec<f64> = (0..nx * ny)
            .map(|k| {
                let (x, y) = ((k % nx) as f64, (k / nx) as f64);
                let f: f64 =
                    stars.iter().map(|(a, b)| 4000.0 * (-((x - a).powi(2) + (y - b).powi(2)) / 5.0).exp()).sum();
                100.0 + 0.3 * ((k * 7919) % 13) as f64 + f
            })
            .collect();
        img[21 * nx + 22] = f64::NAN;
        let strip = |_: usize, py: usize| !(30..34).contains(&py);
        let mut found = 0;
        for &(sx, sy) in &stars {
            for (dx, dy) in [(0.0, 0.0), (1.4, -0.8), (-3.1, 2.2), (4.0, 3.0), (-5.0, 0.5)] {
                for r in [3.0, 6.0] {
                    let at = (sx + dx, sy + dy);
                    let got = centroid(&img, nx, ny, at.0, at.1, r, strip);
                    let want = centroid_plain(&img, nx, ny, at, r, strip);
                    let bits = |p: Option<(f64, f64)>| p.map(|(a, b)| (a.to_bits(), b.to_bits()));
                    assert_eq!(bits(got), bits(want), "star ({sx}, {sy}) from {at:?}, r {r}");
                    found += got.is_some() as usize;
                }
            }
        }
        assert!(found > 10, "only {found} centroids found: the cases test little");
    }
}
