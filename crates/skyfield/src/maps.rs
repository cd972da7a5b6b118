//! The Stokes map: binned `Q/I`, `U/I`, `P`, `chi` over the field with their errors and the
//! number of pixels each bin kept, and its FITS format.
//!
//! # Bin geometry
//! Bins are square, `bin_px` detector pixels on a side, on a regular grid whose bin `(0, 0)`
//! starts at 0-based pixel `(origin_x, origin_y)` of the *ordinary-image* (= sky) coordinates
//! of [`crate::beams`]; bin `(i, j)` covers pixels `[origin_x + i bin_px, origin_x + (i+1)
//! bin_px)` in x and likewise in y. Arrays are row-major, index `j * nx + i`. Bins that fall on
//! masked sky (between strips) have no pixels and are invalid; bins that straddle a strip edge
//! keep only the pixels the mask lets through (see `n_pixels`).
//!
//! # FITS layout (format version 1)
//! Primary HDU: no data; header keywords `MAPVERS`, `INSTRUME`, `FILTER`, `NHWP`, `HWPANG1`..
//! `HWPANGn` (deg), `BINSIZE` (px), `BINORGX`, `BINORGY` (0-based px), `NBINX`, `NBINY`,
//! `PIXSCALE` (arcsec/px), `DETNX`, `DETNY` (px). Image extensions (each `NBINY x NBINX`,
//! float64 unless noted): `Q`, `U` (normalized, fractions), `SIGMA_Q`, `SIGMA_U`, `COV_QU` (from
//! the scatter of the kept pixels), `SIGQ_PHOT`, `SIGU_PHOT` (photon + read noise propagated),
//! `P` (fraction), `CHI` (deg, [0, 180)), `COVERAGE` (int32, pixels kept), `INTENSITY` (mean
//! `f_O + f_E` per exposure, e-/px), `INT_SNR` (per-pixel SNR of the combined intensity image),
//! `VALID` (int32, 1 = usable). Invalid bins hold NaN in the float images. Every image carries
//! `BUNIT` (`''` = dimensionless for the fractions, `deg`, `electron/pix`, `pix`) and two linear
//! WCSs of its bins ([`BinGeometry::wcs_cards`]): detector pixels (primary, `WCSNAME =
//! 'DETECTOR'`) and arcmin from the detector centre (alternate `A`, `WCSNAMEA = 'FIELD'`). When
//! the frames have a celestial WCS it is carried through the binning ([`CelestialWcs::binned`])
//! and becomes the primary WCS (`WCSNAME = 'SKY'`), the detector grid moving to alternate `D`.
//! The primary header carries the run's provenance ([`crate::provenance`]), and, when the
//! frames' headers gave them, the exposures' parallactic angle `PARANG1` (the first frame's
//! start), `PARANG2` (the last frame's end) and rotator angle `ROTANG` (deg, the instrument's
//! sense), and each exposure's HWP angle and parallactic angles at its start and end
//! (`NEXPTRK` exposures, `XHWPk`, `XPASk`, `XPAEk`, deg): optional keywords, within format
//! version 1 (a reader that ignores them corrects over the whole set's track). `HWPZERO` (deg,
//! optional too) is the HWP zero angle of the instrument's filter when the reduction knew it:
//! `Q`, `U` and `CHI` of a map from `instpol reduce` do not carry it (they are at the plate),
//! and a correction that must bring them into the sky frame takes it from there (a name in
//! `INSTRUME` may be a custom instrument file's, whose zero angle no lookup by name can find).
//! `SKYPA` (deg, optional) is the instrument's position angle on the sky of the map's exposures,
//! when its instrument says where to read it (`[polarimetry.sky_angle]`): an uncorrected map's
//! `Q`, `U` and `CHI` are at the plate all the same, and a corrected map's are turned by it onto
//! the sky, north through east (the celestial frame).
//! A corrected map also carries the correction's record ([`CorrectionStamp`]).
//!
//! A circular-polarization map ([`CircularMap`], frames through a quarter-wave plate) has the
//! same primary header with `STOKES = 'V'` and `QWPZERO` (deg, the plate's zero angle its
//! demodulation added to the plate angles, which `NHWP`, `HWPANGk` then hold), and the image
//! extensions `V` (`V/I`, IAU sign), `SIGMA_V` (from the scatter of the kept pixels),
//! `SIGV_PHOT` (photon + read noise), `INTENSITY`, `INT_SNR`, `COVERAGE`, `VALID`, with the same
//! units and WCSs. A map without `STOKES` (or with `STOKES = 'QU'`) is a linear one; the one
//! Stokes-map reader ([`StokesMap::read_fits`], which fitting, calibrating, correcting and the
//! Python package use) refuses a `V` map, as it holds no `Q/I`, `U/I`.

use crate::wcs::{CelestialWcs, WcsValue};
use crate::{fits_err, Error};
use fitsio::images::{ImageDescription, ImageType};
use fitsio::FitsFile;
use std::path::Path;

/// Current version of the Stokes-map FITS format.
pub const MAP_FORMAT_VERSION: i32 = 1;

/// Where the bins of a map lie on the detector.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BinGeometry {
    /// Bin side (px).
    pub bin_px: usize,
    /// 0-based pixel (sky / ordinary-image coordinates) where bin (0, 0) starts.
    pub origin_x: usize,
    pub origin_y: usize,
    /// Number of bins along x and y.
    pub nx: usize,
    pub ny: usize,
    /// Detector pixel scale (arcsec/px).
    pub pixel_scale_arcsec: f64,
    /// Detector size (px).
    pub detector_nx: usize,
    pub detector_ny: usize,
}

impl BinGeometry {
    /// The grid of `bin_px` bins that covers a detector from `(origin_x, origin_y)`.
    pub fn covering(
        bin_px: usize,
        origin_x: usize,
        origin_y: usize,
        detector_nx: usize,
        detector_ny: usize,
        pixel_scale_arcsec: f64,
    ) -> Self {
        let b = bin_px.max(1);
        Self {
            bin_px: b,
            origin_x,
            origin_y,
            nx: detector_nx.saturating_sub(origin_x).div_ceil(b),
            ny: detector_ny.saturating_sub(origin_y).div_ceil(b),
            pixel_scale_arcsec,
            detector_nx,
            detector_ny,
        }
    }

    /// Number of bins.
    pub fn len(&self) -> usize {
        self.nx * self.ny
    }

    /// True for an empty grid.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The bin holding 0-based pixel `(x, y)`, if any.
    pub fn bin_of(&self, x: usize, y: usize) -> Option<usize> {
        if x < self.origin_x || y < self.origin_y {
            return None;
        }
        let (i, j) = ((x - self.origin_x) / self.bin_px, (y - self.origin_y) / self.bin_px);
        (i < self.nx && j < self.ny).then_some(j * self.nx + i)
    }

    /// Geometric centre of bin `(i, j)` in 0-based pixels (a bin cut by the detector edge is
    /// centred on its part inside the detector).
    pub fn centre_px(&self, i: usize, j: usize) -> (f64, f64) {
        let x0 = (self.origin_x + i * self.bin_px) as f64;
        let y0 = (self.origin_y + j * self.bin_px) as f64;
        let x1 = ((self.origin_x + (i + 1) * self.bin_px).min(self.detector_nx)) as f64;
        let y1 = ((self.origin_y + (j + 1) * self.bin_px).min(self.detector_ny)) as f64;
        (0.5 * (x0 + x1) - 0.5, 0.5 * (y0 + y1) - 0.5)
    }

    /// Centre of bin `(i, j)` in arcmin from the detector centre (the field coordinates of
    /// `docs/architecture.md`, Conventions; the same formula as
    /// `instrument::Instrument::pixel_to_arcmin`).
    pub fn centre_arcmin(&self, i: usize, j: usize) -> (f64, f64) {
        let (x, y) = self.centre_px(i, j);
        self.px_to_arcmin(x, y)
    }

    /// 0-based pixel to arcmin from the detector centre.
    pub fn px_to_arcmin(&self, x: f64, y: f64) -> (f64, f64) {
        self.field_coords().pixel_to_arcmin(x, y)
    }

    /// The world coordinates of the binned map's pixels, as FITS WCS cards `(key, value,
    /// comment)`: the primary WCS (`WCSNAME = 'DETECTOR'`) gives the detector pixel (1-based, as
    /// FITS counts) at each bin's nominal centre, `CRVAL + CDELT (p - CRPIX)` with `CDELT` the
    /// bin side; the alternate WCS `A` (`WCSNAMEA = 'FIELD'`) gives arcmin from the detector
    /// centre (`docs/architecture.md`, Conventions). A bin cut by the detector edge keeps its
    /// nominal centre here; [`Self::centre_px`] gives the centre of its part inside the detector.
    pub fn wcs_cards(&self) -> Vec<(String, WcsValue, &'static str)> {
        self.wcs_cards_keyed("")
    }

