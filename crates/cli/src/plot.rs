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
use plotters::element::{DashedPathElement, MultiLineText};
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
/// An axis labelled at 2x and 5x too ([`log_keys`]) beyond that range reads in exponents
/// (`5e-4`, `1e-3`, `2e-3`), one notation for all its labels.
pub fn log_labels(a: f64, b: f64) -> &'static dyn Fn(&f64) -> String {
    let keys = log_keys(a, b);
    if keys.iter().all(|d| (1e-3..1e5).contains(d)) {
        &tick
    } else if keys.len() == decades(a, b).len() {
        &power_tick
    } else {
        &exponent_tick
    }
}

/// A value as `m e k` with one or two significant digits: `5e-4`, `1e-3`, `2.5e-3`.
pub fn exponent_tick(v: &f64) -> String {
    if *v == 0.0 || !v.is_finite() {
        return tick(v);
    }
    let k = v.abs().log10().floor();
    let m = format!("{:.1}", v / 10f64.powf(k));
    format!("{}e{}", m.trim_end_matches('0').trim_end_matches('.'), k as i32)
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
#[derive(Clone)]
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
    /// Blank pixels below the x axis title (where [`chart_with_legend`] puts a legend that
    /// no corner has room for).
    pub below_px: u32,
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
            below_px: 0,
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
    area: &DrawingArea<DB, Shift>,
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
    let mut c = frame(area, ax, x, y)?;
    mesh(&mut c, ax)?;
    Ok(c)
}

/// The height (px) of the band below a chart's x axis: a tick label and the axis title.
fn x_label_area_px() -> u32 {
    pt((1.3 * (TICK_PT + AXIS_PT) + 6.0) / PLOTTERS_SIZE_PER_EM)
}

/// The width of the band left of a chart's y axis: up to seven characters of tick label and
/// the rotated axis title.
fn y_label_area_px() -> u32 {
    pt((0.6 * 6.0 * TICK_PT + 1.3 * AXIS_PT + 6.0) / PLOTTERS_SIZE_PER_EM)
}

/// A [`chart`]'s coordinates and caption, without its mesh and axes yet.
fn frame<'a, DB, X, Y>(
    area: &DrawingArea<DB, Shift>,
    ax: &Axes,
    x: X,
    y: Y,
) -> Result<Chart<'a, DB, X::CoordDescType, Y::CoordDescType>>
where
    DB: DrawingBackend + 'a,
    X: AsRangedCoord<Value = f64>,
    Y: AsRangedCoord<Value = f64>,
{
    // Label areas sized from the fonts: a tick label and the axis title below x; up to seven
    // characters of tick label and the rotated title left of y.
    ChartBuilder::on(area)
        .caption(&ax.caption, (FONT, pt(ax.caption_pt.max(MIN_FONT_PT))))
        .margin(pt(3.0))
        .margin_right(pt(RIGHT_PAD_PT))
        .margin_bottom(pt(3.0) + ax.below_px)
        .x_label_area_size(x_label_area_px())
        .y_label_area_size(y_label_area_px())
        .build_cartesian_2d(x, y)
        .map_err(pe)
}

