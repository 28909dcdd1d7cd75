"""The one fitter: gains learned by gradient through the whole scan, on simulated seeds of a study or on recorded
trials, with one optax loop, early stopping on validation data, and a gains file rewritten after every step that
also holds what a resumed run needs (parameters, optimizer state, step, data order).

* :func:`fit` (also ``jaxatt.fit``): the entry point. ``data`` is a list of BROAD trials
  (:func:`jaxatt.data.broad.load`; loss: the group-weighted mean of the per-trial total RMSE, deg) or a study name
  (:mod:`jaxatt.studies`; loss: a :class:`jaxatt.fitting.losses.LossSpec` over windows of the simulated runs).
* :func:`optimize`: the loop over unconstrained parameters, for any ``objective(theta, batch) -> (loss, aux)``.

Gains are moved in an unconstrained space (:mod:`jaxatt.fitting.parametrize`): positive gains in log space (Adam's
steps are then relative changes, 0.05 ~ 5 %), SPD matrices through scaled Cholesky factors, schedules interval by
interval; bounded gains are projected back into their bounds after each step.

Resuming: ``fit(..., out=path, resume=True)`` continues from the state saved in ``path`` (same settings; the data
order, optimizer state and best-so-far are restored, so the result equals an uninterrupted run to rounding; with a
larger ``steps`` a finished fit with a constant learning rate continues, while a cosine schedule, the default of a
fit on trials, is set by ``steps`` and needs the same ``steps``). A finished gains file is never replaced by a new
fit unless ``overwrite=True``, and then only once the new fit has finished: until then it saves itself in
``<out>.partial.json`` (:func:`partial_path`), which ``resume=True`` continues.

Several processes (``jax.distributed``, :func:`jaxatt.sharding.initialize_distributed`): every process calls
:func:`fit` with the same arguments; the runs of each study minibatch split over every global device, the loss and
gradient are process 0's in every process (so every process takes the same steps) and only process 0 writes the
gains file. Resuming then needs ``out`` where every process can read it (a shared file system).
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
import time
import warnings
from functools import partial
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .. import engine, io
from ..types import MAX_RUNS, Observer, check_seed, shown
from . import flatparams, gainsfile
from . import parametrize as P

__all__ = [
    "fit",
    "FitResult",
    "partial_path",
    "FINISHED",
    "optimize",
    "OptimizeResult",
    "Sampler",
    "print_progress",
    "recorded_objective",
    "simulated_objective",
]


# ------------------------------------------------------------------------------------------------------------
# Minibatches
# ------------------------------------------------------------------------------------------------------------
class Sampler:
    """Minibatches of ``batch`` indices out of ``n``: consecutive slices of per-epoch shuffles (every item used
    equally), or every index each step when ``batch`` is None or >= n. Its state (a JSON-able dict) restores it."""

    def __init__(self, n: int, batch: Optional[int], seed: int = 0):
        self.n = int(n)
        self.batch = self.n if batch is None else int(min(batch, n))
        if self.batch < 1:
            raise ValueError(f"batch must be >= 1, got {batch}")
        self.rng = np.random.default_rng(seed)
        self.order: List[int] = []

    def next(self) -> np.ndarray:
        if self.batch == self.n:
            return np.arange(self.n)
        if len(self.order) < self.batch:
            self.order = self.order + self.rng.permutation(self.n).tolist()
        idx, self.order = self.order[: self.batch], self.order[self.batch :]
        return np.asarray(idx)

    def state(self) -> dict:
        return {"order": list(self.order), "rng": self.rng.bit_generator.state}

    def restore(self, state: Mapping[str, Any]) -> None:
        self.order = [int(i) for i in state["order"]]
        self.rng.bit_generator.state = state["rng"]


# ------------------------------------------------------------------------------------------------------------
# The loop
# ------------------------------------------------------------------------------------------------------------
class OptimizeResult(NamedTuple):
    """theta with the best validation loss (without validation: the best training loss), the last theta, the
    history (one dict per step), how the loop ended ("done", "early-stopped", "interrupted", "non-finite") and the
    state a resumed loop needs."""

    best_theta: Dict[str, Any]
    last_theta: Dict[str, Any]
    best_step: int
    best_val: Optional[float]
    start_val: Optional[float]
    history: List[dict]
    status: str
    resume: dict


def print_progress(info: dict, file=None) -> None:
    """Default progress display: one line per step: the training loss of the gains going into the step (before its
    update), the validation loss of the gains after it when computed, and the gradient norm."""
    from ..progress import report_line

    val = (
        ""
        if info.get("val_loss") is None
        else (
            f"  val {info['val_loss']:.5g}{' *' if info.get('improved') else ''} (best {info['best_val']:.5g} @ step "
            f"{info['best_step']})"
        )
    )
    ang = info.get("train_metric")
    angs = "" if ang is None else f" ({ang:.4g} {info.get('metric_unit', '')})"
    report_line(
        f"step {info['step']:4d}/{info['steps']}  train {info['train_loss']:.5g}{angs}  |g| "
        f"{info['grad_norm']:.3g}{val}  {info['step_s']:.1f} s/step",
        file,
    )


def _global_norm(tree) -> float:
    return float(jnp.sqrt(sum(jnp.sum(jnp.square(x)) for x in jax.tree_util.tree_leaves(tree))))


def _to_lists(tree):
    return jax.tree_util.tree_map(lambda a: np.asarray(a).tolist(), tree)


def _metric_value(aux):
    """``aux["metric"]`` (an array) or None."""
    return aux.get("metric") if isinstance(aux, dict) else None


def _agree(*values):
    """``values`` as they are with one process; with several (``jax.distributed``), numpy copies equal in every
    process (:func:`jaxatt.sharding.agree`: process 0's), so every process takes the same branches."""
    if jax.process_count() == 1:
        return values
    from ..sharding import agree

    return tuple(agree(list(values)))


#: The variance-free objective is differentiated in forward mode when theta has at most this many numbers
#: (research/README.md, "varfree_speed.py": batista-ges, 20-s run, forward mode with 8 tangents 1326 us per step
#: against 3524 for reverse mode through the checkpointed scan, 478 with one tangent; about 120 us more per tangent).
FORWARD_MODE_MAX = 16


def value_and_grad_forward(fn: Callable) -> Callable:
    """``jax.value_and_grad(fn, has_aux=True)`` computed in forward mode: ``fn(theta, batch) -> (loss, aux)``,
    one ``jax.jvp`` per number of the pytree ``theta`` (vmapped over the unit tangents), the gradient with the
    structure of ``theta``. Nothing is stored across a scan (no checkpointing needed); cost grows with the
    number of entries of theta."""

    def vg(theta, batch):
        flat, unravel = ravel_pytree(theta)

        def one(t):
            return jax.jvp(lambda x: fn(unravel(x), batch), (flat,), (t,), has_aux=True)

        loss, dloss, aux = jax.vmap(one, out_axes=(None, 0, None))(jnp.eye(flat.size, dtype=flat.dtype))
        return (loss, aux), unravel(dloss)

    return vg


def _restored_theta(saved, like: dict, dtype, what: str) -> dict:
    """A saved theta (gain -> nested lists) as arrays shaped as ``like``'s (ValueError naming what differs)."""
    if not isinstance(saved, dict) or set(saved) != set(like):
        got = sorted(saved) if isinstance(saved, dict) else type(saved).__name__
        raise ValueError(f"{what} holds {got}, not the gains {sorted(like)}")
    out = {k: jnp.asarray(v, dtype) for k, v in saved.items()}
    bad = [k for k in like if np.shape(out[k]) != np.shape(like[k])]
    if bad:
        raise ValueError(
            f"{what}[{bad[0]!r}] has shape {list(np.shape(out[bad[0]]))}, not {list(np.shape(like[bad[0]]))}"
        )
    return out


def optimize(
    objective: Callable,
    theta0: Dict[str, Any],
    *,
    steps: int,
    sampler: Sampler,
    take: Callable,
    val_batch=None,
    val_objective: Optional[Callable] = None,
    val_every: int = 5,
    patience: Optional[int] = None,
    min_delta: float = 0.0,
    lr: float = 0.05,
    clip: Optional[float] = 1.0,
    schedule: str = "constant",
    project: Optional[Callable] = None,
    callback: Optional[Callable[[dict], None]] = None,
    on_save: Optional[Callable[[OptimizeResult], None]] = None,
    resume: Optional[dict] = None,
    metric_unit: str = "",
    grad: str = "reverse",
    optimizer: str = "adam",
    resume_from: Optional[str] = None,
) -> OptimizeResult:
    """Minimise ``objective(theta, batch) -> (loss, aux)`` with Adam (global-norm clipping ``clip``; learning rate
    ``lr``, constant or ``schedule="cosine"`` decay to lr / 10 over ``steps``).

    Each step uses ``take(sampler.next())`` as its batch. With ``val_batch`` the loss on it (``val_objective``,
    default ``objective``) is computed at the
    start, every ``val_every`` steps and at the last step; the best-validation theta is kept and after ``patience``
    validations without an improvement larger than ``min_delta`` (relative) the loop stops. Without validation the
    theta with the lowest training loss is kept (the last one is evaluated at the end). ``project(theta)`` is applied
    after each update (bounds). A non-finite loss or gradient skips the update; three in a row stop the loop.
    KeyboardInterrupt ends the loop with status "interrupted" and what was found. ``on_save(result_so_far)`` is
    called after every step (write files there); ``resume`` (a previous result's ``resume``) continues a loop
    (``resume_from``: where it was read, named when it is damaged).
    ``aux["metric"]`` (optional scalar) is shown and recorded. History: one dict per step k with ``train_loss``
    / ``train_metric`` of the params *before* update k (on step k's batch), ``grad_norm``, and, when validated,
    ``val_loss`` / ``val_metric`` of the params *after* update k; step 0 holds the start's validation.
    ``grad``: "reverse" (``jax.value_and_grad``) or "forward" (:func:`value_and_grad_forward`: one tangent per
    number of theta; the same gradient, cheaper for a few numbers through a long scan).
    ``optimizer``: "adam" (above) or "lbfgs" (:func:`optax.lbfgs`, memory 10, with a backtracking line search on
    the objective's value; ``lr`` caps the line search's step, ``clip`` and ``schedule`` are not used). L-BFGS needs
    the same loss at every step: every item in each batch (``sampler.batch == sampler.n``, e.g. the variance-free
    objective, or every trial); on such a loss it converges in far fewer steps than Adam.
    """
    import optax

    sched = optax.cosine_decay_schedule(lr, max(int(steps), 1), alpha=0.1) if schedule == "cosine" else lr
    if schedule not in ("constant", "cosine"):
        raise ValueError(f"schedule must be 'constant' or 'cosine', got {schedule!r}")
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {', '.join(OPTIMIZERS)}, got {optimizer!r}")
    lbfgs = optimizer == "lbfgs"
    if lbfgs and sampler.batch != sampler.n:
        raise ValueError(
            f"optimizer 'lbfgs' needs the same loss at every step: a batch of every item ({sampler.n}), "
            f"got {sampler.batch}; use objective 'varfree' or 'adam'"
        )
    if lbfgs:
        search = optax.scale_by_backtracking_linesearch(
            max_backtracking_steps=12,
            decrease_factor=0.5,
            increase_factor=math.inf,  # every search starts from the full (capped) quasi-Newton step
            max_learning_rate=lr,
            store_grad=False,
        )
        opt = optax.lbfgs(memory_size=10, linesearch=search)
    else:
        opt = optax.adam(sched) if not clip else optax.chain(optax.clip_by_global_norm(clip), optax.adam(sched))
    # shared programs: a second fit of the same problem (a new closure, the same program) is not compiled again
    if grad not in ("reverse", "forward"):
        raise ValueError(f"grad must be 'reverse' or 'forward', got {grad!r}")
    differentiate = value_and_grad_forward if grad == "forward" else partial(jax.value_and_grad, has_aux=True)
    vg = engine.jit_shared(differentiate(objective))
    val_fn = engine.jit_shared(val_objective or objective) if val_batch is not None else None
    theta = jax.tree_util.tree_map(jnp.asarray, dict(theta0))
    opt_state = opt.init(theta)
    if lbfgs:  # the line search evaluates the loss (no gradient) at trial steps along the L-BFGS direction

        def _lbfgs_update(g, state, th, value, batch):
            return opt.update(g, state, th, value=value, grad=g, value_fn=lambda t: objective(t, batch)[0])

        update = engine.jit_shared(_lbfgs_update)
    else:
        update = opt.update
    history: List[dict] = []
    best_theta, best_val, best_step, start_val, bad, n_nonfinite, first = theta, None, 0, None, 0, 0, 1
    best_train = math.inf
    if resume:
        dtype = jax.tree_util.tree_leaves(theta)[0].dtype
        leaves, treedef = jax.tree_util.tree_flatten(opt_state)
        try:
            theta = _restored_theta(resume["theta"], theta, dtype, "theta")
            saved = resume["opt_state"]
            if not isinstance(saved, list) or len(saved) != len(leaves):
                raise ValueError("the saved optimizer state does not match these settings")
            restored = [jnp.asarray(v, getattr(leaf, "dtype", None)) for v, leaf in zip(saved, leaves)]
            if any(np.shape(a) != np.shape(leaf) for a, leaf in zip(restored, leaves)):
                raise ValueError("the saved optimizer state's shapes do not match these gains")
            opt_state = jax.tree_util.tree_unflatten(treedef, restored)
            best_theta = _restored_theta(resume["best_theta"], theta, dtype, "best_theta")
            best_val, best_step, start_val = resume["best_val"], int(resume["best_step"]), resume["start_val"]
            bad, n_nonfinite = int(resume["bad"]), int(resume["n_nonfinite"])
            saved_best_train = resume.get("best_train")
            best_train = float(saved_best_train) if saved_best_train is not None else math.inf
            history = list(resume["history"])
            step_done = resume["step"]
            last = history[-1]["step"] if history else 0  # as result() writes it
            if step_done != last or isinstance(step_done, bool):
                raise ValueError(f"step {step_done!r} is not the last step of its history ({last})")
            sampler.restore(resume["sampler"])
            first = step_done + 1
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
            what = f"no {e}" if isinstance(e, KeyError) else str(e).splitlines()[0] if str(e) else type(e).__name__
            where = f" in {resume_from}" if resume_from else ""
            raise ValueError(
                f"resume: the saved fit state{where} is damaged ({what}); fit again without resume (overwrite=True / "
                "--overwrite replaces the file)"
            ) from None
    t_start = time.perf_counter()

    def validate(th):
        loss, aux = val_fn(th, val_batch)
        loss, metric = _agree(loss, _metric_value(aux))
        return float(loss), (None if metric is None else float(metric))

    def result(status):
        state = {
            "step": (history[-1]["step"] if history else 0),
            "theta": _to_lists(theta),
            "opt_state": [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves(opt_state)],
            "best_theta": _to_lists(best_theta),
            "best_val": best_val,
            "best_step": best_step,
            "start_val": start_val,
            "bad": bad,
            "n_nonfinite": n_nonfinite,
            "best_train": best_train if math.isfinite(best_train) else None,
            "history": history,
            # the data order after the last recorded step: a step interrupted after drawing its batch, and the
            # last step's evaluation, do not use up batches of the resumed run
            "sampler": sampler_state,
        }
        return OptimizeResult(best_theta, theta, best_step, best_val, start_val, history, status, state)

    status = "done"
    sampler_state = sampler.state()
    try:
        if val_fn is not None and not resume:
            start_val, start_metric = validate(theta)
            best_val = start_val
            history.append(
                {
                    "step": 0,
                    "val_loss": start_val,
                    "val_metric": start_metric,
                    "elapsed_s": time.perf_counter() - t_start,
                }
            )
        for step in range(first, steps + 1):
            t0 = time.perf_counter()
            batch = take(sampler.next())
            (loss, aux), grads = vg(theta, batch)
            metric = _metric_value(aux)
            if jax.process_count() > 1:  # one set of values in every process (same updates, same decisions)
                loss, metric, grads = _agree(loss, metric, grads)
                grads = jax.tree_util.tree_map(jnp.asarray, grads)
            loss_value = jnp.asarray(loss)
            loss = float(loss)
            metric = None if metric is None else float(metric)
            gnorm = _global_norm(grads)
            finite = math.isfinite(loss) and math.isfinite(gnorm)
            rec = {"step": step, "train_loss": loss, "train_metric": metric, "grad_norm": gnorm, "finite": finite}
            if val_fn is None and finite and loss < best_train:
                best_train, best_theta, best_step = loss, theta, step - 1
            if finite:
                n_nonfinite = 0
                if lbfgs:
                    updates, opt_state = update(grads, opt_state, theta, loss_value, batch)
                else:
                    updates, opt_state = update(grads, opt_state, theta)
                theta = optax.apply_updates(theta, updates)
                if project is not None:
                    theta = project(theta)
            else:
                n_nonfinite += 1
            improved = False
            if val_fn is not None and (step % val_every == 0 or step == steps):
                vl, vm = validate(theta)
                rec.update(val_loss=vl, val_metric=vm)
                # best_val is None when resuming, with validation, a fit saved without it: the first one is the best
                if math.isfinite(vl) and (best_val is None or vl < best_val * (1.0 - min_delta)):
                    best_val, best_theta, best_step, bad, improved = vl, theta, step, 0, True
                else:
                    bad += 1
            rec.update(step_s=time.perf_counter() - t0, elapsed_s=time.perf_counter() - t_start)
            history.append(rec)
            sampler_state = sampler.state()
            if callback is not None:
                callback(
                    {
                        **rec,
                        "steps": steps,
                        "val_loss": rec.get("val_loss"),
                        "best_val": best_val,
                        "best_step": best_step,
                        "improved": improved,
                        "metric_unit": metric_unit,
                    }
                )
            stop = None
            if n_nonfinite >= 3 or (n_nonfinite and step == steps):  # a fit never ends on a non-finite step silently
                stop = "non-finite"
            elif patience is not None and val_fn is not None and bad >= patience:
                stop = "early-stopped"
            if stop is None and step == steps and val_fn is None:
                # the last update has not been evaluated yet
                (last, _), _ = vg(
                    theta, take(np.arange(sampler.n)) if sampler.batch == sampler.n else take(sampler.next())
                )
                (last,) = _agree(last)
                if math.isfinite(float(last)) and float(last) < best_train:
                    best_train, best_theta, best_step = float(last), theta, step
            if on_save is not None:
                on_save(result("running" if stop is None and step < steps else (stop or "done")))
            if stop:
                status = stop
                break
    except KeyboardInterrupt:
        status = "interrupted"
        if on_save is not None:
            on_save(result(status))
    return result(status)


# ------------------------------------------------------------------------------------------------------------
# Objectives
# ------------------------------------------------------------------------------------------------------------
def trials_fingerprint(trials) -> str:
    """A short hash of every number of ``trials`` (times, sensors, truth, movement; in float64), so that a resumed
    fit can tell trials of the same names but other data (another file, frame, columns or units) from its own."""
    h = hashlib.sha256()
    for t in trials:
        s = t.samples
        for a in (s.t, s.gyr, s.acc, s.mag, t.quat_true, t.movement):
            a = np.asarray(a)
            h.update(np.ascontiguousarray(a if a.dtype == bool else a.astype(np.float64)).tobytes())
    return h.hexdigest()[:16]


def _broad_weights(groups: Sequence[str]) -> np.ndarray:
    """Per-trial weights: each group present weighted equally, the trials of a group equally (sum 1)."""
    present = sorted(set(groups))
    return np.array([1.0 / (len(present) * groups.count(g)) for g in groups])


def recorded_objective(
    observer,
    bound: P.BoundParametrization,
    trials,
    *,
    hold: Optional[str] = None,
    dtype=None,
    step_remat: bool = False,
    checkpoint="auto",
):
    """(objective(theta, batch), n_trials, take(indices) -> batch): the group-weighted mean per-trial total RMSE
    (deg, BROAD metric) of ``observer`` on ``trials``, through the whole scan (checkpointed: the reverse pass
    stores one state per segment of about sqrt(T) steps and trial and recomputes each segment;
    :func:`jaxatt.data.broad.metric_batch`). ``aux["metric"]``: the same mean."""
    from ..data import broad as B

    fn, item = B.metric_batch(observer, trials, hold=hold, dtype=dtype, step_remat=step_remat, checkpoint=checkpoint)
    groups = [t.group or B.group_of(t.name) for t in trials]

    def take(idx):
        idx = np.asarray(idx)
        w = _broad_weights([groups[i] for i in idx])
        return {"item": jax.tree_util.tree_map(lambda a: a[idx], item), "weight": jnp.asarray(w)}

    def objective(theta, batch):
        rmse = fn(bound.constrain(theta), batch["item"])["total_rmse_deg"]
        loss = jnp.sum(batch["weight"].astype(rmse.dtype) * rmse)
        return loss, {"metric": loss, "rmse_deg": rmse}

    return objective, len(trials), take


def simulated_objective(
    setup, bound: P.BoundParametrization, spec, *, dtype=None, checkpoint="auto", step_remat=None, devices=None
):
    """objective(theta, keys): the :class:`~jaxatt.fitting.losses.LossSpec` loss of the study set-up's observer over the
    runs of ``keys`` (:func:`jaxatt.fitting.losses.make_loss_fn`). ``aux["metric"]``: the mean angle error (deg) over
    the first window."""
    from . import losses

    f = losses.make_loss_fn(
        setup.observer,
        duration=setup.duration,
        dt=setup.dt,
        spec=spec,
        hold=setup.hold,
        dtype=dtype,
        checkpoint=checkpoint,
        init_params=setup.init_params,
        step_remat=step_remat,
        devices=devices,
    )

    def objective(theta, keys):
        loss, aux = f(setup.scenario, bound.constrain(theta), keys)
        return loss, {**aux, "metric": jnp.mean(aux["window_angle_deg"][0])}

    return objective


# ------------------------------------------------------------------------------------------------------------
# fit
# ------------------------------------------------------------------------------------------------------------
class NonFiniteFit(RuntimeWarning):
    """Warned by :func:`fit` when it stopped on a non-finite loss or gradient (``FitResult.status`` "non-finite"):
    its params are the best finite gains, not a finished fit. The CLI exits 1 instead."""


class FitResult(NamedTuple):
    """:func:`fit`'s result: ``params`` (the best gains, same type as the start), ``start_params``, ``history`` (one
    dict per step), ``status``, ``best_step``, ``best_loss`` (validation loss, or training loss without validation),
    ``start_loss`` and the gains file written (or None)."""

    params: Any
    start_params: Any
    history: List[dict]
    status: str
    best_step: int
    best_loss: Optional[float]
    start_loss: Optional[float]
    path: Optional[str]


def _parametrization(entry, params, *, tune, freeze, masks, method, transforms):
    if entry is not None:
        if tune is None:  # a positive gain at exactly 0 is a term switched off (k_i = 0: no bias integrator);
            # the log map cannot leave 0, so a default fit keeps it off (naming it in ``tune`` is an error)
            off = [
                g.field
                for g in entry.gains
                if g.tuned
                and g.constraint == "positive"
                and np.size(getattr(params, g.field))
                and np.all(np.asarray(getattr(params, g.field)) == 0)
            ]
            freeze = tuple(freeze) + tuple(f for f in off if f not in freeze)
        return P.for_gains(
            entry.gains, tune=tune, freeze=freeze, masks=masks, method=method, transforms=transforms
        ).bind(params)
    p = P.for_params(params, tune=tune)
    if freeze:
        p = p.freeze(*freeze)
    for f, m in (masks or {}).items():
        p = p.with_mask(f, m)
    for f, tr in (transforms or {}).items():
        p = P.Parametrization({**p.transforms, f: tr}, p.masks)
    if not p.transforms:
        why = f"freeze names every tunable field: {sorted(freeze)}" if freeze else "name the gains with tune="
        raise ValueError(f"no gain left to tune ({why})")
    return p.bind(params)


def _start(params, start, entry):
    """The start params: ``params``, or a gains-file path / dict of gains / ``fn(params)`` applied to them."""
    if start is None:
        return params
    if isinstance(start, str):
        d = gainsfile.read(start)
        if entry is not None and d["observer"] != entry.name:
            raise ValueError(f"start {start}: holds gains of {d['observer']!r}, not of {entry.name!r}")
        return gainsfile.apply(params, d["gains"], source=f"start {start}")
    if callable(start):
        return start(params)
    if isinstance(start, Mapping):
        return gainsfile.apply(params, start, source="start")
    raise ValueError(f"start must be a gains-file path, a dict of gains or a callable, got {type(start).__name__}")


#: simulated runs a study fit trains / validates on by default (options of a study fit only)
TRAIN_RUNS, VAL_RUNS = 32, 16


def fit(
    observer=None,
    params=None,
    data=None,
    *,
    steps: int = 100,
    lr: Optional[float] = None,
    tune: Optional[Sequence[str]] = None,
    freeze: Sequence[str] = (),
    masks: Optional[Mapping[str, Any]] = None,
    method: Optional[str] = None,
    transforms: Optional[Mapping[str, P.Transform]] = None,
    start=None,
    batch: Optional[int] = None,
    val=None,
    val_every: int = 5,
    patience: Optional[int] = None,
    clip: Optional[float] = 1.0,
    schedule: Optional[str] = None,
    seed: int = 0,
    out: Optional[str] = None,
    resume: bool = False,
    overwrite: bool = False,
    callback: Optional[Callable[[dict], None]] = None,
    quiet: bool = True,
    dtype=None,
    hold: Optional[str] = None,
    loss: Optional[str] = None,
    transient_weight: float = 0.0,
    config: Optional[Mapping[str, Any]] = None,
    train_runs: int = TRAIN_RUNS,
    val_runs: int = VAL_RUNS,
    refine_schedule: Sequence[float] = (),
    checkpoint="auto",
    step_remat: Optional[bool] = None,
    devices=None,
    objective: str = "montecarlo",
    optimizer: str = "adam",
) -> FitResult:
    """Learn gains by gradient descent through the whole scan.

    Args:
        observer: a registered name or your own Observer (for a study: None = the study's tuned observer, or the
            registered name of another observer the study compares, its ``fittable``, e.g. "mekf" or "nlio" on
            the nlio studies).
        params: start gains (None: a registered observer's shipped/default gains, or the study's paper gains;
            a registered observer's or a study's also take a dict of gain name -> value put into those, or a
            gains-file path).
        data: recorded trials (:class:`jaxatt.data.broad.Trial` s; loss = group-weighted mean per-trial total RMSE,
            deg) or a study name (:data:`jaxatt.studies.TUNABLE`; loss = ``loss`` over its windows on simulated
            runs 0 ... train_runs-1 of ``seed``, validation on the next ``val_runs``).
        steps, lr, clip, schedule ("constant" / "cosine"; default constant for studies, cosine for trials):
            the optimizer (``lr`` default 0.05 for Adam; for L-BFGS 1, the full quasi-Newton step).
        tune / freeze / masks / method / transforms: which gains move and how (registered observers: their
            declared gains, those tuned by default unless ``tune``; your own: every positive Params field unless
            ``tune``). Bounded gains stay inside their bounds. Your own params may be any pytree (a NamedTuple, a
            dict, a registered dataclass, nested ones): each leaf is a gain named by its path (``acc_k`` for
            ``params.acc.k``, :mod:`jaxatt.fitting.flatparams`), and ``FitResult.params`` has your params' shape.
        start: start from these gains (gains-file path, dict, or ``fn(params) -> params``).
        batch: items (runs or trials) per gradient (default: 8 runs for studies, every trial for trials).
        val: validation trials (recorded; default none) ; for studies the ``val_runs`` runs after the training
            runs. ``val_every``, ``patience``: validation cadence and early stopping.
        out: gains file rewritten after every step (best gains, start, settings, history, provenance and the
            resume state). ``resume``: continue from it. ``overwrite``: replace a finished one.
        dtype: arithmetic, float32 or float64 (default: float64 when x64 is on for studies; for trials the data's).
        hold: how a step sees the samples (:data:`jaxatt.types.HOLDS`; default the observer's own); for a study its
            ``hold`` setting (as ``config["hold"]``: "zoh" or "linear").
        checkpoint, step_remat: memory of the reverse pass (:func:`jaxatt.engine.segment_length`: "auto" stores
            one state per segment of about sqrt(T) steps and recomputes each segment; ``step_remat`` also
            rematerialises each step: least memory, about 3x slower on trials).
        loss, transient_weight, config, refine_schedule, devices: study options (``config``: a dict of the study's
            settings, each checked against its Config; :mod:`jaxatt.fitting.losses`,
            :func:`jaxatt.schedule.refine`); ``loss="innovation_nll"`` fits a
            Kalman filter's noise parameters by maximum likelihood of its innovations (no truth used).
        objective: for a study, ``"montecarlo"`` (the loss averaged over minibatches of simulated runs) or
            ``"varfree"`` (its expectation over the noise, computed without runs by covariance propagation along
            the noise-free run, :mod:`jaxatt.fitting.varfree`: no sampling noise in the loss or its gradient, so
            no minibatches and no validation runs: ``train_runs``, ``val_runs`` and ``batch`` are refused; kinds
            ``angle_sq`` / ``euler_sq``; the study's random initial estimates are not drawn; its gradient in
            forward mode when at most :data:`FORWARD_MODE_MAX` numbers are tuned, else in reverse mode).
        optimizer: ``"adam"`` (default) or ``"lbfgs"`` (quasi-Newton with a line search, for a loss that is the
            same at every step: ``objective="varfree"``, or trials with ``batch`` = all of them; ``lr`` caps its
            step on the tuned numbers; see :func:`optimize`).
    Returns :class:`FitResult`. Raises ValueError (one line) on bad arguments.
    """

    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
    if patience is not None and (
        isinstance(patience, bool) or not isinstance(patience, (int, np.integer)) or patience < 1
    ):
        raise ValueError(f"patience must be a whole number of validations >= 1 or None, got {patience!r}")
    seed = check_seed(seed)
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be a function of one dict (each step's record) or None, got {callback!r}")
    if isinstance(tune, str) or isinstance(freeze, str):
        which = "tune" if isinstance(tune, str) else "freeze"
        raise ValueError(f"{which} must be a list of gain names, e.g. [{(tune or freeze)!r}], got the string")
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {', '.join(OPTIMIZERS)}, got {optimizer!r}")
    if lr is None:
        lr = 0.05 if optimizer == "adam" else 1.0
    real = (int, float, np.integer, np.floating)
    if isinstance(lr, bool) or not (isinstance(lr, real) and math.isfinite(lr) and lr > 0):
        raise ValueError(f"lr must be a positive number, got {lr!r}")
    lr = float(lr)
    if batch is not None:
        from ..montecarlo import check_count

        batch = check_count("batch", batch, 1)
    if clip is not None and (
        isinstance(clip, bool) or not (isinstance(clip, real) and math.isfinite(clip) and clip > 0)
    ):
        raise ValueError(
            f"clip must be a positive number (the largest gradient norm) or None (no clipping), got {clip!r}"
        )
    if isinstance(val_every, bool) or not isinstance(val_every, (int, np.integer)) or val_every < 1:
        raise ValueError(f"val_every must be a whole number of steps >= 1, got {val_every!r}")
    if dtype is not None:  # float32 or float64 only (and float64 only with x64 on)
        from ..api import compute_dtype

        dtype = compute_dtype(dtype=dtype)
    if resume and overwrite:
        raise ValueError(
            "resume=True and overwrite=True: pass one (resume continues the fit saved in out, overwrite replaces it)"
        )
    rebuild = None
    if isinstance(observer, Observer) and params is not None and not isinstance(params, str):
        if not hasattr(params, "_fields") or flatparams.needs_flat_view(params):
            # your own params as a dict, a dataclass or nested: tuned as one named gain per leaf, returned in
            # their own shape (the gains file names the leaves: flatparams.leaf_names)
            params, rebuild = flatparams.flat_view(params)
            observer = flatparams.observer_on_view(observer, rebuild)
            if callable(start):
                start = _start_on_view(start, rebuild)
    final_path = io.check_output_path(out, "out", suffixes=io.JSON_SUFFIXES)
    out_path, previous = final_path, None
    if final_path is not None:
        partial = partial_path(final_path)
        if not io.is_special(final_path):  # /dev/null: nothing is saved beside it
            io.check_output_path(partial, "out (its unfinished fit is saved beside it)")
        if resume and partial.exists():  # an overwriting fit was interrupted: continue it
            out_path, previous = partial, gainsfile.read(partial)
        elif final_path.exists():
            try:
                previous = gainsfile.read(final_path)
            except ValueError as e:
                raise ValueError(f"out {out}: exists and is not a gains file, so it is not replaced ({e})") from None
            if not resume and not overwrite:
                raise ValueError(
                    f"out {out}: exists (status {previous.get('status')!r}); pass resume=True (--resume) to continue "
                    "it or overwrite=True (--overwrite) to replace it"
                )
            if not resume and previous.get("status") in FINISHED:
                out_path = partial  # the finished fit stays in out until the new one finishes
    if resume and out is None:
        raise ValueError("resume=True needs out (the gains file of the interrupted fit)")
    if resume and previous is None:
        raise ValueError(f"resume: no gains file at {out!r} to continue")
    res = _fit(
        observer,
        params,
        data,
        out_path=out_path,
        previous=previous if resume else None,
        steps=steps,
        lr=lr,
        tune=tune,
        freeze=freeze,
        masks=masks,
        method=method,
        transforms=transforms,
        start=start,
        batch=batch,
        val=val,
        val_every=val_every,
        patience=patience,
        clip=clip,
        schedule=schedule,
        seed=seed,
        callback=callback,
        quiet=quiet,
        dtype=dtype,
        hold=hold,
        loss=loss,
        transient_weight=transient_weight,
        config=config,
        train_runs=train_runs,
        val_runs=val_runs,
        refine_schedule=refine_schedule,
        checkpoint=checkpoint,
        step_remat=step_remat,
        devices=devices,
        objective=objective,
        optimizer=optimizer,
    )
    if out_path is not None and final_path is not None and out_path != final_path and res.status in FINISHED:
        if io.is_main_process():  # several processes: process 0 writes the files
            os.replace(out_path, final_path)
        res = res._replace(path=str(final_path))
        if not quiet:
            print(f"{final_path} replaced by the finished new fit", file=sys.stderr, flush=True)
    elif out_path is not None and out_path != final_path and not quiet:
        print(
            f"the finished fit in {final_path} is kept; the new one ({res.status}) is in {out_path} "
            "(resume=True / --resume continues it)",
            file=sys.stderr,
            flush=True,
        )
    if rebuild is not None:
        res = res._replace(params=rebuild(res.params), start_params=rebuild(res.start_params))
    if res.status == "non-finite":
        warnings.warn(
            "fit: stopped on a non-finite loss or gradient (three steps in a row, or at the last step); "
            "FitResult.params are the best finite gains (status 'non-finite'): check the data and the gains' range",
            NonFiniteFit,
            stacklevel=2,
        )
    return res


def _check_same_start(saved, start_gains: dict) -> None:
    """ValueError unless the gains a resumed fit starts from are those the saved fit started from (the file's
    ``start``; files without it are not compared): another start would be recorded as this fit's."""
    if not isinstance(saved, Mapping):
        return
    for name, entry in start_gains.items():
        old = saved.get(name)
        old = old.get("value") if isinstance(old, Mapping) else old
        try:
            same = old is None or np.allclose(  # relative only: the batista-so3 gains are 1e-11 ... 1e-9
                np.asarray(old, float), np.asarray(entry["value"], float), rtol=1e-12, atol=0.0
            )
        except (TypeError, ValueError):
            same = False
        if not same:
            raise ValueError(
                f"resume: the start gains differ from the saved fit's ({name}: {shown(old)} vs "
                f"{shown(entry['value'])}): resume with the start it had (start= / --init-gains), or start a new fit"
            )


def _start_on_view(start, rebuild):
    """``start`` (a function of your params) as a function of their flat view."""

    def on_view(view):
        params = rebuild(view)
        got = start(params)
        if jax.tree_util.tree_structure(got) != jax.tree_util.tree_structure(params):
            raise ValueError(
                "start(params) must return params of the structure it was given "
                f"({jax.tree_util.tree_structure(params)}), got {jax.tree_util.tree_structure(got)}"
            )
        return type(view)(*jax.tree_util.tree_leaves(got))

    return on_view


#: the optimizers of :func:`optimize` / :func:`fit`
OPTIMIZERS = ("adam", "lbfgs")

#: statuses of a finished fit (a gains file with one of them is replaced only by another finished fit)
FINISHED = gainsfile.FINISHED


def partial_path(out) -> Path:
    """Where a fit that overwrites a finished gains file ``out`` saves itself until it finishes."""
    out = Path(out)
    return out.with_name(out.name + ".partial.json")


def _fit(
    observer,
    params,
    data,
    *,
    out_path,
    previous,
    steps,
    lr,
    tune,
    freeze,
    masks,
    method,
    transforms,
    start,
    batch,
    val,
    val_every,
    patience,
    clip,
    schedule,
    seed,
    callback,
    quiet,
    dtype,
    hold,
    loss,
    transient_weight,
    config,
    train_runs,
    val_runs,
    refine_schedule,
    checkpoint,
    step_remat,
    devices,
    objective="montecarlo",
    optimizer="adam",
):
    """:func:`fit` once the gains file to write (``out_path``) and the fit to continue (``previous``) are known."""
    if isinstance(data, (str,)) or (data is not None and hasattr(data, "setup") and hasattr(data, "observers")):
        if val is not None:
            raise ValueError("val: a fit on a study validates on its own simulated runs (val_runs), not on trials")
        return _fit_study(
            data,
            observer,
            params,
            steps=steps,
            lr=lr,
            tune=tune,
            freeze=freeze,
            masks=masks,
            method=method,
            transforms=transforms,
            start=start,
            batch=batch,
            val_every=val_every,
            patience=patience,
            clip=clip,
            schedule=schedule or "constant",
            seed=seed,
            out_path=out_path,
            previous=previous,
            callback=callback,
            quiet=quiet,
            dtype=dtype,
            hold=hold,
            loss=loss,
            transient_weight=transient_weight,
            config=config,
            train_runs=train_runs,
            val_runs=val_runs,
            refine_schedule=refine_schedule,
            checkpoint=checkpoint,
            step_remat=step_remat,
            devices=devices,
            objective=objective,
            optimizer=optimizer,
        )
    if objective != "montecarlo":
        raise ValueError(f"objective {objective!r} needs a study as data (recorded trials: objective='montecarlo')")
    study_only = {  # given other than their defaults (the signature's)
        "loss": loss is not None,
        "transient_weight": transient_weight != 0.0,
        "config": config is not None,
        "train_runs": train_runs != TRAIN_RUNS,
        "val_runs": val_runs != VAL_RUNS,
        "refine_schedule": len(refine_schedule) > 0,
        "devices": devices is not None,  # recorded trials run on one device
    }
    given = [k for k, v in study_only.items() if v]
    if given:
        raise ValueError(f"{', '.join(given)}: options of a fit on a study, not on recorded trials")
    from ..api import (
        check_own_estimate,
        check_own_observer,
        compute_dtype,
        recording_defaults_for_trials,
        resolve_observer,
        trial_arrays,
        trials_start_from_valid,
        truth_in_frame_of,
    )
    from ..data import broad as B

    if isinstance(data, B.Trial):
        raise ValueError(f"data must be a list of trials, got one Trial ({data.name}): pass [trial]")
    trials = list(data) if data is not None else []
    if not trials or not all(isinstance(t, B.Trial) for t in trials):
        raise ValueError(
            "data must be a non-empty list of jaxatt.data.broad.Trial (jaxatt.data.broad.load) or a study name"
        )
    trials = B.check_trials(trials, "data", need_scored=True)
    val_list = list(val) if val is not None else []  # once: val may be an iterator
    val_trials = B.check_trials(val_list, "val", need_scored=True) if val_list else []
    dt_ = compute_dtype(*trial_arrays([*trials, *val_trials]), dtype=dtype, what="trial data")
    obs, p0, entry, name = resolve_observer(observer, params, dtype=dt_)
    # one params for every trial: the data-dependent defaults are the trials' median (so FitResult.params, scored
    # with broad_score, gives the fit's own loss); trials far from it are warned about
    p0 = recording_defaults_for_trials(entry, params, p0, trials, warn=start is None)  # start= may set them
    trials = trials_start_from_valid(entry, truth_in_frame_of(entry, trials))
    val_trials = trials_start_from_valid(entry, truth_in_frame_of(entry, val_trials))
    p0 = jax.tree_util.tree_map(
        lambda a: jnp.asarray(a, dt_) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a,
        _start(p0, start, entry),
    )
    if entry is not None and entry.check is not None:
        entry.check(p0)
    bound = _parametrization(entry, p0, tune=tune, freeze=freeze, masks=masks, method=method, transforms=transforms)
    hold = engine.hold_for(obs, hold, "next")
    check_own_observer(obs, p0, entry, dt_, hold)
    check_own_estimate(obs, p0, entry, trials[0].samples, 1.0 / float(trials[0].rate_hz), dt_, hold)
    objective, n, take = recorded_objective(
        obs, bound, trials, hold=hold, dtype=dt_, step_remat=bool(step_remat), checkpoint=checkpoint
    )
    val_batch = val_objective = None
    if val_trials:
        val_objective, vn, vtake = recorded_objective(obs, bound, val_trials, hold=hold, dtype=dt_)
        val_batch = vtake(np.arange(vn))

    settings = {
        "data": "trials",
        "train_trials": [t.name for t in trials],
        "val_trials": [t.name for t in val_trials],
        "train_data": trials_fingerprint(trials),
        "val_data": trials_fingerprint(val_trials) if val_trials else None,
        "steps": int(steps),
        "lr": lr,
        "clip": clip,
        "schedule": schedule or "cosine",
        "batch": batch,
        "val_every": val_every,
        "patience": patience,
        "seed": seed,
        "hold": hold,
        "dtype": str(np.dtype(dt_)),
        "loss": "group-weighted mean per-trial total RMSE (deg), BROAD metric",
        "optimizer": optimizer,
        "tunable": {f: tr.describe() for f, tr in bound.transforms.items()},
        "n_tunable": bound.n_free(),
    }
    return _run(
        name,
        entry,
        obs,
        p0,
        bound,
        objective,
        Sampler(n, batch, seed),
        take,
        val_batch,
        settings,
        val_objective=val_objective,
        steps=steps,
        lr=lr,
        clip=clip,
        schedule=schedule or "cosine",
        val_every=val_every,
        patience=patience,
        out_path=out_path,
        previous=previous,
        callback=callback,
        quiet=quiet,
        study=None,
        metric_unit="deg",
        optimizer=optimizer,
    )


def _fit_study(
    study,
    observer,
    params,
    *,
    steps,
    lr,
    tune,
    freeze,
    masks,
    method,
    transforms,
    start,
    batch,
    val_every,
    patience,
    clip,
    schedule,
    seed,
    out_path,
    previous,
    callback,
    quiet,
    dtype,
    loss,
    transient_weight,
    config,
    train_runs,
    val_runs,
    refine_schedule,
    checkpoint,
    step_remat,
    devices,
    objective="montecarlo",
    optimizer="adam",
    hold=None,
):
    from .. import montecarlo, studies
    from .. import schedule as sched
    from ..observers import registry
    from ..studies.base import setup_params
    from . import losses

    st = studies.get(study)
    if st.name not in studies.TUNABLE:
        raise ValueError(f"study {st.name!r} cannot be tuned; tunable: {', '.join(studies.TUNABLE)}")
    train_runs = montecarlo.check_count("train_runs", train_runs, 1, MAX_RUNS)
    val_runs = montecarlo.check_count("val_runs", val_runs, 0, MAX_RUNS)
    if objective == "varfree":  # the variance-free loss draws no runs: options of the runs would be ignored
        given = [
            k
            for k, v in (("train_runs", train_runs != TRAIN_RUNS), ("val_runs", val_runs != VAL_RUNS))
            + (("batch", batch is not None),)
            if v
        ]
        if given:
            raise ValueError(
                f"{', '.join(given)}: objective='varfree' draws no runs (leave {'them' if len(given) > 1 else 'it'} "
                "out, or use objective='montecarlo')"
            )
    batch = 8 if batch is None else batch
    if config is not None and not isinstance(config, Mapping):
        raise ValueError(f"config must be a dict of {st.name} settings (name -> value), got {type(config).__name__}")
    if config is not None and not all(isinstance(k, str) for k in config):
        raise ValueError(f"config: {st.name} setting names must be strings, got {sorted(map(repr, config))}")
    config = dict(config or {})
    if hold is not None:  # the study's own setting (its samples' hold): honoured through its config
        if "hold" in config and config["hold"] != hold:
            raise ValueError(f"hold={hold!r} and config['hold']={config['hold']!r} differ: give the hold once")
        config["hold"] = hold
    s = st.setup(observer if isinstance(observer, str) else None, **config)
    if observer is not None and not isinstance(observer, str) and observer is not s.observer:
        raise ValueError(f"study {st.name}: pass the observer by its registered name ({s.entry!r}) or None")
    entry = registry.get(s.entry)
    p0 = _start(setup_params(s, params), start, entry)
    if len(refine_schedule):
        fields = [g.field for g in entry.gains if g.constraint == "schedule"]
        if not fields:
            raise ValueError(f"refine_schedule: {entry.name} has no piecewise-constant gain schedule")
        times = np.asarray(list(refine_schedule), float)
        if not np.all(np.isfinite(times)) or np.any(times <= 0) or np.any(times >= s.duration):
            raise ValueError(
                f"refine_schedule: switch times must lie inside the run (0, {s.duration}) s, got "
                f"{list(refine_schedule)}"
            )
        p0 = sched.refine(p0, times, fields)
    st.check_params(p0)
    st.check_step(s.config, p0)  # an explicit integrator's stability limit for these gains at this dt
    bound = _parametrization(entry, p0, tune=tune, freeze=freeze, masks=masks, method=method, transforms=transforms)
    (ss, se), (ts, te) = s.loss_windows["steady"], s.loss_windows["transient"]
    spec = losses.loss_spec(
        loss or s.loss_kind,
        steady_start=ss,
        steady_end=se,
        transient_start=ts,
        transient_end=te,
        w_transient=transient_weight,
    )
    if objective not in ("montecarlo", "varfree"):
        raise ValueError(f"objective must be 'montecarlo' or 'varfree', got {objective!r}")
    n_steps = montecarlo.whole_steps(s.duration, s.dt)
    if objective == "varfree":
        from . import varfree

        # a few tunable numbers: forward mode (one tangent each) is cheaper than reverse mode through the scan
        n_theta = sum(int(np.size(v)) for v in bound.init(jnp.result_type(float)).values())
        grad_mode = "forward" if n_theta <= FORWARD_MODE_MAX else "reverse"

        obj = varfree.varfree_objective(s, bound, spec, dtype=dtype, checkpoint=checkpoint, step_remat=step_remat)
        sampler, take, val_keys = Sampler(1, None, seed), (lambda idx: jnp.zeros(())), None
        settings = {
            "data": "study",
            "objective": "varfree",
            "study": st.name,
            "config": io.to_jsonable(s.config._asdict()),
            "steps": int(steps),
            "seed": seed,
            "lr": lr,
            "dtype": np.dtype(dtype or jnp.result_type(float)).name,
            "clip": clip,
            "schedule": schedule,
            "loss": spec.describe(),
            "duration_s": s.duration,
            "dt_s": s.dt,
            "steps_per_run": n_steps,
            "checkpoint_segment": losses.segment_length(n_steps, checkpoint),
            "tunable": {f: tr.describe() for f, tr in bound.transforms.items()},
            "masks": {f: m.tolist() for f, m in bound.masks.items()},
            "n_tunable": bound.n_free(),
            "note": "variance-free loss (jaxatt.fitting.varfree): expectation over the noise, no runs drawn",
            "optimizer": optimizer,
        }
        if len(refine_schedule):
            settings["refine_schedule"] = [float(x) for x in refine_schedule]
        if not quiet:
            print(
                f"fit {st.name}: {bound.n_free()} tunable numbers in {sorted(bound.transforms)}; variance-free loss "
                f"{spec.describe()['kind']} over {s.duration:g} s at {1 / s.dt:g} Hz; the first step compiles",
                file=sys.stderr,
                flush=True,
            )
        return _run(
            entry.name,
            entry,
            s.observer,
            p0,
            bound,
            obj,
            sampler,
            take,
            None,
            settings,
            steps=steps,
            lr=lr,
            clip=clip,
            schedule=schedule,
            val_every=val_every,
            patience=patience,
            out_path=out_path,
            previous=previous,
            grad=grad_mode,
            callback=callback,
            quiet=quiet,
            study=st.name,
            metric_unit="deg RMS",
            optimizer=optimizer,
        )
    if devices is None:  # every device that the batches split over evenly (3 devices, 16 runs: 2 devices)
        sizes = [int(min(batch or train_runs, train_runs))] + ([val_runs] if val_runs else [])
        devices = devices_for_batches(sizes)
        if devices is not None and devices < jax.local_device_count():
            warnings.warn(
                f"fit: {' and '.join(map(str, sizes))} runs per batch split evenly over {devices} of the "
                f"{jax.local_device_count()} devices, so the fit runs on {devices} (batch and val_runs that are "
                f"multiples of {jax.local_device_count()} use them all)",
                stacklevel=3,
            )
    objective_fn = simulated_objective(
        s, bound, spec, dtype=dtype, checkpoint=checkpoint, step_remat=step_remat, devices=devices
    )
    train_keys = montecarlo.run_keys(seed, list(range(train_runs)))
    val_keys = montecarlo.run_keys(seed, list(range(train_runs, train_runs + val_runs))) if val_runs else None
    settings = {
        "data": "study",
        "study": st.name,
        "config": io.to_jsonable(s.config._asdict()),
        "steps": int(steps),
        "train_runs": train_runs,
        "train_run_indices": [0, train_runs],
        "val_runs": val_runs,
        "val_run_indices": [train_runs, train_runs + val_runs],
        "seed": seed,
        "batch_runs": batch,
        "val_every": val_every,
        "patience": patience,
        "lr": lr,
        "dtype": np.dtype(dtype or jnp.result_type(float)).name,
        "clip": clip,
        "schedule": schedule,
        "loss": spec.describe(),
        "duration_s": s.duration,
        "dt_s": s.dt,
        "steps_per_run": n_steps,
        "checkpoint_segment": losses.segment_length(n_steps, checkpoint),
        "tunable": {f: tr.describe() for f, tr in bound.transforms.items()},
        "masks": {f: m.tolist() for f, m in bound.masks.items()},
        "n_tunable": bound.n_free(),
        "optimizer": optimizer,
    }
    if len(refine_schedule):
        settings["refine_schedule"] = [float(x) for x in refine_schedule]
    if not quiet:
        print(
            f"fit {st.name}: {bound.n_free()} tunable numbers in {sorted(bound.transforms)}; {train_runs} training "
            f"runs (batch {min(batch, train_runs)}), {val_runs} validation runs, {s.duration:g} s at "
            f"{1 / s.dt:g} Hz; loss {spec.describe()['kind']}; the first step compiles",
            file=sys.stderr,
            flush=True,
        )
    return _run(
        entry.name,
        entry,
        s.observer,
        p0,
        bound,
        objective_fn,
        Sampler(train_runs, batch, seed),
        lambda idx: train_keys[np.asarray(idx)],
        val_keys,
        settings,
        steps=steps,
        lr=lr,
        clip=clip,
        schedule=schedule,
        val_every=val_every,
        patience=patience,
        out_path=out_path,
        previous=previous,
        callback=callback,
        quiet=quiet,
        study=st.name,
        metric_unit="deg",
        optimizer=optimizer,
    )


def devices_for_batches(sizes) -> Optional[int]:
    """The most local devices (<= the visible ones) over which every batch size in ``sizes`` splits evenly, as a
    device count for ``devices=``; None (every device) when that is all of them or with several processes (where
    the batch sizes are the caller's to choose)."""
    if jax.process_count() > 1:
        return None
    n = jax.local_device_count()
    best = max(k for k in range(1, n + 1) if all(int(b) % k == 0 for b in sizes))
    return None if best == n else best


def _run(
    name,
    entry,
    obs,
    p0,
    bound,
    objective,
    sampler,
    take,
    val_batch,
    settings,
    *,
    steps,
    lr,
    clip,
    schedule,
    val_every,
    patience,
    out_path,
    previous,
    callback,
    quiet,
    study,
    metric_unit,
    val_objective=None,
    grad="reverse",
    optimizer="adam",
):
    """The loop, the gains file after every step, the result."""
    gains = entry.gains if entry is not None else None
    fields = None if entry is not None else list(bound.transforms)
    start_gains = gainsfile.gains_to_dict(p0, gains, fields)
    env = io.environment()
    resume_state = None
    if previous is not None:
        if previous.get("observer") not in (None, name):
            raise ValueError(f"resume: the saved fit is of observer {previous.get('observer')!r}, not {name!r}")
        if not previous.get("resume"):  # first: a file without one (another version's) has other settings too
            raise ValueError(
                f"resume: {out_path} holds no resume state (a gains file of another jaxatt version, e.g. 0.1, or "
                "written without one): start a new fit from its gains instead (start= / --init-gains)"
            )
        old = previous.get("settings", {})
        keys = [
            "data",
            "study",
            "train_trials",
            "train_runs",
            "seed",
            "lr",
            "batch",
            "batch_runs",
            "loss",
            "n_tunable",
            "schedule",
            "objective",
            "config",
            "val_runs",
            "refine_schedule",
            "tunable",
            "masks",
        ] + (["steps"] if settings.get("schedule") == "cosine" else [])
        old = {"optimizer": "adam", **old}  # files written before the choice existed: Adam
        if "dtype" in old:  # files written before it was saved: not compared
            keys.append("dtype")
        for k in keys + ["optimizer"]:
            if old.get(k) != settings.get(k):
                why = (
                    " (the cosine schedule's length: continue with the same steps, or start a new fit from its gains: "
                    "start= / --init-gains)"
                )
                raise ValueError(
                    f"resume: setting {k!r} differs from the saved fit ({old.get(k)!r} vs {settings.get(k)!r})"
                    + (why if k == "steps" else "")
                )
        for k in ("train_data", "val_data"):  # files written before the fingerprint have none
            if k in old and old[k] != settings.get(k):
                which = "training" if k == "train_data" else "validation"
                raise ValueError(
                    f"resume: the {which} trials hold other numbers than the saved fit's (same names: another file, "
                    "truth frame, columns or units?)"
                )
        _check_same_start(previous.get("start"), start_gains)
        resume_state = previous.get("resume")
        done = resume_state.get("step") if isinstance(resume_state, dict) else None
        if not isinstance(done, int) or isinstance(done, bool) or done < 0:
            raise ValueError(
                f"resume: the saved fit state in {out_path} is damaged (step {done!r} is not a number of steps); fit "
                "again without resume (overwrite=True / --overwrite replaces the file)"
            )
        if done >= steps:
            more = (
                " (its cosine schedule ends there: start a new fit from its gains instead: start= / --init-gains)"
                if settings.get("schedule") == "cosine"
                else "; ask for more steps"
            )
            raise ValueError(f"resume: the saved fit already ran {resume_state['step']} steps{more}")

    def on_save(res: OptimizeResult):
        if out_path is None:
            return
        best = bound.constrain(res.best_theta)
        gainsfile.write(
            out_path,
            observer=name,
            params=best,
            gains=gains,
            fields=fields,
            study=study,
            status=res.status,
            best_step=res.best_step,
            best_loss=res.best_val if res.best_val is not None else (res.resume.get("best_train")),
            start_loss=res.start_val,
            start=start_gains,
            settings=settings,
            history=res.history,
            provenance=env,
            resume=res.resume,
        )

    cb = callback if callback is not None else (None if quiet else print_progress)
    theta_dtype = jnp.result_type(*[jnp.asarray(getattr(p0, f)).dtype for f in bound.transforms])
    res = optimize(
        objective,
        bound.init(theta_dtype),
        steps=steps,
        sampler=sampler,
        take=take,
        val_batch=val_batch,
        val_objective=val_objective,
        val_every=val_every,
        patience=patience,
        lr=lr,
        clip=clip,
        schedule=schedule,
        project=bound.clip,
        callback=cb,
        on_save=on_save,
        resume=resume_state,
        metric_unit=metric_unit,
        grad=grad,
        optimizer=optimizer,
        resume_from=str(out_path) if out_path is not None else None,
    )
    if steps == 0 or (not res.history and out_path is not None):
        on_save(res)
    best = bound.constrain(res.best_theta)
    best_loss = res.best_val if res.best_val is not None else res.resume.get("best_train")
    if not quiet:
        n_done = len([h for h in res.history if "train_loss" in h])
        msg = f"fit {name}: {res.status} after {n_done} steps"
        if best_loss is not None:
            # best_step counts updates: without validation the training loss of the gains after step j is the
            # one printed on progress line j + 1 (each line's loss is of the gains going into that step)
            which = "the starting gains" if res.best_step == 0 else f"the gains after step {res.best_step}"
            msg += f"; best loss {best_loss:.5g} ({which})"
        print(msg + (f"; gains written to {out_path}" if out_path else ""), file=sys.stderr, flush=True)
    return FitResult(
        best, p0, res.history, res.status, res.best_step, best_loss, res.start_val, str(out_path) if out_path else None
    )
