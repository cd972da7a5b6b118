//! Shared plotting helpers (plotters, PNG and SVG side by side) and the calibration plots of
//! the paper: the instrumental polarization map as a colour image of p with vectors and
//! contours of 0.3, 0.6, 0.9% (fig:insmapB), the radial profile with the fit (fig:radprofB, upper), `phi` against the polar
//! angle (fig:radprofB, lower) and the residual field (fig:residB). Drawing only: every number
//! comes from the `fit` crate.

use anyhow::{anyhow, Context, Result};
use fit::files::calfile::{Calibration, Model};
use fit::models::polar::PolarAngleTest;
use fit::RadialModel;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::{CoordTranslate, Shift};
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::{Path, PathBuf};
use std::sync::Once;

/// A pixel position on a drawing backend.
type BackendCoord = (i32, i32);

/// The printed width every figure is designed for: one column of a two-column journal (A&A,
/// PASP, MNRAS: 8.8 cm, 249 pt). Font sizes are given in points at that width and turned into
/// pixels from the figure's own pixel width ([`px_per_pt`]), so a figure scaled into a column
/// keeps every text at least [`MIN_FONT_PT`].
pub const PRINTED_WIDTH_CM: f64 = 8.8;

/// The smallest font size, in points at the printed width (tick labels, legends).
pub const MIN_FONT_PT: f64 = 9.0;

/// A figure at least this wide (px) is drawn to be printed across a page, [`PAGE_WIDTH_CM`]
/// (two columns and their gap): a figure of several panels side by side.
pub const PAGE_FIGURE_PX: u32 = 1800;

/// The printed width of a page-wide figure (A&A's two columns and the gap between: 18 cm).
pub const PAGE_WIDTH_CM: f64 = 18.0;

/// Pixels per typographic point (1/72 inch) for a figure `width_px` wide printed
/// [`PRINTED_WIDTH_CM`] wide (or [`PAGE_WIDTH_CM`] from [`PAGE_FIGURE_PX`] on): e.g.
/// 1000 px / 249.4 pt = 4.01 px/pt.
pub fn px_per_pt(width_px: u32) -> f64 {
    let cm = if width_px >= PAGE_FIGURE_PX { PAGE_WIDTH_CM } else { PRINTED_WIDTH_CM };
    width_px as f64 / (cm / 2.54 * 72.0)
}

thread_local! {
    /// The pixel width of the figure being drawn (set by the `save_*` functions).
    static FIGURE_WIDTH_PX: std::cell::Cell<u32> = const { std::cell::Cell::new(1000) };
}

/// Set the width [`pt`] converts against: the figure's full width, whatever panel is drawn.
pub fn set_figure_width(width_px: u32) {
    FIGURE_WIDTH_PX.with(|w| w.set(width_px));
}

/// plotters' font size is the line height, 1.24 em (its SVG backend writes
/// `font-size = size / 1.24`, and its bitmap text scales the same way).
const PLOTTERS_SIZE_PER_EM: f64 = 1.24;

/// A font size of `points` (em) at the printed width, as the size plotters takes for the
/// figure being drawn (rounded up, so the printed size is never below `points`).
pub fn pt(points: f64) -> u32 {
    (points * PLOTTERS_SIZE_PER_EM * px_per_pt(FIGURE_WIDTH_PX.with(|w| w.get()))).ceil() as u32
}

/// Font sizes in points: tick labels and legends at the minimum, axis titles and captions a
/// little larger.
pub const TICK_PT: f64 = MIN_FONT_PT;
pub const LEGEND_PT: f64 = MIN_FONT_PT;
pub const AXIS_PT: f64 = 10.0;
pub const CAPTION_PT: f64 = 10.0;

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
    set_figure_width(size.0);
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
            // plotters has no PDF backend: refused by name rather than PNG bytes in a .pdf.
            "pdf" => Err(anyhow!(
                "{}: PDF is not supported (plotters has no PDF backend): the supported plot formats are .png and \
                 .svg; write .svg and convert it (e.g. rsvg-convert -f pdf)",
                path.display()
            )),
            _ => Err(anyhow!(
                "{}: cannot tell the image format from the extension '{ext}': the supported plot formats are .png \
                 and .svg",
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
            set_figure_width(size.0);
            atomic(path, ".svg", |tmp| write_svg(tmp, size, svg))
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
    set_figure_width(size.0);
    atomic(&s, ".svg", |tmp| write_svg(tmp, size, svg))?;
    Ok(vec![p, s])
}

/// Draw an SVG of `size` (white background) and write it to `tmp`, every write error kept:
/// the picture is drawn into memory and written here, because plotters' own file target
/// writes through a buffer whose error at the final flush is dropped (on a full disk an SVG
/// under 8 KB became an empty file, with exit 0).
fn write_svg(
    tmp: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> Result<()>,
) -> Result<()> {
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, size).into_drawing_area();
        root.fill(&WHITE).map_err(pe)?;
        draw(&root)?;
        root.present().map_err(pe)?;
    }
    std::fs::write(tmp, text).with_context(|| format!("cannot write {}", tmp.display()))
}