/// The mesh, ticks and axis titles of a [`frame`].
fn mesh<DB, X, Y>(c: &mut Chart<'_, DB, X, Y>, ax: &Axes) -> Result<()>
where
    DB: DrawingBackend,
    X: plotters::coord::ranged1d::Ranged<ValueType = f64> + ValueFormatter<f64>,
    Y: plotters::coord::ranged1d::Ranged<ValueType = f64> + ValueFormatter<f64>,
{
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
    m.draw().map_err(pe)
}

/// What a legend entry draws beside its words (plotters' own keys: a 20 px line, a 22 px
/// dashed line, a marker at the key's middle, a 20 x 10 px bar).
#[derive(Clone, Copy)]
pub enum Mark {
    Line(ShapeStyle),
    Dashed(ShapeStyle),
    Circle(ShapeStyle),
    Cross(ShapeStyle),
    Bar(ShapeStyle),
    /// A solid line above a dashed one: a series with its dashed counterpart.
    LineAndDashed(ShapeStyle),
}

/// A legend entry: its words and its mark.
pub struct Key {
    pub label: String,
    pub mark: Mark,
}

/// A [`Key`].
pub fn key(label: impl Into<String>, mark: Mark) -> Key {
    Key { label: label.into(), mark }
}

/// plotters' legend layout, kept: the key column's width and the box's inner margin (px).
const KEY_AREA_PX: i32 = 30;
const KEY_MARGIN_PX: i32 = 10;

/// The legend's words as one block of lines at [`LEGEND_PT`], placed at `at`.
fn legend_text<'k>(
    keys: &'k [Key],
    font: &TextStyle<'k>,
    at: BackendCoord,
) -> MultiLineText<'k, BackendCoord, &'k str> {
    let mut t = MultiLineText::new(at, font.clone());
    for k in keys {
        t.push_line(k.label.as_str());
    }
    t
}

/// The size (px) of the legend box of `keys`, as plotters lays a legend out.
fn legend_size(keys: &[Key]) -> (i32, i32) {
    let font = TextStyle::from((FONT, pt(LEGEND_PT)).into_font());
    let (w, h) = legend_text(keys, &font, (0, 0)).estimate_dimension().unwrap_or((0, 0));
    (w + KEY_AREA_PX + 2 * KEY_MARGIN_PX, h + 2 * KEY_MARGIN_PX)
}

/// The legend of `keys` laid out in rows at most `width` px wide (a band below a chart): each
/// entry's top left relative to the box, and the box's size.
fn legend_rows(keys: &[Key], width: i32) -> (Vec<BackendCoord>, (i32, i32)) {
    let font = (FONT, pt(LEGEND_PT)).into_font();
    let line = pt(LEGEND_PT) as i32;
    let (mut at, mut x, mut y, mut widest) = (vec![], KEY_MARGIN_PX, KEY_MARGIN_PX, 0);
    for k in keys {
        let w = KEY_AREA_PX + font.box_size(&k.label).map_or(0, |b| b.0 as i32) + 2 * KEY_MARGIN_PX;
        if x > KEY_MARGIN_PX && x + w > width {
            (x, y) = (KEY_MARGIN_PX, y + line);
        }
        at.push((x, y));
        x += w;
        widest = widest.max(x);
    }
    (at, (widest, y + line + KEY_MARGIN_PX))
}

/// A legend box at `(x, y)`, `size` px, on `da`: translucent white with a border.
fn draw_box<DB: DrawingBackend>(da: &DrawingArea<DB, Shift>, (x, y): BackendCoord, (w, h): (i32, i32)) -> Result<()> {
    da.draw(&Rectangle::new([(x, y), (x + w, y + h)], WHITE.mix(0.85).filled())).map_err(pe)?;
    da.draw(&Rectangle::new([(x, y), (x + w, y + h)], BLACK)).map_err(pe)
}

/// The legend box of `keys` drawn on `da` with its top left at `(x, y)` (px in `da`): a
/// translucent white box with a border, each entry's mark and words, one entry a line.
fn draw_legend_box<DB: DrawingBackend>(da: &DrawingArea<DB, Shift>, (x, y): BackendCoord, keys: &[Key]) -> Result<()> {
    draw_box(da, (x, y), legend_size(keys))?;
    let font = TextStyle::from((FONT, pt(LEGEND_PT)).into_font());
    let text = legend_text(keys, &font, (x + KEY_AREA_PX + KEY_MARGIN_PX, y + KEY_MARGIN_PX));
    da.draw(&text).map_err(pe)?;
    let lines = text.compute_line_layout().map_err(pe)?;
    for (((_, y0), (_, y1)), k) in lines.into_iter().zip(keys) {
        draw_mark(da, (x + KEY_MARGIN_PX, (y0 + y1) / 2), k.mark)?;
    }
    Ok(())
}

