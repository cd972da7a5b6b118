"""Rows measured on a rotator (catalog()'s q, u in the celestial frame, turned onto the sky by the
instrument's position angle) corrected with ``sky_pa_deg``: the same star as the rows turned back
by hand in numpy (a rotation of (q, u) by -2 PA) and corrected as the instrument saw them, with
chi0 then turned onto the sky by PA: the identity of a frame rotation, computed here."""

import numpy as np
import pytest

import instpol


@pytest.fixture(scope="module")
def cal(tmp_path_factory):
    d = tmp_path_factory.mktemp("demo")
    instpol.demo(str(d), frames=False)
    return instpol.Calibration.load(f"{d}/cal_V.fits")


def test_celestial_rows_are_turned_back_then_onto_the_sky(cal):
    pa, zero = 37.5, cal.hwp_chi_offset_deg
    x, y = np.array([2.53, -1.0]), np.array([-3.23, 2.0])
    # Rows as the instrument saw them (carrying the calibration's zero angle).
    qi, ui = np.array([0.012, -0.004]), np.array([0.007, 0.015])
    c, s = np.cos(np.radians(2 * pa)), np.sin(np.radians(2 * pa))
    qc, uc = c * qi - s * ui, s * qi + c * ui  # onto the sky by PA
    inst = cal.correct(x, y, qi, ui, 1e-4, 1e-4, hwp_chi_offset_deg=zero)
    sky = cal.correct(x, y, qc, uc, 1e-4, 1e-4, hwp_chi_offset_deg=zero, sky_pa_deg=pa)
    np.testing.assert_allclose(sky["p0"], inst["p0"], rtol=1e-12)
    dchi = (sky["chi0_deg"] - inst["chi0_deg"] - pa + 90.0) % 180.0 - 90.0
    np.testing.assert_allclose(dchi, 0.0, atol=1e-9)


def test_a_position_angle_without_the_zero_angle_is_refused(cal):
    with pytest.raises(instpol.InputError, match="sky_pa_deg without hwp_chi_offset_deg"):
        cal.correct(1.0, 1.0, 0.01, 0.0, 1e-4, 1e-4, sky_pa_deg=10.0)


def test_a_product_stands_for_its_arguments(cal):
    """catalog()["product"] given whole corrects as its fields given one by one; a field given
    both ways and differing is refused."""
    pa, zero = 20.0, cal.hwp_chi_offset_deg
    product = {"instrument": cal.instrument, "filter": cal.filter, "plate": "half_wave",
               "hwp_chi_offset_deg": zero, "sky_pa_deg": pa}
    args = (np.array([1.0, -2.0]), np.array([0.5, 1.5]), np.array([0.01, 0.0]), np.array([0.0, 0.02]), 1e-4, 1e-4)
    by_product = cal.correct(*args, product=product)
    by_hand = cal.correct(*args, instrument=cal.instrument, filter=cal.filter, plate="half_wave",
                          hwp_chi_offset_deg=zero, sky_pa_deg=pa)
    for k in ("q0", "u0", "p0", "chi0_deg"):
        np.testing.assert_array_equal(by_product[k], by_hand[k])
    with pytest.raises(instpol.InputError, match="sky_pa_deg=5.0 but product says 20.0"):
        cal.correct(*args, product=product, sky_pa_deg=5.0)


def test_rows_of_a_rotator_instrument_must_say_their_frame(tmp_path):
    """A calibration of MOPTOP (on a rotator): bare arrays that say nothing of the sky's
    position angle are refused (taken in the instrument's frame, rows from catalog(), which are
    on the sky, would be corrected wrongly with no error); stated either way they are
    corrected, and rows turned onto the sky by PA with sky_pa_deg=PA give the p0 of the
    unturned rows with sky_pa_deg=0 (a frame rotation, done here in numpy)."""
    from test_response import write

    path = tmp_path / "moptop_response.fits"
    write(path, instrument="MOPTOP")
    cal = instpol.Calibration.load(path)
    qi, ui = np.array([0.012, -0.004]), np.array([0.007, 0.015])
    x, y = np.zeros(2), np.zeros(2)
    with pytest.raises(instpol.InputError, match="rotator") as e:
        cal.correct(x, y, qi, ui, 1e-4, 1e-4)
    assert "sky_pa_deg" in str(e.value)
    zero = cal.hwp_chi_offset_deg
    own = cal.correct(x, y, qi, ui, 1e-4, 1e-4, hwp_chi_offset_deg=zero, sky_pa_deg=0.0)
    pa = 25.0
    c, s = np.cos(np.radians(2 * pa)), np.sin(np.radians(2 * pa))
    sky = cal.correct(x, y, c * qi - s * ui, s * qi + c * ui, 1e-4, 1e-4, hwp_chi_offset_deg=zero, sky_pa_deg=pa)
    np.testing.assert_allclose(sky["p0"], own["p0"], rtol=1e-12)
