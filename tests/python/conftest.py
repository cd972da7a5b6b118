"""Shared fixtures of the Python package's tests: the `instpol` binary (env INSTPOL_BIN,
default target/release/instpol), its JSON output, and data made once per session with it
(a FORS1 calibration from `instpol demo --no-frames`, simulated frames).

Every JSON key is looked up through `key()`, the one place that knows the names the CLI
has used for a quantity (the JSON vocabulary of issue 15 renames some of them)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]

# vocabulary name -> names the CLI may still print for it (first match wins)
ALIASES = {
    "output": ["output", "out", "out_dir", "calibration_file"],
    "n_bins": ["n_bins", "bins"],
    "n_valid_bins": ["n_valid_bins", "valid_bins"],
    "n_rows": ["n_rows", "rows"],
    "n_extrapolated": ["n_extrapolated", "extrapolated"],
    "median_p": ["median_p", "p_median"],
    "median_chi_deg": ["median_chi_deg", "chi_median_deg"],
    "median_sigma_q": ["median_sigma_q", "sigma_q_median"],
    "median_p0": ["median_p0", "p0_median"],
    "median_p_inst": ["median_p_inst", "p_inst_median"],
    "interval": ["interval"],
    "sigma_chi_deg": ["sigma_chi_deg", "chi_err_deg"],
}


def key(d, name):
    """`d[name]` under the name the CLI prints for it (see ALIASES)."""
    for k in ALIASES.get(name, [name]):
        if k in d:
            return d[k]
    raise KeyError(f"none of {ALIASES.get(name, [name])} in the JSON keys {sorted(d)}")


def num(v):
    """A JSON number (null -> NaN) as a float, arrays as float arrays."""
    if isinstance(v, list):
        return np.array([num(x) for x in v], dtype=float)
    return float("nan") if v is None else float(v)


def same(a, b):
    """Bit-for-bit equality of floats or float arrays (NaN equals NaN)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


@pytest.fixture(scope="session")
def instpol_bin():
    p = Path(os.environ.get("INSTPOL_BIN", ROOT / "target" / "release" / "instpol"))
    if not p.is_file():
        msg = (
            f"the instpol binary is missing at {p}: build it (cargo build --release -p instpol) "
            "or set INSTPOL_BIN; the tests that compare with the CLI cannot run"
        )
        print(f"\nSKIPPED LOUDLY: {msg}", file=sys.stderr)
        if os.environ.get("INSTPOL_REQUIRE_BIN"):
            pytest.fail(msg)
        pytest.skip(msg)
    return str(p)


@pytest.fixture(scope="session")
def run(instpol_bin):
    """Run `instpol ARGS`; return (exit code, stdout, stderr)."""

    def _run(*args, check=True):
        r = subprocess.run([instpol_bin, *map(str, args)], capture_output=True, text=True, timeout=600)
        if check and r.returncode != 0:
            raise AssertionError(f"instpol {' '.join(map(str, args))} exited {r.returncode}: {r.stderr}")
        return r.returncode, r.stdout, r.stderr

    return _run


@pytest.fixture(scope="session")
def run_json(run):
    """Run `instpol ARGS --json` and parse its stdout."""

    def _run_json(*args):
        return json.loads(run(*args, "--json")[1])

    return _run_json


@pytest.fixture(scope="session")
def demo_dir(run, tmp_path_factory):
    """FORS1 calibrations of the paper's B, V, I fields (`instpol demo --no-frames`)."""
    d = tmp_path_factory.mktemp("demo")
    run("demo", "--no-frames", "--out", d)
    return d


PRODUCT_KEYS = ["INSTHASH", "WAVELEN", "PLATE", "DETSIZE", "PIXSCALE", "INSTRUME", "FILTER"]


def without_product(cal: Path, dest: Path) -> Path:
    """A copy of calibration `cal` without its product keywords, as a file written before
    calibrations recorded them: the demo's calibrations are of the built-in FORS1 (2048 px),
    the tests' maps and catalogs of a tiny FORS1 (128 px), a detector the one compatibility
    check would refuse; these tests are about the correction's arithmetic, not that check
    (test_product.py is)."""
    from astropy.io import fits

    with fits.open(cal) as h:
        for k in list(h[0].header.keys()):
            if k in PRODUCT_KEYS or k.startswith("INHASH"):
                del h[0].header[k]
        h.writeto(dest)
    return dest


@pytest.fixture(scope="session")
def cal_v(demo_dir, tmp_path_factory):
    return without_product(demo_dir / "cal_V.fits", tmp_path_factory.mktemp("calv") / "cal_V.fits")


@pytest.fixture(scope="session")
def cal_b(demo_dir, tmp_path_factory):
    return without_product(demo_dir / "cal_B.fits", tmp_path_factory.mktemp("calb") / "cal_B.fits")


def shrunk(name: str, replacements, dest: Path) -> Path:
    """instruments/NAME.toml with each (a, b) of `replacements` applied (each must be there),
    written to `dest`."""
    text = (ROOT / "instruments" / f"{name}.toml").read_text()
    for a, b in replacements:
        assert a in text, f"instruments/{name}.toml no longer has '{a}'"
        text = text.replace(a, b)
    dest.write_text(text)
    return dest


def tiny_fors1(dir_: Path) -> Path:
    """instruments/fors1.toml shrunk to 128 x 128 px with one strip (as crates/cli/tests)."""
    return shrunk("fors1", [
        ("nx = 2048", "nx = 128"),
        ("ny = 2048", "ny = 128"),
        ("throw_arcsec = 22.0", "throw_arcsec = 8.0"),
        ("strip_count = 9", "strip_count = 1"),
        ("first_strip_y_px = 34", "first_strip_y_px = 20"),
    ], dir_ / "tiny.toml")


@pytest.fixture(scope="session")
def sky_frames(run, tmp_path_factory):
    """Four simulated frames of a uniformly polarized sky (p = 0.0645, chi = 68.4 deg, the
    paper's V field) through a tiny FORS1, and that instrument file."""
    d = tmp_path_factory.mktemp("sky")
    inst = tiny_fors1(d)
    scene = d / "scene.toml"
    scene.write_text(
        f'instrument = "{inst}"\nfilter = "V"\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n[output]\nbitpix = -64\n'
        "[sky]\nbrightness_e = 3000\np = 0.0645\nchi_deg = 68.4\n"
    )
    run("simulate", scene, "--out", d / "frames")
    return sorted((d / "frames").glob("*.fits")), inst


@pytest.fixture(scope="session")
def star_frames(run, tmp_path_factory):
    """Eight simulated frames of three stars through the maskless calcite example instrument
    (instruments/scenes/calcite_stars.toml, with an HWP keyword so no angles need be given)."""
    d = tmp_path_factory.mktemp("stars")
    text = (ROOT / "instruments" / "calcite.toml").read_text()
    assert 'hwp_angle_keyword = ""' in text
    inst = d / "calcite.toml"
    inst.write_text(text.replace('hwp_angle_keyword = ""', 'hwp_angle_keyword = "HWPANG"'))
    scene = (ROOT / "instruments" / "scenes" / "calcite_stars.toml").read_text()
    scene = scene.replace('instrument = "calcite"', f'instrument = "{inst}"')
    sp = d / "scene.toml"
    sp.write_text(scene)
    run("simulate", sp, "--out", d / "frames")
    return sorted((d / "frames").glob("*.fits")), inst
