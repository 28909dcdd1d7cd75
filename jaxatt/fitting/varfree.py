"""The variance-free loss: an observer's expected squared attitude error, predicted without Monte Carlo by
propagating the covariance of its linearised error dynamics along the noise-free run.

What is computed (one generic mechanism for every observer and scenario of :mod:`jaxatt.engine`):

* The **nominal run**: the scenario's truth and its noise-free samples (``scenario.sample(truth, 0, dt)``), the
  observer started by its own ``init`` from its params (no per-run ``init_params`` draw, see below) and stepped as
  in a Monte Carlo run (same hold, same alignment: estimate k >= 1 at t_k = k dt).
* The **noise model** comes from the scenario itself: the sample is a function ``sample(truth, n, dt)`` of the
  standard-normal block n (``scenario.n_channels`` numbers per sample; run k of a Monte Carlo draws them
  i.i.d. N(0, I)); its Jacobian L_k = d sample / d n at n = 0 maps the noise into the sample.
* The **linearised observer** works in the observer's own coordinates: the floating leaves of its state pytree
  flattened (R^ in R^9 as nine numbers, quaternions as four, etc.; nothing assumes a manifold). Per step,
  forward-mode derivatives (``vmap`` of ``jvp``) of ``step`` in the deviation v = [dx_k; n_k; n_{k+1}] (the
  noise of the sample(s) the step reads: n_k with ``hold="zoh"``, n_{k+1} with ``"next"``, both with
  ``"linear"``) give dx_{k+1} = A_k dx_k + B0_k n_k + B1_k n_{k+1}, and the covariance recursion (a discrete
  Lyapunov equation)

      Sigma_v = [[P_k, C_k, 0], [C_k^T, I, 0], [0, 0, I]],   P_{k+1} = J_k Sigma_v J_k^T,   C_{k+1} = B1_k,

  with J_k = [A_k, B0_k, B1_k] and C_k = Cov(dx_k, n_k) (n_k is read by step k - 1 when samples are interpolated
  and by ``init``, which sees sample 0: P_0 = J0 J0^T, C_0 = J0 with J0 = d init / d n_0).
* The **output map**: the estimate k + 1 is the step's output, a function of v too; the attitude error vector
  e(v) (the rotation vector of R^T R^, deg; or the ZYX Euler-angle errors, deg) is linearised in v, G = de/dv,
  and to first order e ~ N(mu, S) with mu = e(0) (the nominal error: transient, discretisation lag) and
  S = G Sigma_v G^T (3 x 3). Then E[theta^2] = |mu|^2 + tr S exactly for that Gaussian, and E[theta] is computed
  from mu and S by a one-dimensional integral (:func:`expected_norm`). theta is the angle of R^T R^, eq. (23) of
  Batista, Silvestre, Oliveira (2019, GES); both are averaged over time windows like
  :class:`jaxatt.fitting.losses.LossSpec`, so the loss of kind ``"angle_sq"`` is the expectation of the Monte
  Carlo loss of :mod:`jaxatt.fitting.losses` over the runs, without its sampling noise.

Only the coordinates that noise can reach are tracked ("active"): found once from the Jacobians of ``init`` and
of the first step (a coordinate is active if the noise moves it or an active coordinate does); the time, the
constants and the coefficients of a state are not. Every step also measures the largest derivative of an
untracked coordinate (``leak``, 0 when the choice holds all along the run); ``track="all"`` tracks every floating
coordinate.

When it holds: the errors must stay small enough for the linearisation about the nominal run (steady state of a
converging observer; noise small against the observer's nonlinearity; no switching of a discrete branch between
the nominal and the noisy runs). Not covered:

* Large random initial estimates (a study's ``init_params``, e.g. the NLIO Case 1 uniform initial attitude):
  the nominal run starts from the params' own initial estimate, and the prediction holds once the random start
  is forgotten (a converged steady-state window); during the transient the errors are far outside the linear
  range. Small random initial errors that are a smooth map of standard normals are linearised like the sensor
  noise (:class:`InitialNoise`: their covariance enters P_0).
* Noise that is not a smooth map of Gaussian numbers (the mixture of :mod:`jaxatt.sim.ahrs` with ``mix_prob > 0``
  and ``mix="mixture"`` picks its component by comparing a normal number with a threshold, whose derivative is
  zero: only the narrow component would be seen). Checked when the function is built: samples drawn with a few
  noise blocks must match their linearisation (ValueError otherwise). ``mix="sum"`` is linear and exact.
* The second-order shift of the mean, E[x] - x_nominal = O(P) (negligible when the errors are small).

Cost: one nominal run with (n_active + n_noise) forward tangents per step and a few n x n products; the error map,
its Jacobian and the moments only on the steps inside a window (``lax.cond``; every step when records are
asked for); reverse mode through it (``jax.grad`` in the gains) is checkpointed like the Monte Carlo loss
(:func:`jaxatt.engine.segment_length`). It uses the one scan of :mod:`jaxatt.engine` with its own source
(:class:`Nominal`), a wrapped observer (:func:`linearised_observer`) and a reducer (:func:`expected_reducer`).

Conventions: rotations map body to the navigation frame; angles in degrees (``_deg``); times in s.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple, Union

import jax
import jax.numpy as jnp
import numpy as np

from .. import engine, so3
from ..montecarlo import check_count, check_dt, check_duration
from ..types import Interval, Observer, check_step_count

__all__ = [
    "Linearised",
    "Nominal",
    "LinState",
    "LinOut",
    "linearised_observer",
    "InitialNoise",
    "expected_reducer",
    "expected_norm",
    "ERROR_VECTORS",
    "tracked_coordinates",
    "check_noise_model",
    "make_predict_fn",
    "PredictFn",
    "predict",
    "predict_study",
    "make_loss_fn",
    "varfree_objective",
]


# ------------------------------------------------------------------------------------------------------------
# Float leaves of a pytree as one vector
# ------------------------------------------------------------------------------------------------------------
def _is_float(a) -> bool:
    return jnp.issubdtype(a.dtype if hasattr(a, "dtype") else jnp.asarray(a).dtype, jnp.floating)


def _flat(tree) -> jax.Array:
    """The floating leaves of ``tree`` raveled and concatenated (leaf order of ``tree_leaves``)."""
    leaves = [jnp.ravel(a) for a in jax.tree_util.tree_leaves(tree) if _is_float(a)]
    return jnp.concatenate(leaves) if leaves else jnp.zeros((0,))


def _with_flat(tree, flat):
    """``tree`` with its floating leaves replaced by the consecutive pieces of ``flat``."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    out, i = [], 0
    for a in leaves:
        if _is_float(a):
            n = int(np.prod(jnp.shape(a)))
            out.append(jnp.reshape(flat[i : i + n], jnp.shape(a)).astype(jnp.asarray(a).dtype))
            i += n
        else:
            out.append(a)
    return jax.tree_util.tree_unflatten(treedef, out)


