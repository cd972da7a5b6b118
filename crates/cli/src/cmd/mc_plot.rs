//! PNG or SVG plots of `instpol mc --sweep` (fig:deltap, fig:bias) and `--accuracy-report`.
//! Drawing only: every number comes from `stokes::mc`.

use anyhow::Result;
use plotters::prelude::*;
use plotters::series::DashedLineSeries;
use std::path::Path;
use stokes::mc::budget::{NoiseRow, ObserverRow, PrecisionRow};
use stokes::mc::sweep::{BiasPoint, DeltaPPoint};
use stokes::stats::rice::{mean_bias_n, mode_n, std_n};

use crate::plot::{
    chart, chart_with_legend, dashed_key, draw_legend, key, line_key, log_axis, marks_y_range, pe, save_image, Axes,
    Key, Mark,
};
use plotters::coord::Shift;

/// Three panels stacked, for one journal column (fonts: crate::plot): 12.3 cm tall at the
/// column's 8.8 cm, half a page.
const SIZE: (u32, u32) = (1000, 1400);

/// The sweep's four quarters (fig:deltap's two panels above, fig:bias and its legend of every
/// estimator below), printed across a page (`crate::plot::PAGE_FIGURE_PX`): 18 x 11.7 cm.
const SWEEP_SIZE: (u32, u32) = (2000, 1300);

fn logspace(a: f64, b: f64, n: usize) -> Vec<f64> {
    (0..n).map(|i| (a.ln() + (b.ln() - a.ln()) * i as f64 / (n - 1) as f64).exp()).collect()
}

/// fig:deltap (sigma_P and Delta P against eta, N and SNR given) and fig:bias.
pub fn sweep_png(path: &Path, dp: &[DeltaPPoint], bias: &[BiasPoint], n: usize, snr: f64) -> Result<()> {
    save_image(path, SWEEP_SIZE, |r| draw_sweep(r, dp, bias, n, snr), |r| draw_sweep(r, dp, bias, n, snr))
}

