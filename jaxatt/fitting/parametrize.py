"""Constrained parametrizations of observer gains, for gradient-based tuning (:mod:`jaxatt.fitting`).

An optimizer moves an unconstrained vector ``u``; a :class:`Transform` maps it to a gain that is always valid:

* :class:`Positive`: x = scale * exp(u) (``"log"``) or x = scale * softplus(u) (``"softplus"``), elementwise.
  With the log map Adam's steps are relative changes (a step of 0.05 changes a gain by about 5 %), whatever
  the gain's unit or size (the batista-so3 gains span 1e-23 ... 1e-1).
* :class:`Schedule`: a piecewise-constant gain (Table 1 of batista2019-ges / -so3) as a positive vector, one
  value per interval; the switch times stay fixed (they are another field of the Params, never tuned).
* :class:`SPD`: a symmetric positive-definite matrix (a gain matrix Q, Kp, a covariance) as
  G = S C C^T S, C lower-triangular with a positive (exp) diagonal, S = diag(scale) fixed (by default the
  square roots of the initial diagonal, so C = I for a diagonal initial G and the off-diagonal entries of C
  are dimensionless). ``structure="diagonal"`` keeps the off-diagonal entries of C at their initial values.
* :class:`Bounded`: low + (high - low) * sigmoid(u), for gains in an open interval (e.g. a threshold in (0, 1)).
* :class:`Identity`: unconstrained.

A :class:`Parametrization` is a set of transforms for some fields of a ``Params`` NamedTuple (any observer:
the code only uses ``_replace`` and field names), plus optional masks that freeze chosen elements. Fields
without a transform are never touched. Its :meth:`Parametrization.bind` takes the starting params and
returns a bound copy that maps ``theta`` (a dict field -> unconstrained array, a pytree for optax) to params
with :meth:`BoundParametrization.constrain`; frozen elements get exactly zero gradient.

Which fields of an observer's Params are gains, with their units and constraints, is declared once in the
observer registry (:class:`jaxatt.observers.registry.Gain`); :func:`for_gains` maps those declarations to
transforms, :func:`for_params` builds a parametrization for any Params of your own (every positive field).

Conventions: gains keep the units of the observer's Params (SI; the vector-sensor unit of the scenario, nT
for the Batista papers).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from typing import Any, Dict, Mapping, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Transform",
    "Positive",
    "Schedule",
    "SPD",
    "Bounded",
    "Identity",
    "LogBasis",
    "ScaledSPD",
    "Parametrization",
    "BoundParametrization",
    "from_constraint",
    "for_gains",
    "for_params",
    "schedule_mask",
    "schedule_mask_from",
    "refine_schedule",
    "softplus_inverse",
]

from ..schedule import mask as schedule_mask  # noqa: E402
from ..schedule import mask_from as schedule_mask_from
from ..schedule import refine as refine_schedule
from ..types import shown


def softplus_inverse(y):
    """u with softplus(u) = y (y > 0), stable for small and large y."""
    y = np.asarray(y, float)
    return np.where(y > 30.0, y, np.log(np.expm1(np.minimum(y, 30.0))))


# ------------------------------------------------------------------------------------------------------
# Transforms
# ------------------------------------------------------------------------------------------------------
class Transform(abc.ABC):
    """Abstract base: ``bind(value) -> Transform`` (fixes reference scales from a starting value),
    ``inverse(value) -> u`` (numpy, concrete), ``forward(u) -> value`` (jax, differentiable)."""

    def bind(self, value) -> "Transform":
        return self

    @abc.abstractmethod
    def inverse(self, value) -> np.ndarray:
        """Unconstrained u of a valid gain value (numpy)."""

    @abc.abstractmethod
    def forward(self, u):
        """The valid gain of any unconstrained u (jax, differentiable)."""

    def describe(self) -> str:
        return type(self).__name__


@dataclasses.dataclass(frozen=True)
class Identity(Transform):
    """x = scale * u (no constraint). ``scale`` sets what one unit of u is worth, so that an optimizer's step of
    about ``lr`` in u is a sensible step of the gain (e.g. 0.01 for a delay in seconds)."""

    scale: float = 1.0

    def inverse(self, value):
        return np.asarray(value, float) / self.scale

    def forward(self, u):
        return u * self.scale if self.scale != 1.0 else u

    def describe(self):
        return "unconstrained" if self.scale == 1.0 else f"unconstrained (scale {self.scale:g})"


@dataclasses.dataclass(frozen=True)
class Positive(Transform):
    """Elementwise positive: x = scale * exp(u) (method "log") or scale * softplus(u) (method "softplus").

    ``scale``: None picks 1 for "log" (u = log x) and the starting value for "softplus" (so the start is
    u = softplus^-1(1) = 0.54, where the map is neither flat nor linear); a number or array fixes it.
    """

    method: str = "log"
    scale: Any = None
    bounds: Any = None

    def __post_init__(self):
        if self.method not in ("log", "softplus"):
            raise ValueError(f"Positive.method must be 'log' or 'softplus', got {self.method!r}")

    def u_bounds(self):
        """(low, high) of u that keep the gain inside ``bounds`` (None without bounds)."""
        if self.bounds is None:
            return None
        lo, hi = (float(b) for b in self.bounds)
        return float(np.min(self.inverse(lo))), float(np.max(self.inverse(hi)))

    def bind(self, value):
        if self.scale is not None:
            return self
        v = np.asarray(value, float)
        if self.method == "log":
            return dataclasses.replace(self, scale=1.0)
        return dataclasses.replace(self, scale=np.where(v > 0, v, 1.0))

    def inverse(self, value):
        v = np.asarray(value, float)
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(f"a positive gain must be finite and > 0, got {shown(v)}")
        s = np.asarray(1.0 if self.scale is None else self.scale, float)
        return np.log(v / s) if self.method == "log" else softplus_inverse(v / s)

    def forward(self, u):
        s = 1.0 if self.scale is None else jnp.asarray(self.scale, u.dtype)
        return s * (jnp.exp(u) if self.method == "log" else jax.nn.softplus(u))

    def describe(self):
        return f"positive ({self.method})"


@dataclasses.dataclass(frozen=True)
class Schedule(Positive):
    """Piecewise-constant positive gain: one value per interval (elementwise :class:`Positive`); the switch
    times (``times_field`` of the Params) are fixed. Freeze chosen intervals with :func:`schedule_mask`."""

    times_field: str = "switch_times"

    def describe(self):
        return f"piecewise-constant schedule, positive ({self.method}), switch times fixed ({self.times_field})"


@dataclasses.dataclass(frozen=True)
class SPD(Transform):
    """Symmetric positive-definite n x n matrix G = S C C^T S, C lower-triangular with exp'd diagonal.

    u holds the n (n + 1) / 2 entries of C's lower triangle, row-major (``np.tril_indices``), with the
    diagonal entries as logarithms. ``scale`` (n,) fixes S; None takes sqrt(diag(G0)) at :meth:`bind`.
    ``structure="diagonal"``: only the diagonal is tunable (the off-diagonal entries of u are masked by
    :class:`Parametrization`, G stays diagonal if it starts diagonal).
    """

    scale: Any = None
    structure: str = "full"

    def __post_init__(self):
        if self.structure not in ("full", "diagonal"):
            raise ValueError(f"SPD.structure must be 'full' or 'diagonal', got {self.structure!r}")

    def bind(self, value):
        if self.scale is not None:
            return self
        g = np.asarray(value, float)
        return dataclasses.replace(self, scale=np.sqrt(np.abs(np.diag(g))))

    def inverse(self, value):
        g = np.asarray(value, float)
        if g.ndim != 2 or g.shape[0] != g.shape[1]:
            raise ValueError(f"an SPD gain must be a square matrix, got shape {g.shape}")
        s = np.asarray(self.bind(g).scale, float)
        gs = 0.5 * (g + g.T) / np.outer(s, s)
        try:
            c = np.linalg.cholesky(gs)
        except np.linalg.LinAlgError as e:
            raise ValueError("an SPD gain must be symmetric positive definite") from e
        n = g.shape[0]
        i, j = np.tril_indices(n)
        u = c[i, j].copy()
        d = i == j
        u[d] = np.log(c[i[d], j[d]])
        return u

    def forward(self, u):
        m = u.shape[-1]
        n = int(round((math.isqrt(8 * m + 1) - 1) / 2))
        i, j = np.tril_indices(n)
        d = i == j
        vals = jnp.where(jnp.asarray(d), jnp.exp(jnp.where(jnp.asarray(d), u, 0.0)), u)
        c = jnp.zeros((n, n), u.dtype).at[i, j].set(vals)
        s = jnp.ones(n, u.dtype) if self.scale is None else jnp.asarray(self.scale, u.dtype)
        cs = s[:, None] * c
        g = cs @ cs.T
        return 0.5 * (g + g.T)  # exactly symmetric whatever order the matrix product sums in

    @staticmethod
    def diagonal_mask(n: int) -> np.ndarray:
        """Mask over u that is True on the diagonal entries of C only."""
        i, j = np.tril_indices(n)
        return i == j

    def describe(self):
        return f"symmetric positive definite (scaled Cholesky, {self.structure})"


@dataclasses.dataclass(frozen=True)
class Bounded(Transform):
    """x = low + (high - low) * sigmoid(u), elementwise, in the open interval (low, high)."""

    low: float = 0.0
    high: float = 1.0

    def inverse(self, value):
        v = np.asarray(value, float)
        f = (v - self.low) / (self.high - self.low)
        if np.any(f <= 0) or np.any(f >= 1):
            raise ValueError(f"a Bounded gain must lie in ({self.low}, {self.high}), got {shown(v)}")
        return np.log(f) - np.log1p(-f)

    def forward(self, u):
        return self.low + (self.high - self.low) * jax.nn.sigmoid(u)

    def describe(self):
        return f"bounded in ({self.low:g}, {self.high:g}) (sigmoid)"


@dataclasses.dataclass(frozen=True, eq=False)
class LogBasis(Transform):
    """Positive gain moved by a few numbers through a fixed basis: log x = log x0 + B u, u of length m.

    ``basis`` (n, m) for a gain of n values (e.g. the intervals of a schedule); x0 is the starting value, fixed
    at :meth:`bind`, so u = 0 is the start. Use it to tune a schedule through a handful of shapes (one level
    for a group of intervals, a power law t^u over them, ...): the gradient of u sums the per-interval
    gradients along each shape, which averages their noise. :meth:`inverse` of a value outside the span is
    the least-squares fit.
    """

    basis: Any
    ref: Any = None

    def bind(self, value):
        v = np.asarray(value, float)
        b = np.asarray(self.basis, float)
        if b.ndim != 2 or b.shape[0] != v.size:
            raise ValueError(f"LogBasis: basis must be ({v.size}, m) for a gain of {v.size} values, got {b.shape}")
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(f"a LogBasis gain must be finite and > 0, got {shown(v)}")
        return dataclasses.replace(self, ref=v)

    def inverse(self, value):
        ref = np.asarray(self.bind(value).ref if self.ref is None else self.ref, float)
        v = np.asarray(value, float)
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(f"a LogBasis gain must be finite and > 0, got {shown(v)}")
        b = np.asarray(self.basis, float)
        return np.linalg.lstsq(b, np.log(v / ref).reshape(-1), rcond=None)[0]

    def forward(self, u):
        ref = jnp.asarray(self.ref, u.dtype)
        return ref * jnp.exp(jnp.asarray(self.basis, u.dtype) @ u).reshape(ref.shape)

    def describe(self):
        return f"positive, log x = log x0 + B u with a fixed {np.shape(self.basis)} basis"


@dataclasses.dataclass(frozen=True, eq=False)
class ScaledSPD(Transform):
    """SPD matrix rescaled along fixed groups of coordinates: G = D G0 D, D = diag(exp(B u)), u of length m.

    ``basis`` (n, m) for an n x n gain; G0 is the starting value (fixed at :meth:`bind`), u = 0 is the start,
    and G stays SPD for every u (a congruence by a positive diagonal). E.g. ``np.ones((9, 1))`` is one
    overall scale (G x exp(2 u)); ``np.kron(np.eye(3), np.ones((3, 1)))`` one scale per block of 3.
    :meth:`inverse` fits u to the diagonal of the value (least squares in log).
    """

    basis: Any
    ref: Any = None

    def bind(self, value):
        g = np.asarray(value, float)
        b = np.asarray(self.basis, float)
        if g.ndim != 2 or g.shape[0] != g.shape[1] or b.ndim != 2 or b.shape[0] != g.shape[0]:
            raise ValueError(f"ScaledSPD: need a square gain and an (n, m) basis, got {g.shape} and {b.shape}")
        if np.min(np.linalg.eigvalsh(0.5 * (g + g.T))) <= 0:
            raise ValueError("a ScaledSPD gain must be symmetric positive definite")
        return dataclasses.replace(self, ref=g)

    def inverse(self, value):
        ref = np.asarray(self.bind(value).ref if self.ref is None else self.ref, float)
        g = np.asarray(value, float)
        return np.linalg.lstsq(np.asarray(self.basis, float), 0.5 * np.log(np.diag(g) / np.diag(ref)), rcond=None)[0]

    def forward(self, u):
        d = jnp.exp(jnp.asarray(self.basis, u.dtype) @ u)
        return d[:, None] * jnp.asarray(self.ref, u.dtype) * d[None, :]

    def describe(self):
        return f"symmetric positive definite, G = D G0 D with D = diag(exp(B u)), fixed {np.shape(self.basis)} basis"


# ------------------------------------------------------------------------------------------------------
# Parametrization of a Params NamedTuple
# ------------------------------------------------------------------------------------------------------
class BoundParametrization(NamedTuple):
    """A :class:`Parametrization` bound to starting params: transforms with their reference scales fixed,
    the starting unconstrained values ``theta0`` and the masks (True = tunable) over them."""

    transforms: Dict[str, Transform]
    masks: Dict[str, np.ndarray]
    theta0: Dict[str, np.ndarray]
    base: Any

    def constrain(self, theta: Mapping[str, jax.Array], base=None):
        """Params with the tunable fields replaced by ``transform.forward(theta[field])``; masked-out
        elements keep their starting values with zero gradient (exactly the values of ``base`` for the
        elementwise transforms; an :class:`SPD` rebuilds G from the frozen Cholesky entries, to rounding).
        ``base`` (default: the bound params) supplies every other field."""
        base = self.base if base is None else base
        new = {}
        for f, tr in self.transforms.items():
            u = jnp.asarray(theta[f])
            ref = jnp.asarray(getattr(base, f))
            m = self.masks.get(f)
            if m is not None and not np.all(m):
                mj = jnp.asarray(m)
                v = tr.forward(jnp.where(mj, u, jnp.asarray(self.theta0[f], u.dtype))).astype(ref.dtype)
                # elementwise transforms: frozen elements are the base values exactly (no exp/log round trip)
                new[f] = jnp.where(mj, v, ref) if v.shape == mj.shape == ref.shape else v
            else:
                new[f] = tr.forward(u).astype(ref.dtype)
        return base._replace(**new)

    def unconstrain(self, params) -> Dict[str, np.ndarray]:
        """theta (numpy) of concrete params."""
        return {f: np.asarray(tr.inverse(np.asarray(getattr(params, f))), float) for f, tr in self.transforms.items()}

    def init(self, dtype=None) -> Dict[str, jax.Array]:
        """The starting theta as jax arrays."""
        return {f: jnp.asarray(v, dtype or jnp.result_type(float)) for f, v in self.theta0.items()}

    def zero_frozen(self, grads):
        """Gradients with the masked-out elements set to exactly zero (constrain already does this; this is
        for gradients computed some other way)."""
        out = dict(grads)
        for f, m in self.masks.items():
            if f in out and not np.all(m):
                out[f] = jnp.where(jnp.asarray(m), out[f], 0.0)
        return out

    def clip(self, theta):
        """``theta`` with each bounded positive gain's u clipped into its bounds (projected gradient steps)."""
        out = dict(theta)
        for f, tr in self.transforms.items():
            ub = tr.u_bounds() if isinstance(tr, Positive) else None
            if ub is not None:
                out[f] = jnp.clip(out[f], ub[0], ub[1])
        return out

    def n_free(self) -> int:
        """Number of tunable scalars."""
        return int(
            sum(int(np.sum(self.masks[f])) if f in self.masks else int(np.size(v)) for f, v in self.theta0.items())
        )


