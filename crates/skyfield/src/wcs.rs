//! The celestial WCS a reduction carries from its frames to its map: read from a frame's
//! header ([`CelestialWcs::read`], [`celestial_wcs_of`]), carried through the binning
//! ([`CelestialWcs::binned`]) and written as the map's `SKY` WCS; and the value type of a WCS
//! card ([`WcsValue`]) the maps' writer uses for it and for the bins' detector WCS.

use crate::fits::read_key_str;
use fitsio::FitsFile;
use std::path::Path;

/// The celestial WCS of a frame file's first image HDU (see [`CelestialWcs::read`]),
/// when that image is `nx x ny` px (the map's detector pixels); `Err(why)` when there is one
/// that cannot be carried.
pub fn celestial_wcs_of(path: &Path, nx: usize, ny: usize) -> Result<Option<CelestialWcs>, String> {
    match celestial_wcs_in(path)? {
        Some((_, (w, h))) if (w, h) != (nx, ny) => {
            Err(format!("the image is {w} x {h} px, the reduced frame {nx} x {ny} px"))
        }
        found => Ok(found.map(|(wcs, _)| wcs)),
    }
}

/// The celestial WCS of a file's first 2-D image HDU and that image's size `(nx, ny)`;
/// `Ok(None)` when the image has no celestial WCS (or the file no 2-D image), `Err(why)` when it
/// has one that cannot be carried ([`CelestialWcs::read`]).
pub fn celestial_wcs_in(path: &Path) -> Result<Option<(CelestialWcs, (usize, usize))>, String> {
    let mut f = FitsFile::open(path).map_err(|e| e.to_string())?;
    let n_hdu = f.iter().count();
    for i in 0..n_hdu {
        let h = f.hdu(i).map_err(|e| e.to_string())?;
        if let fitsio::hdu::HduInfo::ImageInfo { shape, .. } = &h.info {
            if shape.len() == 2 {
                let size = (shape[1], shape[0]);
                return Ok(CelestialWcs::read(&mut f, &h)?.map(|w| (w, size)));
            }
        }
    }
    Ok(None)
}

/// A WCS card's value (see `crate::maps::BinGeometry::wcs_cards`).
#[derive(Debug, Clone, PartialEq)]
pub enum WcsValue {
    Int(i64),
    Real(f64),
    Text(String),
}

/// A celestial FITS WCS without distortion terms: `CTYPEi` (e.g. `RA---TAN`, `DEC--TAN`),
/// `CRPIXi`, `CRVALi` (deg) and the `CD` matrix (deg/px), with `RADESYS`/`EQUINOX` when given.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CelestialWcs {
    pub ctype: [String; 2],
    pub crpix: [f64; 2],
    pub crval: [f64; 2],
    pub cd: [[f64; 2]; 2],
    pub radesys: Option<String>,
    pub equinox: Option<f64>,
}

/// Projections carried through the binning (linear in pixel coordinates before projection, so
/// binning only rescales CD and shifts CRPIX); anything else (SIP, TPV, ...) is not carried.
const PROJECTIONS: [&str; 10] = ["TAN", "SIN", "ARC", "ZEA", "STG", "CAR", "AIT", "MER", "CEA", "ZPN"];

impl CelestialWcs {
    /// The celestial WCS of header `hdu`: `Ok(None)` when it has none (no `CTYPE1` of the
    /// form `xxxx-PPP`), `Err(why)` when it has one this reader does not carry (distortion
    /// terms, an unknown projection, a missing value). The matrix is `CDi_j`, else
    /// `PCi_j * CDELTi`, else `CDELTi` with `CROTA2`.
    pub fn read(f: &mut FitsFile, hdu: &fitsio::hdu::FitsHdu) -> Result<Option<Self>, String> {
        let s = |f: &mut FitsFile, k: &str| read_key_str(f, hdu, k).ok().map(|v| v.trim().to_string());
        let (Some(c1), Some(c2)) = (s(f, "CTYPE1"), s(f, "CTYPE2")) else { return Ok(None) };
        let celestial = |c: &str| c.len() >= 8 && c.as_bytes()[4] == b'-';
        if !celestial(&c1) || !celestial(&c2) {
            return Ok(None);
        }
        for c in [&c1, &c2] {
            if c.len() != 8 || !PROJECTIONS.contains(&&c[5..8]) {
                return Err(format!("CTYPE '{c}' (distortion or projection not carried through binning)"));
            }
        }
        if s(f, "A_ORDER").is_some() || s(f, "PV1_1").is_some() || s(f, "PV2_1").is_some() {
            return Err("distortion terms (SIP or PV) are not carried through binning".into());
        }
        let r = |f: &mut FitsFile, k: &str| hdu.read_key::<f64>(f, k).ok();
        let need = |f: &mut FitsFile, k: &str| r(f, k).ok_or_else(|| format!("{k} missing"));
        let crpix = [need(f, "CRPIX1")?, need(f, "CRPIX2")?];
        let crval = [need(f, "CRVAL1")?, need(f, "CRVAL2")?];
        let cd = if let Some(c11) = r(f, "CD1_1") {
            [[c11, r(f, "CD1_2").unwrap_or(0.0)], [r(f, "CD2_1").unwrap_or(0.0), r(f, "CD2_2").unwrap_or(0.0)]]
        } else {
            let (d1, d2) = (need(f, "CDELT1")?, need(f, "CDELT2")?);
            if r(f, "PC1_1").is_some() || r(f, "PC2_2").is_some() {
                let pc = |f: &mut FitsFile, k: &str, d: f64| r(f, k).unwrap_or(d);
                [
                    [d1 * pc(f, "PC1_1", 1.0), d1 * pc(f, "PC1_2", 0.0)],
                    [d2 * pc(f, "PC2_1", 0.0), d2 * pc(f, "PC2_2", 1.0)],
                ]
            } else {
                let rho = r(f, "CROTA2").unwrap_or(0.0).to_radians();
                [[d1 * rho.cos(), -d2 * rho.sin()], [d1 * rho.sin(), d2 * rho.cos()]]
            }
        };
        if !(crpix.iter().chain(&crval).chain(cd.iter().flatten()).all(|v| v.is_finite())) {
            return Err("a WCS value is not finite".into());
        }
        Ok(Some(Self { ctype: [c1, c2], crpix, crval, cd, radesys: s(f, "RADESYS"), equinox: r(f, "EQUINOX") }))
    }

