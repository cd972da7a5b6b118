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

use crate::plot::{chart_with_legend, data_range, draw_legend, key, pe, save_image, tick, Axes, Mark, FONT};

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
    // What the legend must keep off: the curve, the a_0 level, each point with its error bar.
    let mut marks: Vec<Vec<(f64, f64)>> = vec![d.curve.iter().map(|(t, f)| (*t, pct(*f))).collect()];
    marks.extend(d.points.iter().map(|p| {
        let s = if p.sigma.is_finite() { p.sigma.max(0.0) } else { 0.0 };
        vec![(p.theta_deg, pct(p.f - s)), (p.theta_deg, pct(p.f + s))]
    }));
    if let Some(a0) = d.a0 {
        marks.push(vec![(-pad, pct(a0)), (d.theta_max_deg + pad, pct(a0))]);
    }
    let grey = BLACK.mix(0.6);
    // The fitted curve named by what was fitted, with its value (the title adds its error).
    let mut keys = vec![key(format!("fit, P = {:.3} %", pct(d.p)), Mark::Line(crate::plot::BLUE_OI.stroke_width(2)))];
    if let Some(a0) = d.a0 {
        keys.push(key(format!("a_0 = {:.3} %", pct(a0)), Mark::Dashed(grey.into())));
    }
    keys.push(key("F_i ± 1σ", Mark::Circle(BLACK.filled())));
    let x = || -pad..d.theta_max_deg + pad;
    let (mut c, place) = chart_with_legend(area, &ax, x, || data_range(lo, hi), &marks, &keys)?;
    c.draw_series(LineSeries::new(d.curve.iter().map(|(t, f)| (*t, pct(*f))), crate::plot::BLUE_OI.stroke_width(2)))
        .map_err(pe)?;
    if let Some(a0) = d.a0 {
        c.draw_series(DashedLineSeries::new(
            [(-pad, pct(a0)), (d.theta_max_deg + pad, pct(a0))],
            8,
            6,
            grey.stroke_width(1),
        ))
        .map_err(pe)?;
    }
    // Error bars as one I-shaped path each (capped, cap width 1/200 of the axis).
    let w = d.theta_max_deg / 200.0;
    c.draw_series(d.points.iter().filter(|p| p.sigma > 0.0 && p.sigma.is_finite()).map(|p| {
        let (x, lo, hi) = (p.theta_deg, pct(p.f - p.sigma), pct(p.f + p.sigma));
        PathElement::new([(x - w, hi), (x + w, hi), (x, hi), (x, lo), (x - w, lo), (x + w, lo)], BLACK)
    }))
    .map_err(pe)?;
    c.draw_series(d.points.iter().map(|p| Circle::new((p.theta_deg, pct(p.f)), 4, BLACK.filled()))).map_err(pe)?;
    draw_legend(&c, place, &keys)
}

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
    // What the legend must keep off: each bar's outline and its noise level.
    let marks: Vec<Vec<(f64, f64)>> = d
        .bars
        .iter()
        .flat_map(|b| {
            let (k, a, s) = (b.k as f64, 100.0 * b.amplitude, 100.0 * b.sigma);
            [vec![(k - 0.35, 0.0), (k - 0.35, a), (k + 0.35, a), (k + 0.35, 0.0)], vec![(k - 0.45, s), (k + 0.45, s)]]
        })
        .collect();
    // The bars stand on zero; the axis ends just above the tallest.
    let y = || 0.0..data_range(0.0, top).end;
    let pol = d.k_pol;
    let (other, p_bar) = (crate::plot::BLUE_OI.mix(0.45).filled(), crate::plot::VERMILLION.mix(0.7).filled());
    let mut keys = vec![key("other harmonics", Mark::Bar(other))];
    if d.bars.iter().any(|b| Some(b.k) == pol) {
        keys.push(key(format!("k = {k_pol}: P"), Mark::Bar(p_bar)));
    }
    keys.push(key("1σ noise", Mark::Line(BLACK.stroke_width(2))));
    let (mut c, place) = chart_with_legend(area, &ax, || -0.6..kmax + 0.6, y, &marks, &keys)?;
    c.draw_series(d.bars.iter().filter(|b| Some(b.k) != pol).map(|b| {
        let k = b.k as f64;
        Rectangle::new([(k - 0.35, 0.0), (k + 0.35, 100.0 * b.amplitude)], other)
    }))
    .map_err(pe)?;
    if let Some(b) = d.bars.iter().find(|b| Some(b.k) == pol) {
        let k = b.k as f64;
        c.draw_series(std::iter::once(Rectangle::new([(k - 0.35, 0.0), (k + 0.35, 100.0 * b.amplitude)], p_bar)))
            .map_err(pe)?;
    }
    c.draw_series(d.bars.iter().map(|b| {
        let k = b.k as f64;
        PathElement::new([(k - 0.45, 100.0 * b.sigma), (k + 0.45, 100.0 * b.sigma)], BLACK.stroke_width(2))
    }))
    .map_err(pe)?;
    draw_legend(&c, place, &keys)
}
