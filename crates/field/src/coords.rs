//! The one conversion between detector pixels and field positions.

use serde::{Deserialize, Serialize};

/// Detector pixels <-> field arcminutes about an origin, with binning.
///
/// A field position `(x, y)` is in arcmin from the origin, `x` along increasing detector
/// columns and `y` along increasing rows (arcmin from the detector centre unless an optical-axis
/// centre is fitted: `docs/architecture.md`, Conventions). Pixel coordinates are 0-based,
/// pixel `i` spanning `[i - 0.5, i + 0.5)` (FITS 1-based only in headers).
///
/// Binning: with `binning = b`, pixel coordinates count `b x b` blocks of unbinned detector
/// pixels; binned pixel `i` covers unbinned pixels `[b i, b i + b)` and is centred on
/// unbinned `b i + (b - 1)/2`. The origin and the scale always refer to unbinned pixels, so one
/// `FieldCoords` describes the detector and [`binned`](Self::binned) views of it share its
/// origin.
///
/// ```
/// use field::FieldCoords;
/// // FORS1: 2048 x 2048 px of 0.2"; the corner pixel (0, 0) is 1023.5 px = 3.4117' from the centre.
/// let c = FieldCoords::centred(2048, 2048, 0.2);
/// let (x, y) = c.pixel_to_arcmin(0.0, 0.0);
/// assert!((x + 1023.5 * 0.2 / 60.0).abs() < 1e-15 && (y - x).abs() < 1e-15);
/// // 30 x 30 px bins: bin (0, 0) is centred on unbinned pixel 14.5.
/// let (bx, _) = c.binned(30).pixel_to_arcmin(0.0, 0.0);
/// assert!((bx - (14.5 - 1023.5) * 0.2 / 60.0).abs() < 1e-15);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FieldCoords {
    /// The unbinned 0-based detector pixel at field position `(0, 0)`.
    pub origin_px: [f64; 2],
    /// Arcseconds per unbinned detector pixel.
    pub scale_arcsec: f64,
    /// Unbinned detector pixels per coordinate pixel along each axis (1: unbinned).
    pub binning: usize,
}

impl FieldCoords {
    /// Coordinates of an `nx x ny` px detector of `scale_arcsec` arcsec/px about its centre,
    /// unbinned pixel `((nx - 1)/2, (ny - 1)/2)`.
    pub fn centred(nx: usize, ny: usize, scale_arcsec: f64) -> Self {
        Self::with_origin([0.5 * (nx as f64 - 1.0), 0.5 * (ny as f64 - 1.0)], scale_arcsec)
    }

    /// Coordinates about unbinned pixel `origin_px` (e.g. the centre of an imported map, or a
    /// fitted optical axis).
    pub fn with_origin(origin_px: [f64; 2], scale_arcsec: f64) -> Self {
        Self { origin_px, scale_arcsec, binning: 1 }
    }

    /// The same field with pixel coordinates counting `b x b` blocks of unbinned pixels.
    /// Binning composes: `c.binned(2).binned(3)` is `c.binned(6)`. `b = 0` is taken as 1.
    ///
    /// ```
    /// use field::FieldCoords;
    /// // Binning composes: 2 x 2 of 3 x 3 is 6 x 6; binned pixel 0 is centred on unbinned 2.5.
    /// let c = FieldCoords::centred(2048, 2048, 0.2);
    /// assert_eq!(c.binned(2).binned(3), c.binned(6));
    /// assert_eq!(c.binned(6).pixel_to_arcmin(0.0, 0.0), c.pixel_to_arcmin(2.5, 2.5));
    /// ```
    pub fn binned(self, b: usize) -> Self {
        Self { binning: self.binning * b.max(1), ..self }
    }