def _coordinate_names(tree) -> list:
    """One name per flattened floating coordinate, e.g. ``.r_hat[1, 2]``."""
    names = []
    for path, a in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if not _is_float(a):
            continue
        key = jax.tree_util.keystr(path)
        shape = np.shape(a)
        if shape == ():
            names.append(key)
        else:
            names.extend(f"{key}[{', '.join(map(str, ix))}]" for ix in np.ndindex(*shape))
    return names


def _plain(name: str) -> str:
    """A coordinate or leaf name without the path punctuation of ``keystr``: ``.r_hat[0, 1]`` -> ``r_hat[0, 1]``,
    ``['x']`` -> ``x``."""
    name = name.replace("['", ".").replace("']", "")
    return name[1:] if name.startswith(".") else name


def _jacobian(f, n: int, dtype, has_aux: bool = False):
    """(f(0), df/dv at 0 with the tangent axis last[, aux]) of ``f`` on R^n: forward mode, ``vmap`` of ``jvp`` over
    the n unit tangents (the primal is computed once; nested in an outer ``jvp`` or ``grad`` this stays cheaper
    than ``jax.linearize``)."""
    z = jnp.zeros((n,), dtype)
    eye = jnp.eye(n, dtype=dtype)
    if has_aux:
        return jax.vmap(lambda t: jax.jvp(f, (z,), (t,), has_aux=True), out_axes=(None, -1, None))(eye)
    return jax.vmap(lambda t: jax.jvp(f, (z,), (t,)), out_axes=(None, -1))(eye)


# ------------------------------------------------------------------------------------------------------------
# Source: the noise-free run with the noise Jacobian of every sample
# ------------------------------------------------------------------------------------------------------------
class Linearised(NamedTuple):
    """A noise-free sample and its Jacobian in the scenario's standard-normal noise block: ``jac`` has the
    structure of ``sample`` with a trailing axis of ``n_channels`` on every floating leaf (unit of the leaf per
    standard deviation), so the sample drawn with noise n is ``sample + jac @ n`` to first order."""

    sample: Any
    jac: Any


def _perturb(tree, jac, v):
    """``tree + jac @ v`` on the floating leaves (``jac``: the leaves with a trailing axis of len(v))."""
    return jax.tree_util.tree_map(lambda a, j: a + j @ v, tree, jac)


def linearised_sample(scenario, truth, dt) -> Linearised:
    """The noise-free sample at ``truth`` and its noise Jacobian (``scenario.sample`` linearised at n = 0)."""
    nc = int(scenario.n_channels)
    dtype = jnp.result_type(truth.t)
    s, jac = _jacobian(lambda n: scenario.sample(truth, n, dt), nc, dtype)
    return Linearised(s, jac)


class Nominal(NamedTuple):
    """The engine source of the nominal run: :class:`jaxatt.engine.Simulated`'s truth with noise-free samples,
    each a :class:`Linearised` (no per-run ``init_params`` draw; the batch item, a PRNG key, is not used).

    Fields: n_steps (T - 1), dt (s), sim_dtype (truth and samples)."""

    n_steps: int
    dt: float
    sim_dtype: Any

    def prepare(self, world):
        return engine.cast_floats(world, self.sim_dtype)

    def first(self, scn, item):
        truth0 = scn.truth_at(scn.r0, jnp.zeros((), self.sim_dtype))
        return scn.r0, linearised_sample(scn, truth0, self.dt), truth0, truth0.t

    def params_for_init(self, params, item):
        return params

    def block(self, scn, item, block_index, offset, length):
        return jnp.zeros((length,), self.sim_dtype)

    def constants(self, scn, item):
        return ()

    def advance(self, scn, r, k, x, const):
        t_k = k.astype(self.sim_dtype) * self.dt
        t_next = (k + 1).astype(self.sim_dtype) * self.dt
        r_next = scn.propagate(r, t_k, self.dt)
        truth = scn.truth_at(r_next, t_next)
        return r_next, linearised_sample(scn, truth, self.dt), truth, t_next, self.dt