/// The series colours, decided once: Okabe & Ito's colour-blind-safe palette (2008), the
/// members with a contrast of at least 3 against white (its orange, sky blue and yellow are
/// too light for lines on white), black last.
pub const BLUE_OI: RGBColor = RGBColor(0x00, 0x72, 0xB2);
pub const VERMILLION: RGBColor = RGBColor(0xD5, 0x5E, 0x00);
pub const BLUISH_GREEN: RGBColor = RGBColor(0x00, 0x9E, 0x73);
pub const REDDISH_PURPLE: RGBColor = RGBColor(0xCC, 0x79, 0xA7);
pub const PALETTE: [RGBColor; 5] = [BLUE_OI, VERMILLION, BLUISH_GREEN, REDDISH_PURPLE, BLACK];

/// The `k`-th series colour (cycling through [`PALETTE`]).
pub fn series_colour(k: usize) -> RGBColor {
    PALETTE[k % PALETTE.len()]
}

/// A power of ten as `10⁻⁴`, `10³` (other values as [`tick`]).
pub fn power_tick(v: &f64) -> String {
    let k = v.abs().log10().round();
    if *v <= 0.0 || (v.log10() - k).abs() > 1e-9 {
        return tick(v);
    }
    const SUP: [char; 10] = ['⁰', '¹', '²', '³', '⁴', '⁵', '⁶', '⁷', '⁸', '⁹'];
    let digits: String =
        (k.abs() as u32).to_string().chars().map(|c| SUP[c.to_digit(10).unwrap_or(0) as usize]).collect();
    format!("10{}{digits}", if k < 0.0 { "⁻" } else { "" })
}

/// The label format of a log axis over `a..b`: [`tick`] when every decade reads plainly
/// (0.001 to 10000), else [`power_tick`] for all, so that one axis never mixes `10000` and `1e5`.
pub fn log_labels(a: f64, b: f64) -> &'static dyn Fn(&f64) -> String {
    if decades(a, b).iter().all(|d| (1e-3..1e5).contains(d)) {
        &tick
    } else {
        &power_tick
    }
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
    /// Caption font size (points at the printed width, >= [`MIN_FONT_PT`]).
    pub caption_pt: f64,
    pub x_desc: &'s str,
    pub y_desc: &'s str,
    /// Grid lines (off for maps, where they would hide the vectors).
    pub grid: bool,
    /// Number of x ticks (plotters chooses when `None`).
    pub x_labels: Option<usize>,
    /// x tick labels (default [`tick`]).
    pub x_fmt: Option<&'s dyn Fn(&f64) -> String>,
    /// y tick labels (default [`tick`]).
    pub y_fmt: Option<&'s dyn Fn(&f64) -> String>,
}

/// Room right of the plotting area for half of the last x tick label (points): half of a
/// five-character label ("10000", 0.6 em a character) at the tick font, and a margin.
const RIGHT_PAD_PT: f64 = 0.5 * 5.0 * 0.6 * TICK_PT + 3.0;

