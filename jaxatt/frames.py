"""Navigation frames, quaternion order and units: the conversions to use at the edges, never guessed.

Frames (local level; x, y, z):

* ``"ENU"``: east, north, up: BROAD's, VQF's and the default of :func:`jaxatt.filter` on recorded data.
* ``"NED"``: north, east, down: the papers' simulations (Batista et al., the NLIO paper).
* ``"NWU"``: north, west, up: imufusion's default and the internal frame of Madgwick's and Mahony's C filters.

"North" on recorded data is the horizontal direction of the local magnetic field (magnetic north), as in VQF
and BROAD. A quaternion q (Hamilton, scalar first (w, x, y, z)) maps sensor coordinates to a navigation frame;
:func:`change_frame` moves it to another one by a fixed left multiplication (VQF's FAQ recipe). Vectors move with
:func:`change_vector_frame`. For scipy, :func:`to_scipy` / :func:`from_scipy` handle its scalar-last order.

Units: jaxatt works in rad/s (gyro), m/s^2 (accelerometer, specific force) and s (time); magnetometer data may
stay in any unit (the observers that need a reference take it in the data's unit). A recording in other units is
converted once, at the boundary, by :func:`to_si` from the tables :data:`GYR_UNITS`, :data:`ACC_UNITS` and
:data:`TIME_UNITS`: ``jaxatt.filter(..., gyr_unit="deg/s", acc_unit="g", time_unit="ms")``,
``jaxatt.data.logs.load_log(path, gyr_unit=...)`` or ``jaxatt filter --gyr-unit deg/s``. The helpers at the end
(:func:`deg_s_to_rad_s`, ...) convert arrays by hand.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from .types import check_shape

__all__ = [
    "FRAMES",
    "frame_rotation",
    "change_frame",
    "change_vector_frame",
    "up",
    "to_xyzw",
    "from_xyzw",
    "to_scipy",
    "from_scipy",
    "check_frame",
    "STANDARD_GRAVITY",
    "GYR_UNITS",
    "ACC_UNITS",
    "TIME_UNITS",
    "unit_factor",
    "unit_spelling",
    "to_si",
    "deg_s_to_rad_s",
    "rad_s_to_deg_s",
    "g_to_m_s2",
    "m_s2_to_g",
    "gauss_to_ut",
    "ut_to_gauss",
    "nt_to_ut",
    "ut_to_nt",
]

FRAMES = ("ENU", "NED", "NWU")

#: Rows: the axes of each frame written in ENU coordinates, so v_F = M_F @ v_ENU.
_FROM_ENU = {
    "ENU": np.eye(3),
    "NED": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    "NWU": np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}

#: Standard gravity (m/s^2), for accelerometers that report in g.
STANDARD_GRAVITY = 9.80665

#: Factor from each gyro unit to rad/s (dps: deg/s; mdps: millidegrees per second, as MEMS gyros report).
GYR_UNITS = {"rad/s": 1.0, "deg/s": math.pi / 180.0, "dps": math.pi / 180.0, "mdps": math.pi / 180e3}
#: Factor from each accelerometer unit to m/s^2 (g and mg: standard gravity and a thousandth of it).
ACC_UNITS = {"m/s^2": 1.0, "m/s2": 1.0, "g": STANDARD_GRAVITY, "mg": STANDARD_GRAVITY / 1e3}
#: Factor from each time unit to s.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
_UNIT_TABLES = {"gyr_unit": GYR_UNITS, "acc_unit": ACC_UNITS, "time_unit": TIME_UNITS}


def unit_spelling(unit):
    """``unit`` as the tables spell it, whatever its case and common variants: "DEG/S", "°/s", "deg/sec" ->
    "deg/s"; "m/s²", "m/s/s", "m/s**2" -> "m/s^2"; "µs", "usec" -> "us"; "sec" -> "s". Anything else as it is
    (lower case)."""
    if not isinstance(unit, str):
        return unit
    u = unit.strip().lower().replace(" ", "")
    for old, new in (
        ("°", "deg"),
        ("²", "^2"),
        ("**", "^"),
        ("µ", "u"),
        ("μ", "u"),
        ("degrees", "deg"),
        ("degree", "deg"),
        ("radians", "rad"),
    ):
        u = u.replace(old, new)
    u = re.sub(r"(^|/|[mun])sec(?:ond)?s?(?=$|/|\^)", r"\1s", u)  # "sec", "/second", "msec" -> "s", "/s", "ms"
    if u.endswith("/s/s"):
        u = u[:-4] + "/s^2"
    return u


def unit_factor(argument: str, unit: str) -> float:
    """The factor from ``unit`` to jaxatt's unit for ``argument`` ("gyr_unit", "acc_unit" or "time_unit");
    ValueError (one line naming the argument and its choices) otherwise."""
    table = _UNIT_TABLES.get(argument)
    if table is None:
        raise ValueError(f"unit argument must be one of {', '.join(_UNIT_TABLES)}, got {argument!r}")
    key = unit_spelling(unit) if isinstance(unit, str) else None  # "DEG/S", "°/s", "MS" as written on a logger
    if key not in table:
        raise ValueError(f"{argument} must be one of {', '.join(repr(u) for u in table)}, got {unit!r}")
    return table[key]


def to_si(a, argument: str, unit: str):
    """``a`` (an array, or None) converted from ``unit`` to jaxatt's unit for ``argument`` (:func:`unit_factor`),
    in its own float precision (a float32 recording stays float32; integers become float64); ``a`` itself when
    ``unit`` is already jaxatt's."""
    f = unit_factor(argument, unit)
    if a is None or f == 1.0:
        return a
    a = np.asarray(a)
    return a * np.asarray(f, a.dtype if a.dtype.kind == "f" else np.float64)


