//! What a caller asks of a calibration file, and the correction that answers it: which models
//! apply, in which frame and over which telescope track, for rows (the stars of a catalog
//! table, or arrays a caller gives: [`plan_rows`]) or a whole Stokes map ([`plan_map`]). The
//! one rule set of `instpol correct` and the Python `Calibration.correct` and `.correct_map`:
//! each face parses its own inputs into a [`Request`], makes the plan once, corrects with it
//! ([`RowsPlan::correct`] for each row, [`MapPlan::correct`] for a map, both through the plan's [`Chain`]) and words the
//! [`Refusal`]s and [`Note`]s its own way.
//!
//! The rules, by what the file holds ([`crate::files::calibration::Kind`]):
//!
//! - **A field model** (`eq:instpol` inverted, or `eq:approx`): the rows are turned from their
//!   frame ([`Request::frame`]) into the sky frame of the calibration's HWP zero angle
//!   ([`mueller::Frame::turn_to`]), then corrected by the [`crate::correction::correct::Corrector`]. Telescope
//!   options given as arguments are refused (they would change nothing); per-row angles that
//!   are data (a catalog's column) are noted as unused.
//! - **A Mueller field**: the same zero angle, then the exact inverse of the fitted block; the
//!   first-order method and telescope options are refused.
//! - **A constant response from standards** (`(q0, u0)`, efficiency and angle offset,
//!   [`crate::response::cal`]): the rows are turned from their frame into the sky frame of the
//!   response's zero angle (a celestial row back by its position angle, given back after), then
//!   the response is inverted exactly, whatever the method asked (it is affine in `(q, u)`:
//!   its first order is itself); telescope options are refused.
//! - **A telescope model** (beside a field model or alone): the rows are turned by the field's
//!   zero angle less the carried one (by nothing without a field: the rows are taken in their
//!   own frame, as the telescope's standards were), then the field and the telescope are undone
//!   in the sky frame ([`crate::telescope::cal`] module docs). The track each row saw is its own
//!   (per-row parallactic angles, with a rotator angle per row or one for all when the model
//!   was fitted with rotator angles), or else one track for every row: given, or recorded by
//!   the catalog, whose recorded exposures are then undone one by one unless a given track
//!   replaced them.
//!
//! A Stokes map is at the plate and its bins share their exposures: it is turned by the field
//! calibration's zero angle (without one, by the zero angle the map records,
//! [`crate::correction::setup::map_zero_angle`]), over the map's one track (given, else recorded) and its
//! recorded exposures. A map of another instrument or filter than the calibration's is refused
//! unless the request allows the mismatch.

use crate::correction::chain::{Chain, FieldStep, RecordedExposures, TelescopeStep, Tracks};
use crate::correction::correct::{CorrectOptions, Corrected, CorrectedMap, MapError, Measurement, Method};
use crate::files::calibration::{CalibrationFile, Kind};
use crate::telescope::{BandChoiceError, TelescopeFit, Track, TrackChoiceError};
use mueller::Frame;

pub use crate::correction::chain::RowError;

/// Each row's parallactic angle (deg), as a catalog's columns or a caller's arrays give them.
#[derive(Debug, Clone, Copy)]
pub struct PerRowAngles<'a> {
    /// The parallactic angle at each row's exposure start (deg).
    pub start_deg: &'a [f64],
    /// At its end (deg), when known: the model is averaged over the track.
    pub end_deg: Option<&'a [f64]>,
    /// The rotator angle of each row (deg), when known.
    pub rotator_deg: Option<&'a [f64]>,
}