@dataclasses.dataclass(frozen=True)
class Parametrization:
    """Transforms for chosen fields of a Params NamedTuple, and masks that freeze chosen elements.

    Args:
        transforms: field name -> :class:`Transform`. Fields not named are fixed.
        masks: field name -> boolean array over that field's unconstrained vector (True = tunable). For a
            :class:`Positive` / :class:`Schedule` it has the gain's shape; for an :class:`SPD` it is over the
            n (n + 1) / 2 Cholesky entries.
    """

    transforms: Mapping[str, Transform]
    masks: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def freeze(self, *fields: str) -> "Parametrization":
        """A copy with ``fields`` fixed (removed from the tunable set)."""
        bad = [f for f in fields if f not in self.transforms]
        if bad:
            raise ValueError(f"cannot freeze {bad}: not tunable here (tunable: {sorted(self.transforms)})")
        return Parametrization(
            {k: v for k, v in self.transforms.items() if k not in fields},
            {k: v for k, v in self.masks.items() if k not in fields},
        )

    def only(self, *fields: str) -> "Parametrization":
        """A copy where only ``fields`` are tunable."""
        bad = [f for f in fields if f not in self.transforms]
        if bad:
            raise ValueError(f"unknown tunable fields {bad} (tunable: {sorted(self.transforms)})")
        return self.freeze(*[f for f in self.transforms if f not in fields])

    def with_mask(self, field: str, mask) -> "Parametrization":
        if field not in self.transforms:
            raise ValueError(f"{field!r} is not tunable here (tunable: {sorted(self.transforms)})")
        return Parametrization(dict(self.transforms), {**self.masks, field: np.asarray(mask, bool)})

    def bind(self, params) -> BoundParametrization:
        """Fix reference scales from ``params`` (concrete) and compute the starting theta."""
        missing = [f for f in self.transforms if f not in params._fields]
        if missing:
            raise ValueError(f"fields {missing} are not in {type(params).__name__} (fields: {params._fields})")
        trs, th0, masks = {}, {}, {}
        for f, tr in self.transforms.items():
            v = np.asarray(getattr(params, f), float)
            trs[f] = tr.bind(v)
            try:
                th0[f] = np.asarray(trs[f].inverse(v), float)
            except ValueError as e:  # name the gain (k_i = 0 is a switched-off term: freeze it or start it > 0)
                raise ValueError(f"params.{f}: {e}") from None
            m = self.masks.get(f)
            if m is None and isinstance(tr, SPD) and tr.structure == "diagonal":
                m = SPD.diagonal_mask(v.shape[0])
            if m is not None:
                try:
                    m = np.broadcast_to(np.asarray(m, bool), th0[f].shape).copy()
                except ValueError:
                    raise ValueError(
                        f"masks[{f!r}] of shape {list(np.shape(m))} does not fit its {list(th0[f].shape)} learnt "
                        "values (one True / False per value, or one for all)"
                    ) from None
                masks[f] = m
        return BoundParametrization(trs, masks, th0, params)


