//! Plots for publication, checked on the files the commands write:
//! - every text of every SVG is at least 9 pt when the figure is printed one journal column
//!   wide (8.8 cm = 249.45 pt; px per pt = the SVG's own width / 249.45), read from the SVG;
//! - every decade inside a log axis carries a label (mc --sweep: the eta and SNR_P axes, whose
//!   ranges are read from the command's JSON);
//! - the bytes are the format the extension names (PNG magic, SVG text); .pdf is refused with
//!   an error naming the supported extensions and no file.

use crate::common;

use common::run;
use std::path::{Path, PathBuf};

/// One journal column in points: 8.8 cm / 2.54 cm per inch x 72 pt per inch.
const COLUMN_PT: f64 = 8.8 / 2.54 * 72.0;

/// A page's width in points (A&A: two columns and their gap, 18 cm).
const PAGE_PT: f64 = 18.0 / 2.54 * 72.0;

/// The width (pt) a figure `w` px wide is printed at: a column, or a page from 1800 px on
/// (the CLI's convention for figures of panels side by side).
fn printed_pt(w: f64) -> f64 {
    if w >= 1800.0 {
        PAGE_PT
    } else {
        COLUMN_PT
    }
}

fn svg_width(svg: &str) -> f64 {
    let at = svg.find("<svg width=\"").expect("an <svg width=...> element") + 12;
    svg[at..].split('"').next().unwrap().parse().unwrap()
}

/// Every (font-size in px, text) of an SVG written by plotters.
fn texts(svg: &str) -> Vec<(f64, String)> {
    let mut out = vec![];
    for part in svg.split("<text ").skip(1) {
        let fs = part.split("font-size=\"").nth(1).and_then(|r| r.split('"').next()).expect("font-size");
        let body = part.split_once('>').map(|(_, b)| b.split("</text>").next().unwrap_or("")).unwrap_or("");
        out.push((fs.parse().unwrap(), body.trim().to_string()));
    }
    out
}

/// The smallest text of `svg` in points at one column's width, and that text.
fn smallest_pt(svg: &str) -> (f64, String) {
    let px_per_pt = svg_width(svg) / printed_pt(svg_width(svg));
    texts(svg)
        .into_iter()
        .filter(|(_, t)| !t.is_empty())
        .map(|(px, t)| (px / px_per_pt, t))
        .fold((f64::INFINITY, String::new()), |a, b| if b.0 < a.0 { b } else { a })
}

fn assert_fonts(path: &Path) {
    let svg = std::fs::read_to_string(path).unwrap();
    assert!(!texts(&svg).is_empty(), "{}: no text", path.display());
    let (size, text) = smallest_pt(&svg);
    let at = printed_pt(svg_width(&svg));
    assert!(size >= 9.0 - 1e-9, "{}: '{text}' is {size:.2} pt printed {at:.1} pt wide", path.display());
}

fn magic(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap().into_iter().take(8).collect()
}

const PNG: &[u8] = b"\x89PNG\r\n\x1a\n";

fn fluxes(dir: &Path) -> String {
    let p = dir.join("f.csv");
    std::fs::write(&p, "hwp_deg,f_o,f_e\n0,1000,1100\n22.5,1050,1010\n45,1100,1000\n67.5,1010,1050\n90,1000,1095\n112.5,1049,1012\n135,1101,1001\n157.5,1012,1049\n").unwrap();
    p.to_str().unwrap().to_string()
}

#[test]
fn stokes_plot_fonts_and_formats() {
    let d = tempfile::tempdir().unwrap();
    let input = fluxes(d.path());
    for name in ["f.svg", "f.png", "F.SVG"] {
        let out = d.path().join(name);
        let (code, _, err) = run(&["stokes", "--input", &input, "--plot", out.to_str().unwrap()]);
        assert_eq!(code, 0, "{err}");
        let m = magic(&out);
        if name.to_lowercase().ends_with(".png") {
            assert_eq!(m, PNG, "{name}");
        } else {
            assert!(m.starts_with(b"<svg"), "{name}: {m:?}");
            assert_fonts(&out);
        }
    }
}

/// raytrace and plan draw PNG or SVG by the extension (they drew PNG only), at >= 9 pt.
#[test]
fn raytrace_and_plan_plots_follow_the_extension() {
    let d = tempfile::tempdir().unwrap();
    for ext in ["svg", "png"] {
        let rt = d.path().join(format!("rt.{ext}"));
        let (code, _, err) =
            run(&["raytrace", "--instrument", "fors1", "--filter", "V", "--plot", rt.to_str().unwrap()]);
        assert_eq!(code, 0, "{err}");
        let pl = d.path().join(format!("plan.{ext}"));
        let args = ["plan", "--target-percent", "0.05", "--sky-rate", "2", "--bin", "200", "--candidate", "6.45:68.4"];
        let (code, _, err) = run(&[&args[..], &["--candidate", "4:10", "--plot", pl.to_str().unwrap()]].concat());
        assert_eq!(code, 0, "{err}");
        for f in [&rt, &pl] {
            if ext == "png" {
                assert_eq!(magic(f), PNG, "{}", f.display());
            } else {
                assert!(magic(f).starts_with(b"<svg"), "{}", f.display());
                assert_fonts(f);
            }
        }
    }
}

#[test]
fn pdf_is_refused_naming_the_supported_extensions() {
    let d = tempfile::tempdir().unwrap();
    let input = fluxes(d.path());
    let pdf = d.path().join("f.pdf");
    for args in [
        vec!["stokes", "--input", &input, "--plot", pdf.to_str().unwrap()],
        vec!["mc", "--sweep", "--trials", "10", "--plot", pdf.to_str().unwrap()],
    ] {
        let (code, out, err) = run(&args);
        assert_eq!(code, 2, "{args:?}: {out}");
        assert!(err.contains("f.pdf") && err.contains(".png and .svg"), "{err}");
        assert!(!pdf.exists(), "a refused plot leaves no file");
    }
}

