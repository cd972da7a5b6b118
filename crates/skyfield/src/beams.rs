//! Where the ordinary and extraordinary images of a sky point fall on the detector: the one
//! place this geometry lives (the simulator places light with it, the reduction and the
//! photometry extract with it). The instrument file chooses the layout
//! (`[polarimetry] layout`):
//!
//! - **Strips** (FORS, EFOSC2, ALFOSC): a focal-plane mask lets through strips of the sky, each
//!   imaged twice, side by side along the strip axis. Coordinates of the *sky* are the detector
//!   pixels of the ordinary image ("o coordinates"): the sky point seen by the o image of strip
//!   `k` at detector pixel `(x, y)` appears in the extraordinary image at `(x, y + throw)` (FORS:
//!   `strip_axis = "y"`, `extraordinary_offset_sign = +1`; the throw may vary slowly across the
//!   field, `throw_terms`). Strip `k`'s o image covers the whole pixel rows
//!   `[o_start, o_start + h)` ([`instrument::Instrument::strips`]); the band it shows is imaged
//!   again at `[e_start, e_start + h)` (e), or, with `throw_terms`, on the lines those o lines
//!   reach through the varying throw. Detector pixels in neither image are dark (masked).
//! - **Maskless** (calcite or Savart plate, no mask): every sky point is imaged twice, the e
//!   image at a fixed 2-D offset `(dx, dy)` from the o image, and every detector pixel receives
//!   o light from one sky point and e light from another. The sky of the two beams overlaps,
//!   so an extended sky cannot be split into o and e ([`BeamGeometry::require_separable_sky`]
//!   refuses it with the reason); point sources work ([`BeamGeometry::e_position`]).
//! - **Two cameras** (a polarizing beam splitter, MOPTOP): the o beam on one camera, the e
//!   beam on another, the two placed side by side in one detector frame by the instrument's
//!   `[format]` chips. The sky's coordinates are the o camera's pixels; a point's e image is
//!   where the camera transform puts it on the e camera, turned back into the e chip's pixels as
//!   read ([`CameraMap`]). The transform is the instrument file's, or measured from the stars
//!   of the frames (`skyfield::photometry::layout_for`). A per-pixel map resamples the e
//!   camera onto the o camera's pixels through the transform ([`CameraMap::e_value`],
//!   `skyfield::reduce`).
//!
//! Field positions of a sky point are those of its o pixel (arcmin from the detector centre).

use instrument::{Instrument, Layout, OffsetTerm, Orientation, Strip};

/// Where the two cameras of a [`Layout::TwoCameras`] instrument sit in the detector frame and
/// how a point of the o camera maps onto the e camera.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraMap {
    /// The o chip's first pixel in the detector frame and its size `(x, y)` (px).
    pub o_origin: (usize, usize),
    pub o_size: (usize, usize),
    /// The e chip's first pixel and its size as read.
    pub e_origin: (usize, usize),
    pub e_size: (usize, usize),
    /// How the e chip's image is turned to show the sky as the o camera does.
    pub e_orientation: Orientation,
    /// o camera px `(x, y)` -> turned e camera px: `(a x + b y + c, d x + e y + f)`; `None`
    /// while unknown (to be measured from stars).
    pub transform: Option<[f64; 6]>,
    /// When the transform was measured: its RMS residual (px) and the star pairs it rests on.
    pub measured: Option<(f64, usize)>,
}

impl CameraMap {
    /// The cameras of `inst`, `None` for another layout (or a file without `[polarimetry.cameras]`).
    pub fn of(inst: &Instrument) -> Option<Self> {
        let c = inst.polarimetry.cameras.as_ref()?;
        let chip = |n: &str| inst.format.chips.iter().find(|ch| ch.name == n);
        let (o, e) = (chip(&c.o_chip)?, chip(&c.e_chip)?);
        Some(Self {
            o_origin: (o.origin_px[0], o.origin_px[1]),
            o_size: (o.size_px[0], o.size_px[1]),
            e_origin: (e.origin_px[0], e.origin_px[1]),
            e_size: (e.size_px[0], e.size_px[1]),
            e_orientation: c.e_orientation,
            transform: c.transform,
            measured: None,
        })
    }