impl<'s> Axes<'s> {
    pub fn new(caption: impl Into<String>, x_desc: &'s str, y_desc: &'s str) -> Self {
        Axes {
            caption: caption.into(),
            caption_pt: CAPTION_PT,
            x_desc,
            y_desc,
            grid: true,
            x_labels: None,
            x_fmt: None,
            y_fmt: None,
        }
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
    /// Log axes over `x` and `y` (`None`: linear) labelled in one notation each ([`log_labels`]).
    pub fn log_labels(mut self, x: Option<(f64, f64)>, y: Option<(f64, f64)>) -> Self {
        self.x_fmt = x.map(|(a, b)| log_labels(a, b)).or(self.x_fmt);
        self.y_fmt = y.map(|(a, b)| log_labels(a, b));
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
    // Label areas sized from the fonts: a tick label and the axis title below x; up to seven
    // characters of tick label and the rotated title left of y.
    let mut c = ChartBuilder::on(area)
        .caption(&ax.caption, (FONT, pt(ax.caption_pt.max(MIN_FONT_PT))))
        .margin(pt(3.0))
        .margin_right(pt(RIGHT_PAD_PT))
        .x_label_area_size(pt((1.3 * (TICK_PT + AXIS_PT) + 6.0) / PLOTTERS_SIZE_PER_EM))
        .y_label_area_size(pt((0.6 * 6.0 * TICK_PT + 1.3 * AXIS_PT + 6.0) / PLOTTERS_SIZE_PER_EM))
        .build_cartesian_2d(x, y)
        .map_err(pe)?;
    let xf = ax.x_fmt.unwrap_or(&tick);
    // As many ticks as fit without touching at this font (f = 1.24 em): a y label per 1.6
    // lines of text, an x label per about five characters.
    let (w, h) = c.plotting_area().dim_in_pixel();
    let f = pt(TICK_PT) as f64;
    // At least five asked of y: plotters picks round steps up to that many, and a short panel
    // asked for three may get two.
    let (nx, ny) = (((w as f64 / (2.5 * f)) as usize).clamp(3, 10), ((h as f64 / (2.0 * f)) as usize).clamp(5, 10));
    let mut m = c.configure_mesh();
    m.x_labels(nx).y_labels(ny);
    m.x_desc(ax.x_desc)
        .y_desc(ax.y_desc)
        .label_style((FONT, pt(TICK_PT)))
        .axis_desc_style((FONT, pt(AXIS_PT)))
        .x_label_formatter(xf)
        .y_label_formatter(ax.y_fmt.unwrap_or(&tick));
    if !ax.grid {
        m.disable_mesh();
    }
    if let Some(n) = ax.x_labels {
        m.x_labels(n);
    }
    m.draw().map_err(pe)?;
    Ok(c)
}

/// Height in pixels of a legend box of `entries` lines at [`LEGEND_PT`] (plotters' size `f`:
/// a line is about 1.1 f, the box's padding about f), as [`quiet_corner`] estimates it.
fn legend_height_px(entries: usize) -> f64 {
    let f = pt(LEGEND_PT) as f64;
    f * (1.1 * entries as f64 + 1.0)
}

/// A [`chart`] whose y range starts at `y.start` and leaves, above `y.end` (the data's top),
/// room for a legend of `entries` lines in an upper corner: the plotting area is measured on
/// a first drawing, the area cleared, and the chart drawn again with the top raised so that the
/// data stay below the legend box.
pub fn chart_with_legend_room<'a, DB, X>(
    area: &'a DrawingArea<DB, Shift>,
    ax: &Axes,
    x: X,
    y: std::ops::Range<f64>,
    entries: usize,
) -> Result<Chart<'a, DB, X::CoordDescType, RangedCoordf64>>
where
    DB: DrawingBackend + 'a,
    X: AsRangedCoord<Value = f64> + Clone,
    X::CoordDescType: ValueFormatter<f64>,
{
    chart_with_legend_room_by(area, ax, || x.clone(), y, entries)
}

/// [`chart_with_legend_room`] for an x axis built by `x` (one that cannot be cloned, such as
/// a [`log_axis`]).
pub fn chart_with_legend_room_by<'a, DB, X>(
    area: &'a DrawingArea<DB, Shift>,
    ax: &Axes,
    x: impl Fn() -> X,
    y: std::ops::Range<f64>,
    entries: usize,
) -> Result<Chart<'a, DB, X::CoordDescType, RangedCoordf64>>
where
    DB: DrawingBackend + 'a,
    X: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
{
    let (_, h) = chart(area, ax, x(), y.clone())?.plotting_area().dim_in_pixel();
    area.fill(&WHITE).map_err(pe)?;
    let h = h as f64;
    // The box, a gap of half a line below it, and at least a third of the height for the data.
    let free = (h - legend_height_px(entries) - 0.5 * pt(LEGEND_PT) as f64).max(h / 3.0);
    let top = y.start + (y.end - y.start) * h / free;
    chart(area, ax, x(), y.start..top)
}

/// The key points of a log axis over `[a, b]` (a > 0): its [`decades`], with 2x and 5x
/// between them when fewer than three decades fall inside (so that an axis carries at least
/// three labelled ticks).
pub fn log_keys(a: f64, b: f64) -> Vec<f64> {
    let d = decades(a, b);
    let (lo, hi) = (a.min(b), a.max(b));
    if d.len() >= 3 || !(lo > 0.0) {
        return d;
    }
    let k0 = lo.log10().floor() as i32;
    let k1 = hi.log10().ceil() as i32;
    let inside = |v: &f64| *v >= lo * (1.0 - 1e-9) && *v <= hi * (1.0 + 1e-9);
    let mut keys: Vec<f64> =
        (k0..=k1).flat_map(|k| [1.0, 2.0, 5.0].map(|m| m * 10f64.powi(k))).filter(inside).collect();
    if keys.len() < 3 {
        keys = vec![lo, (lo * hi).sqrt(), hi];
    }
    keys
}

/// The decades 10^k inside `[a, b]` (a > 0): the key points of a log axis, so that every decade
/// carries a label (plotters' own choice may skip some or label 2x, 5x between them). A range
/// that holds no decade gets its two ends.
pub fn decades(a: f64, b: f64) -> Vec<f64> {
    let (lo, hi) = (a.min(b), a.max(b));
    if !(lo > 0.0 && hi.is_finite()) {
        return vec![];
    }
    // A decade a rounding residue outside the range still belongs to it.
    let (k0, k1) = ((lo.log10() - 1e-9).ceil() as i32, (hi.log10() + 1e-9).floor() as i32);
    if k0 > k1 {
        return vec![lo, hi];
    }
    (k0..=k1).map(|k| 10f64.powi(k)).collect()
}

/// A log axis over `a..b` labelled at every decade ([`log_keys`]: 2x and 5x too when it
/// spans fewer than three).
pub fn log_axis(
    a: f64,
    b: f64,
) -> plotters::coord::combinators::WithKeyPoints<plotters::coord::combinators::LogCoord<f64>> {
    use plotters::coord::combinators::{BindKeyPoints, IntoLogRange};
    (a..b).log_scale().with_key_points(log_keys(a, b))
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

/// The legend of the labelled series, boxed, at `pos` (a corner the data leave free).
pub fn legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    c: &mut ChartContext<'a, DB, CT>,
    pos: SeriesLabelPosition,
) -> Result<()> {
    c.configure_series_labels()
        .position(pos)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, pt(LEGEND_PT)))
        .draw()
        .map_err(pe)
}