    /// The WCS of the detector frame carried to a map of bins of `bin_px` px whose first bin's
    /// corner is detector pixel `origin` (0-based x, y; `crate::maps::BinGeometry`'s
    /// `bin_px`, `origin_x`, `origin_y`): map pixel `p` (1-based) is detector pixel
    /// `X = x0 + 1 + b (p - 1)` (`x0` the 0-based centre of bin 0, `b` the bin side), so
    /// `X - CRPIX = b (p - CRPIX')` with `CRPIX' = 1 + (CRPIX - x0 - 1) / b`, and `CD' = b CD`:
    /// every bin centre gets the sky position of its detector pixel.
    pub fn binned(&self, bin_px: usize, origin: [usize; 2]) -> Self {
        let b = bin_px as f64;
        let x0 = [origin[0] as f64 + 0.5 * b - 0.5, origin[1] as f64 + 0.5 * b - 0.5];
        let mut w = self.clone();
        for ((p, x), row) in w.crpix.iter_mut().zip(x0).zip(w.cd.iter_mut()) {
            *p = 1.0 + (*p - x - 1.0) / b;
            for c in row {
                *c *= b;
            }
        }
        w
    }

    /// The sky position (RA, Dec in deg, RA in [0, 360)) of 0-based pixel `(x, y)` of the
    /// image this WCS belongs to, for the gnomonic projection (`TAN`, the projection of CCD
    /// frames); `None` for any other projection or a pixel the projection does not reach.
    /// Calabretta & Greisen 2002, A&A 395, 1077: intermediate world coordinates through the CD
    /// matrix (eq. 1, FITS pixels 1-based), native spherical coordinates of `TAN` (sec. 5.1.3:
    /// `phi = arg(-y, x)`, `theta = atan(180 / (pi R))`), then the turn to celestial
    /// coordinates with the reference point at the native pole's `theta_0 = 90` deg and
    /// `LONPOLE = 180` deg (eq. 2).
    ///
    /// ```
    /// use skyfield::wcs::CelestialWcs;
    /// let w = CelestialWcs { ctype: ["RA---TAN".into(), "DEC--TAN".into()], crpix: [11.0, 21.0],
    ///     crval: [150.0, -30.0], cd: [[-1e-4, 0.0], [0.0, 1e-4]], radesys: None, equinox: None };
    /// let (ra, dec) = w.sky_of_pixel(10.0, 20.0).unwrap(); // CRPIX, 1-based
    /// assert!((ra - 150.0).abs() < 1e-12 && (dec + 30.0).abs() < 1e-12);
    /// ```
    pub fn sky_of_pixel(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        if !(self.ctype[0].ends_with("-TAN") && self.ctype[1].ends_with("-TAN")) {
            return None;
        }
        let (lat_first, lon, lat) = match (&self.ctype[0][..4], &self.ctype[1][..4]) {
            ("RA--", "DEC-") => (false, 0, 1),
            ("DEC-", "RA--") => (true, 1, 0),
            _ => return None,
        };
        let (dx, dy) = (x + 1.0 - self.crpix[0], y + 1.0 - self.crpix[1]);
        let iw = [self.cd[0][0] * dx + self.cd[0][1] * dy, self.cd[1][0] * dx + self.cd[1][1] * dy];
        let (xi, eta) = if lat_first { (iw[1], iw[0]) } else { (iw[0], iw[1]) };
        let (xi, eta) = (xi.to_radians(), eta.to_radians());
        let r = xi.hypot(eta);
        let phi = xi.atan2(-eta);
        let theta = if r == 0.0 { std::f64::consts::FRAC_PI_2 } else { (1.0 / r).atan() };
        let (a0, d0) = (self.crval[lon].to_radians(), self.crval[lat].to_radians());
        // LONPOLE = 180 deg: phi - phi_p = phi - pi.
        let dphi = phi - std::f64::consts::PI;
        // The direction's components: cos(dec) cos(ra - a0), cos(dec) sin(ra - a0), sin(dec);
        // Dec by atan2 of them (an arcsine loses digits near the poles).
        let cx = theta.sin() * d0.cos() - theta.cos() * d0.sin() * dphi.cos();
        let cy = -theta.cos() * dphi.sin();
        let sz = theta.sin() * d0.sin() + theta.cos() * d0.cos() * dphi.cos();
        let ra = a0 + cy.atan2(cx);
        let dec = sz.atan2(cx.hypot(cy));
        let out = (ra.to_degrees().rem_euclid(360.0), dec.to_degrees());
        (out.0.is_finite() && out.1.is_finite()).then_some(out)
    }

