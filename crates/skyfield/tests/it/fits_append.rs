//! `skyfield::table::append_fits_columns`: a copy of a FITS file with columns added to its
//! table HDU, every other HDU, keyword and column of the input kept. Read back with fitsio.

use fitsio::hdu::HduInfo;
use fitsio::images::{ImageDescription, ImageType};
use fitsio::tables::{ColumnDataType, ColumnDescription};
use fitsio::FitsFile;
use skyfield::table::{append_fits_columns, Column};
use std::path::Path;

/// A primary HDU with keywords, an image extension, the table (`STARS`, two columns, a
/// keyword) and an image after it.
fn write_input(path: &Path) {
    let mut f = FitsFile::create(path).open().unwrap();
    let ph = f.primary_hdu().unwrap();
    ph.write_key(&mut f, "OBSERVER", "someone").unwrap();
    ph.write_key(&mut f, "EXPTIME", 12.5).unwrap();
    let desc = ImageDescription { data_type: ImageType::Double, dimensions: &[3, 4] };
    let img = f.create_image("IMG", &desc).unwrap();
    img.write_image(&mut f, &(0..12).map(f64::from).collect::<Vec<_>>()).unwrap();
    img.write_key(&mut f, "FOO", 7i64).unwrap();
    let cols = [
        ColumnDescription::new("X").with_type(ColumnDataType::Double).create().unwrap(),
        ColumnDescription::new("ID").with_type(ColumnDataType::String).that_repeats(4).create().unwrap(),
    ];
    let t = f.create_table("STARS", &cols).unwrap();
    t.write_col(&mut f, "X", &[1.5, -2.25, 3.0]).unwrap();
    t.write_col(&mut f, "ID", &["a".to_string(), "bb".into(), "ccc".into()]).unwrap();
    t.write_key(&mut f, "AIRMASS", 1.25).unwrap();
    let tail = ImageDescription { data_type: ImageType::Double, dimensions: &[2, 2] };
    let h = f.create_image("TAIL", &tail).unwrap();
    h.write_image(&mut f, &[9.0, 8.0, 7.0, 6.0]).unwrap();
}

#[test]
fn appended_columns_and_everything_else_kept() {
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("in.fits"), dir.path().join("out.fits"));
    write_input(&input);
    let before = std::fs::read(&input).unwrap();
    let cols = [
        Column::f64("q0", Some("deg"), "", vec![0.1, 0.2, 0.3]),
        Column::i64("flag", "a flag", vec![0, 1, 0]),
        Column::i64("big", "", vec![1, 5_000_000_000, -3]),
    ];
    append_fits_columns(&input, None, &cols, &[], &out).unwrap();
    assert_eq!(std::fs::read(&input).unwrap(), before, "the input is not touched");
    let mut f = FitsFile::open(&out).unwrap();
    assert_eq!(f.iter().count(), 4, "every HDU kept");
    let ph = f.primary_hdu().unwrap();
    assert_eq!(ph.read_key::<String>(&mut f, "OBSERVER").unwrap(), "someone");
    assert_eq!(ph.read_key::<f64>(&mut f, "EXPTIME").unwrap(), 12.5);
    assert_eq!(ph.read_key::<String>(&mut f, "PROGRAM").unwrap(), "instpol", "provenance stamped");
    let img = f.hdu("IMG").unwrap();
    assert_eq!(img.read_key::<i64>(&mut f, "FOO").unwrap(), 7);
    assert_eq!(img.read_image::<Vec<f64>>(&mut f).unwrap(), (0..12).map(f64::from).collect::<Vec<_>>());
    let tail = f.hdu("TAIL").unwrap();
    assert_eq!(tail.read_image::<Vec<f64>>(&mut f).unwrap(), vec![9.0, 8.0, 7.0, 6.0]);
    let t = f.hdu("STARS").unwrap();
    assert_eq!(t.read_key::<f64>(&mut f, "AIRMASS").unwrap(), 1.25);
    assert_eq!(t.read_col::<f64>(&mut f, "X").unwrap(), vec![1.5, -2.25, 3.0]);
    assert_eq!(t.read_col::<String>(&mut f, "ID").unwrap(), vec!["a", "bb", "ccc"]);
    assert_eq!(t.read_col::<f64>(&mut f, "q0").unwrap(), vec![0.1, 0.2, 0.3]);
    assert_eq!(t.read_col::<i64>(&mut f, "flag").unwrap(), vec![0, 1, 0]);
    assert_eq!(t.read_col::<i64>(&mut f, "big").unwrap(), vec![1, 5_000_000_000, -3]);
    let HduInfo::TableInfo { column_descriptions: d, num_rows } = &t.info else { panic!("not a table") };
    assert_eq!(*num_rows, 3);
    let names: Vec<&str> = d.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["X", "ID", "q0", "flag", "big"]);
    // 0/1 flags fit in 32 bits (TFORM J); a value beyond them keeps 64 (K).
    assert_eq!(t.read_key::<String>(&mut f, "TFORM3").unwrap(), "1D");
    assert_eq!(t.read_key::<String>(&mut f, "TFORM4").unwrap(), "1J");
    assert_eq!(t.read_key::<String>(&mut f, "TFORM5").unwrap(), "1K");
    assert!(t.read_key::<String>(&mut f, "TUNIT3").is_err(), "names and types only");
    // Nothing is left beside the output but the input.
    let mut left: Vec<String> =
        std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into()).collect();
    left.sort();
    assert_eq!(left, ["in.fits", "out.fits"]);
}

#[test]
fn refusals_leave_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("in.fits"), dir.path().join("out.fits"));
    write_input(&input);
    let short = [Column::f64("q0", None, "", vec![0.1, 0.2])];
    let e = append_fits_columns(&input, None, &short, &[], &out).unwrap_err().to_string();
    assert!(e.contains("column 'q0' has 2 values for 3 rows"), "{e}");
    let e = append_fits_columns(&input, Some("NOPE"), &[], &[], &out).unwrap_err().to_string();
    assert!(e.contains("no HDU named 'NOPE'"), "{e}");
    let e = append_fits_columns(&input, Some("IMG"), &[], &[], &out).unwrap_err().to_string();
    assert!(e.contains("is not a table"), "{e}");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "only the input");
}
