//! `instpol explain --plot`: each candidate's ΔBIC as a bar (log scale: 1 + ΔBIC), the
//! threshold of "told apart" marked. Drawing only: the numbers are `fit::mueller_field::explain`'s.

use anyhow::Result;
use fit::mueller_field::explain::{Cause, Explanation};
use plotters::prelude::*;
use plotters::series::DashedLineSeries;

use crate::plot::{chart_with_legend, draw_legend, key, log_axis, log_data_range, pe, Axes, Mark};

/// The figure's size (px), for one journal column.
const SIZE: (u32, u32) = (900, 700);

/// Half a bar's width (in candidates).
const HALF_BAR: f64 = 0.35;

/// Draw `e` at `path`: PNG or SVG by the extension.
pub fn draw(path: &std::path::Path, e: &Explanation) -> Result<()> {
    let vals: Vec<f64> = e.fits.iter().map(|f| 1.0 + f.delta_bic.min(1e12)).collect();
    crate::plot::save_image(path, SIZE, |r| draw_on(r, e, &vals), |r| draw_on(r, e, &vals))
}

/// A candidate's short name: six side by side in a one-column figure.
fn short(c: &Cause) -> &'static str {
    match c {
        Cause::DiattenuationOnly => "none",
        Cause::Raytrace => "trace",
        Cause::StressedLens => "lens",
        Cause::TiltedHwp => "tilt",
        Cause::WedgedHwp => "wedge",
        Cause::PolarizingHwp => "pol",
    }
}

fn draw_on<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    e: &Explanation,
    vals: &[f64],
) -> Result<()> {
    let n = e.fits.len();
    let labels: Vec<&str> = e.fits.iter().map(|f| short(&f.cause)).collect();
    let fmt = move |x: &f64| {
        let k = x.round();
        if (x - k).abs() < 1e-6 && k >= 0.0 && (k as usize) < labels.len() {
            labels[k as usize].to_string()
        } else {
            String::new()
        }
    };
    let t = 1.0 + fit::mueller_field::explain::DELTA_BIC;
    // The bars stand on 1 (ΔBIC = 0); the axis ends just past the tallest and the threshold.
    let hi = vals.iter().copied().filter(|v| v.is_finite()).fold(t, f64::max);
    let (lo, hi) = log_data_range(1.0, hi);
    let ax = Axes::new("Which cause explains the field", "candidate", "1 + ΔBIC")
        .x_ticks(n + 1, &fmt)
        .log_labels(None, Some((lo, hi)));
    let (x0, x1) = (-0.5, n as f64 - 0.5);
    // What the legend must keep off: each bar's outline and the threshold.
    let mut marks: Vec<Vec<(f64, f64)>> = vals
        .iter()
        .enumerate()
        .filter(|(_, v)| v.is_finite())
        .map(|(k, v)| {
            let x = k as f64;
            vec![(x - HALF_BAR, 1.0), (x - HALF_BAR, *v), (x + HALF_BAR, *v), (x + HALF_BAR, 1.0)]
        })
        .collect();
    marks.push(vec![(x0, t), (x1, t)]);
    let bar = crate::plot::BLUE_OI.filled();
    let line = crate::plot::VERMILLION.stroke_width(2);
    let keys = [
        key("1 + ΔBIC of a candidate", Mark::Bar(bar)),
        key(format!("ΔBIC = {}: told apart", fit::mueller_field::explain::DELTA_BIC), Mark::Dashed(line)),
    ];
    let (mut c, place) = chart_with_legend(root, &ax, || x0..x1, || log_axis(lo, hi), &marks, &keys)?;
    for (k, v) in vals.iter().enumerate().filter(|(_, v)| v.is_finite()) {
        let x = k as f64;
        c.draw_series(std::iter::once(Rectangle::new([(x - HALF_BAR, 1.0), (x + HALF_BAR, *v)], bar))).map_err(pe)?;
    }
    c.draw_series(DashedLineSeries::new([(x0, t), (x1, t)], 8, 6, line)).map_err(pe)?;
    draw_legend(&c, place, &keys)
}
