"""A calibration file says what it is, as every table and map does (its primary header's product
keywords, checked here against Python's blake3 of the instrument file), and the one
compatibility check reads them in the Python face as in the CLI: a map of another detector than
the calibration's is refused naming both, and corrected with a warning when allowed."""

import pytest
from astropy.io import fits

import instpol
from conftest import ROOT
from test_correct_map import v_map  # noqa: F401 (fixture)


def test_a_calibration_file_records_its_instrument_file(demo_dir):
    blake3 = pytest.importorskip("blake3")
    with fits.open(demo_dir / "cal_V.fits") as h:
        head = h[0].header
    text = (ROOT / "instruments" / "fors1.toml").read_bytes()
    assert head["INSTHASH"] == blake3.blake3(text).hexdigest()
    assert (head["INSTRUME"], head["FILTER"], head["PLATE"]) == ("FORS1", "V", "half_wave")
    # FORS1's detector as its file gives it (2048 x 2048 px of 0.2 arcsec).
    assert head["DETSIZE"] == "2048x2048" and float(head["PIXSCALE"]) == 0.2


def test_a_map_of_another_detector_is_refused(demo_dir, v_map):  # noqa: F811
    # The demo's V calibration is of the built-in FORS1 (2048 px); the map of a tiny FORS1 (128 px).
    c = instpol.Calibration.load(demo_dir / "cal_V.fits")
    with pytest.raises(instpol.InputError, match="detector is 128x128 px.*2048x2048 px"):
        c.correct_map(v_map)
    with pytest.warns(UserWarning, match="detector"):
        c.correct_map(v_map, allow_mismatch=True)


def _fors1_v_product(**changed):
    """What a catalog of the built-in FORS1 in V says it is (as ``catalog()["product"]``), with
    ``changed`` keys replaced."""
    p = {"instrument": "FORS1", "filter": "V", "plate": "half_wave", "hwp_chi_offset_deg": 0.0,
         "detector_px": (2048, 2048), "pixel_scale_arcsec": 0.2, "sky_pa_deg": None}
    p.update(changed)
    return p


def test_rows_of_another_detector_are_refused(demo_dir):
    # Rows whose product says another detector than the calibration's (2048 px of 0.2"): their
    # field positions are not the calibration's, so the correction is refused naming both, as
    # `instpol correct` refuses a table saying so; allowed, it warns.
    c = instpol.Calibration.load(demo_dir / "cal_V.fits")
    args = (2.53, -3.23, 0.001, 0.0, 1e-4, 1e-4)
    same = c.correct(*args, product=_fors1_v_product())
    with pytest.raises(instpol.InputError, match="detector is 1024x1024 px.*2048x2048 px"):
        c.correct(*args, product=_fors1_v_product(detector_px=(1024, 1024)))
    with pytest.raises(instpol.InputError, match="0.4 arcsec/px.*0.2 arcsec/px"):
        c.correct(*args, product=_fors1_v_product(pixel_scale_arcsec=0.4))
    with pytest.warns(UserWarning, match="detector"):
        allowed = c.correct(*args, product=_fors1_v_product(detector_px=(1024, 1024)), allow_mismatch=True)
    # Allowed, the numbers are those of the rows of the same detector: only the check differs.
    assert float(allowed["q0"]) == float(same["q0"]) and float(allowed["u0"]) == float(same["u0"])


def test_a_product_value_of_the_wrong_type_names_its_key(demo_dir):
    c = instpol.Calibration.load(demo_dir / "cal_V.fits")
    with pytest.raises(instpol.InputError, match="detector_px"):
        c.correct(2.53, -3.23, 0.001, 0.0, 1e-4, 1e-4, product=_fors1_v_product(detector_px="big"))