    /// The same pixels with the field origin moved to `centre_arcmin` (a fitted optical-axis
    /// centre, in arcmin of these coordinates): that point becomes `(0, 0)`.
    pub fn about(self, centre_arcmin: [f64; 2]) -> Self {
        let s = 60.0 / self.scale_arcsec;
        let origin_px = [self.origin_px[0] + centre_arcmin[0] * s, self.origin_px[1] + centre_arcmin[1] * s];
        Self { origin_px, ..self }
    }

    /// Arcminutes per coordinate pixel (binned).
    pub fn arcmin_per_px(&self) -> f64 {
        self.binning as f64 * (self.scale_arcsec / 60.0)
    }

    /// Unbinned detector pixel of (binned) pixel coordinate `x`, along one axis.
    #[inline]
    fn unbinned(&self, x: f64) -> f64 {
        // b x + (b - 1)/2: exactly x when b = 1.
        let b = self.binning as f64;
        b * x + 0.5 * (b - 1.0)
    }

    /// Field position (arcmin from the origin) of 0-based pixel `(x, y)` (binned pixels when
    /// [`binning`](Self::binning) > 1).
    #[inline]
    pub fn pixel_to_arcmin(&self, x: f64, y: f64) -> (f64, f64) {
        let s = self.scale_arcsec / 60.0;
        ((self.unbinned(x) - self.origin_px[0]) * s, (self.unbinned(y) - self.origin_px[1]) * s)
    }

