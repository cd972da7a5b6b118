//! The masked strips of a strip mask as evidence of a level left in plain frames.
//!
//! Behind a focal-plane strip mask (FORS, EFOSC2, ALFOSC) the detector lines between the
//! strips' o and e images receive no light from the sky. In a calibrated frame, once the
//! instrument's bias (`[detector] bias_adu`) is taken off, they sit at zero within the read
//! noise. A pedestal still in the frames (a bias never subtracted, a wrong `bias_adu`) adds the
//! same level to both beams, so `F = (f_o - f_e) / (f_o + f_e)` (eq:F) and with it every `P` of
//! the map is low by the pedestal's fraction of the strips' level: 4 % low for a 200 ADU
//! pedestal under a 5000 ADU sky. The masked lines show it, and the reduction of a map looks.
//!
//! Raw chip files are not checked here: their bias is measured from their overscan or taken from
//! a master bias ([`crate::calib`]). Stars' photometry subtracts a local sky, pedestal included,
//! so catalogs need no such check.

use crate::beams::{BeamGeometry, PixelKind};
use crate::{Error, Warning};
use instrument::Layout;
use std::path::Path;
use stokes::stats::robust::{self, Middle};

/// Detector lines sampled per kind (deep-masked, strip): enough for a median good to a small
/// fraction of the read noise over a FORS-size detector, few enough to read in a millisecond.
const SAMPLE_LINES: usize = 16;

/// A masked pixel counts as dark only this many lines (along the strip axis) from the nearest
/// o or e line: the mask's edge and the stars' wings spill light into the first masked lines.
const EDGE_LINES: usize = 3;

/// A masked level above this fraction of the strips' level is refused: P would be that much
/// low. Scattered light under a focal-plane mask is well under it, a forgotten bias far above.
pub const REFUSE_FRACTION: f64 = 0.02;

/// A masked level above this fraction (and below [`REFUSE_FRACTION`]) is reported.
pub const WARN_FRACTION: f64 = 0.005;

/// The levels of the masked and of the open lines of one frame (its values less the bias).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Levels {
    /// Median of the deep-masked pixels sampled.
    pub masked: f64,
    /// Median of the o and e pixels sampled.
    pub strips: f64,
    /// Pixels behind `masked`.
    pub n_masked: usize,
}

/// The detector rows whose pixels [`levels`] reads: up to 16 rows holding
/// deep-masked pixels and as many holding o or e pixels (the same rows when the strips run
/// along y: every row holds both). Empty for layouts without a mask.
pub fn sample_rows(g: &BeamGeometry) -> Vec<usize> {
    if g.layout != Layout::Strips || g.strips.is_empty() {
        return Vec::new();
    }
    let pick = |rows: Vec<usize>| -> Vec<usize> {
        let n = rows.len();
        if n <= SAMPLE_LINES {
            return rows;
        }
        (0..SAMPLE_LINES).map(|k| rows[(2 * k + 1) * n / (2 * SAMPLE_LINES)]).collect()
    };
    if !g.along_y {
        return pick((0..g.ny).collect());
    }
    let deep: Vec<usize> = (0..g.ny).filter(|&y| deep_masked(g, 0, y)).collect();
    let open: Vec<usize> = (0..g.ny).filter(|&y| matches!(g.kind(0, y), PixelKind::Ordinary(_))).collect();
    let mut rows = pick(deep);
    rows.extend(pick(open));
    rows.sort_unstable();
    rows.dedup();
    rows
}

/// Whether pixel `(x, y)` is masked and at least `EDGE_LINES` lines from any o or e line.
fn deep_masked(g: &BeamGeometry, x: usize, y: usize) -> bool {
    let e = EDGE_LINES as i64;
    (-e..=e).all(|d| {
        let (xx, yy) = if g.along_y { (x as i64, y as i64 + d) } else { (x as i64 + d, y as i64) };
        if xx < 0 || yy < 0 || xx >= g.nx as i64 || yy >= g.ny as i64 {
            return d != 0;
        }
        g.kind(xx as usize, yy as usize) == PixelKind::Masked
    })
}