    /// Whether detector pixel `(x, y)` (real) lies on the o chip, and its local coordinates.
    fn o_local(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let (u, v) = (x - self.o_origin.0 as f64, y - self.o_origin.1 as f64);
        (u >= -0.5 && v >= -0.5 && u < self.o_size.0 as f64 - 0.5 && v < self.o_size.1 as f64 - 0.5).then_some((u, v))
    }

    /// The detector position of the e image of the o camera's local point `(u, v)`, given the
    /// transform `t`: through `t` onto the turned e camera, turned back into the e chip's
    /// pixels as read, placed at the e chip's origin.
    pub fn e_of_local(&self, t: &[f64; 6], u: f64, v: f64) -> (f64, f64) {
        let (tu, tv) = (t[0] * u + t[1] * v + t[2], t[3] * u + t[4] * v + t[5]);
        let (rx, ry) = self.e_orientation.inverse().apply(tu, tv, self.o_size.0, self.o_size.1);
        (self.e_origin.0 as f64 + rx, self.e_origin.1 as f64 + ry)
    }

    /// The e camera's value at the e image of the o camera's local pixel `(u, v)` (the
    /// transform `t`, [`Self::e_of_local`]), by bilinear interpolation between the four e chip
    /// pixels around it in the detector frame `img` (`nx` px wide): NaN when one of the four is
    /// off the e chip, not finite, or at or above `saturation` (a saturated pixel would
    /// otherwise pass into its neighbours' values below the level, unmasked). Bilinear
    /// interpolation keeps a uniform or linear sky as it is and the mean of a bin; it mixes
    /// neighbouring pixels, so their noise is correlated (see `skyfield::reduce` on the
    /// errors of the bins).
    pub fn e_value(&self, img: &[f64], nx: usize, t: &[f64; 6], u: usize, v: usize, saturation: f64) -> f64 {
        let (xe, ye) = self.e_of_local(t, u as f64, v as f64);
        let (x0, y0) = (xe.floor(), ye.floor());
        let (fx, fy) = (xe - x0, ye - y0);
        if !(x0 >= 0.0 && y0 >= 0.0) {
            return f64::NAN;
        }
        let (x0, y0) = (x0 as usize, y0 as usize);
        let mut acc = 0.0;
        for (dx, dy, w) in
            [(0, 0, (1.0 - fx) * (1.0 - fy)), (1, 0, fx * (1.0 - fy)), (0, 1, (1.0 - fx) * fy), (1, 1, fx * fy)]
        {
            let (x, y) = (x0 + dx, y0 + dy);
            if x >= nx || self.kind(x, y) != PixelKind::Extraordinary(0) {
                return f64::NAN;
            }
            let z = img.get(y * nx + x).copied().unwrap_or(f64::NAN);
            if !(z.is_finite() && z < saturation) {
                return f64::NAN;
            }
            acc += w * z;
        }
        acc
    }

    /// The e chip's detector pixel `(x, y)` (real) in the turned e camera's coordinates (the
    /// frame the transform maps into), for measuring the transform from stars.
    pub fn turned_e(&self, x: f64, y: f64) -> (f64, f64) {
        let (rx, ry) = (x - self.e_origin.0 as f64, y - self.e_origin.1 as f64);
        self.e_orientation.apply(rx, ry, self.e_size.0, self.e_size.1)
    }

    fn kind(&self, x: usize, y: usize) -> PixelKind {
        let inside = |(x0, y0): (usize, usize), (w, h): (usize, usize)| x >= x0 && y >= y0 && x < x0 + w && y < y0 + h;
        if inside(self.o_origin, self.o_size) {
            PixelKind::Ordinary(0)
        } else if inside(self.e_origin, self.e_size) {
            PixelKind::Extraordinary(0)
        } else {
            PixelKind::Masked
        }
    }
}