    /// [`Self::wcs_cards`] with the detector WCS under alternate key `det` ("" = primary; the
    /// map writer uses "D" when a celestial WCS takes the primary place).
    pub fn wcs_cards_keyed(&self, det: &str) -> Vec<(String, WcsValue, &'static str)> {
        use WcsValue::{Real, Text};
        let b = self.bin_px as f64;
        // Nominal centre of bin (0, 0), 0-based: origin + b/2 - 1/2.
        let (x0, y0) = (self.origin_x as f64 + 0.5 * b - 0.5, self.origin_y as f64 + 0.5 * b - 0.5);
        let (ax0, ay0) = self.px_to_arcmin(x0, y0);
        let step = b * self.pixel_scale_arcsec / 60.0;
        let v = vec![
            ("WCSAXES".to_string(), WcsValue::Int(2), "number of WCS axes"),
            (format!("WCSNAME{det}"), Text("DETECTOR".into()), "detector pixels (1-based) of the bin centres"),
            (format!("CTYPE1{det}"), Text("DETX".into()), "detector column"),
            (format!("CTYPE2{det}"), Text("DETY".into()), "detector row"),
            (format!("CRPIX1{det}"), Real(1.0), "map pixel of bin (0, 0)"),
            (format!("CRPIX2{det}"), Real(1.0), "map pixel of bin (0, 0)"),
            (format!("CRVAL1{det}"), Real(x0 + 1.0), "detector x (1-based) of the centre of bin (0, 0)"),
            (format!("CRVAL2{det}"), Real(y0 + 1.0), "detector y (1-based) of the centre of bin (0, 0)"),
            (format!("CDELT1{det}"), Real(b), "detector px per map pixel (bin side)"),
            (format!("CDELT2{det}"), Real(b), "detector px per map pixel (bin side)"),
            ("WCSNAMEA".into(), Text("FIELD".into()), "arcmin from the detector centre"),
            ("CTYPE1A".into(), Text("FIELDX".into()), "field x from the detector centre"),
            ("CTYPE2A".into(), Text("FIELDY".into()), "field y from the detector centre"),
            ("CUNIT1A".into(), Text("arcmin".into()), ""),
            ("CUNIT2A".into(), Text("arcmin".into()), ""),
            ("CRPIX1A".into(), Real(1.0), "map pixel of bin (0, 0)"),
            ("CRPIX2A".into(), Real(1.0), "map pixel of bin (0, 0)"),
            ("CRVAL1A".into(), Real(ax0), "field x of the centre of bin (0, 0) [arcmin]"),
            ("CRVAL2A".into(), Real(ay0), "field y of the centre of bin (0, 0) [arcmin]"),
            ("CDELT1A".into(), Real(step), "arcmin per map pixel"),
            ("CDELT2A".into(), Real(step), "arcmin per map pixel"),
        ];
        v
    }

    /// The detector's field coordinates (arcmin from its centre, unbinned pixels).
    pub fn field_coords(&self) -> field::FieldCoords {
        field::FieldCoords::centred(self.detector_nx, self.detector_ny, self.pixel_scale_arcsec)
    }
}

/// The record a corrected Stokes map carries in its primary header
/// ([`StokesMap::write_corrected_fits`]): `INSTCORR` (the calibration file's name), `CORRMETH`,
/// `CORRHWP` and, when a telescope model was removed, `TELMODEL`, `TELBAND`, `TELROT`.
#[derive(Debug, Clone, PartialEq)]
pub struct CorrectionStamp {
    /// The calibration file's name (without its folder).
    pub calibration: String,
    /// How the instrumental polarization was removed (e.g. "exact M_I inverse (eq:instpol)").
    pub method: String,
    /// The HWP zero angle added to chi (deg).
    pub hwp_chi_offset_deg: f64,
    pub telescope: Option<TelescopeStamp>,
}

/// The telescope model a corrected map had removed ([`CorrectionStamp::telescope`]).
#[derive(Debug, Clone, PartialEq)]
pub struct TelescopeStamp {
    /// The model's name (`fit::telescope::ModelKind::name`).
    pub model: String,
    pub band: String,
    /// The rotator angle the model used (deg).
    pub rotator_deg: f64,
}

impl CorrectionStamp {
    fn write_into(&self, f: &mut FitsFile) -> fitsio::errors::Result<()> {
        let ph = f.primary_hdu()?;
        ph.write_key(f, "INSTCORR", (self.calibration.as_str(), "instrumental polarization removed with"))?;
        ph.write_key(f, "CORRMETH", self.method.as_str())?;
        ph.write_key(f, "CORRHWP", (self.hwp_chi_offset_deg, "HWP zero angle added to chi [deg]"))?;
        if let Some(t) = &self.telescope {
            ph.write_key(f, "TELMODEL", (t.model.as_str(), "telescope model removed"))?;
            ph.write_key(f, "TELBAND", (t.band.as_str(), "band of the telescope model"))?;
            ph.write_key(f, "TELROT", (t.rotator_deg, "rotator angle the model used [deg]"))?;
        }
        Ok(())
    }
}

/// A binned Stokes map of one filter. All per-bin arrays have `geometry.len()` entries,
/// row-major (`j * nx + i`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StokesMap {
    pub geometry: BinGeometry,
    pub instrument: String,
    pub filter: String,
    /// HWP angles of the frames that made the map (deg).
    pub hwp_angles_deg: Vec<f64>,
    /// Normalized Stokes parameters `Q/I`, `U/I` (fractions).
    pub q: Vec<f64>,
    pub u: Vec<f64>,
    /// Standard errors of the bin means from the scatter of the kept pixels (`std / sqrt(n)`).
    pub sigma_q: Vec<f64>,
    pub sigma_u: Vec<f64>,
    /// Covariance of the bin means of q and u (scatter).
    pub cov_qu: Vec<f64>,
    /// Errors of the bin means propagated from photon and read noise.
    pub sigma_q_phot: Vec<f64>,
    pub sigma_u_phot: Vec<f64>,
    /// Polarization degree (fraction) and angle (rad, [0, pi)) of the bin means (`eq:poldeg`,
    /// `eq:polang`).
    pub p: Vec<f64>,
    pub chi: Vec<f64>,
    /// Pixels kept by the sigma clipping (coverage).
    pub n_pixels: Vec<u32>,
    /// Mean intensity `f_O + f_E` per exposure of the kept pixels (e-/px).
    pub intensity: Vec<f64>,
    /// Per-pixel SNR of the intensity summed over all exposures (photon + read noise).
    pub intensity_snr: Vec<f64>,
    /// Usable bins.
    pub valid: Vec<bool>,
    /// The celestial WCS of the map's bins (the frames' WCS carried through the binning, see
    /// [`CelestialWcs::binned`]), when the frames had one.
    pub celestial_wcs: Option<CelestialWcs>,
    /// The exposures' parallactic angle (rad): the first frame's start and the last frame's
    /// end, in the instrument's sense, when the frames' headers gave it (what a telescope
    /// model needs to correct the map; `instpol reduce` records it).
    #[serde(default)]
    pub parallactic_rad: Option<(f64, f64)>,
    /// The exposures' rotator / adapter angle (rad, the instrument's sense), when the
    /// instrument names its keyword and the frames' headers gave it.
    #[serde(default)]
    pub rotator_rad: Option<f64>,
    /// Each exposure's HWP angle and parallactic-angle track, when the frames' headers gave
    /// them: a telescope model is then undone exposure by exposure as the map's Q/I, U/I
    /// demodulated them (eq:Q, eq:U), instead of at the whole set's average angle.
    #[serde(default)]
    pub exposure_tracks: Vec<ExposureTrack>,
    /// The HWP zero angle (deg) of the instrument's filter, which the map's Q/I, U/I and chi do
    /// not carry (they are at the plate): set by the reduction from the instrument file,
    /// `HWPZERO` in FITS (module docs); `None` for a map that does not say.
    #[serde(default)]
    pub hwp_zero_angle_deg: Option<f64>,
    /// The instrument's position angle on the sky (deg, north through east) of the map's
    /// exposures, when its instrument says where to read it (`[polarimetry.sky_angle]`,
    /// `crate::sky_angle`): `SKYPA` in FITS. The map's own `Q/I`, `U/I` stay at the plate; a
    /// corrected map is turned by it onto the sky, the celestial frame.
    #[serde(default)]
    pub sky_pa_deg: Option<f64>,
    /// What else the map is ([`crate::provenance::Product`]: the instrument file's hash, the
    /// plate, the filter's wavelength, the detector, the inputs' hashes, a mismatch allowed
    /// in its correction), as primary-header keywords beside the map's own (`INSTRUME`,
    /// `FILTER`, `HWPZERO`, `SKYPA`, which the fields above hold and which say the frame);
    /// `None` for a map that does not say.
    #[serde(default)]
    pub product: Option<crate::provenance::Product>,
}

/// The product keywords a map writes from its own fields, not from its product: its
/// instrument, filter and pixel scale (`write_primary`) and its frame (`HWPZERO`, `SKYPA`).
const MAP_OWN_KEYS: [&str; 6] = ["INSTRUME", "FILTER", "PIXSCALE", "HWPZERO", "SKYPA", "FRAME"];

