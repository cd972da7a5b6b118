"""instpol.Calibration against `instpol correct` (the same numbers to the last bit, through the
CLI's CSV output), against a numpy inversion of the paper's M_I written here, and the radial
model evaluated from the file's header keywords with astropy."""

from pathlib import Path
import csv

import numpy as np
import pytest

import instpol
from conftest import key, same

ADDED = ["q0", "u0", "sigma_q0", "sigma_u0", "cov_qu0", "p0", "sigma_p0", "chi0_deg", "sigma_chi0_deg",
         "p0_mas", "q_inst", "u_inst"]


def catalog(n, seed, lo=-3.3, hi=3.3, cov=True):
    rng = np.random.default_rng(seed)
    c = {
        "x": rng.uniform(lo, hi, n),
        "y": rng.uniform(lo, hi, n),
        "q": rng.normal(0, 0.02, n),
        "u": rng.normal(0, 0.02, n),
        "sigma_q": rng.uniform(1e-4, 3e-3, n),
        "sigma_u": rng.uniform(1e-4, 3e-3, n),
    }
    if cov:
        c["cov_qu"] = 0.3 * c["sigma_q"] * c["sigma_u"] * rng.uniform(-1, 1, n)
    return c


def write_csv(path, cols):
    names = list(cols)
    with open(path, "w") as f:
        f.write(",".join(names) + "\n")
        for row in zip(*(cols[k] for k in names)):
            f.write(",".join(repr(float(v)) for v in row) + "\n")


def read_csv(path):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) if r[k] != "" else np.nan for r in rows]) for k in rows[0]}


def cli_correct(run, cal, cols, tmp_path, *flags):
    """`instpol correct --json` on `cols`: the output CSV's columns, with the JSON summary
    under the key "summary"."""
    import json

    inp, out = tmp_path / "in.csv", tmp_path / "out.csv"
    write_csv(inp, cols)
    summary = json.loads(run("correct", "--cal", cal, "--in", inp, "--out", out, "--json", *flags)[1])
    t = read_csv(out)
    t["summary"] = summary
    return t


@pytest.fixture(scope="module")
def cal_v_offset(cal_v, tmp_path_factory):
    """The V calibration with an HWP zero angle of 3.5 deg (so that the rotation is exercised)."""
    from astropy.io import fits

    p = tmp_path_factory.mktemp("off") / "cal_V_off.fits"
    with fits.open(cal_v) as h:
        h[0].header["HIERARCH IP HWP CHI OFFSET DEG"] = 3.5
        h.writeto(p)
    return p


@pytest.mark.parametrize("which", ["cal_v_offset", "cal_b"])
def test_correct_is_the_cli_bit_for_bit(run, request, tmp_path, which):
    cal = request.getfixturevalue(which)
    cols = catalog(3000, 5, lo=-3.0, hi=3.0)
    c = instpol.Calibration.load(cal)
    inside = c.evaluate(cols["x"], cols["y"])["inside"]
    cols = {k: v[inside] for k, v in cols.items()}
    cli = cli_correct(run, cal, cols, tmp_path, "--coords", "arcmin")
    py = c.correct(**cols, estimator="mas")
    for k in ADDED:
        assert same(py[k], cli[k]), k
    assert same(py["extrapolated"], cli["extrapolated"])
    s = cli["summary"]
    assert key(s, "n_rows") == len(cols["x"]) and key(s, "n_extrapolated") == py["n_extrapolated"] == 0
    assert np.median(py["p0"]) == pytest.approx(key(s, "median_p0"), rel=1e-15)
    assert np.median(np.hypot(py["q_inst"], py["u_inst"])) == pytest.approx(key(s, "median_p_inst"), rel=1e-15)
    assert c.hwp_chi_offset_deg == key(s, "hwp_chi_offset_deg") and c.filter == key(s, "filter")


def test_cli_appends_the_python_keys_in_order(run, cal_v, tmp_path):
    """The columns `instpol correct` appends to a table, in their order, are the keys of the
    arrays `Calibration.correct` returns, in theirs (one list in the library): read from the
    CLI's CSV header here, for an estimator other than the default."""
    cols = catalog(20, 9, lo=-1.0, hi=1.0)
    inp, out = tmp_path / "in.csv", tmp_path / "out.csv"
    write_csv(inp, cols)
    run("correct", "--cal", cal_v, "--in", inp, "--out", out, "--estimator", "wk")
    with open(out) as f:
        header = next(csv.reader(f))
    assert header[: len(cols)] == list(cols)
    py = instpol.Calibration.load(cal_v).correct(**cols, estimator="wk")
    arrays = [k for k, v in py.items() if isinstance(v, np.ndarray)]
    assert header[len(cols):] == arrays
    assert arrays[9] == "p0_wk" and arrays[-1] == "extrapolated"


