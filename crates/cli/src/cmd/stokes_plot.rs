//! `instpol stokes --plot FILE.png`: the paper's fig:fourier for one source. Upper panel, F_i
//! (eq:F) with their 1-sigma errors against the HWP angle, the eq:system curve through the
//! solver's Q/I and U/I and the a_0 level; lower panel, the harmonic amplitudes
//! (eq:fourcoeff) as bars with their noise level. Drawing only: the numbers are
//! [`data::fourier_plot`]'s.

pub mod data;

use anyhow::Result;
use data::FourierPlot;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::series::DashedLineSeries;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::Path;

use crate::plot::{chart_with_legend_room, dashed_key, legend_off_data, line_key, pe, save_image, tick, Axes, FONT};

/// Width and height of the PNG in pixels.
pub const SIZE: (u32, u32) = (1000, 1300);

/// Draw `d` at `path` (through a temporary file beside it): PNG or SVG by the extension,
/// any other extension refused.
pub fn fourier_png(path: &Path, d: &FourierPlot) -> Result<()> {
    save_image(path, SIZE, |root| draw_both(root, d), |root| draw_both(root, d))
}

fn draw_both<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, d: &FourierPlot) -> Result<()> {
    let (upper, lower) = root.split_vertically(SIZE.1 * 11 / 20);
    draw_fit(&upper, d)?;
    draw_harmonics(&lower, d)
}

/// A finite range around `lo..hi` (percent), padded below and with `head` of the span free
/// above for the legend.
fn padded(lo: f64, hi: f64, head: f64) -> std::ops::Range<f64> {
    let span = (hi - lo).max(1e-6);
    (lo - 0.08 * span)..(hi + (0.08 + head) * span)
}

fn draw_fit<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, d: &FourierPlot) -> Result<()> {
    let pct = |x: f64| 100.0 * x;
    let mut ys: Vec<f64> = d.curve.iter().map(|c| pct(c.1)).collect();
    for p in &d.points {
        let s = if p.sigma.is_finite() { p.sigma.max(0.0) } else { 0.0 };
        ys.extend([pct(p.f - s), pct(p.f + s)]);
    }
    let lo = ys.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = ys.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let chi = d.chi_deg.map_or("undefined".to_string(), |c| format!("{c:.2}°"));
    let ax = Axes::new(
        format!("P = {:.3} ± {:.3} %, χ = {chi}, N = {}", pct(d.p), pct(d.sigma_p), d.n),
        "HWP angle θ (deg)",
        "F_i (%)",
    );
    // A little room either side, so that the points at 0 deg are not cut by the axis.
    let pad = d.theta_max_deg / 60.0;
    // Room above the data for the legend's lines at 9 pt: the legend never covers a point.
    let entries = 2 + d.a0.is_some() as usize;
    let mut c = chart_with_legend_room(area, &ax, -pad..d.theta_max_deg + pad, padded(lo, hi, 0.0), entries)?;
    c.draw_series(LineSeries::new(d.curve.iter().map(|(t, f)| (*t, pct(*f))), crate::plot::BLUE_OI.stroke_width(2)))
        .map_err(pe)?
        .label("fit")
        .legend(line_key(crate::plot::BLUE_OI.stroke_width(2)));
    if let Some(a0) = d.a0 {
        let grey = BLACK.mix(0.6);
        c.draw_series(DashedLineSeries::new(
            [(-pad, pct(a0)), (d.theta_max_deg + pad, pct(a0))],
            8,
            6,
            grey.stroke_width(1),
        ))
        .map_err(pe)?
        .label(format!("a_0 = {:.3} %", pct(a0)))
        .legend(dashed_key(grey));
    }
    // Error bars as one I-shaped path each (capped, cap width 1/200 of the axis).
    let w = d.theta_max_deg / 200.0;
    c.draw_series(d.points.iter().filter(|p| p.sigma > 0.0 && p.sigma.is_finite()).map(|p| {
        let (x, lo, hi) = (p.theta_deg, pct(p.f - p.sigma), pct(p.f + p.sigma));
        PathElement::new([(x - w, hi), (x + w, hi), (x, hi), (x, lo), (x - w, lo), (x + w, lo)], BLACK)
    }))
    .map_err(pe)?;
    c.draw_series(d.points.iter().map(|p| Circle::new((p.theta_deg, pct(p.f)), 4, BLACK.filled())))
        .map_err(pe)?
        .label("F_i ± 1σ")
        .legend(|(x, y)| Circle::new((x + 10, y), 4, BLACK.filled()));
    let mut data: Vec<(f64, f64)> = d.curve.iter().map(|(t, f)| (*t, pct(*f))).collect();
    data.extend(d.points.iter().flat_map(|p| {
        let s = if p.sigma.is_finite() { p.sigma.max(0.0) } else { 0.0 };
        [(p.theta_deg, pct(p.f)), (p.theta_deg, pct(p.f - s)), (p.theta_deg, pct(p.f + s))]
    }));
    if let Some(a0) = d.a0 {
        data.extend(d.curve.iter().map(|(t, _)| (*t, pct(a0))));
    }
    legend_off_data(&mut c, &data, entries, 22, UPPER)
}

