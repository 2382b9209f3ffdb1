"""The one check of a latent point (_util.checks.latent_point) and its array form (latent_points)."""

import numpy as np
import pytest

from mitsuba_manifold._util import checks
from mitsuba_manifold._util.checks import latent_point, latent_points
from mitsuba_manifold.errors import InputError


@pytest.mark.parametrize(
    "values",
    [
        "0.5, -1e-3",
        "0.5 -1e-3",
        " 0.5,-1e-3 ",
        "+0.5\t-.001",
        [0.5, -1e-3],
        (np.float32(0.5), -1e-3),
        np.array([[0.5], [-1e-3]]),
        ["0.5", "-1e-3"],
    ],
)
def test_a_latent_point_is_read_from_numbers_or_text(values):
    x = latent_point("`x`", values, 2)
    assert x.dtype == np.float64 and x.shape == (2,)
    np.testing.assert_allclose(x, [0.5, -1e-3], rtol=1e-7)


@pytest.mark.parametrize(
    "values, words",
    [
        ("1_0, 2", ["'1_0' is not a number"]),  # float("1_0") is 10: not what anyone typed
        ("0x1 2", ["'0x1' is not a number"]),
        ("nan, 1", ["'nan' is not a number"]),
        ("1e999, 1", ["finite"]),
        ("\u0661 2", ["is not a number"]),  # an Arabic-Indic digit: float() reads it, we do not
        ("1,,2", ["empty coordinate"]),
        ("1 2 3", ["must be 2 finite numbers", "[1.0, 2.0, 3.0]"]),
        ("", ["must be 2 finite numbers", "[]"]),
        ([True, 1.0], ["boolean True"]),
        (np.array([True, False]), ["boolean"]),
        ([1j, 2.0], ["complex"]),
        (np.array([1 + 0j, 2]), ["complex"]),
        ([np.inf, 1.0], ["finite"]),
        (None, ["must be 2 numbers", "None"]),
        (b"1 2", ["bytes"]),
        ({"a": 1}, ["must be 2 numbers"]),
    ],
)
def test_what_is_not_a_latent_point_is_refused_naming_the_parameter(values, words):
    with pytest.raises(InputError) as e:
        latent_point("`x`", values, 2)
    text = str(e.value)
    assert text.startswith("`x`") and "\n" not in text
    for w in words:
        assert w in text


def test_the_array_form_takes_batches_and_refuses_what_is_not_real():
    X, single = latent_points("latent point", np.zeros((5, 3)), 3)
    assert X.shape == (5, 3) and not single
    x, single = latent_points("latent point", [0.1, 0.2, 0.3], 3)
    assert x.shape == (1, 3) and single
    for bad, word in [
        ("0.1,0.2,0.3", "strings"),
        ([True, 0.0, 1.0], "booleans"),
        (np.ones(3, complex), "complex"),
        (np.zeros((2, 2)), "3 coordinates"),
        ([0.0, np.nan, 1.0], "NaN"),
        (None, "coordinates"),
    ]:
        with pytest.raises(InputError, match=word):
            latent_points("latent point", bad, 3)
    with pytest.raises(InputError, match="too far out"):
        latent_points("latent point", [1e31, 0.0, 0.0], 3, max_abs=1e30)


@pytest.mark.parametrize(
    "value, bounds, message",
    [
        (True, {}, "`w` must be a number, got True"),
        (np.bool_(False), {}, "`w` must be a number, got"),
        ("x", {}, "`w` must be a number, got 'x'"),
        (-1.0, {"lo": 0.0}, "`w` must be a finite number >= 0, got -1.0"),
        (0.0, {"lo": 0.0, "lo_open": True}, "`w` must be a finite number > 0, got 0.0"),
        (2.0, {"lo": 0.0, "hi": 1.0}, r"`w` must be a finite number in \[0, 1\], got 2.0"),
        (float("nan"), {}, "`w` must be a finite number, got nan"),
    ],
)
def test_finite_names_the_parameter_the_value_and_the_range(value, bounds, message):
    with pytest.raises(InputError, match=message):
        checks.finite("`w`", value, **bounds)
    assert checks.finite("`w`", 0.5, **bounds) == 0.5
