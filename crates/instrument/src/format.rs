//! The frame format of an instrument (`[format]` in its TOML): which HDU holds the image,
//! the chips and where they sit in one detector frame, their prescan and overscan regions,
//! binning, gain, read noise and saturation (numbers, or header keywords that carry them), and
//! the keywords that must agree between the chip files of one exposure.
//!
//! Everything after reading sees one detector image per exposure; this section only says how
//! to make it. An instrument without `[format]` (FORS1's simulated frames) has one image per
//! file, already trimmed, in the units `[detector]` describes.

use serde::{Deserialize, Serialize};

/// A number given in the instrument file, or the header keyword that carries it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum NumberOrKeyword {
    Number(f64),
    Keyword(String),
}

/// How raw frames of an instrument are laid out.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FrameFormat {
    /// HDU of the image when a file holds one chip: "" (automatic: the primary HDU if it
    /// holds an image, else the one image extension), a number (0 = primary) or an EXTNAME.
    /// A file name with CFITSIO's `[n]` / `[NAME]` suffix overrides it.
    pub hdu: String,
    /// Binning the instrument file's geometry is written for, `[x, y]`; frames binned
    /// otherwise are refused. Empty: not checked.
    pub binning: Vec<u32>,
    /// Header keywords that carry the binning, `[x, y]` (checked against `binning`).
    pub binning_keywords: Vec<String>,
    /// Keywords that must be equal in the chip files of one exposure, besides the HWP angle,
    /// filter and exposure time (e.g. an exposure number or the observation date).
    pub exposure_keywords: Vec<String>,
    /// The bias level (ADU) raw frames carry. With it, a frame that is neither corrected from
    /// an overscan region nor by a master bias is refused when its darkest pixels sit at or
    /// above this level (a frame still carrying its bias is never reduced silently).
    pub raw_bias_adu: Option<f64>,
    /// What the frames already had done to them before they reach instpol (an archive's
    /// level-1 products): `"bias"` (bias and dark subtracted) and `"flat"` (divided by a flat
    /// field). Such frames are read without subtracting a constant bias level, and a master bias
    /// or flat given for them is refused unless the caller asks for the correction to be made
    /// again ([`FrameFormat::check_masters`]).
    pub already_corrected: Vec<Correction>,
    /// The chips: none means one chip covering the whole detector with no pre/overscan.
    pub chips: Vec<Chip>,
}

/// A correction an archive's pipeline may already have made to its frames
/// ([`FrameFormat::already_corrected`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Correction {
    /// Bias (and dark) subtracted: a master bias would subtract it a second time.
    Bias,
    /// Divided by a flat field: a master flat would divide by the response a second time.
    Flat,
}

impl Correction {
    /// The correction's name in the instrument file (`"bias"`, `"flat"`).
    pub fn name(self) -> &'static str {
        match self {
            Correction::Bias => "bias",
            Correction::Flat => "flat",
        }
    }
}

/// One CCD of a mosaic (or the only one).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Chip {
    pub name: String,
    /// A header keyword whose value identifies this chip's file (chips in separate files)...
    #[serde(default)]
    pub match_keyword: Option<String>,
    #[serde(default)]
    pub match_value: Option<String>,
    /// ...or the HDU (number or EXTNAME) holding this chip in a multi-extension file.
    #[serde(default)]
    pub hdu: Option<String>,
    /// Where the chip's trimmed image starts in the detector frame, `[x, y]` (0-based, binned
    /// px); detector pixels no chip covers are the gap (masked).
    pub origin_px: [usize; 2],
    /// Size of the trimmed image `[nx, ny]` (binned px).
    pub size_px: [usize; 2],
    /// Columns before / after the image and rows below / above it (binned px, or keywords).
    #[serde(default)]
    pub prescan_x: Option<NumberOrKeyword>,
    #[serde(default)]
    pub overscan_x: Option<NumberOrKeyword>,
    #[serde(default)]
    pub prescan_y: Option<NumberOrKeyword>,
    #[serde(default)]
    pub overscan_y: Option<NumberOrKeyword>,
    /// Subtract the robust mean of the prescan and overscan pixels (default true); false: the
    /// regions are only trimmed (an instrument whose extra pixels do not measure the bias).
    #[serde(default = "yes")]
    pub subtract_overscan: bool,
    /// e-/ADU (default: `detector.gain_e_per_adu`).
    #[serde(default)]
    pub gain_e_per_adu: Option<NumberOrKeyword>,
    /// e- (default: `detector.read_noise_e`).
    #[serde(default)]
    pub read_noise_e: Option<NumberOrKeyword>,
    /// Raw ADU at and above which a pixel is saturated (default: `detector.saturation_adu`).
    #[serde(default)]
    pub saturation_adu: Option<f64>,
}

fn yes() -> bool {
    true
}

impl FrameFormat {
    /// True when frames need more than reading: chips to trim and place, or a bias level to
    /// check.
    pub fn is_raw(&self) -> bool {
        !self.chips.is_empty() || self.raw_bias_adu.is_some()
    }

    /// Whether the frames already had `c` done to them ([`FrameFormat::already_corrected`]).
    pub fn already(&self, c: Correction) -> bool {
        self.already_corrected.contains(&c)
    }