def check_frame(frame: str, name: str = "frame") -> str:
    """``frame`` upper-cased if it is one of :data:`FRAMES`; ValueError naming ``name`` otherwise."""
    f = str(frame).upper()
    if f not in FRAMES:
        raise ValueError(f"{name} must be one of {', '.join(FRAMES)}, got {frame!r}")
    return f


def frame_rotation(to: str, frm: str = "ENU") -> np.ndarray:
    """The rotation matrix C (3, 3) with v_to = C @ v_from for coordinates of the same vector."""
    return _FROM_ENU[check_frame(to, "to")] @ _FROM_ENU[check_frame(frm, "frm")].T


def _matrix_to_quat_np(r: np.ndarray) -> np.ndarray:
    w = math.sqrt(max(0.0, 1.0 + np.trace(r))) / 2.0
    if w > 1e-6:
        return np.array(
            [w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)]
        )
    # 180-degree rotation (the NED <-> ENU case): axis from the diagonal
    x = math.sqrt(max(0.0, (1 + r[0, 0] - r[1, 1] - r[2, 2]) / 4))
    y = math.sqrt(max(0.0, (1 - r[0, 0] + r[1, 1] - r[2, 2]) / 4))
    z = math.sqrt(max(0.0, (1 - r[0, 0] - r[1, 1] + r[2, 2]) / 4))
    if x >= y and x >= z:
        return np.array([0.0, x, (r[0, 1] + r[1, 0]) / (4 * x), (r[0, 2] + r[2, 0]) / (4 * x)])
    if y >= z:
        return np.array([0.0, (r[0, 1] + r[1, 0]) / (4 * y), y, (r[1, 2] + r[2, 1]) / (4 * y)])
    return np.array([0.0, (r[0, 2] + r[2, 0]) / (4 * z), (r[1, 2] + r[2, 1]) / (4 * z), z])


