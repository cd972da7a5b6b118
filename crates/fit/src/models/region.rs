//! Where a model is valid and which parts of the field a fit leaves out.

use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// A part of the field left out of a fit.
///
/// Sectors and rings are polar coordinates about the radial model's optical-axis centre (the
/// fitted one when the centre is free; [`Exclusion::excludes_about`]), as the paper's polar
/// angle `alpha` of a bin about the axis (section `sec:fors1`, where the V band drops the
/// sector 10 to 80 deg), counter-clockwise from +x; boxes are in field coordinates (arcmin
/// from the detector centre). The CLI gives angles in degrees and they are kept in degrees
/// here because they are a user's specification, written back into calibration files as text.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Exclusion {
    /// Bins whose polar angle lies in `[from_deg, to_deg]` (counter-clockwise, wraps at 360).
    Sector { from_deg: f64, to_deg: f64 },
    /// Bins inside the box `[x0, x1] x [y0, y1]` arcmin.
    Box { x0: f64, x1: f64, y0: f64, y1: f64 },
    /// Bins whose distance from the model's centre lies in `[r0, r1]` arcmin.
    Ring { r0: f64, r1: f64 },
}

impl Exclusion {
    /// Whether the bin at `(x, y)` arcmin is excluded when the model's centre is the detector
    /// centre (`excludes_about(x, y, [0, 0])`).
    pub fn excludes(&self, x: f64, y: f64) -> bool {
        self.excludes_about(x, y, [0.0, 0.0])
    }

    /// Whether the bin at `(x, y)` arcmin (field coordinates) is excluded by a model whose
    /// optical-axis centre is `centre` (arcmin): sectors and rings are measured about `centre`,
    /// boxes are not.
    pub fn excludes_about(&self, x: f64, y: f64, centre: [f64; 2]) -> bool {
        let (dx, dy) = (x - centre[0], y - centre[1]);
        match *self {
            Exclusion::Sector { from_deg, to_deg } => {
                if dx == 0.0 && dy == 0.0 {
                    return false;
                }
                let a = dy.atan2(dx).to_degrees().rem_euclid(360.0);
                let lo = from_deg.rem_euclid(360.0);
                let width = (to_deg - from_deg).rem_euclid(360.0);
                (a - lo).rem_euclid(360.0) <= width
            }
            Exclusion::Box { x0, x1, y0, y1 } => x >= x0 && x <= x1 && y >= y0 && y <= y1,
            Exclusion::Ring { r0, r1 } => {
                let r = dx.hypot(dy);
                r >= r0 && r <= r1
            }
        }
    }

    /// Whether the exclusion depends on where the model's centre is (sectors and rings).
    pub fn is_polar(&self) -> bool {
        !matches!(self, Exclusion::Box { .. })
    }

    /// The specification as the CLI takes it (`sector:10:80`, `box:x0:x1:y0:y1`, `ring:r0:r1`).
    pub fn spec(&self) -> String {
        match self {
            Exclusion::Sector { from_deg, to_deg } => format!("sector:{from_deg}:{to_deg}"),
            Exclusion::Box { x0, x1, y0, y1 } => format!("box:{x0}:{x1}:{y0}:{y1}"),
            Exclusion::Ring { r0, r1 } => format!("ring:{r0}:{r1}"),
        }
    }
}

impl std::str::FromStr for Exclusion {
    type Err = Error;

