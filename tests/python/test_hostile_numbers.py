"""Every number a function of the Python package takes is refused when it is NaN, +inf or
-inf, with an InputError (a ValueError) that names the parameter: the property the CLI's
hostile-input generator checks of every numeric option (crates/cli/tests/it/hostile.rs, class
`numeric`), here for the other face.

The parameters are found by inspection, not listed: every parameter of every public function
and of `Calibration`'s methods whose annotation holds `float` (a number, an optional number, a
pair or list of numbers, a number or a text). Each function needs a valid call here (`CALLS`);
the parameter under test is then set to each bad value in turn. A new function with a number
cannot pass untried: `test_every_function_with_a_number_has_a_call` fails until it has one.
Arrays (`ArrayLike`) are not in it: a NaN there marks a row that was not measured (a flagged
star passes through `Calibration.correct` with NaN outputs, test_correct.py)."""

import inspect
import math

import pytest

import instpol
from test_calibrate_stars import OFFSETS, write_catalogs
from test_night import INST as NIGHT_INST
from test_night import simulate as simulate_night

BAD = [math.nan, math.inf, -math.inf]

# The words the libraries' messages use for a parameter, where they name the quantity rather
# than the parameter (the CLI's messages and the Python package's are the libraries').
ALIASES = {
    "pointing_tol_arcsec": "pointing tolerance",
    "max_gap_min": "largest gap",
    "cl": "confidence level",
    "reject_alpha": "rejection probability",
}


def public_callables():
    """(name, function) of every public function and `Calibration` method."""
    out = []
    for name in instpol.__all__:
        obj = getattr(instpol, name)
        if inspect.isfunction(obj):
            out.append((name, obj))
    for name, m in inspect.getmembers(instpol.Calibration, inspect.isfunction):
        if not name.startswith("_"):
            out.append((f"Calibration.{name}", m))
    return out


def number_params(fn):
    """The parameters of `fn` whose annotation holds a float (not an array)."""
    out = []
    for p in inspect.signature(fn).parameters.values():
        a = p.annotation if isinstance(p.annotation, str) else getattr(p.annotation, "__name__", "")
        if "float" in a and "ArrayLike" not in a:
            out.append((p.name, a))
    return out


def bad_value(annotation, base, bad):
    """`bad` put where the parameter's number goes: alone, first of a pair, or in a list."""
    if isinstance(base, dict):
        return {k: (bad,) + tuple(v[1:]) for k, v in base.items()}
    if "Tuple" in annotation and isinstance(base, (list, tuple)):
        return (bad,) + tuple(base[1:])
    if "Sequence" in annotation:
        return [bad] + list(base[1:] if isinstance(base, (list, tuple)) else [])
    return bad


