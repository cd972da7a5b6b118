//! A minimal FITS header reader for sorting files: the header cards of every HDU of a file,
//! read block by block with the data skipped (a seek, no pixel read), and the check that the
//! file is as long as its headers say. Sorting a night reads thousands of files; opening each
//! with CFITSIO costs more than the few kilobytes of cards that say what a file is.
//!
//! FITS 4.0 (Pence et al. 2010, A&A 524, A42): 2880-byte blocks of 80-character cards, a
//! header ending at the `END` card, data of `|BITPIX|/8 * GCOUNT * (PCOUNT + NAXIS1 * ... *
//! NAXISn)` bytes padded to whole blocks. ESO's `HIERARCH` convention (keywords longer than
//! eight characters) is read as the whole name before `=`.

use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

const BLOCK: usize = 2880;
const CARD: usize = 80;
/// Headers longer than this are refused as corrupt (a real header has a few hundred cards).
const MAX_HEADER_BLOCKS: usize = 1000;
/// At most this many HDUs are read (a raw frame has one per chip at most).
const MAX_HDUS: usize = 64;

/// A header value as written.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    Str(String),
    Num(f64),
    Bool(bool),
    /// Anything else (complex numbers, an empty value).
    Other(String),
}

/// Every card of a file's HDUs, in order: `(normalized keyword, value)`.
#[derive(Debug, Clone, Default)]
pub struct Cards(pub Vec<(String, Value)>);

/// A keyword as compared: `HIERARCH ` left out, spaces collapsed, upper case.
pub fn normalize(key: &str) -> String {
    let k = key.trim();
    let k = k.strip_prefix("HIERARCH ").or_else(|| k.strip_prefix("hierarch ")).unwrap_or(k);
    // Most keys are written normalized already: one copy instead of three (a scan normalizes
    // every card of every file).
    if !k.contains("  ") && !k.bytes().any(|b| b.is_ascii_lowercase() || (b.is_ascii_whitespace() && b != b' ')) {
        return k.to_string();
    }
    k.split_whitespace().collect::<Vec<_>>().join(" ").to_ascii_uppercase()
}

impl Cards {
    /// The first value of `key` (any spelling [`normalize`] makes equal).
    pub fn get(&self, key: &str) -> Option<&Value> {
        let k = normalize(key);
        self.0.iter().find(|(n, _)| *n == k).map(|(_, v)| v)
    }

    /// `key` as text: a string, or a number or logical as written.
    pub fn text(&self, key: &str) -> Option<String> {
        self.get(key).map(|v| match v {
            Value::Str(s) => s.clone(),
            Value::Num(x) => x.to_string(),
            Value::Bool(b) => (if *b { "T" } else { "F" }).to_string(),
            Value::Other(s) => s.clone(),
        })
    }

    /// `key` as a number (a number, or a string holding one).
    pub fn number(&self, key: &str) -> Option<f64> {
        match self.get(key)? {
            Value::Num(x) => Some(*x),
            Value::Str(s) => s.trim().parse().ok(),
            _ => None,
        }
        .filter(|x: &f64| x.is_finite())
    }
}

/// Why a file's headers cannot be read.
#[derive(Debug, Clone, PartialEq)]
pub enum Problem {
    Unreadable(String),
    NotFits,
    Corrupt(String),
    Truncated { have: u64, need: u64 },
}

impl std::fmt::Display for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Problem::Unreadable(e) => write!(f, "unreadable: {e}"),
            Problem::NotFits => f.write_str("not a FITS file (no SIMPLE = T card first)"),
            Problem::Corrupt(why) => write!(f, "corrupt header: {why}"),
            Problem::Truncated { have, need } => {
                write!(f, "truncated: {have} bytes, its headers describe {need}")
            }
        }
    }
}