    /// 0-based pixel (binned when [`binning`](Self::binning) > 1) of field position `(x, y)`
    /// arcmin from the origin.
    ///
    /// ```
    /// use field::FieldCoords;
    /// // FORS1 (2048 x 2048 px of 0.2"): the field's centre is between pixels 1023 and 1024, and
    /// // 1' is 300 px.
    /// let c = FieldCoords::centred(2048, 2048, 0.2);
    /// assert_eq!(c.arcmin_to_pixel(0.0, 0.0), (1023.5, 1023.5));
    /// let (x, y) = c.arcmin_to_pixel(1.0, -1.0);
    /// assert!((x - 1323.5).abs() < 1e-12 && (y - 723.5).abs() < 1e-12);
    /// ```
    #[inline]
    pub fn arcmin_to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        let s = 60.0 / self.scale_arcsec;
        let (ux, uy) = (x * s + self.origin_px[0], y * s + self.origin_px[1]);
        if self.binning == 1 {
            return (ux, uy);
        }
        let b = self.binning as f64;
        ((ux - 0.5 * (b - 1.0)) / b, (uy - 0.5 * (b - 1.0)) / b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FORS1: (usize, usize, f64) = (2048, 2048, 0.2);

    /// The corner pixel of FORS1 by hand: 1023.5 px x 0.2"/px = 204.7" = 3.411667'.
    #[test]
    fn corner_pixel_against_hand_computation() {
        let c = FieldCoords::centred(FORS1.0, FORS1.1, FORS1.2);
        let (x, y) = c.pixel_to_arcmin(0.0, 2047.0);
        assert!((x + 3.411_666_666_666_667).abs() < 1e-12, "{x}");
        assert!((y - 3.411_666_666_666_667).abs() < 1e-12, "{y}");
        let (px, py) = c.arcmin_to_pixel(3.411_666_666_666_667, 0.0);
        assert!((px - 2047.0).abs() < 1e-9 && (py - 1023.5).abs() < 1e-12);
        // A non-square detector: the centre of 4096 x 2048 px of 0.25" is pixel (2047.5, 1023.5).
        let w = FieldCoords::centred(4096, 2048, 0.25);
        let (x, y) = w.pixel_to_arcmin(2047.5, 1023.5);
        assert!(x.abs() < 1e-15 && y.abs() < 1e-15);
        let (x, _) = w.pixel_to_arcmin(4095.0, 0.0);
        assert!((x - 2047.5 * 0.25 / 60.0).abs() < 1e-15);
    }

    /// 2x2 binning of FORS2-like 0.125" pixels: binned pixel (0, 0) covers unbinned 0..2 and is
    /// centred on unbinned 0.5; binned pixel 1023 on unbinned 2046.5 (the last block of 2048).
    #[test]
    fn binning_by_hand() {
        let c = FieldCoords::centred(2048, 2048, 0.125).binned(2);
        let (x, y) = c.pixel_to_arcmin(0.0, 1023.0);
        assert!((x - (0.5 - 1023.5) * 0.125 / 60.0).abs() < 1e-15, "{x}");
        assert!((y - (2046.5 - 1023.5) * 0.125 / 60.0).abs() < 1e-15, "{y}");
        // The detector centre falls between binned pixels 511 and 512.
        let (bx, by) = c.arcmin_to_pixel(0.0, 0.0);
        assert!((bx - 511.5).abs() < 1e-12 && (by - 511.5).abs() < 1e-12);
        assert!((c.arcmin_per_px() - 0.25 / 60.0).abs() < 1e-18);
        // Binning composes.
        assert_eq!(FieldCoords::centred(10, 10, 1.0).binned(2).binned(3), FieldCoords::centred(10, 10, 1.0).binned(6));
    }

    /// An offset origin (a fitted optical axis 0.3' right of and 0.1' below the centre): the
    /// axis is (0, 0), and a pixel's position is its position from the centre minus the axis.
    #[test]
    fn offset_origin() {
        let d = FieldCoords::centred(FORS1.0, FORS1.1, FORS1.2);
        let a = d.about([0.3, -0.1]);
        // 0.3' = 90 px, -0.1' = -30 px.
        assert!((a.origin_px[0] - 1113.5).abs() < 1e-9 && (a.origin_px[1] - 993.5).abs() < 1e-9);
        let (x, y) = a.pixel_to_arcmin(1113.5, 993.5);
        assert!(x.abs() < 1e-12 && y.abs() < 1e-12);
        for (px, py) in [(0.0, 0.0), (2047.0, 13.0), (500.25, 1800.5)] {
            let (dx, dy) = d.pixel_to_arcmin(px, py);
            let (ax, ay) = a.pixel_to_arcmin(px, py);
            assert!((ax - (dx - 0.3)).abs() < 1e-12 && (ay - (dy + 0.1)).abs() < 1e-12);
        }
        // with_origin is the same thing given in pixels.
        assert_eq!(
            FieldCoords::with_origin([1113.5, 993.5], 0.2).pixel_to_arcmin(7.0, 9.0),
            a.pixel_to_arcmin(7.0, 9.0)
        );
    }

    #[test]
    fn round_trips() {
        for b in [1, 2, 3, 16, 30] {
            let c = FieldCoords::with_origin([700.25, 1200.0], 0.2).binned(b);
            for (x, y) in [(0.0, 0.0), (12.5, -3.0), (63.0, 17.25)] {
                let (ax, ay) = c.pixel_to_arcmin(x, y);
                let (px, py) = c.arcmin_to_pixel(ax, ay);
                assert!((px - x).abs() < 1e-9 && (py - y).abs() < 1e-9, "b {b}: ({x}, {y}) -> ({px}, {py})");
            }
        }
    }

    /// Unbinned conversions are the formula the workspace used before this type, to the bit:
    /// `(x - (n - 1)/2) scale/60` and `x 60/scale + (n - 1)/2`.
    #[test]
    fn unbinned_is_bit_identical_to_the_old_formula() {
        let c = FieldCoords::centred(2048, 1024, 0.2);
        let s = 0.2 / 60.0;
        for (x, y) in [(0.0, 0.0), (17.0, 1001.0), (1023.5, 511.5), (2047.0, 1023.0), (313.7, 77.1)] {
            assert_eq!(c.pixel_to_arcmin(x, y), ((x - 1023.5) * s, (y - 511.5) * s));
            let t = 60.0 / 0.2;
            assert_eq!(c.arcmin_to_pixel(x / 300.0, y / 300.0), ((x / 300.0) * t + 1023.5, (y / 300.0) * t + 511.5));
        }
    }
}