/// What the caller asks of a correction of rows.
#[derive(Debug, Clone, Copy)]
pub struct Request<'a> {
    pub method: Method,
    pub allow_extrapolation: bool,
    /// `F` of the inflation rule outside the field ([`CorrectOptions::extrapolation_rel_error`]).
    pub extrapolation_rel_error: f64,
    /// The telescope model's band (default: the field calibration's filter, else the model's
    /// only band; [`TelescopeFit::choose_band`]).
    pub band: Option<&'a str>,
    /// The frame of the rows' `q, u`: at the plate, as measured, or in the sky frame of the HWP
    /// zero angle they carry (a catalog of `instpol catalog`). The rows' measurements say it too
    /// ([`Measurement::frame`]); the plan uses it for its notes and the exposures' plate.
    pub frame: Frame,
    pub per_row: Option<PerRowAngles<'a>>,
    /// One parallactic track for every row, given by the caller (rad); replaces a recorded one.
    pub parang: Option<Track>,
    /// One rotator angle for every row (rad), given by the caller.
    pub rotator: Option<f64>,
    /// The exposures' angles the catalog recorded (`instpol catalog` writes them).
    pub recorded: Option<&'a skyfield::RecordedAngles>,
    /// Whether `per_row` and `recorded` were given as arguments (a caller's arrays) rather
    /// than found in the data (a table's columns and metadata). Without a telescope model
    /// angles given as arguments are refused (they would change nothing) and angles in the data
    /// are noted; arguments may not give both per-row and recorded angles.
    pub angles_are_arguments: bool,
    /// A Stokes map or rows of another instrument or filter (or a band that is not the map's
    /// filter) is corrected all the same.
    pub allow_mismatch: bool,
    /// What the rows are, as their table says ([`skyfield::provenance::Product`]): checked
    /// against the calibration ([`crate::correction::setup::check_compatible`]); `None`: the rows do not
    /// say (a table of other software, a caller's arrays), and nothing is checked.
    pub data: Option<&'a crate::correction::setup::Setup>,
    /// Nothing stated the rows' frame on the sky (a caller's arrays given without the
    /// instrument's position angle): rows of an instrument on a rotator
    /// ([`FrameUnstated`](Refusal::FrameUnstated)) are then refused, not taken in the
    /// instrument's frame. A table says its frame (its product, its `sky_pa_deg` column).
    pub frame_unstated: bool,
}

/// The one rule of the extrapolation inflation's `F` ([`CorrectOptions::extrapolation_rel_error`]):
/// a finite number, 0 or more. `Err` gives the value back for the face to word.
pub fn check_extrapolation_error(f: f64) -> Result<(), f64> {
    if f.is_finite() && f >= 0.0 {
        Ok(())
    } else {
        Err(f)
    }
}

impl Request<'_> {
    /// A request with `method` and the extrapolation rule, and nothing else asked: no band,
    /// track, rotator or per-row angles, rows at the plate, no mismatch allowed.
    pub fn new(method: Method, allow_extrapolation: bool, extrapolation_rel_error: f64) -> Self {
        Request {
            method,
            allow_extrapolation,
            extrapolation_rel_error,
            band: None,
            frame: Frame::Plate,
            per_row: None,
            parang: None,
            rotator: None,
            recorded: None,
            angles_are_arguments: false,
            allow_mismatch: false,
            data: None,
            frame_unstated: false,
        }
    }
}

/// Why rows cannot be corrected as asked. Each face says it in its own words (its option
/// names), from these values.
#[derive(Debug, Clone, PartialEq)]
pub enum Refusal {
    /// Telescope options (band, one track, a rotator, explicit per-row angles) for a file
    /// without a telescope model; `mueller`: the file holds a Mueller field.
    TelescopeOptions { mueller: bool },
    /// The first-order method asked of a Mueller field (inverted exactly only).
    MuellerFirstOrder,
    /// A file with no model at all (one built by hand: the loader refuses such a file).
    NoModel,
    /// A telescope model and neither per-row nor shared nor recorded parallactic angles.
    NoParallactic,
    /// Per-row angles and one track for every row (given or recorded) both given.
    TwoTracks,
    /// A telescope model fitted with rotator angles and the rows' rotator angle unknown.
    NoRotator { per_row: bool },
    /// A per-row array whose length is not the rows'.
    Length { what: &'static str, len: usize, rows: usize },
    /// The telescope model's band cannot be chosen.
    Band(BandChoiceError),
    /// The recorded exposures cannot be prepared (their telescope chain).
    Exposures(String),
    /// A Stokes map (`map`) or rows of another instrument, filter or plate than the
    /// calibration's ([`crate::correction::setup::check_compatible`]).
    Mismatch { map: bool, mismatch: crate::correction::setup::Mismatch },
    /// A Stokes map corrected by a telescope model alone, in a band that is not its filter.
    BandMismatch { map_filter: String, band: String },
    /// Rows of an instrument on a rotator (`[polarimetry.sky_angle]`) whose frame nobody
    /// stated ([`Request::frame_unstated`]): in the instrument's frame or on the sky?
    FrameUnstated { instrument: String },
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::TelescopeOptions { mueller: true } => {
                write!(
                    f,
                    "the telescope options are for calibrations with a telescope model; this one holds a Mueller field"
                )
            }
            Refusal::TelescopeOptions { mueller: false } => {
                write!(f, "the telescope options are for calibrations with a telescope model; this one has none")
            }
            Refusal::NoModel => write!(f, "the calibration holds no model"),
            Refusal::MuellerFirstOrder => {
                write!(f, "a Mueller field is inverted exactly (eq:approx is the p, phi model's first order)")
            }
            Refusal::NoParallactic => write!(f, "the telescope model needs the rows' parallactic angles"),
            Refusal::TwoTracks => write!(f, "per-row parallactic angles and one track for all rows: give one"),
            Refusal::NoRotator { .. } => {
                write!(f, "the telescope model was fitted with rotator angles and the rows' is not known")
            }
            Refusal::Length { what, len, rows } => write!(f, "{what} has {len} values for {rows} rows"),
            Refusal::Band(BandChoiceError::Missing { band, bands, .. }) => {
                write!(f, "band {band} is not one of the telescope model's ({})", bands.join(", "))
            }
            Refusal::Band(BandChoiceError::Ambiguous { bands }) => {
                write!(f, "the telescope model has bands {} and nothing says which", bands.join(", "))
            }
            Refusal::Exposures(e) => write!(f, "the recorded exposures: {e}"),
            Refusal::Mismatch { map, mismatch } => {
                write!(f, "{} and calibration do not fit together: {mismatch}", if *map { "map" } else { "rows" })
            }
            Refusal::BandMismatch { map_filter, band } => {
                write!(f, "a {map_filter} map and the telescope model's band {band}")
            }
            Refusal::FrameUnstated { instrument } => write!(
                f,
                "{instrument} is on a rotator and nothing says whether the rows' q, u are in its frame or turned onto the sky (its catalogs are on the sky, north through east)"
            ),
        }
    }
}