/// The legend of `keys` in rows ([`legend_rows`]) on `da`, its top left at `(x, y)`.
fn draw_legend_rows<DB: DrawingBackend>(da: &DrawingArea<DB, Shift>, (x, y): BackendCoord, keys: &[Key]) -> Result<()> {
    let (at, size) = legend_rows(keys, da.dim_in_pixel().0 as i32 - x);
    draw_box(da, (x, y), size)?;
    let style = TextStyle::from((FONT, pt(LEGEND_PT)).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    let half = pt(LEGEND_PT) as i32 / 2;
    for ((ex, ey), k) in at.into_iter().zip(keys) {
        let (kx, ky) = (x + ex, y + ey + half);
        draw_mark(da, (kx, ky), k.mark)?;
        da.draw(&Text::new(k.label.clone(), (kx + KEY_AREA_PX, ky), style.clone())).map_err(pe)?;
    }
    Ok(())
}

/// A legend entry's mark with its left end at `(kx, ky)`.
fn draw_mark<DB: DrawingBackend>(da: &DrawingArea<DB, Shift>, (kx, ky): BackendCoord, mark: Mark) -> Result<()> {
    {
        let drawn = match mark {
            Mark::Line(s) => da.draw(&PathElement::new([(kx, ky), (kx + 20, ky)], s)),
            Mark::Dashed(s) => da.draw(&DashedPathElement::new(vec![(kx, ky), (kx + 22, ky)], 6, 2, s)),
            Mark::Circle(s) => da.draw(&Circle::new((kx + 10, ky), 4, s)),
            Mark::Cross(s) => da.draw(&Cross::new((kx + 10, ky), 5, s)),
            Mark::Bar(s) => da.draw(&Rectangle::new([(kx, ky - 5), (kx + 20, ky + 5)], s)),
            Mark::LineAndDashed(s) => da
                .draw(&PathElement::new([(kx, ky - 3), (kx + 22, ky - 3)], s))
                .and_then(|_| da.draw(&DashedPathElement::new(vec![(kx, ky + 3), (kx + 22, ky + 3)], 6, 2, s))),
        };
        drawn.map_err(pe)
    }
}

/// Where a chart's legend goes, decided once for every figure ([`chart_with_legend`]): in a
/// corner of the plotting area where its box covers none of the data (no marker, and no line
/// between a curve's points), else in a band below the chart, outside the axes. No axis is
/// stretched past the data to make room for a legend.
pub enum LegendPlace<DB: DrawingBackend> {
    /// The box's top left in the plotting area (px).
    Corner(BackendCoord),
    /// The band below the chart, and the plotting area's left edge in it (px).
    Below(DrawingArea<DB, Shift>, i32),
}

/// A [`chart`] with its legend's place: `marks` are what the legend must not cover, in data
/// coordinates (each a curve through its points in order, or a single point), and `keys` the
/// legend's entries. The frame is measured first; when no corner of its plotting area is free
/// (tried in [`CORNERS`] order, 5 px in from the axes as plotters puts a legend), the area is
/// cleared and the chart drawn over less height, leaving a band below it for the legend. Draw
/// the legend with [`draw_legend`] after the series.
pub fn chart_with_legend<'a, DB, X, Y>(
    area: &DrawingArea<DB, Shift>,
    ax: &Axes,
    x: impl Fn() -> X,
    y: impl Fn() -> Y,
    marks: &[Vec<(f64, f64)>],
    keys: &[Key],
) -> Result<(Chart<'a, DB, X::CoordDescType, Y::CoordDescType>, LegendPlace<DB>)>
where
    DB: DrawingBackend + 'a,
    X: AsRangedCoord<Value = f64>,
    Y: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let mut c = frame(area, ax, x(), y())?;
    if let Some(at) = free_corner(&c, marks, legend_size(keys)) {
        mesh(&mut c, ax)?;
        return Ok((c, LegendPlace::Corner(at)));
    }
    area.fill(&WHITE).map_err(pe)?;
    // Left-aligned with the plotting area (the chart's margin and y label band in), as wide as
    // the area leaves.
    let left = (pt(3.0) + y_label_area_px()) as i32;
    let band = legend_rows(keys, area.dim_in_pixel().0 as i32 - left).1 .1 as u32 + pt(LEGEND_PT) / 2;
    let (upper, below) = area.split_vertically(area.dim_in_pixel().1.saturating_sub(band));
    let c = chart(&upper, ax, x(), y())?;
    Ok((c, LegendPlace::Below(below, left)))
}