/// Of [`MAP_OWN_KEYS`], those whose meaning in a map is not the product's (the map's frame
/// keywords say what its `Q`, `U` lack, not what they carry): not read into its product.
const MAP_FRAME_KEYS: [&str; 3] = ["HWPZERO", "SKYPA", "FRAME"];

/// A map's product ([`StokesMap::product`], [`CircularMap::product`]) into its primary header
/// `ph`, but for the keywords the map writes from its own fields ([`MAP_OWN_KEYS`]).
fn write_product(
    f: &mut FitsFile,
    ph: &fitsio::hdu::FitsHdu,
    product: Option<&crate::provenance::Product>,
) -> Result<(), fitsio::errors::Error> {
    for (k, v) in product.iter().flat_map(|p| p.with_run_inputs().pairs()) {
        if !MAP_OWN_KEYS.contains(&k.as_str()) {
            crate::fits::KeyValue::Str(v).write(f, ph, &k, "what the map is")?;
        }
    }
    Ok(())
}

/// A map's product read back from its primary header `ph`, with the map's instrument and
/// filter (`of`); `None` for a map that records none of it.
fn read_product(
    f: &mut FitsFile,
    ph: &fitsio::hdu::FitsHdu,
    path: &Path,
    of: (&str, &str),
) -> Result<Option<crate::provenance::Product>, Error> {
    let pairs = crate::table::header_product_pairs(f, ph).map_err(|x| fits_err(path, x))?;
    let own = |k: &str| MAP_FRAME_KEYS.contains(&k);
    let product = crate::provenance::Product::from_pairs(
        pairs.iter().filter(|(k, _)| !own(k)).map(|(k, v)| (k.as_str(), v.as_str())),
    )
    .map_err(|x| fits_err(path, x))?;
    Ok(product.map(|p| crate::provenance::Product {
        instrument: Some(of.0.to_string()),
        filter: Some(of.1.to_string()),
        ..p
    }))
}

/// One exposure of a map ([`StokesMap::exposure_tracks`]): its HWP angle (deg) and the
/// parallactic angle at its start and end (rad, the instrument's sense).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExposureTrack {
    pub hwp_deg: f64,
    pub start: f64,
    pub end: f64,
}

/// The telescope angles data record for a later correction (module docs): the set's
/// parallactic track, the rotator angle, each exposure's HWP angle and track. As keywords they
/// are `PARANG1`, `PARANG2`, `ROTANG`, `NEXPTRK`, `XHWPk`, `XPASk`, `XPAEk` (deg), all
/// optional: the primary header of a Stokes map, the table-level numbers of a catalog table
/// ([`crate::table::Table::meta`]). One writing and one reading of those names.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RecordedAngles {
    /// Rad: the first exposure's start, the last one's end.
    pub parallactic_rad: Option<(f64, f64)>,
    pub rotator_rad: Option<f64>,
    pub exposure_tracks: Vec<ExposureTrack>,
}

impl RecordedAngles {
    /// The keywords, with their comments (`NEXPTRK` a count, the others degrees).
    pub fn keywords(&self) -> Vec<(String, crate::fits::KeyValue, &'static str)> {
        use crate::fits::KeyValue::{F64, I64};
        let mut k = Vec::new();
        if let Some((a, b)) = self.parallactic_rad {
            k.push(("PARANG1".to_string(), F64(a.to_degrees()), "parallactic angle, first start [deg]"));
            k.push(("PARANG2".to_string(), F64(b.to_degrees()), "parallactic angle, last end [deg]"));
        }
        if let Some(r) = self.rotator_rad {
            k.push(("ROTANG".to_string(), F64(r.to_degrees()), "rotator / adapter angle [deg]"));
        }
        if !self.exposure_tracks.is_empty() {
            k.push((
                "NEXPTRK".to_string(),
                I64(self.exposure_tracks.len() as i64),
                "exposures with their parallactic angles",
            ));
            for (n, x) in self.exposure_tracks.iter().enumerate() {
                let n = n + 1;
                k.push((format!("XHWP{n}"), F64(x.hwp_deg), "exposure's HWP angle [deg]"));
                k.push((format!("XPAS{n}"), F64(x.start.to_degrees()), "its parallactic angle, start [deg]"));
                k.push((format!("XPAE{n}"), F64(x.end.to_degrees()), "its parallactic angle, end [deg]"));
            }
        }
        k
    }

    /// Read the keywords back: `get` gives a keyword's text (None when absent). A keyword
    /// present but not an angle in degrees (or `NEXPTRK` not a count up to 4096) is an error
    /// naming it and `path`; so is an exposure's keyword missing, or `PARANG2` without `PARANG1`.
    pub fn from_keywords(mut get: impl FnMut(&str) -> Option<String>, path: &Path) -> Result<Self, Error> {
        let count = get("NEXPTRK");
        // Degrees as written (the HWP angles are kept in degrees; the others become radians).
        let mut degrees = |k: &str| -> Result<Option<f64>, Error> {
            match get(k) {
                None => Ok(None),
                Some(s) => match s.trim().parse::<f64>() {
                    Ok(v) if mueller::plausible_degrees(v) => Ok(Some(v)),
                    _ => Err(Error::BadKeyword {
                        path: path.into(),
                        keyword: k.into(),
                        value: s,
                        expected: "an angle in degrees".into(),
                    }),
                },
            }
        };
        let mut angle = |k: &str| degrees(k).map(|v| v.map(f64::to_radians));
        let parallactic_rad = match (angle("PARANG1")?, angle("PARANG2")?) {
            (Some(a), b) => Some((a, b.unwrap_or(a))),
            (None, None) => None,
            (None, Some(_)) => {
                return Err(Error::MissingKeyword { path: path.into(), keyword: "PARANG1 (beside PARANG2)".into() })
            }
        };
        let rotator_rad = angle("ROTANG")?;
        // Each exposure's angles (NEXPTRK of them), all three keywords each, or none.
        let mut exposure_tracks = vec![];
        if let Some(text) = count {
            let n = match text.trim().parse::<f64>() {
                Ok(n) if (0.0..=4096.0).contains(&n) && n.fract() == 0.0 => n as usize,
                _ => {
                    return Err(Error::BadKeyword {
                        path: path.into(),
                        keyword: "NEXPTRK".into(),
                        value: text,
                        expected: "a number of exposures (0 to 4096)".into(),
                    })
                }
            };
            for k in 1..=n {
                let mut need = |name: String| -> Result<f64, Error> {
                    degrees(&name)?.ok_or(Error::MissingKeyword { path: path.into(), keyword: name })
                };
                exposure_tracks.push(ExposureTrack {
                    hwp_deg: need(format!("XHWP{k}"))?,
                    start: need(format!("XPAS{k}"))?.to_radians(),
                    end: need(format!("XPAE{k}"))?.to_radians(),
                });
            }
        }
        Ok(Self { parallactic_rad, rotator_rad, exposure_tracks })
    }

    /// As a table's numbers ([`crate::table::Table::meta`]).
    pub fn to_meta(&self) -> Vec<(String, f64)> {
        self.keywords()
            .into_iter()
            .filter_map(|(k, v, _)| match v {
                crate::fits::KeyValue::F64(x) => Some((k, x)),
                crate::fits::KeyValue::I64(n) => Some((k, n as f64)),
                crate::fits::KeyValue::Str(_) => None,
            })
            .collect()
    }

    /// Read back from a table's numbers ([`RecordedAngles::from_keywords`]; `path` names the
    /// table in errors).
    pub fn from_meta(meta: &[(String, f64)], path: &Path) -> Result<Self, Error> {
        Self::from_keywords(|k| meta.iter().find(|(n, _)| n == k).map(|(_, v)| format!("{v:?}")), path)
    }
}

/// What a file given to a correction holds, by its content ([`file_kind`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileKind {
    /// CSV, ECSV or VOTable: the format by extension ([`crate::table`]).
    TextTable,
    FitsTable,
    StokesMap,
}