/// The corner of the plotting area whose legend box would cover the fewest of `data` (the
/// points and sampled curves drawn, in data coordinates), for a legend of `entries` lines of
/// up to `chars` characters; ties go to the earlier corner of `prefer`. The box size follows
/// the legend's font ([`LEGEND_PT`]; DejaVu Sans averages 0.6 em per character).
pub fn quiet_corner<'a, DB, X, Y>(
    c: &Chart<'a, DB, X, Y>,
    data: &[(f64, f64)],
    entries: usize,
    chars: usize,
    prefer: [SeriesLabelPosition; 4],
) -> SeriesLabelPosition
where
    DB: DrawingBackend + 'a,
    X: plotters::coord::ranged1d::Ranged<ValueType = f64>,
    Y: plotters::coord::ranged1d::Ranged<ValueType = f64>,
{
    use SeriesLabelPosition::*;
    let (xr, yr) = c.plotting_area().get_pixel_range();
    let f = pt(LEGEND_PT) as f64;
    // f is plotters' size, 1.24 em: a character is about 0.5 f wide, a legend line 1.1 f.
    let (w, h) = ((f * (0.5 * chars as f64 + 3.5)) as i32, (f * (1.1 * entries as f64 + 1.0)) as i32);
    let pts: Vec<(i32, i32)> =
        data.iter().filter(|p| p.0.is_finite() && p.1.is_finite()).map(|p| c.backend_coord(p)).collect();
    let cover = |pos: &SeriesLabelPosition| {
        let x0 = match pos {
            UpperLeft | LowerLeft => xr.start,
            _ => xr.end - w,
        };
        let y0 = match pos {
            UpperLeft | UpperRight => yr.start,
            _ => yr.end - h,
        };
        pts.iter().filter(|p| p.0 >= x0 && p.0 <= x0 + w && p.1 >= y0 && p.1 <= y0 + h).count()
    };
    let mut best = 0;
    let mut best_n = usize::MAX;
    for (i, p) in prefer.iter().enumerate() {
        let n = cover(p);
        if n < best_n {
            (best, best_n) = (i, n);
        }
    }
    let [a, b, cc, d] = prefer;
    [a, b, cc, d].into_iter().nth(best).unwrap_or(UpperRight)
}

/// [`legend`] in the [`quiet_corner`] of the data.
pub fn legend_off_data<'a, DB, X, Y>(
    c: &mut Chart<'a, DB, X, Y>,
    data: &[(f64, f64)],
    entries: usize,
    chars: usize,
    prefer: [SeriesLabelPosition; 4],
) -> Result<()>
where
    DB: DrawingBackend + 'a,
    X: plotters::coord::ranged1d::Ranged<ValueType = f64>,
    Y: plotters::coord::ranged1d::Ranged<ValueType = f64>,
{
    let pos = quiet_corner(c, data, entries, chars, prefer);
    legend(c, pos)
}