# ------------------------------------------------------------------------------------------------------------
# The linearised observer
# ------------------------------------------------------------------------------------------------------------
class LinState(NamedTuple):
    """State of :func:`linearised_observer`: the observer's nominal state ``x``, the nominal sample at its time
    (for estimate 0), the covariance ``p`` (n_a, n_a) of the tracked coordinates' deviations, ``c`` (n_a,
    n_channels) = Cov(dx_k, n_k) with the noise of the sample at the state's time, and ``leak`` (), the largest
    derivative of an untracked coordinate so far (0 when the tracked set is closed)."""

    x: Any
    sample: Any
    p: jax.Array
    c: jax.Array
    leak: jax.Array


class LinOut(NamedTuple):
    """Output of :func:`linearised_observer`: the observer's nominal output ``out``, ``dout`` (one array per
    floating leaf of ``out``, in leaf order, with a trailing axis of len(v): d leaf / dv) and ``cov`` (len(v),
    len(v)), the covariance of v = [dx_k; noise read by the step]."""

    out: Any
    dout: tuple
    cov: jax.Array


def _float_leaves(tree) -> list:
    return [a for a in jax.tree_util.tree_leaves(tree) if _is_float(a)]


def perturbed_output(lo: LinOut, v):
    """The observer's output at deviation ``v``, to first order: each floating leaf ``out + dout @ v``."""
    leaves, treedef = jax.tree_util.tree_flatten(lo.out)
    out, i = [], 0
    for a in leaves:
        if _is_float(a):
            out.append(a + lo.dout[i] @ v)
            i += 1
        else:
            out.append(a)
    return jax.tree_util.tree_unflatten(treedef, out)


def _cov_v(p, c, n_channels: int, prev: bool, nxt: bool):
    """Covariance of v = [dx; n_prev (if read); n_next (if read)]: n_prev correlates with dx through ``c``
    (Cov(dx, n_prev)), n_next is independent of both; both noises are standard normal."""
    na, nc = p.shape[0], n_channels
    nv = na + nc * (int(prev) + int(nxt))
    cov = jnp.zeros((nv, nv), p.dtype).at[:na, :na].set(p)
    if prev:
        cov = cov.at[:na, na : na + nc].set(c).at[na : na + nc, :na].set(c.T)
    return cov.at[na:, na:].set(jnp.eye(nv - na, dtype=p.dtype))


def _step_jacobian(observer: Observer, hold: str, act, n_channels: int, p, x, u, dt):
    """(J_state (N, nv), J_out (one per floating leaf of the output, trailing axis nv), new state, output) of
    ``observer.step`` at the nominal state ``x`` and the :class:`Linearised` input ``u`` (as the engine hands it
    for ``hold``), in v = [dx of the coordinates ``act``; noise of the sample(s) the step reads]."""
    flat_x = _flat(x)
    na, nc = len(act), int(n_channels)
    prev, nxt = hold in ("zoh", "linear"), hold in ("next", "linear")
    nv = na + nc * (int(prev) + int(nxt))
    lp = (u.start if hold == "linear" else u) if prev else None
    ln = (u.end if hold == "linear" else u) if nxt else None

    def f(v):
        xx = _with_flat(x, flat_x.at[act].add(v[:na]))
        sp = _perturb(lp.sample, lp.jac, v[na : na + nc]) if prev else None
        sn = _perturb(ln.sample, ln.jac, v[nv - nc :]) if nxt else None
        uu = Interval(sp, sn) if hold == "linear" else (sp if hold == "zoh" else sn)
        new, out = observer.step(p, xx, uu, dt)
        return (_flat(new), tuple(_float_leaves(out))), (new, out)

    _, (jn, jo), (new, out) = _jacobian(f, nv, flat_x.dtype, has_aux=True)
    return jn, jo, new, out


class InitialNoise(NamedTuple):
    """A random initial estimate as a smooth map of standard normals: ``fn(params, z) -> params`` with z ~ N(0, I)
    of length ``n`` (e.g. ``p._replace(r_hat_0=p.r_hat_0 @ so3.exp(sigma * z))`` for Gaussian initial attitude
    errors of ``sigma`` rad per axis); ``fn(params, 0)`` must be ``params``. Its Jacobian adds
    J J^T to the covariance of ``init``'s state. ``fn`` must be hashable (a module-level function)."""

    fn: Callable
    n: int


