//! The table reader against files astropy wrote (`tests/data/tables/make_tables.py` made them),
//! and the reader's refusals. That astropy reads our tables is checked by
//! `tests/python/test_astropy_outputs.py`.

use skyfield::table::{Column, Data, Format, Table};
use std::path::{Path, PathBuf};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/tables").join(name)
}

fn f64s(t: &Table, name: &str) -> Vec<f64> {
    t.numbers(name, Path::new("t")).unwrap()
}

/// The catalog make_tables.py writes, as every format must give it back.
fn check_astropy_catalog(t: &Table, file: &str, pix: &str) {
    assert_eq!(t.names(), ["id", "x", "q", "chi_deg", "note"], "{file}");
    assert_eq!(t.n_rows(), 3, "{file}");
    assert_eq!(t.column("id").unwrap().data, Data::I64(vec![1, 2, 3]), "{file}");
    let x = f64s(t, "x");
    assert_eq!(&x[..2], &[10.5, 2047.25], "{file}");
    assert!(x[2] == 0.0 && x[2].is_sign_negative(), "{file}: -0.0 kept, got {}", x[2]);
    let q = f64s(t, "q");
    assert_eq!(&q[..2], &[0.0123, -1e-17], "{file}");
    assert!(q[2].is_nan(), "{file}");
    assert_eq!(f64s(t, "chi_deg"), [179.99, 0.0, 90.0], "{file}");
    let note = &t.column("note").unwrap().data;
    assert_eq!(note, &Data::Str(vec!["ok".into(), "near, edge".into(), "said \"hi\"".into()]), "{file}");
    if !pix.is_empty() {
        assert_eq!(t.column("x").unwrap().unit.as_deref(), Some(pix), "{file}");
        assert_eq!(t.column("chi_deg").unwrap().unit.as_deref(), Some("deg"), "{file}");
        assert_eq!(t.column("q").unwrap().unit, None, "{file}");
    }
}

#[test]
fn reads_what_astropy_wrote_in_every_format() {
    let ecsv = Table::read(&data("astropy.ecsv"), None).unwrap();
    check_astropy_catalog(&ecsv, "ecsv", "pix");
    assert_eq!(ecsv.column("q").unwrap().description.as_deref(), Some("Q/I, dimensionless fraction"));
    // ECSV rows are named by their line in the file: the first data row is line 13.
    assert_eq!(ecsv.row_label(0), "row 1 (line 13)");
    // Its header's meta holds one text entry (`comment: made by make_tables.py`): not a number,
    // so no table number.
    assert!(ecsv.meta.is_empty(), "{:?}", ecsv.meta);
    let vot = Table::read(&data("astropy.vot"), None).unwrap();
    check_astropy_catalog(&vot, "votable", "pixel");
    assert_eq!(vot.column("q").unwrap().description.as_deref(), Some("Q/I, dimensionless fraction"));
    let fits = Table::read(&data("astropy.fits"), None).unwrap();
    check_astropy_catalog(&fits, "fits", "pix");
    // astropy writes -0.0 in CSV as "-0.0"; units are not in CSV.
    let csv = Table::read(&data("astropy.csv"), None).unwrap();
    check_astropy_catalog(&csv, "csv", "");
    assert_eq!(csv.row_label(0), "row 1 (line 2)");
}

#[test]
fn format_from_extension_and_unknown_ones_refused() {
    for (name, f) in [
        ("a.csv", Format::Csv),
        ("a.FITS", Format::Fits),
        ("a.fit", Format::Fits),
        ("a.ecsv", Format::Ecsv),
        ("a.vot", Format::Votable),
        ("a.xml", Format::Votable),
    ] {
        assert_eq!(Format::from_path(Path::new(name)).unwrap(), f, "{name}");
    }
    for name in ["a.txt", "a", "a.fits.gz", "a.parquet"] {
        let e = Format::from_path(Path::new(name)).unwrap_err().to_string();
        assert!(e.contains(name) && e.contains("unknown table format") && e.contains(".ecsv"), "{e}");
    }
    let dir = tempfile::tempdir().unwrap();
    let t = Table::new(vec![Column::f64("x", None, "", vec![1.0])]);
    let p = dir.path().join("out.txt");
    assert!(t.write(&p).is_err());
    assert!(!p.exists(), "nothing written under an unknown extension");
}

/// Values that stress the text formats (shortest round-trip digits, subnormals, signed zero,
/// infinities, NaN, text needing quotes and XML escapes) come back bit for bit from each
/// format, and the units and descriptions with them.
#[test]
fn every_format_keeps_every_bit_units_and_text() {
    let vals = vec![0.1 + 0.2, -0.0, 5e-324, f64::MAX, -1.0 / 3.0, f64::INFINITY, f64::NEG_INFINITY, f64::NAN];
    let n = vals.len();
    let text: Vec<String> =
        ["", "a b", "x,y", "q\"uote", "<&>", "'s", "ünï", "tab\tx"].iter().map(|s| s.to_string()).collect();
    let t = Table::new(vec![
        Column::f64("v", Some("arcmin"), "a value: with colon, comma", vals.clone()),
        Column::i64("n", "count", (0..n as i64).map(|i| i64::MAX - i).collect()),
        Column::text("s", "", text.clone()),
    ]);
    let dir = tempfile::tempdir().unwrap();
    for ext in ["ecsv", "vot", "fits", "csv"] {
        let p = dir.path().join(format!("t.{ext}"));
        t.write(&p).unwrap();
        let r = Table::read(&p, None).unwrap();
        let v = f64s(&r, "v");
        for (a, b) in vals.iter().zip(&v) {
            assert!(a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()), "{ext}: {a} -> {b}");
        }
        assert_eq!(r.column("n").unwrap().data, t.columns[1].data, "{ext}");
        if ext != "csv" {
            assert_eq!(r.column("v").unwrap().unit.as_deref(), Some("arcmin"), "{ext}");
            assert_eq!(r.column("v").unwrap().description.as_deref(), Some("a value: with colon, comma"), "{ext}");
        }
        let s = &r.column("s").unwrap().data;
        let want: Vec<String> = match ext {
            // FITS text is ASCII without trailing blanks; CSV trims fields.
            "fits" => text.iter().map(|s| s.trim_end().to_string()).collect(),
            _ => text.clone(),
        };
        if ext == "fits" || ext == "csv" {
            continue; // non-ASCII and tabs are not FITS/CSV-clean; checked for ECSV and VOTable
        }
        assert_eq!(s, &Data::Str(want), "{ext}");
    }
}

