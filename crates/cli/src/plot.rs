//! Shared plotting helpers (plotters, PNG and SVG side by side) and the calibration plots of
//! the paper: the instrumental polarization map as vectors over contours of 0.3, 0.6, 0.9%
//! (fig:insmapB), the radial profile with the fit (fig:radprofB, upper), `phi` against the polar
//! angle (fig:radprofB, lower) and the residual field (fig:residB). Drawing only: every number
//! comes from the `fit` crate.

use anyhow::{anyhow, Context, Result};
use fit::calfile::{Calibration, Model};
use fit::polar::PolarAngleTest;
use fit::RadialModel;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::{CoordTranslate, Shift};
use plotters::element::{DashedPathElement, IntoDynElement};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::{Path, PathBuf};
use std::sync::Once;

/// A pixel position on a drawing backend.
type BackendCoord = (i32, i32);

/// A 2-D chart with x and y coordinates `X`, `Y` (linear or log).
pub type Chart<'a, DB, X, Y> = ChartContext<'a, DB, Cartesian2d<X, Y>>;

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

/// Draw one PNG of `size` pixels (white background) at `path`, through [`atomic`].
pub fn save_png(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
) -> Result<()> {
    require_png(path)?;
    font();
    atomic(path, ".png", |tmp| {
        let root = BitMapBackend::new(tmp, size).into_drawing_area();
        root.fill(&WHITE).map_err(pe)?;
        draw(&root)?;
        root.present().map_err(pe)
    })
}

/// The image format a `--plot` file name asks for: PNG or SVG by its extension (any case);
/// anything else is refused rather than written as PNG bytes under another name.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ImageFormat {
    Png,
    Svg,
}

impl ImageFormat {
    pub fn of(path: &Path) -> Result<Self> {
        let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
        match ext.as_str() {
            "png" => Ok(Self::Png),
            "svg" => Ok(Self::Svg),
            _ => Err(anyhow!(
                "{}: cannot tell the image format from the extension '{ext}': name the file .png or .svg",
                path.display()
            )),
        }
    }
}

/// For plots drawn only as PNG: refuse any other extension (a `.svg` name would get PNG bytes).
pub fn require_png(path: &Path) -> Result<()> {
    if ImageFormat::of(path)? != ImageFormat::Png {
        return Err(anyhow!("{}: this plot is drawn as PNG only: name the file .png", path.display()));
    }
    Ok(())
}

/// Draw one image at `path`, PNG or SVG by its extension ([`ImageFormat::of`]), through
/// [`atomic`]; the two closures are the same drawing code instantiated for each backend.
pub fn save_image(
    path: &Path,
    size: (u32, u32),
    png: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
    svg: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> Result<()>,
) -> Result<()> {
    match ImageFormat::of(path)? {
        ImageFormat::Png => save_png(path, size, png),
        ImageFormat::Svg => {
            font();
            atomic(path, ".svg", |tmp| {
                let root = SVGBackend::new(tmp, size).into_drawing_area();
                root.fill(&WHITE).map_err(pe)?;
                svg(&root)?;
                root.present().map_err(pe)
            })
        }
    }
}

/// Draw the same picture as `STEM.png` and `STEM.svg`; returns both paths. The two closures
/// are the same drawing code instantiated for each backend.
pub fn save_png_svg(
    stem: &Path,
    size: (u32, u32),
    png: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
    svg: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> Result<()>,
) -> Result<Vec<PathBuf>> {
    let (p, s) = (stem.with_extension("png"), stem.with_extension("svg"));
    save_png(&p, size, png)?;
    atomic(&s, ".svg", |tmp| {
        let root = SVGBackend::new(tmp, size).into_drawing_area();
        root.fill(&WHITE).map_err(pe)?;
        svg(&root)?;
        root.present().map_err(pe)
    })?;
    Ok(vec![p, s])
}

/// Tick labels without float noise: `0` (never `-0.0`), `0.25`, `150`, `1e5`, `2.5e-4`:
/// three significant digits, whole numbers below 1e5 in full, trailing zeros dropped.
pub fn tick(v: &f64) -> String {
    let v = *v;
    // Ticks computed as multiples of a step land a rounding residue away from 0.
    if v.abs() < 1e-13 || !v.is_finite() {
        return if v.is_finite() { "0".into() } else { format!("{v}") };
    }
    let trim = |s: String| -> String {
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    };
    let a = v.abs();
    if !(1e-3..1e5).contains(&a) {
        let s = format!("{v:.2e}");
        let (m, e) = s.split_once('e').unwrap_or((&s, "0"));
        format!("{}e{e}", trim(m.to_string()))
    } else {
        let decimals = (2 - a.log10().floor() as i32).max(0) as usize;
        trim(format!("{v:.decimals$}"))
    }
}