#[test]
fn calibration_plots_fonts_and_formats() {
    let d = tempfile::tempdir().unwrap();
    let cal = d.path().join("cal.fits");
    let map = d.path().join("map.fits");
    common::write_v_sky_map(&map, |_| true);
    let (code, _, err) = run(&common::calibrate_v_args(&map, &cal));
    assert_eq!(code, 0, "{err}");
    let plots = d.path().join("plots");
    let (code, out, err) = run(&["plot", cal.to_str().unwrap(), "--out", plots.to_str().unwrap(), "--json"]);
    assert_eq!(code, 0, "{err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    let files: Vec<String> = j["outputs"].as_array().unwrap().iter().map(|v| v.as_str().unwrap().to_string()).collect();
    assert!(files.len() >= 4, "{files:?}");
    for f in &files {
        let p = Path::new(f);
        match p.extension().and_then(|e| e.to_str()) {
            Some("png") => assert_eq!(magic(p), PNG, "{f}"),
            Some("svg") => {
                assert!(magic(p).starts_with(b"<svg"), "{f}");
                assert_fonts(p);
            }
            other => panic!("{f}: unexpected extension {other:?}"),
        }
    }
}

/// The label plotters writes for a decade (the CLI's tick format: 0.1, 1, 10, 1e-6).
fn decade_label(k: i32) -> String {
    if (-3..5).contains(&k) {
        let v = 10f64.powi(k);
        let s = format!("{v:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("1e{k}")
    }
}

#[test]
fn mc_sweep_log_axes_label_every_decade() {
    let d = tempfile::tempdir().unwrap();
    let svg = d.path().join("sweep.svg");
    let (code, out, err) =
        run(&["mc", "--sweep", "--trials", "300", "--noise", "gauss-qu", "--plot", svg.to_str().unwrap(), "--json"]);
    assert_eq!(code, 0, "{err}");
    assert!(magic(&svg).starts_with(b"<svg"));
    assert_fonts(&svg);
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    let range = |key: &str, field: &str| {
        let v: Vec<f64> = j[key].as_array().unwrap().iter().map(|p| p[field].as_f64().unwrap()).collect();
        (v.iter().cloned().fold(f64::INFINITY, f64::min), v.iter().cloned().fold(0.0, f64::max))
    };
    let text = std::fs::read_to_string(&svg).unwrap();
    let labels: Vec<String> = texts(&text).into_iter().map(|t| t.1).collect();
    for (key, field) in [("deltap", "eta"), ("bias", "snr_p")] {
        let (lo, hi) = range(key, field);
        let (k0, k1) = ((lo.log10() - 1e-9).ceil() as i32, (hi.log10() + 1e-9).floor() as i32);
        assert!(k1 > k0, "{key}: the axis spans {lo}..{hi}, at least two decades expected");
        for k in k0..=k1 {
            let want = decade_label(k);
            assert!(labels.contains(&want), "{key}.{field}: decade {want} has no label in {labels:?}");
        }
    }
}

#[test]
fn mc_accuracy_png_magic() {
    let d = tempfile::tempdir().unwrap();
    let png = d.path().join("acc.png");
    let (code, _, err) =
        run(&["mc", "--accuracy-report", "--trials", "1000", "--noise", "gauss-qu", "--plot", png.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(magic(&png), PNG);
}

/// Every text of an SVG written by plotters: (x, y, anchor, its `dy`, plotters' font size in
/// px, rotated, text). plotters writes `font-size` as its size / 1.24 (the em).
fn placed_texts(svg: &str) -> Vec<(f64, f64, String, String, f64, bool, String)> {
    let attr = |part: &str, name: &str| -> Option<String> {
        part.split(&format!(" {name}=\"")).nth(1).and_then(|r| r.split('"').next()).map(str::to_string)
    };
    let mut out = vec![];
    for part in svg.split("<text").skip(1) {
        let head = part.split('>').next().unwrap_or("");
        let body = part.split_once('>').map(|(_, b)| b.split("</text>").next().unwrap_or("")).unwrap_or("");
        let text = body.trim().replace("&lt;", "<").replace("&gt;", ">").replace("&quot;", "\"").replace("&amp;", "&");
        let num = |n: &str| attr(head, n).and_then(|v| v.parse::<f64>().ok()).unwrap_or(f64::NAN);
        let anchor = attr(head, "text-anchor").unwrap_or_else(|| "start".into());
        let dy = attr(head, "dy").unwrap_or_default();
        out.push((num("x"), num("y"), anchor, dy, 1.24 * num("font-size"), head.contains("rotate("), text));
    }
    out
}

/// The width (px) the embedded DejaVu Sans gives `text` at plotters' size `size`: plotters'
/// own measure, the one it lays the text out with.
fn text_width(text: &str, size: f64) -> f64 {
    use plotters::prelude::*;
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
    });
    ("sans-serif", size).into_font().box_size(text).map(|(w, _)| w as f64).unwrap_or(0.0)
}

/// The texts of `svg` whose box reaches outside the image (a pixel of slack), as messages.
fn texts_outside(path: &Path) -> Vec<String> {
    let svg = std::fs::read_to_string(path).unwrap();
    let w = svg_width(&svg);
    let h: f64 = svg.split("height=\"").nth(1).and_then(|r| r.split('"').next()).unwrap().parse().unwrap();
    let mut bad = vec![];
    for (x, y, anchor, dy, size, rotated, text) in placed_texts(&svg) {
        if text.is_empty() {
            continue;
        }
        let len = text_width(&text, size);
        // Along the text, from the anchor.
        let (lo, hi) = match anchor.as_str() {
            "middle" => (-0.5 * len, 0.5 * len),
            "end" => (-len, 0.0),
            _ => (0.0, len),
        };
        // Across it, from the anchor (plotters' dy: top, bottom or centre at the anchor).
        let em = size / 1.24;
        let (a, b) = match dy.as_str() {
            "0.76em" => (0.0, em),
            "-0.5ex" => (-em, 0.0),
            _ => (-0.5 * em, 0.5 * em),
        };
        // Rotated texts (the y-axis titles, by 270 deg) run upwards from their anchor, and
        // what lies below the text before the turn lies right of it after.
        let (x0, x1, y0, y1) = if rotated { (x + a, x + b, y - hi, y - lo) } else { (x + lo, x + hi, y + a, y + b) };
        if x0 < -1.0 || x1 > w + 1.0 || y0 < -1.0 || y1 > h + 1.0 {
            bad.push(format!("{}: '{text}' spans x {x0:.0}..{x1:.0}, y {y0:.0}..{y1:.0} in {w} x {h}", path.display()));
        }
    }
    bad
}

/// No text falls outside the figure, in the stokes plot (its title was cut at the left edge
/// at 1000 px) and in the calibration plots: measured with plotters' own text width.
#[test]
fn no_text_falls_outside_the_figures() {
    let d = tempfile::tempdir().unwrap();
    let svg = d.path().join("fourier.svg");
    let csv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/fors1_v_star_n16.csv");
    let (code, _, err) = run(&["stokes", "--input", csv.to_str().unwrap(), "--plot", svg.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let mut bad = texts_outside(&svg);
    let cal = d.path().join("cal.fits");
    let map = d.path().join("map.fits");
    common::write_v_sky_map(&map, |_| true);
    let (code, _, err) = run(&common::calibrate_v_args(&map, &cal));
    assert_eq!(code, 0, "{err}");
    let plots = d.path().join("plots");
    let (code, _, err) = run(&["plot", cal.to_str().unwrap(), "--out", plots.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let mut n = 1;
    for e in std::fs::read_dir(&plots).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "svg") {
            bad.extend(texts_outside(&p));
            n += 1;
        }
    }
    assert!(n >= 4, "{n} figures");
    assert!(bad.is_empty(), "{}", bad.join("\n"));
    // The measure itself: a longer text is wider, and the old stokes title at 10 pt on 1000 px
    // (plotters' size 50) was wider than the figure.
    assert!(text_width("N = 16: P = 0.421 ± 0.022 %, χ = 21.11 deg", 50.0) > 900.0);
}

/// `(x, y, width, height)` of an SVG element's attributes, or its circle `(cx, cy, r, r)`.
fn geometry(head: &str) -> Option<(f64, f64, f64, f64)> {
    let num = |n: &str| head.split(&format!(" {n}=\"")).nth(1)?.split('"').next()?.parse::<f64>().ok();
    if head.starts_with("circle") {
        return Some((num("cx")?, num("cy")?, num("r")?, num("r")?));
    }
    Some((num("x")?, num("y")?, num("width")?, num("height")?))
}

/// The vertices of a polyline's or polygon's `points`.
fn points(e: &str) -> Vec<(f64, f64)> {
    let pts = e.split("points=\"").nth(1).and_then(|r| r.split('"').next()).unwrap_or("");
    pts.split_whitespace()
        .filter_map(|p| p.split_once(','))
        .filter_map(|(x, y)| Some((x.parse::<f64>().ok()?, y.parse::<f64>().ok()?)))
        .collect()
}

/// Whether the segment `a`-`b` meets the box `(x0, y0, x1, y1)` (Liang-Barsky clipping: the
/// part of the segment inside each of the four half-planes, intersected).
fn segment_meets(a: (f64, f64), b: (f64, f64), (x0, y0, x1, y1): (f64, f64, f64, f64)) -> bool {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [(-dx, a.0 - x0), (dx, x1 - a.0), (-dy, a.1 - y0), (dy, y1 - a.1)] {
        if p == 0.0 {
            if q < 0.0 {
                return false;
            }
        } else if p < 0.0 {
            t0 = t0.max(q / p);
        } else {
            t1 = t1.min(q / p);
        }
    }
    t0 <= t1
}

/// The legend boxes of `svg`'s elements: (index of the bordered rectangle, its box `(x0, y0,
/// x1, y1)`). plotters draws a legend as a translucent white rectangle and a bordered one of
/// the same geometry.
fn legend_boxes(elems: &[&str]) -> Vec<(usize, (f64, f64, f64, f64))> {
    let mut out = vec![];
    for (i, e) in elems.iter().enumerate() {
        let is_border = e.starts_with("rect") && e.contains("fill=\"none\"") && !e.contains("stroke=\"none\"");
        let Some((x, y, w, h)) = is_border.then(|| geometry(e)).flatten() else { continue };
        if i > 0 && elems[i - 1].starts_with("rect") && geometry(elems[i - 1]) == Some((x, y, w, h)) {
            out.push((i, (x, y, x + w, y + h)));
        }
    }
    out
}

/// The plotted points (circles, polygons' vertices), lines (polylines' segments) and bars
/// (filled rectangles that are not a white background) of `svg` that fall inside a legend box
/// drawn after them, as messages.
/// plotters draws a legend as a translucent white rectangle and a bordered one of the same
/// geometry, after the series of its chart and before its own keys: what comes before the
/// box in the file is data.
fn legend_overlaps(path: &Path) -> Vec<String> {
    let svg = std::fs::read_to_string(path).unwrap();
    let elems: Vec<&str> = svg.split('<').skip(1).collect();
    let mut bad = vec![];
    for (i, (lx, ly, x1, y1)) in legend_boxes(&elems) {
        let (lw, lh) = (x1 - lx, y1 - ly);
        let inside = |x: f64, y: f64, pad: f64| x + pad > lx && x - pad < lx + lw && y + pad > ly && y - pad < ly + lh;
        for d in &elems[..i - 1] {
            let hit = if d.starts_with("circle") {
                geometry(d).is_some_and(|(cx, cy, r, _)| inside(cx, cy, r))
            } else if d.starts_with("rect") && !d.contains("fill=\"#FFFFFF\"") && !d.contains("fill=\"none\"") {
                geometry(d).is_some_and(|(x, y, w, h)| x < lx + lw && x + w > lx && y < ly + lh && y + h > ly)
            } else if d.starts_with("polygon") {
                points(d).iter().any(|&(x, y)| inside(x, y, 0.0))
            } else if d.starts_with("polyline") {
                // A line crosses the box even when none of its vertices is inside it.
                let p = points(d);
                p.windows(2).any(|w| segment_meets(w[0], w[1], (lx + 0.5, ly + 0.5, lx + lw - 0.5, ly + lh - 0.5)))
            } else {
                false
            };
            if hit {
                let d: String = d.chars().take(90).collect();
                bad.push(format!("{}: legend at ({lx}, {ly}) {lw} x {lh} covers <{d}", path.display()));
            }
        }
    }
    bad
}

/// Every figure a command draws, as SVG ([`every_figure`]): no legend box covers a plotted
/// point, line or bar, and no text falls outside the image.
#[test]
fn every_figure_keeps_its_legends_off_the_data() {
    let d = tempfile::tempdir().unwrap();
    let figures = every_figure(d.path());
    assert!(figures.len() >= 8, "{figures:?}");
    let mut bad = vec![];
    for f in &figures {
        assert!(magic(f).starts_with(b"<svg"), "{}", f.display());
        bad.extend(legend_overlaps(f));
        bad.extend(texts_outside(f));
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// The overlap check sees what it looks for: a legend drawn over a point, a bar and a line.
#[test]
fn the_legend_check_sees_a_covered_point_bar_and_line() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("x.svg");
    std::fs::write(
        &f,
        "<svg width=\"100\" height=\"100\">\n<circle cx=\"50\" cy=\"50\" r=\"3\" fill=\"#0000FF\"/>\n\
         <rect x=\"60\" y=\"80\" width=\"10\" height=\"30\" opacity=\"0.5\" fill=\"#FF0000\" stroke=\"none\"/>\n\
         <circle cx=\"5\" cy=\"5\" r=\"3\" fill=\"#0000FF\"/>\n\
         <rect x=\"40\" y=\"40\" width=\"40\" height=\"45\" opacity=\"0.85\" fill=\"#FFFFFF\" stroke=\"none\"/>\n\
         <rect x=\"40\" y=\"40\" width=\"40\" height=\"45\" opacity=\"1\" fill=\"none\" stroke=\"#000000\"/>\n\
         <circle cx=\"50\" cy=\"50\" r=\"3\" fill=\"#0000FF\"/>\n</svg>\n",
    )
    .unwrap();
    let bad = legend_overlaps(&f);
    assert_eq!(bad.len(), 2, "{bad:?}");
    assert!(bad[0].contains("circle cx=\"50\"") && bad[1].contains("rect x=\"60\""), "{bad:?}");
    // A line whose vertices are all outside the box but which crosses it, and one that passes by.
    let svg = std::fs::read_to_string(&f).unwrap().replacen(
        "<circle cx=\"5\"",
        "<polyline fill=\"none\" stroke=\"#000000\" stroke-width=\"2\" points=\"10,60 95,70 \"/>\n\
         <polyline fill=\"none\" stroke=\"#000000\" stroke-width=\"2\" points=\"10,90 95,99 \"/>\n<circle cx=\"5\"",
        1,
    );
    std::fs::write(&f, svg).unwrap();
    let bad = legend_overlaps(&f);
    assert!(bad.len() == 3 && bad.iter().any(|b| b.contains("points=\"10,60")), "{bad:?}");
}

/// Every figure the commands draw, as SVG in `dir`: the gallery's (calibration map, profile
/// and residual; the Fourier plot), raytrace, plan, mc's sweep and accuracy report, a telescope
/// fit of the EFOSC2 standards (real data, when present).
fn every_figure(dir: &Path) -> Vec<PathBuf> {
    let s = |n: &str| dir.join(n).to_str().unwrap().to_string();
    let csv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/fors1_v_star_n16.csv");
    let words = |w: &[&str], out: &str| w.iter().map(|x| x.to_string()).chain([s(out)]).collect::<Vec<String>>();
    let runs: Vec<Vec<String>> = vec![
        vec!["stokes".into(), "--input".into(), csv.display().to_string(), "--plot".into(), s("fourier.svg")],
        words(&["raytrace", "--instrument", "fors1", "--filter", "V", "--plot"], "rt.svg"),
        common::QUICK_PLAN.iter().chain(&["--plot"]).map(|x| x.to_string()).chain([s("plan.svg")]).collect(),
        words(&["mc", "--sweep", "--trials", "2000", "--plot"], "sweep.svg"),
        words(&["mc", "--accuracy-report", "--trials", "100000", "--noise", "gauss-qu", "--plot"], "acc.svg"),
    ];
    let mut figures = vec![];
    for args in &runs {
        let a: Vec<&str> = args.iter().map(|x| x.as_str()).collect();
        let (code, _, err) = run(&a);
        assert_eq!(code, 0, "{a:?}: {err}");
        figures.push(PathBuf::from(args.last().unwrap()));
    }
    let (cal, map) = (dir.join("cal.fits"), dir.join("map.fits"));
    common::write_v_sky_map(&map, |_| true);
    let (code, _, err) = run(&common::calibrate_v_args(&map, &cal));
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = run(&["plot", cal.to_str().unwrap(), "--out", &s("plots")]);
    assert_eq!(code, 0, "{err}");
    if let Some(d) =
        crate::common::shared_data::shared_data("efosc2-standards", &["pv_standards.txt"], "the telescope-fit figure")
    {
        let efosc2 = d.join("pv_standards.txt");
        let (code, _, err) =
            run(&["fit-standards", efosc2.to_str().unwrap(), "--model", "wiersema", "--plot-dir", &s("plots")]);
        assert_eq!(code, 0, "{err}");
    }
    for e in std::fs::read_dir(dir.join("plots")).unwrap() {
        let f = e.unwrap().path();
        if f.extension().is_some_and(|x| x == "svg") {
            figures.push(f);
        }
    }
    figures
}

/// Height over width of a figure printed one column wide: at most 1.4 (12.3 cm at a column's
/// 8.8 cm, half a journal page), panels and all; across a page, at most 1.3 (23.4 cm at 18 cm,
/// the height of a page's text).
const MAX_ASPECT: f64 = 1.4;
const MAX_PAGE_ASPECT: f64 = 1.3;

fn svg_height(svg: &str) -> f64 {
    svg.split("height=\"").nth(1).and_then(|r| r.split('"').next()).unwrap().parse().unwrap()
}

fn aspect_problems(name: &str, svg: &str) -> Vec<String> {
    let (w, h) = (svg_width(svg), svg_height(svg));
    let (width_cm, most) = if printed_pt(w) == PAGE_PT { (18.0, MAX_PAGE_ASPECT) } else { (8.8, MAX_ASPECT) };
    let cm = h / w * width_cm;
    if h / w > most {
        return vec![format!("{name}: {w} x {h} px is {cm:.1} cm tall at {width_cm} cm wide (at most {most} x)")];
    }
    vec![]
}

/// A tick label's value: plain (`0.25`, `-4`, `10000`), exponent (`1e-4`) or a power of ten
/// (`10⁻⁴`, `10³`), with its notation.
fn tick_value(t: &str) -> Option<(f64, &'static str)> {
    if let Some(e) = t.strip_prefix("10").filter(|e| !e.is_empty() && e.chars().all(|c| "⁻⁰¹²³⁴⁵⁶⁷⁸⁹".contains(c)))
    {
        let digits: String = e
            .chars()
            .map(|c| match c {
                '⁻' => '-',
                c => char::from_digit("⁰¹²³⁴⁵⁶⁷⁸⁹".chars().position(|d| d == c).unwrap() as u32, 10).unwrap(),
            })
            .collect();
        return digits.parse::<i32>().ok().map(|k| (10f64.powi(k), "power"));
    }
    let v: f64 = t.parse().ok()?;
    Some((v, if t.contains('e') { "exponent" } else { "plain" }))
}

/// The tick labels of each axis: x axes (labels below a line, centred) grouped by their row,
/// y axes and colour bars (labels ended or started at a column) by their column; a figure
/// drawn twice (measured, cleared, redrawn) repeats labels, counted once.
fn tick_groups(svg: &str) -> Vec<(String, Vec<(f64, String)>)> {
    let mut groups: std::collections::BTreeMap<String, Vec<(f64, String)>> = Default::default();
    let placed = placed_texts(svg);
    let is_x = |t: &(f64, f64, String, String, f64, bool, String)| t.2 == "middle" && t.3 == "0.76em" && !t.5;
    let x_rows: Vec<(f64, f64)> =
        placed.iter().filter(|t| is_x(t) && tick_value(&t.6).is_some()).map(|t| (t.0, t.1)).collect();
    for (x, y, anchor, dy, _, rotated, text) in placed.iter().cloned() {
        if rotated || tick_value(&text).is_none() {
            continue;
        }
        // A y axis's panel: the x axis below it (the nearest row of x tick labels right of its
        // labels: a panel beside it may be of another height).
        let panel = x_rows.iter().filter(|r| r.1 > y && r.0 > x).map(|r| r.1).fold(f64::INFINITY, f64::min);
        let (key, at) = match (anchor.as_str(), dy.as_str()) {
            ("middle", "0.76em") => (format!("x axis at row {y}"), x),
            ("end", _) | ("start", "0.5ex") => (format!("y axis ({anchor}) at column {x} above row {panel}"), y),
            _ => continue,
        };
        let g = groups.entry(key).or_default();
        if !g.iter().any(|(a, t)| *a == at && *t == text) {
            g.push((at, text));
        }
    }
    groups.into_iter().collect()
}

/// Each axis carries at least three labelled ticks, in one notation.
fn tick_problems(name: &str, svg: &str) -> Vec<String> {
    let mut bad = vec![];
    for (axis, labels) in tick_groups(svg) {
        let texts: Vec<&str> = labels.iter().map(|l| l.1.as_str()).collect();
        if labels.len() < 3 {
            bad.push(format!("{name}: {axis} has {} labelled tick(s) {texts:?}, at least 3 wanted", labels.len()));
        }
        let mut kinds: Vec<&str> = texts.iter().filter_map(|t| tick_value(t)).map(|v| v.1).collect();
        kinds.sort();
        kinds.dedup();
        if kinds.len() > 1 {
            bad.push(format!("{name}: {axis} mixes notations {kinds:?} in {texts:?}"));
        }
    }
    bad
}

/// Greek written as an ASCII word, a LaTeX label, "um" for µm, a "(s)" plural or a list
/// printed as code, in `text`.
fn text_problem(text: &str) -> Option<String> {
    const GREEK: [&str; 11] =
        ["eta", "Delta", "delta", "sigma", "chi", "phi", "lambda", "alpha", "theta", "kappa", "mu"];
    for t in text.split(|c: char| !c.is_alphanumeric()) {
        if GREEK.contains(&t) || GREEK.contains(&t.trim_end_matches(|c: char| c.is_ascii_digit())) {
            return Some(format!("the Greek letter '{t}' spelled in ASCII"));
        }
        let unit = t.strip_suffix("um").is_some_and(|n| n.is_empty() || n.chars().all(|c| c.is_ascii_digit()));
        if unit && (t != "um" || text.contains(" um")) {
            return Some("'um' for µm".into());
        }
    }
    for label in ["fig:", "eq:", "tab:", "sec:", "\\"] {
        if text.contains(label) {
            return Some(format!("a LaTeX label or command '{label}'"));
        }
    }
    if text.split("(s)").next().is_some_and(|b| b.len() < text.len() && b.ends_with(char::is_alphabetic)) {
        return Some("a '(s)' plural".into());
    }
    let list = text
        .split('[')
        .skip(1)
        .any(|r| r.split(']').next().is_some_and(|l| !l.is_empty() && l.split(", ").all(|n| n.parse::<i64>().is_ok())));
    list.then(|| "a list printed as code ('[0, 1]')".into())
}

fn text_problems(name: &str, svg: &str) -> Vec<String> {
    let mut seen = std::collections::BTreeSet::new();
    placed_texts(svg)
        .into_iter()
        .filter(|t| seen.insert(t.6.clone()))
        .filter_map(|t| text_problem(&t.6).map(|why| format!("{name}: '{}': {why}", t.6)))
        .collect()
}

/// `#RRGGBB` as 0..1 channels, seen through `opacity` on white.
fn colour(hex: &str, opacity: f64) -> Option<[f64; 3]> {
    let h = hex.strip_prefix('#').filter(|h| h.len() == 6)?;
    let ch = |i: usize| u8::from_str_radix(&h[i..i + 2], 16).ok().map(|v| v as f64 / 255.0);
    let o = opacity.clamp(0.0, 1.0);
    Some([ch(0)?, ch(2)?, ch(4)?].map(|c| 1.0 - o + o * c))
}

/// WCAG relative luminance of an sRGB colour.
fn luminance(c: [f64; 3]) -> f64 {
    let lin = |v: f64| if v <= 0.04045 { v / 12.92 } else { ((v + 0.055) / 1.055).powf(2.4) };
    0.2126 * lin(c[0]) + 0.7152 * lin(c[1]) + 0.0722 * lin(c[2])
}

/// WCAG contrast ratio against white: 3 is its least for graphics.
fn contrast_on_white(c: [f64; 3]) -> f64 {
    1.05 / (luminance(c) + 0.05)
}

/// Hue in degrees and saturation (HSV) of a colour.
fn hue_sat(c: [f64; 3]) -> (f64, f64) {
    let (mx, mn) = (c[0].max(c[1]).max(c[2]), c[0].min(c[1]).min(c[2]));
    let d = mx - mn;
    if d < 1e-9 {
        return (0.0, 0.0);
    }
    let h = if mx == c[0] {
        60.0 * ((c[1] - c[2]) / d).rem_euclid(6.0)
    } else if mx == c[1] {
        60.0 * ((c[2] - c[0]) / d + 2.0)
    } else {
        60.0 * ((c[0] - c[1]) / d + 4.0)
    };
    (h, d / mx)
}

/// The colours lines and markers are drawn in (polylines' and paths' strokes, circles' and
/// polygons' fills and strokes; not the rectangles of colour images and bars), with the
/// stroke width of each line.
fn drawn_colours(svg: &str) -> Vec<(String, [f64; 3], f64)> {
    let attr =
        |e: &str, n: &str| e.split(&format!(" {n}=\"")).nth(1).and_then(|r| r.split('"').next()).map(str::to_string);
    let mut out = vec![];
    for e in svg.split('<').skip(1) {
        let e = e.split('>').next().unwrap_or("");
        let line = e.starts_with("polyline") || e.starts_with("path") || e.starts_with("line ");
        let marker = e.starts_with("circle") || e.starts_with("polygon");
        if !(line || marker) {
            continue;
        }
        let opacity: f64 = attr(e, "opacity").and_then(|o| o.parse().ok()).unwrap_or(1.0);
        let width = attr(e, "stroke-width").and_then(|o| o.parse().ok()).unwrap_or(1.0);
        for key in ["stroke", "fill"] {
            if let Some(c) = attr(e, key).and_then(|h| colour(&h, opacity).map(|c| (h, c))) {
                out.push((c.0, c.1, if key == "stroke" { width } else { f64::INFINITY }));
            }
        }
    }
    out
}

/// Lines and markers stand out on white (contrast >= 3, WCAG's least for graphics; white
/// itself only as a line of at least 0.5 pt over an image, never a hairline); no two series
/// told apart by red against green alone.
fn colour_problems(name: &str, svg: &str) -> Vec<String> {
    let px_per_pt = svg_width(svg) / printed_pt(svg_width(svg));
    let mut bad = std::collections::BTreeSet::new();
    let drawn = drawn_colours(svg);
    for (hex, c, width) in &drawn {
        if luminance(*c) > 0.99 {
            if *width < 0.5 * px_per_pt {
                bad.insert(format!("{name}: a white line {width} px wide ({:.2} pt): a hairline", width / px_per_pt));
            }
        } else if hue_sat(*c).1 > 0.05 && contrast_on_white(*c) < 3.0 {
            bad.insert(format!("{name}: {hex} has contrast {:.2} on white (at least 3)", contrast_on_white(*c)));
        }
    }
    let saturated = || drawn.iter().filter(|d| hue_sat(d.1).1 > 0.4);
    let red = saturated().find(|d| hue_sat(d.1).0 <= 15.0 || hue_sat(d.1).0 >= 345.0);
    let green = saturated().find(|d| (75.0..=150.0).contains(&hue_sat(d.1).0));
    if let (Some(r), Some(g)) = (red, green) {
        bad.insert(format!("{name}: red {} and green {} series", r.0, g.0));
    }
    bad.into_iter().collect()
}

/// The plotting areas of `svg`: where plotters' y axis line (a vertical black line one pixel
/// left of the area) meets its x axis line (a horizontal one one pixel below it), as `(x0, y0,
/// x1, y1)`.
fn plotting_areas(elems: &[&str]) -> Vec<(f64, f64, f64, f64)> {
    let axis_lines: Vec<((f64, f64), (f64, f64))> = elems
        .iter()
        .filter(|e| e.starts_with("polyline") && e.contains("stroke=\"#000000\" stroke-width=\"1\""))
        .filter_map(|e| match points(e)[..] {
            [a, b] => Some((a, b)),
            _ => None,
        })
        .collect();
    let mut out = vec![];
    for &((vx, va), (vx2, vb)) in &axis_lines {
        let (ya, yb) = (va.min(vb), va.max(vb));
        if vx != vx2 || yb - ya < 20.0 {
            continue;
        }
        for &((ha, hy), (hb, hy2)) in &axis_lines {
            let (xa, xb) = (ha.min(hb), ha.max(hb));
            if hy == hy2 && xb - xa >= 20.0 && (xa - (vx + 1.0)).abs() <= 1.5 && (hy - (yb + 1.0)).abs() <= 1.5 {
                let a = (xa, ya, xb, yb);
                if !out.contains(&a) {
                    out.push(a);
                }
            }
        }
    }
    out
}

/// The share of each side of a plotting area (x0, y0, x1, y1) that the data leave empty:
/// `[left, right, top, bottom]` as fractions of the area's width and height, from every line
/// vertex, marker, polygon vertex and filled (non-white) rectangle inside the area that is
/// not part of a legend. None when the area holds no data.
fn empty_margins(elems: &[&str], (x0, y0, x1, y1): (f64, f64, f64, f64)) -> Option<[f64; 4]> {
    let boxes = legend_boxes(elems);
    let in_box = |(x, y): (f64, f64), b: &(f64, f64, f64, f64)| x >= b.0 && x <= b.2 && y >= b.1 && y <= b.3;
    let inside = |(x, y): (f64, f64)| x >= x0 - 0.5 && x <= x1 + 0.5 && y >= y0 - 0.5 && y <= y1 + 0.5;
    let (mut lo, mut hi) = ((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY));
    for e in elems {
        let p: Vec<(f64, f64)> = if e.starts_with("polyline") || e.starts_with("polygon") {
            points(e)
        } else if e.starts_with("circle") {
            geometry(e).map(|(x, y, _, _)| vec![(x, y)]).unwrap_or_default()
        } else if e.starts_with("rect") && !e.contains("fill=\"#FFFFFF\"") && !e.contains("fill=\"none\"") {
            geometry(e).map(|(x, y, w, h)| vec![(x, y), (x + w, y + h)]).unwrap_or_default()
        } else {
            vec![]
        };
        // A legend's own keys lie inside its box.
        if p.is_empty() || boxes.iter().any(|(_, b)| p.iter().all(|&q| in_box(q, b))) {
            continue;
        }
        for q in p.into_iter().filter(|&q| inside(q)) {
            lo = (lo.0.min(q.0), lo.1.min(q.1));
            hi = (hi.0.max(q.0), hi.1.max(q.1));
        }
    }
    let (w, h) = (x1 - x0, y1 - y0);
    lo.0.is_finite().then(|| [(lo.0 - x0) / w, (x1 - hi.0) / w, (lo.1 - y0) / h, (y1 - hi.1) / h])
}

/// How far an axis may run past the data: 5 % of its length on each side.
const MAX_EMPTY_MARGIN: f64 = 0.05;

/// Each plotting area's axes end within 5 % of the data on every side.
fn axis_problems(name: &str, svg: &str) -> Vec<String> {
    let elems: Vec<&str> = svg.split('<').skip(1).collect();
    let mut bad = vec![];
    for a in plotting_areas(&elems) {
        let Some(m) = empty_margins(&elems, a) else { continue };
        for (side, v) in ["left", "right", "top", "bottom"].iter().zip(m) {
            if v > MAX_EMPTY_MARGIN {
                bad.push(format!(
                    "{name}: the plotting area at ({}, {}) runs {:.0} % of its size past the data on the {side} (at most {:.0} %)",
                    a.0,
                    a.1,
                    100.0 * v,
                    100.0 * MAX_EMPTY_MARGIN
                ));
            }
        }
    }
    bad
}

/// Every figure reads in print: a column's or half a page's height, three labelled ticks an
/// axis in one notation, axes that end within 5 % of the data, colours that stand out and differ for colour-blind readers, and
/// words a journal prints (no LaTeX labels, no Greek in ASCII, µm, plurals).
#[test]
fn every_figure_reads_in_print() {
    let d = tempfile::tempdir().unwrap();
    let figures = every_figure(d.path());
    assert!(figures.len() >= 8, "{figures:?}");
    let mut bad = vec![];
    for f in &figures {
        let svg = std::fs::read_to_string(f).unwrap();
        let name = f.file_name().unwrap().to_string_lossy().to_string();
        bad.extend(aspect_problems(&name, &svg));
        bad.extend(tick_problems(&name, &svg));
        bad.extend(text_problems(&name, &svg));
        bad.extend(colour_problems(&name, &svg));
        bad.extend(axis_problems(&name, &svg));
    }
    assert!(bad.is_empty(), "{} problems:\n{}", bad.len(), bad.join("\n"));
}

/// The print checks see what they look for, on made-up cases.
#[test]
fn the_print_checks_see_each_problem() {
    assert!(text_problem("fig:deltap  bias").is_some());
    assert!(text_problem("eta = P0 SNR").is_some());
    assert!(text_problem("Delta P / sigma_P").is_some());
    assert!(text_problem("0.550um: model").is_some());
    assert!(text_problem("2 field(s) [0, 1]").is_some());
    assert!(text_problem("fields 1 and 2").is_none());
    assert!(text_problem("total observing time (s)").is_none());
    assert!(text_problem("chi2/dof").is_some());
    assert!(text_problem("V (0.550 µm): Wiersema model, χ²/dof = 1.32").is_none());
    assert!(text_problem("ΔP / σ_P against η = P₀ SNR; beta, zeta, theta_x").is_some());
    assert!(contrast_on_white(colour("#FFE119", 1.0).unwrap()) < 3.0);
    assert!(contrast_on_white(colour("#0072B2", 1.0).unwrap()) > 3.0);
    let svg = "<svg width=\"1000\" height=\"600\">\n<polyline stroke=\"#FF0000\" stroke-width=\"2\"/>\n\
               <polyline stroke=\"#00A000\" stroke-width=\"2\"/>\n<path stroke=\"#FFFFFF\" stroke-width=\"1\"/>\n</svg>";
    let bad = colour_problems("x", svg);
    assert!(bad.iter().any(|b| b.contains("green")) && bad.iter().any(|b| b.contains("hairline")), "{bad:?}");
    assert_eq!(aspect_problems("x", "<svg width=\"1000\" height=\"2400\">").len(), 1);
    assert_eq!(aspect_problems("x", "<svg width=\"1000\" height=\"1300\">").len(), 0);
    assert_eq!(aspect_problems("x", "<svg width=\"2000\" height=\"2700\">").len(), 1);
    let ticks = |labels: &[&str]| -> String {
        labels
            .iter()
            .enumerate()
            .map(|(i, t)| {
                format!(
                    "<text x=\"{}\" y=\"900\" dy=\"0.76em\" text-anchor=\"middle\" font-size=\"40\">{t}</text>\n",
                    100 * i
                )
            })
            .collect()
    };
    assert_eq!(tick_problems("x", &ticks(&["0"])).len(), 1);
    assert_eq!(tick_problems("x", &ticks(&["1000", "10000", "1e5"])).len(), 1);
    assert_eq!(tick_problems("x", &ticks(&["10³", "10⁴", "10⁵"])).len(), 0);
    assert_eq!(tick_value("10⁻⁴"), Some((1e-4, "power")));
    // An area 100 x 100 px whose data fill x but only the lower 80 % of y, beside a legend
    // whose keys sit higher: 20 % empty at the top, the keys not counted.
    let axes = "<svg width=\"400\" height=\"400\">\n\
                <polyline fill=\"none\" opacity=\"1\" stroke=\"#000000\" stroke-width=\"1\" points=\"99,100 99,200 \"/>\n\
                <polyline fill=\"none\" opacity=\"1\" stroke=\"#000000\" stroke-width=\"1\" points=\"100,201 200,201 \"/>\n\
                <polyline fill=\"none\" opacity=\"1\" stroke=\"#0072B2\" stroke-width=\"2\" points=\"100,200 150,120 200,190 \"/>\n\
                <rect x=\"150\" y=\"101\" width=\"40\" height=\"10\" opacity=\"0.85\" fill=\"#FFFFFF\" stroke=\"none\"/>\n\
                <rect x=\"150\" y=\"101\" width=\"40\" height=\"10\" opacity=\"1\" fill=\"none\" stroke=\"#000000\"/>\n\
                <polyline fill=\"none\" opacity=\"1\" stroke=\"#0072B2\" stroke-width=\"2\" points=\"152,105 160,105 \"/>\n</svg>";
    let bad = axis_problems("x", axes);
    assert!(bad.len() == 1 && bad[0].contains("20 %") && bad[0].contains("top"), "{bad:?}");
    assert!(axis_problems("x", &axes.replace("150,120", "150,102")).is_empty());
}

/// The colour bars' marks (short white lines across a bar, at the map's contour levels) that
/// carry no tick label level with them, as messages. A bar is a black outline (`fill="none"`)
/// of a narrow, tall rectangle; a mark is a white two-point line spanning its width; its label
/// a number written right of the bar within two pixels of the mark's row.
fn colour_bar_problems(name: &str, svg: &str) -> Vec<String> {
    let elems: Vec<&str> = svg.split('<').skip(1).collect();
    let bars: Vec<(f64, f64, f64, f64)> = elems
        .iter()
        .filter(|e| e.starts_with("rect") && e.contains("fill=\"none\"") && e.contains("stroke=\"#000000\""))
        .filter_map(|e| geometry(e))
        .filter(|&(_, _, w, h)| w > 0.0 && h > 4.0 * w)
        .collect();
    let labels: Vec<(f64, f64, String)> = placed_texts(svg)
        .into_iter()
        .filter(|t| t.2 == "start" && tick_value(&t.6).is_some())
        .map(|t| (t.0, t.1, t.6))
        .collect();
    let mut bad = vec![];
    for &(bx, by, bw, bh) in &bars {
        for e in elems.iter().filter(|e| e.starts_with("polyline") && e.contains("stroke=\"#FFFFFF\"")) {
            let [a, b] = points(e)[..] else { continue };
            let across = a.1 == b.1 && (a.0.min(b.0) - bx).abs() <= 1.0 && (a.0.max(b.0) - (bx + bw)).abs() <= 1.0;
            if !across || a.1 < by - 1.0 || a.1 > by + bh + 1.0 {
                continue;
            }
            let labelled = labels.iter().any(|l| l.0 > bx + bw && l.0 < bx + bw + 60.0 && (l.1 - a.1).abs() <= 2.0);
            if !labelled {
                bad.push(format!("{name}: the colour bar's mark at row {} has no label", a.1));
            }
        }
    }
    bad
}

/// The legend entries of `svg`: each text inside a legend box (a bordered translucent box, as
/// plotters and plot.rs draw one) or written right of a key (a marker or a short line ending
/// within two font sizes left of it, at its row), as (x, y, text), with the legend it belongs
/// to (its box, or its row).
fn legend_entries(svg: &str) -> Vec<(f64, f64, String, String)> {
    let elems: Vec<&str> = svg.split('<').skip(1).collect();
    let boxes = legend_boxes(&elems);
    let keys = key_marks(svg);
    placed_texts(svg)
        .into_iter()
        .filter(|t| !t.5 && !t.6.is_empty() && tick_value(&t.6).is_none())
        .filter(|t| {
            let in_box = boxes.iter().any(|(_, b)| t.0 >= b.0 && t.0 <= b.2 && t.1 >= b.1 && t.1 <= b.3);
            in_box
                || (t.2 == "start"
                    && keys.iter().any(|k| k.1 < t.0 && k.1 > t.0 - 2.0 * t.4 && (k.2 - t.1).abs() <= 3.0))
        })
        .map(|t| {
            let b = boxes.iter().find(|(_, b)| t.0 >= b.0 && t.0 <= b.2 && t.1 >= b.1 && t.1 <= b.3);
            let legend = b.map_or_else(|| format!("the row at {}", t.1), |(i, _)| format!("the legend box {i}"));
            (t.0, t.1, t.6, legend)
        })
        .collect()
}

/// Every marker (circle, polygon) and line of `svg` as (kind and fill, right end x, y): the
/// circles and polygons with their shape and colour, the lines as their stroke.
fn key_marks(svg: &str) -> Vec<(String, f64, f64)> {
    let attr = |e: &str, n: &str| {
        e.split(&format!(" {n}=\"")).nth(1).and_then(|r| r.split('"').next()).unwrap_or("").to_string()
    };
    let mut out = vec![];
    for e in svg.split('<').skip(1) {
        if e.starts_with("circle") {
            let Some((cx, cy, r, _)) = geometry(e) else { continue };
            out.push((format!("circle {}", attr(e, "fill")), cx + r, cy));
        } else if e.starts_with("polygon") {
            let p = points(e);
            let Some(right) = p.iter().map(|q| q.0).reduce(f64::max) else { continue };
            let cy = p.iter().map(|q| q.1).sum::<f64>() / p.len() as f64;
            out.push((format!("polygon {}", attr(e, "fill")), right, cy));
        } else if e.starts_with("polyline") {
            if let [a, b] = points(e)[..] {
                if a.1 == b.1 && (b.0 - a.0).abs() <= 30.0 {
                    out.push((format!("line {}", attr(e, "stroke")), a.0.max(b.0), a.1));
                }
            }
        }
    }
    out
}

/// No legend entry is written twice in a legend (one entry per kind of bar, not one per bar),
/// and the entry of a fitted curve says what was fitted: a function of its variable (`fit
/// p(r)`) or a quantity with its value (`fit, P = 0.421 %`); "fit" alone does not.
fn legend_text_problems(name: &str, svg: &str) -> Vec<String> {
    let entries = legend_entries(svg);
    let mut bad = vec![];
    let mut seen = std::collections::BTreeMap::<(String, String), usize>::new();
    for (_, _, t, legend) in &entries {
        *seen.entry((legend.clone(), t.clone())).or_default() += 1;
    }
    for ((legend, t), n) in seen.into_iter().filter(|s| s.1 > 1) {
        bad.push(format!("{name}: the legend entry '{t}' is written {n} times in {legend}"));
    }
    for (_, _, t, _) in entries.iter().filter(|e| e.2.split_whitespace().next().is_some_and(|w| w.starts_with("fit"))) {
        let valued =
            t.split(" = ").skip(1).any(|v| v.trim_start_matches('-').starts_with(|c: char| c.is_ascii_digit()));
        let function = t.split_whitespace().skip(1).any(|w| w.contains('(') && w.ends_with(')'));
        if !(valued || function) {
            bad.push(format!("{name}: the fit's legend entry '{t}' names no fitted quantity with its value"));
        }
    }
    bad
}

/// Each legend entry that names data ("data", "standards", "polarized") carries a marker left
/// of its words, and each such marker is of a shape and colour the plotted points have (a
/// marker of the same kind and fill outside every legend row).
fn legend_marker_problems(name: &str, svg: &str) -> Vec<String> {
    let marks = key_marks(svg);
    let is_marker = |m: &&(String, f64, f64)| !m.0.starts_with("line");
    let mut bad = vec![];
    let entries = legend_entries(svg);
    let near = |m: &(String, f64, f64), e: &(f64, f64, String, String)| {
        m.1 < e.0 && m.1 > e.0 - 60.0 && (m.2 - e.1).abs() <= 3.0
    };
    for e in entries.iter().filter(|e| ["data", "standards", "polarized"].iter().any(|w| e.2.contains(w))) {
        let keys: Vec<&(String, f64, f64)> = marks.iter().filter(is_marker).filter(|m| near(m, e)).collect();
        if keys.is_empty() {
            bad.push(format!("{name}: the legend entry '{}' names data but shows no marker", e.2));
        }
        for k in keys {
            let plotted = marks.iter().filter(is_marker).any(|m| m.0 == k.0 && !entries.iter().any(|e| near(m, e)));
            if !plotted {
                bad.push(format!("{name}: the legend entry '{}' shows a {} no plotted point has", e.2, k.0));
            }
        }
    }
    bad
}

/// Each axis's labelled ticks reach its ends: the stretch of an axis past its last label, at
/// either end, is at most a third of the axis (a log axis labelled only in its lower half
/// fails). Axes are the plotting areas' ([`plotting_areas`]); their labels the numbers written
/// under the x axis and left of the y axis.
fn axis_end_problems(name: &str, svg: &str) -> Vec<String> {
    let elems: Vec<&str> = svg.split('<').skip(1).collect();
    let placed = placed_texts(svg);
    let mut bad = vec![];
    for (x0, y0, x1, y1) in plotting_areas(&elems) {
        let numbers = |t: &&(f64, f64, String, String, f64, bool, String)| !t.5 && tick_value(&t.6).is_some();
        let xs: Vec<f64> = placed
            .iter()
            .filter(numbers)
            .filter(|t| t.2 == "middle" && t.3 == "0.76em" && t.0 >= x0 - 1.0 && t.0 <= x1 + 1.0)
            .filter(|t| t.1 > y1 && t.1 < y1 + 2.0 * t.4)
            .map(|t| t.0)
            .collect();
        let ys: Vec<f64> = placed
            .iter()
            .filter(numbers)
            .filter(|t| t.2 == "end" && t.0 < x0 && t.0 > x0 - 8.0 * t.4 && t.1 >= y0 - 1.0 && t.1 <= y1 + 1.0)
            .map(|t| t.1)
            .collect();
        for (axis, at, lo, hi) in [("x", &xs, x0, x1), ("y", &ys, y0, y1)] {
            let (Some(a), Some(b)) = (at.iter().copied().reduce(f64::min), at.iter().copied().reduce(f64::max)) else {
                continue;
            };
            let len = hi - lo;
            for (end, gap) in [("low", a - lo), ("high", hi - b)] {
                // Screen rows grow downwards: a y axis's low end on screen is its top.
                let side = if axis == "y" {
                    if end == "low" {
                        "top"
                    } else {
                        "bottom"
                    }
                } else {
                    end
                };
                if gap > len / 3.0 + 1.0 {
                    bad.push(format!(
                        "{name}: the {axis} axis of the area at ({x0}, {y0}) has no label over its {side} {:.0} % ({at:?})",
                        100.0 * gap / len
                    ));
                }
            }
        }
    }
    bad
}

/// A Mueller field and the EFOSC2-like standards (two polarized): the figures `every_figure`
/// leaves out, drawn into `dir`: explain's candidates, a weak field's map (its p under 0.6 %,
/// so that one contour level falls inside its colour bar) and a telescope fit with polarized
/// standards (triangles in the legend).
fn more_figures(dir: &Path) -> Vec<PathBuf> {
    std::fs::create_dir_all(dir).unwrap();
    let s = |n: &str| dir.join(n).to_str().unwrap().to_string();
    let lens = crate::explain::write(dir, fit::mueller_field::Kind::diattenuation_retardance(), "lens_pub.json");
    let (code, _, err) =
        run(&["explain", lens.to_str().unwrap(), "--instrument", "fors1", "--band", "B", "--plot", &s("explain.svg")]);
    assert_eq!(code, 0, "{err}");
    let _ = std::fs::remove_file(&lens);
    // The inner bins of the V field (r < 2.1'): p up to about 0.5 %, whose
    // colour bar's round ticks (0, 0.2, 0.4) miss the 0.3 % contour.
    let (cal, map) = (dir.join("weak.fits"), dir.join("weak_map.fits"));
    let geom = skyfield::BinGeometry::covering(60, 0, 0, 2048, 2048, 0.2);
    common::write_v_sky_map(&map, move |k| {
        let c = geom.centre_arcmin(k % geom.nx, k / geom.nx);
        c.0.hypot(c.1) < 2.1
    });
    let (code, _, err) = run(&common::calibrate_v_args(&map, &cal));
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = run(&["plot", cal.to_str().unwrap(), "--out", &s("weak")]);
    assert_eq!(code, 0, "{err}");
    let csv = standards_csv(dir);
    let (code, _, err) =
        run(&["fit-standards", csv.to_str().unwrap(), "--model", "wiersema", "--plot-dir", &s("standards")]);
    assert_eq!(code, 0, "{err}");
    let mut out = vec![PathBuf::from(s("explain.svg"))];
    for sub in ["weak", "standards"] {
        for e in std::fs::read_dir(dir.join(sub)).unwrap() {
            let f = e.unwrap().path();
            if f.extension().is_some_and(|x| x == "svg") {
                out.push(f);
            }
        }
    }
    out
}

/// The standards of [`common::standards::polarized_standards_csv`], at 0.55 µm with no filter
/// column: `dir/standards.csv`.
fn standards_csv(dir: &Path) -> PathBuf {
    let path = dir.join("standards.csv");
    std::fs::write(&path, common::standards::polarized_standards_csv(None)).unwrap();
    path
}

/// The figures' words and marks, on every figure and those [`more_figures`] adds (explain,
/// a weak field's map, a fit of polarized standards): the print checks of
/// [`every_figure_reads_in_print`] and the legend-overlap checks, and colour-bar marks
/// labelled, legend entries written once with the fit's value, data markers in the legend as
/// plotted, every axis labelled to within a third of its ends.
#[test]
fn every_figure_labels_its_marks_and_keys() {
    let d = tempfile::tempdir().unwrap();
    let figures = every_figure(d.path());
    let more = more_figures(&d.path().join("more"));
    assert!(figures.len() >= 8 && more.len() >= 5, "{figures:?} {more:?}");
    let mut bad = vec![];
    for f in figures.iter().chain(&more) {
        let svg = std::fs::read_to_string(f).unwrap();
        let name = f.strip_prefix(d.path()).unwrap_or(f).to_string_lossy().to_string();
        bad.extend(colour_bar_problems(&name, &svg));
        bad.extend(legend_text_problems(&name, &svg));
        bad.extend(legend_marker_problems(&name, &svg));
        bad.extend(axis_end_problems(&name, &svg));
        // The figures every_figure draws pass the print checks in every_figure_reads_in_print.
        if more.contains(f) {
            bad.extend(aspect_problems(&name, &svg));
            bad.extend(tick_problems(&name, &svg));
            bad.extend(text_problems(&name, &svg));
            bad.extend(colour_problems(&name, &svg));
            bad.extend(axis_problems(&name, &svg));
            bad.extend(legend_overlaps(f));
            bad.extend(texts_outside(f));
        }
    }
    assert!(bad.is_empty(), "{} problems:\n{}", bad.len(), bad.join("\n"));
}

/// fit-standards names a band given by its wavelength as astronomers write it: the filter
/// there and the wavelength in nm ("V (550 nm)": Bessell's V is at 545-551 nm), on the console
/// and in the figure's title; never "0.550um".
#[test]
fn fit_standards_names_its_band_and_wavelength() {
    let d = tempfile::tempdir().unwrap();
    let csv = standards_csv(d.path());
    let plots = d.path().join("p");
    let (code, out, err) =
        run(&["fit-standards", csv.to_str().unwrap(), "--model", "wiersema", "--plot-dir", plots.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("V (550 nm)"), "{out}");
    let micron = |t: &str| t.strip_suffix("um").is_some_and(|n| n.parse::<f64>().is_ok());
    assert!(!out.split([' ', ':', ',', '(', ')']).any(micron) && !out.contains("µm"), "{out}");
    let svg = std::fs::read_to_string(plots.join("standards_wiersema_0.svg")).unwrap();
    assert!(placed_texts(&svg).iter().any(|t| t.6.starts_with("V (550 nm)")), "the title names the band");
}

/// The checks above see what they look for, on made-up figures.
#[test]
fn the_mark_and_key_checks_see_each_problem() {
    // A bar 20 x 200 px at (100, 100) with white marks at rows 160 (labelled) and 240 (not).
    let bar = "<svg width=\"400\" height=\"400\">\n\
               <rect x=\"100\" y=\"100\" width=\"20\" height=\"200\" opacity=\"1\" fill=\"none\" stroke=\"#000000\"/>\n\
               <polyline fill=\"none\" opacity=\"1\" stroke=\"#FFFFFF\" stroke-width=\"3\" points=\"100,160 120,160 \"/>\n\
               <polyline fill=\"none\" opacity=\"1\" stroke=\"#FFFFFF\" stroke-width=\"3\" points=\"100,240 120,240 \"/>\n\
               <text x=\"130\" y=\"160\" dy=\"0.5ex\" text-anchor=\"start\" font-size=\"20\">0.6</text>\n\
               <text x=\"130\" y=\"250\" dy=\"0.5ex\" text-anchor=\"start\" font-size=\"20\">0.2</text>\n</svg>";
    let bad = colour_bar_problems("x", bar);
    assert!(bad.len() == 1 && bad[0].contains("row 240"), "{bad:?}");
    // Legend entries: a box with "fit" alone and a bar's words twice.
    let legend = "<svg width=\"400\" height=\"400\">\n\
                  <rect x=\"10\" y=\"10\" width=\"200\" height=\"100\" opacity=\"0.85\" fill=\"#FFFFFF\" stroke=\"none\"/>\n\
                  <rect x=\"10\" y=\"10\" width=\"200\" height=\"100\" opacity=\"1\" fill=\"none\" stroke=\"#000000\"/>\n\
                  <text x=\"50\" y=\"30\" dy=\"0.5ex\" text-anchor=\"start\" font-size=\"20\">fit</text>\n\
                  <text x=\"50\" y=\"60\" dy=\"0.5ex\" text-anchor=\"start\" font-size=\"20\">k = 1 dust, 2 pleochroism</text>\n\
                  <text x=\"50\" y=\"90\" dy=\"0.5ex\" text-anchor=\"start\" font-size=\"20\">k = 1 dust, 2 pleochroism</text>\n</svg>";
    let bad = legend_text_problems("x", legend);
    assert!(bad.len() == 2 && bad.iter().any(|b| b.contains("2 times")), "{bad:?}");
    assert!(legend_text_problems("x", &legend.replace(">fit<", ">fit, P = 0.421 %<")).len() == 1);
    // A data entry whose key is a black triangle beside vermillion plotted triangles, and one
    // whose key is a line only.
    let keys = "<svg width=\"400\" height=\"400\">\n\
                <polygon points=\"200,200 206,210 194,210 \" opacity=\"1\" fill=\"#D55E00\"/>\n\
                <polygon points=\"20,300 26,310 14,310 \" opacity=\"1\" fill=\"#000000\"/>\n\
                <text x=\"40\" y=\"306\" dy=\"0.5ex\" text-anchor=\"start\" font-size=\"20\">polarized, own P removed</text>\n\
                <polyline fill=\"none\" opacity=\"1\" stroke=\"#D55E00\" stroke-width=\"2\" points=\"10,350 32,350 \"/>\n\
                <text x=\"40\" y=\"350\" dy=\"0.5ex\" text-anchor=\"start\" font-size=\"20\">q data, model</text>\n</svg>";
    let bad = legend_marker_problems("x", keys);
    assert!(bad.len() == 2 && bad[0].contains("polygon #000000") && bad[1].contains("no marker"), "{bad:?}");
    assert_eq!(legend_marker_problems("x", &keys.replace("fill=\"#000000\"", "fill=\"#D55E00\"")).len(), 1);
    // A y axis (rows 100..400) labelled at rows 400, 330, 300 only: its top 67 % unlabelled.
    let axes = |rows: &[f64]| -> String {
        let mut s = String::from(
            "<svg width=\"600\" height=\"600\">\n\
             <polyline fill=\"none\" opacity=\"1\" stroke=\"#000000\" stroke-width=\"1\" points=\"99,100 99,400 \"/>\n\
             <polyline fill=\"none\" opacity=\"1\" stroke=\"#000000\" stroke-width=\"1\" points=\"100,401 400,401 \"/>\n",
        );
        for (i, r) in rows.iter().enumerate() {
            s += &format!("<text x=\"90\" y=\"{r}\" dy=\"0.5ex\" text-anchor=\"end\" font-size=\"20\">{i}</text>\n");
        }
        s + "</svg>"
    };
    let bad = axis_end_problems("x", &axes(&[400.0, 330.0, 300.0]));
    assert!(bad.len() == 1 && bad[0].contains("top 67 %"), "{bad:?}");
    assert!(axis_end_problems("x", &axes(&[400.0, 300.0, 200.0])).is_empty());
}