@functools.lru_cache(maxsize=64)
def linearised_observer(
    observer: Observer, hold: str, active: Tuple[int, ...], n_channels: int, initial: Optional[InitialNoise] = None
) -> Observer:
    """``observer`` stepped on :class:`Linearised` samples with the covariance of its tracked coordinates
    ``active`` (indices into the flattened floating leaves of its state) propagated alongside (the recursion of
    the module docstring); ``initial`` adds the covariance of a random initial estimate. State
    :class:`LinState`, output :class:`LinOut`. Cached on its arguments, so the jitted scan of
    :mod:`jaxatt.engine` is reused."""
    engine.check_hold(hold)
    act = np.asarray(active, int)
    na, nc = len(act), int(n_channels)
    prev, nxt = hold in ("zoh", "linear"), hold in ("next", "linear")
    nv = na + nc * (int(prev) + int(nxt))

    def untracked(jac):
        """max |row| of the untracked coordinates of a Jacobian (N, ...)."""
        mask = np.ones(jac.shape[0], bool)
        mask[act] = False
        return jnp.max(jnp.abs(jac[mask]), initial=0.0) if mask.any() else jnp.zeros((), jac.dtype)

    def init(p, lin0: Linearised) -> LinState:
        s0 = lin0.sample
        dtype = jnp.result_type(*_float_leaves(s0))
        x0 = observer.init(p, s0)
        _, j0 = _jacobian(lambda n: _flat(observer.init(p, _perturb(s0, lin0.jac, n))), nc, dtype)
        ja = j0[act]
        p0, leak = ja @ ja.T, untracked(j0)
        if initial is not None:
            _, jz = _jacobian(lambda z: _flat(observer.init(initial.fn(p, z), s0)), int(initial.n), dtype)
            p0, leak = p0 + jz[act] @ jz[act].T, jnp.maximum(leak, untracked(jz))
        return LinState(x0, s0, p0, ja, leak.astype(ja.dtype))

    def step(p, s: LinState, u, dt):
        jn, jo, new, out = _step_jacobian(observer, hold, act, nc, p, s.x, u, dt)
        cov = _cov_v(s.p, s.c, nc, prev, nxt)
        ja = jn[act]
        p_new = ja @ cov @ ja.T
        p_new = 0.5 * (p_new + p_new.T)
        c_new = ja[:, nv - nc :] if nxt else jnp.zeros((na, nc), s.p.dtype)
        leak = jnp.maximum(s.leak, untracked(jn))
        return LinState(new, s.sample, p_new, c_new, leak), LinOut(out, tuple(jo), cov)

    def output(p, s: LinState) -> LinOut:
        """Estimate 0 (``init``'s) with its derivative in the tracked coordinates (covariance ``s.p``)."""
        flat_x = _flat(s.x)
        one = jnp.ones((), flat_x.dtype)

        def f(v):
            out = engine.initial_output(observer, p, _with_flat(s.x, flat_x.at[act].add(v[:na])), s.sample, one)
            return tuple(_float_leaves(out)), out

        _, jo, out = _jacobian(f, nv, flat_x.dtype, has_aux=True)
        return LinOut(out, tuple(jo), _cov_v(s.p, s.c, nc, prev, nxt))

    return Observer(init=init, step=step, name=f"{observer.name} (linearised)", output=output)


# ------------------------------------------------------------------------------------------------------------
# Expected errors
# ------------------------------------------------------------------------------------------------------------
def _rotvec_deg(truth, out):
    """Rotation vector (deg) of R^T R^, body frame: its norm is the angle of eq. (23) (batista2019-ges)."""
    r = engine.estimate_r(out)
    return jnp.rad2deg(so3.log(so3.mm(jnp.swapaxes(truth.r.astype(r.dtype), -1, -2), r)))


def _euler_deg(truth, out):
    """ZYX roll, pitch, yaw errors (deg), wrapped differences estimate - truth (the NLIO paper's tables)."""
    r = engine.estimate_r(out)
    return jnp.rad2deg(jnp.stack(so3.euler_error_zyx(truth.r.astype(r.dtype), r)))


#: Error vectors whose squared norm is a pointwise loss of :mod:`jaxatt.fitting.losses`, by that loss's name.
ERROR_VECTORS: Dict[str, Callable] = {"angle_sq": _rotvec_deg, "euler_sq": _euler_deg}

# Trapezoid nodes in y = log(s tr) for expected_norm (|y| <= 40, step 0.4: relative error about 1e-8).
_Y = np.linspace(-40.0, 40.0, 201)


def expected_norm(mu, cov):
    """E|z| for z ~ N(mu, cov) in R^d (any d; ``cov`` positive semi-definite, may be singular).

    |z| = (4 pi)^(-1/2) int_0^inf (1 - exp(-s |z|^2)) s^(-3/2) ds, and E exp(-s |z|^2) =
    det(I + 2 s cov)^(-1/2) exp(-s mu^T (I + 2 s cov)^(-1) mu); the integral over s = exp(y) / (|mu|^2 + tr cov)
    is a trapezoid rule in y (smooth, decaying both ways). Differentiable; no eigen-decomposition."""
    mu = jnp.asarray(mu)
    d = mu.shape[-1]
    scale = jnp.sum(mu * mu) + jnp.trace(cov)
    safe = jnp.where(scale > 0, scale, 1.0)
    y = jnp.asarray(_Y, mu.dtype)
    s = jnp.exp(y) / safe
    eye = jnp.eye(d, dtype=mu.dtype)
    m = eye[None] + 2.0 * s[:, None, None] * cov[None]
    det = jnp.linalg.det(m)
    quad = jnp.einsum("i,nij,j->n", mu, jnp.linalg.inv(m), mu)
    g = 1.0 - jnp.exp(-s * quad) / jnp.sqrt(det)
    # ds s^(-3/2) = s^(-1/2) dy
    integral = jnp.sum(g * jnp.sqrt(1.0 / s)) * (_Y[1] - _Y[0])
    return jnp.where(scale > 0, integral / (2.0 * jnp.sqrt(jnp.pi)), 0.0)


class _Acc(NamedTuple):
    sq: jax.Array  # (n_windows,) sums of E|e|^2 (deg^2)
    norm: jax.Array  # (n_windows,) sums of E|e| (deg)
    bias_sq: jax.Array  # (n_windows,) sums of |mu|^2 (deg^2)
    n: jax.Array  # (n_windows,) sample counts
    errors: Dict[str, jax.Array]  # name -> (n_windows, size) sums of E[e_i^2]


