//! The page of `instpol report`: `workflow::night::report`'s values printed as one HTML file,
//! its figures (SVG files beside it) named by [`Figures`]. Printing only: every number is
//! read from the report; fractions are shown in percent, labelled.

use skyfield::provenance::Provenance;
use std::fmt::Write;
use workflow::night::report::{NightReport, Report, UnitState};
use workflow::night::trend::Trend;

/// What the report's figures are: the file names under figures/, by what they show.
#[derive(Default)]
pub struct Figures {
    /// Per night, per calibration (in the report's order): its map, profile and residual SVGs.
    pub calibrations: Vec<Vec<Vec<String>>>,
    /// Per night: the standards' pulls, when it measured any.
    pub pulls: Vec<Option<String>>,
    /// The trend's series, when any point was measured.
    pub trend: Option<String>,
}

/// Text escaped for HTML (quick-xml's escape of `&`, `<`, `>`, `"` and `'`).
fn esc(s: &str) -> String {
    quick_xml::escape::escape(s).into_owned()
}

/// A number as written in a JSON output, for a person: four significant digits.
fn num(x: f64) -> String {
    if x == 0.0 || (1e-3..1e5).contains(&x.abs()) {
        let s = format!("{x:.4}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{x:.3e}")
    }
}

/// A fraction in percent, three decimals.
fn pct(x: f64) -> String {
    format!("{:.3}", 100.0 * x)
}

const STYLE: &str = "body{font-family:DejaVu Sans,Verdana,sans-serif;margin:2em auto;padding:0 1.5em;max-width:72em;color:#111;line-height:1.4}\
table{border-collapse:collapse;margin:0.6em 0 1.2em}th,td{border:1px solid #bbb;padding:0.2em 0.5em;text-align:left;vertical-align:top}\
th{background:#eee}td.n{text-align:right;font-variant-numeric:tabular-nums}code{font-size:0.9em}\
.done{color:#064}.bad{color:#a00;font-weight:bold}.other{color:#864}img{max-width:100%;height:auto;border:1px solid #ddd}\
figure{display:inline-block;margin:0.5em;vertical-align:top;width:27em}figcaption{font-size:0.9em}nav a{margin-right:1em}table.nw td{white-space:nowrap}";

/// The whole page.
pub fn page(r: &Report, figs: &Figures, prov: &Provenance) -> String {
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>instpol report</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>instpol report</h1>\n<p>{} night(s); made {} UTC by instpol {}.</p>\n<nav>",
        r.nights.len(),
        esc(&prov.date_utc),
        esc(&prov.version)
    );
    for k in 0..r.nights.len() {
        let _ = write!(h, "<a href=\"#night-{k}\">night {}</a>", k + 1);
    }
    h += "<a href=\"#trend\">trend</a><a href=\"#provenance\">provenance</a></nav>\n";
    for (k, n) in r.nights.iter().enumerate() {
        night(&mut h, k, n, figs);
    }
    trend(&mut h, &r.trend, figs.trend.as_deref());
    provenance(&mut h, prov, &r.trend.product);
    h += "</body>\n</html>\n";
    h
}

fn night(h: &mut String, k: usize, n: &NightReport, figs: &Figures) {
    let _ = write!(
        h,
        "<section id=\"night-{k}\">\n<h2>Night {}: <code>{}</code></h2>\n<p>Instrument <code>{}</code>. Usable files: {}.</p>\n",
        k + 1,
        esc(&n.plan.display().to_string()),
        esc(&n.instrument),
        esc(&n.roles.iter().map(|(r, c)| format!("{c} {r}")).collect::<Vec<_>>().join(", "))
    );
    summary(h, n);
    standards(h, k, n, figs);
    calibrations(h, k, n, figs);
    found(h, n);
    units(h, n);
    h.push_str("</section>\n");
}

/// The night in one line: its sets, what was left out, the units' outcomes, the standards.
fn summary(h: &mut String, n: &NightReport) {
    let count = |f: fn(&UnitState) -> bool| n.units.iter().filter(|u| f(&u.state)).count();
    let left: usize = n.left_out.iter().map(|l| l.files.len()).sum();
    let _ = writeln!(
        h,
        "<p><b>{} set(s)</b>, {left} file(s) left out; <b>{} of {} unit(s) done</b>, {} check(s) not passed, {} not run or failed, {} not recorded; {} standard value(s), {} beyond 3 &sigma;; {} calibration(s).</p>",
        n.sets.len(),
        count(|s| *s == UnitState::Done),
        n.units.len(),
        count(|s| matches!(s, UnitState::CheckFailed(_))),
        count(|s| *s == UnitState::NotRun),
        count(|s| *s == UnitState::NotRecorded),
        n.standards.len(),
        n.standards.iter().filter(|s| s.pull.abs() > 3.0).count(),
        n.calibrations.len()
    );
}

