//! The built-in FORS2 beam layout against the published FORS2 IPOL geometry of
//! Gonzalez-Gaitan et al. 2020 (A&A 634, A70), released at github.com/gongsale/FORS2-INSTPOL:
//!
//! - `Information/default_quadpars.dat`: the o/e offset `y_o - y_e = P1 + P3 (y_o - P0)^2` in
//!   rows of the merged two-chip frame (their `find_shift`: the linear term is fixed at 0 and
//!   `y_o` is the o star's row); v_HIGH: `P0 = 450.0`, `P1 = 90.5587463591`,
//!   `P3 = 2.29758491222e-06`.
//! - `Information/default_strips.dat`: per filter, the o/e strip boundaries as `(y1, y2)` row
//!   pairs of the raw chip files (0-based, before trimming the 5 prescan rows), 12 for CHIP1
//!   then 9 for CHIP2. Their `separate_beams` takes rows `y2[s] + 1 .. y1[s + 1]` (exclusive,
//!   the boundaries truncated to integers) as strip `s`: on CHIP1 even `s` are o, on CHIP2 odd
//!   `s` are; `stick_chips` puts trimmed CHIP2 at merged rows 0..1024 and trimmed CHIP1 from
//!   row 1040 (a 16-row gap).
//!
//! The numbers are typed here as published; the conversion to merged rows is written here from
//! those descriptions, independently of the instrument file. Checked: the layout's o/e offset
//! is the published quadratic everywhere, and every sky row the reduction uses has its o row
//! inside a published o strip and its e row inside the same pair's published e strip, for each
//! of the four broad-band filters.

use instrument::Instrument;
use skyfield::BeamGeometry;

