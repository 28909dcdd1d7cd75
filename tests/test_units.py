"""jaxatt.units: the factors are the definitions (deg = pi / 180 rad, standard gravity 9.80665 m/s^2, SI
prefixes), a conversion keeps a float32 recording float32, and an unknown unit is one line naming the argument."""

import math

import numpy as np
import pytest

from jaxatt import units


def test_factors_are_the_definitions():
    assert units.factor("gyr_unit", "deg/s") * 180.0 == pytest.approx(math.pi, rel=1e-15)
    assert units.factor("acc_unit", "g") == 9.80665
    assert [units.factor("time_unit", u) for u in ("s", "ms", "us", "ns")] == [1.0, 1e-3, 1e-6, 1e-9]
    for argument in ("gyr_unit", "acc_unit", "time_unit"):
        assert units.factor(argument, next(iter(units._TABLES[argument]))) == 1.0  # the first is jaxatt's own


def test_to_si_keeps_float32_and_makes_integers_float64():
    a32 = np.array([[180.0, -90.0, 1.0]], np.float32)
    out = units.to_si(a32, "gyr_unit", "deg/s")
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, np.deg2rad(a32.astype(np.float64)), rtol=1e-7)
    ints = units.to_si(np.array([1, 2, 3]), "time_unit", "ms")
    assert ints.dtype == np.float64 and np.array_equal(ints, [1e-3, 2e-3, 3e-3])
    assert units.to_si(None, "acc_unit", "g") is None
    same = np.ones(3)
    assert units.to_si(same, "acc_unit", "m/s^2") is same  # already in jaxatt's unit: not copied


@pytest.mark.parametrize(
    "argument, unit, match",
    [
        ("gyr_unit", "rpm", r"gyr_unit must be one of 'rad/s', 'deg/s', got 'rpm'"),
        ("acc_unit", None, r"acc_unit must be one of 'm/s\^2', 'g', got None"),
        ("time_unit", "sec", r"time_unit must be one of 's', 'ms', 'us', 'ns', got 'sec'"),
    ],
)
def test_an_unknown_unit_is_one_line_naming_the_argument(argument, unit, match):
    with pytest.raises(ValueError, match=match) as e:
        units.to_si(np.ones(3), argument, unit)
    assert "\n" not in str(e.value)