/// The upper corners, right first: [`chart_with_legend_room`] keeps the data below them.
const UPPER: [SeriesLabelPosition; 4] = [
    SeriesLabelPosition::UpperRight,
    SeriesLabelPosition::UpperLeft,
    SeriesLabelPosition::UpperRight,
    SeriesLabelPosition::UpperLeft,
];

/// Tick labels at the whole harmonic numbers only.
fn whole(v: &f64) -> String {
    if (v - v.round()).abs() < 1e-9 && *v >= 0.0 {
        tick(&v.round())
    } else {
        String::new()
    }
}

fn draw_harmonics<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, d: &FourierPlot) -> Result<()> {
    if d.bars.is_empty() {
        let (w, h) = area.dim_in_pixel();
        let style = TextStyle::from((FONT, crate::plot::pt(crate::plot::AXIS_PT)).into_font())
            .pos(Pos::new(HPos::Center, VPos::Center));
        area.draw(&Text::new("no harmonics (needs θ_i = i × 22.5°)", (w as i32 / 2, h as i32 / 2), style))
            .map_err(pe)?;
        return Ok(());
    }
    let kmax = d.bars.last().map_or(0, |b| b.k) as f64;
    let top = d.bars.iter().map(|b| 100.0 * b.amplitude.max(b.sigma)).fold(0.0, f64::max);
    let k_pol = d.k_pol.map_or("N/4".to_string(), |k| k.to_string());
    let ax = Axes::new(format!("harmonics √(a_k² + b_k²); P at k = {k_pol}"), "harmonic k", "amplitude (%)")
        .x_ticks(d.bars.len() + 1, &whole);
    let mut c = chart_with_legend_room(area, &ax, -0.6..kmax + 0.6, 0.0..padded(0.0, top, 0.0).end, 3)?;
    let pol = d.k_pol;
    c.draw_series(d.bars.iter().filter(|b| Some(b.k) != pol).map(|b| {
        let k = b.k as f64;
        Rectangle::new([(k - 0.35, 0.0), (k + 0.35, 100.0 * b.amplitude)], crate::plot::BLUE_OI.mix(0.45).filled())
    }))
    .map_err(pe)?
    .label("other harmonics")
    .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 20, y + 5)], crate::plot::BLUE_OI.mix(0.45).filled()));
    if let Some(b) = d.bars.iter().find(|b| Some(b.k) == pol) {
        let k = b.k as f64;
        c.draw_series(std::iter::once(Rectangle::new(
            [(k - 0.35, 0.0), (k + 0.35, 100.0 * b.amplitude)],
            crate::plot::VERMILLION.mix(0.7).filled(),
        )))
        .map_err(pe)?
        .label("k = N/4: P")
        .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 20, y + 5)], crate::plot::VERMILLION.mix(0.7).filled()));
    }
    c.draw_series(d.bars.iter().map(|b| {
        let k = b.k as f64;
        PathElement::new([(k - 0.45, 100.0 * b.sigma), (k + 0.45, 100.0 * b.sigma)], BLACK.stroke_width(2))
    }))
    .map_err(pe)?
    .label("1σ noise")
    .legend(line_key(BLACK.stroke_width(2)));
    let data: Vec<(f64, f64)> = d
        .bars
        .iter()
        .flat_map(|b| {
            let k = b.k as f64;
            // The bar's top edge and its middle: a legend may not sit on a bar.
            [
                (k, 100.0 * b.amplitude),
                (k, 50.0 * b.amplitude),
                (k, 100.0 * b.sigma),
                (k - 0.3, 100.0 * b.amplitude),
                (k + 0.3, 100.0 * b.amplitude),
            ]
        })
        .collect();
    legend_off_data(&mut c, &data, 3, 25, UPPER)
}