fn parse_value(s: &str) -> Value {
    let t = s.trim_start();
    if let Some(rest) = t.strip_prefix('\'') {
        // A string ends at a quote not doubled; '' inside is one quote.
        let mut out = String::new();
        let mut chars = rest.chars().peekable();
        while let Some(c) = chars.next() {
            if c == '\'' {
                if chars.peek() == Some(&'\'') {
                    chars.next();
                    out.push('\'');
                } else {
                    break;
                }
            } else {
                out.push(c);
            }
        }
        return Value::Str(out.trim_end().to_string());
    }
    let v = t.split('/').next().unwrap_or("").trim();
    match v {
        "T" => Value::Bool(true),
        "F" => Value::Bool(false),
        _ => match v.replace(['D', 'd'], "E").parse::<f64>() {
            Ok(x) => Value::Num(x),
            Err(_) => Value::Other(v.to_string()),
        },
    }
}

/// One card: `Some((keyword, value))` for a keyword with a value, `None` for commentary and
/// blank cards. `Err` at `END`.
fn parse_card(card: &str) -> Result<Option<(String, Value)>, ()> {
    let key8 = card.get(..8).unwrap_or(card).trim_end();
    if key8 == "END" {
        return Err(());
    }
    if key8 == "HIERARCH" {
        return Ok(card.split_once('=').map(|(k, v)| (normalize(k), parse_value(v))));
    }
    if card.get(8..10) == Some("= ") {
        return Ok(Some((normalize(key8), parse_value(&card[10..]))));
    }
    Ok(None)
}