def test_first_order_pixels_and_extrapolation_match_cli(run, cal_v_offset, tmp_path):
    cols = catalog(2000, 6, lo=-100.0, hi=2148.0, cov=False)  # pixels, some beyond the detector
    c = instpol.Calibration.load(cal_v_offset)
    cli = cli_correct(run, cal_v_offset, cols, tmp_path, "--coords", "pixel", "--method", "first-order",
                      "--allow-extrapolation", "--extrapolation-error", "0.7", "--estimator", "wk")
    py = c.correct(**cols, units="px", method="first-order", allow_extrapolation=True, extrapolation_error=0.7,
                   estimator="wk")
    for k in ADDED:
        k = "p0_wk" if k == "p0_mas" else k
        assert same(py[k], cli[k]), k
    assert same(py["extrapolated"], cli["extrapolated"])
    assert 0 < py["n_extrapolated"] == int(cli["extrapolated"].sum()) < len(cols["x"])


def numpy_exact_inversion(qi, ui, q, u, offset_deg):
    """Rotate the measured (q, u) by twice the HWP zero angle, then solve M_I S0 = (1, q1, u1)
    with M_I the paper's partial polarizer (section sec:instr, eq:instpol) built here."""
    t = 2 * np.radians(offset_deg)
    q1 = np.cos(t) * q - np.sin(t) * u
    u1 = np.sin(t) * q + np.cos(t) * u
    p = np.hypot(qi, ui)
    c, s = np.divide(qi, p, out=np.ones_like(p), where=p > 0), np.divide(ui, p, out=np.zeros_like(p), where=p > 0)
    M = np.empty((len(p), 3, 3))
    M[:, 0] = np.stack([np.ones_like(p), p * c, p * s], 1)
    M[:, 1] = np.stack([p * c, 1 - p * s * s, p * c * s], 1)
    M[:, 2] = np.stack([p * s, p * c * s, 1 - p * c * c], 1)
    M /= (1 + p)[:, None, None]
    S0 = np.linalg.solve(M, np.stack([np.ones_like(q1), q1, u1], 1)[..., None])[..., 0]
    return S0[:, 1] / S0[:, 0], S0[:, 2] / S0[:, 0]


