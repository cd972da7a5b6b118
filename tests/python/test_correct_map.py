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


NASMYTH = """
[telescope]
focus = "nasmyth"
site_latitude_deg = -29.26
parang_start_keyword = "HIERARCH ESO TEL PARANG START"
parang_end_keyword = "HIERARCH ESO TEL PARANG END"
rotator_keyword = "HIERARCH ESO ADA POSANG"

[[telescope.mirrors]]
name = "M3"
metal = "aluminium"
aoi_deg = 45.0
"""


def test_reduce_records_each_exposure_and_correct_map_undoes_it(run, tmp_path):
    """Frames of a polarized sky seen through an M3 (the tiny FORS1 put on a Nasmyth focus,
    simulated with each exposure's parallactic angles in its header): the package's reduce
    records every exposure's HWP angle and track as `instpol reduce` does (and as the frames'
    headers say, read with astropy), and correct_map undoes the telescope exposure by
    exposure, bit for bit the CLI's file."""
    tel, inst = nasmyth_setup(run, tmp_path, "the exposure-by-exposure map correction was not compared")
    scene = tmp_path / "scene.toml"
    scene.write_text(
        f'instrument = "{inst}"\nfilter = "V"\nseed = 5\nexposure_s = 20\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n'
        "[output]\nbitpix = -32\n[sky]\nbrightness_e = 20000.0\np = 0.02\nchi_deg = 30\n"
        "[telescope]\nfactor = 0.86\noffset_deg = 40\ndec_deg = -40\nha_start_deg = 30\noverhead_s = 5\n"
    )
    run("simulate", scene, "--out", tmp_path / "frames")
    frames = sorted((tmp_path / "frames").glob("*.fits"))
    py_map, cli_map = tmp_path / "py_map.fits", tmp_path / "cli_map.fits"
    instpol.reduce(frames, instrument=inst, bin=16, output=py_map)
    run("reduce", *frames, "--instrument", inst, "--bin", "16", "--out", cli_map)
    with fits.open(py_map) as a, fits.open(cli_map) as b:
        ha, hb = a[0].header, b[0].header
        assert ha["NEXPTRK"] == hb["NEXPTRK"] == len(frames) == 4
        keys = ["PARANG1", "PARANG2"] + [f"{k}{i}" for i in range(1, 5) for k in ("XHWP", "XPAS", "XPAE")]
        for k in keys:
            assert ha[k] == hb[k], k
        starts = sorted(fits.getheader(f)["HIERARCH ESO TEL PARANG START"] for f in frames)
        assert sorted(ha[f"XPAS{i}"] for i in range(1, 5)) == pytest.approx(starts, abs=1e-9)
        assert ha["XPAS4"] != ha["XPAS1"]
    c = instpol.Calibration.load(tel)
    py_corr, cli_corr = tmp_path / "py_corr.fits", tmp_path / "cli_corr.fits"
    run("correct", "--cal", tel, "--in", cli_map, "--out", cli_corr)
    m = c.correct_map(py_map, py_corr)
    same_files(cli_corr, py_corr)
    assert "exposure by exposure, 4" in m.correction["method"]
    # One track for the set (parang_deg) is another correction, by the exposures' spread.
    with fits.open(py_map) as h:
        track = (h[0].header["PARANG1"], h[0].header["PARANG2"])
    one = c.correct_map(py_map, parang_deg=track)
    ok = m.valid
    assert "exposure by exposure" not in one.correction["method"]
    assert np.max(np.abs(one.q[ok] - m.q[ok])) > 1e-6


EIGHT = "[0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]"