/// The beam layout of an instrument's detector.
#[derive(Debug, Clone, PartialEq)]
pub struct BeamGeometry {
    pub nx: usize,
    pub ny: usize,
    pub layout: Layout,
    /// Strips: true when the strips are stacked along y (FORS), false along x.
    pub along_y: bool,
    /// Strips: the whole pixel rows (along the strip axis) of every strip's o and e image.
    pub strips: Vec<Strip>,
    /// Strips: the signed o/e offset along the strip axis (px, real) before its variation.
    throw: f64,
    /// Strips: the variation of the throw across the field (`OffsetTerm::sum`).
    terms: Vec<OffsetTerm>,
    /// Maskless: the e image's offset from the o image (px), when known.
    pub oe_offset: Option<(f64, f64)>,
    /// Two cameras: where they are and how they map.
    pub cameras: Option<CameraMap>,
    name: String,
    /// Strips: the kind of every detector line across the strip axis, indexed by the
    /// coordinate along it (what [`BeamGeometry::kind`] answers). A table, because the
    /// photometry asks for every pixel of every aperture, annulus and centroid window: the
    /// loop over the strips was the largest part of a 500-star catalog's time.
    kinds: Vec<PixelKind>,
}

/// Which image a detector pixel belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelKind {
    Ordinary(usize),
    Extraordinary(usize),
    Masked,
    /// Maskless layouts: the pixel receives the o light of one sky point and the e light of
    /// another.
    Both,
}

impl BeamGeometry {
    /// The layout of `inst`.
    pub fn new(inst: &Instrument) -> Self {
        let p = &inst.polarimetry;
        let (nx, ny) = (inst.detector.nx, inst.detector.ny);
        let strips = inst.strips();
        let along_y = p.strip_axis == "y";
        let mut g = Self {
            nx,
            ny,
            layout: p.layout,
            along_y,
            strips,
            throw: p.extraordinary_offset_sign as f64 * inst.throw_px_exact(),
            terms: p.throw_terms.clone(),
            oe_offset: p.oe_offset_px.map(|[dx, dy]| (dx, dy)),
            cameras: if p.layout == Layout::TwoCameras { CameraMap::of(inst) } else { None },
            name: inst.name.clone(),
            kinds: vec![],
        };
        if g.layout == Layout::Strips {
            g.kinds = g.line_kinds(&inst.e_line_ranges());
        }
        g
    }

    /// The kind of every detector line across the strip axis: each strip's o lines, then the
    /// lines its e image covers (`e_ranges`, [`Instrument::e_line_ranges`]: with
    /// `throw_terms`, the o lines moved by the varying throw; FORS2's e images sit 2.6 to 7.9
    /// rows below the nominal e strip, and taken as masked, their stars' e images went
    /// undetected, flagged, or cut by the simulator).
    fn line_kinds(&self, e_ranges: &[(i64, i64)]) -> Vec<PixelKind> {
        let n = if self.along_y { self.ny } else { self.nx };
        (0..n)
            .map(|a| {
                for (s, &(elo, ehi)) in self.strips.iter().zip(e_ranges) {
                    if a >= s.o_start && a < s.o_start + s.height {
                        return PixelKind::Ordinary(s.index);
                    }
                    if (elo..=ehi).contains(&(a as i64)) {
                        return PixelKind::Extraordinary(s.index);
                    }
                }
                PixelKind::Masked
            })
            .collect()
    }

    /// The same layout with the maskless o/e offset set (measured from the frames, say).
    pub fn with_oe_offset(mut self, dx: f64, dy: f64) -> Self {
        self.oe_offset = Some((dx, dy));
        self
    }

