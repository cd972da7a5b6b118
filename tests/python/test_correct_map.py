"""instpol.Calibration.correct_map against `instpol correct` on the same Stokes map file (every
extension read back with astropy, to the last bit, and the correction's header record), and its
q0, u0 against a numpy inversion of the paper's M_I written in test_correct.py."""

import numpy as np
import pytest
from astropy.io import fits

import instpol
from conftest import same
from test_correct import cal_v_offset, cal_v_telescope, numpy_exact_inversion  # noqa: F401 (fixtures)

EXTENSIONS = ["Q", "U", "SIGMA_Q", "SIGMA_U", "COV_QU", "SIGQ_PHOT", "SIGU_PHOT", "P", "CHI", "INTENSITY",
              "INT_SNR", "COVERAGE", "VALID"]
RECORD = ["INSTCORR", "CORRMETH", "CORRHWP", "TELMODEL", "TELBAND", "TELROT", "PARANG1", "PARANG2"]


@pytest.fixture(scope="module")
def v_map(sky_frames, tmp_path_factory):
    """The tiny FORS1's V sky (p = 6.45 %) reduced to a Stokes map file by the package."""
    frames, inst = sky_frames
    out = tmp_path_factory.mktemp("map") / "map_V.fits"
    instpol.reduce(frames, instrument=inst, bin=16, output=out)
    return out


def same_files(a, b):
    """Every extension's data bit for bit, and the correction's primary keywords alike."""
    with fits.open(a) as x, fits.open(b) as y:
        for e in EXTENSIONS:
            assert same(np.asarray(x[e].data, dtype=float), np.asarray(y[e].data, dtype=float)), e
        for k in RECORD:
            assert x[0].header.get(k) == y[0].header.get(k), k


def test_correct_map_is_the_cli_bit_for_bit(run, v_map, cal_v_offset, tmp_path):  # noqa: F811
    cli, py = tmp_path / "cli.fits", tmp_path / "py.fits"
    run("correct", "--cal", cal_v_offset, "--in", v_map, "--out", cli)
    c = instpol.Calibration.load(cal_v_offset)
    m = c.correct_map(v_map, py)
    same_files(cli, py)
    with fits.open(py) as h:
        assert h[0].header["INSTCORR"] == cal_v_offset.name
        assert h[0].header["CORRHWP"] == 3.5
        assert "eq:instpol" in h[0].header["CORRMETH"]
        assert same(h["Q"].data.ravel(), m.q.ravel())
    r = m.correction
    assert r["n_bins"] == int(m.valid.sum()) > 0 and r["n_extrapolated"] == 0
    assert r["hwp_chi_offset_deg"] == 3.5 and r["calibration"] == cal_v_offset.name
    # Independent: the exact inversion written with numpy, from the instrumental (q, u) the
    # calibration gives at the bin centres and the measured map.
    with fits.open(v_map) as h:
        q, u = h["Q"].data.ravel(), h["U"].data.ravel()
    ok = m.valid.ravel()
    inst = c.evaluate(m.x_arcmin.ravel()[ok], m.y_arcmin.ravel()[ok])
    q0, u0 = numpy_exact_inversion(inst["q"], inst["u"], q[ok], u[ok], 3.5)
    assert np.max(np.abs(m.q.ravel()[ok] - q0)) < 1e-15
    assert np.max(np.abs(m.u.ravel()[ok] - u0)) < 1e-15


def test_first_order_is_the_cli_bit_for_bit(run, v_map, cal_v_offset, tmp_path):  # noqa: F811
    cli, py = tmp_path / "cli.fits", tmp_path / "py.fits"
    run("correct", "--cal", cal_v_offset, "--in", v_map, "--out", cli, "--method", "first-order")
    instpol.Calibration.load(cal_v_offset).correct_map(v_map, py, method="first-order")
    same_files(cli, py)


def test_correct_map_refuses(v_map, cal_v, cal_b, tmp_path):
    c = instpol.Calibration.load(cal_v)
    out = tmp_path / "once.fits"
    c.correct_map(v_map, out)
    # A corrected map is not corrected again.
    with pytest.raises(instpol.InputError, match="already corrected"):
        c.correct_map(out, tmp_path / "twice.fits")
    # Another filter's calibration, unless asked.
    with pytest.raises(instpol.InputError, match="calibrates FORS1 B"):
        instpol.Calibration.load(cal_b).correct_map(v_map)
    instpol.Calibration.load(cal_b).correct_map(v_map, allow_mismatch=True)
    # No writing over an input; telescope options without a telescope model.
    with pytest.raises(instpol.InputError, match="refusing to write over an input"):
        c.correct_map(v_map, v_map)
    with pytest.raises(instpol.InputError, match="holds none"):
        c.correct_map(v_map, parang_deg=(10, 20))
    with pytest.raises(instpol.InputError, match="method 'best'"):
        c.correct_map(v_map, method="best")
    with pytest.raises(instpol.InputError, match="not a Stokes map|cannot open|MAPVERS"):
        c.correct_map(cal_v)
    assert not (tmp_path / "twice.fits").exists()


def test_telescope_chain_on_a_map_is_the_cli_bit_for_bit(run, v_map, cal_v, cal_v_telescope, tmp_path):  # noqa: F811
    """The field then the telescope over the exposures' one track (--parang START,END), as
    `instpol correct` does (the map is the tiny FORS1's, the chain EFOSC2's: allowed by
    --allow-mismatch, what is compared is the arithmetic and the record)."""
    c = instpol.Calibration.load(cal_v_telescope)
    with pytest.raises(instpol.InputError, match="parallactic angle"):
        c.correct_map(v_map, allow_mismatch=True)
    cli, py = tmp_path / "cli.fits", tmp_path / "py.fits"
    run("correct", "--cal", cal_v_telescope, "--in", v_map, "--out", cli, "--parang", "10,25", "--allow-mismatch")
    m = c.correct_map(v_map, py, parang_deg=(10, 25), allow_mismatch=True)
    same_files(cli, py)
    r = m.correction
    assert r["telescope_model"] == "wiersema" and r["telescope_band"] == "V"
    assert r["parang_deg"] == pytest.approx((10.0, 25.0), abs=1e-12)
    with fits.open(py) as h:
        assert h[0].header["TELMODEL"] == "wiersema" and h[0].header["CORRHWP"] == 0.0
        assert h[0].header["PARANG1"] == pytest.approx(10.0, abs=1e-12)
    with pytest.raises(instpol.InputError, match="band 'B'"):
        c.correct_map(v_map, parang_deg=(10, 25), band="B", allow_mismatch=True)
    with pytest.raises(instpol.InputError, match="parang_deg"):
        c.correct_map(v_map, parang_deg=(10, 20, 30), allow_mismatch=True)
    # The telescope term is there: the chain's map differs from the field's alone by the M3's
    # few per cent.
    field = instpol.Calibration.load(cal_v).correct_map(v_map)
    ok = field.valid
    assert np.median(np.hypot(m.q[ok] - field.q[ok], m.u[ok] - field.u[ok])) > 0.01
