//! `instpol fit-standards --plot-dir`: one band's figure of a telescope fit (q and u against
//! the parallactic angle with the model curve, and the residuals).

use anyhow::Result;
use fit::telescope::TelescopeFit;
use plotters::prelude::*;
use std::path::Path;

/// One standard's point in the `--plot-dir` figure (fractions; angle in deg).
#[derive(Debug, Clone, Copy, PartialEq)]
struct PlotPoint {
    pa_deg: f64,
    /// What the upper panel draws: the measured `(q, u)`, or for a star the model gives its
    /// own polarization (a polarized standard, a rotator angle) the measurement with that
    /// removed as the fitted model has it, `q - (q_model - q_curve(pa))`.
    q: f64,
    u: f64,
    sigma_q: f64,
    sigma_u: f64,
    /// Data minus model (the lower panel).
    resid_q: f64,
    resid_u: f64,
    flagged: bool,
    /// The star's own polarization was removed (drawn as a triangle).
    shifted: bool,
}

/// The series of one band's figure: the model curve of an unpolarized star at rotator angle
/// 0, `(pa_deg, q, u)` every degree, and the points. Every point sits on the curve exactly
/// when its residual is zero: a polarized standard is not drawn at its raw `(q, u)`, which the
/// model puts on a curve of its own (its `p_true`, `chi_true` through the telescope).
struct BandPlot {
    curve: Vec<(f64, f64, f64)>,
    points: Vec<PlotPoint>,
}

fn band_plot(f: &TelescopeFit, bi: usize) -> Result<BandPlot> {
    let (band, m) = &f.bands[bi];
    let unpol = |pa_rad: f64| m.unpolarized(pa_rad).map_err(|e| anyhow::anyhow!("model: {e}"));
    let mut curve = Vec::with_capacity(361);
    for k in 0..=360 {
        let pa = -180.0 + k as f64;
        let (q, u) = unpol(f64::to_radians(pa))?;
        curve.push((pa, q, u));
    }
    let mut points = Vec::new();
    for p in f.points.iter().filter(|p| &p.obs.band == band) {
        let o = &p.obs;
        let shifted = o.sky != (0.0, 0.0) || o.rotator != 0.0;
        let (q, u) = if shifted {
            let (cq, cu) = unpol(o.parallactic)?;
            (o.qu.q - p.q_model + cq, o.qu.u - p.u_model + cu)
        } else {
            (o.qu.q, o.qu.u)
        };
        points.push(PlotPoint {
            pa_deg: o.parallactic.to_degrees(),
            q,
            u,
            sigma_q: o.qu.sigma_q(),
            sigma_u: o.qu.sigma_u(),
            resid_q: o.qu.q - p.q_model,
            resid_u: o.qu.u - p.u_model,
            flagged: p.flagged,
            shifted,
        });
    }
    Ok(BandPlot { curve, points })
}

/// The legend's key of the polarized standards' triangles.
const POL_KEY: &str = "polarized, own P removed";

/// The figure's size (px): 900 x 1000, drawn for one journal column (`crate::plot`).
const SIZE: (u32, u32) = (900, 1000);

/// q and u against the parallactic angle with the model curve (upper panel), residuals
/// (lower panel); flagged points hollow; polarized standards (triangles) with their own
/// polarization removed as the model has it, so that they sit on the same curve ([`band_plot`]).
/// Written as `STEM.png` and `STEM.svg`; returns both paths.
/// `band` is the band as the title writes it (`V (550 nm)`).
pub fn plot_band(stem: &Path, f: &TelescopeFit, bi: usize, band: &str) -> Result<Vec<std::path::PathBuf>> {
    let d = figure(f, bi, band)?;
    crate::plot::save_png_svg(stem, SIZE, |root| draw(root, &d), |root| draw(root, &d))
}

/// What one band's figure draws, in percent.
struct Figure {
    title: String,
    curve: Vec<(f64, f64, f64)>,
    pts: Vec<PlotPoint>,
    /// The q, u panel's and the residual panel's y ranges: the data's, error bars included
    /// ([`crate::plot::data_range`]).
    y: std::ops::Range<f64>,
    r: std::ops::Range<f64>,
    /// The parallactic angles shown: the data's, 5 % of their span beyond each end.
    xr: (f64, f64),
}