impl std::error::Error for Refusal {}

/// Something the caller should be told about a correction that goes ahead.
#[derive(Debug, Clone, PartialEq)]
pub enum Note {
    /// The rows carry the zero angle `carried` (deg); the calibration's is `calibration`: only
    /// the difference `applied` is turned.
    CarriedZeroAngle { carried: f64, calibration: f64, applied: f64 },
    /// The data have per-row parallactic angles but the file holds no telescope model: the
    /// telescope's polarization is not removed.
    AnglesWithoutTelescope,
    /// The given track replaced the recorded one (rad, start and end), which differs.
    TrackReplaced { recorded: (f64, f64) },
    /// A rotator angle was given but the model was fitted without rotator angles.
    RotatorIgnored,
    /// Data of another instrument, filter or plate than the calibration's, corrected because
    /// the request allows the mismatch: what differs (the output records it).
    MismatchAllowed(crate::correction::setup::Mismatch),
    /// The data and the calibration are of one instrument but were made with two different
    /// instrument files (their BLAKE3, `blake3:<hex>`): corrected, and said, since an edit of
    /// the file may have changed what the calibration assumed.
    InstrumentFileDiffers { data: String, calibration: String },
    /// A map corrected by a telescope model alone records no HWP zero angle and its
    /// instrument gives none: what was taken, in words ([`crate::correction::setup::map_zero_angle`]).
    ZeroAngleUnknown(String),
}

/// The telescope part of a plan, as a face reports it.
#[derive(Debug)]
pub struct TelescopePlan<'a> {
    pub fit: &'a TelescopeFit,
    pub band: String,
    /// How many recorded exposures are undone one by one (0: over a track).
    pub exposures: usize,
}

/// The correction of rows resolved from a file and a request: [`RowsPlan::correct`] undoes
/// one row, in any order and in parallel, through the plan's [`Chain`].
pub struct RowsPlan<'a> {
    pub kind: Kind,
    /// The zero angle (deg) rows in the request's frame are turned by into the sky frame
    /// ([`Frame::turn_to`]; for the report: each row's measurement is turned by its own).
    pub to_sky_deg: f64,
    /// The zero angle (deg) of the plate the exposures were taken through.
    pub plate_deg: f64,
    pub telescope: Option<TelescopePlan<'a>>,
    pub notes: Vec<Note>,
    /// The chain the rows are corrected through.
    pub chain: Chain<'a>,
}

/// The refusals that do not depend on the rows, which a Stokes map's correction makes too: a
/// file without any model, telescope options (a band, one track, a rotator angle, angles given as arguments) for a file
/// without a telescope model, and the first-order method for a Mueller field.
pub fn check_options(file: &CalibrationFile, req: &Request<'_>) -> Result<(), Refusal> {
    if file.field.is_none() && file.telescope.is_none() && file.mueller.is_none() && file.response.is_none() {
        return Err(Refusal::NoModel);
    }
    if file.telescope.is_none() {
        let explicit = req.angles_are_arguments && (req.per_row.is_some() || req.recorded.is_some());
        if req.band.is_some() || req.parang.is_some() || req.rotator.is_some() || explicit {
            return Err(Refusal::TelescopeOptions { mueller: file.mueller.is_some() });
        }
    }
    if file.mueller.is_some() && req.method == Method::FirstOrder {
        return Err(Refusal::MuellerFirstOrder);
    }
    Ok(())
}

