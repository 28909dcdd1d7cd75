"""The filtering floor: the smallest expected attitude error any estimator can reach with a study's sensors, from
the Kalman filter (Riccati recursion) of the problem linearised along the noise-free run.

For a linear-Gaussian model the Kalman filter's covariance is the posterior Cramér-Rao bound: no estimator that
sees the same samples has a smaller mean squared error. Here the model is the scenario itself, linearised about
its noise-free run (the truth R(t) of ``scenario.truth_at`` / ``propagate`` and its noise-free samples), so the
ratio observer / floor of :mod:`jaxatt.fitting.varfree` (which linearises an observer along the same run) says
how much of an observer's error is the sensors' and how much is the observer's.

The linearised problem (any scenario of :mod:`jaxatt.sim`: ``truth_at``, ``propagate``, ``sample``,
``n_channels``; frames: R maps body to navigation):

* **Unknowns**: the attitude error eps (rad, navigation frame: R = exp(S(eps)) R_bar) and, with ``bias=True``,
  the constant gyro-bias error beta (rad/s, body; the scenario's ``gyro_bias`` perturbed). What the papers take
  as known stays known: the references of the vector sensors (their ``*_nav`` / inertial values) and, for the
  Batista studies, the Earth rate in the navigation frame ({}^I omega_E, eq. (4) of Batista et al. 2019 (GES)).
  The body-frame Earth rate omega_E(t) = R^T {}^I omega_E, which those observers estimate, is a function of the
  attitude and is not a separate unknown.
* **The gyro is the input**: the body rate is an arbitrary unknown signal (no prior on the trajectory); the gyro
  sample gyr_k = omega + c(R, b) + L_g n_k (c: the Earth rate R^T {}^I omega_E and the bias, as the scenario
  writes them; L_g n_k: its noise, per sample) defines the rate over the integration step through the same
  ``hold`` as the observers (``"zoh"``: sample k over [t_k, t_k+1); ``"next"``: sample k+1; ``"linear"``: the
  line between them). The kinematics R' = R S(omega) give, to first order,

      eps' = -R_bar (C_eps eps + C_b beta + g(t)),   C_eps = dc/deps,  C_b = dc/db,  g = the held gyro noise,

  (Batista et al. 2019 (GES), eqs. (1), (3): C_eps = R_bar^T S({}^I omega_E), so eps' = -S({}^I omega_E) eps
  - R_bar g: the Earth rate couples the heading to the measured directions, which is what makes the heading
  observable from one vector). Per step, eps_{k+1} = Phi eps_k - Gamma_b beta - Gamma_0 g_k - Gamma_1 g_{k+1}
  with Phi = expm(A dt) (A = -R_bar C_eps at mid-step) and the Gamma's Simpson's rule of
  int expm(A (t_{k+1} - s)) R_bar(s) w(s) ds (w: the hold's weights of samples k and k+1; R_bar at t_k,
  t_k + dt/2, t_{k+1}).
* **Vector measurements**: every other floating field of the sample, y = h(R) + L_y n; H = dh/deps at the
  nominal truth, measurement covariance L_y L_y^T (the scenario's own noise densities, bursts and ``noise_scale``
  included), by forward-mode derivatives of ``scenario.sample``. Fields without noise and without dependence on
  R (e.g. the references a :class:`jaxatt.types.VectorSample` carries) are dropped. The gyro and vector noises
  must use disjoint channels of the noise block (true of every scenario of :mod:`jaxatt.sim`).
* **Information pattern**: estimate k (time t_k = k dt) uses the samples an observer's estimate k uses with the
  same hold (:mod:`jaxatt.engine`): samples 0 ... k - 1 with ``"zoh"`` (the predicted covariance P_k|k-1),
  0 ... k with ``"next"`` / ``"linear"`` (the filtered P_k|k); estimate 0 uses sample 0. With ``"linear"`` the
  gyro noise of sample k enters two steps, so the state is augmented with it (exact, no approximation).
* **Prior** (:class:`Prior`): eps(0) ~ N(0, attitude_rad^2 I), beta ~ N(0, bias_rad_s^2 I). The default
  attitude_rad = pi / sqrt(3) (1.81 rad, the standard deviation of an angle uniform in [-pi, pi]) stands for
  "no prior": every study starts its observers far from the truth (Batista: R^(0) 180 deg / 179 deg off;
  sensors2020 Case 1: random ZYX angles uniform in [-pi, pi]; Trumpf et al.: 150 deg off) and their global
  convergence is what is compared. The default bias_rad_s = 0.05 rad/s is the bias bound L_b the sensors2020
  observers are given (:mod:`jaxatt.studies.nlio`). Over windows that start minutes after t = 0 the floor does
  not depend on either (checked in research/floor.py); ``Prior(0, 0)`` (a known start) is the floor to compare
  with an observer started at the truth.

Output per estimate: E[theta^2] = tr P_eps (rad^2 -> deg^2) and E[theta] = E|eps| for eps ~ N(0, P_eps)
(:func:`jaxatt.fitting.varfree.expected_norm`); theta is the angle of R^T R^, eq. (23) of Batista et al. 2019
(GES). Window means over start <= t_k < end as :func:`jaxatt.fitting.varfree.predict`, so the ratios are like
for like; with ``smoother=True`` also the Rauch-Tung-Striebel smoother's (every sample, past and future: the
offline floor of :mod:`jaxatt.smoothing`-style forward-backward estimates).

Cost: one ``lax.scan`` over the samples with a few (n x n) products (n = 6 to 12) and forward derivatives of
``truth_at`` / ``sample``; float64 only (the heading variance spans seven decades along a run).
"""

