//! The sky maps of a Mueller-field calibration as its fields: each map read, turned into the
//! sky frame of its known polarization by the HWP zero angle it records
//! ([`crate::models::pipeline::map_to_sky_frame`]), and the one rule that they fit together:
//! one zero angle, one setup by the one compatibility check
//! ([`crate::correction::setup::check_compatible`]: instrument, filter, plate, detector) and
//! one system of field coordinates. `instpol calibrate-mueller` reads its `--field` maps here.

use crate::correction::setup::{check_compatible, Mismatch, Setup};
use crate::mueller_field::{observations_of_map, CalField};
use std::path::{Path, PathBuf};

/// One field: its map and the sky's known polarization there (fraction, degrees) with its
/// error (fraction).
#[derive(Debug, Clone, PartialEq)]
pub struct FieldMap {
    pub path: PathBuf,
    pub p: f64,
    pub chi_deg: f64,
    pub sigma: f64,
}

/// The fields of the maps, in the sky frame, with what they share.
#[derive(Debug, Clone)]
pub struct MapFields {
    pub fields: Vec<CalField>,
    /// The first map's setup, with what its product records (instrument file, plate,
    /// detector): the calibration's.
    pub setup: Setup,
    pub coords: field::FieldCoords,
    /// The detector's half width and half height (arcmin) the maps cover.
    pub half_field_arcmin: (f64, f64),
    /// The HWP zero angle every map records (deg; 0 when none does).
    pub zero_angle_deg: f64,
}

/// Why the maps cannot be the fields of one calibration; each names its files.
#[derive(Debug, thiserror::Error)]
pub enum MapsError {
    #[error("no field map")]
    NoMap,
    #[error("reading {}: {source}", .path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: skyfield::Error,
    },
    #[error("{}: records an HWP zero angle of {} (HWPZERO), but {} records {}: fit the maps of one instrument and filter together", .path.display(), says(*.this), .first.display(), says(*.theirs))]
    ZeroAngle { path: PathBuf, this: Option<f64>, first: PathBuf, theirs: Option<f64> },
    #[error("{}: the Stokes map has no valid bin", .0.display())]
    Empty(PathBuf),
    /// Each side's instrument and filter, and what differs.
    #[error("{}: a {} {} map, but {} is {} {} ({mismatch}): fit the fields of one instrument and filter together", .path.display(), .this.0, .this.1, .first.display(), .theirs.0, .theirs.1)]
    Mixed { path: PathBuf, this: (String, String), first: PathBuf, theirs: (String, String), mismatch: Mismatch },
    #[error("{}: its field coordinates (centre, scale) are not those of {}: fit the fields of one detector together", .path.display(), .first.display())]
    Coords { path: PathBuf, first: PathBuf },
}

fn says(z: Option<f64>) -> String {
    z.map_or("none (taken as 0 deg)".to_string(), |z| format!("{z} deg"))
}

/// Read the maps of `specs` as the fields of one Mueller-field calibration (module docs).
pub fn read_field_maps(specs: &[FieldMap]) -> Result<MapFields, MapsError> {
    let mut fields = Vec::with_capacity(specs.len());
    // The first map's: its zero angle as recorded, setup, coordinates and detector's half size.
    let mut first: Option<(Option<f64>, Setup, field::FieldCoords, (f64, f64), &Path)> = None;
    for s in specs {
        let path = s.path.as_path();
        let map = skyfield::maps::StokesMap::read_uncorrected(path)
            .map_err(|source| MapsError::Read { path: path.to_path_buf(), source })?;
        let setup = Setup::named(&map.instrument, &map.filter).with_product(map.product.as_ref());
        let coords = map.geometry.field_coords();
        let g = &map.geometry;
        let arcmin = g.pixel_scale_arcsec / 60.0;
        let half = (0.5 * g.detector_nx as f64 * arcmin, 0.5 * g.detector_ny as f64 * arcmin);
        match &first {
            None => first = Some((map.hwp_zero_angle_deg, setup, coords, half, path)),
            Some((z0, s0, c0, _, p0)) => {
                if z0.unwrap_or(0.0) != map.hwp_zero_angle_deg.unwrap_or(0.0) {
                    return Err(MapsError::ZeroAngle {
                        path: path.to_path_buf(),
                        this: map.hwp_zero_angle_deg,
                        first: p0.to_path_buf(),
                        theirs: *z0,
                    });
                }
                if let Err(mismatch) = check_compatible(&setup, Some(s0)) {
                    let names = |s: &Setup| (s.instrument.clone(), s.filter.clone());
                    let (this, first, theirs) = (names(&setup), p0.to_path_buf(), names(s0));
                    return Err(MapsError::Mixed { path: path.to_path_buf(), this, first, theirs, mismatch });
                }
                if &coords != c0 {
                    return Err(MapsError::Coords { path: path.to_path_buf(), first: p0.to_path_buf() });
                }
            }
        }
        let z = map.hwp_zero_angle_deg.unwrap_or(0.0);
        let map = crate::models::pipeline::map_to_sky_frame(&map, z.to_radians());
        let obs = observations_of_map(&map);
        if obs.is_empty() {
            return Err(MapsError::Empty(path.to_path_buf()));
        }
        fields.push(CalField::from_p_chi(&path.display().to_string(), s.p, s.chi_deg, s.sigma, obs));
    }
    let (z, setup, coords, half_field_arcmin, _) = first.ok_or(MapsError::NoMap)?;
    Ok(MapFields { fields, setup, coords, half_field_arcmin, zero_angle_deg: z.unwrap_or(0.0) })
}