/// A legend as one row of keys across `area` (a strip below a chart), each drawn by its
/// `key` at the key's left (the text follows), centred: for a chart whose data leave no
/// corner free, so that the axes need not grow past the data to make room.
pub fn key_row<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[(String, &dyn Fn(&DrawingArea<DB, Shift>, BackendCoord) -> Result<()>)],
) -> Result<()> {
    let f = pt(LEGEND_PT) as f64;
    // f is plotters' size, 1.24 em: a character about 0.5 f, a key 2 f with its gap.
    let widths: Vec<f64> = entries.iter().map(|(t, _)| f * (0.5 * t.chars().count() as f64 + 2.0)).collect();
    let (w, h) = area.dim_in_pixel();
    let mut x = 0.5 * (w as f64 - widths.iter().sum::<f64>() - f * (entries.len() as f64 - 1.0)).max(0.0);
    let y = h as i32 / 2;
    let style = TextStyle::from((FONT, pt(LEGEND_PT)).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    for ((text, key), wd) in entries.iter().zip(&widths) {
        key(area, (x as i32, y))?;
        area.draw(&Text::new(text.clone(), ((x + 1.5 * f) as i32, y), style.clone())).map_err(pe)?;
        x += wd + f;
    }
    Ok(())
}

/// The four corners, upper right first (the usual place of a legend).
pub const CORNERS: [SeriesLabelPosition; 4] = [
    SeriesLabelPosition::UpperRight,
    SeriesLabelPosition::UpperLeft,
    SeriesLabelPosition::LowerRight,
    SeriesLabelPosition::LowerLeft,
];

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

/// Width kept right of the map for its colour bar and, above it, the scale vector.
const MAP_SIDE_ROOM: u32 = COLOUR_BAR_ROOM;

/// `(x, y)` ranges about the field's that make one arcmin as long on x as on y in the plotting
/// area `(w, h)` px: the shorter side's range grows, the field stays centred.
fn equal_aspect(
    xr: std::ops::Range<f64>,
    yr: std::ops::Range<f64>,
    (w, h): (u32, u32),
) -> (std::ops::Range<f64>, std::ops::Range<f64>) {
    let (sx, sy) = ((xr.end - xr.start) / w.max(1) as f64, (yr.end - yr.start) / h.max(1) as f64);
    let grow = |r: std::ops::Range<f64>, f: f64| {
        let (c, half) = (0.5 * (r.start + r.end), 0.5 * (r.end - r.start) * f);
        c - half..c + half
    };
    if sx < sy {
        (grow(xr, sy / sx), yr)
    } else {
        (xr, grow(yr, sx / sy))
    }
}

/// A field map's chart on `area` with equal arcmin per pixel on both axes: the frame is
/// measured on a first drawing, the area cleared, and the chart drawn again with
/// [`equal_aspect`] ranges.
fn map_chart<'a, DB: DrawingBackend + 'a>(
    area: &'a DrawingArea<DB, Shift>,
    caption: String,
    xr: std::ops::Range<f64>,
    yr: std::ops::Range<f64>,
) -> Result<(Chart<'a, DB, RangedCoordf64, RangedCoordf64>, std::ops::Range<f64>, std::ops::Range<f64>)> {
    let dims = chart(area, &map_axes(caption.clone()), xr.clone(), yr.clone())?.plotting_area().dim_in_pixel();
    area.fill(&WHITE).map_err(pe)?;
    let (xr, yr) = equal_aspect(xr, yr, dims);
    Ok((chart(area, &map_axes(caption), xr.clone(), yr.clone())?, xr, yr))
}

/// The contours of the map (fig:insmapB): 0.3, 0.6 and 0.9 %.
const CONTOUR_LEVELS: [f64; 3] = [0.003, 0.006, 0.009];

/// fig:insmapB: a colour image of the model's p with its colour bar, white contours of 0.3, 0.6
/// and 0.9 % (marked and labelled on the colour bar), vectors at about 18 bins across (black on a white halo, readable
/// on any colour), the scale vector of 1 % above the colour bar, and the centre as a cross; equal
/// aspect, nothing in a box over the data.
pub fn draw_map<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, d: &CalPlotData) -> Result<()> {
    let radial_centre = d.radial.map(|r| r.centre);
    let cal = d.cal;
    let (xr, yr) = field_ranges(cal);
    let (main, side) = split_right(area, MAP_SIDE_ROOM);
    let caption = format!("{}: instrumental p", d.title);
    let (mut c, xr, _yr) = map_chart(&main, caption, xr, yr)?;
    // The gridded model: its p as a colour image, 0 to the largest value.
    let g = match (&cal.model, &cal.grid) {
        (Model::Map(g), _) => g.clone(),
        _ => cal.gridded(((xr.end - xr.start) / 120.0).max(0.02)),
    };
    let p: Vec<f64> = g.q.iter().zip(&g.u).map(|(q, u)| q.hypot(*u)).collect();
    let top = p.iter().copied().filter(|v| v.is_finite()).fold(0.0, f64::max).max(1e-6);
    let (hx, hy) = (0.5 * g.dx, 0.5 * g.dy);
    c.draw_series((0..g.ny).flat_map(|j| (0..g.nx).map(move |i| (i, j))).filter_map(|(i, j)| {
        let v = p[j * g.nx + i];
        let (x, y) = (g.x0 + i as f64 * g.dx, g.y0 + j as f64 * g.dy);
        v.is_finite()
            .then(|| Rectangle::new([(x - hx, y - hy), (x + hx, y + hy)], ViridisRGB::get_color(v / top).filled()))
    }))
    .map_err(pe)?;
    // Contours of p in white; the colour bar carries the same levels as white lines.
    for level in CONTOUR_LEVELS {
        let segs = contour_segments(&p, g.nx, g.ny, g.x0, g.y0, g.dx, g.dy, level);
        c.draw_series(segs.into_iter().map(|s| PathElement::new(s.to_vec(), WHITE.stroke_width(3)))).map_err(pe)?;
    }
    // Vectors at the bins, about 18 across, the longest 0.9 of their spacing.
    let bins = thin(&cal.bins, &cal.region, 18.0);
    let spacing = (xr.end - xr.start) / 18.0;
    let pmax = bins.iter().map(|b| b.p_phi().0).fold(0.0, f64::max).max(1e-6);
    let scale = 0.9 * spacing / pmax;
    let stick = |b: &&fit::Bin| {
        let (pp, phi) = b.p_phi();
        let (hx, hy) = (0.5 * pp * scale * phi.cos(), 0.5 * pp * scale * phi.sin());
        vec![(b.x - hx, b.y - hy), (b.x + hx, b.y + hy)]
    };
    c.draw_series(bins.iter().map(|b| PathElement::new(stick(b), WHITE.stroke_width(5)))).map_err(pe)?;
    c.draw_series(bins.iter().map(|b| PathElement::new(stick(b), BLACK.stroke_width(2)))).map_err(pe)?;
    // The radial fit's centre (for an imported map: the free-centre refit the profile panel
    // uses), else the calibration's own.
    let cen = radial_centre.unwrap_or_else(|| cal.centre_arcmin());
    c.draw_series(std::iter::once(Cross::new((cen[0], cen[1]), 9, MAGENTA.stroke_width(3)))).map_err(pe)?;
    // The scale vector, in pixels of this map, above the colour bar.
    let px_per_arcmin = c.backend_coord(&(xr.start + 1.0, 0.0)).0 - c.backend_coord(&(xr.start, 0.0)).0;
    let one_pct_px = (0.01 * scale * px_per_arcmin as f64).round() as i32;
    let (_, rows) = c.plotting_area().get_pixel_range();
    // The bar's ticks at the contours' levels (and 0), so that each white mark is labelled.
    let levels: Vec<f64> =
        std::iter::once(0.0).chain(CONTOUR_LEVELS.into_iter().filter(|l| *l < top).map(|l| 100.0 * l)).collect();
    let ticks = if levels.len() >= 3 { Some(levels.as_slice()) } else { None };
    colour_bar(&side, "p (%)", 100.0 * top, (rows.start, rows.end), ticks)?;
    // The contours' levels as white lines across the bar.
    let (bx0, bx1) = (pt(4.0) as i32, pt(10.0) as i32);
    for level in CONTOUR_LEVELS.into_iter().filter(|l| *l < top) {
        let y = rows.end - ((rows.end - rows.start) as f64 * level / top).round() as i32;
        side.draw(&PathElement::new(vec![(bx0, y), (bx1, y)], WHITE.stroke_width(3))).map_err(pe)?;
    }
    // Below the bar, level with the x axis's tick labels: the vector of 1 %, labelled beside it.
    let (x0, y0) = (pt(4.0) as i32, rows.end + pt(7.0) as i32);
    side.draw(&PathElement::new(vec![(x0, y0), (x0 + one_pct_px, y0)], BLACK.stroke_width(3))).map_err(pe)?;
    let beside = TextStyle::from((FONT, pt(LEGEND_PT)).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    side.draw(&Text::new("= 1%", (x0 + one_pct_px + pt(1.5) as i32, y0), beside)).map_err(pe)?;
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
    let ax =
        Axes::new(format!("{}: radial profile", d.title), "r (arcmin from the model centre)", "p along the radius (%)");
    let mut c = chart(&upper, &ax, 0.0..rmax, (lo * 100.0)..(hi * 100.0))?;
    c.draw_series(
        pts.iter()
            .step_by(stride)
            .filter(|p| !p.2)
            .map(|p| Circle::new((p.0, p.1 * 100.0), 2, VERMILLION.mix(0.6).filled())),
    )
    .map_err(pe)?;
    c.draw_series(
        pts.iter()
            .step_by(stride)
            .filter(|p| p.2)
            .map(|p| Circle::new((p.0, p.1 * 100.0), 2, BLUE_OI.mix(0.8).filled())),
    )
    .map_err(pe)?
    .label("bins (orange: not used)")
    .legend(|(x, y)| Circle::new((x + 10, y), 3, BLUE_OI.filled()));
    if let Some(r) = d.radial {
        let curve: Vec<(f64, f64)> =
            (0..=200).map(|k| rmax * k as f64 / 200.0).map(|x| (x, 100.0 * r.p_of_r(x))).collect();
        c.draw_series(LineSeries::new(curve, BLACK.stroke_width(3)))
            .map_err(pe)?
            .label("fit p(r)")
            .legend(line_key(BLACK.stroke_width(3)));
    }
    if let Some(rt) = &d.raytrace {
        c.draw_series(LineSeries::new(rt.iter().map(|(x, p)| (*x, 100.0 * p)), VERMILLION.stroke_width(2)))
            .map_err(pe)?
            .label("ray trace")
            .legend(line_key(VERMILLION.stroke_width(2)));
    }
    let mut data: Vec<(f64, f64)> = pts.iter().step_by(stride).map(|p| (p.0, p.1 * 100.0)).collect();
    if let Some(r) = d.radial {
        data.extend((0..=200).map(|k| rmax * k as f64 / 200.0).map(|x| (x, 100.0 * r.p_of_r(x))));
    }
    if let Some(rt) = &d.raytrace {
        data.extend(rt.iter().map(|(x, p)| (*x, 100.0 * p)));
    }
    legend_off_data(&mut c, &data, 3, 20, CORNERS)?;

    // Lower panel: phi against alpha.
    let Some(t) = d.polar else { return Ok(()) };
    let (plo, phi_hi) = t.phi_deg.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| (l.min(*p), h.max(*p)));
    let (plo, phi_hi) = (plo.min(-190.0), phi_hi.max(190.0));
    let ax = Axes::new(
        format!("slope {:.4} ± {:.4}, intercept {:.1}°", t.slope, t.slope_err, t.intercept_deg),
        "polar angle α (deg)",
        "φ (deg)",
    );
    let mut c = chart(&lower, &ax, -180.0..180.0, plo..phi_hi)?;
    let stride = (t.alpha_deg.len() / 6000).max(1);
    c.draw_series(
        t.alpha_deg
            .iter()
            .zip(&t.phi_deg)
            .step_by(stride)
            .map(|(a, p)| Circle::new((*a, *p), 2, BLUE_OI.mix(0.8).filled())),
    )
    .map_err(pe)?;
    c.draw_series(LineSeries::new([(-180.0, -180.0), (180.0, 180.0)], BLACK.stroke_width(2)))
        .map_err(pe)?
        .label("unit slope")
        .legend(line_key(BLACK.stroke_width(2)));
    for off in [-90.0, 90.0] {
        if (t.intercept_deg - off).abs() < 30.0 {
            c.draw_series(LineSeries::new(
                [(-180.0, off - 180.0), (180.0, off + 180.0)],
                BLACK.mix(0.5).stroke_width(1),
            ))
            .map_err(pe)?
            .label("tangential (±90°)")
            .legend(line_key(BLACK.mix(0.5)));
        }
    }
    let mut data: Vec<(f64, f64)> = t.alpha_deg.iter().zip(&t.phi_deg).step_by(stride).map(|(a, p)| (*a, *p)).collect();
    data.extend((-180..=180).step_by(5).flat_map(|a| {
        let a = a as f64;
        [(a, a), (a, a - 90.0), (a, a + 90.0)]
    }));
    legend_off_data(&mut c, &data, 2, 17, CORNERS)
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
    let caption = format!("{}: residual, 0 to {:.3}%", d.title, top * 100.0);
    let (mut c, xr, _yr) = map_chart(&main, caption, xr, yr)?;
    let (_, rows) = c.plotting_area().get_pixel_range();
    colour_bar(&side, "|residual| (%)", 100.0 * top, (rows.start, rows.end), None)?;
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
    let stick = |b: &&fit::Bin| {
        let (q, u) = radial.qu(b.x, b.y);
        let (dq, du) = (b.q - q, b.u - u);
        let m = dq.hypot(du).min(top);
        let a = 0.5 * du.atan2(dq);
        let (hx, hy) = (0.5 * m * scale * a.cos(), 0.5 * m * scale * a.sin());
        vec![(b.x - hx, b.y - hy), (b.x + hx, b.y + hy)]
    };
    // Black on a white halo, as on the map: readable on every colour of the scale.
    c.draw_series(thinned.iter().map(|b| PathElement::new(stick(b), WHITE.stroke_width(5)))).map_err(pe)?;
    c.draw_series(thinned.iter().map(|b| PathElement::new(stick(b), BLACK.stroke_width(2)))).map_err(pe)?;
    Ok(())
}

