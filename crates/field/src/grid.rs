//! A gridded map of the instrumental `Q/I`, `U/I` with errors: the form in which calibration
//! files store their images, the model of an imported third-party map, and a simulation's
//! map-shaped input field (evaluated by nearest cell, [`NearestCell`]).

use crate::coords::FieldCoords;
use crate::model::{FieldModel, InstPol};
use serde::{Deserialize, Serialize};

/// A regular grid of `q`, `u` (fractions) and their errors, row-major `[j * nx + i]`, NaN where
/// there is no measurement. Pixel `(i, j)` is centred at `(x0 + i dx, y0 + j dy)` arcmin.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridMap {
    pub nx: usize,
    pub ny: usize,
    pub x0: f64,
    pub y0: f64,
    pub dx: f64,
    pub dy: f64,
    pub q: Vec<f64>,
    pub u: Vec<f64>,
    pub sigma_q: Vec<f64>,
    pub sigma_u: Vec<f64>,
}

impl GridMap {
    /// A map whose pixel `(i, j)` is pixel `(i, j)` of `coords` (binned or not): pixel centres
    /// at `coords.pixel_to_arcmin(i, j)`, steps of one (binned) pixel. The values are
    /// row-major `[j * nx + i]`, each `nx * ny` long.
    #[allow(clippy::too_many_arguments)]
    pub fn on_pixels(
        coords: &FieldCoords,
        nx: usize,
        ny: usize,
        q: Vec<f64>,
        u: Vec<f64>,
        sigma_q: Vec<f64>,
        sigma_u: Vec<f64>,
    ) -> Self {
        let (x0, y0) = coords.pixel_to_arcmin(0.0, 0.0);
        let d = coords.arcmin_per_px();
        GridMap { nx, ny, x0, y0, dx: d, dy: d, q, u, sigma_q, sigma_u }
    }

    /// `model` sampled at the centres of the `nx x ny` pixels of `coords` (e.g. 16 x 16 px
    /// cells of a detector), with the model's own errors.
    pub fn sample(model: &dyn FieldModel, coords: &FieldCoords, nx: usize, ny: usize) -> Self {
        let mut g = Self::on_pixels(
            coords,
            nx,
            ny,
            vec![0.0; nx * ny],
            vec![0.0; nx * ny],
            vec![0.0; nx * ny],
            vec![0.0; nx * ny],
        );
        for j in 0..ny {
            for i in 0..nx {
                let (x, y) = coords.pixel_to_arcmin(i as f64, j as f64);
                let v = model.eval(x, y);
                let k = j * nx + i;
                g.q[k] = v.q;
                g.u[k] = v.u;
                g.sigma_q[k] = v.var_q.sqrt();
                g.sigma_u[k] = v.var_u.sqrt();
            }
        }
        g
    }

    /// The measured pixel whose cell holds `(x, y)` arcmin (the nearest pixel centre), if any.
    pub fn nearest(&self, x: f64, y: f64) -> Option<InstPol> {
        let (fi, fj) = self.frac(x, y);
        let (i, j) = (fi.round(), fj.round());
        if !(i >= 0.0 && j >= 0.0 && i < self.nx as f64 && j < self.ny as f64) {
            return None;
        }
        let (i, j) = (i as usize, j as usize);
        if !self.is_finite_at(i, j) {
            return None;
        }
        let k = j * self.nx + i;
        Some(InstPol {
            q: self.q[k],
            u: self.u[k],
            var_q: self.sigma_q[k].powi(2),
            var_u: self.sigma_u[k].powi(2),
            cov_qu: 0.0,
        })
    }

    /// Centre of pixel `(i, j)` in arcmin.
    pub fn pixel_centre(&self, i: usize, j: usize) -> (f64, f64) {
        (self.x0 + i as f64 * self.dx, self.y0 + j as f64 * self.dy)
    }

    /// Whether pixel `(i, j)` holds a measurement.
    pub fn is_finite_at(&self, i: usize, j: usize) -> bool {
        let k = j * self.nx + i;
        self.q[k].is_finite() && self.u[k].is_finite()
    }

