//! Frame-to-frame alignment from matched stars: each frame's shift and small
//! rotation (and scale) against the first, as the least-squares similarity transform
//! `q = s R(theta) p + t` between the stars' positions `p` in the first frame and `q` in this
//! one. The closed form (centre both sets; `a = sum p'.q'`, `b = sum p' x q'`;
//! `theta = atan2(b, a)`, `s = sqrt(a^2 + b^2) / sum |p'|^2`) needs no iteration and is exact for
//! noiseless points. Errors come from the residual scatter: `sigma_theta = sigma / sqrt(sum
//! |p'|^2)` per axis, `sigma` the rms residual per coordinate over `2n - 4` degrees of freedom.
//!
//! The apertures of `instpol photometry` and `catalog` follow each star by its own centroid, so
//! a rotation is followed already for every star bright enough to centre; the transform is
//! measured from those centroids and reported, and a rotation beyond its noise is said.

/// One frame's similarity transform against the reference frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Similarity {
    /// Rotation (rad, counter-clockwise in pixel coordinates) and its 1-sigma error.
    pub rotation: f64,
    pub sigma_rotation: f64,
    /// Scale (1: none).
    pub scale: f64,
    /// Translation (px): `q = s R p + t`.
    pub tx: f64,
    pub ty: f64,
    /// The shift of the stars' centroid (px), the translation a shift-only model would give.
    pub dx: f64,
    pub dy: f64,
    /// rms residual per coordinate (px) and the number of stars.
    pub rms_px: f64,
    pub n_stars: usize,
}

impl Similarity {
    /// Map a reference-frame position into this frame.
    pub fn apply(&self, x: f64, y: f64) -> (f64, f64) {
        let (s, c) = self.rotation.sin_cos();
        (self.scale * (c * x - s * y) + self.tx, self.scale * (s * x + c * y) + self.ty)
    }

    /// The rotation is measured beyond `k` times its error.
    pub fn rotation_significant(&self, k: f64) -> bool {
        self.rotation.abs() > k * self.sigma_rotation
    }
}

/// The least-squares similarity transform taking `from[k]` to `to[k]` (see the module docs).
/// `None` with fewer than three pairs, non-finite positions, or all stars at one point.
pub fn similarity(from: &[(f64, f64)], to: &[(f64, f64)]) -> Option<Similarity> {
    let pairs: Vec<((f64, f64), (f64, f64))> = from
        .iter()
        .zip(to)
        .filter(|(p, q)| p.0.is_finite() && p.1.is_finite() && q.0.is_finite() && q.1.is_finite())
        .map(|(p, q)| (*p, *q))
        .collect();
    let n = pairs.len();
    if n < 3 {
        return None;
    }
    let nf = n as f64;
    let (px, py) = pairs.iter().fold((0.0, 0.0), |a, (p, _)| (a.0 + p.0, a.1 + p.1));
    let (qx, qy) = pairs.iter().fold((0.0, 0.0), |a, (_, q)| (a.0 + q.0, a.1 + q.1));
    let (px, py, qx, qy) = (px / nf, py / nf, qx / nf, qy / nf);
    let (mut a, mut b, mut spp) = (0.0, 0.0, 0.0);
    for ((x0, y0), (x1, y1)) in &pairs {
        let (u, v, u1, v1) = (x0 - px, y0 - py, x1 - qx, y1 - qy);
        a += u * u1 + v * v1;
        b += u * v1 - v * u1;
        spp += u * u + v * v;
    }
    if !(spp > 0.0) {
        return None;
    }
    let rotation = b.atan2(a);
    let scale = a.hypot(b) / spp;
    let (s, c) = rotation.sin_cos();
    let tx = qx - scale * (c * px - s * py);
    let ty = qy - scale * (s * px + c * py);
    let mut t = Similarity {
        rotation,
        sigma_rotation: f64::NAN,
        scale,
        tx,
        ty,
        dx: qx - px,
        dy: qy - py,
        rms_px: f64::NAN,
        n_stars: n,
    };
    let ss: f64 = pairs
        .iter()
        .map(|((x0, y0), (x1, y1))| {
            let (mx, my) = t.apply(*x0, *y0);
            (x1 - mx).powi(2) + (y1 - my).powi(2)
        })
        .sum();
    // Four parameters on 2n coordinates.
    let dof = 2 * n - 4;
    if dof > 0 {
        t.rms_px = (ss / dof as f64).sqrt();
        t.sigma_rotation = t.rms_px / (scale * spp.sqrt());
    }
    Some(t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_distr::{Distribution, Normal};

    /// 40 stars rotated by 0.2 deg about (350, 420) and shifted by (1.3, -2.1) px, with
    /// 0.02 px centroid noise: the rotation comes back within 4 sigma, its error matches the
    /// closed form sigma / sqrt(sum |p'|^2), the transform maps the pivot to itself plus the
    /// shift, and the rotation is significant (0.2 deg is ~100 sigma here).
    #[test]
    fn rotation_about_a_point() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        let (cx, cy, th, sx, sy, noise) = (350.0, 420.0, 0.2f64.to_radians(), 1.3, -2.1, 0.02);
        let from: Vec<(f64, f64)> =
            (0..40).map(|_| (rng.random_range(0.0..700.0), rng.random_range(0.0..700.0))).collect();
        let normal = Normal::new(0.0, 1.0).unwrap();
        let g = |rng: &mut rand_xoshiro::Xoshiro256PlusPlus| normal.sample(rng);
        let to: Vec<(f64, f64)> = from
            .iter()
            .map(|&(x, y)| {
                let (dx, dy) = (x - cx, y - cy);
                let (s, c) = th.sin_cos();
                (cx + c * dx - s * dy + sx + noise * g(&mut rng), cy + s * dx + c * dy + sy + noise * g(&mut rng))
            })
            .collect();
        let t = similarity(&from, &to).unwrap();
        assert!((t.rotation - th).abs() < 4.0 * t.sigma_rotation, "{} vs {th} +- {}", t.rotation, t.sigma_rotation);
        assert!((t.scale - 1.0).abs() < 1e-4);
        assert!((t.rms_px - noise).abs() < 0.3 * noise, "rms {}", t.rms_px);
        let (mx, my) = t.apply(cx, cy);
        assert!((mx - cx - sx).abs() < 0.02 && (my - cy - sy).abs() < 0.02, "pivot -> ({mx}, {my})");
        assert!(t.rotation_significant(5.0));
        // Noiseless points: exact to rounding.
        let exact: Vec<(f64, f64)> = from
            .iter()
            .map(|&(x, y)| {
                let (s, c) = th.sin_cos();
                (cx + c * (x - cx) - s * (y - cy), cy + s * (x - cx) + c * (y - cy))
            })
            .collect();
        let e = similarity(&from, &exact).unwrap();
        assert!((e.rotation - th).abs() < 1e-13 && (e.scale - 1.0).abs() < 1e-13 && e.rms_px < 1e-9);
        // A pure shift: no rotation, significant or not.
        let shifted: Vec<(f64, f64)> = from.iter().map(|&(x, y)| (x + 2.5 + noise * g(&mut rng), y - 1.0)).collect();
        let s = similarity(&from, &shifted).unwrap();
        assert!(!s.rotation_significant(5.0) && (s.dx - 2.5).abs() < 0.01, "{s:?}");
        // Degenerate inputs.
        assert!(similarity(&from[..2], &to[..2]).is_none());
        assert!(similarity(&[(1.0, 1.0); 5], &[(2.0, 2.0); 5]).is_none());
    }
}