from __future__ import annotations

import functools
import math
from typing import Any, Dict, NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import engine, so3
from ..montecarlo import check_count, check_dt, check_duration
from ..types import check_step_count, shown
from .varfree import _windows, expected_norm

__all__ = ["Prior", "Model", "floor", "floor_study", "heading_floor_closed_form"]


class Prior(NamedTuple):
    """Initial uncertainty of the floor's estimator: per-axis standard deviations of the attitude error
    (``attitude_rad``, rad, navigation frame) and of the gyro bias (``bias_rad_s``, rad/s, body; used when the
    bias is an unknown). See the module docstring for the defaults."""

    attitude_rad: float = math.pi / math.sqrt(3.0)
    bias_rad_s: float = 0.05


class Model(NamedTuple):
    """The linearised problem's structure, found once from the scenario at t = 0: ``rows`` (indices of the noisy
    measurement components in the flattened non-gyro floating fields of a sample), ``names`` (their field
    names), ``bias`` (whether the gyro bias is an unknown), ``n`` (unknowns: 3 or 6)."""

    rows: Tuple[int, ...]
    names: Tuple[str, ...]
    bias: bool
    n: int


def _fields(sample) -> Tuple[Dict[str, Any], Any]:
    """(non-gyro floating fields by name, gyro) of a sample NamedTuple (``t`` and None fields dropped)."""
    if not hasattr(sample, "_fields") or "gyr" not in sample._fields:
        raise ValueError(f"the scenario's samples must be a NamedTuple with a 'gyr' field, got {type(sample).__name__}")
    out = {}
    for k in sample._fields:
        v = getattr(sample, k)
        if k in ("t", "gyr") or v is None or not jnp.issubdtype(jnp.asarray(v).dtype, jnp.floating):
            continue
        out[k] = v
    return out, sample.gyr


def _flat_meas(sample) -> jax.Array:
    f, _ = _fields(sample)
    return jnp.concatenate([jnp.ravel(v) for v in f.values()]) if f else jnp.zeros((0,))


def _perturbed(scn, r, t, dt, x, noise, bias: bool):
    """Noise-free-or-noisy sample at t for the truth exp(S(eps)) r and bias + beta (x = [eps; beta])."""
    if bias:
        scn = scn._replace(gyro_bias=scn.gyro_bias + x[3:6])
    truth = scn.truth_at(so3.mm(so3.exp(x[:3]), r), t)
    return scn.sample(truth, noise, dt)