fn draw_sweep<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    dp: &[DeltaPPoint],
    bias: &[BiasPoint],
    n: usize,
    snr: f64,
) -> Result<()> {
    let k = (n as f64 / 2.0).sqrt();
    {
        let areas = root.split_evenly((2, 2));
        let emin = dp.iter().map(|p| p.eta).fold(f64::INFINITY, f64::min).max(1e-3);
        let emax = dp.iter().map(|p| p.eta).fold(0.0, f64::max).max(emin * 10.0);
        let curve = logspace(emin, emax, 200);
        // Upper panel of fig:deltap: sigma_P x SNR.
        let ax = Axes::new(format!("σ_P (N = {n}, SNR = {snr})"), "η = P₀ SNR", "σ_P × SNR");
        let ray = (2.0 - std::f64::consts::PI / 2.0).sqrt() / k;
        let mut marks: Vec<Vec<(f64, f64)>> = vec![
            vec![(emin, 1.0 / k), (emax, 1.0 / k)],
            vec![(emin, ray), (emax, ray)],
            curve.iter().map(|&e| (e, std_n(k * e) / k)).collect(),
        ];
        marks.extend(dp.iter().map(|p| vec![(p.eta, p.sigma_p * snr)]));
        let y = || marks_y_range(&marks);
        let keys = [
            key("√(2/N) / SNR", Mark::Line(BLACK.stroke_width(2))),
            key("Rayleigh", Mark::Dashed(crate::plot::BLUE_OI.stroke_width(2))),
            key("Rice", Mark::Line(crate::plot::VERMILLION.stroke_width(2))),
            key("Monte Carlo", Mark::Circle(BLACK.into())),
        ];
        let (mut c, place) = chart_with_legend(&areas[0], &ax, || log_axis(emin, emax), y, &marks, &keys)?;
        c.draw_series(LineSeries::new([(emin, 1.0 / k), (emax, 1.0 / k)], BLACK.stroke_width(2))).map_err(pe)?;
        c.draw_series(DashedLineSeries::new([(emin, ray), (emax, ray)], 8, 6, crate::plot::BLUE_OI.stroke_width(2)))
            .map_err(pe)?;
        c.draw_series(LineSeries::new(
            curve.iter().map(|&e| (e, std_n(k * e) / k)),
            crate::plot::VERMILLION.stroke_width(2),
        ))
        .map_err(pe)?;
        c.draw_series(dp.iter().map(|p| Circle::new((p.eta, p.sigma_p * snr), 4, BLACK.stroke_width(1))))
            .map_err(pe)?;
        draw_legend(&c, place, &keys)?;

        // Lower panel of fig:deltap: Delta P x SNR.
        let ax = Axes::new("bias ΔP", "η = P₀ SNR", "ΔP × SNR");
        let mut marks: Vec<Vec<(f64, f64)>> = vec![
            curve.iter().map(|&e| (e, (mode_n(k * e) - k * e) / k)).collect(),
            curve.iter().map(|&e| (e, mean_bias_n(k * e) / k)).collect(),
        ];
        marks.extend(dp.iter().filter_map(|p| p.delta_mode.map(|d| vec![(p.eta, d * snr)])));
        marks.extend(dp.iter().map(|p| vec![(p.eta, p.delta_mean * snr)]));
        let y = || marks_y_range(&marks);
        let keys = [
            key("W&K (Rice mode)", Mark::Line(BLACK.stroke_width(2))),
            key("Rice mean", Mark::Dashed(crate::plot::BLUE_OI.stroke_width(2))),
            key("MC mode", Mark::Circle(BLACK.into())),
            key("MC mean", Mark::Cross(crate::plot::BLUE_OI.into())),
        ];
        let (mut c, place) = chart_with_legend(&areas[1], &ax, || log_axis(emin, emax), y, &marks, &keys)?;
        c.draw_series(LineSeries::new(curve.iter().map(|&e| (e, (mode_n(k * e) - k * e) / k)), BLACK.stroke_width(2)))
            .map_err(pe)?;
        c.draw_series(DashedLineSeries::new(
            curve.iter().map(|&e| (e, mean_bias_n(k * e) / k)),
            8,
            6,
            crate::plot::BLUE_OI.stroke_width(2),
        ))
        .map_err(pe)?;
        c.draw_series(
            dp.iter().filter_map(|p| p.delta_mode.map(|d| Circle::new((p.eta, d * snr), 4, BLACK.stroke_width(1)))),
        )
        .map_err(pe)?;
        c.draw_series(
            dp.iter().map(|p| Cross::new((p.eta, p.delta_mean * snr), 5, crate::plot::BLUE_OI.stroke_width(2))),
        )
        .map_err(pe)?;
        draw_legend(&c, place, &keys)?;

        // fig:bias: Delta P / sigma_P against SNR_P.
        let smin = bias.iter().map(|b| b.snr_p).fold(f64::INFINITY, f64::min).max(1e-3);
        let smax = bias.iter().map(|b| b.snr_p).fold(0.0, f64::max).max(smin * 10.0);
        let ax = Axes::new("ΔP / σ_P", "SNR_P = P₀ / σ_P", "ΔP / σ_P");
        // Every estimator's curve crosses the whole panel: no corner is free for a legend of
        // this many lines, so it stands beside the chart, in a column of its own.
        let (plot_area, key_area) = (&areas[2], &areas[3]);
        let ys = bias
            .iter()
            .flat_map(|b| b.estimators.iter().map(|e| e.1).chain([b.mc_mean]).chain(b.mc_mode).chain(b.mc_median));
        let (ylo, yhi) = crate::plot::extent(ys).unwrap_or((-1.0, 1.0));
        let mut c = chart(plot_area, &ax, log_axis(smin, smax), crate::plot::data_range(ylo, yhi))?;
        // The legend's chart: no axes, the plotting area the whole column below the caption's
        // height, so that the box starts level with the chart's top.
        let mut keys = ChartBuilder::on(key_area)
            .margin(crate::plot::pt(3.0))
            .margin_top(crate::plot::pt(3.0 + 1.3 * crate::plot::CAPTION_PT))
            .build_cartesian_2d(0f64..1.0, 0f64..1.0)
            .map_err(pe)?;
        let names: Vec<String> =
            bias.first().map(|b| b.estimators.iter().map(|e| e.0.clone()).collect()).unwrap_or_default();
        for (j, nm) in names.iter().enumerate() {
            // The palette's colours solid, then again dashed.
            let col = crate::plot::series_colour(j).stroke_width(2);
            let pts = bias.iter().map(|b| (b.snr_p, b.estimators[j].1));
            let key = keys.draw_series(LineSeries::new(std::iter::empty(), col)).map_err(pe)?;
            key.label(format!("E[{nm}] − P₀"));
            if j < crate::plot::PALETTE.len() {
                c.draw_series(LineSeries::new(pts, col)).map_err(pe)?;
                key.legend(line_key(col));
            } else {
                c.draw_series(DashedLineSeries::new(pts, 8, 6, col)).map_err(pe)?;
                key.legend(dashed_key(col));
            }
        }
        c.draw_series(
            bias.iter().filter_map(|b| b.mc_mode.map(|m| Circle::new((b.snr_p, m), 4, BLACK.stroke_width(1)))),
        )
        .map_err(pe)?;
        c.draw_series(bias.iter().map(|b| Cross::new((b.snr_p, b.mc_mean), 5, crate::plot::BLUE_OI.stroke_width(2))))
            .map_err(pe)?;
        c.draw_series(bias.iter().filter_map(|b| {
            b.mc_median.map(|m| TriangleMarker::new((b.snr_p, m), 5, crate::plot::VERMILLION.stroke_width(1)))
        }))
        .map_err(pe)?;
        keys.draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())
            .map_err(pe)?
            .label("MC mode")
            .legend(|(x, y)| Circle::new((x + 10, y), 4, BLACK));
        keys.draw_series(std::iter::empty::<Cross<(f64, f64), i32>>())
            .map_err(pe)?
            .label("MC mean")
            .legend(|(x, y)| Cross::new((x + 10, y), 5, crate::plot::BLUE_OI));
        keys.draw_series(std::iter::empty::<TriangleMarker<(f64, f64), i32>>())
            .map_err(pe)?
            .label("MC median")
            .legend(|(x, y)| TriangleMarker::new((x + 10, y), 5, crate::plot::VERMILLION));
        crate::plot::legend(&mut keys, plotters::chart::SeriesLabelPosition::UpperLeft)?;
        Ok(())
    }
}