/// The masked and open levels of the rows `rows` (`(y, values)` of [`sample_rows`]), their
/// values less `bias`; values not finite or at or above `saturation` are left out. `None` when
/// either kind has no usable pixel.
pub fn levels(g: &BeamGeometry, rows: &[(usize, &[f64])], bias: f64, saturation: f64) -> Option<Levels> {
    let (mut masked, mut open) = (Vec::new(), Vec::new());
    for &(y, v) in rows {
        for (x, &a) in v.iter().enumerate().take(g.nx) {
            if !(a.is_finite() && a < saturation) {
                continue;
            }
            match g.kind(x, y) {
                PixelKind::Ordinary(_) | PixelKind::Extraordinary(_) => open.push(a - bias),
                PixelKind::Masked if deep_masked(g, x, y) => masked.push(a - bias),
                _ => {}
            }
        }
    }
    if masked.is_empty() || open.is_empty() {
        return None;
    }
    let n_masked = masked.len();
    Some(Levels {
        masked: robust::median(&mut masked, Middle::Mean),
        strips: robust::median(&mut open, Middle::Mean),
        n_masked,
    })
}

/// What the levels of `path` say: an error when the masked lines sit above [`REFUSE_FRACTION`]
/// of the strips' level, a warning above [`WARN_FRACTION`], nothing otherwise (or when the
/// strips hold no light to compare with). Plain frames' values, and so the levels, are ADU.
pub fn judge(path: &Path, l: &Levels, bias: f64) -> Result<Option<Warning>, Error> {
    if !(l.strips > 0.0) || !(l.masked > 0.0) {
        return Ok(None);
    }
    let f = l.masked / l.strips;
    let what = format!(
        "the masked strips, which receive no light, sit at {:.1} ADU above the instrument's bias of {bias} ADU: {:.1} % of the strips' level of {:.1} ADU, so P would be {:.1} % low",
        l.masked,
        100.0 * f,
        l.strips,
        100.0 * f
    );
    if f > REFUSE_FRACTION {
        return Err(Error::Invalid(format!(
            "{}: {what}. The frame still carries a bias or pedestal: subtract it, reduce the raw frames (their overscan or a master bias), or state it as the instrument file's [detector] bias_adu",
            path.display()
        )));
    }
    if f > WARN_FRACTION {
        return Ok(Some(Warning {
            file: Some(path.into()),
            message: format!("{what} (a bias left in the frame, or scattered light)"),
        }));
    }
    Ok(None)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A strip-mask geometry of the built-in FORS1 file, shrunk: the sample holds rows of both
    /// kinds, and a flat 200 ADU pedestal under a 5000 ADU sky is measured as such and refused
    /// (4 %), 10 ADU is reported (0.2 %: not even a warning), 50 ADU warned (1 %).
    #[test]
    fn a_pedestal_is_measured_from_the_masked_lines() {
        let inst = instrument::Instrument::load("fors1").unwrap();
        let g = BeamGeometry::new(&inst);
        let rows = sample_rows(&g);
        assert!(!rows.is_empty() && rows.len() <= 2 * SAMPLE_LINES);
        let frame = |pedestal: f64| -> Vec<(usize, Vec<f64>)> {
            rows.iter()
                .map(|&y| {
                    let v = (0..g.nx)
                        .map(|x| match g.kind(x, y) {
                            PixelKind::Masked => pedestal,
                            _ => 5000.0 + pedestal,
                        })
                        .collect();
                    (y, v)
                })
                .collect()
        };
        let judge_of = |p: f64| {
            let f = frame(p);
            let r: Vec<(usize, &[f64])> = f.iter().map(|(y, v)| (*y, &v[..])).collect();
            let l = levels(&g, &r, 0.0, f64::INFINITY).unwrap();
            assert_eq!(l.masked, p);
            assert_eq!(l.strips, 5000.0 + p);
            judge(Path::new("f.fits"), &l, 0.0)
        };
        let e = judge_of(200.0).unwrap_err().to_string();
        assert!(e.contains("f.fits") && e.contains("200.0 ADU") && e.contains("3.8 %"), "{e}");
        assert!(judge_of(10.0).unwrap().is_none());
        assert!(judge_of(50.0).unwrap().unwrap().message.contains("1.0 %"));
        assert!(judge_of(0.0).unwrap().is_none());
    }
}