/// The sets found and the files left out.
fn found(h: &mut String, n: &NightReport) {
    h.push_str("<h3>Sets found</h3>\n<table><tr><th>set</th><th>filter</th><th>start (MJD)</th><th>standard</th><th>files</th><th>units</th></tr>\n");
    for s in &n.sets {
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{}</td><td class=\"n\">{}</td><td>{}</td><td class=\"n\">{}</td><td>{}</td></tr>",
            esc(&s.name),
            esc(s.filter.as_deref().unwrap_or("")),
            s.mjd.map_or(String::new(), |m| format!("{m:.5}")),
            esc(s.standard.as_deref().unwrap_or("")),
            s.n_files,
            esc(&s.units.join(", "))
        );
    }
    h.push_str("</table>\n<h3>Left out</h3>\n");
    if n.left_out.is_empty() {
        h.push_str("<p>Nothing.</p>\n");
    } else {
        h.push_str("<table><tr><th>files</th><th>why</th></tr>\n");
        for l in &n.left_out {
            let files = super::night::left_out_files(l);
            let _ = writeln!(h, "<tr><td><code>{}</code></td><td>{}</td></tr>", esc(&files), esc(&l.why));
        }
        h.push_str("</table>\n");
    }
}

fn units(h: &mut String, n: &NightReport) {
    h.push_str("<h3>Units</h3>\n<table><tr><th>unit</th><th>kind</th><th>outcome</th><th>outputs (BLAKE3 as recorded)</th><th>values</th></tr>\n");
    for u in &n.units {
        let (class, state) = match &u.state {
            UnitState::Done => ("done", "done".to_string()),
            UnitState::CheckFailed(why) => ("bad", format!("check failed: {why}")),
            UnitState::NotRecorded => {
                ("other", "outputs present, not recorded (changed since, or made by hand)".into())
            }
            UnitState::NotRun => ("bad", "not run, or failed".into()),
        };
        let outputs: Vec<String> = u
            .outputs
            .iter()
            .map(|(p, hash)| {
                let short =
                    hash.strip_prefix("blake3:").map_or(String::new(), |x| format!(" {}", &x[..x.len().min(12)]));
                let name = p.file_name().map_or_else(|| p.display().to_string(), |f| f.to_string_lossy().into());
                format!("<code title=\"{}\">{}</code>{}", esc(&p.display().to_string()), esc(&name), esc(&short))
            })
            .collect();
        let values: Vec<String> = u.values.iter().map(|(k, v)| format!("{} = {}", esc(k), num(*v))).collect();
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{}</td><td class=\"{class}\">{}</td><td>{}</td><td>{}</td></tr>",
            esc(&u.id),
            esc(&u.kind),
            esc(&state),
            outputs.join("<br>"),
            values.join("<br>")
        );
    }
    h.push_str("</table>\n");
}

fn standards(h: &mut String, k: usize, n: &NightReport, figs: &Figures) {
    h.push_str("<h3>Standards against their catalogued values</h3>\n");
    if n.standards.is_empty() {
        h.push_str("<p>No standard was measured.</p>\n");
        return;
    }
    h.push_str("<p>p: a polarized standard's measured P against the standards list; q, u: an unpolarized standard's against 0; p_corrected: the P a validation corrected against the published one (0 for an unpolarized star). Pull = (measured &minus; catalogued) / &sigma;, both errors combined. p, q and u are measured before any correction: their pulls carry the instrument's own polarization where the star sits.</p>\n");
    h.push_str("<table class=\"nw\"><tr><th>row</th><th>star</th><th>filter</th><th>quantity</th><th>measured (%)</th><th>&sigma; (%)</th><th>catalogued (%)</th><th>&sigma; (%)</th><th>pull</th><th>unit</th></tr>\n");
    for (i, s) in n.standards.iter().enumerate() {
        let class = if s.pull.abs() > 3.0 { " bad" } else { "" };
        let _ = writeln!(
            h,
            "<tr><td class=\"n\">{}</td><td>{}</td><td>{}</td><td>{}</td><td class=\"n\">{}</td><td class=\"n\">{}</td><td class=\"n\">{}</td><td class=\"n\">{}</td><td class=\"n{class}\">{:.2}</td><td title=\"{}\">{}</td></tr>",
            i + 1,
            esc(&s.star),
            esc(&s.filter),
            esc(&s.quantity),
            pct(s.measured),
            pct(s.sigma),
            pct(s.catalogue),
            pct(s.sigma_catalogue),
            s.pull,
            esc(&s.unit),
            esc(&s.kind)
        );
    }
    h.push_str("</table>\n");
    if let Some(Some(f)) = figs.pulls.get(k) {
        let _ = writeln!(h, "<figure><img src=\"figures/{}\" alt=\"pulls of the standards\"><figcaption>The pulls by row; lines at 0, &plusmn;1 and &plusmn;3 &sigma;.</figcaption></figure>", esc(f));
    }
}