    /// The rule for calibration frames given for frames of this format: a master bias
    /// (`bias_given`) or flat (`flat_given`) for frames that already had that correction is
    /// refused, unless `again` (the caller asks for the correction to be made a second time).
    /// `Err` names the correction, the instrument (`inst_name`) and the way to ask.
    ///
    /// ```
    /// use instrument::{Correction, FrameFormat};
    /// let f = FrameFormat { already_corrected: vec![Correction::Bias, Correction::Flat], ..Default::default() };
    /// assert!(f.check_masters("MOPTOP", true, false, false).unwrap_err().contains("already bias corrected"));
    /// assert!(f.check_masters("MOPTOP", false, true, true).is_ok());
    /// assert!(FrameFormat::default().check_masters("FORS2", true, true, false).is_ok());
    /// ```
    pub fn check_masters(
        &self,
        inst_name: &str,
        bias_given: bool,
        flat_given: bool,
        again: bool,
    ) -> Result<(), String> {
        if again {
            return Ok(());
        }
        let given =
            [(bias_given, Correction::Bias, "subtract a bias"), (flat_given, Correction::Flat, "divide by a flat")];
        match given.into_iter().find(|(g, c, _)| *g && self.already(*c)) {
            None => Ok(()),
            Some((_, c, what)) => Err(format!(
                "instrument {inst_name}'s frames are already {} corrected ([format] already_corrected = [{}]): a master {} would {what} a second time; leave it out, or ask for the correction again (--correct-again)",
                c.name(),
                self.already_corrected.iter().map(|c| format!("\"{}\"", c.name())).collect::<Vec<_>>().join(", "),
                c.name()
            )),
        }
    }

    /// Check the section against the detector size `nx` x `ny`; `Err((key, value, why))`.
    pub(crate) fn check(&self, nx: usize, ny: usize) -> Result<(), (String, String, String)> {
        let bad = |k: &str, v: String, w: &str| Err((format!("format.{k}"), v, w.to_string()));
        if !self.binning.is_empty() && (self.binning.len() != 2 || self.binning.contains(&0)) {
            return bad("binning", format!("{:?}", self.binning), "must be [x, y] with both >= 1");
        }
        if !self.binning_keywords.is_empty() && (self.binning_keywords.len() != 2 || self.binning.is_empty()) {
            return bad(
                "binning_keywords",
                format!("{:?}", self.binning_keywords),
                "must be [x keyword, y keyword], with format.binning saying the expected binning",
            );
        }
        if let Some(b) = self.raw_bias_adu {
            if !b.is_finite() {
                return bad("raw_bias_adu", b.to_string(), "must be a number of ADU");
            }
        }
        let by_keyword = self.chips.iter().filter(|c| c.match_keyword.is_some()).count();
        if self.chips.len() > 1 && by_keyword != 0 && by_keyword != self.chips.len() {
            return bad(
                "chips",
                format!("{} chips", self.chips.len()),
                "either every chip is found by match_keyword (one file per chip) or none (chips as HDUs of one file)",
            );
        }
        for (i, c) in self.chips.iter().enumerate() {
            let k = format!("chips.{}", c.name);
            if c.match_keyword.is_some() != c.match_value.is_some() {
                return bad(&k, c.name.clone(), "match_keyword and match_value go together");
            }
            if c.match_keyword.is_some() && c.hdu.is_some() {
                return bad(&k, c.name.clone(), "give match_keyword or hdu, not both");
            }
            if self.chips.len() > 1 && c.match_keyword.is_none() && c.hdu.is_none() {
                return bad(&k, c.name.clone(), "a chip of a mosaic needs match_keyword/match_value or hdu");
            }
            let [x0, y0] = c.origin_px;
            let [cx, cy] = c.size_px;
            if cx == 0
                || cy == 0
                || x0.checked_add(cx).is_none_or(|e| e > nx)
                || y0.checked_add(cy).is_none_or(|e| e > ny)
            {
                return bad(
                    &format!("{k}.origin_px/size_px"),
                    format!("{:?} + {:?}", c.origin_px, c.size_px),
                    &format!("the chip must lie inside the {nx} x {ny} detector"),
                );
            }
            for (n, v) in [
                ("prescan_x", &c.prescan_x),
                ("overscan_x", &c.overscan_x),
                ("prescan_y", &c.prescan_y),
                ("overscan_y", &c.overscan_y),
            ] {
                if let Some(NumberOrKeyword::Number(x)) = v {
                    if !(x.fract() == 0.0 && *x >= 0.0 && *x < 1e6) {
                        return bad(&format!("{k}.{n}"), x.to_string(), "must be a whole number of px or a keyword");
                    }
                }
            }
            for (n, v) in [("gain_e_per_adu", &c.gain_e_per_adu), ("read_noise_e", &c.read_noise_e)] {
                if let Some(NumberOrKeyword::Number(x)) = v {
                    if !(x.is_finite() && *x >= 0.0 && (n != "gain_e_per_adu" || *x > 0.0)) {
                        return bad(&format!("{k}.{n}"), x.to_string(), "must be a positive number or a keyword");
                    }
                }
            }
            if let Some(s) = c.saturation_adu {
                if !(s.is_finite() && s > 0.0) {
                    return bad(&format!("{k}.saturation_adu"), s.to_string(), "must be a positive number");
                }
            }
            // Chips are rectangles: two overlap when their spans overlap on both axes (a
            // per-pixel coverage map of the detector took 2 ms of every command's start).
            for o in &self.chips[..i] {
                let (xa, xb) = (x0.max(o.origin_px[0]), (x0 + cx).min(o.origin_px[0] + o.size_px[0]));
                let (ya, yb) = (y0.max(o.origin_px[1]), (y0 + cy).min(o.origin_px[1] + o.size_px[1]));
                if xa < xb && ya < yb {
                    return bad(&k, c.name.clone(), &format!("overlaps chip {} at pixel ({xa}, {ya})", o.name));
                }
            }
        }
        Ok(())
    }
}