/// The accuracy report: Monte Carlo precision vs trials, sigma_P and floors vs SNR, noise modes.
pub fn accuracy_png(path: &Path, prec: &[PrecisionRow], obs: &[ObserverRow], nm: &[NoiseRow], p0: f64) -> Result<()> {
    save_image(path, SIZE, |r| draw_accuracy(r, prec, obs, nm, p0), |r| draw_accuracy(r, prec, obs, nm, p0))
}

fn draw_accuracy<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    prec: &[PrecisionRow],
    obs: &[ObserverRow],
    nm: &[NoiseRow],
    p0: f64,
) -> Result<()> {
    {
        let areas = root.split_evenly((3, 1));
        // 1. Scatter of the estimates against trials (the longest run's wall time in the caption).
        let tmin = prec.iter().map(|r| r.trials as f64).fold(f64::INFINITY, f64::min).max(1.0);
        let tmax = prec.iter().map(|r| r.trials as f64).fold(1.0, f64::max).max(tmin * 10.0);
        type Get = fn(&PrecisionRow) -> f64;
        let series: [(&str, Get, RGBColor); 3] = [
            ("σ_P", |r| r.sigma_p_scatter, BLACK),
            ("bias (mean)", |r| r.bias_mean_scatter, crate::plot::BLUE_OI),
            ("bias (mode)", |r| r.bias_mode_scatter, crate::plot::VERMILLION),
        ];
        let positive = |(t, v): (f64, f64)| (v.is_finite() && v > 0.0).then_some((t, v));
        let marks: Vec<Vec<(f64, f64)>> = series
            .iter()
            .map(|(_, get, _)| prec.iter().filter_map(|r| positive((r.trials as f64, get(r) / p0))).collect())
            .collect();
        let (ylo, yhi) = crate::plot::extent(marks.iter().flatten().map(|p| p.1)).unwrap_or((1e-4, 1e-2));
        let (ylo, yhi) = crate::plot::log_data_range(ylo, yhi);
        let longest = prec.iter().map(|r| r.seconds).fold(0.0, f64::max);
        let caption = format!("MC precision (longest run {longest:.3} s)");
        let ax = Axes::new(caption, "trials", "scatter / P₀").log_labels(Some((tmin, tmax)), Some((ylo, yhi)));
        let (x, y) = (|| log_axis(tmin, tmax), || log_axis(ylo, yhi));
        let keys: Vec<Key> = series.iter().map(|(name, _, col)| key(*name, Mark::Line(col.stroke_width(2)))).collect();
        let (mut c, place) = chart_with_legend(&areas[0], &ax, x, y, &marks, &keys)?;
        for ((_, _, col), m) in series.iter().zip(&marks) {
            c.draw_series(LineSeries::new(m.iter().copied(), col.stroke_width(2))).map_err(pe)?;
        }
        draw_legend(&c, place, &keys)?;

        // 2. sigma_P vs SNR with the systematic floors.
        let smin = obs.first().and_then(|o| o.sigma_p.first()).map_or(10.0, |s| s.0);
        let smax = obs.first().and_then(|o| o.sigma_p.last()).map_or(1e4, |s| s.0);
        let worst = |o: &ObserverRow| o.floors.iter().map(|f| f.1).fold(0.0, f64::max).max(1e-6);
        let marks: Vec<Vec<(f64, f64)>> = obs
            .iter()
            .flat_map(|o| [o.sigma_p.iter().map(|s| (s.0, s.1)).collect(), vec![(smin, worst(o)), (smax, worst(o))]])
            .collect();
        let (ylo, yhi) = crate::plot::extent(marks.iter().flatten().map(|p| p.1)).unwrap_or((1e-6, 0.2));
        let (ylo, yhi) = crate::plot::log_data_range(ylo, yhi);
        let ax = Axes::new("σ_P (solid), HWP floors (dashed)", "SNR per HWP angle", "P error")
            .log_labels(Some((smin, smax)), Some((ylo, yhi)));
        let (x, y) = (|| log_axis(smin, smax), || log_axis(ylo, yhi));
        let keys: Vec<Key> = (obs.iter().enumerate())
            .map(|(j, o)| {
                key(format!("N = {}", o.n_hwp), Mark::LineAndDashed(crate::plot::series_colour(j).stroke_width(2)))
            })
            .collect();
        let (mut c, place) = chart_with_legend(&areas[1], &ax, x, y, &marks, &keys)?;
        for (j, o) in obs.iter().enumerate() {
            let col = crate::plot::series_colour(j);
            c.draw_series(LineSeries::new(o.sigma_p.iter().map(|s| (s.0, s.1)), col.stroke_width(2))).map_err(pe)?;
            let w = worst(o);
            c.draw_series(DashedLineSeries::new([(smin, w), (smax, w)], 8, 6, col.stroke_width(2))).map_err(pe)?;
        }
        draw_legend(&c, place, &keys)?;

        // 3. Noise modes: relative sigma_P difference to Poisson vs SNR.
        let snrs: Vec<f64> = nm.iter().map(|r| r.snr).collect();
        let (a, b) = (snrs.iter().cloned().fold(f64::INFINITY, f64::min), snrs.iter().cloned().fold(0.0, f64::max));
        let ax = Axes::new("fast noise modes vs exact Poisson", "SNR", "relative σ_P difference")
            .log_labels(Some((a, b.max(a * 2.0))), None);
        let modes = ["gauss-f", "gauss-qu"];
        let marks: Vec<Vec<(f64, f64)>> = modes
            .iter()
            .map(|m| nm.iter().filter(|r| r.noise == *m).map(|r| (r.snr, r.rms_rel_dev)).collect())
            .collect();
        let (x, y) = (|| log_axis(a, b.max(a * 2.0)), || marks_y_range(&marks));
        let keys: Vec<Key> = modes
            .iter()
            .enumerate()
            .map(|(j, m)| key(*m, Mark::Line(crate::plot::series_colour(j).stroke_width(2))))
            .collect();
        let (mut c, place) = chart_with_legend(&areas[2], &ax, x, y, &marks, &keys)?;
        for (j, m) in marks.iter().enumerate() {
            c.draw_series(LineSeries::new(m.iter().copied(), crate::plot::series_colour(j).stroke_width(2)))
                .map_err(pe)?;
        }
        draw_legend(&c, place, &keys)?;
        Ok(())
    }
}