/// Table-level numbers (`Table::meta`) come back exactly from ECSV, FITS and VOTable (whole
/// numbers, negatives, fractions that need every digit), are left out of CSV, and a name that
/// is no FITS keyword or a value that is not finite is refused before anything is written.
/// (That astropy reads them: tests/python/test_correct_map.py.)
#[test]
fn every_format_but_csv_keeps_the_table_numbers() {
    let mut t = Table::new(vec![Column::f64("v", None, "", vec![1.0, 2.0])]);
    t.meta = vec![("NEXPTRK".into(), 4.0), ("XPAS1".into(), -157.531404512083), ("ROTANG".into(), 0.1 + 0.2)];
    let dir = tempfile::tempdir().unwrap();
    for ext in ["ecsv", "vot", "fits", "csv"] {
        let p = dir.path().join(format!("m.{ext}"));
        t.write(&p).unwrap();
        let r = Table::read(&p, None).unwrap();
        if ext == "csv" {
            assert!(r.meta.is_empty(), "{:?}", r.meta);
            continue;
        }
        assert_eq!(r.meta.len(), 3, "{ext}: {:?}", r.meta);
        for ((a, x), (b, y)) in t.meta.iter().zip(&r.meta) {
            assert_eq!(a, b, "{ext}");
            assert_eq!(x.to_bits(), y.to_bits(), "{ext}: {a} {x} -> {y}");
        }
    }
    for bad in [("lower", 1.0), ("TOOLONGNAME", 1.0), ("NAN", f64::NAN)] {
        let mut b = t.clone();
        b.meta = vec![(bad.0.to_string(), bad.1)];
        let p = dir.path().join("bad.ecsv");
        let e = b.write(&p).unwrap_err().to_string();
        assert!(e.contains(bad.0), "{e}");
        assert!(!p.exists());
    }
}

#[test]
fn bad_tables_are_refused_with_the_file_and_row() {
    let dir = tempfile::tempdir().unwrap();
    let w = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let p = w(
        "a.ecsv",
        "# %ECSV 1.0\n# ---\n# datatype:\n# - {name: a, datatype: float64}\n# schema: astropy-2.0\na\n1\nx\n",
    );
    let e = Table::read(&p, None).unwrap_err().to_string();
    assert!(e.contains("a.ecsv") && e.contains("line 8") && e.contains("'x'"), "{e}");
    let p = w("b.ecsv", "a,b\n1,2\n");
    let e = Table::read(&p, None).unwrap_err().to_string();
    assert!(e.contains("%ECSV"), "{e}");
    let p = w("c.ecsv", "# %ECSV 1.0\n# ---\n# datatype:\n# - {name: a, datatype: float64}\nb\n1\n");
    let e = Table::read(&p, None).unwrap_err().to_string();
    assert!(e.contains("column names"), "{e}");
    let p = w("d.vot", "<VOTABLE><RESOURCE><TABLE><FIELD name=\"a\" datatype=\"double\"/><DATA><BINARY2><STREAM encoding=\"base64\">AAAA</STREAM></BINARY2></DATA></TABLE></RESOURCE></VOTABLE>");
    let e = Table::read(&p, None).unwrap_err().to_string();
    assert!(e.contains("BINARY2") && e.contains("TABLEDATA"), "{e}");
    let p = w("e.vot", "<VOTABLE><RESOURCE><TABLE><FIELD name=\"a\" datatype=\"double\"/><DATA><TABLEDATA><TR><TD>1</TD><TD>2</TD></TR></TABLEDATA></DATA></TABLE>");
    let e = Table::read(&p, None).unwrap_err().to_string();
    assert!(e.contains("row 1") && e.contains("2 TD"), "{e}");
    let p = w("f.vot", "<VOTABLE><RESOURCE><TABLE><FIELD name=\"a\" datatype=\"double\"/><DATA><TABLEDATA><TR><TD>1</TD></TR></TABLEDATA></DATA></TABLE></RESOURCE>");
    let t = Table::read(&p, None).unwrap();
    assert_eq!(f64s(&t, "a"), [1.0]);
    let p = w("g.vot", "<VOTABLE><RESOURCE><TABLE><FIELD name=\"a\" datatype=\"double\"/><DATA><TABLEDATA><TR><TD>1</TD></TR></TABLEDATA></DATA></TABLE></RESOURCE></VOTABLE");
    let e = Table::read(&p, None).unwrap_err().to_string();
    assert!(e.contains("g.vot"), "{e}");
    let p = w("h.csv", "x,y\n1,2\n3,abc\n");
    let t = Table::read(&p, None).unwrap();
    let e = t.numbers("y", &p).unwrap_err().to_string();
    assert!(e.contains("line 3") && e.contains("'abc'"), "{e}");
    let e = t.numbers("z", &p).unwrap_err().to_string();
    assert!(e.contains("no column 'z'") && e.contains("x, y"), "{e}");
}
