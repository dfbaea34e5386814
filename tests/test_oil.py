import math

import numpy as np
import pytest

from cmcan.oil import VG46, Oil


def astm_d341(temp_c: float, a: float, b: float) -> float:
    """ASTM D341 written out by hand: log10(log10(nu + 0.7)) = A - B log10(T)."""
    return 10 ** (10 ** (a - b * math.log10(temp_c + 273.15))) - 0.7


def test_viscosity_at_the_two_reference_points():
    assert VG46.kinematic_viscosity_cst(40.0) == pytest.approx(46.0, rel=1e-9)
    assert VG46.kinematic_viscosity_cst(100.0) == pytest.approx(6.8, rel=1e-9)


def test_walther_constants_match_the_reference_notes():
    a, b = VG46.walther_ab
    assert a == pytest.approx(9.418, abs=0.01)
    assert b == pytest.approx(3.684, abs=0.01)


@pytest.mark.parametrize(("temp_c", "nu_cst"), [(50.0, 30.0), (60.0, 20.6), (80.0, 11.1)])
def test_viscosity_between_reference_points_matches_published_figures(temp_c, nu_cst):
    assert VG46.kinematic_viscosity_cst(temp_c) == pytest.approx(nu_cst, rel=0.02)


def test_viscosity_matches_hand_written_astm_d341_over_the_range():
    a, b = VG46.walther_ab
    temps = np.linspace(-10, 120, 27)
    expected = [astm_d341(t, a, b) for t in temps]
    np.testing.assert_allclose(VG46.kinematic_viscosity_cst(temps), expected, rtol=1e-12)


def test_laminar_leakage_ratio_80_to_40_c_is_about_four():
    ratio = VG46.dynamic_viscosity_pa_s(40.0) / VG46.dynamic_viscosity_pa_s(80.0)
    assert 3.6 < ratio < 4.6


def test_another_grade_passes_through_its_own_points():
    vg32 = Oil(nu40_cst=32.0, nu100_cst=5.4)
    assert vg32.kinematic_viscosity_cst([40.0, 100.0]) == pytest.approx([32.0, 5.4])
