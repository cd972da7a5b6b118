//! Shared plotting helpers (plotters, PNG and SVG side by side) and the calibration plots of
//! the paper: the instrumental polarization map as vectors over contours of 0.3, 0.6, 0.9%
//! (fig:insmapB), the radial profile with the fit (fig:radprofB, upper), `phi` against the polar
//! angle (fig:radprofB, lower) and the residual field (fig:residB). Drawing only: every number
//! comes from the `fit` crate.

use anyhow::{anyhow, Context, Result};
use fit::calfile::{Calibration, Model};
use fit::polar::PolarAngleTest;
use fit::RadialModel;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Once;

/// The font family every plot uses (the embedded DejaVu Sans).
pub const FONT: &str = "sans-serif";

/// Register the embedded DejaVu Sans once, so plots render on machines without fonts.
pub fn font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
    });
}

/// plotters errors carry backend types; flatten them to text.
pub fn pe<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("plot: {e:?}")
}

/// Write through a temporary file in the destination folder and rename.
pub fn atomic(path: &Path, suffix: &str, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    crate::util::write_via_temp(path, suffix, |tmp| {
        write(tmp).with_context(|| format!("cannot draw {}", path.display()))
    })
}

/// Draw the same picture as `STEM.png` and `STEM.svg`; returns both paths. The two closures
/// are the same drawing code instantiated for each backend.
pub fn save_png_svg(
    stem: &Path,
    size: (u32, u32),
    png: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
    svg: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> Result<()>,
) -> Result<Vec<PathBuf>> {
    font();
    let (p, s) = (stem.with_extension("png"), stem.with_extension("svg"));
    atomic(&p, ".png", |tmp| {
        let root = BitMapBackend::new(tmp, size).into_drawing_area();
        root.fill(&WHITE).map_err(pe)?;
        png(&root)?;
        root.present().map_err(pe)
    })?;
    atomic(&s, ".svg", |tmp| {
        let root = SVGBackend::new(tmp, size).into_drawing_area();
        root.fill(&WHITE).map_err(pe)?;
        svg(&root)?;
        root.present().map_err(pe)
    })?;
    Ok(vec![p, s])
}

/// Line segments where a gridded field crosses `level` (marching squares; cells with a NaN
/// corner are skipped). `v[j * nx + i]` is the value at `(x0 + i dx, y0 + j dy)`.
#[allow(clippy::too_many_arguments)]
pub fn contour_segments(
    v: &[f64],
    nx: usize,
    ny: usize,
    x0: f64,
    y0: f64,
    dx: f64,
    dy: f64,
    level: f64,
) -> Vec<[(f64, f64); 2]> {
    let mut segs = vec![];
    let at = |i: usize, j: usize| v[j * nx + i];
    for j in 0..ny.saturating_sub(1) {
        for i in 0..nx.saturating_sub(1) {
            let c = [(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)];
            let vals: Vec<f64> = c.iter().map(|&(a, b)| at(a, b)).collect();
            if vals.iter().any(|x| !x.is_finite()) {
                continue;
            }
            let mut pts = vec![];
            for e in 0..4 {
                let (a, b) = (e, (e + 1) % 4);
                let (va, vb) = (vals[a] - level, vals[b] - level);
                if (va < 0.0) != (vb < 0.0) {
                    let t = va / (va - vb);
                    let (xa, ya) = (x0 + c[a].0 as f64 * dx, y0 + c[a].1 as f64 * dy);
                    let (xb, yb) = (x0 + c[b].0 as f64 * dx, y0 + c[b].1 as f64 * dy);
                    pts.push((xa + t * (xb - xa), ya + t * (yb - ya)));
                }
            }
            for pair in pts.chunks(2) {
                if pair.len() == 2 {
                    segs.push([pair[0], pair[1]]);
                }
            }
        }
    }
    segs
}

/// Everything the calibration plots need, taken from a calibration (and, for a map without a
/// radial model, from a radial fit made for display).
pub struct CalPlotData<'a> {
    pub cal: &'a Calibration,
    pub radial: Option<&'a RadialModel>,
    pub polar: Option<&'a PolarAngleTest>,
    /// Optional ray-trace prediction `p(r)` (r arcmin, p fraction) for the profile.
    pub raytrace: Option<Vec<(f64, f64)>>,
    pub title: String,
}

fn field_ranges(cal: &Calibration) -> (std::ops::Range<f64>, std::ops::Range<f64>) {
    let r = &cal.region;
    let (cx, cy) = (0.5 * (r.x_min + r.x_max), 0.5 * (r.y_min + r.y_max));
    let h = 0.5 * (r.x_max - r.x_min).max(r.y_max - r.y_min) * 1.04;
    (cx - h..cx + h, cy - h..cy + h)
}