    /// Fractional pixel coordinates of `(x, y)` arcmin.
    fn frac(&self, x: f64, y: f64) -> (f64, f64) {
        ((x - self.x0) / self.dx, (y - self.y0) / self.dy)
    }

    /// Bilinear interpolation over the measured corners of the cell around `(x, y)`: corners
    /// without a measurement are left out and the weights renormalized, so the map is usable
    /// up to its NaN edges. `None` when no corner is measured or the point is off the grid.
    ///
    /// ```
    /// use field::{FieldCoords, GridMap};
    /// // A 2 x 2 map of q = 0, 0.01 (left, right) and u = 0: halfway between the pixel centres the
    /// // bilinear value is the mean, 0.005; beyond half a pixel outside the grid there is none.
    /// let c = FieldCoords::with_origin([0.0, 0.0], 60.0); // 1 px = 1'
    /// let m = GridMap::on_pixels(&c, 2, 2, vec![0.0, 0.01, 0.0, 0.01], vec![0.0; 4], vec![1e-4; 4], vec![1e-4; 4]);
    /// assert!((m.interpolate(0.5, 0.5).unwrap().q - 0.005).abs() < 1e-16);
    /// assert!(m.interpolate(3.0, 0.0).is_none());
    /// ```
    pub fn interpolate(&self, x: f64, y: f64) -> Option<InstPol> {
        let (fi, fj) = self.frac(x, y);
        if !(fi > -0.5 && fj > -0.5 && fi < self.nx as f64 - 0.5 && fj < self.ny as f64 - 0.5) {
            return None;
        }
        let i0 = fi.floor().clamp(0.0, (self.nx.max(2) - 2) as f64) as usize;
        let j0 = fj.floor().clamp(0.0, (self.ny.max(2) - 2) as f64) as usize;
        let (tx, ty) = ((fi - i0 as f64).clamp(0.0, 1.0), (fj - j0 as f64).clamp(0.0, 1.0));
        let mut acc = [0.0; 5];
        let mut wsum = 0.0;
        for (di, dj, w) in
            [(0, 0, (1.0 - tx) * (1.0 - ty)), (1, 0, tx * (1.0 - ty)), (0, 1, (1.0 - tx) * ty), (1, 1, tx * ty)]
        {
            let (i, j) = (i0 + di, j0 + dj);
            if i >= self.nx || j >= self.ny || w <= 0.0 || !self.is_finite_at(i, j) {
                continue;
            }
            let k = j * self.nx + i;
            acc[0] += w * self.q[k];
            acc[1] += w * self.u[k];
            acc[2] += w * self.sigma_q[k].powi(2);
            acc[3] += w * self.sigma_u[k].powi(2);
            wsum += w;
        }
        if wsum <= 0.0 {
            // The point sits exactly on a measured pixel whose neighbours are all NaN.
            let (i, j) = (fi.round() as usize, fj.round() as usize);
            if i < self.nx && j < self.ny && self.is_finite_at(i, j) {
                let k = j * self.nx + i;
                return Some(InstPol {
                    q: self.q[k],
                    u: self.u[k],
                    var_q: self.sigma_q[k].powi(2),
                    var_u: self.sigma_u[k].powi(2),
                    cov_qu: 0.0,
                });
            }
            return None;
        }
        // The pixel errors are treated as fully correlated between neighbours (smoothed maps),
        // so the variance is the weighted mean of the variances.
        Some(InstPol { q: acc[0] / wsum, u: acc[1] / wsum, var_q: acc[2] / wsum, var_u: acc[3] / wsum, cov_qu: 0.0 })
    }
}

impl FieldModel for GridMap {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        self.interpolate(x, y).unwrap_or(InstPol {
            q: f64::NAN,
            u: f64::NAN,
            var_q: f64::NAN,
            var_u: f64::NAN,
            cov_qu: 0.0,
        })
    }

    fn contains(&self, x: f64, y: f64) -> bool {
        let (fi, fj) = self.frac(x, y);
        let (i, j) = (fi.round(), fj.round());
        i >= 0.0
            && j >= 0.0
            && (i as usize) < self.nx
            && (j as usize) < self.ny
            && self.is_finite_at(i as usize, j as usize)
    }

    fn describe(&self) -> String {
        format!("{} x {} map, bilinear, {:.4}' x {:.4}' per pixel", self.nx, self.ny, self.dx, self.dy)
    }
}