# ------------------------------------------------------------------------------------------------------
# From the registry's gain declarations, or from any Params
# ------------------------------------------------------------------------------------------------------
def from_constraint(gain) -> Transform:
    """The transform of a :class:`jaxatt.observers.registry.Gain`'s constraint (log maps for positive gains)."""
    c = gain.constraint
    if c == "positive":
        return Positive("log", bounds=gain.bounds)
    if c == "schedule":
        return Schedule("log")
    if c == "spd":
        return SPD()
    if c == "spd-diagonal":
        return SPD(structure="diagonal")
    if c == "real":
        return Identity(scale=gain.scale or 1.0)
    raise ValueError(f"gain {gain.field}: unknown constraint {c!r}")


def for_gains(
    gains: Sequence[Any],
    *,
    tune: Optional[Sequence[str]] = None,
    freeze: Sequence[str] = (),
    masks: Optional[Mapping[str, Any]] = None,
    method: Optional[str] = None,
    transforms: Optional[Mapping[str, Transform]] = None,
) -> Parametrization:
    """The Parametrization of declared gains (:class:`jaxatt.observers.registry.Gain`): those tuned by default, or
    exactly ``tune``; minus ``freeze``; optional ``masks`` (field -> bool array over its unconstrained vector, True =
    tunable), ``method`` ("log" / "softplus") for every positive gain, and ``transforms`` (field -> Transform)
    replacing the map of chosen gains (e.g. a :class:`LogBasis` for a schedule)."""
    known = {g.field: g for g in gains}
    for label, fields in (
        ("tune", tune or ()),
        ("freeze", freeze),
        ("transforms", transforms or {}),
        ("masks", masks or {}),
    ):
        bad = [f for f in fields if f not in known]
        if bad:
            raise ValueError(f"{label}: {bad} are not gains of this observer (gains: {sorted(known)})")
    chosen = list(tune) if tune is not None else [g.field for g in gains if g.tuned]
    trs = {}
    for f in chosen:
        if f in freeze:
            continue
        tr = (transforms or {}).get(f, from_constraint(known[f]))
        if method is not None and isinstance(tr, Positive):
            tr = dataclasses.replace(tr, method=method)
        trs[f] = tr
    if not trs:
        raise ValueError("no gain left to tune")
    p = Parametrization(trs)
    for f, m in (masks or {}).items():
        p = p.with_mask(f, m)
    return p