/// The one track of rows or of a map that share their exposures: the request's, else the one
/// the data recorded (rad), with the rotator angle where the model was fitted with rotator
/// angles ([`TelescopeFit::choose_track`]); what replaced or went unused is noted.
fn shared_track(
    tel: &TelescopeFit,
    req: &Request<'_>,
    recorded: Option<(f64, f64)>,
    recorded_rotator: Option<f64>,
    notes: &mut Vec<Note>,
) -> Result<Track, Refusal> {
    let c = tel.choose_track(req.parang, recorded, req.rotator, recorded_rotator).map_err(|e| match e {
        TrackChoiceError::NoParallactic => Refusal::NoParallactic,
        TrackChoiceError::NoRotator => Refusal::NoRotator { per_row: false },
    })?;
    if let (Some(r), Some(_)) = (c.replaced, req.parang) {
        notes.push(Note::TrackReplaced { recorded: r });
    }
    if c.rotator_ignored {
        notes.push(Note::RotatorIgnored);
    }
    Ok(c.track)
}

/// Resolve how `n` rows are corrected with `file` as `req` asks.
impl RowsPlan<'_> {
    /// What differed between the input and the calibration when `--allow-mismatch` let it
    /// through (the short form a product records as `MISMATCH`), if anything did.
    pub fn mismatch_allowed(&self) -> Option<String> {
        mismatch_in(&self.notes)
    }

    /// The product a corrected table records: the input's, with the mismatch this plan allowed
    /// (the one rule maps use too).
    pub fn recorded(&self, product: Option<skyfield::provenance::Product>) -> Option<skyfield::provenance::Product> {
        recorded(product, &self.notes)
    }
}

/// What differed between data and calibration when `--allow-mismatch` let it through, among a
/// plan's notes (the short form a product records as `MISMATCH`).
fn mismatch_in(notes: &[Note]) -> Option<String> {
    notes.iter().find_map(|n| match n {
        Note::MismatchAllowed(m) => Some(m.short()),
        _ => None,
    })
}

/// The product corrected data record: the input's (`product`), with the mismatch a plan's
/// `notes` allowed, if any, in place of one it recorded before; data that said nothing of
/// themselves get a product that says only that. `None` when there is nothing to record.
/// Every corrected catalog and map records it through here, whatever its format.
fn recorded(product: Option<skyfield::provenance::Product>, notes: &[Note]) -> Option<skyfield::provenance::Product> {
    match (product, mismatch_in(notes)) {
        (Some(p), None) => Some(p),
        (p, Some(m)) => Some(skyfield::provenance::Product { mismatch_allowed: Some(m), ..p.unwrap_or_default() }),
        (None, None) => None,
    }
}

/// Refuse rows whose frame nobody stated ([`Request::frame_unstated`]) when the calibration's
/// instrument (a built-in one, by the name the file records) is on a rotator: taken in the
/// instrument's frame, rows turned onto the sky would be corrected wrongly by twice the
/// position angle, with no error.
fn check_frame_stated(file: &CalibrationFile, req: &Request<'_>) -> Result<(), Refusal> {
    if !req.frame_unstated || matches!(req.frame, Frame::Celestial { .. }) {
        return Ok(());
    }
    let rotator = instrument::Instrument::load(&file.instrument).is_ok_and(|i| i.polarimetry.sky_angle.is_some());
    if rotator {
        return Err(Refusal::FrameUnstated { instrument: file.instrument.clone() });
    }
    Ok(())
}