    /// The position angle on the sky (deg, north through east) of the image's +y axis, at the
    /// reference point: the direction of the CD matrix's second column in the intermediate
    /// (east, north) coordinates (Calabretta & Greisen 2002, A&A 395, 1077, eq. 1). `Err(why)`
    /// when the axes are not RA and Dec, or when the image is mirrored against the sky (east
    /// counter-clockwise from north when seen with +y up: `det CD > 0` for RA first), in which
    /// a polarization angle counted from x toward y runs the other way round on the sky.
    ///
    /// ```
    /// use skyfield::wcs::CelestialWcs;
    /// // North up, east left, then the image turned: the CROTA2 form of the same matrix.
    /// let rho = 30f64.to_radians();
    /// let s = 1e-4;
    /// let w = CelestialWcs { ctype: ["RA---TAN".into(), "DEC--TAN".into()], crpix: [1.0, 1.0],
    ///     crval: [150.0, -30.0], cd: [[-s * rho.cos(), -s * rho.sin()], [-s * rho.sin(), s * rho.cos()]],
    ///     radesys: None, equinox: None };
    /// assert!((w.y_axis_position_angle_deg().unwrap() + 30.0).abs() < 1e-12);
    /// ```
    pub fn y_axis_position_angle_deg(&self) -> Result<f64, String> {
        let (ra_row, dec_row) = match (&self.ctype[0][..4], &self.ctype[1][..4]) {
            ("RA--", "DEC-") => (0, 1),
            ("DEC-", "RA--") => (1, 0),
            _ => return Err(format!("CTYPE '{}', '{}' are not RA and Dec", self.ctype[0], self.ctype[1])),
        };
        // Pixel axis x then y: (east, north) of each.
        let east = [self.cd[ra_row][0], self.cd[ra_row][1]];
        let north = [self.cd[dec_row][0], self.cd[dec_row][1]];
        let det = east[0] * north[1] - east[1] * north[0];
        if det.is_nan() || det >= 0.0 {
            return Err(format!(
                "the image is mirrored against the sky (CD matrix of determinant {det:e} in east, north): a \
                 polarization angle counted from x toward y would turn west of north"
            ));
        }
        Ok(east[1].atan2(north[1]).to_degrees())
    }

    pub(crate) fn cards(&self) -> Vec<(String, WcsValue, &'static str)> {
        use WcsValue::{Real, Text};
        let mut v = vec![
            ("WCSNAME".to_string(), Text("SKY".into()), "the frames' celestial WCS, binned"),
            ("CTYPE1".into(), Text(self.ctype[0].clone()), ""),
            ("CTYPE2".into(), Text(self.ctype[1].clone()), ""),
            ("CUNIT1".into(), Text("deg".into()), ""),
            ("CUNIT2".into(), Text("deg".into()), ""),
            ("CRPIX1".into(), Real(self.crpix[0]), "map pixel of CRVAL"),
            ("CRPIX2".into(), Real(self.crpix[1]), "map pixel of CRVAL"),
            ("CRVAL1".into(), Real(self.crval[0]), "[deg]"),
            ("CRVAL2".into(), Real(self.crval[1]), "[deg]"),
            ("CD1_1".into(), Real(self.cd[0][0]), "[deg per map pixel]"),
            ("CD1_2".into(), Real(self.cd[0][1]), "[deg per map pixel]"),
            ("CD2_1".into(), Real(self.cd[1][0]), "[deg per map pixel]"),
            ("CD2_2".into(), Real(self.cd[1][1]), "[deg per map pixel]"),
        ];
        if let Some(r) = &self.radesys {
            v.push(("RADESYS".into(), Text(r.clone()), ""));
        }
        if let Some(e) = self.equinox {
            v.push(("EQUINOX".into(), Real(e), ""));
        }
        v
    }
}
