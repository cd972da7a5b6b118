//! `instpol report` on the simulated night of docs/nights.md (`instpol simulate --night`, then
//! `scan`, `run`, `report`): the page's content against the night as it was simulated (its
//! sets, what is left out, its standards' catalogued values read from instruments/standards.toml
//! here, the corrected standards within their errors of the simulated truth), the page checked
//! statically (every local `src`/`href` resolves inside the folder, every anchor has its id, no
//! script, nothing fetched from a network, every SVG well-formed XML), a report refused where it
//! would write over its input, and the page opened in headless Chromium when it is on PATH
//! (required with INSTPOL_REQUIRE_CHROMIUM=1, as CI sets it): no console message, every figure
//! decoded, and a screenshot written (to $INSTPOL_REPORT_SCREENSHOT, else the test target's
//! temporary folder).

use crate::common;

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn instpol(args: &[&str]) -> std::process::Output {
    common::instpol().args(args).output().expect("run instpol")
}

fn ok(args: &[&str]) -> std::process::Output {
    let o = instpol(args);
    assert!(o.status.success(), "instpol {args:?}: {}", String::from_utf8_lossy(&o.stderr));
    o
}

/// The night of docs/nights.md written, scanned and run under `root`: the plan's path.
fn night(root: &Path) -> PathBuf {
    let s = |p: PathBuf| p.to_str().unwrap().to_string();
    let dir = s(root.join("night"));
    ok(&["simulate", "--night", &dir]);
    let plan = s(root.join("night.toml"));
    let raw = s(root.join("night/raw"));
    let inst = s(root.join("night/tiny_fors2.toml"));
    let skies = s(root.join("night/skies.csv"));
    let scan = ["scan", &raw, "--instrument", &inst, "--sky-table", &skies, "--out", &plan];
    ok(&[&scan[..], &["--bin", "8", "--fwhm", "3", "--aperture", "4"]].concat());
    ok(&["run", &plan, "--jobs", "2"]);
    PathBuf::from(plan)
}

/// Every value of attribute `attr` (`src`, `href`, `id`) in `html`.
fn attributes(html: &str, attr: &str) -> Vec<String> {
    let key = format!(" {attr}=\"");
    let mut out = vec![];
    let mut rest = html;
    while let Some(i) = rest.find(&key) {
        rest = &rest[i + key.len()..];
        let end = rest.find('"').expect("a closed attribute");
        out.push(rest[..end].to_string());
        rest = &rest[end..];
    }
    out
}

/// `text` read as XML to its end; the root element's name.
fn xml_root(text: &str) -> Result<String, String> {
    use quick_xml::events::Event;
    let mut r = quick_xml::Reader::from_str(text);
    let (mut root, mut depth) = (None, 0usize);
    loop {
        match r.read_event() {
            Ok(Event::Start(e)) => {
                root.get_or_insert_with(|| String::from_utf8_lossy(e.name().as_ref()).into_owned());
                depth += 1;
            }
            Ok(Event::End(_)) => depth = depth.checked_sub(1).ok_or("an end tag without its start")?,
            Ok(Event::Empty(e)) => {
                root.get_or_insert_with(|| String::from_utf8_lossy(e.name().as_ref()).into_owned());
            }
            Ok(Event::Eof) => break,
            Ok(_) => {}
            Err(e) => return Err(format!("at byte {}: {e}", r.buffer_position())),
        }
    }
    if depth != 0 {
        return Err(format!("{depth} element(s) not closed"));
    }
    root.ok_or_else(|| "no element".into())
}

/// The static checks of a report folder; the figures' paths (relative to the folder).
pub fn check_static(dir: &Path) -> Vec<String> {
    let html = std::fs::read_to_string(dir.join("index.html")).unwrap();
    assert!(!html.contains("<script"), "the page runs no script");
    assert!(!html.contains("http://") && !html.contains("https://") && !html.contains("//cdn"), "nothing fetched");
    let ids = attributes(&html, "id");
    for h in attributes(&html, "href") {
        let anchor = h.strip_prefix('#').unwrap_or_else(|| panic!("href {h}: only in-page links"));
        assert!(ids.iter().any(|i| i == anchor), "href {h}: no element has id {anchor}");
    }
    let srcs = attributes(&html, "src");
    for s in &srcs {
        assert!(!s.starts_with('/') && !s.contains("..") && !s.contains(':'), "src {s}: not inside the folder");
        let p = dir.join(s);
        let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("src {s}: {e}"));
        assert_eq!(xml_root(&text).unwrap_or_else(|e| panic!("{s}: not well-formed XML: {e}")), "svg", "{s}");
        assert!(!text.contains("href=\"http"), "{s} links out");
    }
    // Every figure written is shown.
    for e in std::fs::read_dir(dir.join("figures")).unwrap() {
        let name = format!("figures/{}", e.unwrap().file_name().to_string_lossy());
        assert!(srcs.contains(&name), "{name} is written but not shown");
    }
    srcs
}