/// Why [`file_kind`] could not tell.
#[derive(Debug, thiserror::Error)]
pub enum FileKindError {
    #[error("cannot open {}", .0.display())]
    Open(std::path::PathBuf, #[source] std::io::Error),
    #[error("cannot read {}", .0.display())]
    Read(std::path::PathBuf, #[source] std::io::Error),
    #[error(transparent)]
    Fits(#[from] Error),
}

/// A FITS file (its first bytes `SIMPLE  =`) whose primary header has `MAPVERS` is a Stokes map
/// (this module's format), another FITS file a FITS table; anything else a text table.
pub fn file_kind(path: &Path) -> Result<FileKind, FileKindError> {
    use std::io::Read;
    let mut head = [0u8; 9];
    let mut f = std::fs::File::open(path).map_err(|e| FileKindError::Open(path.into(), e))?;
    let n = f.read(&mut head).map_err(|e| FileKindError::Read(path.into(), e))?;
    if n == 9 && &head == b"SIMPLE  =" {
        let mut ff = FitsFile::open(path).map_err(|e| fits_err(path, format!("cannot open as FITS: {e}")))?;
        let ph = ff.primary_hdu().map_err(|e| fits_err(path, e))?;
        if ph.read_key::<i64>(&mut ff, "MAPVERS").is_ok() {
            return Ok(FileKind::StokesMap);
        }
        return Ok(FileKind::FitsTable);
    }
    Ok(FileKind::TextTable)
}

/// Which Stokes parameters a map holds: its `STOKES` keyword (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MapStokes {
    /// `Q/I`, `U/I` from a half-wave plate (no `STOKES` keyword, or `'QU'`).
    Linear,
    /// `V/I` from a quarter-wave plate (`STOKES = 'V'`, a [`CircularMap`]).
    Circular,
}

/// The `STOKES` keyword of a map's primary header: absent or `'QU'` a linear map, `'V'` a
/// circular one; anything else is an error naming it.
fn map_stokes(f: &mut FitsFile, ph: &fitsio::hdu::FitsHdu, path: &Path) -> Result<MapStokes, Error> {
    match crate::fits::read_key_str(f, ph, "STOKES") {
        Err(_) => Ok(MapStokes::Linear),
        Ok(v) => match v.trim() {
            "QU" => Ok(MapStokes::Linear),
            "V" => Ok(MapStokes::Circular),
            _ => Err(Error::BadKeyword {
                path: path.into(),
                keyword: "STOKES".into(),
                value: v,
                expected: "'QU' (a linear map) or 'V' (a circular one)".into(),
            }),
        },
    }
}

/// What the primary header of every map holds ([`write_primary`]).
struct MapHeader {
    instrument: String,
    filter: String,
    angles_deg: Vec<f64>,
    geometry: BinGeometry,
}

/// Read and check the primary header every map starts with (format version, instrument,
/// filter, plate angles, bin geometry).
fn read_header(f: &mut FitsFile, ph: &fitsio::hdu::FitsHdu, path: &Path) -> Result<MapHeader, Error> {
    let key_i = |f: &mut FitsFile, k: &str| -> Result<i64, Error> {
        ph.read_key::<i64>(f, k).map_err(|_| Error::MissingKeyword { path: path.into(), keyword: k.into() })
    };
    let ver = key_i(f, "MAPVERS")?;
    if ver != MAP_FORMAT_VERSION as i64 {
        return Err(Error::BadKeyword {
            path: path.into(),
            keyword: "MAPVERS".into(),
            value: ver.to_string(),
            expected: format!("a supported Stokes-map format version ({MAP_FORMAT_VERSION})"),
        });
    }
    let key_s = |f: &mut FitsFile, k: &str| -> Result<String, Error> {
        crate::fits::read_key_str(f, ph, k).map_err(|_| Error::MissingKeyword { path: path.into(), keyword: k.into() })
    };
    let instrument = key_s(f, "INSTRUME")?;
    let filter = key_s(f, "FILTER")?;
    let nhwp = key_i(f, "NHWP")?.max(0) as usize;
    let mut hwp = Vec::with_capacity(nhwp);
    for k in 1..=nhwp {
        let name = format!("HWPANG{k}");
        hwp.push(
            ph.read_key::<f64>(f, &name)
                .map_err(|_| Error::MissingKeyword { path: path.into(), keyword: name.clone() })?,
        );
    }
    let usz = |f: &mut FitsFile, k: &str| -> Result<usize, Error> {
        let v = key_i(f, k)?;
        usize::try_from(v).map_err(|_| Error::BadKeyword {
            path: path.into(),
            keyword: k.into(),
            value: v.to_string(),
            expected: "a non-negative integer".into(),
        })
    };
    let geometry = BinGeometry {
        bin_px: usz(f, "BINSIZE")?,
        origin_x: usz(f, "BINORGX")?,
        origin_y: usz(f, "BINORGY")?,
        nx: usz(f, "NBINX")?,
        ny: usz(f, "NBINY")?,
        pixel_scale_arcsec: ph
            .read_key::<f64>(f, "PIXSCALE")
            .map_err(|_| Error::MissingKeyword { path: path.into(), keyword: "PIXSCALE".into() })?,
        detector_nx: usz(f, "DETNX")?,
        detector_ny: usz(f, "DETNY")?,
    };
    Ok(MapHeader { instrument, filter, angles_deg: hwp, geometry })
}

/// Image extension `name` of a map of `n` bins.
fn read_plane(f: &mut FitsFile, path: &Path, name: &str, n: usize) -> Result<Vec<f64>, Error> {
    let hdu = f.hdu(name).map_err(|_| fits_err(path, format!("missing image extension {name}")))?;
    let v: Vec<f64> = hdu.read_image(f).map_err(|e| fits_err(path, format!("extension {name}: {e}")))?;
    if v.len() != n {
        return Err(fits_err(path, format!("extension {name} has {} values, header says {n} bins", v.len())));
    }
    Ok(v)
}

/// Units as FITS/astropy unit strings; '' for the dimensionless Stokes fractions (an empty
/// BUNIT reads as dimensionless in astropy; 'fraction' is no unit and fails).
const FRAC: (&str, &str) = ("", "dimensionless fraction");

/// One float image of a map: extension name, values, `CONTENT`, `BUNIT` with its comment.
type Plane<'a> = (&'a str, &'a [f64], &'a str, (&'a str, &'a str));

/// The primary header every map starts with (module docs): format version, instrument,
/// filter, plate angles and bin geometry.
fn write_primary(
    f: &mut FitsFile,
    path: &Path,
    g: &BinGeometry,
    instrument: &str,
    filter: &str,
    angles_deg: &[f64],
) -> Result<fitsio::hdu::FitsHdu, Error> {
    let e = |x: fitsio::errors::Error| Error::Write { path: path.into(), message: x.to_string() };
    let ph = f.primary_hdu().map_err(e)?;
    ph.write_key(f, "MAPVERS", (MAP_FORMAT_VERSION, "instpol Stokes map format version")).map_err(e)?;
    ph.write_key(f, "ORIGIN", "instpol").map_err(e)?;
    ph.write_key(f, "INSTRUME", instrument).map_err(e)?;
    ph.write_key(f, "FILTER", filter).map_err(e)?;
    ph.write_key(f, "NHWP", (angles_deg.len() as i64, "number of HWP angles")).map_err(e)?;
    for (k, a) in angles_deg.iter().enumerate() {
        ph.write_key(f, &format!("HWPANG{}", k + 1), (*a, "HWP angle [deg]")).map_err(e)?;
    }
    ph.write_key(f, "BINSIZE", (g.bin_px as i64, "bin side [px]")).map_err(e)?;
    ph.write_key(f, "BINORGX", (g.origin_x as i64, "0-based x pixel where bin 0 starts")).map_err(e)?;
    ph.write_key(f, "BINORGY", (g.origin_y as i64, "0-based y pixel where bin 0 starts")).map_err(e)?;
    ph.write_key(f, "NBINX", (g.nx as i64, "bins along x")).map_err(e)?;
    ph.write_key(f, "NBINY", (g.ny as i64, "bins along y")).map_err(e)?;
    ph.write_key(f, "PIXSCALE", (g.pixel_scale_arcsec, "detector scale [arcsec/px]")).map_err(e)?;
    ph.write_key(f, "DETNX", (g.detector_nx as i64, "detector size x [px]")).map_err(e)?;
    ph.write_key(f, "DETNY", (g.detector_ny as i64, "detector size y [px]")).map_err(e)?;
    Ok(ph)
}

/// The image extensions of a map: its float `planes`, then `COVERAGE` and `VALID`, each with
/// its `BUNIT` and the bins' WCSs (module docs).
fn write_planes(
    f: &mut FitsFile,
    path: &Path,
    g: &BinGeometry,
    celestial: Option<&CelestialWcs>,
    planes: &[Plane],
    n_pixels: &[u32],
    valid: &[bool],
) -> Result<(), Error> {
    let e = |x: fitsio::errors::Error| Error::Write { path: path.into(), message: x.to_string() };
    let dims = [g.ny, g.nx];
    // The celestial WCS, when the frames had one, is the primary WCS (what astropy's
    // WCS(header) gives); the detector grid is then alternate D.
    let wcs = match celestial {
        Some(c) => {
            let mut v = g.wcs_cards_keyed("D");
            v.splice(1..1, c.cards());
            v
        }
        None => g.wcs_cards(),
    };
    let put = |f: &mut FitsFile, hdu: &fitsio::hdu::FitsHdu, bunit: (&str, &str)| -> Result<(), Error> {
        hdu.write_key(f, "BUNIT", (bunit.0, bunit.1)).map_err(e)?;
        for (k, v, c) in &wcs {
            match v {
                WcsValue::Int(x) => hdu.write_key(f, k, (*x, *c)),
                WcsValue::Real(x) => hdu.write_key(f, k, (*x, *c)),
                WcsValue::Text(x) => hdu.write_key(f, k, (x.as_str(), *c)),
            }
            .map_err(e)?;
        }
        Ok(())
    };
    for (name, data, comment, bunit) in planes.iter() {
        let d = ImageDescription { data_type: ImageType::Double, dimensions: &dims };
        let hdu = f.create_image(name.to_string(), &d).map_err(e)?;
        hdu.write_image(f, data).map_err(e)?;
        hdu.write_key(f, "CONTENT", *comment).map_err(e)?;
        put(f, &hdu, *bunit)?;
    }
    let d = ImageDescription { data_type: ImageType::Long, dimensions: &dims };
    let cov: Vec<i32> = n_pixels.iter().map(|&n| n as i32).collect();
    let hdu = f.create_image("COVERAGE".to_string(), &d).map_err(e)?;
    hdu.write_image(f, &cov).map_err(e)?;
    hdu.write_key(f, "CONTENT", "pixels kept by sigma clipping").map_err(e)?;
    put(f, &hdu, ("pix", "detector pixels kept"))?;
    let valid: Vec<i32> = valid.iter().map(|&v| v as i32).collect();
    let hdu = f.create_image("VALID".to_string(), &d).map_err(e)?;
    hdu.write_image(f, &valid).map_err(e)?;
    hdu.write_key(f, "CONTENT", "1 = usable bin").map_err(e)?;
    put(f, &hdu, ("", "flag"))?;
    Ok(())
}

impl StokesMap {
    /// The telescope angles the map records ([`RecordedAngles`]).
    pub fn recorded_angles(&self) -> RecordedAngles {
        RecordedAngles {
            parallactic_rad: self.parallactic_rad,
            rotator_rad: self.rotator_rad,
            exposure_tracks: self.exposure_tracks.clone(),
        }
    }