/// The legend of `keys` at `place` ([`chart_with_legend`]).
pub fn draw_legend<'a, DB, X, Y>(c: &Chart<'a, DB, X, Y>, place: LegendPlace<DB>, keys: &[Key]) -> Result<()>
where
    DB: DrawingBackend + 'a,
    X: plotters::coord::ranged1d::Ranged<ValueType = f64>,
    Y: plotters::coord::ranged1d::Ranged<ValueType = f64>,
{
    match place {
        LegendPlace::Corner(at) => draw_legend_box(&c.plotting_area().strip_coord_spec(), at, keys),
        LegendPlace::Below(band, left) => draw_legend_rows(&band, (left, pt(LEGEND_PT) as i32 / 4), keys),
    }
}

/// The first corner of [`CORNERS`] whose legend box of `size` covers none of `marks` (points,
/// and the segments between a curve's consecutive points): the box's top left in the plotting
/// area, or None.
fn free_corner<'a, DB, X, Y>(
    c: &Chart<'a, DB, X, Y>,
    marks: &[Vec<(f64, f64)>],
    size: (i32, i32),
) -> Option<BackendCoord>
where
    DB: DrawingBackend + 'a,
    X: plotters::coord::ranged1d::Ranged<ValueType = f64>,
    Y: plotters::coord::ranged1d::Ranged<ValueType = f64>,
{
    let (x0, y0) = c.plotting_area().get_base_pixel();
    let curves: Vec<Vec<(f64, f64)>> = marks
        .iter()
        .map(|m| {
            let finite = m.iter().filter(|p| p.0.is_finite() && p.1.is_finite());
            finite.map(|p| c.backend_coord(p)).map(|(x, y)| ((x - x0) as f64, (y - y0) as f64)).collect()
        })
        .collect();
    let (w, h) = c.plotting_area().dim_in_pixel();
    let (bw, bh) = size;
    CORNERS.into_iter().find_map(|pos| {
        use SeriesLabelPosition::*;
        let x = if matches!(pos, UpperLeft | LowerLeft) { 5 } else { w as i32 - bw - 5 };
        let y = if matches!(pos, UpperLeft | UpperRight) { 5 } else { h as i32 - bh - 5 };
        // A marker's size beyond its centre: a few pixels of slack around the box.
        let pad = 0.2 * pt(LEGEND_PT) as f64;
        let b = (x as f64 - pad, y as f64 - pad, (x + bw) as f64 + pad, (y + bh) as f64 + pad);
        let covered = curves.iter().any(|k| match k[..] {
            [p] => inside(p, b),
            _ => k.windows(2).any(|s| crosses(s[0], s[1], b)),
        });
        (!covered).then_some((x, y))
    })
}

/// Whether `p` lies in the box `(x0, y0, x1, y1)`.
fn inside(p: (f64, f64), b: (f64, f64, f64, f64)) -> bool {
    p.0 >= b.0 && p.0 <= b.2 && p.1 >= b.1 && p.1 <= b.3
}