@functools.lru_cache(maxsize=64)
def expected_reducer(
    windows: Tuple[Tuple[str, float, float], ...], kind="angle_sq", errors_fn=None, every: int = 0, mean_norm=True
):
    """The engine reducer of the nominal run: per window ((name, start_s, end_s), ...; start <= t < end), the
    sums over the estimates of E|e|^2 (deg^2), E|e| (deg) and |mu|^2 of the error vector ``kind`` (a key of
    :data:`ERROR_VECTORS` or a hashable ``fn(truth, out) -> (d,)``), and with ``errors_fn`` (named error
    vectors, :func:`jaxatt.montecarlo.monte_carlo`'s) the sums of each element's E[e_i^2]. ``every``: record
    (t, E|e|^2, E|e|, mu) of every ``every``-th estimate. ``mean_norm=False`` skips E|e| (NaN; a loss needs only
    E|e|^2, and its reverse pass is then cheaper)."""
    vec = ERROR_VECTORS[kind] if isinstance(kind, str) else kind
    starts = np.asarray([w[1] for w in windows], float)
    ends = np.asarray([w[2] for w in windows], float)
    nw = len(windows)

    def moments(truth, lo: LinOut):
        dtype = lo.cov.dtype
        nv = lo.cov.shape[-1]

        def e(v):
            o = perturbed_output(lo, v)
            named = {} if errors_fn is None else {k: jnp.ravel(a) for k, a in errors_fn(truth, o).items()}
            return vec(truth, o), named

        (mu, named0), (g, named_g) = _jacobian(e, nv, dtype)
        s = g @ lo.cov @ g.T
        sq = jnp.sum(mu * mu) + jnp.trace(s)
        named_sq = {k: named0[k] ** 2 + jnp.einsum("iv,vw,iw->i", named_g[k], lo.cov, named_g[k]) for k in named0}
        nrm = expected_norm(mu, s) if mean_norm else jnp.full((), jnp.nan, dtype)
        return mu, sq, nrm, named_sq

    def init(t0, truth0, lo):
        dtype = lo.cov.dtype
        z = jnp.zeros((nw,), dtype)
        named = {}
        if errors_fn is not None:
            named = {
                k: jnp.zeros((nw, int(np.prod(jnp.shape(a)))), dtype) for k, a in errors_fn(truth0, lo.out).items()
            }
        rec = None
        if every:
            mu, sq, nrm, _ = moments(truth0, lo)
            rec = {"t": t0, "mean_sq": sq, "mean_norm": nrm, "mu": mu}
        return _Acc(z, z, z, z, named), rec

    def update(acc, t, truth, lo):
        w = ((t >= starts) & (t < ends)).astype(acc.sq.dtype)
        if every:  # every record needs the moments
            mu, sq, nrm, named = moments(truth, lo)
        else:  # outside the windows nothing is added: skip the error map and its Jacobian there
            mu0, sq0, nrm0, named0 = jax.tree_util.tree_map(jnp.zeros_like, jax.eval_shape(moments, truth, lo))
            zero = (mu0, sq0, nrm0 if mean_norm else nrm0 + jnp.nan, named0)  # E|e| skipped: NaN, as inside
            mu, sq, nrm, named = jax.lax.cond(jnp.any(w > 0), moments, lambda *_: zero, truth, lo)
        acc = _Acc(
            acc.sq + w * sq,
            acc.norm + w * nrm,
            acc.bias_sq + w * jnp.sum(mu * mu),
            acc.n + w,
            {k: acc.errors[k] + w[:, None] * named[k][None, :] for k in acc.errors},
        )
        rec = {"t": t, "mean_sq": sq, "mean_norm": nrm, "mu": mu} if every else None
        return acc, rec

    return engine.Reducer(init, update, lambda acc: acc, every)


# ------------------------------------------------------------------------------------------------------------
# Tracked coordinates
# ------------------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=64)
def _probe(observer: Observer, hold: str, n: int, nc: int, initial, dt: float, dtype_name: str):
    """``probe(params, scenario) -> (P_0, J_1)`` (jitted, cached on the structure so a second set-up reuses it):
    the covariance of ``init``'s state and the Jacobian of the first step with every one of the ``n`` floating
    coordinates tracked."""
    dtype = jnp.dtype(dtype_name)
    src = Nominal(1, dt, dtype)
    obs = linearised_observer(observer, hold, tuple(range(n)), nc, initial)

    @jax.jit
    def probe(p, scn):
        _, lin0, _, _ = src.first(scn, None)
        s0 = obs.init(p, lin0)
        _, lin1, _, _, _ = src.advance(scn, scn.r0, jnp.zeros((), jnp.int32), None, ())
        u = lin0 if hold == "zoh" else (lin1 if hold == "next" else Interval(lin0, lin1))
        j = _step_jacobian(observer, hold, np.arange(n), nc, p, s0.x, u, jnp.asarray(dt, dtype))[0]
        return s0.p, j

    return probe