/// `default_strips.dat`, the four broad-band filters' columns: CHIP1 then CHIP2 boundaries.
type Table = (&'static str, [(f64, f64); 12], [(f64, f64); 9]);
const STRIPS: [Table; 4] = [
    (
        "b_HIGH",
        [
            (4., 4.),
            (27., 31.),
            (113., 125.),
            (208., 211.),
            (295., 306.),
            (390., 393.),
            (476., 489.),
            (572., 573.),
            (656., 670.),
            (753., 754.),
            (838., 852.),
            (936., 936.),
        ],
        [
            (347., 347.),
            (431., 431.),
            (524., 529.),
            (612., 622.),
            (705., 710.),
            (795., 803.),
            (889., 890.),
            (973., 984.),
            (1027., 1028.),
        ],
    ),
    (
        "v_HIGH",
        [
            (4., 4.),
            (25., 31.),
            (114., 123.),
            (206., 211.),
            (296., 304.),
            (389., 394.),
            (477., 487.),
            (570.5, 574.),
            (657., 668.),
            (752., 755.),
            (838., 850.),
            (934., 934.),
        ],
        [
            (348., 348.),
            (432., 432.),
            (523., 530.),
            (612., 621.),
            (703., 711.),
            (796., 802.),
            (887., 891.),
            (974., 982.),
            (1027., 1028.),
        ],
    ),
    (
        "R_SPECIAL",
        [
            (4., 4.),
            (24., 31.),
            (114., 122.),
            (205., 212.),
            (296., 303.),
            (388., 394.),
            (477., 486.),
            (569., 574.),
            (657., 667.),
            (750., 755.),
            (838., 849.),
            (933., 933.),
        ],
        [
            (348., 348.),
            (432., 432.),
            (521.5, 530.),
            (612., 620.),
            (702., 711.),
            (796., 801.),
            (886., 891.),
            (974., 981.),
            (1027., 1028.),
        ],
    ),
    (
        "I_BESS",
        [
            (4., 4.),
            (24., 32.),
            (115., 122.),
            (205., 212.),
            (297., 303.),
            (387., 395.),
            (478., 486.),
            (569., 575.),
            (658., 667.),
            (750., 756.),
            (839., 849.),
            (933., 933.),
        ],
        [
            (349., 349.),
            (433., 433.),
            (521., 531.),
            (613., 619.),
            (702., 712.),
            (797., 800.5),
            (886., 892.),
            (975., 981.),
            (1027., 1028.),
        ],
    ),
];

/// Merged-frame row of raw chip row `r` (5 prescan rows trimmed; CHIP1 from row 1040).
fn merged(chip1: bool, r: i64) -> i64 {
    r - 5 + if chip1 { 1040 } else { 0 }
}

/// The published o and e strips of one filter as inclusive merged-row ranges, bottom to top;
/// the o strip cut by the chip gap is joined across it (one sky strip).
fn strips(t: &Table) -> (Vec<(i64, i64)>, Vec<(i64, i64)>) {
    let (mut o, mut e) = (Vec::new(), Vec::new());
    for (chip1, b) in [(true, &t.1[..]), (false, &t.2[..])] {
        for s in 0..b.len() - 1 {
            let lo = merged(chip1, b[s].1 as i64 + 1);
            let hi = merged(chip1, b[s + 1].0 as i64 - 1);
            let is_o = if chip1 { s % 2 == 0 } else { s % 2 == 1 };
            if is_o { &mut o } else { &mut e }.push((lo, hi));
        }
    }
    o.sort();
    e.sort();
    // CHIP2's top o strip ends at the chip's last rows and CHIP1's first begins at its first:
    // one strip of the sky, the gap inside it.
    let k = o.iter().position(|s| s.1 >= 1018 && s.1 < 1024).expect("an o strip at the top of CHIP2");
    assert_eq!(o[k + 1].0, 1040, "{}: CHIP1's first o strip starts at its first row", t.0);
    o[k].1 = o[k + 1].1;
    o.remove(k + 1);
    (o, e)
}

/// `default_quadpars.dat`: each broad-band filter's `P1` (px) and `P3` (px^-1), `P0 = 450`.
const QUADPARS: [(&str, f64, f64); 4] = [
    ("b_HIGH", 92.5609853356, 2.41646229638e-06),
    ("v_HIGH", 90.5587463591, 2.29758491222e-06),
    ("R_SPECIAL", 89.5308957802, 2.30830075534e-06),
    ("I_BESS", 88.3922576965, 2.33049539846e-06),
];

/// The layout frames of `filter` are reduced and measured with.
fn layout(inst: &Instrument, filter: &str) -> BeamGeometry {
    BeamGeometry::new(&inst.for_filter(filter))
}

#[test]
fn fors2_offset_is_the_published_quadratic() {
    let inst = Instrument::load("fors2").unwrap();
    for (filter, p1, p3) in QUADPARS {
        let g = layout(&inst, filter);
        let p0 = 450.0;
        for y in [0.0, 100.0, 450.0, 777.7, 1031.5, 1500.0, 1968.0, 2063.0] {
            for x in [0.0, 1024.0, 2047.0] {
                let (dx, dy) = BeamGeometry::e_offset(&g, x, y).unwrap();
                let want = -(p1 + p3 * (y - p0) * (y - p0));
                assert_eq!(dx, 0.0);
                assert!((dy - want).abs() < 1e-9, "{filter} ({x}, {y}): {dy} vs published {want}");
            }
        }
    }
    let g = BeamGeometry::new(&inst);
    // The published values at the strips' ends: 90.56 px at row 450, 95.85 px at row 1968.
    assert!((g.e_offset(5.0, 1968.0).unwrap().1 + 95.8531).abs() < 1e-3);
    assert!(g.strips.len() == 9);
}

#[test]
fn fors2_used_rows_lie_in_the_published_strips() {
    let inst = Instrument::load("fors2").unwrap();
    for t in &STRIPS {
        // Each filter's e rows through its own published offset.
        let g = layout(&inst, t.0);
        let bands = g.sky_bands();
        assert_eq!(bands.len(), 9);
        let (o, e) = strips(t);
        assert_eq!((o.len(), e.len()), (9, 9), "{}: nine strip pairs", t.0);
        for (k, band) in bands.iter().enumerate() {
            assert!(band.len() >= 68, "strip {k}: {} rows used", band.len());
            for y in band.clone() {
                let yi = y as i64;
                assert!(o[k].0 <= yi && yi <= o[k].1, "{}: strip {k}: o row {y} outside the published {:?}", t.0, o[k]);
                let (_, ye) = g.e_pixel_of_sky(700, y).expect("sky row has an e pixel");
                let ye = ye as i64;
                assert!(e[k].0 <= ye && ye <= e[k].1, "{}: strip {k}: e row {ye} (o row {y}) outside {:?}", t.0, e[k]);
                assert!(ye < yi, "the e image lies below the o image");
            }
        }
    }
    // v_HIGH's published pairs, as the instrument file's comment lists them.
    let (o, e) = strips(&STRIPS[1]);
    assert_eq!(o[0], (428, 517));
    assert_eq!(o[3], (978, 1059));
    assert_eq!(o[8], (1886, 1968));
    assert_eq!(e[0], (344, 426));
    assert_eq!(e[8], (1791, 1872));
}

/// The layout's pixel kinds (what detection, the photometry's placement checks and the
/// simulator read) agree with its o/e pixel pairs (what the reduction reads): every used sky
/// pixel's e pixel is an e pixel of the same strip, though FORS2's throw varies by 2.6 to 7.9
/// px from the nominal 88 px across the strips (with the nominal e strips, the e images of the
/// lowest used rows of each strip were taken as masked), and its o pixel an o pixel.
#[test]
fn fors2_e_pixels_of_the_sky_are_e_pixels() {
    let inst = Instrument::load("fors2").unwrap();
    let mut n = 0;
    for g in QUADPARS.map(|(f, _, _)| layout(&inst, f)) {
        for x in [0, 700, 2047] {
            for y in 0..g.ny {
                let Some(k) = g.strip_of_sky(x, y) else { continue };
                let (xe, ye) = g.e_pixel_of_sky(x, y).unwrap();
                assert_eq!(g.kind(x, y), skyfield::beams::PixelKind::Ordinary(k));
                assert_eq!(
                    g.kind(xe, ye),
                    skyfield::beams::PixelKind::Extraordinary(k),
                    "sky ({x}, {y}) -> e row {ye}"
                );
                n += 1;
            }
        }
    }
    assert!(n > 4 * 3 * 9 * 68, "{n}");
}