/// Whether the segment `p`-`q` meets the box `b`: an end inside it, or the segment crossing
/// one of its four edges.
fn crosses(p: (f64, f64), q: (f64, f64), b: (f64, f64, f64, f64)) -> bool {
    // The signed area of (a, b, c): which side of a-b the point c is on.
    let side = |a: (f64, f64), b: (f64, f64), c: (f64, f64)| (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0);
    let cut =
        |a: (f64, f64), b: (f64, f64)| side(p, q, a) * side(p, q, b) <= 0.0 && side(a, b, p) * side(a, b, q) <= 0.0;
    let (c00, c10, c11, c01) = ((b.0, b.1), (b.2, b.1), (b.2, b.3), (b.0, b.3));
    inside(p, b) || inside(q, b) || cut(c00, c10) || cut(c10, c11) || cut(c11, c01) || cut(c01, c00)
}

/// The data range `lo..hi` with 2 % of its span added on each side (an axis that ends just
/// past its data; a single value gets 2 % of its size, or 1e-9): what every linear axis of
/// data spans.
pub fn data_range(lo: f64, hi: f64) -> std::ops::Range<f64> {
    let span = hi - lo;
    let pad = if span > 0.0 { 0.02 * span } else { (0.02 * lo.abs().max(hi.abs())).max(1e-9) };
    lo - pad..hi + pad
}

/// [`data_range`] for a log axis over positive data: 2 % of the span in decades added on each
/// side, at least a factor 1.02.
pub fn log_data_range(lo: f64, hi: f64) -> (f64, f64) {
    let k = 10f64.powf(0.02 * (hi / lo).log10()).max(1.02);
    (lo / k, hi * k)
}

/// [`data_range`] of the y values of `marks` (0..1 when there are none).
pub fn marks_y_range(marks: &[Vec<(f64, f64)>]) -> std::ops::Range<f64> {
    let (lo, hi) = extent(marks.iter().flatten().map(|p| p.1)).unwrap_or((0.0, 1.0));
    data_range(lo, hi)
}

/// The smallest and largest finite value of `v` (None when there is none).
pub fn extent(v: impl IntoIterator<Item = f64>) -> Option<(f64, f64)> {
    v.into_iter().filter(|x| x.is_finite()).fold(None, |acc, x| match acc {
        None => Some((x, x)),
        Some((a, b)) => Some((a.min(x), b.max(x))),
    })
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
    let with = |ms: &[f64]| -> Vec<f64> {
        (k0..=k1).flat_map(|k| ms.iter().map(move |m| m * 10f64.powi(k))).filter(inside).collect()
    };
    // 1x and 5x when they give three labels reaching both ends (fewer to crowd a short
    // axis), else 2x too.
    let mut keys = with(&[1.0, 5.0]);
    if keys.len() < 3 || !reaches_ends(&keys, lo, hi) {
        keys = with(&[1.0, 2.0, 5.0]);
    }
    if keys.len() < 3 {
        keys = vec![lo, (lo * hi).sqrt(), hi];
    }
    keys
}