def tracked_coordinates(
    observer: Observer, scenario, params, *, dt: float, hold: Optional[str] = None, track=None, dtype=None, initial=None
):
    """(indices, names) of the coordinates of the flattened floating state that the noise can reach.

    ``track``: None (found from ``init`` and the first step: a coordinate is tracked if the noise moves it, or a
    tracked coordinate does, closed under the step's Jacobian), ``"all"`` (every floating coordinate) or field
    names / leaf paths (coordinates whose name starts with one of them, e.g. ``("x1", "r_hat")``). ``hold``: None,
    the observer's own, else "zoh"."""
    hold = engine.hold_for(observer, hold)
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    scn = engine.cast_floats(scenario, dtype)
    p = engine.cast_floats(params, dtype)
    nc = int(scn.n_channels)
    src = Nominal(1, float(dt), dtype)
    x0 = jax.eval_shape(  # shapes only: the names need no evaluation
        lambda p, scn: engine.cast_floats(observer.init(p, src.first(scn, None)[1].sample), dtype), p, scn
    )
    names = _coordinate_names(x0)
    n = len(names)
    if track is not None:
        if isinstance(track, str) and track == "all":
            return tuple(range(n)), names
        pre = tuple(_plain(q) for q in ((track,) if isinstance(track, str) else tuple(track)))
        want = [
            i
            for i, nm in enumerate(names)
            if any(_plain(nm) == q or _plain(nm).startswith((q + "[", q + ".")) for q in pre)
        ]
        if not want:
            raise ValueError(f"track: no state coordinate starts with {pre}; coordinates: {sorted(set(names))[:20]}")
        return tuple(want), names
    p0, j = _probe(observer, hold, n, nc, initial, float(dt), dtype.name)(p, scn)
    p0, j = np.asarray(p0), np.asarray(j)
    a, b = j[:, :n] - np.eye(n), j[:, n:]
    reach = np.any(p0 != 0, axis=1) | np.any(b != 0, axis=1)
    while True:
        new = reach | np.any(a[:, reach] != 0, axis=1)
        if np.array_equal(new, reach):
            break
        reach = new
    idx = tuple(int(i) for i in np.flatnonzero(reach))
    if not idx:
        raise ValueError(f"{observer.name}: the scenario's noise reaches no coordinate of the observer's state")
    return idx, names