/// The frame every chart shares: caption, axis titles, tick labels ([`tick`]) and margins that
/// leave room for the widest labels. Build with [`Axes::new`], adjust, draw with [`chart`].
pub struct Axes<'s> {
    pub caption: String,
    pub caption_size: u32,
    pub x_desc: &'s str,
    pub y_desc: &'s str,
    /// Grid lines (off for maps, where they would hide the vectors).
    pub grid: bool,
    /// Number of x ticks (plotters chooses when `None`).
    pub x_labels: Option<usize>,
    /// x tick labels (default [`tick`]).
    pub x_fmt: Option<&'s dyn Fn(&f64) -> String>,
}

/// Room right of the plotting area for half of the last x tick label.
const RIGHT_PAD: u32 = 30;

impl<'s> Axes<'s> {
    pub fn new(caption: impl Into<String>, x_desc: &'s str, y_desc: &'s str) -> Self {
        Axes { caption: caption.into(), caption_size: 22, x_desc, y_desc, grid: true, x_labels: None, x_fmt: None }
    }
    pub fn caption_size(mut self, px: u32) -> Self {
        self.caption_size = px;
        self
    }
    pub fn no_grid(mut self) -> Self {
        self.grid = false;
        self
    }
    pub fn x_ticks(mut self, n: usize, fmt: &'s dyn Fn(&f64) -> String) -> Self {
        self.x_labels = Some(n);
        self.x_fmt = Some(fmt);
        self
    }
}

/// A chart with `ax`'s frame on `area`, x and y ranges given (linear `a..b` or
/// `(a..b).log_scale()`), mesh and axis labels drawn.
pub fn chart<'a, DB, X, Y>(
    area: &'a DrawingArea<DB, Shift>,
    ax: &Axes,
    x: X,
    y: Y,
) -> Result<Chart<'a, DB, X::CoordDescType, Y::CoordDescType>>
where
    DB: DrawingBackend + 'a,
    X: AsRangedCoord<Value = f64>,
    Y: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let mut c = ChartBuilder::on(area)
        .caption(&ax.caption, (FONT, ax.caption_size))
        .margin(12)
        .margin_right(RIGHT_PAD)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(x, y)
        .map_err(pe)?;
    let xf = ax.x_fmt.unwrap_or(&tick);
    let mut m = c.configure_mesh();
    m.x_desc(ax.x_desc)
        .y_desc(ax.y_desc)
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 15))
        .x_label_formatter(xf)
        .y_label_formatter(&tick);
    if !ax.grid {
        m.disable_mesh();
    }
    if let Some(n) = ax.x_labels {
        m.x_labels(n);
    }
    m.draw().map_err(pe)?;
    Ok(c)
}

/// A legend key: a short line in `style` (for `.legend(line_key(BLUE))`).
pub fn line_key<S: Into<ShapeStyle>>(style: S) -> impl Fn(BackendCoord) -> PathElement<BackendCoord> {
    let style = style.into();
    move |(x, y)| PathElement::new([(x, y), (x + 20, y)], style)
}

/// A legend key for a dashed series.
pub fn dashed_key<S: Into<ShapeStyle>>(
    style: S,
) -> impl Fn(BackendCoord) -> DashedPathElement<std::vec::IntoIter<BackendCoord>, i32> {
    let style = style.into();
    move |(x, y)| DashedPathElement::new(vec![(x, y), (x + 22, y)], 6, 2, style)
}

/// A legend in a panel of its own, for a plot where a box inside would hide the data (the
/// map): a blank chart on `area` (its top level with the plots beside it), entries added with
/// [`key`], drawn with [`legend`].
pub fn key_panel<'a, DB: DrawingBackend + 'a>(
    area: &'a DrawingArea<DB, Shift>,
) -> Result<Chart<'a, DB, RangedCoordf64, RangedCoordf64>> {
    ChartBuilder::on(area).margin_top(45).build_cartesian_2d(0.0..1.0, 0.0..1.0).map_err(pe)
}