fn calibrations(h: &mut String, k: usize, n: &NightReport, figs: &Figures) {
    h.push_str("<h3>Calibration maps</h3>\n");
    if n.calibrations.is_empty() {
        h.push_str("<p>No sky-field calibration.</p>\n");
        return;
    }
    for (i, c) in n.calibrations.iter().enumerate() {
        let edge = c.p_edge.map_or("undefined".into(), |(p, s)| format!("{} &plusmn; {} %", pct(p), pct(s)));
        let _ = writeln!(
            h,
            "<h4>{} ({})</h4>\n<p><code>{}</code>: instrumental P at the field's edge {edge}.</p>",
            esc(&c.unit),
            esc(&c.filter),
            esc(&c.file.display().to_string())
        );
        for f in figs.calibrations.get(k).and_then(|v| v.get(i)).into_iter().flatten() {
            let what =
                ["map", "profile", "residual"].into_iter().find(|w| f.contains(&format!("_{w}."))).unwrap_or("figure");
            let _ = writeln!(
                h,
                "<figure><img src=\"figures/{}\" alt=\"{} {what}\"><figcaption>{what}</figcaption></figure>",
                esc(f),
                esc(&c.unit)
            );
        }
    }
}

fn trend(h: &mut String, t: &Trend, fig: Option<&str>) {
    h.push_str("<section id=\"trend\">\n<h2>Trend</h2>\n");
    if t.points.is_empty() {
        h.push_str("<p>The plans measured no standard and no calibration: no trend.</p>\n</section>\n");
        return;
    }
    let _ = writeln!(h, "<p>{} measurement(s); in each series (a quantity in one filter) the most significant step, flagged above {} &sigma; (at least two points on each side: a series of fewer than four points has none).</p>", t.points.len(), num(t.threshold_sigma));
    h.push_str("<table><tr><th>quantity</th><th>filter</th><th>points</th><th>before</th><th>after</th><th>step</th><th>&sigma;</th><th>significance</th><th>between MJD</th></tr>\n");
    let mut series: Vec<(&str, &str)> = t.points.iter().map(|p| (p.quantity.as_str(), p.filter.as_str())).collect();
    series.dedup();
    for (q, f) in series {
        let count = t.points.iter().filter(|p| p.quantity == q && p.filter == f).count();
        let step = t.steps.iter().find(|s| s.quantity == q && s.filter == f);
        let cells = step.map_or("<td colspan=\"6\">no step (fewer than four points)</td>".to_string(), |s| {
            format!(
                "<td class=\"n\">{}</td><td class=\"n\">{}</td><td class=\"n\">{}</td><td class=\"n\">{}</td><td class=\"n{}\">{:.1}{}</td><td>{:.2} &ndash; {:.2}</td>",
                num(s.before),
                num(s.after),
                num(s.delta),
                num(s.sigma_delta),
                if s.flagged { " bad" } else { "" },
                s.significance,
                if s.flagged { " flagged" } else { "" },
                s.last_before_mjd,
                s.first_after_mjd
            )
        });
        let _ = writeln!(h, "<tr><td>{}</td><td>{}</td><td class=\"n\">{count}</td>{cells}</tr>", esc(q), esc(f));
    }
    h.push_str("</table>\n");
    if let Some(f) = fig {
        let _ = writeln!(h, "<figure style=\"width:50em\"><img src=\"figures/{}\" alt=\"trend of every series\"><figcaption>Each series against date, errors drawn, its step's two means as lines (red when flagged).</figcaption></figure>", esc(f));
    }
    h.push_str("</section>\n");
}

fn provenance(h: &mut String, p: &Provenance, product: &skyfield::provenance::Product) {
    let _ = write!(
        h,
        "<section id=\"provenance\">\n<h2>Provenance</h2>\n<p>{} {}, <code>{}</code>, {} UTC.</p>\n<p>What the nights' products are of: <code>{}</code>.</p>\n",
        esc(&p.program),
        esc(&p.version),
        esc(&p.command_line),
        esc(&p.date_utc),
        esc(&product.describe())
    );
    if let Some(m) = &product.mismatch_allowed {
        let _ = writeln!(h, "<p class=\"bad\">--allow-mismatch: {} in one report.</p>", esc(m));
    }
    h.push_str("<table><tr><th>input</th><th>BLAKE3</th></tr>\n");
    for i in &p.inputs {
        let _ = writeln!(h, "<tr><td><code>{}</code></td><td><code>{}</code></td></tr>", esc(&i.path), esc(&i.hash));
    }
    h.push_str("</table>\n</section>\n");
}