/// A map's height (px) beside its 900 px: the plotting area about square.
const MAP_HEIGHT: u32 = 790;

/// Width kept right of a map for its colour bar: the bar, tick labels of up to five
/// characters and the rotated title (at 9 pt on a column-wide figure of about 1000 px).
const COLOUR_BAR_ROOM: u32 = 260;

/// A tick step of 1, 2 or 5 times a power of ten giving about four steps up to `top`.
fn nice_step(top: f64) -> f64 {
    let raw = top / 4.0;
    let mag = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0].into_iter().map(|m| m * mag).find(|s| *s >= raw).unwrap_or(10.0 * mag)
}

/// A viridis colour bar from 0 to `top` on `area` (the strip right of a map), spanning the
/// map's plotting area from pixel row `rows.0` to `rows.1` (the map's own frame, so the two are
/// level), tick labels right of the bar (at `ticks`, else round steps) and `label` rotated
/// beside them. Drawn in pixels: the
/// strip is too narrow for a chart's label areas.
fn colour_bar<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    label: &str,
    top: f64,
    rows: (i32, i32),
    ticks: Option<&[f64]>,
) -> Result<()> {
    let (y0, y1) = rows;
    let (x0, x1) = (pt(4.0) as i32, pt(10.0) as i32);
    let n = 200;
    for i in 0..n {
        let (a, b) = (y1 - (y1 - y0) * i / n, y1 - (y1 - y0) * (i + 1) / n);
        let colour = ViridisRGB::get_color((i as f64 + 0.5) / n as f64);
        area.draw(&Rectangle::new([(x0, b), (x1, a)], colour.filled())).map_err(pe)?;
    }
    area.draw(&Rectangle::new([(x0, y0), (x1, y1)], BLACK.stroke_width(1))).map_err(pe)?;
    let tick_style = TextStyle::from((FONT, pt(TICK_PT)).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    let step = nice_step(top);
    let nice: Vec<f64> = (0..).map(|i| i as f64 * step).take_while(|v| *v <= top * (1.0 + 1e-9)).collect();
    for v in ticks.unwrap_or(&nice) {
        let y = y1 - ((y1 - y0) as f64 * v / top).round() as i32;
        area.draw(&PathElement::new(vec![(x1, y), (x1 + pt(1.5) as i32, y)], BLACK.stroke_width(1))).map_err(pe)?;
        area.draw(&Text::new(tick(v), (x1 + pt(2.5) as i32, y), tick_style.clone())).map_err(pe)?;
    }
    let (w, _) = area.dim_in_pixel();
    let title = TextStyle::from((FONT, pt(AXIS_PT)).into_font())
        .transform(FontTransform::Rotate270)
        .pos(Pos::new(HPos::Center, VPos::Bottom));
    area.draw(&Text::new(label.to_string(), (w as i32 - pt(1.0) as i32, (y0 + y1) / 2), title)).map_err(pe)?;
    Ok(())
}

fn nearest_spacing(res: &[(f64, f64, f64, f64)]) -> f64 {
    // The median distance (the upper middle) to the next bin along x in the same row: enough
    // for a regular grid.
    let mut xs: Vec<f64> = res.iter().map(|r| r.0).collect();
    xs.sort_by(|a, b| a.total_cmp(b));
    xs.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let mut d: Vec<f64> = xs.windows(2).map(|w| w[1] - w[0]).collect();
    if d.is_empty() {
        return 0.1;
    }
    stokes::stats::robust::median(&mut d, stokes::stats::robust::Middle::Upper)
}

/// Draw the three calibration plots into `dir` as `{stem}_map`, `{stem}_profile`,
/// `{stem}_residual` (PNG and SVG, or SVG only when `png` is false: a report's figures);
/// returns the files written.
pub fn calibration_figures(dir: &Path, stem: &str, d: &CalPlotData, png: bool) -> Result<Vec<PathBuf>> {
    let mut out = vec![];
    // The plotting area about square (the label areas take more height than width), so that
    // equal arcmin per pixel adds little to the field's ranges.
    let map_size = (900 + MAP_SIDE_ROOM, MAP_HEIGHT);
    let stem_of = |name: &str| dir.join(format!("{stem}_{name}"));
    out.extend(save_figure(&stem_of("map"), map_size, png, |a| draw_map(a, d), |a| draw_map(a, d))?);
    out.extend(save_figure(&stem_of("profile"), (900, 1100), png, |a| draw_profile(a, d), |a| draw_profile(a, d))?);
    if d.radial.is_some() {
        out.extend(save_figure(
            &stem_of("residual"),
            (900 + COLOUR_BAR_ROOM, MAP_HEIGHT),
            png,
            |a| draw_residual(a, d),
            |a| draw_residual(a, d),
        )?);
    }
    Ok(out)
}

/// `STEM.png` and `STEM.svg` ([`save_png_svg`]), or `STEM.svg` alone when `png` is false.
fn save_figure(
    stem: &Path,
    size: (u32, u32),
    png: bool,
    png_draw: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
    svg_draw: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> Result<()>,
) -> Result<Vec<PathBuf>> {
    if png {
        return save_png_svg(stem, size, png_draw, svg_draw);
    }
    let s = stem.with_extension("svg");
    save_image(&s, size, png_draw, svg_draw)?;
    Ok(vec![s])
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

#[cfg(test)]
mod publication_tests {
    use super::*;

    /// The data's top lies below a legend box of three lines in the upper corners, with half a
    /// line to spare, on a panel as short as the stokes plot's lower one (585 px).
    #[test]
    fn legend_room_keeps_the_data_below_the_legend_box() {
        font();
        set_figure_width(1000);
        let mut buf = vec![0u8; 1000 * 585 * 3];
        let root = BitMapBackend::with_buffer(&mut buf, (1000, 585)).into_drawing_area();
        let ax = Axes::new("caption", "x", "y");
        let c = chart_with_legend_room(&root, &ax, 0.0..360.0, -0.1..0.9, 3).unwrap();
        let (_, rows) = c.plotting_area().get_pixel_range();
        let data_top = c.backend_coord(&(0.0, 0.9)).1;
        let box_bottom = rows.start as f64 + legend_height_px(3);
        assert!(data_top as f64 >= box_bottom + 0.5 * pt(LEGEND_PT) as f64 - 1.0, "{data_top} vs {box_bottom}");
    }

    /// Equal aspect: the same arcmin per pixel on both axes, the shorter range grown about its
    /// centre.
    #[test]
    fn map_ranges_have_equal_scales() {
        let (x, y) = equal_aspect(-3.0..3.0, -3.0..3.0, (600, 400));
        assert!((x.end - x.start) / 600.0 - (y.end - y.start) / 400.0 < 1e-15);
        assert_eq!((y.start, y.end), (-3.0, 3.0));
        assert!((x.start + 4.5).abs() < 1e-12 && (x.end - 4.5).abs() < 1e-12);
    }

    #[test]
    fn decades_inside_the_range() {
        let close =
            |a: &[f64], b: &[f64]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x / y - 1.0).abs() < 1e-12);
        assert!(close(&decades(0.1, 30.0), &[0.1, 1.0, 10.0]));
        assert!(close(&decades(1e-6, 0.2), &[1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 0.1]));
        // Ends that are decades up to rounding are kept; a range with no decade gets its ends.
        assert!(close(&decades(1000.0 * (1.0 + 1e-13), 1e5 * (1.0 - 1e-13)), &[1e3, 1e4, 1e5]));
        assert!(close(&decades(2.0, 8.0), &[2.0, 8.0]));
        assert!(decades(0.0, 1.0).is_empty() && decades(-1.0, 1.0).is_empty());
    }

    #[test]
    fn font_size_scales_with_the_figure_width() {
        // 8.8 cm = 249.45 pt: a 1000 px figure has 4.009 px/pt; 9 pt is 9 x 1.24 x 4.009 =
        // 44.7 -> 45 in plotters' size (its em is size / 1.24).
        set_figure_width(1000);
        assert!((px_per_pt(1000) - 1000.0 / (8.8 / 2.54 * 72.0)).abs() < 1e-12);
        assert_eq!(pt(9.0), 45);
        set_figure_width(500);
        assert_eq!(pt(9.0), 23);
    }

    #[test]
    fn pdf_and_unknown_extensions_are_refused_by_name() {
        let e = ImageFormat::of(Path::new("fig.pdf")).unwrap_err().to_string();
        assert!(e.contains("fig.pdf") && e.contains(".png and .svg") && e.contains("PDF"), "{e}");
        let e = ImageFormat::of(Path::new("fig.jpg")).unwrap_err().to_string();
        assert!(e.contains(".png and .svg"), "{e}");
        assert_eq!(ImageFormat::of(Path::new("a.SVG")).unwrap(), ImageFormat::Svg);
    }
}
