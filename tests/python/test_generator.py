"""The Python face's share of the hostile generator (crates/cli/tests/it/hostile.rs): each
class's property over every public function of the package that takes its kind of input,
enumerated from the package itself (``inspect``), so that a function added later is tried or
named here with a reason, never skipped without a word.

- duplicate input: every parameter taking a list of files (``frames``, ``catalogs``) given its
  first file again after it under another name (the same path, a copy, a hard link, a
  symlink): refused (InputError) naming both names; never counted twice.
- plate set: every parameter taking frames given the set with one frame left out (one plate
  angle missing): refused (InputError) or reduced with a warning, either way naming the
  missing angle.
- another product: every public function or method taking a calibration and the data's
  instrument and filter (``Calibration.correct``) given data of another filter: refused
  naming both, unless ``allow_mismatch``; and every method taking the data's whole
  ``product`` (``catalog()["product"]``) given one of another filter, instrument or detector:
  refused naming what differs.
"""

import inspect
import os
import shutil

import numpy as np
import pytest

import instpol
from test_calibrate_stars import write_catalogs

LISTS = ("frames", "catalogs")

# Functions taking a list of files that the generator does not call here, with the reason.
NOT_HERE = {
    "scan": "takes folders of a night (its duplicates are the CLI's night tests, the same library call)",
}


def public_functions():
    return {n: f for n, f in vars(instpol).items() if inspect.isfunction(f) and not n.startswith("_")}


def taking(names):
    """The public functions whose first parameter is one of `names` (a keyword of the same name,
    demo's ``frames=True``, is not a list of files)."""
    return sorted(n for n, f in public_functions().items()
                  if next(iter(inspect.signature(f).parameters), None) in names)


@pytest.fixture(scope="module")
def calls(sky_frames, star_frames, tmp_path_factory):
    """Per function taking a list of files: its valid files and a call with a list of them."""
    cats, _ = write_catalogs(tmp_path_factory.mktemp("cats"))
    return {
        "reduce": (list(sky_frames[0]), lambda f: instpol.reduce(f, instrument=str(sky_frames[1]), bin=10)),
        "catalog": (list(star_frames[0]), lambda f: instpol.catalog(f, instrument=str(star_frames[1]))),
        "calibrate_stars": (cats, lambda f: instpol.calibrate_stars(f, "fors1", filter="V", model="plane",
                                                                    interstellar="zero")),
    }


def test_every_function_taking_files_is_tried_or_named(calls):
    for name in taking(LISTS):
        assert name in calls or name in NOT_HERE, f"instpol.{name} takes a list of files: add it to the generator"


@pytest.mark.parametrize("how", ["same path", "copy", "hard link", "symlink"])
@pytest.mark.parametrize("name", ["reduce", "catalog", "calibrate_stars"])
def test_duplicate_input(calls, name, how, tmp_path):
    files, call = calls[name]
    first = str(files[0])
    other = {"same path": first, "copy": str(tmp_path / ("copy" + os.path.splitext(first)[1])),
             "hard link": str(tmp_path / ("link" + os.path.splitext(first)[1])),
             "symlink": str(tmp_path / ("sym" + os.path.splitext(first)[1]))}[how]
    if how == "copy":
        shutil.copyfile(first, other)
    elif how == "hard link":
        os.link(first, other)
    elif how == "symlink":
        os.symlink(first, other)
    with pytest.raises(instpol.InputError) as e:
        call([str(f) for f in files] + [other])
    msg = str(e.value)
    assert os.path.basename(first) in msg and os.path.basename(other) in msg, f"{name} [{how}]: {msg}"


@pytest.mark.parametrize("name", ["reduce", "catalog"])
def test_plate_set_with_an_angle_missing(calls, name):
    files, call = calls[name]
    assert len(files) >= 4
    try:
        r = call([str(f) for f in files[1:]])
    except instpol.InputError as e:
        assert "missing [" in str(e), f"{name}: refused without naming the missing angle: {e}"
        return
    warnings = r["warnings"] if isinstance(r, dict) else getattr(r, "warnings", [])
    assert any("missing [" in str(w) for w in warnings), f"{name}: reduced without naming the gap: {warnings}"


def test_another_filter_for_every_correction(cal_v):
    """Every method of Calibration that corrects data of a stated filter refuses another one."""
    cal = instpol.Calibration.load(cal_v)
    methods = [m for m, f in inspect.getmembers(instpol.Calibration, inspect.isfunction)
               if not m.startswith("_") and "filter" in inspect.signature(f).parameters]
    assert "correct" in methods, methods
    x, y = np.array([0.5]), np.array([-0.3])
    q, u = np.array([0.01]), np.array([0.0])
    s = np.array([1e-3])
    for m in methods:
        assert m == "correct", f"Calibration.{m} takes a filter: add it to the generator"
        with pytest.raises(instpol.InputError) as e:
            cal.correct(x, y, q, u, s, s, instrument="FORS1", filter="I")
        assert "I" in str(e.value) and "V" in str(e.value), str(e.value)
        ok = cal.correct(x, y, q, u, s, s, instrument="FORS1", filter="I", allow_mismatch=True)
        assert np.isfinite(ok["q0"]).all()


# A product of the demo's V calibration's own setup (the built-in FORS1: 2048 px of 0.2"), and
# each way another product differs from it, with the word the refusal must name.
SAME = {"instrument": "FORS1", "filter": "V", "plate": "half_wave", "hwp_chi_offset_deg": 0.0,
        "detector_px": (2048, 2048), "pixel_scale_arcsec": 0.2, "sky_pa_deg": None}
OTHER = [({"filter": "I"}, "filter I"), ({"instrument": "EFOSC2"}, "EFOSC2"),
         ({"detector_px": (1000, 1000)}, "1000x1000"), ({"pixel_scale_arcsec": 0.25}, "0.25 arcsec")]


@pytest.mark.parametrize("change,word", OTHER, ids=[w for _, w in OTHER])
def test_another_product_for_every_correction(demo_dir, change, word):
    """Every method of Calibration taking the data's product refuses one of another setup."""
    cal = instpol.Calibration.load(demo_dir / "cal_V.fits")
    methods = [m for m, f in inspect.getmembers(instpol.Calibration, inspect.isfunction)
               if not m.startswith("_") and "product" in inspect.signature(f).parameters]
    assert methods == ["correct"], f"Calibration methods taking a product: {methods}; add each to the generator"
    args = (np.array([0.5]), np.array([-0.3]), np.array([0.01]), np.array([0.0]), np.array([1e-3]), np.array([1e-3]))
    same = cal.correct(*args, product=dict(SAME))
    assert np.isfinite(same["q0"]).all()
    with pytest.raises(instpol.InputError) as e:
        cal.correct(*args, product={**SAME, **change})
    assert word in str(e.value), str(e.value)