/// A [`GridMap`] evaluated piecewise constant: every position takes the value of the map
/// pixel whose cell holds it (no interpolation), NaN outside the map or on a pixel without a
/// measurement. This is how a simulation's map-shaped input field covers the detector: each
/// map pixel is a block of detector pixels with one `M_I`.
#[derive(Debug, Clone, PartialEq)]
pub struct NearestCell(pub GridMap);

impl FieldModel for NearestCell {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        self.0.nearest(x, y).unwrap_or(InstPol {
            q: f64::NAN,
            u: f64::NAN,
            var_q: f64::NAN,
            var_u: f64::NAN,
            cov_qu: 0.0,
        })
    }

    fn contains(&self, x: f64, y: f64) -> bool {
        self.0.nearest(x, y).is_some()
    }

    fn describe(&self) -> String {
        format!("{} x {} map, nearest cell, {:.4}' x {:.4}' per cell", self.0.nx, self.0.ny, self.0.dx, self.0.dy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_is_exact_on_planes_and_respects_nan() {
        let (nx, ny) = (5, 4);
        let f = |x: f64, y: f64| 0.01 * x - 0.002 * y;
        let mut g = GridMap {
            nx,
            ny,
            x0: -1.0,
            y0: -2.0,
            dx: 0.5,
            dy: 0.25,
            q: vec![0.0; nx * ny],
            u: vec![0.0; nx * ny],
            sigma_q: vec![1e-4; nx * ny],
            sigma_u: vec![1e-4; nx * ny],
        };
        for j in 0..ny {
            for i in 0..nx {
                let (x, y) = g.pixel_centre(i, j);
                g.q[j * nx + i] = f(x, y);
                g.u[j * nx + i] = -f(x, y);
            }
        }
        let v = g.interpolate(-0.1, -1.6).unwrap();
        assert!((v.q - f(-0.1, -1.6)).abs() < 1e-15 && (v.u + f(-0.1, -1.6)).abs() < 1e-15);
        assert!((v.var_q.sqrt() - 1e-4).abs() < 1e-18);
        assert!(g.interpolate(10.0, 0.0).is_none());
        g.q[nx + 1] = f64::NAN;
        assert!(!g.contains(-0.5, -1.75));
        let v = g.interpolate(-0.4, -1.7).unwrap();
        assert!(v.q.is_finite(), "a NaN corner is left out");
    }

    /// Nearest cell on 16-px cells of a 100 x 40 px detector (7 x 3 cells, the last ones cut):
    /// detector pixel `(x, y)` takes cell `(x / 16, y / 16)` (integer division), as the
    /// simulator's map input did before it took models.
    #[test]
    fn nearest_cell_is_integer_division_of_pixels() {
        let det = FieldCoords::centred(100, 40, 0.2);
        let cells = det.binned(16);
        let (nx, ny) = (7, 3);
        let q: Vec<f64> = (0..nx * ny).map(|k| k as f64).collect();
        let mut g =
            GridMap::on_pixels(&cells, nx, ny, q.clone(), vec![0.5; nx * ny], vec![0.0; nx * ny], vec![0.0; nx * ny]);
        g.q[nx + 2] = f64::NAN;
        let m = NearestCell(g);
        for y in 0..40usize {
            for x in 0..100usize {
                let (xa, ya) = det.pixel_to_arcmin(x as f64, y as f64);
                let v = m.eval(xa, ya);
                let k = (y / 16) * nx + x / 16;
                if k == nx + 2 {
                    assert!(v.q.is_nan() && !m.contains(xa, ya));
                } else {
                    assert_eq!(v.q, q[k], "pixel ({x}, {y})");
                }
            }
        }
        // Outside the 7 x 16 = 112 px the map covers: nothing.
        let (xa, ya) = det.pixel_to_arcmin(112.0, 0.0);
        assert!(m.eval(xa, ya).q.is_nan());
        let (xa, ya) = det.pixel_to_arcmin(111.0, 0.0);
        assert_eq!(m.eval(xa, ya).q, 6.0);
    }
}
