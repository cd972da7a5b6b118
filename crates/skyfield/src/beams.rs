//! Where the ordinary and extraordinary images of each mask strip fall on the detector: the
//! one place this geometry lives (the simulator places light with it, the reduction extracts
//! with it).
//!
//! # Geometry
//! Coordinates of the *sky* are the detector pixels of the ordinary image ("o coordinates"):
//! the sky position seen by the o image of mask strip `k` at detector pixel `(x, y)` appears
//! in the extraordinary image at `(x, y + throw_px)` (for FORS, `strip_axis = "y"` and
//! `extraordinary_offset_sign = +1`; in general the offset is `e_start - o_start` along the
//! strip axis, taken from `instrument::Instrument::strips()`). Strip `k`'s o image covers rows
//! `[o_start, o_start + h)` of the detector, `h` = the throw in pixels, and those are also the
//! sky rows it sees: the mask hides every other throw-high band of the sky, and the band it
//! shows is imaged twice, at `[o_start, o_start + h)` (o) and `[e_start, e_start + h)` (e).
//! Detector pixels in neither image are dark (masked): only bias and read noise.
//! Field positions of a sky pixel are those of its o pixel (arcmin from the detector centre).

use instrument::{Instrument, Strip};

/// The strip layout of an instrument's detector.
#[derive(Debug, Clone, PartialEq)]
pub struct BeamGeometry {
    pub nx: usize,
    pub ny: usize,
    /// True when the strips are stacked along y (FORS), false along x.
    pub along_y: bool,
    pub strips: Vec<Strip>,
}

/// Which image a detector pixel belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelKind {
    Ordinary(usize),
    Extraordinary(usize),
    Masked,
}

impl BeamGeometry {
    /// The layout of `inst`.
    pub fn new(inst: &Instrument) -> Self {
        Self {
            nx: inst.detector.nx,
            ny: inst.detector.ny,
            along_y: inst.polarimetry.strip_axis == "y",
            strips: inst.strips(),
        }
    }

    /// The coordinate along the strip axis and across it.
    #[inline]
    fn along(&self, x: usize, y: usize) -> usize {
        if self.along_y {
            y
        } else {
            x
        }
    }

    /// Row-major index of detector pixel `(x, y)`.
    #[inline]
    pub fn index(&self, x: usize, y: usize) -> usize {
        y * self.nx + x
    }

    /// The strip whose o image sees sky pixel `(x, y)` (o coordinates), if the mask lets it
    /// through.
    #[inline]
    pub fn strip_of_sky(&self, x: usize, y: usize) -> Option<usize> {
        if x >= self.nx || y >= self.ny {
            return None;
        }
        let a = self.along(x, y);
        self.strips.iter().position(|s| a >= s.o_start && a < s.o_start + s.height)
    }

    /// Detector pixels `(o, e)` (row-major indices) that image sky pixel `(x, y)`, or `None`
    /// for masked sky.
    #[inline]
    pub fn beams_of_sky(&self, x: usize, y: usize) -> Option<(usize, usize)> {
        let k = self.strip_of_sky(x, y)?;
        let s = &self.strips[k];
        // e along-axis coordinate = o coordinate + (e_start - o_start); in range by construction.
        let shift = |a: usize| (a as isize + s.e_start as isize - s.o_start as isize) as usize;
        let (xe, ye) = if self.along_y { (x, shift(y)) } else { (shift(x), y) };
        Some((self.index(x, y), self.index(xe, ye)))
    }

    /// The e pixel `(x, y)` of sky pixel `(x, y)`, as coordinates, or `None` for masked sky.
    pub fn e_pixel_of_sky(&self, x: usize, y: usize) -> Option<(usize, usize)> {
        let (_, e) = self.beams_of_sky(x, y)?;
        Some((e % self.nx, e / self.nx))
    }

    /// What detector pixel `(x, y)` shows.
    pub fn kind(&self, x: usize, y: usize) -> PixelKind {
        let a = self.along(x, y);
        for s in &self.strips {
            if a >= s.o_start && a < s.o_start + s.height {
                return PixelKind::Ordinary(s.index);
            }
            if a >= s.e_start && a < s.e_start + s.height {
                return PixelKind::Extraordinary(s.index);
            }
        }
        PixelKind::Masked
    }

    /// Ranges of sky coordinates along the strip axis that the mask lets through, one per strip.
    pub fn sky_bands(&self) -> Vec<std::ops::Range<usize>> {
        self.strips.iter().map(|s| s.o_start..s.o_start + s.height).collect()
    }

    /// Every sky pixel the mask lets through, as `(x, y)`, in row-major order.
    pub fn sky_pixels(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        let (nx, ny) = (self.nx, self.ny);
        (0..ny).flat_map(move |y| (0..nx).map(move |x| (x, y))).filter(move |&(x, y)| self.strip_of_sky(x, y).is_some())
    }

    /// Number of sky pixels the mask lets through.
    pub fn n_sky_pixels(&self) -> usize {
        let across = if self.along_y { self.nx } else { self.ny };
        self.strips.iter().map(|s| s.height).sum::<usize>() * across
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fors1_e_image_is_throw_above_o_image() {
        let inst = Instrument::load("fors1").unwrap();
        let g = BeamGeometry::new(&inst);
        let h = inst.throw_px();
        // First strip: o rows [34, 144), e rows [144, 254).
        let (o, e) = g.beams_of_sky(100, 34).unwrap();
        assert_eq!(o, g.index(100, 34));
        assert_eq!(e, g.index(100, 34 + h));
        assert_eq!(g.kind(100, 34 + h), PixelKind::Extraordinary(0));
        assert_eq!(g.beams_of_sky(100, 34 + h), None, "the e band of the sky is behind the mask");
        assert_eq!(g.kind(5, 10), PixelKind::Masked);
        assert_eq!(g.sky_pixels().count(), g.n_sky_pixels());
        assert_eq!(g.n_sky_pixels(), 9 * h * 2048);
        // Every o and e pixel is distinct: no detector pixel serves two sky pixels.
        let mut seen = vec![false; g.nx * g.ny];
        for (x, y) in g.sky_pixels() {
            let (o, e) = g.beams_of_sky(x, y).unwrap();
            assert!(!seen[o] && !seen[e]);
            seen[o] = true;
            seen[e] = true;
        }
    }

    #[test]
    fn negative_offset_sign() {
        let text = include_str!("../../../instruments/fors1.toml")
            .replace("extraordinary_offset_sign = 1", "extraordinary_offset_sign = -1")
            .replace("first_strip_y_px = 34", "first_strip_y_px = 144")
            .replace("strip_count = 9", "strip_count = 8");
        let inst = Instrument::from_toml_str(&text, std::path::Path::new("neg.toml")).unwrap();
        let g = BeamGeometry::new(&inst);
        let s = g.strips[0];
        assert_eq!(s.e_start + s.height, s.o_start);
        let (o, e) = g.beams_of_sky(7, s.o_start + 3).unwrap();
        assert_eq!(o - e, s.height * g.nx);
    }
}
