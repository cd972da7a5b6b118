//! Regression tests for defects found by the cargo-fuzz targets (fuzz/FINDINGS.md).

use skyfield::fits::{read_key_str, write_frame, Bitpix, KeyValue};

/// fuzz/FINDINGS.md, frame_fits 1: a header card whose value starts right after the `=` and
/// fills the card (71 characters, `EXPTIME =<71 bytes>`) made fitsio 0.21's
/// `read_key::<String>` overflow its 71-byte buffer by one byte inside CFITSIO (an
/// AddressSanitizer heap-buffer-overflow in `ffc2s`; without ASan the byte lands in malloc's
/// padding, so no ordinary test can see the overflow itself: the fuzz target under ASan is
/// the guard). The string-keyword reader now reads into buffers longer than a card; this
/// checks it returns that whole value, a quoted value, and an error for a missing key.
#[test]
fn string_keyword_filling_the_card_is_read_whole() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("f.fits");
    let keys = vec![
        ("OBJECT".to_string(), KeyValue::Str("placeholder".into()), String::new()),
        ("FILTER".to_string(), KeyValue::Str("V_BESS".into()), String::new()),
    ];
    write_frame(&p, 4, 4, &[1.0; 16], Bitpix::F32, &keys).unwrap();
    let mut b = std::fs::read(&p).unwrap();
    let at = b.windows(9).position(|w| w == b"OBJECT  =").unwrap();
    let long = "A".repeat(71);
    b[at..at + 80].copy_from_slice(format!("OBJECT  ={long}").as_bytes());
    std::fs::write(&p, b).unwrap();

    let mut f = fitsio::FitsFile::open(&p).unwrap();
    let hdu = f.primary_hdu().unwrap();
    assert_eq!(read_key_str(&mut f, &hdu, "OBJECT").unwrap(), long);
    assert_eq!(read_key_str(&mut f, &hdu, "FILTER").unwrap(), "V_BESS");
    assert!(read_key_str(&mut f, &hdu, "NOSUCHKY").is_err());
}