def meridian_star(run, tmp_path, inst, seed, hwp_angles, effects=""):
    """Frames of one star through the M3 of the Nasmyth `inst` (NASMYTH), observed through the
    meridian 5 deg from the zenith (60 s exposures at `hwp_angles`, a TOML list), simulated by
    `instpol simulate`: the frames' paths in time order."""
    scene = tmp_path / "stars.toml"
    scene.write_text(
        f'instrument = "{inst}"\nfilter = "V"\nseed = {seed}\nexposure_s = 60\nhwp_angles_deg = {hwp_angles}\n'
        '[output]\nbitpix = -64\n[[stars]]\nx = 64\ny = 34\ncoords = "pixel"\nflux_e = 4e6\nfwhm_arcsec = 1.6\n'
        f"{effects}[telescope]\nfactor = 0.86\noffset_deg = 40\ndec_deg = -24\nha_start_deg = -2.5\noverhead_s = 20\n"
    )
    run("simulate", scene, "--out", tmp_path / "stars")
    return sorted((tmp_path / "stars").glob("*.fits"))


def nasmyth_setup(run, tmp_path, what):
    """The tiny FORS1 put on a Nasmyth focus (its [telescope] section replaced by NASMYTH), and a
    telescope model fitted to V standards as that instrument measured them (`instpol
    fit-standards --instrument` it: a model is of its instrument, and correcting another
    instrument's data with it is refused)."""
    from conftest import tiny_fors1
    from test_correct import v_standards

    std = v_standards(tmp_path, what)
    tel = tmp_path / "tel_V.fits"
    text = tiny_fors1(tmp_path).read_text()
    head, _, rest = text.partition("[telescope]")
    assert rest, "instruments/fors1.toml no longer has a [telescope] section"
    # The FORS1 [telescope] section (the Cassegrain focus) is the file's last: replaced whole.
    assert "\n[" not in rest.replace("\n[[telescope", ""), "a section follows [telescope] in fors1.toml"
    inst = tmp_path / "nasmyth.toml"
    inst.write_text(head + NASMYTH)
    run("fit-standards", std, "--instrument", inst, "--model", "wiersema", "--output", tel)
    return tel, inst


def test_catalog_with_a_telescope_model_is_the_cli_catalog(run_json, run, tmp_path):
    """catalog(frames, cal=...) with a telescope model: every corrected column as `instpol
    catalog --cal --json` gives it, bit for bit, the telescope undone exposure by exposure from
    the frames' headers (8 exposures); the unpolarized star comes back within 4 sigma of 0."""
    tel, inst = nasmyth_setup(run, tmp_path, "the catalog's telescope correction was not compared")
    frames = meridian_star(run, tmp_path, inst, 7, EIGHT, "[effects]\nphoton_noise = true\n")
    args = ["--fwhm", "4", "--aperture", "10", "--annulus", "14,24"]
    j = run_json("catalog", *frames, "--instrument", inst, *args, "--cal", tel)
    c = instpol.catalog(frames, instrument=str(inst), fwhm=4.0, aperture=10.0, annulus=(14.0, 24.0), cal=tel)
    assert j["telescope_exposures"] == c["telescope_exposures"] == 8
    assert j["telescope_model"] == c["telescope_model"] and j["telescope_band"] == c["telescope_band"]
    rows = j["corrected"]
    assert len(rows) == len(c["q0"]) == 1
    for k in ["q0", "u0", "sigma_q0", "sigma_u0", "cov_qu0", "p0", "sigma_p0", "chi0_deg", "sigma_chi0_deg",
              "q_inst", "u_inst"]:
        assert same(c[k], [r[k] for r in rows]), k
    # The star is unpolarized: the telescope's few percent removed, within the errors.
    assert np.hypot(c["q"][0], c["u"][0]) > 0.01
    assert abs(c["q0"][0]) < 4 * c["sigma_q0"][0] and abs(c["u0"][0]) < 4 * c["sigma_u0"][0]