def _local(scn, r, t, dt, n: int, bias: bool, rows):
    """At the truth r (time t): R_bar (3, 3), C = dc/dx (3, n) of the gyro's attitude/bias-dependent part, the
    gyro noise map Lg (3, nc), and for the measurement rows: H (m, n), Ly (m, nc)."""
    nc = int(scn.n_channels)
    dtype = r.dtype
    zx, zn = jnp.zeros((n,), dtype), jnp.zeros((nc,), dtype)

    def f(x, noise):
        s = _perturbed(scn, r, t, dt, x, noise, bias)
        return s.gyr, _flat_meas(s)[jnp.asarray(rows, int)] if len(rows) else jnp.zeros((0,), dtype)

    (cg, hy) = jax.jacfwd(f, argnums=(0, 1))(zx, zn)
    return r, cg[0], cg[1], hy[0], hy[1]


def _gyro_jac(scn, r, t, dt, n: int, bias: bool):
    """C = dc/dx (3, n) of the gyro's attitude/bias-dependent part at the truth r (time t)."""
    zx, zn = jnp.zeros((n,), r.dtype), jnp.zeros((int(scn.n_channels),), r.dtype)
    return jax.jacfwd(lambda x: _perturbed(scn, r, t, dt, x, zn, bias).gyr)(zx)


def _model(scn, dt, bias: Optional[bool]) -> Model:
    """Structure of the problem from the first sample (concrete): noisy rows, bias, checks."""
    dtype = jnp.result_type(float)
    has_bias = "gyro_bias" in getattr(scn, "_fields", ())
    if bias is None:
        bias = bool(has_bias) and not isinstance(scn, _imu_scenario_type())
    if bias and not has_bias:
        raise ValueError(f"bias=True needs a scenario with a gyro_bias field, got {type(scn).__name__}")
    n = 6 if bias else 3
    truth0 = scn.truth_at(scn.r0, jnp.zeros((), dtype))
    s0 = scn.sample(truth0, jnp.zeros((int(scn.n_channels),), dtype), dt)
    fields, _ = _fields(s0)
    names = [f"{k}[{i}]" for k, v in fields.items() for i in range(int(np.prod(jnp.shape(v))))]
    allrows = tuple(range(len(names)))
    _, _, lg, h, ly = _local(scn, scn.r0, jnp.zeros((), dtype), dt, n, bias, allrows)
    h, ly, lg = np.asarray(h), np.asarray(ly), np.asarray(lg)
    noisy = np.any(ly != 0, axis=1)
    seen = np.any(h != 0, axis=1)
    bad = [names[i] for i in np.flatnonzero(seen & ~noisy)]
    if bad:
        raise ValueError(f"measurements without noise ({', '.join(bad[:4])}): the floor would be zero")
    if not np.any(lg != 0):
        raise ValueError("the gyro has no noise: the floor would be zero")
    shared = np.any(lg != 0, axis=0) & np.any(ly[noisy] != 0, axis=0)
    if np.any(shared):
        raise ValueError("gyro and vector measurements share noise channels: correlated noise is not supported")
    rows = tuple(int(i) for i in np.flatnonzero(noisy))
    if not rows:
        raise ValueError("the scenario has no noisy vector measurement: the attitude is unobservable")
    return Model(rows, tuple(names[i] for i in rows), bool(bias), n)


def _imu_scenario_type():
    from ..sim.imu import ImuScenario

    return ImuScenario


def _joseph(p, h, rm, nx: int):
    """Kalman update of the augmented covariance ``p`` with y = [H 0] s + v, Cov v = ``rm`` (Joseph form)."""
    na = p.shape[0]
    hh = jnp.zeros((h.shape[0], na), p.dtype).at[:, :nx].set(h)
    s = hh @ p @ hh.T + rm
    k = jnp.linalg.solve(s, hh @ p).T
    a = jnp.eye(na, dtype=p.dtype) - k @ hh
    p = a @ p @ a.T + k @ rm @ k.T
    return 0.5 * (p + p.T)


def _window_sums(starts, ends, t, sq, nrm):
    w = ((t >= starts) & (t < ends)).astype(sq.dtype)
    return w * sq, w * nrm, w