/// Every `k`-th bin so that about `n` vectors cover the field.
fn thin<'b>(bins: &'b [fit::Bin], region: &fit::FieldRegion, n_across: f64) -> Vec<&'b fit::Bin> {
    let step = (region.x_max - region.x_min).max(region.y_max - region.y_min) / n_across;
    let mut seen = std::collections::HashSet::new();
    bins.iter()
        .filter(|b| b.is_valid())
        .filter(|b| seen.insert(((b.x / step).floor() as i64, (b.y / step).floor() as i64)))
        .collect()
}

/// fig:insmapB: vectors of the instrumental polarization over contours of 0.3, 0.6, 0.9%.
pub fn draw_map<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, d: &CalPlotData) -> Result<()> {
    let radial_centre = d.radial.map(|r| r.centre);
    let cal = d.cal;
    let (xr, yr) = field_ranges(cal);
    let mut c = ChartBuilder::on(area)
        .caption(format!("{}: instrumental polarization (contours 0.3, 0.6, 0.9%)", d.title), (FONT, 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(xr.clone(), yr.clone())
        .map_err(pe)?;
    c.configure_mesh()
        .x_desc("x (arcmin from detector centre)")
        .y_desc("y (arcmin)")
        .label_style((FONT, 15))
        .disable_mesh()
        .draw()
        .map_err(pe)?;
    // Contours of p on the gridded model.
    let g = match (&cal.model, &cal.grid) {
        (Model::Map(g), _) => g.clone(),
        _ => cal.gridded(((xr.end - xr.start) / 120.0).max(0.02)),
    };
    let p: Vec<f64> = g.q.iter().zip(&g.u).map(|(q, u)| q.hypot(*u)).collect();
    for (level, colour) in [(0.003, BLUE), (0.006, RGBColor(0, 150, 0)), (0.009, RED)] {
        let segs = contour_segments(&p, g.nx, g.ny, g.x0, g.y0, g.dx, g.dy, level);
        c.draw_series(segs.into_iter().map(|s| PathElement::new(s.to_vec(), colour.stroke_width(2))))
            .map_err(pe)?
            .label(format!("{:.1}%", level * 100.0))
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(2)));
    }
    // Vectors at the bins, about 30 across.
    let bins = thin(&cal.bins, &cal.region, 30.0);
    let spacing = (xr.end - xr.start) / 30.0;
    let pmax = bins.iter().map(|b| b.p_phi().0).fold(0.0, f64::max).max(1e-6);
    let scale = 0.9 * spacing / pmax;
    c.draw_series(bins.iter().map(|b| {
        let (pp, phi) = b.p_phi();
        let (hx, hy) = (0.5 * pp * scale * phi.cos(), 0.5 * pp * scale * phi.sin());
        PathElement::new(vec![(b.x - hx, b.y - hy), (b.x + hx, b.y + hy)], BLACK.stroke_width(1))
    }))
    .map_err(pe)?;
    // Scale bar: 1%.
    let (bx, by) = (xr.start + 0.05 * (xr.end - xr.start), yr.start + 0.04 * (yr.end - yr.start));
    c.draw_series(std::iter::once(PathElement::new(vec![(bx, by), (bx + 0.01 * scale, by)], BLACK.stroke_width(3))))
        .map_err(pe)?;
    c.draw_series(std::iter::once(Text::new("1%", (bx, by + 0.03 * (yr.end - yr.start)), (FONT, 15)))).map_err(pe)?;
    // The radial fit's centre (for an imported map: the free-centre refit the profile panel
    // uses), else the calibration's own.
    let cen = radial_centre.unwrap_or_else(|| cal.centre_arcmin());
    c.draw_series(std::iter::once(Cross::new((cen[0], cen[1]), 7, MAGENTA.stroke_width(2))))
        .map_err(pe)?
        .label("radial-model centre")
        .legend(|(x, y)| Cross::new((x + 10, y), 5, MAGENTA.stroke_width(2)));
    c.configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, 14))
        .draw()
        .map_err(pe)?;
    Ok(())
}