pub fn plan_rows<'a>(file: &'a CalibrationFile, req: &Request<'_>, n: usize) -> Result<RowsPlan<'a>, Refusal> {
    check_frame_stated(file, req)?;
    if let Some(p) = &req.per_row {
        for (what, len) in [
            ("the parallactic angles", Some(p.start_deg.len())),
            ("the parallactic angles' ends", p.end_deg.map(<[f64]>::len)),
            ("the rotator angles", p.rotator_deg.map(<[f64]>::len)),
        ] {
            if let Some(len) = len.filter(|&l| l != n) {
                return Err(Refusal::Length { what, len, rows: n });
            }
        }
    }
    let opts = |zero_angle_deg: f64| CorrectOptions {
        method: req.method,
        allow_extrapolation: req.allow_extrapolation,
        extrapolation_rel_error: req.extrapolation_rel_error,
        zero_angle_deg,
    };
    let mut notes = vec![];
    let note_carried = |notes: &mut Vec<Note>, calibration: f64, applied: f64| {
        notes.extend(carried_note(req.frame, calibration, applied));
    };
    check_options(file, req)?;
    if let Some(data) = req.data {
        check_setup(file, req, data, false, &mut notes)?;
    }
    if req.angles_are_arguments && req.per_row.is_some() && req.recorded.is_some() {
        return Err(Refusal::TwoTracks);
    }
    let Some(tel) = &file.telescope else {
        if let Some(r) = &file.response {
            return Ok(response_rows(r, req.frame, notes));
        }
        if let Some(mc) = &file.mueller {
            let (to_sky, plate) = row_zero_angles(Some(mc.hwp_chi_offset_deg), req.frame);
            note_carried(&mut notes, mc.hwp_chi_offset_deg, to_sky);
            return Ok(RowsPlan {
                kind: Kind::Mueller,
                to_sky_deg: to_sky,
                plate_deg: plate,
                telescope: None,
                notes,
                chain: Chain::new(
                    Some(mc.hwp_chi_offset_deg),
                    FieldStep::Mueller(mc, opts(mc.hwp_chi_offset_deg)),
                    None,
                )
                .with_elements(&file.elements),
            });
        }
        let cal = file.field.as_ref().expect("check_options refuses a file without a model");
        if req.per_row.is_some() {
            notes.push(Note::AnglesWithoutTelescope);
        }
        let (to_sky, plate) = row_zero_angles(Some(cal.hwp_chi_offset_deg), req.frame);
        note_carried(&mut notes, cal.hwp_chi_offset_deg, to_sky);
        return Ok(RowsPlan {
            kind: Kind::Field,
            to_sky_deg: to_sky,
            plate_deg: plate,
            telescope: None,
            notes,
            chain: Chain::new(
                Some(cal.hwp_chi_offset_deg),
                FieldStep::partial_polarizer(cal, opts(cal.hwp_chi_offset_deg)),
                None,
            )
            .with_elements(&file.elements),
        });
    };
    let field = file.field.as_ref();
    let models = models_beside(file);
    let band = tel.choose_band(req.band, models.map(|m| m.0), None).map_err(Refusal::Band)?;
    if let Some(d) = req.data.filter(|_| models.is_none() && !req.allow_mismatch) {
        if !crate::correction::setup::band_fits_data(&d.instrument, &d.filter, &band) {
            return Err(Refusal::BandMismatch { map_filter: d.filter.clone(), band });
        }
    }
    let (to_sky, plate) = row_zero_angles(models.map(|m| m.1), req.frame);
    if let Some((_, z)) = models {
        note_carried(&mut notes, z, to_sky);
    }
    let (tracks, exposures) = match &req.per_row {
        Some(p) => {
            if req.parang.is_some() {
                return Err(Refusal::TwoTracks);
            }
            // The rotator angle per row, when the model was fitted with rotator angles: the
            // rows' own, or the one given for all; never an assumed 0. Otherwise the model's
            // offset already holds it.
            let rotator = |i: usize| -> Result<f64, Refusal> {
                if !tel.with_rotator {
                    return Ok(0.0);
                }
                match (p.rotator_deg, req.rotator) {
                    (Some(r), _) => Ok(r[i].to_radians()),
                    (None, Some(r)) => Ok(r),
                    (None, None) => Err(Refusal::NoRotator { per_row: true }),
                }
            };
            let tracks = (0..n)
                .map(|i| {
                    let end = p.end_deg.map(|e| e[i].to_radians());
                    Ok(Track::new(p.start_deg[i].to_radians(), end).with_rotator(rotator(i)?))
                })
                .collect::<Result<Vec<_>, Refusal>>()?;
            (Tracks::PerRow(tracks), 0)
        }
        None => {
            let recorded = req.recorded.and_then(|r| r.parallactic_rad);
            let recorded_rotator = req.recorded.and_then(|r| r.rotator_rad);
            if req.parang.is_none() && recorded.is_none() {
                return Err(Refusal::NoParallactic);
            }
            let track = shared_track(tel, req, recorded, recorded_rotator, &mut notes)?;
            // The recorded exposures, undone as each saw the telescope (their demodulations
            // built once), unless a given track replaced them.
            let exposures: &[skyfield::ExposureTrack] = match (req.parang, req.recorded) {
                (None, Some(r)) => &r.exposure_tracks,
                _ => &[],
            };
            let prepared = RecordedExposures::new(tel, &band, track, exposures, plate.to_radians())
                .map_err(|e| Refusal::Exposures(e.to_string()))?;
            match prepared {
                Some(p) => (Tracks::Exposures(Box::new(p)), exposures.len()),
                None => (Tracks::Shared(track), 0),
            }
        }
    };
    Ok(RowsPlan {
        kind: file.kind(),
        to_sky_deg: to_sky,
        plate_deg: plate,
        telescope: Some(TelescopePlan { fit: tel, band: band.clone(), exposures }),
        notes,
        // The telescope's offset is the instrument's angle zero: the chain turns each row
        // itself, once, into the field's frame before both models (a telescope model alone
        // takes the rows in their own frame).
        chain: Chain::new(
            models.map(|m| m.1),
            field_beside(file, field, &opts),
            Some(TelescopeStep { fit: tel, band, tracks }),
        )
        .with_elements(&file.elements),
    })
}