    /// The same layout with the camera transform set (measured from the frames' stars, with
    /// its RMS residual in px and the number of star pairs).
    pub fn with_camera_transform(mut self, t: [f64; 6], rms_px: f64, pairs: usize) -> Self {
        if let Some(c) = self.cameras.as_mut() {
            c.transform = Some(t);
            c.measured = Some((rms_px, pairs));
        }
        self
    }

    /// `Ok` when an extended sky can be split into its o and e images (strip layouts);
    /// otherwise the reason, for an error message.
    pub fn require_separable_sky(&self) -> Result<(), String> {
        match self.layout {
            Layout::Strips => Ok(()),
            Layout::TwoCameras => Err(format!(
                "instrument {} has two cameras: its sky's o and e images are on two detectors, not in one frame's pixels; a Stokes map resamples the e camera onto the o camera's pixels (reduce), a per-pixel view of the frames as read is not built",
                self.name
            )),
            Layout::Maskless => Err(format!(
                "instrument {} has a maskless layout: the o and e images of the sky overlap on the detector, so an extended sky (a sky-field calibration, a Stokes map) cannot be separated into its two beams; point sources can: use photometry or validate",
                self.name
            )),
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

    /// True when the o/e shift of a strip layout is the same whole number of pixels everywhere.
    #[inline]
    pub fn uniform_shift(&self) -> bool {
        self.terms.is_empty()
    }

    /// True when the o/e shift of a strip layout is the same along every detector line across
    /// the strip axis (rows, for strips stacked along y): the throw's variation depends on the
    /// position along the strip axis only (FORS2's published quadratic in y). The reduction
    /// then plans a row as one run instead of pixel by pixel.
    #[inline]
    pub fn shift_constant_across(&self) -> bool {
        self.layout == Layout::Strips && self.terms.iter().all(|t| if self.along_y { t.i == 0 } else { t.j == 0 })
    }

    /// The offset `(dx, dy)` (px) from the o image of the sky point seen at o position `(x, y)`
    /// to its e image: along the strip axis the throw plus its variation (strips), or the fixed
    /// 2-D vector (maskless; `None` while unknown).
    pub fn e_offset(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        match self.layout {
            Layout::Maskless => self.oe_offset,
            Layout::TwoCameras => {
                let c = self.cameras.as_ref()?;
                let (u, v) = c.o_local(x, y)?;
                let (xe, ye) = c.e_of_local(c.transform.as_ref()?, u, v);
                Some((xe - x, ye - y))
            }
            Layout::Strips => {
                // (`OffsetTerm::sum` is 0 without terms.)
                let d = self.throw + OffsetTerm::sum(&self.terms, self.nx, self.ny, x, y);
                Some(if self.along_y { (0.0, d) } else { (d, 0.0) })
            }
        }
    }

    /// Where the e image of the sky point whose o image is at `(x, y)` (px, real) falls, or
    /// `None` when the mask hides that sky point, the offset is unknown, or the e image falls
    /// off the detector.
    pub fn e_position(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        if self.layout == Layout::Strips {
            let (xi, yi) = (x.round(), y.round());
            if !(xi >= 0.0 && yi >= 0.0) || self.strip_of_sky(xi as usize, yi as usize).is_none() {
                return None;
            }
        }
        let (dx, dy) = self.e_offset(x, y)?;
        let (xe, ye) = (x + dx, y + dy);
        let on = xe >= -0.5 && ye >= -0.5 && xe < self.nx as f64 - 0.5 && ye < self.ny as f64 - 0.5;
        // Two cameras: the e image must fall on the e camera, not beside it.
        let on_e = self.layout != Layout::TwoCameras
            || (on && self.kind(xe.round() as usize, ye.round() as usize) == PixelKind::Extraordinary(0));
        (on && on_e).then_some((xe, ye))
    }

    /// Row-major index of detector pixel `(x, y)`.
    #[inline]
    pub fn index(&self, x: usize, y: usize) -> usize {
        y * self.nx + x
    }

    /// The strip whose o image sees sky pixel `(x, y)` (o coordinates), if the mask lets it
    /// through (always `None` for a maskless layout, whose sky has no strips).
    #[inline]
    pub fn strip_of_sky(&self, x: usize, y: usize) -> Option<usize> {
        if x >= self.nx || y >= self.ny {
            return None;
        }
        if self.layout == Layout::TwoCameras {
            // The o camera's pixels are the sky's, one band (index 0).
            return (self.kind(x, y) == PixelKind::Ordinary(0)).then_some(0);
        }
        let a = self.along(x, y);
        self.strips.iter().position(|s| a >= s.o_start && a < s.o_start + s.height)
    }

    /// Detector pixels `(o, e)` (row-major indices) that image sky pixel `(x, y)` of a strip
    /// layout, the e pixel the nearest to the e image, or `None` for masked sky.
    #[inline]
    pub fn beams_of_sky(&self, x: usize, y: usize) -> Option<(usize, usize)> {
        if self.layout != Layout::Strips {
            return None;
        }
        let k = self.strip_of_sky(x, y)?;
        let s = &self.strips[k];
        let shift = if self.terms.is_empty() {
            // e along-axis coordinate = o coordinate + (e_start - o_start); in range by
            // construction.
            s.e_start as isize - s.o_start as isize
        } else {
            let (dx, dy) = self.e_offset(x as f64, y as f64)?;
            (if self.along_y { dy } else { dx }).round() as isize
        };
        let sh = |a: usize, n: usize| {
            let v = a as isize + shift;
            (v >= 0 && (v as usize) < n).then_some(v as usize)
        };
        let (xe, ye) = if self.along_y { (x, sh(y, self.ny)?) } else { (sh(x, self.nx)?, y) };
        Some((self.index(x, y), self.index(xe, ye)))
    }

    /// The e pixel `(x, y)` of sky pixel `(x, y)`, as coordinates, or `None` for masked sky.
    pub fn e_pixel_of_sky(&self, x: usize, y: usize) -> Option<(usize, usize)> {
        let (_, e) = self.beams_of_sky(x, y)?;
        Some((e % self.nx, e / self.nx))
    }

    /// What detector pixel `(x, y)` shows.
    #[inline]
    pub fn kind(&self, x: usize, y: usize) -> PixelKind {
        if self.layout == Layout::Maskless {
            return PixelKind::Both;
        }
        if let Some(c) = &self.cameras {
            return c.kind(x, y);
        }
        self.kinds.get(self.along(x, y)).copied().unwrap_or(PixelKind::Masked)
    }

    /// What every pixel of detector row `y` shows, when the whole row shows the same
    /// (maskless layouts; strips stacked along y); `None` when it varies along the row.
    #[inline]
    pub fn row_kind(&self, y: usize) -> Option<PixelKind> {
        match self.layout {
            Layout::Maskless => Some(PixelKind::Both),
            Layout::Strips if self.along_y => Some(self.kind(0, y)),
            Layout::Strips | Layout::TwoCameras => None,
        }
    }

    /// Ranges of sky coordinates along the strip axis that the mask lets through, one per strip.
    pub fn sky_bands(&self) -> Vec<std::ops::Range<usize>> {
        self.strips.iter().map(|s| s.o_start..s.o_start + s.height).collect()
    }

    /// Every sky pixel the mask lets through, as `(x, y)`, in row-major order (none for a
    /// maskless layout: its sky is not separable into pixels of one beam).
    pub fn sky_pixels(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        let (nx, ny) = (self.nx, self.ny);
        (0..ny).flat_map(move |y| (0..nx).map(move |x| (x, y))).filter(move |&(x, y)| self.beams_of_sky(x, y).is_some())
    }

    /// Number of sky pixels the mask lets through.
    pub fn n_sky_pixels(&self) -> usize {
        if self.terms.is_empty() {
            let across = if self.along_y { self.nx } else { self.ny };
            self.strips.iter().map(|s| s.height).sum::<usize>() * across
        } else {
            self.sky_pixels().count()
        }
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