/// One entry of a [`key_panel`] legend: `label` with the key `draw` makes.
pub fn key<'a, DB, E>(
    k: &mut Chart<'a, DB, RangedCoordf64, RangedCoordf64>,
    label: impl Into<String>,
    draw: impl Fn(BackendCoord) -> E + 'a,
) -> Result<()>
where
    DB: DrawingBackend + 'a,
    E: IntoDynElement<'a, DB, BackendCoord>,
{
    k.draw_series(std::iter::empty::<Circle<(f64, f64), i32>>()).map_err(pe)?.label(label).legend(draw);
    Ok(())
}

/// The legend of the labelled series, boxed, at `pos` (a corner the data leave free).
pub fn legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    c: &mut ChartContext<'a, DB, CT>,
    pos: SeriesLabelPosition,
) -> Result<()> {
    c.configure_series_labels()
        .position(pos)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, 14))
        .draw()
        .map_err(pe)
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

/// The frame of a field map: arcmin axes, no grid (it would hide the vectors).
fn map_axes(caption: String) -> Axes<'static> {
    Axes::new(caption, "x (arcmin from detector centre)", "y (arcmin)").no_grid()
}

/// `area` less `px` pixels on the right, and those pixels (for a legend or a colour bar).
fn split_right<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    px: u32,
) -> (DrawingArea<DB, Shift>, DrawingArea<DB, Shift>) {
    area.split_horizontally(area.dim_in_pixel().0.saturating_sub(px))
}

/// Width kept right of the map for its legend.
const MAP_LEGEND_ROOM: u32 = 200;