def _qmul_np(a, b):
    aw, ax, ay, az = np.moveaxis(np.asarray(a), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _real(x, name: str) -> np.ndarray:
    """``x`` as a numpy array of floats: a float dtype is kept, integers become float64 (numpy's default float);
    TypeError naming ``name`` for anything else (bool, complex, text, objects)."""
    a = np.asarray(x)
    if np.issubdtype(a.dtype, np.floating):
        return a
    if np.issubdtype(a.dtype, np.integer):
        return a.astype(np.float64)
    raise TypeError(f"{name} must be real numbers, got dtype {a.dtype}")


def change_frame(q, to: str, frm: str = "ENU"):
    """Sensor-to-``frm`` quaternions (..., 4), (w, x, y, z), re-expressed as sensor-to-``to``: q_to = c (x) q_frm
    with c the quaternion of :func:`frame_rotation`. numpy in, numpy out (a float dtype of ``q`` is kept, integers
    become float64)."""
    check_shape(q, "change_frame: q", (4,))
    q = _real(q, "change_frame: q")
    c = _matrix_to_quat_np(frame_rotation(to, frm))
    return _qmul_np(c.astype(q.dtype), q).astype(q.dtype, copy=False)


def change_vector_frame(v, to: str, frm: str = "ENU"):
    """Vectors (..., 3) given in ``frm`` coordinates, in ``to`` coordinates (numpy; a float dtype is kept, integers
    become float64)."""
    check_shape(v, "change_vector_frame: v", (3,))
    v = _real(v, "change_vector_frame: v")
    return (v @ frame_rotation(to, frm).T.astype(v.dtype)).astype(v.dtype, copy=False)


def up(frame: str) -> np.ndarray:
    """The unit "up" vector (direction of the specific force at rest) in ``frame`` coordinates."""
    return frame_rotation(frame, "ENU")[:, 2].copy()


def to_xyzw(q):
    """(w, x, y, z) -> (x, y, z, w) (scipy's order), shape (..., 4); works on numpy and jax arrays."""
    check_shape(q, "to_xyzw: q", (4,))
    return (q if hasattr(q, "shape") else np.asarray(q))[..., [1, 2, 3, 0]]


def from_xyzw(q):
    """(x, y, z, w) -> (w, x, y, z), shape (..., 4); works on numpy and jax arrays."""
    check_shape(q, "from_xyzw: q", (4,))
    return (q if hasattr(q, "shape") else np.asarray(q))[..., [3, 0, 1, 2]]


def to_scipy(q) -> Any:
    """A ``scipy.spatial.transform.Rotation`` of (..., 4) (w, x, y, z) quaternions (needs scipy)."""
    from scipy.spatial.transform import Rotation

    check_shape(q, "to_scipy: q", (4,))
    return Rotation.from_quat(to_xyzw(_real(q, "to_scipy: q").astype(float)))


def from_scipy(rotation) -> np.ndarray:
    """(w, x, y, z) quaternions (..., 4) of a ``scipy.spatial.transform.Rotation``, w >= 0."""
    if not callable(getattr(rotation, "as_quat", None)):
        raise TypeError(
            f"from_scipy: rotation must be a scipy.spatial.transform.Rotation, got {type(rotation).__name__}"
        )
    q = from_xyzw(np.asarray(rotation.as_quat(), float))
    return np.where(q[..., :1] < 0, -q, q)


def deg_s_to_rad_s(x):
    """deg/s -> rad/s."""
    return np.deg2rad(np.asarray(x, float))


def rad_s_to_deg_s(x):
    """rad/s -> deg/s."""
    return np.rad2deg(np.asarray(x, float))


def g_to_m_s2(x):
    """Accelerations in g (standard gravity) -> m/s^2."""
    return np.asarray(x, float) * STANDARD_GRAVITY


def m_s2_to_g(x):
    """m/s^2 -> g (standard gravity)."""
    return np.asarray(x, float) / STANDARD_GRAVITY


def gauss_to_ut(x):
    """Magnetic field in gauss -> uT (1 G = 100 uT)."""
    return np.asarray(x, float) * 100.0


def ut_to_gauss(x):
    """uT -> gauss."""
    return np.asarray(x, float) / 100.0


def nt_to_ut(x):
    """nT -> uT."""
    return np.asarray(x, float) / 1000.0


def ut_to_nt(x):
    """uT -> nT."""
    return np.asarray(x, float) * 1000.0