def for_params(params, tune: Optional[Sequence[str]] = None) -> Parametrization:
    """A Parametrization of a Params NamedTuple of your own. By default every floating field whose values are all
    > 0, kept positive (learnt in log space); a floating field with values <= 0 is left fixed with a warning that
    names it. ``tune``: the fields to learn, positive ones in log space and the others unconstrained (one unit of
    the optimiser's variable = the field's largest magnitude, or 1). Integer fields are not gains (write 1.0, not
    1). Other fields are fixed."""
    if not hasattr(params, "_fields"):
        raise ValueError(f"params must be a NamedTuple (fields are the gains), got {type(params).__name__}")
    if tune is not None:
        bad = [f for f in tune if f not in params._fields]
        if bad:
            raise ValueError(f"tune: {bad} are not fields of {type(params).__name__} (fields: {params._fields})")
    trs: Dict[str, Transform] = {}
    signed, integers = [], []
    for f in params._fields:
        v = getattr(params, f)
        if v is None:
            continue
        a = np.asarray(v)
        floating = np.issubdtype(a.dtype, np.floating) and a.size > 0
        positive = floating and bool(np.all(a > 0))
        if np.issubdtype(a.dtype, np.integer) or a.dtype == bool:
            integers.append(f)
        if tune is None:
            if positive:
                trs[f] = Positive("log")
            elif floating and np.all(np.isfinite(a)):
                signed.append(f)
        elif f in tune:
            if not floating:
                kind = "an integer array" if f in integers else f"{a.dtype} of size {a.size}"
                raise ValueError(f"params.{f} = {a} is {kind}, not a gain to tune: give it as floats (e.g. 1.0)")
            scale = float(np.max(np.abs(a))) if np.all(np.isfinite(a)) else 0.0
            trs[f] = Positive("log") if positive else Identity(scale=scale if scale > 0 else 1.0)
    if not trs:
        hint = f" (integer fields {integers} are not gains: write 1.0, not 1)" if integers else ""
        raise ValueError(f"no positive floating field of {type(params).__name__} to tune{hint}; name them with tune=")
    if signed:
        import warnings

        warnings.warn(
            f"fit: {type(params).__name__} fields {signed} have values <= 0 and are left fixed; name them in tune= to "
            "learn them unconstrained",
            stacklevel=3,
        )
    return Parametrization(trs)
