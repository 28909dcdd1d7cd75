"""The sensor units a recording may come in, and their conversion to the units jaxatt works in.

jaxatt works in rad/s (gyro), m/s^2 (accelerometer, specific force) and s (time); the magnetometer may be in any
unit (only its direction and relative size are used). A recording in deg/s, g or ms timestamps is converted once,
at the boundary: ``jaxatt.filter(..., gyr_unit="deg/s", acc_unit="g", time_unit="ms")`` or
``jaxatt filter --gyr-unit deg/s --acc-unit g --time-unit ms``.
"""

from __future__ import annotations

import math
from typing import Dict, Optional

import numpy as np

#: Factor from each gyro unit to rad/s.
GYR_UNITS: Dict[str, float] = {"rad/s": 1.0, "deg/s": math.pi / 180.0}
#: Factor from each accelerometer unit to m/s^2 (g: standard gravity, 9.80665 m/s^2).
ACC_UNITS: Dict[str, float] = {"m/s^2": 1.0, "g": 9.80665}
#: Factor from each time unit to s.
TIME_UNITS: Dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}

_TABLES = {"gyr_unit": GYR_UNITS, "acc_unit": ACC_UNITS, "time_unit": TIME_UNITS}


def factor(argument: str, unit: str) -> float:
    """The factor from ``unit`` to jaxatt's unit for ``argument`` ("gyr_unit", "acc_unit" or "time_unit");
    ValueError (one line naming the argument and the choices) for an unknown unit."""
    table = _TABLES[argument]
    if not isinstance(unit, str) or unit not in table:
        raise ValueError(f"{argument} must be one of {', '.join(repr(u) for u in table)}, got {unit!r}")
    return table[unit]


def to_si(a: Optional[np.ndarray], argument: str, unit: str):
    """``a`` (an array, or None) converted from ``unit`` to jaxatt's unit, in its own float precision (a float32
    recording stays float32; integers become float64); ``a`` itself when the unit is already jaxatt's."""
    f = factor(argument, unit)
    if a is None or f == 1.0:
        return a
    a = np.asarray(a)
    return a * np.asarray(f, a.dtype if a.dtype.kind == "f" else np.float64)