def test_catalog_tables_record_the_exposures_angles_for_astropy(run, tmp_path):
    """`instpol catalog --out` in ECSV, FITS and VOTable records its exposures' telescope
    angles as the table's numbers, read here with astropy: the ECSV header's meta, the FITS
    table HDU's keywords, the VOTable's PARAMs, equal to the frames' headers (PARANG START/END
    of each exposure); `instpol correct` then needs no --parang."""
    from astropy.io.votable import parse
    from astropy.table import Table

    _, inst = nasmyth_setup(run, tmp_path, "the catalog tables' recorded angles were not checked")
    frames = meridian_star(run, tmp_path, inst, 8, "[0, 22.5, 45, 67.5]")
    starts = [fits.getheader(f)["HIERARCH ESO TEL PARANG START"] for f in frames]
    ends = [fits.getheader(f)["HIERARCH ESO TEL PARANG END"] for f in frames]
    hwp = [fits.getheader(f)["HIERARCH ESO INS RETA2 POSANG"] for f in frames]
    metas = {}
    for ext in ["ecsv", "fits", "vot"]:
        out = tmp_path / f"stars.{ext}"
        run("catalog", *frames, "--instrument", inst, "--fwhm", "4", "--aperture", "10", "--annulus", "14,24",
            "--out", out)
        if ext == "ecsv":
            metas[ext] = dict(Table.read(out, format="ascii.ecsv").meta)
        elif ext == "fits":
            metas[ext] = dict(fits.getheader(out, "CATALOG"))
        else:
            # The numbers' PARAMs (the catalog's product keywords are text PARAMs).
            metas[ext] = {p.name: float(p.value) for p in parse(str(out)).get_first_table().params
                          if p.datatype == "double"}
    for ext, m in metas.items():
        assert m["NEXPTRK"] == 4, ext
        got = sorted((m[f"XHWP{k}"], m[f"XPAS{k}"], m[f"XPAE{k}"]) for k in range(1, 5))
        want = sorted(zip(hwp, starts, ends))
        assert np.allclose(got, want, atol=1e-9, rtol=0), (ext, got, want)
        assert m["PARANG1"] == pytest.approx(starts[0], abs=1e-9), ext
        assert m["PARANG2"] == pytest.approx(ends[-1], abs=1e-9), ext


def test_correct_with_a_catalogs_recorded_angles_is_catalog_cal(run, tmp_path):
    """catalog(frames)["recorded_angles"] given to Calibration.correct(recorded=...) undoes the
    telescope exposure by exposure: the corrected columns of catalog(frames, cal=...) to 1e-12
    (the angles pass through degrees), 8 exposures; recorded with parang_deg, or on a
    calibration without a telescope model, raises InputError."""
    tel, inst = nasmyth_setup(run, tmp_path, "correct(recorded=) was not compared")
    frames = meridian_star(run, tmp_path, inst, 9, EIGHT)
    args = dict(instrument=str(inst), fwhm=4.0, aperture=10.0, annulus=(14.0, 24.0))
    cat = instpol.catalog(frames, **args)
    ref = instpol.catalog(frames, cal=tel, **args)
    rec = cat["recorded_angles"]
    assert rec is not None and len(rec["exposures"]) == 8
    c = instpol.Calibration.load(tel)
    r = c.correct(cat["x_arcmin"], cat["y_arcmin"], cat["q"], cat["u"], cat["sigma_q"], cat["sigma_u"],
                  cat["cov_qu"], recorded=rec)
    assert r["telescope_exposures"] == 8
    for k in ["q0", "u0", "sigma_q0", "sigma_u0"]:
        assert np.max(np.abs(r[k] - ref[k])) < 1e-12, k
    with pytest.raises(instpol.InputError, match="not both"):
        c.correct(cat["x_arcmin"], cat["y_arcmin"], cat["q"], cat["u"], cat["sigma_q"], cat["sigma_u"],
                  parang_deg=[10.0], recorded=rec)