def floor(
    scenario,
    *,
    duration: float,
    dt: float,
    windows=(("all", 0.0, math.inf),),
    hold: str = "zoh",
    bias: Optional[bool] = None,
    prior: Optional[Prior] = None,
    smoother: bool = False,
    every: int = 0,
) -> dict:
    """The filtering floor of ``scenario`` over ``duration`` s sampled every ``dt`` s (see the module docstring).

    ``windows``: ((name, start_s, end_s), ...), as :func:`jaxatt.fitting.varfree.predict`. ``hold``: the
    observers' hold ("zoh", "next", "linear"). ``bias``: whether the gyro bias is an unknown (default: yes for
    scenarios with a ``gyro_bias`` field other than :class:`jaxatt.sim.imu.ImuScenario`, whose high-grade gyro
    the Batista papers take as unbiased). ``prior``: :class:`Prior`. ``smoother``: also the RTS smoother's
    windows (``smoothed``). ``every``: also ``records`` of every ``every``-th estimate: ``t`` (s), ``p_att``
    (3, 3) the attitude-error covariance (rad^2, navigation frame), ``mean_sq_deg2``, ``mean_deg``.

    Returns ``windows.<name>.{start_s, end_s, count, mean_sq_deg2, rms_deg, mean_deg}``: the Kalman filter's
    window mean of E[theta^2] (deg^2; a lower bound for every estimator with the same samples), its square root
    (deg) and its window mean of E[theta] (deg; that of the optimal estimator, comparable with varfree's
    ``mean_deg`` but not a bound on every estimator's), plus ``unknowns``, ``measurements`` (names of the
    measurement components), ``prior``, ``hold``, ``dt``, ``n_steps``. ValueError (one line) on bad input."""
    if not jax.config.values["jax_enable_x64"]:
        raise ValueError("the floor needs float64: call jax.config.update('jax_enable_x64', True) first")
    dt, duration = check_dt(dt), check_duration(duration)
    n_steps = check_step_count(duration, dt)
    every = check_count("every", every)
    if bias is not None and not isinstance(bias, (bool, np.bool_)):
        raise ValueError(f"bias must be True, False or None (the scenario decides), got {bias!r}")
    if not isinstance(smoother, (bool, np.bool_)):
        raise ValueError(f"smoother must be True or False, got {smoother!r}")
    engine.check_hold(hold)
    wins = _windows(windows)
    last = max(w[2] for w in wins)
    if math.isfinite(last):
        n_steps = max(1, min(n_steps, math.ceil(last / dt - 1e-9)))
    prior = Prior() if prior is None else prior
    try:
        if not isinstance(prior, tuple) or len(prior) != 2 or any(isinstance(x, (bool, str)) for x in prior):
            raise TypeError
        pa, pb = float(prior[0]), float(prior[1])
    except (TypeError, ValueError):
        raise ValueError(
            f"prior must be a Prior(attitude_rad, bias_rad_s) of two numbers or None, got {prior!r}"
        ) from None
    if not (math.isfinite(pa) and math.isfinite(pb) and pa >= 0 and pb >= 0):
        raise ValueError(f"prior standard deviations must be finite and >= 0, got {shown(prior)}")
    scn = engine.cast_floats(scenario, jnp.float64)
    mdl = _model(scn, dt, bias)
    for name, start, _ in wins:
        if start > n_steps * dt:
            raise ValueError(f"window {name!r} starts at {start} s, after the run's last estimate ({n_steps * dt} s)")
    res = _run(scn, mdl, dt, n_steps, hold, wins, pa, pb, every, bool(smoother))
    out: Dict[str, Any] = {
        "windows": _report(res["sq"], res["nrm"], res["cnt"], wins),
        "unknowns": ["attitude (3, rad, navigation frame)"] + (["gyro bias (3, rad/s, body)"] if mdl.bias else []),
        "measurements": list(mdl.names),
        "prior": {"attitude_rad": pa, "bias_rad_s": pb if mdl.bias else None},
        "hold": hold,
        "dt": dt,
        "n_steps": n_steps,
    }
    if smoother:
        out["smoothed"] = _report(res["s_sq"], res["s_nrm"], res["cnt"], wins)
    if every:
        out["records"] = {k: np.asarray(v) for k, v in res["records"].items()}
    return out


