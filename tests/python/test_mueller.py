"""instpol.Calibration with a Mueller-field calibration (`instpol calibrate-mueller --out
CAL.fits`): the same numbers as `instpol correct` to the last bit, and the sky a field was
calibrated on given back when its own measured map is corrected as a catalog.

The four sky maps are written here with astropy in the Stokes-map format (docs: `instpol
reduce`), seen through a Mueller field built here in numpy: a diattenuation growing with the
radius followed by a stressed-lens-like retardance, neither taken from the package."""

import json

import numpy as np
import pytest
from astropy.io import fits

import instpol
from conftest import same
from test_correct import ADDED, cli_correct

NB, BIN, DET, SCALE = 32, 64, 2048, 0.2  # 32 x 32 bins of 64 px on a 2048 px FORS1 chip
SKIES = [(6.45, 68.4), (4.0, 10.0), (8.0, 130.0), (5.0, 100.0)]  # P (%), chi (deg): the general
# block (8 parameters) needs four skies not on one line in (q, u)


def centres():
    """Bin centres in arcmin from the detector centre (x along the row)."""
    c = ((np.arange(NB) + 0.5) * BIN - 0.5 - (DET - 1) / 2) * SCALE / 60
    return np.meshgrid(c, c)


def truth_block(x, y):
    """The linear (I, Q, U) block at (x, y) arcmin: a diattenuator of vector (2e-4 (x^2 - y^2),
    4e-4 x y) then a linear retarder of retardance 18 deg (r / 3.4')^2 with its axis along the
    radius (a stressed lens)."""
    dq, du = 2e-4 * (x * x - y * y), 4e-4 * x * y
    d = np.hypot(dq, du)
    s = np.sqrt(1 - d * d)
    n = x.shape
    D = np.zeros(n + (3, 3))
    D[..., 0, 0] = 1
    D[..., 0, 1] = D[..., 1, 0] = dq
    D[..., 0, 2] = D[..., 2, 0] = du
    w = np.divide(1 - s, d * d, out=np.full(n, 0.5), where=d > 0)
    D[..., 1, 1] = s + w * dq * dq
    D[..., 2, 2] = s + w * du * du
    D[..., 1, 2] = D[..., 2, 1] = w * dq * du
    delta = np.radians(18.0) * (x * x + y * y) / 3.4**2
    th = np.arctan2(y, x)
    c, sn, cd = np.cos(2 * th), np.sin(2 * th), np.cos(delta)
    R = np.zeros(n + (3, 3))
    R[..., 0, 0] = 1
    R[..., 1, 1] = c * c + sn * sn * cd
    R[..., 2, 2] = sn * sn + c * c * cd
    R[..., 1, 2] = R[..., 2, 1] = c * sn * (1 - cd)
    return R @ D


def measured(p_pct, chi_deg):
    """The (q, u) maps a sky of p, chi gives through the truth."""
    x, y = centres()
    t = 2 * np.radians(chi_deg)
    s = np.stack([np.ones_like(x), 0.01 * p_pct * np.cos(t) * np.ones_like(x), 0.01 * p_pct * np.sin(t) * np.ones_like(x)], -1)
    o = (truth_block(x, y) @ s[..., None])[..., 0]
    return o[..., 1] / o[..., 0], o[..., 2] / o[..., 0]


def write_map(path, q, u, sigma=3e-4):
    ph = fits.PrimaryHDU()
    h = ph.header
    h["MAPVERS"] = 1
    h["ORIGIN"] = "instpol test (astropy)"
    h["INSTRUME"] = "fors1"
    h["FILTER"] = "B"
    h["NHWP"] = 4
    for k, a in enumerate([0.0, 22.5, 45.0, 67.5]):
        h[f"HWPANG{k + 1}"] = a
    for k, v in [("BINSIZE", BIN), ("BINORGX", 0), ("BINORGY", 0), ("NBINX", NB), ("NBINY", NB),
                 ("PIXSCALE", SCALE), ("DETNX", DET), ("DETNY", DET)]:
        h[k] = v
    err = np.full_like(q, sigma)
    images = {"Q": q, "U": u, "SIGMA_Q": err, "SIGMA_U": err, "COV_QU": np.zeros_like(q), "SIGQ_PHOT": err,
              "SIGU_PHOT": err, "P": np.hypot(q, u), "CHI": np.degrees(0.5 * np.arctan2(u, q)) % 180,
              "INTENSITY": np.full_like(q, 1000.0), "INT_SNR": np.full_like(q, 100.0)}
    hdus = [ph] + [fits.ImageHDU(v.astype(">f8"), name=k) for k, v in images.items()]
    hdus += [fits.ImageHDU(np.full(q.shape, 4096, ">i4"), name="COVERAGE"),
             fits.ImageHDU(np.ones(q.shape, ">i4"), name="VALID")]
    fits.HDUList(hdus).writeto(path)


@pytest.fixture(scope="module")
def mueller_cal(run, tmp_path_factory):
    d = tmp_path_factory.mktemp("mueller")
    args = ["calibrate-mueller"]
    for k, (p, chi) in enumerate(SKIES):
        m = d / f"sky{k}.fits"
        write_map(m, *measured(p, chi))
        args += ["--field", f"{m}:{p}:{chi}"]
    out = d / "mueller_B.fits"
    j = json.loads(run(*args, "--general", "--deg", "4", "--out", out, "--json")[1])
    assert j["model"] == "general", j
    return out


def sky_catalog(p_pct, chi_deg, sigma=3e-4):
    x, y = centres()
    q, u = measured(p_pct, chi_deg)
    e = np.full(q.size, sigma)
    return {"x": x.ravel(), "y": y.ravel(), "q": q.ravel(), "u": u.ravel(), "sigma_q": e, "sigma_u": e}