fn figure(f: &TelescopeFit, bi: usize, band: &str) -> Result<Figure> {
    let BandPlot { curve, points: pts } = band_plot(f, bi)?;
    let (lo, hi) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| (l.min(p.pa_deg), h.max(p.pa_deg)));
    let pad = 0.05 * (hi - lo).max(20.0);
    let xr = if lo.is_finite() { ((lo - pad).max(-180.0), (hi + pad).min(180.0)) } else { (-180.0, 180.0) };
    let curve: Vec<(f64, f64, f64)> = curve
        .iter()
        .filter(|c| c.0 >= xr.0 - 1.0 && c.0 <= xr.1 + 1.0)
        .map(|&(pa, q, u)| (pa.clamp(xr.0, xr.1), 100.0 * q, 100.0 * u))
        .collect();
    let ys = curve.iter().flat_map(|c| [c.1, c.2]).chain(pts.iter().flat_map(|p| {
        [100.0 * (p.q - p.sigma_q), 100.0 * (p.q + p.sigma_q), 100.0 * (p.u - p.sigma_u), 100.0 * (p.u + p.sigma_u)]
    }));
    let (ylo, yhi) = crate::plot::extent(ys).unwrap_or((-0.05, 0.05));
    // The residuals with their error bars, and the zero line drawn through them.
    let rs = pts.iter().flat_map(|p| {
        [100.0 * (p.resid_q - p.sigma_q), 100.0 * (p.resid_q + p.sigma_q), 100.0 * (p.resid_u - p.sigma_u)]
            .into_iter()
            .chain([100.0 * (p.resid_u + p.sigma_u), 0.0])
    });
    let (rlo, rhi) = crate::plot::extent(rs).unwrap_or((-0.05, 0.05));
    let (y, r) = (crate::plot::data_range(ylo, yhi), crate::plot::data_range(rlo, rhi));
    let model = f.model.name();
    let model = model.get(..1).map_or(String::new(), |c| c.to_uppercase()) + model.get(1..).unwrap_or("");
    let title = format!("{band}, {model}: χ²/dof = {:.2}", f.chi2_reduced);
    Ok(Figure { title, curve, pts, y, r, xr })
}