/// fig:radprofB: upper, the signed radial component of each bin's polarization against r with
/// the fitted p(r) (and the ray-trace curve when given); lower, phi against the polar angle
/// with the unit-slope line.
pub fn draw_profile<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, d: &CalPlotData) -> Result<()> {
    let cal = d.cal;
    let (upper, lower) = area.split_vertically(area.dim_in_pixel().1 / 2);
    let centre = d.radial.map(|r| r.centre).unwrap_or([0.0, 0.0]);
    // Radial component p_r = q cos 2a + u sin 2a: p(r) itself for a radial pattern, negative
    // for a tangential one.
    let pts: Vec<(f64, f64, bool)> = cal
        .bins
        .iter()
        .filter(|b| b.is_valid())
        .map(|b| {
            let (dx, dy) = (b.x - centre[0], b.y - centre[1]);
            let a = dy.atan2(dx);
            (dx.hypot(dy), b.q * (2.0 * a).cos() + b.u * (2.0 * a).sin(), b.used)
        })
        .collect();
    // Thin very large sets (imported maps) for drawing.
    let stride = (pts.len() / 6000).max(1);
    let rmax = pts.iter().map(|p| p.0).fold(0.0, f64::max) * 1.03;
    let (mut lo, mut hi) = pts.iter().fold((0.0f64, 0.0f64), |(l, h), p| (l.min(p.1), h.max(p.1)));
    let pad = 0.05 * (hi - lo).max(1e-4);
    lo -= pad;
    hi += pad;
    let mut c = ChartBuilder::on(&upper)
        .caption(format!("{}: radial profile", d.title), (FONT, 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(65)
        .build_cartesian_2d(0.0..rmax, (lo * 100.0)..(hi * 100.0))
        .map_err(pe)?;
    c.configure_mesh()
        .x_desc("r (arcmin from the model centre)")
        .y_desc("p along the radius (%)")
        .label_style((FONT, 14))
        .draw()
        .map_err(pe)?;
    c.draw_series(
        pts.iter()
            .step_by(stride)
            .filter(|p| !p.2)
            .map(|p| Circle::new((p.0, p.1 * 100.0), 2, RGBColor(200, 120, 120).filled())),
    )
    .map_err(pe)?;
    c.draw_series(
        pts.iter().step_by(stride).filter(|p| p.2).map(|p| Circle::new((p.0, p.1 * 100.0), 2, BLUE.mix(0.5).filled())),
    )
    .map_err(pe)?
    .label("bins (red: not used)")
    .legend(|(x, y)| Circle::new((x + 10, y), 3, BLUE.filled()));
    if let Some(r) = d.radial {
        let curve: Vec<(f64, f64)> =
            (0..=200).map(|k| rmax * k as f64 / 200.0).map(|x| (x, 100.0 * r.p_of_r(x))).collect();
        c.draw_series(LineSeries::new(curve, BLACK.stroke_width(3)))
            .map_err(pe)?
            .label("fit p(r)")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK.stroke_width(3)));
    }
    if let Some(rt) = &d.raytrace {
        c.draw_series(LineSeries::new(rt.iter().map(|(x, p)| (*x, 100.0 * p)), RED.stroke_width(1)))
            .map_err(pe)?
            .label("ray trace")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], RED));
    }
    c.configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, 14))
        .draw()
        .map_err(pe)?;

    // Lower panel: phi against alpha.
    let Some(t) = d.polar else { return Ok(()) };
    let (plo, phi_hi) = t.phi_deg.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| (l.min(*p), h.max(*p)));
    let (plo, phi_hi) = (plo.min(-190.0), phi_hi.max(190.0));
    let mut c = ChartBuilder::on(&lower)
        .caption(
            format!(
                "phi vs polar angle: slope {:.4} +- {:.4}, intercept {:.2} deg",
                t.slope, t.slope_err, t.intercept_deg
            ),
            (FONT, 20),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(65)
        .build_cartesian_2d(-180.0..180.0, plo..phi_hi)
        .map_err(pe)?;
    c.configure_mesh()
        .x_desc("polar angle alpha (deg)")
        .y_desc("phi (deg)")
        .label_style((FONT, 14))
        .draw()
        .map_err(pe)?;
    let stride = (t.alpha_deg.len() / 6000).max(1);
    c.draw_series(
        t.alpha_deg
            .iter()
            .zip(&t.phi_deg)
            .step_by(stride)
            .map(|(a, p)| Circle::new((*a, *p), 2, BLUE.mix(0.5).filled())),
    )
    .map_err(pe)?;
    c.draw_series(LineSeries::new([(-180.0, -180.0), (180.0, 180.0)], BLACK.stroke_width(2)))
        .map_err(pe)?
        .label("unit slope, zero intercept")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK.stroke_width(2)));
    for off in [-90.0, 90.0] {
        if (t.intercept_deg - off).abs() < 30.0 {
            c.draw_series(LineSeries::new(
                [(-180.0, off - 180.0), (180.0, off + 180.0)],
                BLACK.mix(0.5).stroke_width(1),
            ))
            .map_err(pe)?
            .label("unit slope, +-90 deg (tangential)")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK.mix(0.5)));
        }
    }
    c.configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, 14))
        .draw()
        .map_err(pe)?;
    Ok(())
}