/// Read one header from the current position: its cards and its length in bytes.
fn read_header(r: &mut impl Read, first: bool) -> Result<(Vec<(String, Value)>, u64), Problem> {
    let mut cards = Vec::new();
    let mut buf = [0u8; BLOCK];
    for b in 0..MAX_HEADER_BLOCKS {
        let mut got = 0;
        while got < BLOCK {
            match r.read(&mut buf[got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(e) => return Err(Problem::Unreadable(e.to_string())),
            }
        }
        if got == 0 && b == 0 && first {
            return Err(Problem::NotFits);
        }
        if got < BLOCK {
            return Err(if b == 0 && first && !buf.starts_with(b"SIMPLE  =") {
                Problem::NotFits
            } else {
                Problem::Corrupt("the file ends inside a header (no END card)".into())
            });
        }
        if b == 0 && first && !(buf.starts_with(b"SIMPLE  =") && String::from_utf8_lossy(&buf[10..30]).trim() == "T") {
            return Err(Problem::NotFits);
        }
        for c in buf.chunks(CARD) {
            let text = String::from_utf8_lossy(c);
            match parse_card(&text) {
                Err(()) => return Ok((cards, ((b + 1) * BLOCK) as u64)),
                Ok(Some(kv)) => cards.push(kv),
                Ok(None) => {}
            }
        }
    }
    Err(Problem::Corrupt(format!("no END card in {MAX_HEADER_BLOCKS} blocks")))
}

/// Bytes of an HDU's data (without padding) from its header's cards.
fn data_bytes(cards: &[(String, Value)]) -> Result<u64, Problem> {
    let int = |k: &str, default: Option<i64>| -> Result<i64, Problem> {
        match cards.iter().find(|(n, _)| n == k).map(|(_, v)| v) {
            Some(Value::Num(x)) if x.fract() == 0.0 => Ok(*x as i64),
            Some(v) => Err(Problem::Corrupt(format!("{k} = {v:?} is not an integer"))),
            None => default.ok_or_else(|| Problem::Corrupt(format!("no {k} card"))),
        }
    };
    let bitpix = int("BITPIX", None)?;
    if ![8, 16, 32, 64, -32, -64].contains(&bitpix) {
        return Err(Problem::Corrupt(format!("BITPIX = {bitpix}")));
    }
    let naxis = int("NAXIS", None)?;
    if !(0..=999).contains(&naxis) {
        return Err(Problem::Corrupt(format!("NAXIS = {naxis}")));
    }
    if naxis == 0 {
        return Ok(0);
    }
    let mut n: u64 = 1;
    for i in 1..=naxis {
        let a = int(&format!("NAXIS{i}"), None)?;
        n = n
            .checked_mul(u64::try_from(a).map_err(|_| Problem::Corrupt(format!("NAXIS{i} = {a}")))?)
            .ok_or_else(|| Problem::Corrupt("data size overflows".into()))?;
    }
    let pcount = int("PCOUNT", Some(0))?.max(0) as u64;
    let gcount = int("GCOUNT", Some(1))?.max(1) as u64;
    Ok(bitpix.unsigned_abs() / 8 * gcount * (pcount + n))
}

/// The cards of every HDU of `path` (primary first), the data skipped; [`Problem::Truncated`]
/// when the file is shorter than its headers and data (the last HDU's padding aside).
pub fn read_cards(path: &Path) -> Result<Cards, Problem> {
    let mut f = std::fs::File::open(path).map_err(|e| Problem::Unreadable(e.to_string()))?;
    let len = f.metadata().map_err(|e| Problem::Unreadable(e.to_string()))?.len();
    let mut r = std::io::BufReader::with_capacity(BLOCK * 4, &mut f);
    let mut all = Vec::new();
    let mut pos: u64 = 0;
    for hdu in 0..MAX_HDUS {
        let (cards, hlen) = read_header(&mut r, hdu == 0)?;
        let data = data_bytes(&cards)?;
        all.extend(cards);
        let need = pos + hlen + data;
        if len < need {
            return Err(Problem::Truncated { have: len, need });
        }
        pos = need.div_ceil(BLOCK as u64) * BLOCK as u64;
        if pos >= len {
            break;
        }
        r.seek(SeekFrom::Start(pos)).map_err(|e| Problem::Unreadable(e.to_string()))?;
    }
    Ok(Cards(all))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn card(s: &str) -> String {
        format!("{s:<80}")
    }

    #[test]
    fn values_and_hierarch() {
        assert_eq!(parse_value(" 'O''Brien '  / name"), Value::Str("O'Brien".into()));
        assert_eq!(parse_value("  1.5E2 / x"), Value::Num(150.0));
        assert_eq!(parse_value("  1.5D2"), Value::Num(150.0));
        assert_eq!(parse_value("   T"), Value::Bool(true));
        let c = card("HIERARCH ESO DPR CATG = 'CALIB   ' / Observation category");
        assert_eq!(parse_card(&c), Ok(Some(("ESO DPR CATG".into(), Value::Str("CALIB".into())))));
        assert_eq!(normalize("HIERARCH ESO  DPR catg"), "ESO DPR CATG");
        assert_eq!(parse_card(&card("END")), Err(()));
        assert_eq!(parse_card(&card("HISTORY a = b")), Ok(None));
    }

    #[test]
    fn a_file_written_by_cfitsio_reads_and_its_truncation_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.fits");
        let keys = [
            ("HIERARCH ESO DPR TYPE".to_string(), skyfield::fits::KeyValue::Str("BIAS".into()), String::new()),
            ("EXPTIME".to_string(), skyfield::fits::KeyValue::F64(12.5), String::new()),
        ];
        skyfield::fits::write_frame(&p, 30, 20, &[1.0; 600], skyfield::fits::Bitpix::U16, &keys).unwrap();
        let c = read_cards(&p).unwrap();
        assert_eq!(c.text("HIERARCH ESO DPR TYPE").as_deref(), Some("BIAS"));
        assert_eq!(c.number("EXPTIME"), Some(12.5));
        assert_eq!(c.number("NAXIS1"), Some(30.0));
        let bytes = std::fs::read(&p).unwrap();
        // The header and part of the 1200 data bytes: truncated, with both lengths named.
        let cut = dir.path().join("cut.fits");
        std::fs::write(&cut, &bytes[..bytes.len() - 2880 + 600]).unwrap();
        match read_cards(&cut) {
            Err(Problem::Truncated { have, need }) => assert!(have < need, "{have} {need}"),
            other => panic!("{other:?}"),
        }
        let txt = dir.path().join("t.fits");
        std::fs::write(&txt, b"hello").unwrap();
        assert_eq!(read_cards(&txt).unwrap_err(), Problem::NotFits);
        let empty = dir.path().join("e.fits");
        std::fs::write(&empty, b"").unwrap();
        assert_eq!(read_cards(&empty).unwrap_err(), Problem::NotFits);
    }
}
