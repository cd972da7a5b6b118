"""instpol.simulate and instpol.calibrate against `instpol simulate` and `instpol calibrate
--map --json` (the same library calls: the same frames, bit for bit, and the same fit), and
against what the frames were simulated with: the paper's V field (section 11 [sec:fors1],
p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3 %) recovered within its errors."""

import json

import numpy as np
import pytest

import instpol
from conftest import same

SCENE = {
    "instrument": "fors1", "filter": "V", "hwp_angles_deg": [0, 22.5, 45, 67.5], "seed": 102,
    "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8},
    "effects": {"instpol": {"kind": "radial", "coeffs_percent": [0, 0.012, 0.046, 0.002]},
                "photon_noise": True, "read_noise": True},
}
SCENE_TOML = """instrument = "fors1"
filter = "V"
hwp_angles_deg = [0, 22.5, 45, 67.5]
seed = 102
[sky]
brightness_e = 12000
p = 0.0174
chi_deg = -53.8
[effects]
instpol = { kind = "radial", coeffs_percent = [0, 0.012, 0.046, 0.002] }
photon_noise = true
read_noise = true
"""


@pytest.fixture(scope="module")
def frames(run, tmp_path_factory):
    """The scene simulated three ways: by the CLI from a file, by Python from the file and
    from the dict."""
    d = tmp_path_factory.mktemp("simulate")
    scene = d / "scene.toml"
    scene.write_text(SCENE_TOML)
    run("simulate", scene, "--out", d / "cli")
    from_file = instpol.simulate(scene, d / "file")
    from_dict = instpol.simulate(SCENE, d / "dict")
    return d, sorted((d / "cli").glob("*.fits")), from_file, from_dict


def test_simulate_writes_the_clis_frames(frames):
    from astropy.io import fits

    d, cli, from_file, from_dict = frames
    assert [p.name for p in cli] == [p.split("/")[-1] for p in from_file["outputs"]]
    assert from_file["truth_output"].endswith("truth.json")
    for c, f, g in zip(cli, from_file["outputs"], from_dict["outputs"]):
        with fits.open(c) as a, fits.open(f) as b, fits.open(g) as e:
            assert same(a[0].data, b[0].data) and same(a[0].data, e[0].data), c.name
            for key in ("HIERARCH ESO INS RETA2 POSANG", "HIERARCH ESO INS FILT1 NAME", "EXPTIME"):
                assert a[0].header[key] == b[0].header[key] == e[0].header[key], key


def test_simulate_refuses_bad_scenes_and_overwriting_its_inputs(frames, tmp_path):
    with pytest.raises(instpol.InputError, match="unknown field"):
        instpol.simulate(dict(SCENE, colour="blue"), tmp_path / "x")
    with pytest.raises(instpol.InputError, match="exposure_s = nan: not a finite number"):
        instpol.simulate(dict(SCENE, seed=1, exposure_s=float("nan")), tmp_path / "y")
    scene = tmp_path / "frame_00_hwp000.0.fits"
    scene.write_text(SCENE_TOML)
    with pytest.raises(instpol.InputError):
        instpol.simulate(scene, tmp_path)
    assert scene.read_text() == SCENE_TOML


def test_calibrate_is_the_cli_and_finds_the_papers_field(frames, run):
    d, cli, _, _ = frames
    instpol.reduce([str(p) for p in cli], "fors1", output=d / "map.fits")
    py = instpol.calibrate(d / "map.fits", 1.74, -53.8, "fors1", out=d / "cal_py.fits")
    _, out, _ = run("calibrate", "--map", d / "map.fits", "--instrument", "fors1", "--sky-p", "1.74",
                    "--sky-chi", "-53.8", "--out", d / "cal_cli.fits", "--json")
    cli_fit = json.loads(out)
    for k in ("coefficients", "sigma_coefficients", "rms_residual", "chi2_dof", "n_bins_used", "polar_angle_slope"):
        assert same(py[k], cli_fit[k]), k
    # The paper's polynomial (fractions per arcmin^k) within 3 sigma of the fit.
    pulls = (np.array(py["coefficients"]) - [0.012e-2, 0.046e-2, 0.002e-2]) / np.array(py["sigma_coefficients"])
    assert np.all(np.abs(pulls) < 3), pulls
    a = instpol.Calibration.load(d / "cal_py.fits").evaluate([1.0, 3.0], [2.0, -1.0])
    b = instpol.Calibration.load(d / "cal_cli.fits").evaluate([1.0, 3.0], [2.0, -1.0])
    assert same(a["q"], b["q"]) and same(a["u"], b["u"])


def test_calibrate_refuses_bad_options(frames):
    d = frames[0]
    with pytest.raises(instpol.InputError, match="sky_p_percent"):
        instpol.calibrate(d / "map.fits", float("nan"), -53.8, "fors1")
    with pytest.raises(instpol.InputError, match="radial|poly|plane|model"):
        instpol.calibrate(d / "map.fits", 1.74, -53.8, "fors1", model="spline")
    with pytest.raises(instpol.InputError, match="sector"):
        instpol.calibrate(d / "map.fits", 1.74, -53.8, "fors1", exclude=["sector:10"])
    with pytest.raises(instpol.FileError):
        instpol.calibrate(d / "no-such-map.fits", 1.74, -53.8, "fors1")
