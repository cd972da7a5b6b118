"""instpol.calibrate_stars against `instpol calibrate-stars --json` on the same catalogs (the
same library call: the same numbers to the bit) and against the field the catalogs were drawn
from: 150 stars over 4 dithered pointings of FORS1 through a plane field (q = 0.1 % + 0.03 % x
- 0.02 % y, u = -0.04 % + 0.01 % x + 0.025 % y), 15 of them polarized at 3 %, each measurement
with 0.05 % Gaussian errors drawn here (numpy, seeded)."""

import json
import os

import numpy as np
import pytest

import instpol
from conftest import same

OFFSETS = [(0.0, 0.0), (0.6, 0.25), (-0.35, 0.55), (0.3, -0.6)]
PLANE_Q = (1e-3, 3e-4, -2e-4)
PLANE_U = (-4e-4, 1e-4, 2.5e-4)
SIGMA = 5e-4


def write_catalogs(d):
    rng = np.random.default_rng(5)
    n = 150
    sky = rng.uniform(-3.0, 3.0, size=(n, 2))
    own = np.zeros((n, 2))
    chi = rng.uniform(0, np.pi, 15)
    own[:15] = 0.03 * np.stack([np.cos(2 * chi), np.sin(2 * chi)], 1)
    files = []
    for k, (dx, dy) in enumerate(OFFSETS):
        x, y = sky[:, 0] - dx, sky[:, 1] - dy
        keep = (np.abs(x) < 3.41) & (np.abs(y) < 3.41)
        q = PLANE_Q[0] + PLANE_Q[1] * x + PLANE_Q[2] * y + own[:, 0] + rng.normal(0, SIGMA, n)
        u = PLANE_U[0] + PLANE_U[1] * x + PLANE_U[2] * y + own[:, 1] + rng.normal(0, SIGMA, n)
        lines = ["id,x_arcmin,y_arcmin,q,u,sigma_q,sigma_u,hwp_chi_offset_deg"]
        for i in np.flatnonzero(keep):
            lines.append(f"{i + 1},{float(x[i])!r},{float(y[i])!r},{float(q[i])!r},{float(u[i])!r},{SIGMA},{SIGMA},0")
        p = d / f"p{k + 1}.csv"
        p.write_text("\n".join(lines) + "\n")
        files.append(p)
    return files, sky[:15]


def test_calibrate_stars_is_the_cli_and_finds_the_plane(tmp_path, run):
    files, polarized = write_catalogs(tmp_path)
    out = tmp_path / "cal_plane.fits"
    s = instpol.calibrate_stars(files, "fors1", filter="V", model="plane", interstellar="zero",
                                offsets=OFFSETS, out=out)
    args = ["calibrate-stars", *files, "--filter", "V", "--model", "plane", "--interstellar", "zero",
            "--out", tmp_path / "cli.fits", "--json"]
    for dx, dy in OFFSETS:
        args += ["--offset", f"{dx},{dy}"]
    code, stdout, err = run(*args)
    assert code == 0, err
    cli = json.loads(stdout)
    for k in ("coefficients", "chi2_dof", "rms_residual", "n_bins_used"):
        assert same(s[k], cli[k]), k
    for k in ("q", "u", "sigma_q", "sigma_u"):
        assert same(s["poly"][k], cli["poly"][k]), k
    assert [r["id"] for r in s["rejected"]] == [r["id"] for r in cli["rejected"]]
    # The plane within errors, every polarized star named.
    poly = s["poly"]
    for k in range(3):
        assert abs(poly["q"][k] - PLANE_Q[k]) < 3 * poly["sigma_q"][k], (k, poly)
        assert abs(poly["u"][k] - PLANE_U[k]) < 3 * poly["sigma_u"][k], (k, poly)
    named = np.array([[r["x_arcmin"], r["y_arcmin"]] for r in s["rejected"]])
    for x, y in polarized:
        assert np.min(np.hypot(named[:, 0] - x, named[:, 1] - y)) < 1e-6, (x, y)
    # The file is a calibration the package loads.
    assert instpol.Calibration.load(out).model == "POLY"


def test_calibrate_stars_refusals(tmp_path):
    files, _ = write_catalogs(tmp_path)
    with pytest.raises(instpol.InputError, match="constant term"):
        instpol.calibrate_stars(files, "fors1", filter="V", model="plane", offsets=OFFSETS)
    with pytest.raises(instpol.InputError, match="interstellar"):
        instpol.calibrate_stars(files, "fors1", filter="V", interstellar="some")
    with pytest.raises(instpol.InputError, match="2 offsets for 4 catalogs"):
        instpol.calibrate_stars(files, "fors1", filter="V", offsets=OFFSETS[:2])
    with pytest.raises(instpol.InputError, match="refusing to write over an input"):
        instpol.calibrate_stars(files, "fors1", filter="V", interstellar="zero", offsets=OFFSETS, out=files[0])


def test_the_same_catalog_under_two_names_is_one_input(tmp_path):
    """A copy, a hard link or a symlink of a catalog beside it is refused naming both; a
    catalog with every row written twice gives the numbers of the catalog written once, with a
    warning naming the repeats (counted twice, the errors would shrink by sqrt(2))."""
    files, _ = write_catalogs(tmp_path)
    copy, link, sym = tmp_path / "copy.csv", tmp_path / "link.csv", tmp_path / "sym.csv"
    copy.write_bytes(files[0].read_bytes())
    os.link(files[0], link)
    os.symlink(files[0], sym)
    for other in (files[0], copy, link, sym):
        with pytest.raises(instpol.InputError, match="given once") as e:
            instpol.calibrate_stars([files[0], other], "fors1", filter="V", model="plane", interstellar="zero")
        assert other.name in str(e.value) and files[0].name in str(e.value)
    lines = files[0].read_text().splitlines()
    twice = tmp_path / "twice.csv"
    twice.write_text("\n".join(lines + lines[1:]) + "\n")
    once = instpol.calibrate_stars([files[0]], "fors1", filter="V", model="plane", interstellar="zero")
    again = instpol.calibrate_stars([twice], "fors1", filter="V", model="plane", interstellar="zero")
    assert again["poly"]["sigma_q"] == once["poly"]["sigma_q"]
    assert any("repeat" in w and "twice.csv row" in w for w in again["warnings"]), again["warnings"]


def test_catalogs_of_another_filter_are_refused_unless_allowed(tmp_path):
    """A catalog whose keywords say filter I, for a V calibration, raises InputError naming
    both, as instpol calibrate-stars refuses it; allow_mismatch=True uses it, with the numbers
    of the same catalog that says nothing."""
    files, _ = write_catalogs(tmp_path)
    said = tmp_path / "said_i.csv"
    said.write_text("# INSTRUME = FORS1\n# FILTER = I\n" + files[0].read_text())
    kw = dict(filter="V", model="plane", interstellar="zero")
    with pytest.raises(instpol.InputError, match="filter I") as e:
        instpol.calibrate_stars([said], "fors1", **kw)
    assert "said_i.csv" in str(e.value) and "filter V" in str(e.value)
    forced = instpol.calibrate_stars([said], "fors1", allow_mismatch=True, **kw)
    plain = instpol.calibrate_stars([files[0]], "fors1", **kw)
    assert forced["poly"]["q"] == plain["poly"]["q"]