/// The catalogued V-band P (fraction) of `star` in instruments/standards.toml.
fn catalogued_v(star: &str) -> f64 {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/standards.toml");
    let t: toml::Value = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let s = t["star"].as_array().unwrap().iter().find(|s| s["name"].as_str() == Some(star)).unwrap();
    let b = s["band"].as_array().unwrap().iter().find(|b| b["band"].as_str() == Some("V")).unwrap();
    b["p_percent"].as_float().unwrap() / 100.0
}

#[test]
fn the_simulated_night_reported_as_a_static_page() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let plan = night(root);
    let out = root.join("report");
    let o = ok(&["report", plan.to_str().unwrap(), "--out", out.to_str().unwrap(), "--json"]);
    let j: Value = serde_json::from_slice(&o.stdout).unwrap();
    // The night as sim::night describes it: 4 empty fields, 4 standards and a target observed
    // twice (one set of 16 angles twice over) are 9 sets; 4 HAWKI exposures of 2 chip files and
    // the aborted set's 3 exposures of 2 are 14 files left out; each empty field calibrated.
    let n = workflow::night::report::night(&plan).unwrap();
    assert_eq!(n.sets.len(), 9, "{:?}", n.sets);
    assert_eq!(n.left_out.iter().map(|l| l.files.len()).sum::<usize>(), 14);
    assert_eq!((j["nights"].as_u64(), j["calibrations"].as_u64()), (Some(1), Some(4)), "{j}");
    assert_eq!(j["units"], j["units_done"], "every unit of the night ran: {j}");
    // 2 polarized standards' P, 2 unpolarized ones' q and u, and 4 validations.
    assert_eq!(j["standards"].as_u64(), Some(10), "{j}");
    for (star, named) in [("HD 110984", "HD 110984"), ("HD 161056", "HD 161056")] {
        let c = n.standards.iter().find(|c| c.star == named && c.quantity == "p").unwrap();
        assert!((c.catalogue - catalogued_v(star)).abs() < 1e-12, "{c:?}");
    }
    // The scenes gave the standards their catalogued P: corrected, they are within errors.
    for c in n.standards.iter().filter(|c| c.quantity == "p_corrected") {
        assert!(c.pull.abs() < 4.0, "{c:?}");
    }
    let srcs = check_static(&out);
    assert_eq!(srcs.len(), j["figures"].as_array().unwrap().len());
    assert_eq!(srcs.len(), 4 * 3 + 2, "three figures per calibration, the pulls and the trend: {srcs:?}");
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    for u in &n.units {
        assert!(html.contains(&u.id), "unit {} is not on the page", u.id);
    }
    assert!(html.contains("incomplete, HWP angle(s) 67.5 missing"), "the aborted set's reason");
    chromium(&out, srcs.len());

    // A report is refused where it would write over its input: the plan named index.html in
    // the output folder.
    let clash = root.join("clash");
    std::fs::create_dir_all(&clash).unwrap();
    let plan_copy = clash.join("index.html");
    std::fs::copy(&plan, &plan_copy).unwrap();
    let before = std::fs::read(&plan_copy).unwrap();
    let o = instpol(&["report", plan_copy.to_str().unwrap(), "--out", clash.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(std::fs::read(&plan_copy).unwrap(), before);
}

fn chromium_on_path() -> Option<PathBuf> {
    std::env::var_os("PATH")?.to_str()?.split(':').map(|d| Path::new(d).join("chromium")).find(|p| p.is_file())
}

/// The page in headless Chromium (module docs).
fn chromium(dir: &Path, n_figures: usize) {
    let Some(exe) = chromium_on_path() else {
        assert!(
            std::env::var("INSTPOL_REQUIRE_CHROMIUM").map_or(true, |v| v != "1"),
            "INSTPOL_REQUIRE_CHROMIUM=1 but chromium is not on PATH (Debian: apt-get install chromium)"
        );
        eprintln!("SKIPPED: chromium is not on PATH: the report is not opened in a browser");
        return;
    };
    let profile = tempfile::tempdir().unwrap();
    let run = |args: &[String]| {
        let o = Command::new(&exe)
            .args(["--headless", "--disable-gpu", "--no-sandbox", "--enable-logging=stderr", "--v=0"])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .args(args)
            .output()
            .expect("run chromium");
        assert!(o.status.success(), "chromium {args:?}: {}", String::from_utf8_lossy(&o.stderr));
        (String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
    };
    let url = |p: &Path| format!("file://{}", std::path::absolute(p).unwrap().display());
    // The page: no console message (it runs no script, so any is an error), its DOM built.
    let (dom, err) = run(&["--dump-dom".into(), url(&dir.join("index.html"))]);
    let console: Vec<&str> = err.lines().filter(|l| l.contains("CONSOLE") || l.contains("Uncaught")).collect();
    assert!(console.is_empty(), "console messages:\n{}", console.join("\n"));
    assert!(dom.contains("<h1>instpol report</h1>"), "{}", &dom[..dom.len().min(500)]);
    // Every figure decoded: a page of the test's own (outside the report) shows them all and
    // says in its title which did not load.
    let html = std::fs::read_to_string(dir.join("index.html")).unwrap();
    let imgs: String = attributes(&html, "src").iter().map(|s| format!("<img src=\"{s}\">")).collect();
    let harness = dir.parent().unwrap().join("harness.html");
    std::fs::write(
        &harness,
        format!(
            "<!DOCTYPE html><html><head><base href=\"{}/\"><title>-</title></head><body>{imgs}<script>window.addEventListener('load',()=>{{const b=[...document.images].filter(i=>!(i.complete&&i.naturalWidth>0)).map(i=>i.getAttribute('src'));document.title='broken:'+b.join(',')+';of:'+document.images.length;}});</script></body></html>",
            url(dir)
        ),
    )
    .unwrap();
    let (dom, _) = run(&["--dump-dom".into(), "--virtual-time-budget=20000".into(), url(&harness)]);
    assert!(dom.contains(&format!("<title>broken:;of:{n_figures}</title>")), "{}", &dom[..dom.len().min(800)]);
    // The screenshot.
    let shot = std::env::var_os("INSTPOL_REPORT_SCREENSHOT")
        .map_or_else(|| Path::new(env!("CARGO_TARGET_TMPDIR")).join("report.png"), PathBuf::from);
    let _ = std::fs::remove_file(&shot);
    run(&["--window-size=1000,1400".into(), format!("--screenshot={}", shot.display()), url(&dir.join("index.html"))]);
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&shot).unwrap()));
    let info = decoder.read_info().unwrap();
    assert_eq!((info.info().width, info.info().height), (1000, 1400));
    eprintln!("screenshot of the report: {}", shot.display());
}