def test_recorded_angles_carry_the_zero_angle_of_the_catalog(run, tmp_path):
    """Through a half-wave plate whose zero angle is 7 deg (the instrument's V filter says so,
    the frames are taken through it), catalog()'s q, u carry that angle and its
    recorded_angles say so (hwp_chi_offset_deg); Calibration.correct(recorded=...) with a
    telescope model alone then gives catalog(cal=...)'s corrected columns to 1e-12 (the
    exposures' plate angles taken in the sky frame: without the recorded zero angle they
    differ by 9e-4)."""
    tel, inst = nasmyth_setup(run, tmp_path, "correct(recorded=) through a zero angle was not compared")
    v = 'name = "V"\naliases = ["V_BESS"]\nlambda_eff_nm = 554.0\n'
    text = inst.read_text()
    assert v in text, "the V filter of FORS1's file"
    inst.write_text(text.replace(v, v + "hwp_chi_offset_deg = 7.0\n"))
    frames = meridian_star(run, tmp_path, inst, 11, EIGHT, "[effects]\nhwp_chi_offset_from_filter = true\n")
    args = dict(instrument=str(inst), fwhm=4.0, aperture=10.0, annulus=(14.0, 24.0))
    cat = instpol.catalog(frames, **args)
    assert cat["chi_offset_deg"] == 7.0
    rec = cat["recorded_angles"]
    assert rec["hwp_chi_offset_deg"] == 7.0
    ref = instpol.catalog(frames, cal=tel, **args)
    c = instpol.Calibration.load(tel)
    cols = [cat[k] for k in ("x_arcmin", "y_arcmin", "q", "u", "sigma_q", "sigma_u", "cov_qu")]
    r = c.correct(*cols, recorded=rec)
    for k in ["q0", "u0", "sigma_q0", "sigma_u0"]:
        assert np.max(np.abs(r[k] - ref[k])) < 1e-12, k
    # The plate's zero angle matters: recorded angles that do not say it give other numbers.
    bare = {k: v for k, v in rec.items() if k != "hwp_chi_offset_deg"}
    r0 = c.correct(*cols, recorded=bare)
    d0 = np.max(np.hypot(r0["q0"] - r["q0"], r0["u0"] - r["u0"]))
    assert d0 > 1e-4


def test_a_wavelength_band_corrects_the_filter_at_that_wavelength(run, v_map, tmp_path):
    """A telescope model fitted from the real EFOSC2 V standards without a filter column names
    its band by wavelength (0.550um); an EFOSC2 V map is corrected with it without
    allow_mismatch (the band is the filter at that wavelength), as the CLI does, bit for bit;
    a B map is refused naming the band."""
    from test_correct import EFOSC2

    src = EFOSC2 / "pv_standards.txt"
    if not src.is_file():
        pytest.skip(f"*** SKIPPED LOUDLY: {src} not found: the wavelength band was not checked ***")
    tel = tmp_path / "tel.fits"
    run("fit-standards", src, "--instrument", "efosc2", "--model", "wiersema", "--output", tel)
    c = instpol.Calibration.load(tel)
    assert c.telescope_bands == ["0.550um"]
    maps = {}
    for f in ["V", "B"]:
        maps[f] = tmp_path / f"efosc2_{f}.fits"
        with fits.open(v_map) as h:
            h[0].header["INSTRUME"] = "EFOSC2"
            h[0].header["FILTER"] = f
            h.writeto(maps[f])
    cli, py = tmp_path / "cli.fits", tmp_path / "py.fits"
    run("correct", "--cal", tel, "--in", maps["V"], "--out", cli, "--parang", "10,25")
    c.correct_map(maps["V"], py, parang_deg=(10, 25))
    same_files(cli, py)
    with fits.open(py) as h:
        assert h[0].header["TELBAND"] == "0.550um"
    with pytest.raises(instpol.InputError, match="B map but the telescope model's band is 0.550um"):
        c.correct_map(maps["B"], tmp_path / "b.fits", parang_deg=(10, 25))