/// Whether the labels `keys` (ascending, inside `[lo, hi]`) leave at most a third of the log
/// axis `lo..hi` unlabelled at either end (a label near each end, so that no end of the axis
/// is read by eye from a grid line alone).
fn reaches_ends(keys: &[f64], lo: f64, hi: f64) -> bool {
    let third = (hi / lo).log10() / 3.0;
    match (keys.first(), keys.last()) {
        (Some(a), Some(b)) => (a / lo).log10() <= third && (hi / b).log10() <= third,
        _ => false,
    }
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
    let ticks = bar_ticks(100.0 * top);
    colour_bar(&side, "p (%)", 100.0 * top, (rows.start, rows.end), Some(&ticks))?;
    // The contours' levels as white lines across the bar.
    let (bx0, bx1) = (pt(4.0) as i32, pt(10.0) as i32);
    for level in CONTOUR_LEVELS.into_iter().filter(|l| *l < top) {
        let y = rows.end - ((rows.end - rows.start) as f64 * level / top).round() as i32;
        side.draw(&PathElement::new(vec![(bx0, y), (bx1, y)], WHITE.stroke_width(3))).map_err(pe)?;
    }
    // Below the bar, level with the x axis's tick labels: the scale vector (1 %, or the
    // largest of 0.5, 0.2, 0.1 % that fits the strip beside its words), labelled beside it.
    let (x0, y0) = (pt(4.0) as i32, rows.end + pt(7.0) as i32);
    let room = side.dim_in_pixel().0 as i32 - x0 - pt(1.5) as i32;
    let font = (FONT, pt(LEGEND_PT)).into_font();
    let (len, words) = [1.0, 0.5, 0.2, 0.1]
        .into_iter()
        .map(|pct| ((pct * one_pct_px as f64).round() as i32, format!("= {}%", tick(&pct))))
        .find(|(len, w)| len + font.box_size(w).map_or(0, |b| b.0 as i32) <= room)
        .unwrap_or_else(|| ((0.1 * one_pct_px as f64).round() as i32, "= 0.1%".into()));
    side.draw(&PathElement::new(vec![(x0, y0), (x0 + len, y0)], BLACK.stroke_width(3))).map_err(pe)?;
    let beside = TextStyle::from(font).pos(Pos::new(HPos::Left, VPos::Center));
    side.draw(&Text::new(words, (x0 + len + pt(1.5) as i32, y0), beside)).map_err(pe)?;
    Ok(())
}