/// fig:residB: the residual field (data minus radial model, as Q and U), coloured by its size,
/// with vectors.
pub fn draw_residual<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, d: &CalPlotData) -> Result<()> {
    let cal = d.cal;
    let Some(radial) = d.radial else { return Ok(()) };
    let (xr, yr) = field_ranges(cal);
    let res: Vec<(f64, f64, f64, f64)> = cal
        .bins
        .iter()
        .filter(|b| b.is_valid())
        .map(|b| {
            let (q, u) = radial.qu(b.x, b.y);
            (b.x, b.y, b.q - q, b.u - u)
        })
        .collect();
    let mut mags: Vec<f64> = res.iter().map(|r| r.2.hypot(r.3)).collect();
    mags.sort_by(|a, b| a.total_cmp(b));
    let top = mags.get(mags.len() * 98 / 100).copied().unwrap_or(1e-4).max(1e-6);
    let mut c = ChartBuilder::on(area)
        .caption(format!("{}: residual field (colour |residual|, 0 to {:.3}%)", d.title, top * 100.0), (FONT, 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(xr.clone(), yr.clone())
        .map_err(pe)?;
    c.configure_mesh()
        .x_desc("x (arcmin)")
        .y_desc("y (arcmin)")
        .label_style((FONT, 15))
        .disable_mesh()
        .draw()
        .map_err(pe)?;
    // Squares at the bins, coloured with viridis; size from the typical bin spacing.
    let spacing = nearest_spacing(&res);
    let h = 0.5 * spacing;
    c.draw_series(res.iter().map(|r| {
        let t = (r.2.hypot(r.3) / top).clamp(0.0, 1.0);
        Rectangle::new([(r.0 - h, r.1 - h), (r.0 + h, r.1 + h)], ViridisRGB::get_color(t).filled())
    }))
    .map_err(pe)?;
    let thinned: Vec<&fit::Bin> = thin(&cal.bins, &cal.region, 30.0);
    let vspace = (xr.end - xr.start) / 30.0;
    let scale = 0.9 * vspace / top;
    c.draw_series(thinned.iter().map(|b| {
        let (q, u) = radial.qu(b.x, b.y);
        let (dq, du) = (b.q - q, b.u - u);
        let m = dq.hypot(du).min(top);
        let a = 0.5 * du.atan2(dq);
        let (hx, hy) = (0.5 * m * scale * a.cos(), 0.5 * m * scale * a.sin());
        PathElement::new(vec![(b.x - hx, b.y - hy), (b.x + hx, b.y + hy)], WHITE.stroke_width(1))
    }))
    .map_err(pe)?;
    Ok(())
}

fn nearest_spacing(res: &[(f64, f64, f64, f64)]) -> f64 {
    // Median distance to the next bin along x in the same row: enough for a regular grid.
    let mut xs: Vec<f64> = res.iter().map(|r| r.0).collect();
    xs.sort_by(|a, b| a.total_cmp(b));
    xs.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let mut d: Vec<f64> = xs.windows(2).map(|w| w[1] - w[0]).collect();
    d.sort_by(|a, b| a.total_cmp(b));
    d.get(d.len() / 2).copied().unwrap_or(0.1)
}

/// Draw the three calibration plots into `dir` as `{stem}_map`, `{stem}_profile`,
/// `{stem}_residual` (PNG and SVG); returns the files written.
pub fn calibration_plots(dir: &Path, stem: &str, d: &CalPlotData) -> Result<Vec<PathBuf>> {
    let mut out = vec![];
    out.extend(save_png_svg(&dir.join(format!("{stem}_map")), (900, 900), |a| draw_map(a, d), |a| draw_map(a, d))?);
    out.extend(save_png_svg(
        &dir.join(format!("{stem}_profile")),
        (900, 1100),
        |a| draw_profile(a, d),
        |a| draw_profile(a, d),
    )?);
    if d.radial.is_some() {
        out.extend(save_png_svg(
            &dir.join(format!("{stem}_residual")),
            (900, 900),
            |a| draw_residual(a, d),
            |a| draw_residual(a, d),
        )?);
    }
    Ok(out)
}

/// A progress bar on stderr (hidden when `quiet`, e.g. with --json, or when stderr is not a
/// terminal, as indicatif decides).
pub fn progress(total: u64, msg: &str, quiet: bool) -> indicatif::ProgressBar {
    let bar = if quiet { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(total) };
    if let Ok(st) =
        indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg}")
    {
        bar.set_style(st);
    }
    bar.set_message(msg.to_string());
    bar
}
