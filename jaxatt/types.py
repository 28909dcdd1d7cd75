"""The data types every part of jaxatt shares: samples, the input of one step, and the observer interface.

This module imports nothing of jaxatt (it is the bottom of the import graph with :mod:`jaxatt.so3`).

Conventions (stated once here, used everywhere):

* Body (sensor) frame for every measurement; a rotation ``R`` / quaternion ``q`` (Hamilton, scalar first
  ``(w, x, y, z)``) maps body coordinates to the navigation frame: ``v_nav = R @ v_body``.
* SI units: t in s, gyro in rad/s, accelerometer (specific force) in m/s^2; the magnetometer in the unit of the
  data or scenario (nT for the Batista papers, gauss for the NLIO paper, uT for BROAD).
* Arrays are time-major ``(T, 3)``; batches of runs or trials lead ``(B, T, 3)``.

Alignment (one rule for every path, :mod:`jaxatt.engine`): T samples at t_0 ... t_{T-1} give T estimates; estimate
0 is ``init``'s (at t_0), estimate k >= 1 is the state after the step over [t_{k-1}, t_k].
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

__all__ = ["ArrayLike", "ImuSample", "VectorSample", "Interval", "Observer", "HOLDS", "MAX_RUNS"]

#: Most runs of one Monte Carlo study: run k's key is fold_in(PRNGKey(seed), k) with k a uint32, so beyond this
#: keys would repeat.
MAX_RUNS = 2**32


#: Most time steps of one run: the engine counts steps in int32.
MAX_STEPS = 2**31 - 1


def check_step_count(duration: float, dt: float) -> int:
    """round(duration / dt), the number of steps of a run: ValueError naming both unless 1 <= it <= MAX_STEPS
    (``duration`` and ``dt`` are already finite positive seconds)."""
    ratio = float(duration) / float(dt)
    if not ratio < MAX_STEPS + 0.5:
        raise ValueError(
            f"duration / dt = {ratio:.3g} steps: at most {MAX_STEPS} steps per run (duration {duration:g} s, "
            f"dt {dt:g} s)"
        )
    n = int(round(ratio))
    if n < 1:
        raise ValueError(f"duration must be at least one step, got {duration} s with dt = {dt} s")
    return n


def check_window_start(window_start, duration) -> float:
    """``window_start`` (s) as a float: a number in [0, ``duration``) s, where a run's metric window begins
    (NaN, or a start at or past the end, would leave the window empty); ValueError naming it otherwise."""
    real = isinstance(window_start, (int, float)) or _is_numpy_number(window_start)
    if isinstance(window_start, bool) or not real:
        raise ValueError(f"window_start must be a number of seconds, got {window_start!r}")
    if not 0.0 <= float(window_start) < duration:
        raise ValueError(f"window_start ({float(window_start)} s) must lie inside the run [0, {duration}) s")
    return float(window_start)


def check_seed(seed) -> int:
    """A PRNG seed: a whole number that fits in 64 bits, |seed| < 2^63 (what ``jax.random.PRNGKey`` takes);
    ValueError otherwise. (Here, without jax, so that the command line checks ``--seed`` before importing it.)"""
    if seed is None or isinstance(seed, bool) or not isinstance(seed, int) and not _is_numpy_integer(seed):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    if not -(2**63) <= int(seed) < 2**63:
        raise ValueError(f"seed must fit in 64 bits (|seed| < 2^63), got {seed}")
    return int(seed)


def check_shape(x, name: str, tail: tuple) -> tuple:
    """The shape of ``x`` after checking that its last axes are ``tail`` (a size None: any), with any leading batch
    axes: ``check_shape(q, "q", (4,))`` takes (4,), (T, 4), (B, T, 4). ValueError naming ``name`` otherwise. Reads
    only the static shape, so it also works on jax tracers (inside ``jit`` / ``vmap`` it runs once, at tracing)."""
    want = "(..., " + ", ".join("n" if d is None else str(d) for d in tail) + ")"
    shape = getattr(x, "shape", None)
    if shape is None:
        import numpy as np

        try:
            shape = np.shape(x)
        except ValueError:  # a ragged nested sequence
            raise ValueError(f"{name} must be an array of shape {want}, got a ragged sequence") from None
    shape = tuple(shape)
    k = len(tail)
    if len(shape) < k or any(d is not None and s != d for s, d in zip(shape[len(shape) - k :], tail)):
        raise ValueError(f"{name} must have shape {want}, got {shape}")
    return shape


def shown(value) -> str:
    """``value`` (a number or an array of any shape) on one line, for an error message: ``[-1.0, 5e-09]``."""
    import numpy as np

    try:
        arr = np.asarray(value)
    except Exception:  # noqa: BLE001 - anything a user passed: its repr
        return " ".join(repr(value).split())
    if arr.ndim == 0:
        return " ".join(repr(value).split()) if arr.dtype == object else f"{arr.item()!r}"
    return " ".join(np.array2string(arr, separator=", ", max_line_width=10**9, threshold=12, edgeitems=3).split())


def shown_for_shape(value, shape: tuple) -> str:
    """For "must be a finite array of ``shape``": ``shape (2, 3)`` when the shape is wrong, else the values."""
    import numpy as np

    got = np.shape(value)
    return f"shape {got}" if got != tuple(shape) else shown(value)


def _is_numpy_integer(x) -> bool:
    import numpy as np

    return isinstance(x, np.integer)


def _is_numpy_number(x) -> bool:
    import numpy as np

    return isinstance(x, (np.integer, np.floating))


#: The type of a gain or reference in an observer's ``Params``: a numpy array or float when the params are built,
#: a jax array or a tracer inside ``jit`` / ``grad`` / ``vmap``. Deliberately loose for the type checker (``Any``).
ArrayLike = Any

#: How a step over [t_k, t_{k+1}] sees the samples (see :class:`Interval` and :mod:`jaxatt.engine`):
#: "zoh" hands it sample k (held over the step, continuous-time observers integrated forward), "linear" an
#: :class:`Interval` (sample k, sample k+1) for interpolation at the integrator's stage times, "next" sample
#: k+1 (a discrete filter that updates with each new sample and reports the estimate at its time, as ahrs,
#: VQF and BROAD's example code do).
HOLDS = ("zoh", "linear", "next")


class ImuSample(NamedTuple):
    """One IMU sample (or, stacked time-major, a log of them). Absent sensors are None; a missing reading
    inside a log is NaN.

    Fields:
        t:   time (s), shape () (a log: (T,)).
        gyr: angular rate (rad/s), body frame, (3,).
        acc: specific force (m/s^2), body frame, (3,) or None ("up" at rest).
        mag: magnetic field (unit of the data: nT, gauss or uT), body frame, (3,) or None.
    """

    t: Any
    gyr: Any
    acc: Optional[Any] = None
    mag: Optional[Any] = None


class VectorSample(NamedTuple):
    """One sample of gyro and general vector measurements with their references valid at that time (the
    setting of Trumpf, Mahony, Hamel, Lageman 2012, Sections III-IV).

    Fields (one time step; a log stacks them time-major, e.g. body_meas (T, n1, 3)):
        t:             time (s), shape ().
        gyr:           angular rate (rad/s), body frame, (3,).
        body_meas:     complementary measurements a_i = R^T a_ref_i(t), body frame, (n1, 3); None if n1 = 0.
        ref_inertial:  their references a_ref_i(t), inertial frame, (n1, 3); None = constant references of
                       the observer's params.
        inertial_meas: compatible measurements b_j = R b_ref_j(t), inertial frame, (n2, 3); None if n2 = 0.
        ref_body:      their references b_ref_j(t), body frame, (n2, 3); None = constant references.

    Vectors need not be unit. NaN marks a missing reading.
    """

    t: Any
    gyr: Any
    body_meas: Optional[Any] = None
    ref_inertial: Optional[Any] = None
    inertial_meas: Optional[Any] = None
    ref_body: Optional[Any] = None


class Interval(NamedTuple):
    """The samples at both ends of one step (``hold="linear"``): the input at the integrator's stage times is
    interpolated linearly between them (:func:`jaxatt.integrate.input_at`)."""

    start: Any
    end: Any


class Observer(NamedTuple):
    """An observer: pure functions over a state pytree (the shape of optax's ``GradientTransformation``).

    * ``init(params, first_sample) -> state``: the state at the time of the first sample.
    * ``step(params, state, u, dt) -> (state, out)``: advances the state by ``dt`` seconds; ``u`` is the input
      of the step (a sample, or an :class:`Interval` of two; see :data:`HOLDS`). ``out`` is the estimate at the
      end of the step and carries it as a field ``q`` (w, x, y, z) or ``r`` (3x3), body to navigation frame
      (with both, the estimate is read from ``q``).
    * ``output(params, state) -> out`` (optional): the estimate held by a state, with the structure ``step``
      returns; gives estimate 0 (``init``'s). Without it the state's own ``q`` or ``r`` field is used.
    * ``name``: a label for messages and files.
    * ``time_reversed(params) -> params`` (optional): the params with which the same observer runs on the
      time-reversed recording (the backward pass of the offline mode, :mod:`jaxatt.smoothing`), for params that
      change meaning when time runs backwards (a delay of one sensor behind another changes sign). Without it the
      backward pass uses the params unchanged.
    * ``hold`` (optional): the input of a step the observer is written for (:data:`HOLDS`): "next" for a filter
      that updates with each new sample (ahrs, VQF), "zoh" or "linear" for a continuous-time observer. Every
      runner uses it unless given a hold of its own; None (an observer that declares none): "next" at the front
      door (:func:`jaxatt.filter`, :func:`jaxatt.broad_score`, :func:`jaxatt.fit`, :func:`jaxatt.monte_carlo`),
      "zoh" in :mod:`jaxatt.montecarlo`, :mod:`jaxatt.engine` and the losses (:func:`jaxatt.engine.hold_for`).

    Gains live in the ``params`` pytree passed to every call, never in the closure, so ``jax.grad`` over gains
    and ``jax.vmap`` over seeds or gain grids need nothing more.
    """

    init: Callable[[Any, Any], Any]
    step: Callable[[Any, Any, Any, Any], tuple]
    name: str = "observer"
    output: Optional[Callable[[Any, Any], Any]] = None
    time_reversed: Optional[Callable[[Any], Any]] = None
    hold: Optional[str] = None