    /// Parse `sector:FROM_DEG:TO_DEG`, `box:X0:X1:Y0:Y1` (arcmin) or `ring:R0:R1` (arcmin).
    fn from_str(s: &str) -> Result<Self> {
        let bad = |why: &str| Error::BadExclusion { spec: s.into(), why: why.into() };
        let mut parts = s.split(':');
        let kind = parts.next().unwrap_or("").trim().to_ascii_lowercase();
        let nums: Vec<f64> = parts
            .map(|t| t.trim().parse::<f64>().map_err(|_| bad(&format!("'{t}' is not a number"))))
            .collect::<Result<_>>()?;
        if nums.iter().any(|v| !v.is_finite()) {
            return Err(bad("numbers must be finite"));
        }
        match (kind.as_str(), nums.as_slice()) {
            ("sector", [a, b]) => {
                // Widths are taken modulo 360, so 0:360 was a sector of width 0 that excluded
                // nothing (silently); a full turn would exclude every bin.
                if (b - a).abs() >= 360.0 {
                    return Err(bad("a sector of 360 deg or more is the full circle: it would exclude every bin"));
                }
                if (b - a).rem_euclid(360.0) == 0.0 {
                    return Err(bad("FROM and TO are the same angle: the sector is empty"));
                }
                Ok(Exclusion::Sector { from_deg: *a, to_deg: *b })
            }
            ("box", [x0, x1, y0, y1]) => {
                if x1 <= x0 || y1 <= y0 {
                    return Err(bad("need x0 < x1 and y0 < y1"));
                }
                Ok(Exclusion::Box { x0: *x0, x1: *x1, y0: *y0, y1: *y1 })
            }
            ("ring", [r0, r1]) => {
                if *r0 < 0.0 || r1 <= r0 {
                    return Err(bad("need 0 <= r0 < r1"));
                }
                Ok(Exclusion::Ring { r0: *r0, r1: *r1 })
            }
            _ => Err(bad("expected sector:FROM_DEG:TO_DEG, box:X0:X1:Y0:Y1 or ring:R0:R1 (arcmin)")),
        }
    }
}

/// The rectangle of the field (arcmin from the detector centre) where a model was calibrated.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FieldRegion {
    pub x_min: f64,
    pub x_max: f64,
    pub y_min: f64,
    pub y_max: f64,
}

impl FieldRegion {
    /// Whether `(x, y)` arcmin lies inside, edges included to within [`Self::EDGE_TOLERANCE_ARCMIN`].
    ///
    /// Why a tolerance: the limits pass through a FITS header, which keeps 15 significant
    /// digits (CFITSIO's `%.15G`), and a position given in pixels passes through the pixel
    /// scale; a star on the edge was inside in arcmin and outside in pixels when either
    /// rounding went the wrong way. 1e-9 arcmin (6e-8 arcsec) is far below any position error
    /// and far above either rounding.
    pub fn contains(&self, x: f64, y: f64) -> bool {
        let t = Self::EDGE_TOLERANCE_ARCMIN;
        x >= self.x_min - t && x <= self.x_max + t && y >= self.y_min - t && y <= self.y_max + t
    }

    /// How far outside its limits [`Self::contains`] still counts a position as on the edge.
    pub const EDGE_TOLERANCE_ARCMIN: f64 = 1e-9;

    /// The smallest rectangle holding every point, widened by `margin` arcmin on each side.
    pub fn bounding(points: impl Iterator<Item = (f64, f64)>, margin: f64) -> Option<Self> {
        let mut r = FieldRegion {
            x_min: f64::INFINITY,
            x_max: f64::NEG_INFINITY,
            y_min: f64::INFINITY,
            y_max: f64::NEG_INFINITY,
        };
        let mut any = false;
        for (x, y) in points.filter(|(x, y)| x.is_finite() && y.is_finite()) {
            any = true;
            r.x_min = r.x_min.min(x);
            r.x_max = r.x_max.max(x);
            r.y_min = r.y_min.min(y);
            r.y_max = r.y_max.max(y);
        }
        any.then_some(FieldRegion {
            x_min: r.x_min - margin,
            x_max: r.x_max + margin,
            y_min: r.y_min - margin,
            y_max: r.y_max + margin,
        })
    }

    /// Largest distance from `(x0, y0)` to a corner: the radius a radial profile must reach.
    pub fn max_radius_from(&self, x0: f64, y0: f64) -> f64 {
        [(self.x_min, self.y_min), (self.x_min, self.y_max), (self.x_max, self.y_min), (self.x_max, self.y_max)]
            .iter()
            .map(|(x, y)| (x - x0).hypot(y - y0))
            .fold(0.0, f64::max)
    }
}

/// Polar angle of `(dx, dy)` in (-pi, pi], the paper's `alpha`.
pub fn polar_angle(dx: f64, dy: f64) -> f64 {
    let a = dy.atan2(dx);
    if a <= -PI {
        a + 2.0 * PI
    } else {
        a
    }
}