    /// An all-invalid map on `geometry`.
    pub fn empty(geometry: BinGeometry, instrument: &str, filter: &str, hwp_angles_deg: Vec<f64>) -> Self {
        let n = geometry.len();
        let nan = vec![f64::NAN; n];
        Self {
            geometry,
            instrument: instrument.into(),
            filter: filter.into(),
            hwp_angles_deg,
            q: nan.clone(),
            u: nan.clone(),
            sigma_q: nan.clone(),
            sigma_u: nan.clone(),
            cov_qu: nan.clone(),
            sigma_q_phot: nan.clone(),
            sigma_u_phot: nan.clone(),
            p: nan.clone(),
            chi: nan.clone(),
            n_pixels: vec![0; n],
            intensity: nan.clone(),
            intensity_snr: nan,
            valid: vec![false; n],
            celestial_wcs: None,
            parallactic_rad: None,
            rotator_rad: None,
            exposure_tracks: vec![],
            hwp_zero_angle_deg: None,
            sky_pa_deg: None,
            product: None,
        }
    }

    /// Number of valid bins.
    pub fn n_valid(&self) -> usize {
        self.valid.iter().filter(|&&v| v).count()
    }

    /// Iterate over valid bins as `(index, i, j)`.
    pub fn valid_bins(&self) -> impl Iterator<Item = (usize, usize, usize)> + '_ {
        let nx = self.geometry.nx;
        (0..self.geometry.len()).filter(move |&k| self.valid[k]).map(move |k| (k, k % nx, k / nx))
    }

    fn check_lengths(&self) -> Result<(), Error> {
        let n = self.geometry.len();
        let lens = [
            ("Q", self.q.len()),
            ("U", self.u.len()),
            ("SIGMA_Q", self.sigma_q.len()),
            ("SIGMA_U", self.sigma_u.len()),
            ("COV_QU", self.cov_qu.len()),
            ("SIGQ_PHOT", self.sigma_q_phot.len()),
            ("SIGU_PHOT", self.sigma_u_phot.len()),
            ("P", self.p.len()),
            ("CHI", self.chi.len()),
            ("COVERAGE", self.n_pixels.len()),
            ("INTENSITY", self.intensity.len()),
            ("INT_SNR", self.intensity_snr.len()),
            ("VALID", self.valid.len()),
        ];
        for (name, l) in lens {
            if l != n {
                return Err(Error::Invalid(format!("Stokes map array {name} has {l} entries, geometry has {n} bins")));
            }
        }
        Ok(())
    }

    /// Write the map as a multi-extension FITS file (layout in the module docs), atomically:
    /// a temporary file in the same folder renamed over `path` only when complete.
    pub fn write_fits(&self, path: &Path) -> Result<(), Error> {
        self.check_lengths()?;
        crate::fits::write_fits_atomic(path, |f| self.write_into(f, path))
    }

    fn write_into(&self, f: &mut FitsFile, path: &Path) -> Result<(), Error> {
        let e = |x: fitsio::errors::Error| Error::Write { path: path.into(), message: x.to_string() };
        let ph = write_primary(f, path, &self.geometry, &self.instrument, &self.filter, &self.hwp_angles_deg)?;
        for (k, v, comment) in self.recorded_angles().keywords() {
            v.write(f, &ph, &k, comment).map_err(e)?;
        }
        if let Some(z) = self.hwp_zero_angle_deg {
            crate::fits::KeyValue::F64(z)
                .write(f, &ph, "HWPZERO", "HWP zero angle of the filter, not in Q, U [deg]")
                .map_err(e)?;
        }
        if let Some(a) = self.sky_pa_deg {
            crate::fits::KeyValue::F64(a)
                .write(f, &ph, "SKYPA", "instrument position angle on the sky [deg]")
                .map_err(e)?;
        }
        write_product(f, &ph, self.product.as_ref()).map_err(e)?;
        let chi_deg: Vec<f64> = self.chi.iter().map(|c| c.to_degrees()).collect();
        let floats: [Plane; 11] = [
            ("Q", &self.q, "Q/I", FRAC),
            ("U", &self.u, "U/I", FRAC),
            ("SIGMA_Q", &self.sigma_q, "error of Q/I from pixel scatter", FRAC),
            ("SIGMA_U", &self.sigma_u, "error of U/I from pixel scatter", FRAC),
            ("COV_QU", &self.cov_qu, "covariance of Q/I and U/I", FRAC),
            ("SIGQ_PHOT", &self.sigma_q_phot, "error of Q/I from photon+read noise", FRAC),
            ("SIGU_PHOT", &self.sigma_u_phot, "error of U/I from photon+read noise", FRAC),
            ("P", &self.p, "polarization degree (fraction)", FRAC),
            ("CHI", &chi_deg, "polarization angle [deg]", ("deg", "degrees")),
            ("INTENSITY", &self.intensity, "mean f_O+f_E per exposure [e-/px]", ("electron/pix", "per exposure")),
            ("INT_SNR", &self.intensity_snr, "per-pixel SNR of combined intensity", ("", "dimensionless ratio")),
        ];
        write_planes(f, path, &self.geometry, self.celestial_wcs.as_ref(), &floats, &self.n_pixels, &self.valid)
    }

    /// Write a map corrected for the instrumental polarization ([`StokesMap::write_fits`], the
    /// same layout) with the correction's record in the primary header (`stamp`): what
    /// [`StokesMap::read_uncorrected`] refuses, so that a map is never corrected twice.
    pub fn write_corrected_fits(&self, path: &Path, stamp: &CorrectionStamp) -> Result<(), Error> {
        self.check_lengths()?;
        crate::fits::write_fits_atomic(path, |f| {
            self.write_into(f, path)?;
            stamp.write_into(f).map_err(|x| Error::Write { path: path.into(), message: x.to_string() })
        })
    }

    /// [`StokesMap::read_fits`] for inputs that must still hold the instrumental polarization
    /// (`instpol correct`, a sky-field calibration): a map that `instpol correct` wrote
    /// (primary keyword `INSTCORR`, the calibration it was corrected with) is refused, as
    /// correcting it again, or calibrating on it, would take the instrumental polarization
    /// out twice. (The error does not name the file: callers say which input it was.)
    pub fn read_uncorrected(path: &Path) -> Result<Self, Error> {
        Self::read(path, true)
    }

    /// Read a map written by [`Self::write_fits`].
    pub fn read_fits(path: &Path) -> Result<Self, Error> {
        Self::read(path, false)
    }