/// fig:insmapB: vectors of the instrumental polarization over contours of 0.3, 0.6, 0.9%.
pub fn draw_map<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, d: &CalPlotData) -> Result<()> {
    let radial_centre = d.radial.map(|r| r.centre);
    let cal = d.cal;
    let (xr, yr) = field_ranges(cal);
    let (main, side) = split_right(area, MAP_LEGEND_ROOM);
    let caption = format!("{}: instrumental polarization (contours 0.3, 0.6, 0.9%)", d.title);
    let mut c = chart(&main, &map_axes(caption), xr.clone(), yr.clone())?;
    // The legend goes beside the map: inside, its box would hide contours and vectors.
    let mut k = key_panel(&side)?;
    // Contours of p on the gridded model.
    let g = match (&cal.model, &cal.grid) {
        (Model::Map(g), _) => g.clone(),
        _ => cal.gridded(((xr.end - xr.start) / 120.0).max(0.02)),
    };
    let p: Vec<f64> = g.q.iter().zip(&g.u).map(|(q, u)| q.hypot(*u)).collect();
    for (level, colour) in [(0.003, BLUE), (0.006, RGBColor(0, 150, 0)), (0.009, RED)] {
        let segs = contour_segments(&p, g.nx, g.ny, g.x0, g.y0, g.dx, g.dy, level);
        c.draw_series(segs.into_iter().map(|s| PathElement::new(s.to_vec(), colour.stroke_width(2)))).map_err(pe)?;
        key(&mut k, format!("p = {:.1}%", level * 100.0), line_key(colour.stroke_width(2)))?;
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
    // The label right of the bar, in the empty margin below the lowest row of vectors.
    let label = TextStyle::from((FONT, 15).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    c.draw_series(std::iter::once(Text::new("1%", (bx + 0.01 * scale + 0.01 * (xr.end - xr.start), by), label)))
        .map_err(pe)?;
    // The radial fit's centre (for an imported map: the free-centre refit the profile panel
    // uses), else the calibration's own.
    let cen = radial_centre.unwrap_or_else(|| cal.centre_arcmin());
    c.draw_series(std::iter::once(Cross::new((cen[0], cen[1]), 7, MAGENTA.stroke_width(2)))).map_err(pe)?;
    key(&mut k, "radial-model centre", |(x, y)| Cross::new((x + 10, y), 5, MAGENTA.stroke_width(2)))?;
    legend(&mut k, SeriesLabelPosition::UpperLeft)
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
    let ax =
        Axes::new(format!("{}: radial profile", d.title), "r (arcmin from the model centre)", "p along the radius (%)");
    let mut c = chart(&upper, &ax, 0.0..rmax, (lo * 100.0)..(hi * 100.0))?;
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
            .legend(line_key(BLACK.stroke_width(3)));
    }
    if let Some(rt) = &d.raytrace {
        c.draw_series(LineSeries::new(rt.iter().map(|(x, p)| (*x, 100.0 * p)), RED.stroke_width(1)))
            .map_err(pe)?
            .label("ray trace")
            .legend(line_key(RED));
    }
    legend(&mut c, SeriesLabelPosition::UpperLeft)?;

    // Lower panel: phi against alpha.
    let Some(t) = d.polar else { return Ok(()) };
    let (plo, phi_hi) = t.phi_deg.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| (l.min(*p), h.max(*p)));
    let (plo, phi_hi) = (plo.min(-190.0), phi_hi.max(190.0));
    let ax = Axes::new(
        format!("phi vs polar angle: slope {:.4} +- {:.4}, intercept {:.2} deg", t.slope, t.slope_err, t.intercept_deg),
        "polar angle alpha (deg)",
        "phi (deg)",
    )
    .caption_size(20);
    let mut c = chart(&lower, &ax, -180.0..180.0, plo..phi_hi)?;
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
        .legend(line_key(BLACK.stroke_width(2)));
    for off in [-90.0, 90.0] {
        if (t.intercept_deg - off).abs() < 30.0 {
            c.draw_series(LineSeries::new(
                [(-180.0, off - 180.0), (180.0, off + 180.0)],
                BLACK.mix(0.5).stroke_width(1),
            ))
            .map_err(pe)?
            .label("unit slope, +-90 deg (tangential)")
            .legend(line_key(BLACK.mix(0.5)));
        }
    }
    legend(&mut c, SeriesLabelPosition::UpperLeft)
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
    let (main, side) = split_right(area, COLOUR_BAR_ROOM);
    let caption = format!("{}: residual field (colour |residual|, 0 to {:.3}%)", d.title, top * 100.0);
    let mut c = chart(&main, &map_axes(caption), xr.clone(), yr.clone())?;
    colour_bar(&side, "|residual| (%)", 100.0 * top)?;
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

/// Width kept right of a map for its colour bar.
const COLOUR_BAR_ROOM: u32 = 150;

/// A viridis colour bar from 0 to `top` on `area`, level with a [`chart`] beside it (same
/// caption size and label areas).
fn colour_bar<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, label: &str, top: f64) -> Result<()> {
    let none = |_: &f64| String::new();
    let ax = Axes::new(" ", "", label).no_grid().x_ticks(2, &none);
    let mut c = chart(area, &ax, 0.0..1.0, 0.0..top)?;
    let n = 200;
    c.draw_series((0..n).map(|i| {
        let (a, b) = (top * i as f64 / n as f64, top * (i + 1) as f64 / n as f64);
        Rectangle::new([(0.0, a), (1.0, b)], ViridisRGB::get_color((i as f64 + 0.5) / n as f64).filled())
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
    let map_size = (900 + MAP_LEGEND_ROOM, 900);
    out.extend(save_png_svg(&dir.join(format!("{stem}_map")), map_size, |a| draw_map(a, d), |a| draw_map(a, d))?);
    out.extend(save_png_svg(
        &dir.join(format!("{stem}_profile")),
        (900, 1100),
        |a| draw_profile(a, d),
        |a| draw_profile(a, d),
    )?);
    if d.radial.is_some() {
        out.extend(save_png_svg(
            &dir.join(format!("{stem}_residual")),
            (900 + COLOUR_BAR_ROOM, 900),
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

#[cfg(test)]
mod tests {
    use super::tick;

    /// Tick labels: no rounding residue, no negative zero, no trailing zeros.
    #[test]
    fn tick_labels() {
        let cases = [
            (0.0, "0"),
            (-0.0, "0"),
            (5.551115123125783e-17, "0"),
            (0.1 + 0.2, "0.3"),
            (-0.1, "-0.1"),
            (0.25, "0.25"),
            (0.0015, "0.0015"),
            (150.0, "150"),
            (10000.0, "10000"),
            (1e5, "1e5"),
            (2.5e-4, "2.5e-4"),
            (-1e-5, "-1e-5"),
        ];
        for (v, s) in cases {
            assert_eq!(tick(&v), s, "tick({v:e})");
        }
    }
}