def check_noise_model(scenario, *, dt: float, dtype=None, draws: int = 16) -> None:
    """ValueError when the scenario's first sample is not (close to) affine in its standard-normal noise block:
    for ``draws`` fixed normal blocks n, |sample(n) - sample(0) - L n| must stay below 10 % of |L n| (a smooth
    noise map passes, a threshold such as a Gaussian mixture's component selector does not)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    scn = engine.cast_floats(scenario, dtype)
    off, step = _noise_check(float(dt), int(draws), int(scn.n_channels), dtype.name)(scn)
    if np.any(np.asarray(off) > 0.1 * np.asarray(step)):
        raise ValueError(
            "the scenario's samples are not a smooth function of its noise (e.g. a Gaussian mixture's component "
            "selector): the variance-free loss would see only their derivative at zero noise; use Monte Carlo"
        )


@functools.lru_cache(maxsize=64)
def _noise_check(dt: float, draws: int, nc: int, dtype_name: str):
    """``check(scenario) -> (|sample(n) - sample(0) - L n|, |L n|)`` for ``draws`` fixed normal blocks n (jitted,
    cached: a second set-up of the same structure reuses it)."""
    dtype = jnp.dtype(dtype_name)

    @jax.jit
    def check(scn):
        truth = scn.truth_at(scn.r0, jnp.zeros((), dtype))
        lin = linearised_sample(scn, truth, dt)
        ns = jax.random.normal(jax.random.PRNGKey(20), (draws, nc), dtype)

        def one(n):
            exact = _flat(scn.sample(truth, n, dt))
            first = _flat(_perturb(lin.sample, lin.jac, n))
            return jnp.linalg.norm(exact - first), jnp.linalg.norm(first - _flat(lin.sample))

        return jax.vmap(one)(ns)

    return check


# ------------------------------------------------------------------------------------------------------------
# Prediction and loss
# ------------------------------------------------------------------------------------------------------------
def _windows(windows) -> Tuple[Tuple[str, float, float], ...]:
    out = []
    for w in windows:
        try:
            name, start, end = w[:3]
        except (TypeError, ValueError):
            raise ValueError(f"each window must be (name, start_s, end_s[, weight]), got {w!r}") from None
        start, end = float(start), float(end)
        if not (math.isfinite(start) and end > start):
            raise ValueError(f"window {name!r} must have a finite start and end > start, got [{start}, {end})")
        out.append((str(name), start, end))
    if not out:
        raise ValueError("give at least one window (name, start_s, end_s)")
    return tuple(out)


def _check_kind(kind):
    if not ((isinstance(kind, str) and kind in ERROR_VECTORS) or (callable(kind) and not isinstance(kind, str))):
        raise ValueError(
            f"variance-free kind must be one of {sorted(ERROR_VECTORS)} (squared norm of an error vector) or a "
            f"callable fn(truth, out) -> error vector, got {kind!r}"
        )
    return kind


@functools.lru_cache(maxsize=64)
def _summary_post(names: Tuple[str, ...]):
    def post(res):
        acc: _Acc = jax.tree_util.tree_map(lambda a: a[0], res.summary)  # the single nominal run
        state = jax.tree_util.tree_map(lambda a: a[0], res.state) if res.state is not None else None
        cnt = jnp.maximum(acc.n, 1.0)
        out = {
            "mean_sq_deg2": acc.sq / cnt,
            "mean_deg": acc.norm / cnt,
            "bias_sq_deg2": acc.bias_sq / cnt,
            "count": acc.n,
            "errors_mean_sq": {k: v / cnt[:, None] for k, v in acc.errors.items()},
            "leak": state.leak if state is not None else jnp.zeros(()),
        }
        if res.records is not None:
            out["records"] = jax.tree_util.tree_map(lambda a: a[0], res.records)
        return out

    return post


class PredictFn(NamedTuple):
    """``fn(scenario, params) -> dict`` of :func:`make_predict_fn`, with the names of the tracked coordinates
    and the windows."""

    compiled: Callable
    tracked: Tuple[str, ...]
    windows: Tuple[Tuple[str, float, float], ...]

    def __call__(self, scenario, params) -> dict:
        return self.compiled(scenario, params, jnp.zeros((1, 2), jnp.uint32))


def make_predict_fn(
    observer: Observer,
    scenario,
    params,
    *,
    duration: float,
    dt: float,
    windows=(("all", 0.0, math.inf),),
    kind="angle_sq",
    errors_fn=None,
    hold: Optional[str] = None,
    dtype=None,
    checkpoint: Union[str, int, bool, None] = False,
    step_remat: Optional[bool] = None,
    track=None,
    every: int = 0,
    mean_norm: bool = True,
    initial: Optional[InitialNoise] = None,
):
    """``fn(scenario, params) -> dict``: the expected errors of ``observer`` on ``scenario`` (see the module
    docstring), jitted and differentiable in ``params`` (and the scenario's arrays).

    The dict: ``mean_sq_deg2`` (n_windows,) window means of E|e|^2 (deg^2; ``kind="angle_sq"``: E[theta^2]),
    ``mean_deg`` (n_windows,) window means of E|e| (deg), ``bias_sq_deg2`` the nominal part |mu|^2 of the first,
    ``count`` estimates per window, ``errors_mean_sq`` (name -> (n_windows, size): window means of E[e_i^2] of
    ``errors_fn``'s named errors), ``leak`` (0 when the tracked coordinates are closed; see
    :func:`tracked_coordinates`) and, with ``every``, ``records`` (t, mean_sq, mean_norm, mu) of every
    ``every``-th estimate.

    The run stops at the last estimate a window needs (all windows finite) or at ``duration``.
    ``scenario`` and ``params`` given here choose the tracked coordinates (``track``) and the structure; the
    returned function takes new values of both. ``checkpoint`` / ``step_remat``: as
    :func:`jaxatt.fitting.losses.make_loss_fn` (needed for ``jax.grad`` over long runs; off by default).
    ``mean_norm=False``: skip E|e| (``mean_deg`` NaN). ``initial``: a random initial estimate
    (:class:`InitialNoise`; default none: the params' own).
    """
    dt, duration = check_dt(dt), check_duration(duration)
    n_steps = check_step_count(duration, dt)
    every = check_count("every", every)
    hold = engine.hold_for(observer, hold)
    _check_kind(kind)
    wins = _windows(windows)
    last = max(w[2] for w in wins)
    if math.isfinite(last):  # propagate only as far as the last window needs (t_k = k dt < end; one spare)
        n_steps = max(1, min(n_steps, math.ceil(last / dt - 1e-9)))
    obs_dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    sim_dtype = jnp.result_type(float)
    check_noise_model(scenario, dt=dt, dtype=obs_dtype)
    active, names = tracked_coordinates(
        observer, scenario, params, dt=dt, hold=hold, track=track, dtype=obs_dtype, initial=initial
    )
    lin = linearised_observer(observer, hold, active, int(scenario.n_channels), initial)
    segment = engine.segment_length(n_steps, checkpoint)
    if every and segment and segment % every:
        raise ValueError(f"every ({every}) must divide the checkpoint segment ({segment} steps)")
    fn = engine.compiled(
        lin,
        Nominal(n_steps, dt, sim_dtype),
        expected_reducer(wins, kind, errors_fn, every, bool(mean_norm)),
        None,
        post=_summary_post(tuple(w[0] for w in wins)),
        hold=hold,
        obs_dtype=obs_dtype,
        segment=segment,
        step_remat=bool(segment) if step_remat is None else bool(step_remat),
        keep_state=True,
    )
    return PredictFn(fn, tuple(names[i] for i in active), wins)


def _report(res: dict, wins, tracked) -> dict:
    """Concrete results as plain floats per window, with RMS values."""
    out: Dict[str, Any] = {"windows": {}, "leak": float(res["leak"]), "tracked": list(tracked)}
    for i, (name, start, end) in enumerate(wins):
        ms = float(res["mean_sq_deg2"][i])
        out["windows"][name] = {
            "start_s": start,
            "end_s": None if math.isinf(end) else end,
            "count": int(res["count"][i]),
            "mean_sq_deg2": ms,
            "rms_deg": math.sqrt(ms),
            "mean_deg": float(res["mean_deg"][i]),
            "bias_rms_deg": math.sqrt(float(res["bias_sq_deg2"][i])),
            "errors_rms": {k: np.sqrt(np.asarray(v[i])).tolist() for k, v in res["errors_mean_sq"].items()},
        }
    if "records" in res:
        out["records"] = {k: np.asarray(v) for k, v in res["records"].items()}
    return out


def predict(
    observer: Observer,
    scenario,
    params,
    *,
    duration: float,
    dt: float,
    windows=(("all", 0.0, math.inf),),
    kind="angle_sq",
    errors_fn=None,
    hold: Optional[str] = None,
    dtype=None,
    track=None,
    every: int = 0,
    leak_tol: float = 0.0,
    initial: Optional[InitialNoise] = None,
) -> dict:
    """The expected errors of ``observer`` (params ``params``) on ``scenario`` over ``duration`` s at steps of
    ``dt`` s, as plain numbers: ``windows.<name>.{mean_sq_deg2, rms_deg, mean_deg, bias_rms_deg, count,
    errors_rms}`` (RMS = sqrt of the window mean of E|e|^2; ``mean_deg`` the window mean of E|e|, comparable with
    :func:`jaxatt.montecarlo.monte_carlo`'s ``mean_angle_error_deg`` for ``kind="angle_sq"``), ``leak``,
    ``tracked`` (coordinate names) and, with ``every``, ``records`` (numpy arrays). ValueError when an untracked
    coordinate moved by more than ``leak_tol`` (pass ``track="all"``). ``initial``: a random initial estimate
    (:class:`InitialNoise`). See :func:`make_predict_fn`."""
    if (
        isinstance(leak_tol, bool)
        or not isinstance(leak_tol, (int, float, np.integer, np.floating))
        or not leak_tol >= 0
    ):
        raise ValueError(f"leak_tol must be a number >= 0, got {leak_tol!r}")
    fn = make_predict_fn(
        observer,
        scenario,
        params,
        duration=duration,
        dt=dt,
        windows=windows,
        kind=kind,
        errors_fn=errors_fn,
        hold=hold,
        dtype=dtype,
        track=track,
        every=every,
        initial=initial,
    )
    res = _report(fn(scenario, params), fn.windows, fn.tracked)
    if res["leak"] > leak_tol:
        raise ValueError(
            f"{observer.name}: an untracked state coordinate moved with the noise (derivative {res['leak']:.3g}); "
            "pass track='all'"
        )
    return res


def predict_study(study, params=None, *, windows=None, kind=None, errors: bool = True, every: int = 0, **config):
    """:func:`predict` on a study's set-up (:meth:`jaxatt.studies.base.Study.setup` with ``config``): its tuned
    observer, scenario, hold, duration and step, with ``params`` (default: the paper's gains; a dict of gain name ->
    value put into them, a gains-file path, or the observer's Params), its loss windows
    (default: "steady" [window_start, end) and "transient" [0, window_start)), its loss kind (if it is one of
    :data:`ERROR_VECTORS`, else ``"angle_sq"``) and its named errors."""
    from .. import studies

    st = studies.get(study)
    s = st.setup(**config)
    p = studies.base.setup_params(s, params)
    if windows is None:
        windows = tuple((n, a, b) for n, (a, b) in s.loss_windows.items())
    if kind is None:
        kind = s.loss_kind if s.loss_kind in ERROR_VECTORS else "angle_sq"
    return predict(
        s.observer,
        s.scenario,
        p,
        duration=s.duration,
        dt=s.dt,
        windows=windows,
        kind=kind,
        errors_fn=s.errors_fn if errors else None,
        hold=s.hold,
        every=every,
    )


def make_loss_fn(
    observer: Observer,
    scenario,
    params,
    *,
    duration: float,
    dt: float,
    spec,
    hold: Optional[str] = None,
    dtype=None,
    checkpoint: Union[str, int, bool, None] = "auto",
    step_remat: Optional[bool] = None,
    track=None,
):
    """``loss(scenario, params) -> (loss, aux)``: the expectation over the noise of the Monte Carlo loss of
    :func:`jaxatt.fitting.losses.make_loss_fn` for the :class:`~jaxatt.fitting.losses.LossSpec` ``spec`` (kind
    ``"angle_sq"`` or ``"euler_sq"``: sum over windows of weight x window mean of E|e|^2, deg^2), to first order
    in the noise and without sampling noise. ``aux``: ``window_loss`` (n_windows,), ``window_rms_deg``
    (n_windows,: sqrt of ``window_loss``, deg), ``leak``. Differentiable in ``params``; checkpointed for long runs
    (the reverse pass stores one carry per segment, :func:`jaxatt.engine.segment_length`)."""
    _check_kind(spec.kind)
    fn = make_predict_fn(
        observer,
        scenario,
        params,
        duration=duration,
        dt=dt,
        windows=tuple(w[:3] for w in spec.windows),
        kind=spec.kind,
        hold=hold,
        dtype=dtype,
        checkpoint=checkpoint,
        step_remat=step_remat,
        track=track,
        mean_norm=False,
    )
    weights = np.asarray([float(w[3]) for w in spec.windows])

    def loss(scenario, params):
        r = fn(scenario, params)
        val = jnp.sum(jnp.asarray(weights, r["mean_sq_deg2"].dtype) * r["mean_sq_deg2"])
        return val, {"window_loss": r["mean_sq_deg2"], "window_rms_deg": jnp.sqrt(r["mean_sq_deg2"]), "leak": r["leak"]}

    return loss


def varfree_objective(setup, bound, spec, *, dtype=None, checkpoint="auto", step_remat=None, track=None):
    """``objective(theta, batch) -> (loss, aux)`` for :func:`jaxatt.fitting.fitter.optimize`: the variance-free
    loss (:func:`make_loss_fn`) of a study set-up's observer at the gains ``bound.constrain(theta)``; ``batch`` is
    ignored (nothing is sampled). ``aux["metric"]``: the RMS error (deg) over the first window."""
    f = make_loss_fn(
        setup.observer,
        setup.scenario,
        setup.params,
        duration=setup.duration,
        dt=setup.dt,
        spec=spec,
        hold=setup.hold,
        dtype=dtype,
        checkpoint=checkpoint,
        step_remat=step_remat,
        track=track,
    )

    def objective(theta, batch=None):
        loss, aux = f(setup.scenario, bound.constrain(theta))
        return loss, {**aux, "metric": aux["window_rms_deg"][0]}

    return objective