@pytest.fixture(scope="module")
def ctx(run, cal_v, sky_frames, star_frames, tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile_numbers")
    catalogs, _ = write_catalogs(d)
    simulate_night(run, d, "bias", [0, 22.5, 45, 67.5, 90], 58546.80, 1, ["CALIB", "BIAS", "IMAGE"], "BIAS")
    sky, sky_inst = sky_frames
    stars, star_inst = star_frames
    stokes_map = d / "map.fits"
    instpol.reduce(sky, instrument=str(sky_inst), bin=8, output=stokes_map)
    # An empty field of FORS1 in V, full size (the tiny one's bins are too few to calibrate on).
    empty = instpol.simulate(
        {"instrument": "fors1", "filter": "V", "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8},
         "effects": {"instpol": {"kind": "radial", "coeffs_percent": [0, 0.012, 0.046, 0.002]}, "photon_noise": True}},
        d / "empty_V",
    )
    empty_map = d / "empty_V.fits"
    instpol.reduce(empty["outputs"], instrument="fors1", output=empty_map)
    return {
        "dir": d,
        "cal": instpol.Calibration.load(cal_v),
        "catalogs": catalogs,
        "sky": (sky, str(sky_inst)),
        "stars": (stars, str(star_inst)),
        "map": stokes_map,
        "empty_map": empty_map,
        "raw": d / "raw",
    }


# A valid call of each function with a number: (function, keyword arguments), the numbers that
# the defaults leave out given (the parameter under test is set on top of these).
CALLS = {
    "stokes": lambda c: (
        instpol.stokes,
        dict(
            hwp_deg=[0, 22.5, 45, 67.5],
            f_o=[505000.0, 508660.25, 495000.0, 491339.75],
            f_e=[495000.0, 491339.75, 505000.0, 508660.25],
            kappa=0.0,
        ),
    ),
    "bias": lambda c: (instpol.bias, dict(p=0.01, sigma=0.003)),
    "reduce": lambda c: (
        instpol.reduce,
        dict(frames=c["sky"][0], instrument=c["sky"][1], bin=8, hwp_angles=[0.0, 22.5, 45.0, 67.5]),
    ),
    "catalog": lambda c: (
        instpol.catalog,
        dict(frames=c["stars"][0], instrument=c["stars"][1], fwhm=4.0, kappa=0.0),
    ),
    "calibrate": lambda c: (
        instpol.calibrate,
        dict(map=c["empty_map"], sky_p_percent=1.74, sky_chi_deg=-53.8, instrument="fors1"),
    ),
    "calibrate_stars": lambda c: (
        instpol.calibrate_stars,
        dict(
            catalogs=c["catalogs"], instrument="fors1", filter="V", offsets=OFFSETS, model="plane",
            interstellar=(0.5, 30.0),
        ),
    ),
    "scan": lambda c: (
        instpol.scan,
        dict(dirs=c["raw"], instrument=str(NIGHT_INST), products=c["dir"] / "products", sky={"NGC 1": (2.0, 30.0)}),
    ),
    "Calibration.correct": lambda c: (
        c["cal"].correct,
        dict(
            x=[0.1], y=[0.2], q=[0.01], u=[0.0], sigma_q=[1e-3], sigma_u=[1e-3], hwp_chi_offset_deg=0.0,
        ),
    ),
    "Calibration.correct_map": lambda c: (
        c["cal"].correct_map,
        dict(input=c["map"], output=c["dir"] / "corrected.fits", allow_mismatch=True),
    ),
}

# Numbers that cannot be tried from a valid call here, with why.
NOT_TRIED = {
    ("Calibration.correct_map", "parang_deg"): "needs a telescope model, which the demo's calibration has not",
    ("Calibration.correct_map", "rotator_deg"): "needs a telescope model fitted with rotator angles",
}


def cases():
    out = []
    for name, fn in public_callables():
        for param, annotation in number_params(fn):
            if (name, param) not in NOT_TRIED:
                out.append((name, param, annotation))
    return out


def test_every_function_with_a_number_has_a_call():
    missing = sorted({name for name, _, _ in cases() if name not in CALLS})
    assert not missing, f"functions with a number but no valid call in CALLS: {missing}"
    params = {(n, p) for n, p, _ in cases()}
    assert len(params) >= 20, sorted(params)
    for key in NOT_TRIED:
        fn = dict(public_callables())[key[0]]
        assert key[1] in dict(number_params(fn)), f"NOT_TRIED names {key}, which is no number parameter"


def test_the_valid_calls_work(ctx):
    for name, call in CALLS.items():
        fn, kwargs = call(ctx)
        fn(**kwargs)


@pytest.mark.parametrize("name,param,annotation", cases(), ids=lambda v: str(v))
def test_a_number_that_is_not_finite_is_refused_by_name(ctx, name, param, annotation):
    fn, kwargs = CALLS[name](ctx)
    default = inspect.signature(fn).parameters[param].default
    base = kwargs.get(param, default)
    for bad in BAD:
        args = dict(kwargs, **{param: bad_value(annotation, base, bad)})
        with pytest.raises(instpol.InputError) as e:
            fn(**args)
        words = str(e.value).lower()
        names = [param, param.replace("_", "-"), ALIASES.get(param, param)]
        assert any(n in words for n in names), f"{name}({param}={bad}): {words}"