/// Bad inputs are refused by name, with exit 2 and nothing written: a plan that is not there,
/// an output folder under a file, a threshold that is no threshold, and a simulated night into
/// a folder that holds files already.
#[test]
fn bad_inputs_of_report_and_simulate_night_are_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let s = |p: PathBuf| p.to_str().unwrap().to_string();
    let refused = |args: &[&str], names: &str| {
        let o = instpol(args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(names), "{args:?}: the message should name {names}: {err}");
    };
    let missing = s(root.join("no_such_plan.toml"));
    refused(&["report", &missing, "--out", &s(root.join("r1"))], "no_such_plan.toml");
    assert!(!root.join("r1").exists());
    std::fs::write(root.join("afile"), "x").unwrap();
    let plan = root.join("plan.toml");
    std::fs::write(&plan, "version = 1\ninstrument = \"fors2\"\nrecords = \"products/.instpol-run\"\nunits = []\n")
        .unwrap();
    refused(&["report", &s(plan.clone()), "--out", &s(root.join("afile/report"))], "afile");
    refused(&["report", &s(plan), "--out", &s(root.join("r2")), "--threshold", "-1"], "threshold");
    assert!(!root.join("r2").exists());
    let full = root.join("full");
    std::fs::create_dir_all(&full).unwrap();
    std::fs::write(full.join("notes.txt"), "mine").unwrap();
    refused(&["simulate", "--night", &s(full.clone())], "not empty");
    assert_eq!(std::fs::read_dir(&full).unwrap().count(), 1, "nothing written beside the folder's file");
}
