//! A valid invocation of every command on tiny inputs made by the binary itself, and the CLI's
//! own definition of its commands (`instpol cli-spec`): the starting points of the
//! hostile-input generator (hostile.rs) and of the full-disk test (full_disk.rs), which vary
//! one argument at a time, so that what is valid is written once.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::mueller_maps;

/// Every command's arguments and their kinds and roles, from the binary's own definition.
pub fn spec() -> serde_json::Value {
    let (code, out, err) = super::run(&["cli-spec"]);
    assert_eq!(code, 0, "cli-spec: {err}");
    serde_json::from_str(&out).unwrap()
}

/// The arguments (their spec objects) of every command of `spec`, by command name.
pub fn args_by_command(spec: &serde_json::Value) -> BTreeMap<String, Vec<serde_json::Value>> {
    spec.as_array()
        .unwrap()
        .iter()
        .map(|c| (c["name"].as_str().unwrap().to_string(), c["args"].as_array().unwrap().clone()))
        .collect()
}

/// The long flags of `kind` (`number`, `text`, `path`) of every command of `spec`.
pub fn flags_of_kind(spec: &serde_json::Value, kind: &str) -> BTreeMap<String, Vec<String>> {
    args_by_command(spec)
        .into_iter()
        .map(|(name, args)| {
            let flags = args
                .iter()
                .filter(|a| a["kind"] == kind)
                .filter_map(|a| a["long"].as_str().map(str::to_string))
                .collect();
            (name, flags)
        })
        .collect()
}

/// Commands without a valid invocation in [`templates`], with the reason.
pub const NOT_YET: &[(&str, &str)] = &[];

/// The valid inputs every case starts from, made by the binary itself (and the test
/// libraries' writers where the binary has no command for them: Mueller-test maps, q/u cubes,
/// star catalogs).
pub struct Fixture {
    pub dir: tempfile::TempDir,
}