def test_mueller_correct_is_the_cli_bit_for_bit(run, mueller_cal, tmp_path):
    c = instpol.Calibration.load(mueller_cal)
    assert c.model == "MUELLER" and c.mueller_model == "general" and c.hwp_chi_offset_deg == 0.0
    assert c.filter == "B" and c.instrument == "fors1" and c.telescope_bands == []
    cols = sky_catalog(*SKIES[1])
    rng = np.random.default_rng(16)
    cols["cov_qu"] = 0.2 * cols["sigma_q"] * cols["sigma_u"] * rng.uniform(-1, 1, cols["x"].size)
    cli = cli_correct(run, mueller_cal, cols, tmp_path, "--coords", "arcmin")
    py = c.correct(**cols, estimator="mas")
    for k in ADDED:
        assert same(py[k], cli[k]), k
    assert same(py["extrapolated"], cli["extrapolated"])
    assert cli["summary"]["mueller_model"] == c.mueller_model
    # evaluate: the field's instrumental (q, u) of unpolarized light, as correct's q_inst, u_inst.
    ev = c.evaluate(cols["x"], cols["y"])
    assert same(ev["q"], py["q_inst"]) and same(ev["u"], py["u_inst"]) and ev["inside"].all()


@pytest.mark.parametrize("sky", SKIES)
def test_each_calibrating_sky_comes_back(mueller_cal, sky):
    """The sky of every field, corrected through the field fitted to all four, is that sky:
    P and chi at every bin within the errors of the map (3e-4)."""
    c = instpol.Calibration.load(mueller_cal)
    r = c.correct(**sky_catalog(*sky))
    q0, u0 = 0.01 * sky[0] * np.cos(2 * np.radians(sky[1])), 0.01 * sky[0] * np.sin(2 * np.radians(sky[1]))
    pulls = np.concatenate([(r["q0"] - q0) / r["sigma_q0"], (r["u0"] - u0) / r["sigma_u0"]])
    assert np.abs(pulls).max() < 3, np.abs(pulls).max()
    # The uncorrected map is far from the sky: the test can fail.
    x, y = centres()
    qm, um = measured(*sky)
    assert np.abs(np.concatenate([(qm.ravel() - q0), (um.ravel() - u0)]) / 3e-4).max() > 10


def test_mueller_refusals_name_the_file(mueller_cal):
    c = instpol.Calibration.load(mueller_cal)
    cols = sky_catalog(*SKIES[0])
    with pytest.raises(instpol.InputError, match="holds a Mueller field, which is inverted exactly"):
        c.correct(**cols, method="first-order")
    with pytest.raises(instpol.InputError, match="Mueller field"):
        c.correct(**cols, parang_deg=10.0)


def test_rows_carrying_a_zero_angle_are_turned_back(run, mueller_cal, tmp_path):
    """A Mueller field lives in the maps' frame (no zero angle): rows whose chi carries a zero
    angle z (turned here with numpy by 2z, their covariance alike) and say so
    (hwp_chi_offset_deg=z) give the rows' own correction back to 1e-12, and the CLI does the
    same with a table's hwp_chi_offset_deg column, bit for bit."""
    c = instpol.Calibration.load(mueller_cal)
    cols = sky_catalog(*SKIES[1])
    ref = c.correct(**cols)
    z = np.radians(2.89)
    cz, sz = np.cos(2 * z), np.sin(2 * z)
    turned = dict(cols)
    turned["q"] = cz * cols["q"] - sz * cols["u"]
    turned["u"] = sz * cols["q"] + cz * cols["u"]
    vq, vu = cols["sigma_q"] ** 2, cols["sigma_u"] ** 2
    turned["sigma_q"] = np.sqrt(cz * cz * vq + sz * sz * vu)
    turned["sigma_u"] = np.sqrt(sz * sz * vq + cz * cz * vu)
    turned["cov_qu"] = cz * sz * (vq - vu)
    r = c.correct(**turned, hwp_chi_offset_deg=2.89)
    for k in ["q0", "u0", "sigma_q0", "sigma_u0"]:
        assert np.max(np.abs(r[k] - ref[k])) < 1e-12, k
    assert np.max(np.abs(c.correct(**turned)["q0"] - ref["q0"])) > 1e-4
    turned["hwp_chi_offset_deg"] = np.full(turned["x"].size, 2.89)
    cli = cli_correct(run, mueller_cal, turned, tmp_path, "--coords", "arcmin")
    del turned["hwp_chi_offset_deg"]
    py = c.correct(**turned, hwp_chi_offset_deg=2.89, estimator="mas")
    for k in ADDED:
        assert same(py[k], cli[k]), k


def test_mueller_correct_map_is_the_cli_bit_for_bit(run, mueller_cal, tmp_path):
    """A Stokes map through the Mueller field: the package's correct_map and `instpol correct`
    write the same map, and the map's calibrating sky comes back where the field is inside."""
    from test_correct_map import same_files

    m = tmp_path / "sky1.fits"
    write_map(m, *measured(*SKIES[1]))
    cli, py = tmp_path / "cli.fits", tmp_path / "py.fits"
    run("correct", "--cal", mueller_cal, "--in", m, "--out", cli)
    r = instpol.Calibration.load(mueller_cal).correct_map(m, py)
    same_files(cli, py)
    p, chi = SKIES[1]
    t = 2 * np.radians(chi)
    ok = r.valid
    pulls = np.concatenate([(r.q[ok] - 0.01 * p * np.cos(t)) / r.sigma_q[ok], (r.u[ok] - 0.01 * p * np.sin(t)) / r.sigma_u[ok]])
    assert np.abs(pulls).max() < 3, np.abs(pulls).max()
