//! PNG plots of `instpol mc --sweep` (fig:deltap, fig:bias) and `--accuracy-report`.
//! Drawing only: every number comes from `stokes::mc`.

use anyhow::Result;
use plotters::prelude::*;
use plotters::series::DashedLineSeries;
use std::path::Path;
use stokes::mc::budget::{NoiseRow, ObserverRow, PrecisionRow};
use stokes::mc::sweep::{BiasPoint, DeltaPPoint};
use stokes::stats::rice::{mean_bias_n, mode_n, std_n};

use crate::plot::{font, pe, FONT};

/// Draw into a temporary PNG in the target folder, then rename: no half-written plot.
fn atomic_png(
    path: &Path,
    w: u32,
    h: u32,
    draw: impl FnOnce(&DrawingArea<BitMapBackend, plotters::coord::Shift>) -> Result<()>,
) -> Result<()> {
    font();
    crate::plot::atomic(path, ".png", |tmp| {
        let root = BitMapBackend::new(tmp, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(pe)?;
        draw(&root)?;
        root.present().map_err(pe)
    })
}

fn logspace(a: f64, b: f64, n: usize) -> Vec<f64> {
    (0..n).map(|i| (a.ln() + (b.ln() - a.ln()) * i as f64 / (n - 1) as f64).exp()).collect()
}

/// fig:deltap (sigma_P and Delta P against eta, N and SNR given) and fig:bias.
pub fn sweep_png(path: &Path, dp: &[DeltaPPoint], bias: &[BiasPoint], n: usize, snr: f64) -> Result<()> {
    let k = (n as f64 / 2.0).sqrt();
    atomic_png(path, 1000, 1500, |root| {
        let areas = root.split_evenly((3, 1));
        let emin = dp.iter().map(|p| p.eta).fold(f64::INFINITY, f64::min).max(1e-3);
        let emax = dp.iter().map(|p| p.eta).fold(0.0, f64::max).max(emin * 10.0);
        let curve = logspace(emin, emax, 200);
        // Upper panel of fig:deltap: sigma_P x SNR.
        let mut c = ChartBuilder::on(&areas[0])
            .caption(format!("fig:deltap  sigma_P (N = {n}, SNR = {snr})"), (FONT, 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d((emin..emax).log_scale(), 0.0..(1.25 / k))
            .map_err(pe)?;
        c.configure_mesh().x_desc("eta = P0 SNR").y_desc("sigma_P x SNR").label_style((FONT, 14)).draw().map_err(pe)?;
        c.draw_series(LineSeries::new([(emin, 1.0 / k), (emax, 1.0 / k)], BLACK.stroke_width(2)))
            .map_err(pe)?
            .label("eq:sigp")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK));
        let ray = (2.0 - std::f64::consts::PI / 2.0).sqrt() / k;
        c.draw_series(DashedLineSeries::new([(emin, ray), (emax, ray)], 8, 6, BLUE.stroke_width(2)))
            .map_err(pe)?
            .label("Rayleigh")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLUE));
        c.draw_series(LineSeries::new(curve.iter().map(|&e| (e, std_n(k * e) / k)), RED.mix(0.6)))
            .map_err(pe)?
            .label("Rice")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], RED));
        c.draw_series(dp.iter().map(|p| Circle::new((p.eta, p.sigma_p * snr), 4, BLACK.stroke_width(1))))
            .map_err(pe)?
            .label("Monte Carlo")
            .legend(|(x, y)| Circle::new((x + 10, y), 4, BLACK));
        c.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font((FONT, 14))
            .draw()
            .map_err(pe)?;

        // Lower panel of fig:deltap: Delta P x SNR.
        let ymax = dp.iter().map(|p| p.delta_mean * snr).fold(0.0, f64::max).max(0.1) * 1.1;
        let mut c = ChartBuilder::on(&areas[1])
            .caption("fig:deltap  bias Delta P", (FONT, 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d((emin..emax).log_scale(), 0.0..ymax)
            .map_err(pe)?;
        c.configure_mesh().x_desc("eta = P0 SNR").y_desc("Delta P x SNR").label_style((FONT, 14)).draw().map_err(pe)?;
        c.draw_series(LineSeries::new(curve.iter().map(|&e| (e, (mode_n(k * e) - k * e) / k)), BLACK.stroke_width(2)))
            .map_err(pe)?
            .label("Wardle & Kronberg (Rice mode)")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK));
        c.draw_series(DashedLineSeries::new(
            curve.iter().map(|&e| (e, mean_bias_n(k * e) / k)),
            8,
            6,
            BLUE.stroke_width(2),
        ))
        .map_err(pe)?
        .label("Rice mean (average)")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLUE));
        c.draw_series(
            dp.iter().filter_map(|p| p.delta_mode.map(|d| Circle::new((p.eta, d * snr), 4, BLACK.stroke_width(1)))),
        )
        .map_err(pe)?
        .label("MC mode")
        .legend(|(x, y)| Circle::new((x + 10, y), 4, BLACK));
        c.draw_series(dp.iter().map(|p| Cross::new((p.eta, p.delta_mean * snr), 5, BLUE.stroke_width(2))))
            .map_err(pe)?
            .label("MC mean")
            .legend(|(x, y)| Cross::new((x + 10, y), 5, BLUE));
        c.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font((FONT, 14))
            .draw()
            .map_err(pe)?;

        // fig:bias: Delta P / sigma_P against SNR_P.
        let smin = bias.iter().map(|b| b.snr_p).fold(f64::INFINITY, f64::min).max(1e-3);
        let smax = bias.iter().map(|b| b.snr_p).fold(0.0, f64::max).max(smin * 10.0);
        let mut c = ChartBuilder::on(&areas[2])
            .caption("fig:bias  Delta P / sigma_P", (FONT, 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d((smin..smax).log_scale(), -0.6f64..1.6)
            .map_err(pe)?;
        c.configure_mesh()
            .x_desc("SNR_P = P0 / sigma_P")
            .y_desc("Delta P / sigma_P")
            .label_style((FONT, 14))
            .draw()
            .map_err(pe)?;
        let names: Vec<String> =
            bias.first().map(|b| b.estimators.iter().map(|e| e.0.clone()).collect()).unwrap_or_default();
        for (j, nm) in names.iter().enumerate() {
            let col = Palette99::pick(j + 2).to_rgba();
            c.draw_series(LineSeries::new(bias.iter().map(|b| (b.snr_p, b.estimators[j].1)), col.stroke_width(2)))
                .map_err(pe)?
                .label(format!("E[{nm}] - P0"))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], col));
        }
        c.draw_series(
            bias.iter().filter_map(|b| b.mc_mode.map(|m| Circle::new((b.snr_p, m), 4, BLACK.stroke_width(1)))),
        )
        .map_err(pe)?
        .label("MC mode")
        .legend(|(x, y)| Circle::new((x + 10, y), 4, BLACK));
        c.draw_series(bias.iter().map(|b| Cross::new((b.snr_p, b.mc_mean), 5, BLUE.stroke_width(2))))
            .map_err(pe)?
            .label("MC mean")
            .legend(|(x, y)| Cross::new((x + 10, y), 5, BLUE));
        c.draw_series(
            bias.iter().filter_map(|b| b.mc_median.map(|m| TriangleMarker::new((b.snr_p, m), 5, RED.stroke_width(1)))),
        )
        .map_err(pe)?
        .label("MC median")
        .legend(|(x, y)| TriangleMarker::new((x + 10, y), 5, RED));
        c.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font((FONT, 13))
            .draw()
            .map_err(pe)?;
        Ok(())
    })
}