/// The filter and the HWP zero angle (deg) of the field's frame of the model beside a
/// telescope model in `file`: its field calibration's, else its Mueller field's; `None` for a
/// telescope model alone.
fn models_beside(file: &CalibrationFile) -> Option<(&str, f64)> {
    match (&file.field, &file.mueller) {
        (Some(c), _) => Some((c.filter.as_str(), c.hwp_chi_offset_deg)),
        (None, Some(m)) => Some((m.filter.as_str(), m.hwp_chi_offset_deg)),
        (None, None) => None,
    }
}

/// The field step behind a telescope model: the field calibration `field` (of `file`), else
/// the file's Mueller field (inverted with the telescope through the whole chain), with the
/// options of their zero angle; none for a telescope model alone.
fn field_beside<'a>(
    file: &'a CalibrationFile,
    field: Option<&'a crate::files::calfile::Calibration>,
    opts: &dyn Fn(f64) -> CorrectOptions,
) -> FieldStep<'a> {
    match (field, &file.mueller) {
        (Some(c), _) => FieldStep::partial_polarizer(c, opts(c.hwp_chi_offset_deg)),
        (None, Some(mc)) => FieldStep::Mueller(mc, opts(mc.hwp_chi_offset_deg)),
        (None, None) => FieldStep::None,
    }
}

/// The note for rows in `frame` that carry a zero angle while the calibration's is
/// `calibration` (deg): `applied` (deg) is what is turned; none when nothing is.
fn carried_note(frame: Frame, calibration: f64, applied: f64) -> Option<Note> {
    frame.zero_angle_deg().filter(|_| applied != 0.0).map(|carried| Note::CarriedZeroAngle {
        carried,
        calibration,
        applied,
    })
}

/// The plan of rows in `frame` corrected by a constant response (module docs).
fn response_rows<'a>(r: &'a crate::response::cal::ResponseCal, frame: Frame, mut notes: Vec<Note>) -> RowsPlan<'a> {
    let z = r.hwp_chi_offset_deg;
    let (to_sky, plate) = row_zero_angles(Some(z), frame);
    notes.extend(carried_note(frame, z, to_sky));
    let chain = Chain::new(Some(z), FieldStep::Response(r), None);
    RowsPlan { kind: Kind::Response, to_sky_deg: to_sky, plate_deg: plate, telescope: None, notes, chain }
}

/// The HWP zero angles (deg) of a correction of rows in `frame` by models in the sky frame of
/// the zero angle `models` (`None`: a telescope model alone, which takes the rows in their own
/// frame, as its standards were measured): `(to_sky, plate)`. `to_sky` is the turn the rows
/// get for the zero angle ([`Frame::turn_to`] from the instrument's frame: 0 for a catalog of
/// `instpol catalog` in that frame already; a celestial row's position angle is undone before
/// the models and given back after them, `crate::correction::chain::Chain::invert`); `plate`
/// is the zero angle of the plate the exposures were taken through, for their demodulation
/// (`telescope_cal::telescope_exposures`): the models', else the one the rows carry, else 0.
fn row_zero_angles(models: Option<f64>, frame: Frame) -> (f64, f64) {
    (models.map_or(0.0, |z| frame.in_instrument().turn_to(z)), models.or(frame.zero_angle_deg()).unwrap_or(0.0))
}

impl RowsPlan<'_> {
    /// Correct row `i` (its track, when the rows each have their own): [`Chain::invert`].
    pub fn correct(&self, i: usize, m: &Measurement) -> Result<Corrected, RowError> {
        self.chain.invert(i, m)
    }
}

/// The telescope part of a map's plan: the band, the one track of the map's exposures, and
/// whether its recorded exposures are undone one by one (not when a given track replaced the
/// recorded one).
#[derive(Debug, Clone)]
pub struct MapTelescope<'a> {
    pub fit: &'a TelescopeFit,
    pub band: String,
    pub track: Track,
    pub by_exposure: bool,
}

/// The correction of a Stokes map resolved from a file and a request ([`plan_map`]):
/// [`MapPlan::correct`] undoes every bin through the plan's [`Chain`].
pub struct MapPlan<'a> {
    pub kind: Kind,
    pub method: Method,
    pub telescope: Option<MapTelescope<'a>>,
    /// The HWP zero angle (deg) the map is turned by into the sky frame before a telescope
    /// chain: the field calibration's, else the one the map records.
    pub zero_angle_deg: f64,
    pub notes: Vec<Note>,
    /// The chain every bin is corrected through.
    pub chain: Chain<'a>,
    /// How many recorded exposures the chain undoes one by one (0: over one track).
    pub exposures: usize,
}

