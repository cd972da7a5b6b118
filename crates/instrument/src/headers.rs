//! How an instrument's headers say what a file is: the optional `[headers]` table of an
//! instrument file, read by `workflow::night::scan` to sort a folder of raw files (bias, flat,
//! polarimetric exposure, standard) without a person.
//!
//! A file's *role string* is the values of `role_keywords` joined by `/` in the order given
//! (ESO: `DPR CATG`/`DPR TYPE`/`DPR TECH`, e.g. `CALIB/BIAS/IMAGE`); each role lists patterns
//! matched against it, `*` standing for any run of characters (`SCIENCE/OBJECT/*POLARIMETRY*`).
//! An instrument whose headers carry one type keyword (`IMAGETYP`) lists that one keyword and
//! its values (`bias = ["BIAS", "ZERO"]`).

use serde::{Deserialize, Serialize};

/// The `[headers]` table (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Headers {
    /// The keyword naming the instrument that wrote a file (FITS `INSTRUME`).
    #[serde(default = "default_instrument_keyword")]
    pub instrument_keyword: String,
    /// Its values meaning this instrument (case-insensitive); empty: any value is accepted.
    #[serde(default)]
    pub instrument_values: Vec<String>,
    /// The keywords whose values, joined by `/`, make a file's role string (module docs).
    pub role_keywords: Vec<String>,
    /// Role-string patterns of a bias frame.
    #[serde(default)]
    pub bias: Vec<String>,
    /// Role-string patterns of a flat field.
    #[serde(default)]
    pub flat: Vec<String>,
    /// Role-string patterns of a polarimetric exposure of a science target (or an empty field).
    #[serde(default)]
    pub polarimetry: Vec<String>,
    /// Role-string patterns of a polarimetric exposure of a standard star (a target matched to
    /// the standards list by name or position is a standard whatever its role string says).
    #[serde(default)]
    pub standard: Vec<String>,
    /// The keyword of the target's name.
    #[serde(default = "default_target_keyword")]
    pub target_keyword: String,
    /// The keywords of the pointing's right ascension and declination (deg).
    #[serde(default = "default_ra_keyword")]
    pub ra_keyword: String,
    #[serde(default = "default_dec_keyword")]
    pub dec_keyword: String,
    /// The keyword of the exposure's start, a Modified Julian Date.
    #[serde(default = "default_mjd_keyword")]
    pub mjd_keyword: String,
}

fn default_instrument_keyword() -> String {
    "INSTRUME".into()
}
fn default_target_keyword() -> String {
    "OBJECT".into()
}
fn default_ra_keyword() -> String {
    "RA".into()
}
fn default_dec_keyword() -> String {
    "DEC".into()
}
fn default_mjd_keyword() -> String {
    "MJD-OBS".into()
}

/// What a file's role string says it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    Bias,
    Flat,
    Polarimetry,
    Standard,
}

impl Role {
    pub fn name(self) -> &'static str {
        match self {
            Role::Bias => "bias",
            Role::Flat => "flat",
            Role::Polarimetry => "polarimetry",
            Role::Standard => "standard",
        }
    }
}

/// `*` matches any run of characters (none included); other characters match themselves,
/// case aside.
pub fn glob_match(pattern: &str, text: &str) -> bool {
    let p: Vec<char> = pattern.to_uppercase().chars().collect();
    let t: Vec<char> = text.to_uppercase().chars().collect();
    // Iterative match with one backtrack point (the last '*'), linear in practice.
    let (mut i, mut j, mut star, mut mark) = (0, 0, None, 0);
    while j < t.len() {
        if i < p.len() && p[i] != '*' && p[i] == t[j] {
            i += 1;
            j += 1;
        } else if i < p.len() && p[i] == '*' {
            star = Some(i);
            mark = j;
            i += 1;
        } else if let Some(s) = star {
            i = s + 1;
            mark += 1;
            j = mark;
        } else {
            return false;
        }
    }
    p[i..].iter().all(|&c| c == '*')
}

impl Headers {
    /// The role whose patterns match `role_string` (the first of bias, flat, standard,
    /// polarimetry that does), or `None`.
    pub fn role_of(&self, role_string: &str) -> Option<Role> {
        [
            (Role::Bias, &self.bias),
            (Role::Flat, &self.flat),
            (Role::Standard, &self.standard),
            (Role::Polarimetry, &self.polarimetry),
        ]
        .into_iter()
        .find(|(_, pats)| pats.iter().any(|p| glob_match(p, role_string)))
        .map(|(r, _)| r)
    }

    /// True when `value` of the instrument keyword names this instrument.
    pub fn is_instrument(&self, value: &str) -> bool {
        self.instrument_values.is_empty() || self.instrument_values.iter().any(|v| v.eq_ignore_ascii_case(value.trim()))
    }

    /// `Err((key, value, why))` for a table that cannot classify anything.
    pub(crate) fn check(&self) -> Result<(), (String, String, String)> {
        if self.role_keywords.is_empty() || self.role_keywords.iter().any(|k| k.trim().is_empty()) {
            return Err((
                "headers.role_keywords".into(),
                format!("{:?}", self.role_keywords),
                "list at least one keyword, none empty".into(),
            ));
        }
        if self.polarimetry.is_empty() && self.standard.is_empty() {
            return Err((
                "headers.polarimetry".into(),
                "[]".into(),
                "give the role patterns of a polarimetric exposure (polarimetry or standard)".into(),
            ));
        }
        let n = self.role_keywords.len();
        for (key, pats) in [
            ("bias", &self.bias),
            ("flat", &self.flat),
            ("polarimetry", &self.polarimetry),
            ("standard", &self.standard),
        ] {
            if let Some(p) = pats.iter().find(|p| p.split('/').count() != n) {
                return Err((
                    format!("headers.{key}"),
                    p.clone(),
                    format!("a pattern has one part per role keyword ({n}), separated by '/'"),
                ));
            }
        }
        for (key, v) in [
            ("headers.instrument_keyword", &self.instrument_keyword),
            ("headers.target_keyword", &self.target_keyword),
            ("headers.ra_keyword", &self.ra_keyword),
            ("headers.dec_keyword", &self.dec_keyword),
            ("headers.mjd_keyword", &self.mjd_keyword),
        ] {
            if v.trim().is_empty() {
                return Err((key.into(), String::new(), "must name a keyword".into()));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn globs() {
        assert!(glob_match("CALIB/BIAS/*", "calib/BIAS/IMAGE"));
        assert!(glob_match("SCIENCE/OBJECT/*POLARIMETRY*", "SCIENCE/OBJECT/IMAGE,POLARIMETRY"));
        assert!(glob_match("*", ""));
        assert!(!glob_match("CALIB/BIAS/*", "CALIB/FLAT,SKY/IMAGE"));
        assert!(!glob_match("A*B", "A"));
        assert!(glob_match("A*B*C", "AxxBxBxC"));
        assert!(!glob_match("A*B*C", "AxxBxBx"));
    }
}
