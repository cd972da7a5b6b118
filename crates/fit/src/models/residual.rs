//! The residual field: what a radial model leaves in each bin (as `Q/I` and `U/I`, not as `p`,
//! so that residuals of different angles do not add up as positive numbers), interpolated by
//! natural neighbours on the Delaunay triangulation of the bins (spade). This is how a field
//! that is not radial (the paper's B band, fig:residB) is still corrected.

use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use spade::{DelaunayTriangulation, HasPosition, HierarchyHintGenerator, Point2, Triangulation};

/// One residual at a bin position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ResidualPoint {
    pub x: f64,
    pub y: f64,
    pub dq: f64,
    pub du: f64,
}

impl HasPosition for ResidualPoint {
    type Scalar = f64;
    fn position(&self) -> Point2<f64> {
        Point2::new(self.x, self.y)
    }
}

type Tri = DelaunayTriangulation<ResidualPoint, (), (), (), HierarchyHintGenerator<f64>>;

/// Natural-neighbour interpolant of the residual field.
#[derive(Debug, Clone)]
pub struct ResidualMap {
    points: Vec<ResidualPoint>,
    tri: Tri,
    /// RMS of the leave-one-out prediction errors of `dq` and `du`: each bin predicted from the
    /// others. It holds the interpolation error and the bins' own noise.
    pub loo_rms_q: f64,
    pub loo_rms_u: f64,
    /// Per point: leave-one-out prediction errors (NaN on the hull, where the point cannot be
    /// predicted from the others).
    pub loo_q: Vec<f64>,
    pub loo_u: Vec<f64>,
}

impl ResidualMap {
    /// Triangulate the residuals and estimate the interpolation error by leave-one-out.
    pub fn new(points: Vec<ResidualPoint>) -> Result<Self> {
        let points: Vec<ResidualPoint> = points
            .into_iter()
            .filter(|p| p.x.is_finite() && p.y.is_finite() && p.dq.is_finite() && p.du.is_finite())
            .collect();
        if points.len() < 3 {
            return Err(Error::TooFewBins { used: points.len(), total: points.len(), needed: 3 });
        }
        let mut tri = Tri::bulk_load(points.clone())
            .map_err(|e| Error::Input(format!("cannot triangulate the residual bins: {e:?}")))?;
        if tri.num_inner_faces() == 0 {
            return Err(Error::Degenerate("the residual bins are all on one line: no area to interpolate over".into()));
        }
        // Leave-one-out: take each vertex out, predict it from its neighbours, put it back.
        let mut loo_q = vec![f64::NAN; points.len()];
        let mut loo_u = vec![f64::NAN; points.len()];
        for (i, p) in points.iter().enumerate() {
            let pos = p.position();
            let Some(h) = tri.locate_vertex(pos).map(|v| v.fix()) else { continue };
            let removed = tri.remove(h);
            {
                let nn = tri.natural_neighbor();
                if let (Some(q), Some(u)) = (nn.interpolate(|v| v.data().dq, pos), nn.interpolate(|v| v.data().du, pos))
                {
                    loo_q[i] = q - p.dq;
                    loo_u[i] = u - p.du;
                }
            }
            tri.insert(removed).map_err(|e| Error::Input(format!("cannot re-insert bin {i}: {e:?}")))?;
        }
        let rms = |v: &[f64]| {
            let f: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
            if f.is_empty() {
                f64::NAN
            } else {
                (f.iter().map(|x| x * x).sum::<f64>() / f.len() as f64).sqrt()
            }
        };
        Ok(ResidualMap { loo_rms_q: rms(&loo_q), loo_rms_u: rms(&loo_u), points, tri, loo_q, loo_u })
    }

    /// The residual `(dq, du)` at `(x, y)` arcmin; `None` outside the convex hull of the bins.
    pub fn eval(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        // spade panics on positions it cannot represent (NaN, |v| > 2^201) instead of answering:
        // those are outside any hull of bins. Tiny values are flushed to 0 as spade's own inputs.
        if !(x.abs() <= spade::MAX_ALLOWED_VALUE && y.abs() <= spade::MAX_ALLOWED_VALUE) {
            return None;
        }
        let nn = self.tri.natural_neighbor();
        let pos = spade::mitigate_underflow(Point2::new(x, y));
        Some((nn.interpolate(|v| v.data().dq, pos)?, nn.interpolate(|v| v.data().du, pos)?))
    }

    /// The points the interpolant passes through.
    pub fn points(&self) -> &[ResidualPoint] {
        &self.points
    }
}

impl PartialEq for ResidualMap {
    fn eq(&self, other: &Self) -> bool {
        self.points == other.points
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_neighbour_reproduces_a_linear_field_and_is_none_outside() {
        // Natural-neighbour interpolation is exact for linear functions (Sibson).
        let f = |x: f64, y: f64| (0.3 * x - 0.2 * y + 0.1, -0.5 * x + 0.05);
        let mut pts = vec![];
        for i in 0..12 {
            for j in 0..12 {
                let (x, y) = (i as f64 * 0.5 + 0.1 * ((i * j) % 3) as f64, j as f64 * 0.5);
                let (q, u) = f(x, y);
                pts.push(ResidualPoint { x, y, dq: q, du: u });
            }
        }
        let m = ResidualMap::new(pts).unwrap();
        let (q, u) = m.eval(2.33, 3.71).unwrap();
        let (eq, eu) = f(2.33, 3.71);
        assert!((q - eq).abs() < 1e-12 && (u - eu).abs() < 1e-12);
        assert!(m.eval(-1.0, 0.0).is_none());
        // Leave-one-out errors of a linear field vanish too.
        assert!(m.loo_rms_q < 1e-10 && m.loo_rms_u < 1e-10, "{} {}", m.loo_rms_q, m.loo_rms_u);
    }

    #[test]
    fn collinear_bins_are_an_error() {
        let pts: Vec<_> = (0..10).map(|i| ResidualPoint { x: i as f64, y: 2.0 * i as f64, dq: 0.0, du: 0.0 }).collect();
        assert!(ResidualMap::new(pts).is_err());
    }
}