/// The colour bar's tick values (%) from 0 to `top` (%): 0 and every contour level inside the
/// bar (each white mark labelled), and when that makes fewer than three, the bar's round steps
/// ([`nice_step`]) that stand at least a seventh of the bar from those.
fn bar_ticks(top: f64) -> Vec<f64> {
    let mut ticks: Vec<f64> =
        std::iter::once(0.0).chain(CONTOUR_LEVELS.iter().map(|l| 100.0 * l).filter(|l| *l < top)).collect();
    if ticks.len() < 3 {
        let step = nice_step(top);
        let steps = (1..).map(|i| i as f64 * step).take_while(|v| *v <= top * (1.0 + 1e-9));
        let apart: Vec<f64> = steps.filter(|v| ticks.iter().all(|t| (v - t).abs() >= top / 7.0)).collect();
        ticks.extend(apart);
        ticks.sort_by(f64::total_cmp);
    }
    ticks
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
            (dx.hypot(dy), b.qu.q * (2.0 * a).cos() + b.qu.u * (2.0 * a).sin(), b.used)
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
    let mut marks: Vec<Vec<(f64, f64)>> = pts.iter().step_by(stride).map(|p| vec![(p.0, p.1 * 100.0)]).collect();
    if let Some(r) = d.radial {
        marks.push((0..=200).map(|k| rmax * k as f64 / 200.0).map(|x| (x, 100.0 * r.p_of_r(x))).collect());
    }
    if let Some(rt) = &d.raytrace {
        marks.push(rt.iter().map(|(x, p)| (*x, 100.0 * p)).collect());
    }
    let mut keys = vec![key("bins (orange: not used)", Mark::Circle(BLUE_OI.filled()))];
    if d.radial.is_some() {
        keys.push(key("fit p(r)", Mark::Line(BLACK.stroke_width(3))));
    }
    if d.raytrace.is_some() {
        keys.push(key("ray trace", Mark::Line(VERMILLION.stroke_width(2))));
    }
    let (mut c, place) = chart_with_legend(&upper, &ax, || 0.0..rmax, || (lo * 100.0)..(hi * 100.0), &marks, &keys)?;
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
    .map_err(pe)?;
    if let Some(r) = d.radial {
        let curve: Vec<(f64, f64)> =
            (0..=200).map(|k| rmax * k as f64 / 200.0).map(|x| (x, 100.0 * r.p_of_r(x))).collect();
        c.draw_series(LineSeries::new(curve, BLACK.stroke_width(3))).map_err(pe)?;
    }
    if let Some(rt) = &d.raytrace {
        c.draw_series(LineSeries::new(rt.iter().map(|(x, p)| (*x, 100.0 * p)), VERMILLION.stroke_width(2)))
            .map_err(pe)?;
    }
    draw_legend(&c, place, &keys)?;

    // Lower panel: phi against alpha.
    let Some(t) = d.polar else { return Ok(()) };
    let (plo, phi_hi) = t.phi_deg.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| (l.min(*p), h.max(*p)));
    let (plo, phi_hi) = (plo.min(-190.0), phi_hi.max(190.0));
    let ax = Axes::new(
        format!("slope {:.4} ± {:.4}, intercept {:.1}°", t.slope, t.slope_err, t.intercept_deg),
        "polar angle α (deg)",
        "φ (deg)",
    );
    let stride = (t.alpha_deg.len() / 6000).max(1);
    let tangential: Vec<f64> = [-90.0, 90.0].into_iter().filter(|off| (t.intercept_deg - off).abs() < 30.0).collect();
    let mut marks: Vec<Vec<(f64, f64)>> =
        t.alpha_deg.iter().zip(&t.phi_deg).step_by(stride).map(|(a, p)| vec![(*a, *p)]).collect();
    marks.push(vec![(-180.0, -180.0), (180.0, 180.0)]);
    marks.extend(tangential.iter().map(|off| vec![(-180.0, off - 180.0), (180.0, off + 180.0)]));
    let mut keys = vec![key("unit slope", Mark::Line(BLACK.stroke_width(2)))];
    if !tangential.is_empty() {
        keys.push(key("tangential (±90°)", Mark::Line(BLACK.mix(0.5).into())));
    }
    let (mut c, place) = chart_with_legend(&lower, &ax, || -180.0..180.0, || plo..phi_hi, &marks, &keys)?;
    c.draw_series(
        t.alpha_deg
            .iter()
            .zip(&t.phi_deg)
            .step_by(stride)
            .map(|(a, p)| Circle::new((*a, *p), 2, BLUE_OI.mix(0.8).filled())),
    )
    .map_err(pe)?;
    c.draw_series(LineSeries::new([(-180.0, -180.0), (180.0, 180.0)], BLACK.stroke_width(2))).map_err(pe)?;
    for off in tangential {
        c.draw_series(LineSeries::new([(-180.0, off - 180.0), (180.0, off + 180.0)], BLACK.mix(0.5).stroke_width(1)))
            .map_err(pe)?;
    }
    draw_legend(&c, place, &keys)
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
            (b.x, b.y, b.qu.q - q, b.qu.u - u)
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
        let (dq, du) = (b.qu.q - q, b.qu.u - u);
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

    /// A legend goes in the first corner whose box no line crosses, and in a band below the
    /// chart, outside the axes, when every corner is crossed; the axes keep their ranges.
    #[test]
    fn a_legend_takes_a_free_corner_or_goes_below_the_chart() {
        font();
        set_figure_width(1000);
        let mut buf = vec![0u8; 1000 * 585 * 3];
        let root = BitMapBackend::with_buffer(&mut buf, (1000, 585)).into_drawing_area();
        let ax = Axes::new("caption", "x", "y");
        let (x, y) = (|| 0.0..1.0, || 0.0..1.0);
        let keys = [key("one", Mark::Line(BLACK.into())), key("two", Mark::Circle(BLACK.into()))];
        // A diagonal from the lower left to the upper right crosses those two corners' boxes,
        // though neither of its two points lies in them: the upper left is taken.
        let diagonal = vec![vec![(0.0, 0.0), (1.0, 1.0)]];
        let (c, place) = chart_with_legend(&root, &ax, x, y, &diagonal, &keys).unwrap();
        assert!(matches!(place, LegendPlace::Corner((5, 5))));
        let full_height = c.plotting_area().dim_in_pixel().1;
        // Both diagonals: no corner is free.
        let crossed = vec![vec![(0.0, 0.0), (1.0, 1.0)], vec![(0.0, 1.0), (1.0, 0.0)]];
        let (c, place) = chart_with_legend(&root, &ax, x, y, &crossed, &keys).unwrap();
        let LegendPlace::Below(band, _) = place else { panic!("no band below") };
        // The chart gave up the band's height, the band lies below the chart's x axis title,
        // and the ranges are the caller's.
        let h = c.plotting_area().dim_in_pixel().1;
        assert_eq!(full_height - h, band.dim_in_pixel().1);
        // One row: both entries fit across.
        assert_eq!(band.dim_in_pixel().1, (pt(LEGEND_PT) as i32 + 2 * KEY_MARGIN_PX) as u32 + pt(LEGEND_PT) / 2);
        assert!(band.get_base_pixel().1 >= c.plotting_area().get_base_pixel().1 + h as i32);
        assert_eq!(c.x_range(), 0.0..1.0);
    }

    /// The segment test against its definition: ends inside, a crossing with no end inside,
    /// and segments that pass by, along and beyond the box.
    #[test]
    fn a_segment_meets_a_box_where_it_crosses_it() {
        let b = (0.0, 0.0, 10.0, 10.0);
        assert!(crosses((5.0, 5.0), (20.0, 20.0), b));
        assert!(crosses((-5.0, 5.0), (15.0, 6.0), b));
        assert!(!crosses((-5.0, 12.0), (15.0, 11.0), b));
        assert!(!crosses((11.0, -5.0), (30.0, 20.0), b));
        assert!(crosses((-5.0, -5.0), (15.0, 15.0), b));
    }

    /// Axes end 2 % past their data: of the span, or of the value when there is one.
    #[test]
    fn data_ranges_end_just_past_the_data() {
        let r = data_range(1.0, 3.0);
        assert!((r.start - 0.96).abs() < 1e-12 && (r.end - 3.04).abs() < 1e-12);
        let r = data_range(5.0, 5.0);
        assert!((r.start - 4.9).abs() < 1e-12 && (r.end - 5.1).abs() < 1e-12);
        let (a, b) = log_data_range(1e-3, 1e2);
        assert!((a.log10() + 3.1).abs() < 1e-12 && (b.log10() - 2.1).abs() < 1e-12);
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
    fn colour_bar_ticks_label_every_contour_mark() {
        // 0.5 %: the 0.3 % contour's mark, with the round steps 0.2 and 0.4 (0.1 from it, a
        // fifth of the bar); 1.2 %: 0 and the three contours.
        let close = |a: &[f64], b: &[f64]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12);
        assert!(close(&bar_ticks(0.5), &[0.0, 0.2, 0.3, 0.4]), "{:?}", bar_ticks(0.5));
        assert!(close(&bar_ticks(1.2), &[0.0, 0.3, 0.6, 0.9]), "{:?}", bar_ticks(1.2));
        // 0.25 %: no contour inside; the round steps of 0.1.
        assert!(close(&bar_ticks(0.25), &[0.0, 0.1, 0.2]), "{:?}", bar_ticks(0.25));
    }

    #[test]
    fn log_labels_reach_both_ends() {
        let close =
            |a: &[f64], b: &[f64]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x / y - 1.0).abs() < 1e-12);
        // The plan's RMS axis, 0.0098 to 0.36: 1x and 5x alone stop at 0.1, 0.56 decade (a
        // third of its 1.57) below the top; with 2x the last label is 0.2, 0.26 decade below.
        assert!(close(&log_keys(0.0098, 0.36), &[0.01, 0.02, 0.05, 0.1, 0.2]));
        // A short axis whose 1x and 5x reach both ends keeps them.
        assert!(close(&log_keys(0.009, 0.11), &[0.01, 0.05, 0.1]));
        assert!(reaches_ends(&[0.01, 0.05, 0.1], 0.009, 0.11) && !reaches_ends(&[0.01, 0.05, 0.1], 0.0098, 0.36));
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