/// The accuracy report: Monte Carlo precision vs trials, sigma_P and floors vs SNR, noise modes.
pub fn accuracy_png(path: &Path, prec: &[PrecisionRow], obs: &[ObserverRow], nm: &[NoiseRow], p0: f64) -> Result<()> {
    atomic_png(path, 1000, 1500, |root| {
        let areas = root.split_evenly((3, 1));
        // 1. Scatter of the estimates against trials (and seconds).
        let tmin = prec.iter().map(|r| r.trials as f64).fold(f64::INFINITY, f64::min).max(1.0);
        let tmax = prec.iter().map(|r| r.trials as f64).fold(1.0, f64::max).max(tmin * 10.0);
        let vals: Vec<f64> = prec
            .iter()
            .flat_map(|r| [r.sigma_p_scatter, r.bias_mean_scatter, r.bias_mode_scatter])
            .filter(|v| v.is_finite() && *v > 0.0)
            .map(|v| v / p0)
            .collect();
        let (ylo, yhi) = (
            vals.iter().cloned().fold(f64::INFINITY, f64::min).max(1e-6) / 2.0,
            vals.iter().cloned().fold(1e-5, f64::max) * 2.0,
        );
        let mut c = ChartBuilder::on(&areas[0])
            .caption("Monte Carlo precision (scatter of one run, relative to P0) vs trials", (FONT, 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d((tmin..tmax).log_scale(), (ylo..yhi).log_scale())
            .map_err(pe)?;
        c.configure_mesh().x_desc("trials").y_desc("scatter / P0").label_style((FONT, 14)).draw().map_err(pe)?;
        type Get = fn(&PrecisionRow) -> f64;
        let series: [(&str, Get, RGBColor); 3] = [
            ("sigma_P", |r| r.sigma_p_scatter, BLACK),
            ("bias (mean)", |r| r.bias_mean_scatter, BLUE),
            ("bias (mode)", |r| r.bias_mode_scatter, RED),
        ];
        for (name, get, col) in series {
            c.draw_series(LineSeries::new(prec.iter().map(|r| (r.trials as f64, get(r) / p0)), col.stroke_width(2)))
                .map_err(pe)?
                .label(name)
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], col));
        }
        for r in prec {
            c.draw_series(std::iter::once(Text::new(
                format!("{:.3} s", r.seconds),
                (r.trials as f64, yhi / 1.6),
                (FONT, 13),
            )))
            .map_err(pe)?;
        }
        c.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font((FONT, 14))
            .draw()
            .map_err(pe)?;

        // 2. sigma_P vs SNR with the systematic floors.
        let smin = obs.first().and_then(|o| o.sigma_p.first()).map_or(10.0, |s| s.0);
        let smax = obs.first().and_then(|o| o.sigma_p.last()).map_or(1e4, |s| s.0);
        let mut c = ChartBuilder::on(&areas[1])
            .caption("observer: sigma_P (eq:sigp) and HWP systematic floors vs SNR", (FONT, 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d((smin..smax).log_scale(), (1e-6f64..0.2).log_scale())
            .map_err(pe)?;
        c.configure_mesh()
            .x_desc("SNR per HWP angle (time ~ SNR^2)")
            .y_desc("P error")
            .label_style((FONT, 14))
            .draw()
            .map_err(pe)?;
        for (j, o) in obs.iter().enumerate() {
            let col = Palette99::pick(j).to_rgba();
            c.draw_series(LineSeries::new(o.sigma_p.iter().map(|s| (s.0, s.1)), col.stroke_width(2)))
                .map_err(pe)?
                .label(format!("sigma_P, N = {}", o.n_hwp))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], col));
            let worst = o.floors.iter().map(|f| f.1).fold(0.0, f64::max).max(1e-6);
            c.draw_series(DashedLineSeries::new([(smin, worst), (smax, worst)], 8, 6, col.stroke_width(2)))
                .map_err(pe)?
                .label(format!("worst floor, N = {}", o.n_hwp))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], col));
        }
        c.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font((FONT, 13))
            .draw()
            .map_err(pe)?;

        // 3. Noise modes: relative sigma_P difference to Poisson vs SNR.
        let snrs: Vec<f64> = nm.iter().map(|r| r.snr).collect();
        let (a, b) = (snrs.iter().cloned().fold(f64::INFINITY, f64::min), snrs.iter().cloned().fold(0.0, f64::max));
        let mut c = ChartBuilder::on(&areas[2])
            .caption("fast noise modes vs exact Poisson: (sigma_P - sigma_P[poisson]) / sigma_P[poisson]", (FONT, 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d((a..b.max(a * 2.0)).log_scale(), -0.3f64..0.3)
            .map_err(pe)?;
        c.configure_mesh()
            .x_desc("SNR")
            .y_desc("relative sigma_P difference")
            .label_style((FONT, 14))
            .draw()
            .map_err(pe)?;
        for (j, mode) in ["gauss-f", "gauss-qu"].iter().enumerate() {
            let col = if j == 0 { BLUE } else { RED };
            c.draw_series(LineSeries::new(
                nm.iter().filter(|r| r.noise == *mode).map(|r| (r.snr, r.rms_rel_dev)),
                col.stroke_width(2),
            ))
            .map_err(pe)?
            .label(*mode)
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], col));
        }
        c.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font((FONT, 14))
            .draw()
            .map_err(pe)?;
        Ok(())
    })
}