/// The words of a method in a corrected map's record.
fn method_words(m: Method) -> &'static str {
    match m {
        Method::Exact => "exact M_I inverse (eq:instpol)",
        Method::FirstOrder => "first order (eq:approx)",
    }
}

impl MapPlan<'_> {
    /// `what` the file's model is inverted by, or, for a file of several field elements, the
    /// whole chain of them by which its record says the map was corrected.
    fn chain_words(&self, what: &str) -> String {
        match self.chain.elements() {
            [] => what.to_string(),
            els => format!("{what}, within the chain of {} field elements inverted together", els.len()),
        }
    }

    /// Correct every valid bin of `map` ([`Chain::invert_map`]), and the record the corrected
    /// map carries ([`skyfield::StokesMap::write_corrected_fits`]; `calibration`: the file's
    /// name). The one map correction of `instpol correct` and the Python package.
    /// - A field: the calibration's HWP zero angle is added to chi (`CORRHWP`).
    /// - A Mueller field: inverted exactly after the zero angle its maps were turned by
    ///   (`CORRHWP`; 0 for maps that recorded none).
    /// - A telescope model: the map is brought into the sky frame by the field calibration's HWP
    ///   zero angle, or without a field by its instrument's (`CORRHWP`), then corrected by both
    ///   models there ([`crate::telescope::cal`] module docs); the corrected map records the
    ///   track used (its parallactic and rotator angles).
    pub fn correct(
        &self,
        map: &skyfield::StokesMap,
        calibration: &str,
    ) -> Result<(CorrectedMap, skyfield::CorrectionStamp), MapError> {
        let mut c = self.chain.invert_map(map)?;
        let stamp = |method: String, hwp: f64, telescope| skyfield::CorrectionStamp {
            calibration: calibration.to_string(),
            method,
            hwp_chi_offset_deg: hwp,
            telescope,
        };
        let s = match (&self.chain.field, &self.telescope) {
            (FieldStep::Mueller(mc, _), None) => stamp(
                format!("exact inverse of the {}", self.chain_words("Mueller field (calibrate-mueller)")),
                mc.hwp_chi_offset_deg,
                None,
            ),
            (FieldStep::PartialPolarizer { .. }, None) => {
                stamp(self.chain_words(method_words(self.method)), self.zero_angle_deg, None)
            }
            (FieldStep::Response(r), _) => stamp(
                "exact inverse of the constant response from standards ((q0, u0), efficiency, angle offset)".into(),
                r.hwp_chi_offset_deg,
                None,
            ),
            (field, Some(t)) => {
                if !t.by_exposure {
                    c.map.exposure_tracks.clear();
                }
                c.map.parallactic_rad = Some((t.track.start, t.track.end));
                if t.fit.with_rotator {
                    c.map.rotator_rad = Some(t.track.rotator);
                }
                let mut method = match field {
                    FieldStep::PartialPolarizer { .. } => {
                        format!("{}, then the telescope", self.chain_words(method_words(self.method)))
                    }
                    FieldStep::Mueller(..) => {
                        "exact inverse of the telescope and the Mueller field (calibrate-mueller) together".into()
                    }
                    _ => "telescope model only".to_string(),
                };
                if self.exposures > 0 {
                    method += &format!(" (exposure by exposure, {})", self.exposures);
                }
                let ts = skyfield::TelescopeStamp {
                    model: t.fit.model.name().to_string(),
                    band: t.band.clone(),
                    rotator_deg: t.track.rotator.to_degrees(),
                };
                stamp(method, self.zero_angle_deg, Some(ts))
            }
            (FieldStep::None, None) => unreachable!("plan_map refuses a file without a model"),
        };
        // The corrected map is in the sky frame, its zero angle applied (CORRHWP): it no longer
        // lacks one (HWPZERO).
        c.map.hwp_zero_angle_deg = None;
        c.map.product = recorded(map.product.clone(), &self.notes);
        Ok((c, s))
    }
}

