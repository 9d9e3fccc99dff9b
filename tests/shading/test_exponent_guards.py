"""The library's exponent guards call the one check (``shading.exponents.check_exponents``): the SH coefficients of
a lobe and the AlbedoMM baseline refuse exactly the exponents its positivity rule refuses."""
from __future__ import annotations

import math

import numpy as np
import pytest

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.baselines import global_exponent_model
from reflectmm_cli.shading import brdf, exponents
from reflectmm_cli.shading.sh import blinn_phong_sh_coeffs

VALUES = [1.0, 8.0, 64.0, 1e-6, 2e4, 1e5, 0.0, -0.0, -1.0, -1e-300, math.inf, -math.inf, math.nan]


def _positive_ok(p) -> bool:
    try:
        exponents.check_exponents(np.reshape(p, -1), max_exponent=None, distinct=False, nonempty=False)
        return True
    except exponents.ExponentError:
        return False


def test_brdf_re_exports_the_one_check():
    assert brdf.check_exponents is exponents.check_exponents and brdf.ExponentError is exponents.ExponentError
    assert brdf.DEFAULT_EXPONENTS == exponents.DEFAULT_EXPONENTS == (1.0, 8.0, 64.0)
    assert brdf.MAX_EXPONENT == exponents.MAX_EXPONENT and brdf.LOBE_RCOND_MIN == exponents.LOBE_RCOND_MIN


@pytest.mark.parametrize("p", VALUES + [[1.0, 8.0], [1.0, 0.0], [8.0, math.nan]], ids=str)
def test_sh_coefficients_refuse_what_the_check_refuses(p):
    # the independent rule: every value finite and > 0
    expected = bool(np.all(np.isfinite(p)) and np.all(np.asarray(p) > 0))
    assert _positive_ok(p) == expected
    if expected:
        b = blinn_phong_sh_coeffs(p, 2)
        assert np.allclose(np.reshape(b, (-1, 3))[:, 0], 1.0)  # B_0 = 1 for any p > 0
    else:
        with pytest.raises(ReflectmmError, match=r"^blinn_phong_sh_coeffs: exponents must be finite and > 0, got "):
            blinn_phong_sh_coeffs(p, 2)


@pytest.mark.parametrize("p", [0.0, -3.0, math.nan, math.inf], ids=str)
def test_the_baseline_refuses_what_the_check_refuses(p):
    assert not _positive_ok(p)
    with pytest.raises(ReflectmmError, match=r"^baseline: the global exponent must be > 0, got "):
        global_exponent_model([], exponent=p)