    /// [`Self::read_fits`], refusing a corrected map first when `uncorrected_only`.
    fn read(path: &Path, uncorrected_only: bool) -> Result<Self, Error> {
        let mut f = FitsFile::open(path).map_err(|e| fits_err(path, format!("cannot open as FITS: {e}")))?;
        let ph = f.primary_hdu().map_err(|e| fits_err(path, e))?;
        // The one check that keeps a circular map from every reader that needs Q/I, U/I (fit,
        // calibrate, correct, the Python package all read maps here).
        if map_stokes(&mut f, &ph, path)? == MapStokes::Circular {
            return Err(Error::Invalid(
                "a circular-polarization map (STOKES = 'V': V/I from a quarter-wave plate, by instpol reduce): it holds no Q/I, U/I, which fitting, calibrating and correcting the instrumental polarization need".into(),
            ));
        }
        if uncorrected_only {
            if let Ok(cal) = crate::fits::read_key_str(&mut f, &ph, "INSTCORR") {
                return Err(Error::Invalid(format!(
                    "already corrected for the instrumental polarization (INSTCORR = '{cal}', by instpol correct); correcting it again or calibrating on it would remove that polarization twice: use the map from instpol reduce"
                )));
            }
        }
        let MapHeader { instrument, filter, angles_deg: hwp, geometry } = read_header(&mut f, &ph, path)?;
        let n = geometry.len();
        let read_f = |f: &mut FitsFile, name: &str| read_plane(f, path, name, n);
        let q = read_f(&mut f, "Q")?;
        let u = read_f(&mut f, "U")?;
        let sigma_q = read_f(&mut f, "SIGMA_Q")?;
        let sigma_u = read_f(&mut f, "SIGMA_U")?;
        let cov_qu = read_f(&mut f, "COV_QU")?;
        let sigma_q_phot = read_f(&mut f, "SIGQ_PHOT")?;
        let sigma_u_phot = read_f(&mut f, "SIGU_PHOT")?;
        let p = read_f(&mut f, "P")?;
        let chi: Vec<f64> = read_f(&mut f, "CHI")?.into_iter().map(f64::to_radians).collect();
        let intensity = read_f(&mut f, "INTENSITY")?;
        let intensity_snr = read_f(&mut f, "INT_SNR")?;
        let n_pixels: Vec<u32> = read_f(&mut f, "COVERAGE")?.into_iter().map(|v| v.max(0.0) as u32).collect();
        let valid: Vec<bool> = read_f(&mut f, "VALID")?.into_iter().map(|v| v > 0.5).collect();
        // The celestial WCS the writer put on every image (read from Q); maps without one, or
        // with one this reader does not carry, have None.
        let celestial_wcs = match f.hdu("Q") {
            Ok(h) => CelestialWcs::read(&mut f, &h).ok().flatten(),
            Err(_) => None,
        };
        let RecordedAngles { parallactic_rad, rotator_rad, exposure_tracks } =
            RecordedAngles::from_keywords(|k| crate::fits::read_key_str(&mut f, &ph, k).ok(), path)?;
        let mut angle = |key: &str| match crate::fits::read_key_str(&mut f, &ph, key).ok() {
            None => Ok(None),
            Some(v) => match v.trim().parse::<f64>() {
                Ok(z) if z.is_finite() => Ok(Some(z)),
                _ => Err(Error::BadKeyword {
                    path: path.into(),
                    keyword: key.into(),
                    value: v,
                    expected: "a finite angle in degrees".into(),
                }),
            },
        };
        let (hwp_zero_angle_deg, sky_pa_deg) = (angle("HWPZERO")?, angle("SKYPA")?);
        let product = read_product(&mut f, &ph, path, (&instrument, &filter))?;
        // A map made elsewhere (or edited) is checked before anything is fitted to it: every
        // valid bin holds a physical polarization and a covariance that is one.
        for k in (0..n).filter(|&k| valid[k]) {
            let (i, j) = (k % geometry.nx.max(1), k / geometry.nx.max(1));
            let why = if !(q[k].is_finite() && u[k].is_finite()) {
                Some(format!("Q/U = {}, {} is not finite", q[k], u[k]))
            } else if q[k].hypot(u[k]) > 1.0 {
                Some(format!("P = hypot(Q, U) = {} exceeds 1 (a map in percent?)", q[k].hypot(u[k])))
            } else if !(sigma_q[k] >= 0.0 && sigma_u[k] >= 0.0 && sigma_q[k].is_finite() && sigma_u[k].is_finite()) {
                Some(format!("SIGMA_Q, SIGMA_U = {}, {} are not finite errors >= 0", sigma_q[k], sigma_u[k]))
            } else if !(cov_qu[k].is_finite()
                && cov_qu[k] * cov_qu[k] <= sigma_q[k] * sigma_q[k] * sigma_u[k] * sigma_u[k] * (1.0 + 1e-9))
            {
                Some(format!(
                    "COV_QU = {} is not a covariance of errors {} and {} (|cov| > sigma_q sigma_u)",
                    cov_qu[k], sigma_q[k], sigma_u[k]
                ))
            } else {
                None
            };
            if let Some(w) = why {
                return Err(fits_err(path, format!("bin ({i}, {j}): {w}")));
            }
        }
        Ok(Self {
            geometry,
            instrument,
            filter,
            hwp_angles_deg: hwp,
            q,
            u,
            sigma_q,
            sigma_u,
            cov_qu,
            sigma_q_phot,
            sigma_u_phot,
            p,
            chi,
            n_pixels,
            intensity,
            intensity_snr,
            valid,
            celestial_wcs,
            parallactic_rad,
            rotator_rad,
            exposure_tracks,
            hwp_zero_angle_deg,
            sky_pa_deg,
            product,
        })
    }
}

/// A binned map of circular polarization `V/I` of one filter, from frames taken through a
/// quarter-wave plate (`skyfield::reduce`'s circular reduction; `stokes::circular` for the
/// demodulation). The same bins, coverage, intensity and WCS as a [`StokesMap`]; in place of
/// `Q/I`, `U/I`, `P`, `chi` it holds `V/I` and its errors, as those plate positions do not
/// determine `Q/I`, `U/I`. In FITS (module docs) its primary header says `STOKES = 'V'`, which
/// the Stokes-map reader ([`StokesMap::read_fits`]) refuses with the reason.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CircularMap {
    pub geometry: BinGeometry,
    pub instrument: String,
    pub filter: String,
    /// The frames' plate angles (deg, as the headers or the caller gave them).
    pub plate_angles_deg: Vec<f64>,
    /// The plate's zero angle (deg) the demodulation added to them: its fast axis at the plate
    /// angle plus this (the instrument's `qwp_zero_angle_deg` of the filter).
    pub qwp_zero_angle_deg: f64,
    /// `V/I` (fraction, IAU sign) of the bin means.
    pub v: Vec<f64>,
    /// Standard error of the bin mean of `V/I` from the scatter of the kept pixels (floored by
    /// the photon error in bins of few pixels, as `SIGMA_Q` of a [`StokesMap`]).
    pub sigma_v: Vec<f64>,
    /// Error of the bin mean propagated from photon and read noise.
    pub sigma_v_phot: Vec<f64>,
    /// Pixels kept by the sigma clipping (coverage).
    pub n_pixels: Vec<u32>,
    /// Mean intensity `f_O + f_E` per exposure of the kept pixels (e-/px).
    pub intensity: Vec<f64>,
    /// Per-pixel SNR of the intensity summed over all exposures (photon + read noise).
    pub intensity_snr: Vec<f64>,
    /// Usable bins.
    pub valid: Vec<bool>,
    /// The frames' celestial WCS carried through the binning, when they had one.
    pub celestial_wcs: Option<CelestialWcs>,
    /// What else the map is, as a [`StokesMap`]'s product.
    pub product: Option<crate::provenance::Product>,
}

impl CircularMap {
    /// Number of valid bins.
    pub fn n_valid(&self) -> usize {
        self.valid.iter().filter(|&&v| v).count()
    }

