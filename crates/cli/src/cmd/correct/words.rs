//! `instpol correct`'s words: its refusals and notes as the command says them (the library
//! decides them: `fit::correction::request::Refusal`, `fit::correction::request::Note`).

use anyhow::anyhow;
use fit::correction::columns::PARANG_COLUMNS as PARANG;
use skyfield::table::Table;
use skyfield::table::ZERO_ANGLE_COLUMN as ZERO_ANGLE;
use std::path::Path;

/// A refusal of `fit::correction::request` in this command's words (`table`: the catalog, for the names of its
/// columns).
pub(super) fn rows_error(
    cal_path: &Path,
    input: &Path,
    table: Option<&Table>,
    e: fit::correction::request::Refusal,
) -> anyhow::Error {
    use fit::correction::request::Refusal as E;
    let (cal, input) = (cal_path.display(), input.display());
    match e {
        E::TelescopeOptions { mueller } => anyhow!(
            "--band, --parang, --rotator are for calibrations with a telescope model; {cal} {}",
            if mueller { "holds a Mueller field" } else { "has none" }
        ),
        E::MuellerFirstOrder => anyhow!(
            "--method first-order: {cal} holds a Mueller field, which is inverted exactly (eq:approx is the p, phi model's first order)"
        ),
        E::NoParallactic if table.is_none() => anyhow!(
            "{input}: a Stokes map needs the parallactic angle of its exposures for the telescope model of {cal}: give --parang START[,END] (deg: the first frame's start, the last frame's end, as their headers say; instpol reduce records it in the map when the instrument's [telescope] section names the header keywords)"
        ),
        E::NoParallactic => anyhow!(
            "{input}: no column '{}' (columns: {}) and no recorded parallactic angles: the telescope model of {cal} needs each row's parallactic angle (deg), or --parang START[,END] when every row comes from the same frames (instpol catalog records them in ECSV, FITS and VOTable outputs when the instrument's [telescope] section names the header keywords)",
            PARANG[0],
            table.map_or(String::new(), |t| t.names().join(", "))
        ),
        E::TwoTracks => anyhow!(
            "{input} has a {} column and --parang is given: use one (the column gives each row's angle)",
            PARANG[0]
        ),
        E::NoRotator { per_row: true } => anyhow!(
            "{input}: no column 'rotator_deg': the telescope model of {cal} was fitted with rotator angles and needs each row's (or --rotator DEG for all)"
        ),
        E::NoRotator { per_row: false } => {
            anyhow!("the telescope model of {cal} was fitted with rotator angles: give the exposures' with --rotator DEG")
        }
        E::Band(b) => crate::util::band_choice_error(b, cal_path, None),
        E::Exposures(m) => anyhow!("{input}: its exposures: {m}"),
        E::Mismatch { map, mismatch: fit::correction::setup::Mismatch::Setup { data, calibration } } => anyhow!(
            "{input} is a {} {} {} but {cal} calibrates {} {} (instrument, filter): use the calibration of the {}'s instrument and filter (or --allow-mismatch)",
            data.0,
            data.1,
            if map { "map" } else { "catalog" },
            calibration.0,
            calibration.1,
            if map { "map" } else { "catalog" },
        ),
        E::Mismatch { mismatch, .. } => anyhow!("{input} and {cal}: {mismatch}"),
        E::BandMismatch { map_filter, band } => anyhow!(
            "{input} is a {map_filter} map but the telescope model's band is {band}: use the band of the map's filter (--band), or --allow-mismatch"
        ),
        e => anyhow!("{input}: {e}"),
    }
}

/// Say what `fit::correction::request` noted about a correction that goes ahead.
pub(super) fn print_notes(cal: &Path, input: &Path, parang: Option<&str>, notes: &[fit::correction::request::Note]) {
    use fit::correction::request::Note;
    let (cal, input) = (cal.display(), input.display());
    for n in notes {
        match n {
            Note::CarriedZeroAngle { carried, calibration, applied } => eprintln!(
                "warning: {input}: q, u carry the HWP zero angle {carried} deg (column '{ZERO_ANGLE}') but {cal} records {calibration} deg: the rows are turned by the difference, {applied} deg, into the calibration's frame (every chi0 moves by it); if the catalog's zero angle is the right one, remake the calibration with it (import-map --zero-angle, or the instrument file's hwp_chi_offset_deg; see {})",
                instrument::ZERO_ANGLE_GUIDE
            ),
            Note::AnglesWithoutTelescope => eprintln!(
                "warning: {input} has a {} column but {cal} holds no telescope model: the telescope's polarization is NOT removed (fit one with instpol fit-standards --output)",
                PARANG[0]
            ),
            Note::TrackReplaced { recorded: (s, e) } => eprintln!(
                "warning: --parang {} replaces the parallactic angle {input} recorded ({:.3} to {:.3} deg)",
                parang.unwrap_or(""),
                s.to_degrees(),
                e.to_degrees()
            ),
            Note::ZeroAngleUnknown(w) => eprintln!("warning: {input}: {w}"),
            Note::InstrumentFileDiffers { data, calibration } => eprintln!(
                "warning: {input} and {cal} are of one instrument but were made with two different instrument files ({data} and {calibration}, BLAKE3): corrected; if the file's geometry, strips or zero angles changed between them, remake the calibration"
            ),
            Note::MismatchAllowed(m) => eprintln!(
                "warning: --allow-mismatch: {input} and {cal} do not fit together ({m}); corrected all the same, and a catalog written records it (MISMATCH)"
            ),

            Note::RotatorIgnored => eprintln!(
                "warning: --rotator is ignored: the telescope model of {cal} was fitted without rotator angles (its offset holds the rotator's)"
            ),
        }
    }
}

/// A map correction's failure, naming the map.
pub(super) fn map_error(e: fit::correction::correct::MapError, input: &Path) -> anyhow::Error {
    match e {
        fit::correction::correct::MapError::NoValidBins => anyhow!("{}: {e}", input.display()),
        e => anyhow!("{} {e}", input.display()),
    }
}

/// What a summary counts: a map's bins or a table's rows.
pub(super) fn what_counted(s: &fit::correction::columns::Report) -> &'static str {
    if s.kind == "Stokes map" {
        "bins"
    } else {
        "rows"
    }
}

/// The warning for corrected positions outside the model's field (`field`: which).
pub(super) fn warn_extrapolated(s: &fit::correction::columns::Report, field: &str) {
    if s.extrapolated > 0 {
        eprintln!(
            "warning: {} of {} positions lie outside the {field}; corrected by extrapolation with inflated errors (flagged)",
            s.extrapolated, s.rows
        );
    }
    if s.unmeasured > 0 {
        eprintln!(
            "note: {} of {} rows were not measured (q, u empty: flagged stars); they are passed through with empty corrected columns",
            s.unmeasured, s.rows
        );
    }
}

/// What a correction's summary adds for a file whose field model is not inverted on its own:
/// the number of field elements inverted together, a telescope model before a Mueller field.
pub(super) fn chain(loaded: &fit::files::calibration::CalibrationFile) -> String {
    let mut out = String::new();
    if !loaded.elements.is_empty() {
        out += &format!(", within the chain of {} field elements inverted together", loaded.elements.len());
    }
    if loaded.mueller.is_some() && loaded.telescope.is_some() {
        out += ", behind the telescope model (inverted together)";
    }
    out
}