/// The data's setup against the file's ([`CalibrationFile::setup`]: a
/// telescope model alone is checked by its band apart), unless the request allows a
/// mismatch; two instrument files of one instrument are a note.
fn check_setup(
    file: &CalibrationFile,
    req: &Request<'_>,
    data: &crate::correction::setup::Setup,
    map: bool,
    notes: &mut Vec<Note>,
) -> Result<(), Refusal> {
    use crate::correction::setup::{check_compatible, definition_differs, Mismatch};
    let cal = file.setup();
    let checked = check_compatible(data, Some(&cal)).map_err(|m| match m {
        Mismatch::Setup { data, calibration: (i, f) } if f.is_empty() => {
            Mismatch::Setup { data, calibration: (i, "(a telescope model's band)".into()) }
        }
        m => m,
    });
    if let Some((data, calibration)) = definition_differs(data, &cal) {
        notes.push(Note::InstrumentFileDiffers { data, calibration });
    }
    match checked {
        Ok(()) => Ok(()),
        Err(mismatch) if req.allow_mismatch => {
            notes.push(Note::MismatchAllowed(mismatch));
            Ok(())
        }
        Err(mismatch) => Err(Refusal::Mismatch { map, mismatch }),
    }
}

/// Resolve how the Stokes map `map` is corrected with `file` as `req` asks (module docs; the
/// request's per-row angles, recorded angles and carried zero angle are a table's and not
/// used).
pub fn plan_map<'a>(
    file: &'a CalibrationFile,
    req: &Request<'_>,
    map: &skyfield::StokesMap,
) -> Result<MapPlan<'a>, Refusal> {
    check_options(file, req)?;
    let data = crate::correction::setup::Setup::named(&map.instrument, &map.filter).with_product(map.product.as_ref());
    let mut notes = vec![];
    check_setup(file, req, &data, true, &mut notes)?;
    let kind = file.kind();
    let opts = |method, zero_angle_deg: f64| CorrectOptions {
        method,
        allow_extrapolation: req.allow_extrapolation,
        extrapolation_rel_error: req.extrapolation_rel_error,
        zero_angle_deg,
    };
    let Some(tel) = &file.telescope else {
        // The plan's zero angle (reported; a Mueller field's record states its own) and the
        // zero angle of the frame the model lives in.
        let (zero_angle_deg, model_zero, field) = match (&file.response, &file.mueller, &file.field) {
            (Some(r), _, _) => (r.hwp_chi_offset_deg, r.hwp_chi_offset_deg, FieldStep::Response(r)),
            (None, Some(mc), _) => {
                let z = mc.hwp_chi_offset_deg;
                (0.0, z, FieldStep::Mueller(mc, opts(Method::Exact, z)))
            }
            (None, None, Some(c)) => {
                let z = c.hwp_chi_offset_deg;
                (z, z, FieldStep::partial_polarizer(c, opts(req.method, z)))
            }
            (None, None, None) => unreachable!("check_options refuses a file without a model"),
        };
        let chain = Chain::new(Some(model_zero), field, None).with_elements(&file.elements);
        return Ok(MapPlan { kind, method: req.method, telescope: None, zero_angle_deg, notes, chain, exposures: 0 });
    };
    let field = file.field.as_ref();
    let models = models_beside(file);
    let band = tel.choose_band(req.band, models.map(|m| m.0), Some(&map.filter)).map_err(Refusal::Band)?;
    if models.is_none()
        && !req.allow_mismatch
        && !crate::correction::setup::band_fits_data(&map.instrument, &map.filter, &band)
    {
        return Err(Refusal::BandMismatch { map_filter: map.filter.clone(), band });
    }
    let track = shared_track(tel, req, map.parallactic_rad, map.rotator_rad, &mut notes)?;
    // The map is at the plate: without a field calibration its zero angle is the one it
    // records (HWPZERO), else its instrument's (a built-in one known by the name it records).
    let zero_angle_deg = match models {
        Some((_, z)) => z,
        None => {
            let (z, unknown) = crate::correction::setup::map_zero_angle(map);
            notes.extend(unknown.map(Note::ZeroAngleUnknown));
            z
        }
    };
    let by_exposure = req.parang.is_none();
    // The map's exposures, undone as each saw the telescope (their demodulations built once
    // for every bin), unless a given track replaced them.
    let recorded = if by_exposure { &map.exposure_tracks[..] } else { &[] };
    let prepared = RecordedExposures::new(tel, &band, track, recorded, zero_angle_deg.to_radians())
        .map_err(|e| Refusal::Exposures(e.to_string()))?;
    let (tracks, exposures) = match prepared {
        Some(p) => (Tracks::Exposures(Box::new(p)), recorded.len()),
        None => (Tracks::Shared(track), 0),
    };
    let chain = Chain::new(
        Some(zero_angle_deg),
        field_beside(file, field, &|z| opts(req.method, z)),
        Some(TelescopeStep { fit: tel, band: band.clone(), tracks }),
    )
    .with_elements(&file.elements);
    let telescope = MapTelescope { fit: tel, band, track, by_exposure };
    Ok(MapPlan { kind, method: req.method, telescope: Some(telescope), zero_angle_deg, notes, chain, exposures })
}