/// The upper panel's legend below it: q and u (data and model), and in a second row, when
/// any is drawn, the polarized standards' triangles in q's and u's colours, as plotted.
fn draw_keys<DB: DrawingBackend>(area: &DrawingArea<DB, plotters::coord::Shift>, keyed: bool) -> Result<()> {
    type Key<'k, DB> = &'k dyn Fn(&DrawingArea<DB, plotters::coord::Shift>, (i32, i32)) -> Result<()>;
    let data_and_model = |col: RGBColor| {
        move |a: &DrawingArea<DB, plotters::coord::Shift>, (x, y): (i32, i32)| -> Result<()> {
            a.draw(&PathElement::new([(x, y), (x + 22, y)], col.stroke_width(2))).map_err(crate::plot::pe)?;
            a.draw(&Circle::new((x + 11, y), 5, col.filled())).map_err(crate::plot::pe)
        }
    };
    let (q, u) = (data_and_model(crate::plot::VERMILLION), data_and_model(crate::plot::BLUE_OI));
    let tri = |a: &DrawingArea<DB, plotters::coord::Shift>, (x, y): (i32, i32)| -> Result<()> {
        for (dx, col) in [(6, crate::plot::VERMILLION), (20, crate::plot::BLUE_OI)] {
            a.draw(&TriangleMarker::new((x + dx, y), 6, col.filled())).map_err(crate::plot::pe)?;
        }
        Ok(())
    };
    let qu: Vec<(String, Key<DB>)> = vec![("q data, model".into(), &q), ("u data, model".into(), &u)];
    if !keyed {
        return crate::plot::key_row(area, &qu);
    }
    let (first, second) = area.split_vertically(area.dim_in_pixel().1 / 2);
    crate::plot::key_row(&first, &qu)?;
    crate::plot::key_row(&second, &[(POL_KEY.to_string(), &tri as Key<DB>)])
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, plotters::coord::Shift>, d: &Figure) -> Result<()> {
    let Figure { title, curve, pts, y, r: rr, xr } = d;
    let xr = xr.0..xr.1;
    {
        let (top, bottom) = root.split_vertically(520);
        // The model spans every angle and leaves no corner free: the legend is a row below
        // (two with the polarized standards' key).
        let keyed = pts.iter().any(|p| p.shifted);
        let rows = if keyed { 3 } else { 2 };
        let (top, keys) = top.split_vertically(520 - rows * crate::plot::pt(crate::plot::LEGEND_PT));
        let ax = crate::plot::Axes::new(title.clone(), "parallactic angle (deg)", "q, u (%)");
        let mut c = crate::plot::chart(&top, &ax, xr.clone(), y.clone())?;
        for (col, idx) in [(crate::plot::VERMILLION, 0usize), (crate::plot::BLUE_OI, 1)] {
            c.draw_series(LineSeries::new(
                curve.iter().map(|p| (p.0, if idx == 0 { p.1 } else { p.2 })),
                col.stroke_width(2),
            ))
            .map_err(crate::plot::pe)?;
            for p in pts.iter() {
                let (v, s) = if idx == 0 { (p.q, p.sigma_q) } else { (p.u, p.sigma_u) };
                let x = p.pa_deg;
                c.draw_series(std::iter::once(PathElement::new([(x, 100.0 * (v - s)), (x, 100.0 * (v + s))], col)))
                    .map_err(crate::plot::pe)?;
                let style = if p.flagged { col.stroke_width(2) } else { col.filled() };
                if p.shifted {
                    c.draw_series(std::iter::once(TriangleMarker::new((x, 100.0 * v), 6, style)))
                        .map_err(crate::plot::pe)?;
                } else {
                    c.draw_series(std::iter::once(Circle::new((x, 100.0 * v), 5, style))).map_err(crate::plot::pe)?;
                }
            }
        }
        draw_keys(&keys, keyed)?;
        let ax = crate::plot::Axes::new(
            "residuals (data - model; hollow: flagged)",
            "parallactic angle (deg)",
            "residual (%)",
        );
        let mut r = crate::plot::chart(&bottom, &ax, xr.clone(), rr.clone())?;
        r.draw_series(LineSeries::new([(xr.start, 0.0), (xr.end, 0.0)], BLACK)).map_err(crate::plot::pe)?;
        for p in pts.iter() {
            let x = p.pa_deg;
            let (q, u) = (crate::plot::VERMILLION, crate::plot::BLUE_OI);
            for (col, d, s, dx) in [(q, p.resid_q, p.sigma_q, -1.5), (u, p.resid_u, p.sigma_u, 1.5)] {
                r.draw_series(std::iter::once(PathElement::new(
                    [(x + dx, 100.0 * (d - s)), (x + dx, 100.0 * (d + s))],
                    col,
                )))
                .map_err(crate::plot::pe)?;
                let style = if p.flagged { col.stroke_width(2) } else { col.filled() };
                r.draw_series(std::iter::once(Circle::new((x + dx, 100.0 * d), 4, style))).map_err(crate::plot::pe)?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
#[path = "../../tests/common/standards.rs"]
mod standards;

#[cfg(test)]
mod tests {
    use super::*;
    use fit::telescope::{fit_band, parse_observations, FitOptions, ModelKind};
    use mueller::mirror::MetalTable;

    /// Two unpolarized and two polarized standards (5 % at 30 deg, 4 % at 120 deg) seen through
    /// an aluminium M3 (factor 0.86, offset 40 deg) at twelve parallactic angles each, made
    /// with the track-averaged chain (`BandModel::sky_through`, not the fit's residuals), with
    /// a fixed +-2e-4 pattern for noise; fitted with the Wiersema model.
    fn fitted() -> TelescopeFit {
        let table = MetalTable::builtin("aluminium").unwrap();
        let text = standards::polarized_standards_csv(Some("V"));
        let obs = parse_observations(&text, Path::new("night.csv")).unwrap();
        fit_band(ModelKind::Wiersema, &obs, &table, &FitOptions { clip: None, ..Default::default() }).unwrap()
    }

    /// The upper panel once drew the curve of an unpolarized star only, so polarized
    /// standards sat off it by their own 4-5 %. Every point lies on the curve up to its
    /// residual (the lower panel's value, data minus model): the polarized standards with the
    /// residuals the fit leaves (~2e-4), far closer than their raw values (several %).
    #[test]
    fn polarized_standards_sit_on_the_curve_up_to_their_residual() {
        let f = fitted();
        let bp = band_plot(&f, 0).unwrap();
        assert_eq!(bp.points.len(), 48);
        assert_eq!(bp.curve.len(), 361);
        let (_, m) = &f.bands[0];
        for (p, fp) in bp.points.iter().zip(f.points.iter()) {
            // The curve at this angle, from the band model at the fitted parameters.
            let (cq, cu) = m.unpolarized(p.pa_deg.to_radians()).unwrap();
            assert!((p.q - cq - p.resid_q).abs() < 1e-12 && (p.u - cu - p.resid_u).abs() < 1e-12, "{p:?}");
            assert!(p.resid_q.abs() < 1e-3 && p.resid_u.abs() < 1e-3, "{p:?}");
            let polarized = fp.obs.sky != (0.0, 0.0);
            assert_eq!(p.shifted, polarized);
            if polarized {
                // The raw measurement is far off the unpolarized curve: what the old plot drew.
                assert!((fp.obs.qu.q - cq).hypot(fp.obs.qu.u - cu) > 0.02, "{:?}", fp.obs);
            } else {
                assert_eq!((p.q, p.u), (fp.obs.qu.q, fp.obs.qu.u), "unpolarized stars drawn as measured");
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let written = plot_band(&dir.path().join("v"), &f, 0, "V (550 nm)").unwrap();
        assert_eq!(written, [dir.path().join("v.png"), dir.path().join("v.svg")]);
        assert!(written.iter().all(|p| p.is_file()));
    }
}