def test_exact_correction_against_numpy_matrix_inverse(cal_v_offset):
    cols = catalog(5000, 7, lo=-3.0, hi=3.0)
    c = instpol.Calibration.load(cal_v_offset)
    r = c.correct(**cols)
    ev = c.evaluate(cols["x"], cols["y"])
    assert same(ev["q"], r["q_inst"]) and same(ev["u"], r["u_inst"])
    q0, u0 = numpy_exact_inversion(ev["q"], ev["u"], cols["q"], cols["u"], 3.5)
    np.testing.assert_allclose(r["q0"], q0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(r["u0"], u0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(r["p0"], np.hypot(q0, u0), rtol=0, atol=1e-14)
    # an unpolarized star seen through the instrument comes back unpolarized (P -> 0 edge)
    t = -2 * np.radians(3.5)
    qm, um = np.cos(t) * ev["q"] - np.sin(t) * ev["u"], np.sin(t) * ev["q"] + np.cos(t) * ev["u"]
    z = c.correct(cols["x"], cols["y"], qm, um, 1e-4, 1e-4)
    assert np.max(z["p0"]) < 1e-15


def test_evaluate_is_the_header_radial_polynomial(cal_v):
    """p(r) = sum C_k r^k about the centre, angle along the radius (q, u) = p (cos 2a, sin 2a)."""
    from astropy.io import fits

    h = fits.getheader(cal_v)
    assert h["HIERARCH IP MODEL"] == "RADIAL"
    k0, deg = h["HIERARCH IP RADIAL FIRST POWER"], h["HIERARCH IP RADIAL DEGREE"]
    coef = {k: h[f"HIERARCH IP RADIAL C{k}"] for k in range(k0, deg + 1)}
    cx, cy = h["HIERARCH IP CENTRE X"], h["HIERARCH IP CENTRE Y"]
    rng = np.random.default_rng(8)
    x, y = rng.uniform(-3, 3, 1000), rng.uniform(-3, 3, 1000)
    r = np.hypot(x - cx, y - cy)
    p = sum(v * r**k for k, v in coef.items())
    a = np.arctan2(y - cy, x - cx)
    ev = instpol.Calibration.load(cal_v).evaluate(x, y)
    assert ev["inside"].all()
    np.testing.assert_allclose(ev["q"], p * np.cos(2 * a), rtol=0, atol=1e-15)
    np.testing.assert_allclose(ev["u"], p * np.sin(2 * a), rtol=0, atol=1e-15)
    # pixels: origin and scale from the header
    s, ox, oy = h["HIERARCH IP PIX SCALE ARCSEC"], h["HIERARCH IP PIX ORIGIN X"], h["HIERARCH IP PIX ORIGIN Y"]
    evp = instpol.Calibration.load(cal_v).evaluate(ox + x * 60 / s, oy + y * 60 / s, units="px")
    np.testing.assert_allclose(evp["q"], ev["q"], rtol=0, atol=1e-15)
    # scalars in, scalars out
    one = instpol.Calibration.load(cal_v).evaluate(1.0, -0.5)
    assert isinstance(one["q"], float) and isinstance(one["inside"], bool)


def test_errors(cal_v, tmp_path):
    c = instpol.Calibration.load(cal_v)
    with pytest.raises(instpol.InputError, match=r"index 1: position \(9, 0\) arcmin is outside the calibrated field"):
        c.correct([0.0, 9.0], [0.0, 0.0], 0.01, 0.0, 1e-3, 1e-3)
    with pytest.raises(instpol.InputError, match="sigma_q = -0.001 is negative"):
        c.correct(0.0, 0.0, 0.01, 0.0, -1e-3, 1e-3)
    with pytest.raises(instpol.InputError, match="units 'deg'"):
        c.evaluate(0.0, 0.0, units="deg")
    with pytest.raises(instpol.InputError, match="method 'best'"):
        c.correct(0.0, 0.0, 0.01, 0.0, 1e-3, 1e-3, method="best")
    with pytest.raises(instpol.FileError, match="cannot load calibration"):
        instpol.Calibration.load(tmp_path / "missing.fits")
    bad = tmp_path / "bad.fits"
    bad.write_text("not a FITS file")
    with pytest.raises(OSError, match="cannot load calibration"):
        instpol.Calibration.load(bad)


def test_the_gil_is_released_during_a_correction(cal_v):
    """While one thread is inside `correct` (1e6 rows, ~0.1-0.5 s), another runs Python code:
    with the GIL held it could not run a single bytecode until the call returned."""
    import threading
    import time

    cols = catalog(1_000_000, 9, lo=-3.0, hi=3.0)
    c = instpol.Calibration.load(cal_v)
    state = {"in_call": False, "done": False}
    started = threading.Event()

    def work():
        state["in_call"] = True
        started.set()
        c.correct(**cols)
        state["in_call"] = False
        state["done"] = True

    t = threading.Thread(target=work)
    t.start()
    started.wait()
    # Sleeping hands the GIL over, so the other thread enters correct(); were the GIL held
    # there, this thread could not wake before the call returned (checked with a GIL-holding
    # call, sorted() of 3e6 floats: 0 ticks).
    time.sleep(0.02)
    ticks = 0
    while not state["done"]:
        if state["in_call"]:
            ticks += 1
    t.join()
    assert ticks > 100, f"the main thread ran {ticks} loop iterations while correct() ran"


EFOSC2 = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "efosc2-standards"


def v_standards(d, skipped):
    """The real EFOSC2 V standards as a fit-standards table in folder `d` (skipped loudly,
    saying what was `skipped`, when the data are absent)."""
    src = EFOSC2 / "pv_standards.txt"
    if not src.is_file():
        pytest.skip(f"*** SKIPPED LOUDLY: {src} not found: {skipped} ***")
    std = d / "std_V.csv"
    with open(src) as f, open(std, "w") as out:
        out.write("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter\n")
        for line in f:
            if line.strip():
                out.write(line.strip() + ",V\n")
    return std


@pytest.fixture(scope="module")
def cal_v_telescope(run, cal_v, tmp_path_factory):
    """The V field calibration with a telescope model fitted to the real EFOSC2 V standards
    beside it (`fit-standards --output --field-cal`): the file `correct` applies as a chain."""
    d = tmp_path_factory.mktemp("tel")
    std = v_standards(d, "the telescope chain was not compared")
    # The demo's FORS1 V field stands in for an EFOSC2 field calibration (fit-standards refuses
    # a field and a telescope of two instruments); what is compared is the chain's arithmetic.
    from astropy.io import fits

    field = d / "cal_V_as_efosc2.fits"
    with fits.open(cal_v) as h:
        h[0].header["HIERARCH IP INSTRUMENT"] = "EFOSC2"
        h.writeto(field)
    both = d / "cal_V_tel.fits"
    run("fit-standards", std, "--instrument", "efosc2", "--model", "wiersema", "--output", both,
        "--field-cal", field)
    return both


def test_telescope_chain_is_the_cli_bit_for_bit(run, cal_v_telescope, cal_v, tmp_path):
    cols = catalog(500, 11, lo=-2.5, hi=2.5)
    rng = np.random.default_rng(12)
    cols["parang_deg"] = rng.uniform(-180, 180, 500)
    cols["parang_end_deg"] = cols["parang_deg"] + rng.uniform(0, 20, 500)
    c = instpol.Calibration.load(cal_v_telescope)
    assert c.telescope_bands == ["V"]
    cli = cli_correct(run, cal_v_telescope, cols, tmp_path, "--coords", "arcmin", "--estimator", "mas")
    py = c.correct(**cols, estimator="mas")
    for k in ADDED:
        assert same(py[k], cli[k]), k
    assert py["telescope_model"] == cli["summary"]["telescope_model"] == "wiersema"
    # The telescope term is really there: without it (the field alone) the numbers differ by
    # the M3's few per cent.
    field_only = instpol.Calibration.load(cal_v).correct(
        **{k: v for k, v in cols.items() if not k.startswith("parang")})
    assert np.median(np.hypot(py["q0"] - field_only["q0"], py["u0"] - field_only["u0"])) > 0.01
    # A telescope model without the angles, or angles without a telescope model: refused.
    # The band rule is the CLI's (fit::telescope::TelescopeFit::choose_band): a band the model
    # lacks is refused by name.
    with pytest.raises(instpol.InputError, match="band 'B': the telescope model .* has bands V"):
        c.correct(**cols, band="B")
    bare = {k: v for k, v in cols.items() if not k.startswith("parang")}
    with pytest.raises(instpol.InputError, match="parang_deg"):
        c.correct(**bare)
    with pytest.raises(instpol.InputError, match="holds no telescope model"):
        instpol.Calibration.load(cal_v).correct(**cols)
    with pytest.raises(instpol.InputError, match="band 'B'"):
        c.correct(**cols, band="B")


def test_telescope_only_file_is_the_cli_bit_for_bit(run, tmp_path):
    """A telescope-only calibration (fit-standards --output without --field-cal) loads and
    corrects rows as `instpol correct` does, bit for bit: the telescope alone."""
    std = v_standards(tmp_path, "the telescope-only file was not compared")
    tel = tmp_path / "tel_V.fits"
    run("fit-standards", std, "--instrument", "efosc2", "--model", "wiersema", "--output", tel)
    c = instpol.Calibration.load(tel)
    assert c.model == "TELESCOPE" and c.telescope_bands == ["V"] and c.filter == "V"
    cols = catalog(300, 5, lo=-2.5, hi=2.5)
    rng = np.random.default_rng(5)
    cols["parang_deg"] = rng.uniform(-180, 180, 300)
    cols["parang_end_deg"] = cols["parang_deg"] + rng.uniform(0, 20, 300)
    cli = cli_correct(run, tel, cols, tmp_path, "--coords", "arcmin", "--estimator", "mas")
    py = c.correct(**cols, estimator="mas")
    for k in ADDED:
        assert same(py[k], cli[k]), k
    assert py["telescope_model"] == cli["summary"]["telescope_model"] == "wiersema"
    # The mirror's few per cent came out of the rows.
    assert np.median(np.hypot(py["q0"] - cols["q"], py["u0"] - cols["u"])) > 0.01
    # The band rule is the CLI's (fit::telescope::TelescopeFit::choose_band): a band the model
    # lacks is refused by name.
    with pytest.raises(instpol.InputError, match="band 'B': the telescope model .* has bands V"):
        c.correct(**cols, band="B")
    bare = {k: v for k, v in cols.items() if not k.startswith("parang")}
    with pytest.raises(instpol.InputError, match="parang_deg"):
        c.correct(**bare)
    with pytest.raises(instpol.InputError, match="only a telescope model"):
        c.evaluate(0.0, 0.0)


def test_catalog_columns_are_not_turned_twice(run, cal_v_offset, tmp_path):
    """catalog()'s q, u carry the filter's HWP zero angle (here 3.5 deg, the calibration's
    too): Calibration.correct(..., hwp_chi_offset_deg=cat["chi_offset_deg"]) applies only the
    difference, as `instpol correct` does with a table's column, and gives catalog(cal=...)'s
    columns to 1e-12; without it the zero angle is applied a second time: chi 3.5 deg off on
    the 3 % star."""
    from conftest import tiny_fors1

    text = tiny_fors1(tmp_path).read_text()
    v = 'name = "V"\naliases = ["V_BESS"]\nlambda_eff_nm = 554.0\n'
    assert v in text, "the V filter of FORS1's file"
    inst = tmp_path / "zero.toml"
    inst.write_text(text.replace(v, v + "hwp_chi_offset_deg = 3.5\n"))
    scene = tmp_path / "scene.toml"
    scene.write_text(
        f'instrument = "{inst}"\nfilter = "V"\nseed = 5\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n'
        '[output]\nbitpix = -64\n'
        '[[stars]]\nx = 40\ny = 34\ncoords = "pixel"\nflux_e = 4e6\nfwhm_arcsec = 1.6\np = 0.03\nchi_deg = 20\n'
        '[[stars]]\nx = 90\ny = 34\ncoords = "pixel"\nflux_e = 4e6\nfwhm_arcsec = 1.6\n'
        "[effects]\nhwp_chi_offset_from_filter = true\n"
    )
    run("simulate", scene, "--out", tmp_path / "frames")
    frames = sorted((tmp_path / "frames").glob("*.fits"))
    args = dict(instrument=str(inst), fwhm=4.0, aperture=10.0, annulus=(14.0, 24.0))
    cat = instpol.catalog(frames, **args)
    assert cat["chi_offset_deg"] == 3.5 and len(cat["x"]) == 2
    ref = instpol.catalog(frames, cal=cal_v_offset, **args)
    c = instpol.Calibration.load(cal_v_offset)
    cols = [cat[k] for k in ("x_arcmin", "y_arcmin", "q", "u", "sigma_q", "sigma_u", "cov_qu")]
    r = c.correct(*cols, hwp_chi_offset_deg=cat["chi_offset_deg"])
    for k in ["q0", "u0", "sigma_q0", "sigma_u0"]:
        assert np.max(np.abs(r[k] - ref[k])) < 1e-12, k
    # What the catalog is travels with it: the same rows of another filter are refused, as
    # instpol correct refuses a table whose keywords say so, unless allow_mismatch.
    prod = cat["product"]
    assert prod["instrument"] == "FORS1" and prod["filter"] == "V" and prod["plate"] == "half_wave"
    said = c.correct(*cols, hwp_chi_offset_deg=cat["chi_offset_deg"], instrument=prod["instrument"],
                     filter=prod["filter"])
    assert np.array_equal(said["q0"], r["q0"], equal_nan=True)
    with pytest.raises(instpol.InputError, match="filter I"):
        c.correct(*cols, hwp_chi_offset_deg=cat["chi_offset_deg"], instrument="FORS1", filter="I")
    forced = c.correct(*cols, hwp_chi_offset_deg=cat["chi_offset_deg"], instrument="FORS1", filter="I",
                       allow_mismatch=True)
    assert np.array_equal(forced["q0"], r["q0"], equal_nan=True)
    twice = c.correct(*cols)
    i = int(np.argmax(cat["p"]))
    dchi = (twice["chi0_deg"][i] - r["chi0_deg"][i] + 90) % 180 - 90
    assert abs(dchi - 3.5) < 0.05, dchi
    with pytest.raises(instpol.InputError, match="hwp_chi_offset_deg"):
        c.correct(*cols, hwp_chi_offset_deg=float("nan"))


def test_frames_of_no_built_in_instrument_need_one_named(tmp_path):
    """No silent default instrument: frames whose INSTRUME no built-in instrument writes are
    refused naming the keyword and instrument=, where they were read as FORS1."""
    from astropy.io import fits
    path = tmp_path / "f.fits"
    h = fits.Header()
    h["INSTRUME"] = "NOSUCH"
    fits.PrimaryHDU(np.zeros((8, 8), dtype=np.float32), header=h).writeto(path)
    with pytest.raises(instpol.InputError, match="INSTRUME = 'NOSUCH'.*instrument="):
        instpol.catalog([path])
    with pytest.raises(instpol.InputError, match="INSTRUME = 'NOSUCH'"):
        instpol.reduce([path])