    /// Iterate over valid bins as `(index, i, j)`.
    pub fn valid_bins(&self) -> impl Iterator<Item = (usize, usize, usize)> + '_ {
        let nx = self.geometry.nx;
        (0..self.geometry.len()).filter(move |&k| self.valid[k]).map(move |k| (k, k % nx, k / nx))
    }

    fn check_lengths(&self) -> Result<(), Error> {
        let n = self.geometry.len();
        for (name, l) in [
            ("V", self.v.len()),
            ("SIGMA_V", self.sigma_v.len()),
            ("SIGV_PHOT", self.sigma_v_phot.len()),
            ("COVERAGE", self.n_pixels.len()),
            ("INTENSITY", self.intensity.len()),
            ("INT_SNR", self.intensity_snr.len()),
            ("VALID", self.valid.len()),
        ] {
            if l != n {
                return Err(Error::Invalid(format!(
                    "circular map array {name} has {l} entries, geometry has {n} bins"
                )));
            }
        }
        Ok(())
    }

    /// Write the map as a multi-extension FITS file (module docs: `STOKES = 'V'`, `QWPZERO`,
    /// images `V`, `SIGMA_V`, `SIGV_PHOT`, `INTENSITY`, `INT_SNR`, `COVERAGE`, `VALID`),
    /// atomically.
    pub fn write_fits(&self, path: &Path) -> Result<(), Error> {
        self.check_lengths()?;
        crate::fits::write_fits_atomic(path, |f| {
            let e = |x: fitsio::errors::Error| Error::Write { path: path.into(), message: x.to_string() };
            let ph = write_primary(f, path, &self.geometry, &self.instrument, &self.filter, &self.plate_angles_deg)?;
            ph.write_key(f, "STOKES", ("V", "circular polarization V/I (quarter-wave plate)")).map_err(e)?;
            ph.write_key(f, "QWPZERO", (self.qwp_zero_angle_deg, "QWP zero angle used in the demodulation [deg]"))
                .map_err(e)?;
            write_product(f, &ph, self.product.as_ref()).map_err(e)?;
            let planes: [Plane; 5] = [
                ("V", &self.v, "V/I (IAU sign)", FRAC),
                ("SIGMA_V", &self.sigma_v, "error of V/I from pixel scatter", FRAC),
                ("SIGV_PHOT", &self.sigma_v_phot, "error of V/I from photon+read noise", FRAC),
                ("INTENSITY", &self.intensity, "mean f_O+f_E per exposure [e-/px]", ("electron/pix", "per exposure")),
                ("INT_SNR", &self.intensity_snr, "per-pixel SNR of combined intensity", ("", "dimensionless ratio")),
            ];
            write_planes(f, path, &self.geometry, self.celestial_wcs.as_ref(), &planes, &self.n_pixels, &self.valid)
        })
    }

    /// Read a map written by [`Self::write_fits`]; a linear map (no `STOKES = 'V'`) is refused
    /// naming what it is, and so is a valid bin whose `V/I` is not a fraction or whose error is
    /// not one.
    pub fn read_fits(path: &Path) -> Result<Self, Error> {
        let mut f = FitsFile::open(path).map_err(|e| fits_err(path, format!("cannot open as FITS: {e}")))?;
        let ph = f.primary_hdu().map_err(|e| fits_err(path, e))?;
        if map_stokes(&mut f, &ph, path)? != MapStokes::Circular {
            return Err(fits_err(
                path,
                "a linear Stokes map (Q/I, U/I; no STOKES = 'V'), not a circular-polarization map",
            ));
        }
        let MapHeader { instrument, filter, angles_deg, geometry } = read_header(&mut f, &ph, path)?;
        let qwp_zero_angle_deg = ph
            .read_key::<f64>(&mut f, "QWPZERO")
            .map_err(|_| Error::MissingKeyword { path: path.into(), keyword: "QWPZERO".into() })?;
        let product = read_product(&mut f, &ph, path, (&instrument, &filter))?;
        let n = geometry.len();
        let v = read_plane(&mut f, path, "V", n)?;
        let sigma_v = read_plane(&mut f, path, "SIGMA_V", n)?;
        let sigma_v_phot = read_plane(&mut f, path, "SIGV_PHOT", n)?;
        let intensity = read_plane(&mut f, path, "INTENSITY", n)?;
        let intensity_snr = read_plane(&mut f, path, "INT_SNR", n)?;
        let n_pixels = read_plane(&mut f, path, "COVERAGE", n)?.into_iter().map(|v| v.max(0.0) as u32).collect();
        let valid: Vec<bool> = read_plane(&mut f, path, "VALID", n)?.into_iter().map(|v| v > 0.5).collect();
        let celestial_wcs = match f.hdu("V") {
            Ok(h) => CelestialWcs::read(&mut f, &h).ok().flatten(),
            Err(_) => None,
        };
        for k in (0..n).filter(|&k| valid[k]) {
            let (i, j) = (k % geometry.nx.max(1), k / geometry.nx.max(1));
            if !(v[k].is_finite() && v[k].abs() <= 1.0) {
                return Err(fits_err(path, format!("bin ({i}, {j}): V/I = {} is not a fraction in [-1, 1]", v[k])));
            }
            if !(sigma_v[k].is_finite() && sigma_v[k] >= 0.0) {
                return Err(fits_err(
                    path,
                    format!("bin ({i}, {j}): SIGMA_V = {} is not a finite error >= 0", sigma_v[k]),
                ));
            }
        }
        Ok(Self {
            geometry,
            instrument,
            filter,
            plate_angles_deg: angles_deg,
            qwp_zero_angle_deg,
            v,
            sigma_v,
            sigma_v_phot,
            n_pixels,
            intensity,
            intensity_snr,
            valid,
            celestial_wcs,
            product,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> StokesMap {
        let g = BinGeometry::covering(30, 0, 34, 100, 130, 0.2);
        assert_eq!((g.nx, g.ny), (4, 4));
        let mut m = StokesMap::empty(g, "FORS1", "V", vec![0.0, 22.5, 45.0, 67.5]);
        for k in 0..m.geometry.len() {
            if k % 3 == 0 {
                continue;
            }
            m.q[k] = 0.01 * k as f64;
            m.u[k] = -0.002 * k as f64;
            let (p, chi) = stokes::polarization(m.q[k], m.u[k]);
            m.p[k] = p;
            m.chi[k] = chi;
            m.sigma_q[k] = 1e-4;
            m.sigma_u[k] = 2e-4;
            m.cov_qu[k] = 1e-9;
            m.sigma_q_phot[k] = 1.1e-4;
            m.sigma_u_phot[k] = 1.2e-4;
            m.n_pixels[k] = 900 - k as u32;
            m.intensity[k] = 5000.0;
            m.intensity_snr[k] = 141.0;
            m.valid[k] = true;
        }
        m
    }

    #[test]
    fn fits_round_trip_keeps_everything() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.fits");
        let m = sample();
        m.write_fits(&path).unwrap();
        let r = StokesMap::read_fits(&path).unwrap();
        assert_eq!(r.geometry, m.geometry);
        assert_eq!(r.hwp_angles_deg, m.hwp_angles_deg);
        assert_eq!((r.instrument.as_str(), r.filter.as_str()), ("FORS1", "V"));
        assert_eq!(r.valid, m.valid);
        assert_eq!(r.n_pixels, m.n_pixels);
        for k in 0..m.geometry.len() {
            if m.valid[k] {
                assert_eq!(r.q[k], m.q[k]);
                assert!((r.chi[k] - m.chi[k]).abs() < 1e-14);
            } else {
                assert!(r.q[k].is_nan());
            }
        }
        // Rewriting over an existing file works (atomic rename).
        m.write_fits(&path).unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    /// Every image carries a valid BUNIT and the two WCSs of the binning: read back through
    /// CFITSIO and evaluated with the linear WCS formula `CRVAL + CDELT (p - CRPIX)`, map pixel
    /// `(i + 1, j + 1)` lands on the 1-based detector pixel at the centre of bin `(i, j)`,
    /// `origin + b (i + 1/2) + 1/2`, and on the FORS1 arcmin position of that pixel.
    #[test]
    fn every_image_has_units_and_the_binning_wcs() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.fits");
        let m = sample();
        m.write_fits(&path).unwrap();
        let mut f = FitsFile::open(&path).unwrap();
        let key_s = |f: &mut FitsFile, h: &fitsio::hdu::FitsHdu, k: &str| crate::fits::read_key_str(f, h, k).unwrap();
        let (b, ox, oy) = (30.0, 0.0, 34.0);
        for (name, unit) in [
            ("Q", ""),
            ("SIGMA_U", ""),
            ("P", ""),
            ("CHI", "deg"),
            ("INTENSITY", "electron/pix"),
            ("COVERAGE", "pix"),
            ("VALID", ""),
        ] {
            let h = f.hdu(name).unwrap();
            assert_eq!(key_s(&mut f, &h, "BUNIT"), unit, "{name}");
            assert_eq!(key_s(&mut f, &h, "WCSNAME"), "DETECTOR");
            assert_eq!(key_s(&mut f, &h, "CUNIT1A"), "arcmin");
            let r = |f: &mut FitsFile, k: &str| h.read_key::<f64>(f, k).unwrap();
            for (i, j) in [(0usize, 0usize), (3, 2)] {
                let x = r(&mut f, "CRVAL1") + r(&mut f, "CDELT1") * ((i + 1) as f64 - r(&mut f, "CRPIX1"));
                let y = r(&mut f, "CRVAL2") + r(&mut f, "CDELT2") * ((j + 1) as f64 - r(&mut f, "CRPIX2"));
                assert_eq!(
                    (x, y),
                    (ox + b * (i as f64 + 0.5) + 0.5, oy + b * (j as f64 + 0.5) + 0.5),
                    "{name} {i} {j}"
                );
                let xa = r(&mut f, "CRVAL1A") + r(&mut f, "CDELT1A") * ((i + 1) as f64 - r(&mut f, "CRPIX1A"));
                let ya = r(&mut f, "CRVAL2A") + r(&mut f, "CDELT2A") * ((j + 1) as f64 - r(&mut f, "CRPIX2A"));
                // 100 x 130 px of 0.2": the centre is 0-based pixel (49.5, 64.5).
                let (ex, ey) = ((x - 1.0 - 49.5) * 0.2 / 60.0, (y - 1.0 - 64.5) * 0.2 / 60.0);
                assert!((xa - ex).abs() < 1e-14 && (ya - ey).abs() < 1e-14, "{name}: {xa} {ya} vs {ex} {ey}");
            }
        }
        let ph = f.primary_hdu().unwrap();
        assert_eq!(key_s(&mut f, &ph, "PROGRAM"), "instpol");
        assert_eq!(key_s(&mut f, &ph, "PROGVER"), env!("CARGO_PKG_VERSION"));
        assert_eq!(key_s(&mut f, &ph, "DATE").len(), 19);
    }

    #[test]
    fn bin_centres_match_instrument_convention() {
        let inst = instrument::Instrument::load("fors1").unwrap();
        let g = BinGeometry::covering(30, 0, 34, 2048, 2048, 0.2);
        let (x, y) = g.centre_px(3, 5);
        assert_eq!((x, y), (104.5, 34.0 + 165.0 - 0.5));
        let (ax, ay) = g.centre_arcmin(3, 5);
        let (bx, by) = inst.pixel_to_arcmin(x, y);
        assert!((ax - bx).abs() < 1e-12 && (ay - by).abs() < 1e-12);
        assert_eq!(g.bin_of(104, 199), Some(5 * g.nx + 3));
        assert_eq!(g.bin_of(104, 10), None);
    }

    #[test]
    fn missing_file_and_wrong_file_are_named_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("nope.fits");
        let e = StokesMap::read_fits(&p).unwrap_err().to_string();
        assert!(e.contains("nope.fits"), "{e}");
    }

    /// A map whose valid bins hold a negative error, P > 1 or a covariance larger than the
    /// errors allow is refused naming the file and the bin; the sample itself reads.
    #[test]
    fn unphysical_bins_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        for (what, edit) in [
            ("not finite errors", &(|m: &mut StokesMap| m.sigma_q[1] = -1e-4) as &dyn Fn(&mut StokesMap)),
            ("exceeds 1", &|m: &mut StokesMap| m.q[2] = 1.5),
            ("not a covariance", &|m: &mut StokesMap| m.cov_qu[4] = 1e-6),
        ] {
            let mut m = sample();
            edit(&mut m);
            let path = dir.path().join("bad.fits");
            m.write_fits(&path).unwrap();
            let e = StokesMap::read_fits(&path).unwrap_err().to_string();
            assert!(e.contains("bad.fits") && e.contains(what) && e.contains("bin ("), "{what}: {e}");
        }
        let path = dir.path().join("good.fits");
        sample().write_fits(&path).unwrap();
        StokesMap::read_fits(&path).unwrap();
    }

    /// Each exposure's HWP angle and parallactic-angle track are written as header keywords
    /// (read back here with CFITSIO, in degrees) and read back; a count beyond the keywords
    /// written, an angle that is no number, or a count that is none are refused by name.
    #[test]
    fn exposure_tracks_are_kept_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.fits");
        let mut m = sample();
        let d = f64::to_radians;
        m.exposure_tracks = vec![
            ExposureTrack { hwp_deg: 0.0, start: d(-40.5), end: d(-31.25) },
            ExposureTrack { hwp_deg: 22.5, start: d(-30.0), end: d(-21.0) },
        ];
        m.write_fits(&path).unwrap();
        {
            let mut f = FitsFile::open(&path).unwrap();
            let ph = f.primary_hdu().unwrap();
            assert_eq!(ph.read_key::<i64>(&mut f, "NEXPTRK").unwrap(), 2);
            assert_eq!(ph.read_key::<f64>(&mut f, "XHWP2").unwrap(), 22.5);
            assert!((ph.read_key::<f64>(&mut f, "XPAS1").unwrap() + 40.5).abs() < 1e-12);
            assert!((ph.read_key::<f64>(&mut f, "XPAE1").unwrap() + 31.25).abs() < 1e-12);
        }
        let r = StokesMap::read_fits(&path).unwrap();
        assert_eq!(r.exposure_tracks.len(), 2);
        for (a, b) in r.exposure_tracks.iter().zip(&m.exposure_tracks) {
            assert!(a.hwp_deg == b.hwp_deg && (a.start - b.start).abs() < 1e-15 && (a.end - b.end).abs() < 1e-15);
        }
        let edit = |key: &str, value: &str| {
            let p = dir.path().join(format!("bad_{key}.fits"));
            std::fs::copy(&path, &p).unwrap();
            let mut f = FitsFile::edit(&p).unwrap();
            f.primary_hdu().unwrap();
            let (k, v) = (std::ffi::CString::new(key).unwrap(), std::ffi::CString::new(value).unwrap());
            let mut status = 0;
            // SAFETY: an open file at its primary HDU; NUL-terminated strings (CFITSIO's update,
            // which replaces the card: `write_key` would add a second one after it).
            unsafe { fitsio::sys::ffukys(f.as_raw(), k.as_ptr(), v.as_ptr(), std::ptr::null(), &mut status) };
            assert_eq!(status, 0);
            drop(f);
            StokesMap::read_fits(&p).unwrap_err().to_string()
        };
        let e = edit("NEXPTRK", "3");
        assert!(e.contains("XHWP3") && e.contains("bad_NEXPTRK.fits"), "{e}");
        let e = edit("XPAE2", "north");
        assert!(e.contains("XPAE2") && e.contains("north"), "{e}");
        let e = edit("NEXPTRK", "many");
        assert!(e.contains("NEXPTRK") && e.contains("many"), "{e}");
    }

    /// A circular map written and read back keeps every value (the V plane and its errors, the
    /// plate angles and zero angle); its primary header says STOKES = 'V' (read here with
    /// CFITSIO); the Stokes-map reader refuses it by what it is, with the reason, both as
    /// read_fits and as read_uncorrected; the circular reader refuses a linear map, and an
    /// unknown STOKES value is named.
    #[test]
    fn circular_map_round_trip_and_refusals() {
        let dir = tempfile::tempdir().unwrap();
        let lin = sample();
        let c = CircularMap {
            geometry: lin.geometry.clone(),
            instrument: "FORS_QWP".into(),
            filter: "V".into(),
            plate_angles_deg: vec![-45.0, 45.0],
            qwp_zero_angle_deg: 1.5,
            v: lin.q.iter().map(|q| 0.5 * q).collect(),
            sigma_v: lin.sigma_q.clone(),
            sigma_v_phot: lin.sigma_q_phot.clone(),
            n_pixels: lin.n_pixels.clone(),
            intensity: lin.intensity.clone(),
            intensity_snr: lin.intensity_snr.clone(),
            valid: lin.valid.clone(),
            celestial_wcs: None,
            product: None,
        };
        let path = dir.path().join("vmap.fits");
        c.write_fits(&path).unwrap();
        {
            let mut f = FitsFile::open(&path).unwrap();
            let ph = f.primary_hdu().unwrap();
            assert_eq!(crate::fits::read_key_str(&mut f, &ph, "STOKES").unwrap(), "V");
            assert_eq!(ph.read_key::<f64>(&mut f, "QWPZERO").unwrap(), 1.5);
            assert!(f.hdu("Q").is_err() && f.hdu("V").is_ok() && f.hdu("SIGV_PHOT").is_ok());
        }
        let r = CircularMap::read_fits(&path).unwrap();
        assert_eq!(
            (r.geometry.clone(), r.plate_angles_deg.clone(), r.qwp_zero_angle_deg),
            (c.geometry.clone(), c.plate_angles_deg.clone(), 1.5)
        );
        assert_eq!((r.valid.clone(), r.n_pixels.clone()), (c.valid.clone(), c.n_pixels.clone()));
        for k in (0..c.v.len()).filter(|&k| c.valid[k]) {
            assert_eq!((r.v[k], r.sigma_v[k], r.sigma_v_phot[k]), (c.v[k], c.sigma_v[k], c.sigma_v_phot[k]));
        }
        for e in [StokesMap::read_fits(&path).unwrap_err(), StokesMap::read_uncorrected(&path).unwrap_err()] {
            let e = e.to_string();
            assert!(e.contains("STOKES = 'V'") && e.contains("holds no Q/I, U/I"), "{e}");
        }
        assert_eq!(file_kind(&path).unwrap(), FileKind::StokesMap);
        let lpath = dir.path().join("qmap.fits");
        lin.write_fits(&lpath).unwrap();
        let e = CircularMap::read_fits(&lpath).unwrap_err().to_string();
        assert!(e.contains("qmap.fits") && e.contains("a linear Stokes map"), "{e}");
        // An unknown STOKES value is refused by name.
        let bad = dir.path().join("bad.fits");
        std::fs::copy(&path, &bad).unwrap();
        {
            let mut f = FitsFile::edit(&bad).unwrap();
            f.primary_hdu().unwrap();
            let (k, v) = (std::ffi::CString::new("STOKES").unwrap(), std::ffi::CString::new("I").unwrap());
            let mut status = 0;
            // SAFETY: an open file at its primary HDU; NUL-terminated strings (CFITSIO's update).
            unsafe { fitsio::sys::ffukys(f.as_raw(), k.as_ptr(), v.as_ptr(), std::ptr::null(), &mut status) };
            assert_eq!(status, 0);
        }
        let e = StokesMap::read_fits(&bad).unwrap_err().to_string();
        assert!(e.contains("STOKES") && e.contains("bad.fits"), "{e}");
    }
}