def _report(sq, nrm, cnt, wins) -> dict:
    out = {}
    for i, (name, start, end) in enumerate(wins):
        c = float(cnt[i])
        ms = float(sq[i]) / max(c, 1.0)
        out[name] = {
            "start_s": start,
            "end_s": None if math.isinf(end) else end,
            "count": int(c),
            "mean_sq_deg2": ms,
            "rms_deg": math.sqrt(ms),
            "mean_deg": float(nrm[i]) / max(c, 1.0),
        }
    return out


def _expm(a):
    """exp(a) of a small matrix: Taylor series of order 8 after 2^-6 scaling, squared back (relative error below
    1e-15 for |a| <= 1; the floor's |A dt| is the Earth rate times dt, about 1e-6)."""
    x = a / 64.0
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    term, out = eye, eye
    for i in range(1, 9):
        term = term @ x / i
        out = out + term
    for _ in range(6):
        out = out @ out
    return out


def _run(scn, mdl: Model, dt, n_steps, hold, wins, pa, pb, every, smoother):
    fn = _compiled(mdl, float(dt), int(n_steps), hold, len(wins), int(every), bool(smoother))
    starts = jnp.asarray([w[1] for w in wins], jnp.float64)
    ends = jnp.asarray([w[2] for w in wins], jnp.float64)
    acc, ys, p00, sq0, nrm0 = fn(scn, starts, ends, jnp.asarray(pa, jnp.float64), jnp.asarray(pb, jnp.float64))
    out: Dict[str, Any] = {"sq": np.asarray(acc[0]), "nrm": np.asarray(acc[1]), "cnt": np.asarray(acc[2])}
    if every:
        t_r, p_r, sq_r, nrm_r = ys["rec"]
        sel = slice(every - 1, None, every)
        out["records"] = {
            "t": np.concatenate([[0.0], np.asarray(t_r)[sel]]),
            "p_att": np.concatenate([np.asarray(p00[:3, :3])[None], np.asarray(p_r)[sel]]),
            "mean_sq_deg2": np.concatenate([[float(sq0)], np.asarray(sq_r)[sel]]),
            "mean_deg": np.concatenate([[float(nrm0)], np.asarray(nrm_r)[sel]]),
        }
    if smoother:
        s_sq, s_nrm = _smooth_fn(int(n_steps), float(dt))(ys["sm"], p00, starts, ends)
        out.update(s_sq=np.asarray(s_sq), s_nrm=np.asarray(s_nrm))
    return out


def _moments(t, p_att, starts, ends):
    """(E[theta^2] in deg^2, E[theta] in deg; 0 outside every window) of eps ~ N(0, p_att) (rad^2)."""
    f64 = jnp.float64
    deg2 = (180.0 / math.pi) ** 2
    inside = jnp.any((t >= starts) & (t < ends))
    sq = jnp.trace(p_att) * deg2
    nrm = jax.lax.cond(
        inside, lambda c: expected_norm(jnp.zeros((3,), f64), c * deg2), lambda c: jnp.zeros((), f64), p_att
    )
    return sq, nrm


