"""An instrument's constant response from standards (``IP MODEL = 'RESPONSE'``,
docs/calibration-file.md) read by ``Calibration.load`` and applied by ``correct``: the file is
written here with astropy from the specification, and the corrected values and their covariance
are computed here in numpy from the model (q, u)_true = R(k) ((q, u)_measured - (q0, u0)) / eta
and its Jacobians, written out independently of the library."""

import numpy as np
import pytest
from astropy.io import fits

import instpol
from conftest import same
from test_correct_map import v_map  # noqa: F401 (fixture)

Q0, U0, ETA, K_DEG, ZERO = 0.004, -0.003, 0.9, 3.0, 2.5
# Covariance of (q0, u0, eta, k) with k in rad.
COV = np.array([
    [1e-8, 2e-9, 0.0, 0.0],
    [2e-9, 1.2e-8, 0.0, 0.0],
    [0.0, 0.0, 4e-5, 1e-7],
    [0.0, 0.0, 1e-7, 2.5e-5],
])


def write(path, efficiency=ETA, instrument="CALCITE", zero=ZERO):
    h = fits.Header()
    for k, v in [("FORMAT VERSION", 1), ("INSTRUMENT", instrument), ("FILTER", "V"), ("MODEL", "RESPONSE"),
                 ("PLATE", "half_wave"), ("FRAME", "sky"), ("HWP CHI OFFSET DEG", zero), ("RE Q0", Q0),
                 ("RE U0", U0), ("RE EFFICIENCY", efficiency), ("RE OFFSET DEG", K_DEG)]:
        h[f"HIERARCH IP {k}"] = v
    for i in range(4):
        for j in range(i, 4):
            h[f"HIERARCH IP RE COV{i + 1}{j + 1}"] = COV[i, j]
    fits.PrimaryHDU(header=h).writeto(path)


def truth(q, u, var):
    """The inverse and its covariance, in numpy: A = R(k) / eta, B the Jacobian in the
    parameters."""
    k = np.radians(K_DEG)
    c, s = np.cos(2 * k), np.sin(2 * k)
    a = np.array([[c, -s], [s, c]]) / ETA
    t = a @ np.array([q - Q0, u - U0])
    b = np.column_stack([-a[:, 0], -a[:, 1], -t / ETA, 2 * np.array([-t[1], t[0]])])
    return t, a @ var @ a.T + b @ COV @ b.T


def test_a_response_file_is_read_and_applied(tmp_path):
    path = tmp_path / "response.fits"
    write(path)
    cal = instpol.Calibration.load(str(path))
    assert cal.model == "RESPONSE" and cal.instrument == "CALCITE" and cal.filter == "V"
    assert cal.hwp_chi_offset_deg == ZERO
    q, u, sq, su, cqu = np.array([0.03, -0.01]), np.array([0.012, 0.02]), 3e-4, 4e-4, 1e-8
    out = cal.correct(np.zeros(2), np.zeros(2), q, u, sq, su, cqu, hwp_chi_offset_deg=ZERO)
    for i in range(2):
        t, cov = truth(q[i], u[i], np.array([[sq**2, cqu], [cqu, su**2]]))
        np.testing.assert_allclose([out["q0"][i], out["u0"][i]], t, rtol=1e-12)
        np.testing.assert_allclose([out["sigma_q0"][i] ** 2, out["sigma_u0"][i] ** 2, out["cov_qu0"][i]],
                                   [cov[0, 0], cov[1, 1], cov[0, 1]], rtol=1e-9)
        np.testing.assert_allclose([out["q_inst"][i], out["u_inst"][i]], [Q0, U0], rtol=1e-15)
    ev = cal.evaluate(np.array([0.0, 1.0]), np.array([0.0, -1.0]))
    np.testing.assert_allclose(ev["q"], Q0)
    np.testing.assert_allclose(ev["sigma_u"], np.sqrt(COV[1, 1]))


def test_celestial_rows_and_other_setups(tmp_path):
    """Rows on the sky (turned by the position angle PA) are turned back, corrected and turned
    forward: the corrected chi of the same star differs by PA, its P is the same. Rows of another
    filter are refused as for any calibration; an efficiency above 1 is refused on loading."""
    path = tmp_path / "response.fits"
    write(path)
    cal = instpol.Calibration.load(str(path))
    pa = 37.5
    q, u = 0.02, 0.01
    c, s = np.cos(np.radians(2 * pa)), np.sin(np.radians(2 * pa))
    inst = cal.correct(0.0, 0.0, q, u, 1e-4, 1e-4, hwp_chi_offset_deg=ZERO)
    sky = cal.correct(0.0, 0.0, c * q - s * u, s * q + c * u, 1e-4, 1e-4, hwp_chi_offset_deg=ZERO, sky_pa_deg=pa)
    np.testing.assert_allclose(sky["p0"], inst["p0"], rtol=1e-12)
    np.testing.assert_allclose((sky["chi0_deg"] - inst["chi0_deg"] - pa + 90.0) % 180.0 - 90.0, 0.0, atol=1e-9)
    with pytest.raises(instpol.InputError, match="in filter R, the calibration of instrument CALCITE in filter V"):
        cal.correct(0.0, 0.0, q, u, 1e-4, 1e-4, instrument="CALCITE", filter="R")
    bad = tmp_path / "bad.fits"
    write(bad, efficiency=1.2)
    with pytest.raises(Exception, match="efficiency 1.2 must lie in"):
        instpol.Calibration.load(str(bad))


def test_a_map_is_corrected_as_by_the_cli_and_by_numpy(run, v_map, tmp_path):  # noqa: F811
    """A Stokes map (at the plate, a response of zero angle 0) through correct_map: the CLI's
    file bit for bit, and each valid bin's q0, u0 the numpy inverse of the response."""
    path = tmp_path / "response.fits"
    write(path, instrument="FORS1", zero=0.0)
    cli, py = tmp_path / "cli.fits", tmp_path / "py.fits"
    run("correct", "--cal", path, "--in", v_map, "--out", cli)
    m = instpol.Calibration.load(str(path)).correct_map(v_map, py)
    with fits.open(cli) as a, fits.open(py) as b:
        for e in ("Q", "U", "SIGMA_Q", "SIGMA_U", "COV_QU"):
            assert same(np.asarray(a[e].data, dtype=float), np.asarray(b[e].data, dtype=float)), e
        assert "constant response" in b[0].header["CORRMETH"]
    with fits.open(v_map) as h:
        q, u = h["Q"].data.ravel(), h["U"].data.ravel()
    ok = m.valid.ravel()
    t = np.array([truth(qi, ui, np.zeros((2, 2)))[0] for qi, ui in zip(q[ok], u[ok])])
    np.testing.assert_allclose(m.q.ravel()[ok], t[:, 0], rtol=1e-12, atol=1e-17)
    np.testing.assert_allclose(m.u.ravel()[ok], t[:, 1], rtol=1e-12, atol=1e-17)