#[cfg(test)]
mod tests {
    /// A limit as a FITS header keeps it: 15 significant digits (CFITSIO writes `%.15G`).
    fn as_header(v: f64) -> f64 {
        format!("{v:.14e}").parse().unwrap()
    }

    /// The field's edge is inside whichever way the header's rounding and the pixel scale's
    /// went: 0.1 + 0.2 (= 0.30000000000000004) is stored as 0.3, below a star placed at the
    /// edge in arcmin; a star given in pixels on FORS1's 0.2"/px grid lands a few ulps beyond.
    /// A position 1e-6 arcmin beyond the edge is still outside.
    #[test]
    fn the_edge_survives_header_rounding_and_the_pixel_scale() {
        let edge = 0.1 + 0.2;
        assert!(as_header(edge) < edge, "the case must round down");
        let r = super::FieldRegion { x_min: -as_header(edge), x_max: as_header(edge), y_min: -1.0, y_max: 1.0 };
        let scale_arcsec = 0.2;
        // The pixel of the edge and back, as `correct --coords px` computes it.
        let px = edge * 60.0 / scale_arcsec;
        let from_px = px * scale_arcsec / 60.0;
        for x in [edge, -edge, from_px, -from_px] {
            assert!(r.contains(x, 0.0), "{x:e} on the edge counted outside");
        }
        for x in [edge + 1e-6, -edge - 1e-6] {
            assert!(!r.contains(x, 0.0), "{x:e} beyond the edge counted inside");
        }
    }

    use super::*;

    #[test]
    fn sector_10_80_of_sec_fors1() {
        let e: Exclusion = "sector:10:80".parse().unwrap();
        let at = |deg: f64| e.excludes(deg.to_radians().cos(), deg.to_radians().sin());
        assert!(at(45.0) && at(10.5) && at(79.5));
        assert!(!at(5.0) && !at(85.0) && !at(225.0) && !at(-45.0));
        // A sector across the wrap at 0 deg.
        let w: Exclusion = "sector:350:20".parse().unwrap();
        let atw = |deg: f64| w.excludes(deg.to_radians().cos(), deg.to_radians().sin());
        assert!(atw(0.0) && atw(355.0) && atw(-5.0) && atw(19.0));
        assert!(!atw(30.0) && !atw(340.0));
    }

    #[test]
    fn sectors_and_rings_follow_the_centre_boxes_do_not() {
        // A point 1 arcmin above a centre at (2, 0): polar angle 90 deg about that centre,
        // ~153 deg about the detector centre.
        let c = [2.0, 0.0];
        let s: Exclusion = "sector:80:100".parse().unwrap();
        assert!(s.excludes_about(2.0, 1.0, c) && !s.excludes(2.0, 1.0));
        let r: Exclusion = "ring:0:1.5".parse().unwrap();
        assert!(r.excludes_about(2.0, 1.0, c) && !r.excludes(2.0, 1.0));
        let b: Exclusion = "box:1.5:2.5:0.5:1.5".parse().unwrap();
        assert!(b.excludes_about(2.0, 1.0, c) && b.excludes(2.0, 1.0) && !b.excludes_about(0.0, 1.0, [-2.0, 0.0]));
        assert!(s.is_polar() && r.is_polar() && !b.is_polar());
    }

    #[test]
    fn box_and_ring_and_bad_specs() {
        let b: Exclusion = "box:-1:1:0:2".parse().unwrap();
        assert!(b.excludes(0.0, 1.0) && !b.excludes(0.0, -0.5));
        let r: Exclusion = "ring:0:0.5".parse().unwrap();
        assert!(r.excludes(0.3, 0.3) && !r.excludes(0.5, 0.5));
        for bad in [
            "sector:10",
            "box:1:0:0:1",
            "circle:1:2",
            "sector:a:b",
            "ring:2:1",
            "sector:0:360",
            "sector:-180:180",
            "sector:10:730",
            "sector:30:30",
        ] {
            let e = bad.parse::<Exclusion>().unwrap_err().to_string();
            assert!(e.contains(bad), "{e}");
        }
        assert_eq!(b.spec().parse::<Exclusion>().unwrap(), b);
    }
}