@functools.lru_cache(maxsize=32)
def _compiled(mdl: Model, dt: float, n_steps: int, hold: str, nw: int, every: int, smoother: bool):
    """The jitted forward pass fn(scn, starts, ends, prior_att, prior_bias) for one structure."""
    n, rows, bias = mdl.n, mdl.rows, mdl.bias
    na = n + 3  # [eps; beta; g] with g the gyro noise of the latest sample read
    f64 = jnp.float64
    eye3 = jnp.eye(3, dtype=f64)
    # weights of samples k and k+1 at (t_k, t_k + dt/2, t_k+1) under the hold
    w0 = {"zoh": (1.0, 1.0, 1.0), "next": (0.0, 0.0, 0.0), "linear": (1.0, 0.5, 0.0)}[hold]
    w1 = {"zoh": (0.0, 0.0, 0.0), "next": (1.0, 1.0, 1.0), "linear": (0.0, 0.5, 1.0)}[hold]

    def fn(scn, starts, ends, pa, pb):
        def local(r, t):
            return _local(scn, r, t, dt, n, bias, rows)

        def transition(r0, t0, loc0):
            """(F_aug (na, na), G_aug (na, 3), local quantities at k+1, r_k+1) of step k -> k+1."""
            h2 = 0.5 * dt
            rm = scn.propagate(r0, t0, h2)
            r1 = scn.propagate(r0, t0, dt)
            rb0, c0 = loc0[0], loc0[1]
            rbm, cm = rm, _gyro_jac(scn, rm, t0 + h2, dt, n, bias)
            loc1 = local(r1, t0 + dt)
            rb1, c1 = loc1[0], loc1[1]
            a = -rbm @ cm[:, :3]
            e_full, e_half = _expm(a * dt), _expm(a * h2)
            m0, mm, m1 = e_full @ rb0, e_half @ rbm, rb1
            g0 = dt / 6.0 * (w0[0] * m0 + 4.0 * w0[1] * mm + w0[2] * m1)
            g1 = dt / 6.0 * (w1[0] * m0 + 4.0 * w1[1] * mm + w1[2] * m1)
            fa = jnp.zeros((na, na), f64).at[:3, :3].set(e_full)
            if bias:
                gb = dt / 6.0 * (m0 @ c0[:, 3:6] + 4.0 * mm @ cm[:, 3:6] + m1 @ c1[:, 3:6])
                fa = fa.at[:3, 3:6].set(-gb).at[3:6, 3:6].set(eye3)
            fa = fa.at[:3, n:].set(-g0)
            ga = jnp.zeros((na, 3), f64).at[:3].set(-g1).at[n:].set(eye3)
            return fa, ga, loc1, r1

        t0 = jnp.zeros((), f64)
        r0 = jnp.asarray(scn.r0, f64)
        loc0 = local(r0, t0)
        lg0, h0, ly0 = loc0[2], loc0[3], loc0[4]
        p0 = jnp.zeros((na, na), f64).at[:3, :3].set(pa**2 * eye3)
        if bias:
            p0 = p0.at[3:6, 3:6].set(pb**2 * eye3)
        p0 = p0.at[n:, n:].set(lg0 @ lg0.T)
        p00 = _joseph(p0, h0, ly0 @ ly0.T, n)
        sq0, nrm0 = _moments(t0, p00[:3, :3], starts, ends)
        acc0 = _window_sums(starts, ends, t0, sq0, nrm0)

        def body(carry, k):
            r, loc, p, acc = carry
            t = k.astype(f64) * dt
            fa, ga, loc1, r1 = transition(r, t, loc)
            lg1, h1, ly1 = loc1[2], loc1[3], loc1[4]
            pp = fa @ p @ fa.T + ga @ (lg1 @ lg1.T) @ ga.T
            pp = 0.5 * (pp + pp.T)
            pf = _joseph(pp, h1, ly1 @ ly1.T, n)
            t1 = t + dt
            p_att = (pp if hold == "zoh" else pf)[:3, :3]
            sq, nrm = _moments(t1, p_att, starts, ends)
            a = _window_sums(starts, ends, t1, sq, nrm)
            acc = tuple(x + y for x, y in zip(acc, a))
            ys = {}
            if every:
                ys["rec"] = (t1, p_att, sq, nrm)
            if smoother:
                ys["sm"] = (fa, pp, pf)
            return (r1, loc1, pf, acc), ys

        carry, ys = jax.lax.scan(body, (r0, loc0, p00, acc0), jnp.arange(n_steps))
        return carry[3], ys, p00, sq0, nrm0

    return jax.jit(fn)