impl Fixture {
    pub fn p(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
    pub fn s(&self, name: &str) -> String {
        self.p(name).to_str().unwrap().to_string()
    }
    pub fn frames(&self) -> Vec<String> {
        super::fits_in(&self.p("frames")).iter().map(|p| p.to_str().unwrap().to_string()).collect()
    }
}

pub const SCENE: &str = r#"instrument = "mini.toml"
filter = "V"
seed = 3
exposure_s = 10.0
[sky]
brightness_e = 20000
p = 0.02
[[stars]]
x = 48
y = 24
coords = "pixel"
flux_e = 200000
p = 0.0
fwhm_arcsec = 8.0
[[stars]]
x = 20
y = 24
coords = "pixel"
flux_e = 200000
p = 0.05
chi_deg = 30
fwhm_arcsec = 8.0
[effects]
photon_noise = true
read_noise_e = 3.0
cosmic_rays = { rate_per_frame = 2 }
"#;

const STOKES_CSV: &str =
    "hwp_deg,f_o,f_e\n0,505000,495000\n22.5,508660.25,491339.75\n45,495000,505000\n67.5,491339.75,508660.25\n";

/// Dither offsets (arcmin) of the star catalogs of `calibrate-stars`.
const OFFSETS: [[f64; 2]; 4] = [[0.0, 0.0], [0.6, 0.25], [-0.35, 0.55], [0.3, -0.6]];

/// The three sky fields of the Mueller maps: (file, P percent, chi deg).
const SKIES: [(&str, f64, f64); 3] = [("m1.fits", 6.45, 68.4), ("m2.fits", 4.0, 10.0), ("m3.fits", 8.0, 130.0)];

fn must(args: &[&str]) {
    let (code, _, err) = super::run(args);
    assert_eq!(code, 0, "fixture step {args:?} failed: {err}");
}

/// A Mueller field with a diattenuation and a retardance growing from the centre (the
/// stressed-lens form of the Mueller tests, smaller).
fn mueller_truth(x: f64, y: f64) -> mueller::linear::LinearBlock {
    use mueller::linear::{physical_block, retardance_vector};
    physical_block(
        2e-4 * (x * x - y * y),
        4e-4 * x * y,
        retardance_vector(0.01 * (x * x + y * y), y.atan2(x)),
        0.0,
        0.0,
    )
}

/// Write `text` to the fixture file `name`.
fn put(f: &Fixture, name: &str, text: &str) {
    std::fs::write(f.p(name), text).unwrap();
}

/// One small night of the shrunk FORS2 under `root`: biases, sky flats and an empty field of
/// known sky polarization at four angles, scanned (`root/night.toml`, its sky field from
/// `root/skies.csv`) and run.
fn night(root: &Path, mjd: f64, seed: u64) {
    use super::night::{simulate_scene, tiny_fors2, Spec};
    let q4 = vec![0.0, 22.5, 45.0, 67.5];
    let specs = [
        Spec::bias(vec![0.0, 22.5, 45.0], mjd + 0.80, seed),
        Spec::sky_flat("flat", "v_HIGH", q4.clone(), mjd + 0.81, 11, seed + 1),
        Spec {
            dir: "empty",
            filter: "v_HIGH",
            angles: q4,
            start_mjd: mjd + 0.83,
            first_exp: 21,
            dpr: ["SCIENCE", "OBJECT", "POLARIMETRY"],
            target: "EMPTY-V",
            ra_dec: (150.0, -30.0),
            sky: Some((3000.0, 0.0174, -53.8)),
            stars: vec![],
            instrume: None,
            seed: seed + 2,
        },
    ];
    std::fs::create_dir_all(root).unwrap();
    for s in &specs {
        simulate_scene(root, s, &tiny_fors2(), [0.0, 0.1, 0.3, 0.05], "");
    }
    std::fs::write(root.join("skies.csv"), "target,p_percent,chi_deg\nEMPTY-V,1.74,-53.8\n").unwrap();
    let st = |p: &Path| p.to_str().unwrap().to_string();
    let plan = st(&root.join("night.toml"));
    let args = night_scan_args(&st(&root.join("raw")), &st(&tiny_fors2()), &plan, &st(&root.join("skies.csv")));
    let (code, _, err) = super::run(&args);
    assert_eq!(code, 0, "fixture scan: {err}");
    must(&["run", &plan]);
}

/// `instpol scan` of a night with the tiny FORS2's sizes (8 px bins, 3 px stars in 4 px
/// apertures) and the sky fields from a table.
fn night_scan_args(raw: &str, instrument: &str, plan: &str, skies: &str) -> Vec<String> {
    [
        "scan",
        raw,
        "--instrument",
        instrument,
        "--out",
        plan,
        "--bin",
        "8",
        "--fwhm",
        "3",
        "--aperture",
        "4",
        "--sky-table",
        skies,
    ]
    .map(String::from)
    .to_vec()
}

pub fn fixture() -> Fixture {
    let f = Fixture { dir: tempfile::tempdir().unwrap() };
    put(&f, "mini.toml", &super::MINI.toml());
    put(&f, "scene.toml", SCENE);
    put(&f, "f.csv", STOKES_CSV);
    // A catalog that says what it is (the keywords `instpol catalog` writes), of the
    // calibration's instrument, filter and detector (MINI's 96 px of 4").
    put(
        &f,
        "cat.csv",
        "# INSTRUME = MINI\n# FILTER = V\n# PLATE = half_wave\n# DETSIZE = 96x96\n# PIXSCALE = 4.0\nx,y,q,u,sigma_q,sigma_u\n0.5,0.5,0.01,0,0.001,0.001\n-1,1,0,0.01,0.001,0.001\n",
    );
    // Standards' rows of that instrument and filter: one unpolarized, two polarized.
    put(
        &f,
        "std.csv",
        "# INSTRUME = MINI\n# FILTER = V\n# PLATE = half_wave\nx,y,q,u,sigma_q,sigma_u\n10,10,0.004,-0.003,3e-4,3e-4\n30,30,0.018,0.030,3e-4,3e-4\n50,10,0.035,-0.012,3e-4,3e-4\n",
    );
    must(&["simulate", &f.s("scene.toml"), "--out", &f.s("frames"), "--json"]);
    // The truth file is not an input of anything.
    std::fs::remove_file(f.p("frames/truth.json")).unwrap();
    let mut a = vec!["reduce".to_string()];
    a.extend(f.frames());
    a.extend(["--instrument", &f.s("mini.toml"), "--bin", "8", "--out", &f.s("map.fits"), "--json"].map(String::from));
    must(&a.iter().map(|s| s.as_str()).collect::<Vec<_>>());
    must(&[
        "calibrate",
        "--map",
        &f.s("map.fits"),
        "--instrument",
        &f.s("mini.toml"),
        "--sky-p",
        "2",
        "--sky-chi",
        "30",
        "--out",
        &f.s("cal.fits"),
        "--json",
    ]);
    // Raw chip files of the shrunk FORS2 (bias and flats) for the masters.
    std::fs::create_dir_all(f.p("raw")).unwrap();
    put(&f, "fors2_tiny.toml", &super::raw::fors2_tiny_text());
    let raw = super::raw::write_raw_set(&f.p("raw"), &super::raw::fors2_tiny());
    let list = |v: &[PathBuf]| v.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join("\n");
    put(&f, "raw/bias.list", &list(&raw.bias));
    put(&f, "raw/flats.list", &list(&raw.flats));
    // Standards through an aluminium M3 (factor 0.86, offset 40 deg: Wiersema et al. 2018's
    // model), q, u = 3.5 % turned by the parallactic angle, at twelve angles.
    let mut t = String::from("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter\n");
    for k in 0..12 {
        let pa = -160.0 + 29.0 * k as f64;
        let a = 2.0 * (40f64 - pa).to_radians();
        t += &format!("S{k},{pa},{},0.0002,{},0.0002,0.55,V\n", 0.035 * a.cos(), -0.035 * a.sin());
    }
    put(&f, "standards.csv", &t);
    // A second filter for the wavelength law: the same calibration relabelled B at 440 nm.
    std::fs::copy(f.p("cal.fits"), f.p("cal2.fits")).unwrap();
    patch_card(&f.p("cal2.fits"), "IP FILTER", "'B'");
    patch_card(&f.p("cal2.fits"), "IP LAMBDA NM", "440.0");
    // Imported q, u maps (a 96 x 96 px detector of 4" pixels in 8 px bins).
    let field = fit::RadialModel::new(1, vec![1e-4, 4e-4, 0.0], [0.0, 0.0]);
    fit::models::synth::write_qu_cubes(&f.p("q.fits"), &f.p("u.fits"), &field, 96, 96, 4.0, 8, 1e-4).unwrap();
    // Star catalogs of four dithered pointings for calibrate-stars.
    std::fs::create_dir_all(f.p("stars")).unwrap();
    super::star_catalogs(&f.p("stars"), 5, 60, 0, (0.0, 0.0), 5e-4, &OFFSETS);
    // Three FORS1 B sky maps (256 px bins) through a Mueller field, a table of two polarized
    // standards seen through it, and the field calibrate-mueller fits from them.
    for (name, p, chi) in SKIES {
        mueller_maps::map_binned(f.dir.path(), name, p / 100.0, chi, 3e-4, &mueller_truth, 256);
    }
    let mut stars = String::from("x_arcmin,y_arcmin,q,u,sigma_q,sigma_u,p_true,chi_true_deg\n");
    for (x, y, p, chi) in [(1.0f64, -0.5f64, 0.05f64, 20.0f64), (-1.5, 1.2, 0.03, 100.0)] {
        let c = 2.0 * chi.to_radians();
        let (q, u) = mueller_truth(x, y).forward(p * c.cos(), p * c.sin()).unwrap();
        stars += &format!("{x},{y},{q},{u},0.0005,0.0005,{p},{chi}\n");
    }
    put(&f, "mueller_stars.csv", &stars);
    let mut a: Vec<String> = vec!["calibrate-mueller".into()];
    for (name, p, chi) in SKIES {
        a.extend(["--field".to_string(), format!("{}:{p}:{chi}", f.s(name))]);
    }
    a.extend(["--deg", "2", "--out", &f.s("mueller.fits")].map(String::from));
    let (code, _, err) = super::run(&a);
    assert_eq!(code, 0, "fixture calibrate-mueller: {err}");
    // Zero angles measured before (a table of two standards).
    put(
        &f,
        "measured.csv",
        "label,chi_measured_deg,sigma_chi_measured_deg,chi_catalogue_deg,sigma_chi_catalogue_deg\nA,31.2,0.3,30.0,0.2\nB,12.9,0.4,11.5,0.3\n",
    );
    // Two small nights of the shrunk FORS2, scanned and run: trend reads both; run's valid
    // invocation is a dry run of the first (a real run would write into the shared fixture).
    night(&f.p("night1"), 58546.0, 1);
    night(&f.p("night2"), 58576.0, 11);
    f
}

/// Replace the value of the header card holding `key` (the comment dropped).
pub fn patch_card(path: &Path, key: &str, value: &str) {
    let mut b = std::fs::read(path).unwrap();
    let pos = b.windows(key.len()).position(|w| w == key.as_bytes()).unwrap_or_else(|| panic!("no card {key}"));
    let card = pos - pos % 80;
    let eq = card + b[card..card + 80].iter().position(|&c| c == b'=').unwrap();
    let mut field = format!(" {value}");
    while field.len() < 80 - (eq + 1 - card) {
        field.push(' ');
    }
    b[eq + 1..card + 80].copy_from_slice(&field.as_bytes()[..card + 80 - eq - 1]);
    std::fs::write(path, b).unwrap();
}

/// A command's valid invocation. `{OUT}` stands for the case's output file (`out_name` in the
/// case's folder) and `{DIR}` for the case's folder itself (for outputs that are folders).
pub struct Template {
    /// The label of the invocation in the results (the command, and what it reads if the
    /// command has several invocations).
    pub command: &'static str,
    pub args: Vec<String>,
    pub out_name: Option<&'static str>,
}

impl Template {
    /// The command's name (the first argument).
    pub fn name(&self) -> &str {
        &self.args[0]
    }
}

pub fn templates(f: &Fixture) -> Vec<Template> {
    let fr = f.frames();
    let ins = f.s("mini.toml");
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
    let with_frames = |mut v: Vec<String>| {
        v.extend(fr.iter().cloned());
        v
    };
    let star = ["--instrument", &ins, "--x", "48", "--y", "24", "--aperture", "3", "--annulus", "4,6"];
    let cat_opts = ["--instrument", &ins, "--fwhm", "3", "--aperture", "3", "--annulus", "4,6"];
    let cal = f.s("cal.fits");
    let lines = |name: &str| -> Vec<String> {
        std::fs::read_to_string(f.p(name)).unwrap().lines().map(str::to_string).collect()
    };
    let (bias, flats) = (lines("raw/bias.list"), lines("raw/flats.list"));
    let tiny = f.s("fors2_tiny.toml");
    let t =
        |command: &'static str, args: Vec<String>, out_name: Option<&'static str>| Template { command, args, out_name };
    let catalogs: Vec<String> = (1..=4).map(|k| f.s(&format!("stars/pointing{k}.csv"))).collect();
    let mut calibrate_stars = [s(&["calibrate-stars"]), catalogs].concat();
    calibrate_stars.extend(s(&["--filter", "V", "--out", "{OUT}", "--json"]));
    for o in OFFSETS {
        calibrate_stars.extend(["--offset".to_string(), format!("{},{}", o[0], o[1])]);
    }
    let mut calibrate_mueller = s(&["calibrate-mueller"]);
    for (name, p, chi) in SKIES {
        calibrate_mueller.extend(["--field".to_string(), format!("{}:{p}:{chi}", f.s(name))]);
    }
    calibrate_mueller.extend(s(&["--deg", "2", "--stars", &f.s("mueller_stars.csv"), "--out", "{OUT}", "--json"]));
    let mut scan = night_scan_args(
        &f.s("night1/raw"),
        &super::night::tiny_fors2().display().to_string(),
        "{OUT}",
        &f.s("night1/skies.csv"),
    );
    scan.push("--json".into());
    vec![
        t("demo", s(&["demo", "--no-frames", "--out", "{DIR}/demo", "--json"]), None),
        t("scan", scan, Some("night.toml")),
        t("run", s(&["run", &f.s("night1/night.toml"), "--dry-run", "--json"]), None),
        t(
            "trend",
            s(&["trend", &f.s("night1/night.toml"), &f.s("night2/night.toml"), "--out", "{OUT}", "--json"]),
            Some("trend.ecsv"),
        ),
        t("report", s(&["report", &f.s("night1/night.toml"), "--out", "{DIR}/report", "--json"]), None),
        t(
            "master-bias",
            [s(&["master-bias", "--instrument", &tiny, "--out", "{OUT}", "--json"]), bias].concat(),
            Some("bias.fits"),
        ),
        t(
            "master-flat",
            [s(&["master-flat", "--instrument", &tiny, "--out", "{OUT}", "--json"]), flats].concat(),
            Some("flat.fits"),
        ),
        t(
            "zero-angle",
            with_frames(s(&[
                "zero-angle",
                "--instrument",
                &ins,
                "--x",
                "20",
                "--y",
                "24",
                "--chi-deg",
                "30",
                "--aperture",
                "3",
                "--annulus",
                "4,6",
                "--json",
            ])),
            None,
        ),
        t(
            "zero-angle --measured",
            s(&["zero-angle", "--measured", &f.s("measured.csv"), "--filter", "V", "--json"]),
            None,
        ),
        t(
            "efficiency",
            s(&[
                "efficiency",
                "--standard",
                &format!("{}:10,10:unpolarized", f.s("std.csv")),
                "--standard",
                &format!("{}:30,30:0.04+-0.0001/30+-0.1", f.s("std.csv")),
                "--standard",
                &format!("{}:50,10:0.04+-0.0001/170+-0.1", f.s("std.csv")),
                "--output",
                "{OUT}",
                "--json",
            ]),
            Some("response.fits"),
        ),
        t("fit-standards", s(&["fit-standards", &f.s("standards.csv"), "--model", "wiersema", "--json"]), None),
        t("stokes", s(&["stokes", "--input", &f.s("f.csv"), "--json"]), None),
        t("stokes --plot", s(&["stokes", "--input", &f.s("f.csv"), "--plot", "{OUT}", "--json"]), Some("fourier.png")),
        t("bias", s(&["bias", "--p", "0.01", "--sigma", "0.003", "--json"]), None),
        t("mc", s(&["mc", "--trials", "2000", "--json"]), None),
        t("fresnel", s(&["fresnel", "--n-real", "1.5", "--aoi-deg", "10", "--json"]), None),
        t("raytrace", s(&["raytrace", "--instrument", "fors1", "--json"]), None),
        t(
            "reduce",
            with_frames(s(&["reduce", "--instrument", &ins, "--bin", "8", "--out", "{OUT}", "--json"])),
            Some("map.fits"),
        ),
        t(
            "catalog",
            with_frames(s(&[&["catalog"][..], &cat_opts[..], &["--out", "{OUT}", "--json"]].concat())),
            Some("cat.csv"),
        ),
        t(
            "catalog --cal",
            with_frames(s(&[&["catalog"][..], &cat_opts[..], &["--cal", &cal, "--out", "{OUT}", "--json"]].concat())),
            Some("cat.csv"),
        ),
        t("photometry", with_frames(s(&[&["photometry"][..], &star[..], &["--json"]].concat())), None),
        t(
            "calibrate",
            s(&[
                "calibrate",
                "--map",
                &f.s("map.fits"),
                "--instrument",
                &ins,
                "--sky-p",
                "2",
                "--sky-chi",
                "30",
                "--out",
                "{OUT}",
                "--json",
            ]),
            Some("cal.fits"),
        ),
        t("calibrate-stars", calibrate_stars, Some("stars_cal.fits")),
        t("calibrate-mueller", calibrate_mueller, Some("mueller.fits")),
        t(
            "explain",
            s(&[
                "explain",
                &f.s("mueller.fits"),
                "--instrument",
                "fors1",
                "--band",
                "B",
                "--causes",
                "stressed_lens",
                "--grid",
                "8",
                "--json",
            ]),
            None,
        ),
        t("plan", s(&[&super::QUICK_PLAN[..], &["--plot", "{OUT}", "--json"]].concat()), Some("plan.svg")),
        t(
            "import-map",
            s(&[
                "import-map",
                "--q",
                &f.s("q.fits"),
                "--u",
                &f.s("u.fits"),
                "--pixel-scale",
                "4",
                "--bin",
                "8",
                "--filter",
                "V",
                "--out",
                "{OUT}",
                "--json",
            ]),
            Some("imported.fits"),
        ),
        t("fit", s(&["fit", &f.s("cal.fits"), "--out", "{OUT}", "--json"]), Some("refit.fits")),
        t("plot", s(&["plot", &f.s("cal.fits"), "--out", "{DIR}/plots", "--json"]), None),
        t(
            "correct (catalog)",
            s(&["correct", "--cal", &f.s("cal.fits"), "--in", &f.s("cat.csv"), "--out", "{OUT}", "--json"]),
            Some("cat_out.csv"),
        ),
        t(
            "correct (map)",
            s(&["correct", "--cal", &f.s("cal.fits"), "--in", &f.s("map.fits"), "--out", "{OUT}", "--json"]),
            Some("map_out.fits"),
        ),
        t(
            "validate",
            with_frames(s(&[&["validate", "--cal", &f.s("cal.fits")][..], &star[..], &["--json"]].concat())),
            None,
        ),
        t("wavelength-law", s(&["wavelength-law", &f.s("cal.fits"), &f.s("cal2.fits"), "--json"]), None),
        t("simulate", s(&["simulate", &f.s("scene.toml"), "--out", "{DIR}/frames", "--json"]), None),
        t("simulate", s(&["simulate", "--night", "{DIR}/night", "--json"]), None),
    ]
}

/// `args` with `{OUT}` and `{DIR}` filled for the case folder `dir` (output file `out_name`).
pub fn fill(args: &[String], dir: &Path, out_name: Option<&str>) -> Vec<String> {
    let o = dir.join(out_name.unwrap_or("out"));
    args.iter().map(|x| x.replace("{OUT}", o.to_str().unwrap()).replace("{DIR}", dir.to_str().unwrap())).collect()
}