@functools.lru_cache(maxsize=8)
def _smooth_fn(n_steps: int, dt: float):
    """Rauch-Tung-Striebel backward pass over the stored (F_k, P_k+1|k, P_k+1|k+1): window sums of E[theta^2] and
    E[theta] of the smoothed attitude covariance (every estimate uses every sample)."""
    f64 = jnp.float64

    def fn(sm, p00, starts, ends):
        fa, pp, pf = sm
        pf_all = jnp.concatenate([p00[None], pf], axis=0)  # P_k|k, k = 0 .. n_steps

        def body(carry, k):
            ps_next, acc = carry  # P_{k+1|N}
            pk = pf_all[k]
            c = jnp.linalg.lstsq(pp[k], fa[k] @ pk, rcond=None)[0].T  # P_k|k F^T P_{k+1|k}^+ (P symmetric)
            ps = pk + c @ (ps_next - pp[k]) @ c.T
            ps = 0.5 * (ps + ps.T)
            t = k.astype(f64) * dt
            sq, nrm = _moments(t, ps[:3, :3], starts, ends)
            w = ((t >= starts) & (t < ends)).astype(f64)
            return (ps, (acc[0] + w * sq, acc[1] + w * nrm)), None

        pn = pf_all[n_steps]
        tn = jnp.asarray(n_steps * dt, f64)
        sqn, nrmn = _moments(tn, pn[:3, :3], starts, ends)
        wn = ((tn >= starts) & (tn < ends)).astype(f64)
        (_, acc), _ = jax.lax.scan(body, (pn, (wn * sqn, wn * nrmn)), jnp.arange(n_steps - 1, -1, -1))
        return acc

    return jax.jit(fn)


def floor_study(study, *, windows=None, prior: Optional[Prior] = None, bias=None, smoother=False, every=0, **config):
    """:func:`floor` of a study's set-up (:meth:`jaxatt.studies.base.Study.setup` with ``config``): its scenario,
    duration, step and hold, over its loss windows (default "steady" and "transient", as
    :func:`jaxatt.fitting.varfree.predict_study`)."""
    from .. import studies

    s = studies.get(study).setup(**config)
    if windows is None:
        windows = tuple((nm, a, b) for nm, (a, b) in s.loss_windows.items())
    return floor(
        s.scenario,
        duration=s.duration,
        dt=s.dt,
        windows=windows,
        hold=s.hold,
        bias=bias,
        prior=prior,
        smoother=smoother,
        every=every,
    )


def heading_floor_closed_form(scenario, t) -> np.ndarray:
    """Variance (rad^2) of the heading error about the measured direction m_hat = {}^I m / |{}^I m| for the
    Batista problem (one vector, Earth rate known in the navigation frame), in the limit of a noise-free vector
    sensor and an uninformative prior:

        P_psi(t) = (q / c) coth(c t),   q = sigma_g^2 dt (gyro angle random walk^2, rad^2/s),
        c = |{}^I omega_E x m_hat| (rad/s),

    the Kalman-Bucy solution for the random walk psi' = w_m (the gyro noise about m_hat) observed through
    z' = c psi + w_u (the measured tilt z of m_hat towards u = m_hat x {}^I omega_E / c, driven by the gyro noise
    about u, which is independent of w_m). For c t << 1 it is q / (c^2 t) (1 + (c t)^2 / 3 + ...), i.e. the
    standard deviation sigma_g sqrt(dt) / (c sqrt(t)) (sigma_g: the gyro's per-sample standard deviation).
    Valid for t much longer than the time to forget a finite prior and than the tilt's settling time
    tau = sqrt(r / q) (r = (sigma_m / |m|)^2 dt, the vector sensor's noise density; 17 s in Section IV of
    Batista et al. 2019); a noisy vector sensor raises the heading variance above this limit by about
    2 tau / t (the ends of the tilt record are known only to within its noise; tests/test_floor.py). ``scenario``: an
    :class:`jaxatt.sim.imu.ImuScenario`; ``t`` (s)."""
    w = np.asarray(scenario.earth_rate_nav, float)
    m = np.asarray(scenario.ref_nav, float)
    m_hat = m / np.linalg.norm(m)
    c = float(np.linalg.norm(np.cross(w, m_hat)))
    sg = float(scenario.gyro_arw) * float(scenario.noise_scale)  # rad/s/sqrt(Hz): q = ARW^2
    q = sg**2
    t = np.asarray(t, float)
    if c <= 0 or q <= 0 or np.any(t <= 0):
        raise ValueError("need a non-zero Earth rate across m, gyro noise and t > 0")
    return q / c / np.tanh(c * t)
