"""The gains file: one versioned JSON format that every command reads and :func:`jaxatt.fit` writes.

Layout (``"format": "jaxatt-gains/2"``)::

    {"format": "jaxatt-gains/2",
     "observer": "robust",                 # registry name (or the name of your own Observer)
     "study": null,                        # the simulated study tuned on ("batista-ges", ...), or null
     "gains": {"tau_acc": {"value": 1.75, "unit": "s", "constraint": "positive", "doc": "..."}, ...},
     "start": {"tau_acc": 2.0, ...},       # the gains the fit started from
     "status": "done", "best_step": 12, "settings": {...}, "history": [...],
     "provenance": {...},                  # jaxatt.io.environment()
     "resume": {...}}                      # optimizer state etc. while a fit is running or was interrupted

A schedule (constraint "schedule") also carries ``switch_times_s`` and ``intervals_s``; a gain whose unit is not a
rate may carry ``as_rate``. Values are numbers or nested lists (matrices). Files of jaxatt 0.1
(``"jaxatt-gains/1"``: ``{"experiment", "gains": {field: {"value"}}}`` from ``jaxatt tune`` or ``{"observer",
"gains": {field: number}}`` from ``jaxatt broad-tune``) are read too.
"""

from __future__ import annotations

from importlib import resources
from typing import Any, Mapping, Optional, Sequence

import jax.numpy as jnp
import numpy as np

from .. import io

__all__ = [
    "FORMAT",
    "gains_to_dict",
    "write",
    "read",
    "apply",
    "read_params",
    "load_shipped",
    "shipped_path",
    "STUDY_OBSERVER",
]

FORMAT = "jaxatt-gains/2"
_OLD = "jaxatt-gains/1"

#: The observer tuned in each study of jaxatt 0.1's gains files (``"experiment"`` key).
#: keys of jaxatt 0.1's tune files -> this format's
_RENAMED = {
    "tuning": "settings",
    "environment": "provenance",
    "start_gains": "start",
    "best_val_loss": "best_loss",
    "start_val_loss": "start_loss",
}

STUDY_OBSERVER = {
    "batista-ges": "batista-ges",
    "batista-so3": "batista-so3",
    "nlio-case1": "nlio-fg",
    "nlio-case2": "nlio-fg",
    "nlio-case3": "nlio-fg",
}


def _tolist(a):
    a = np.asarray(a, float)
    return a.tolist() if a.ndim else float(a)


def _fields(params):
    if hasattr(params, "_asdict"):
        return params._asdict()
    if isinstance(params, dict):
        return dict(params)
    raise ValueError(f"params must be a NamedTuple or a dict, got {type(params).__name__}")


def gains_to_dict(params, gains: Optional[Sequence[Any]] = None, fields: Optional[Sequence[str]] = None) -> dict:
    """Human-readable gains: field -> {value, unit, constraint, doc} (+ switch times and intervals for a schedule,
    + ``as_rate``). ``gains``: the registry's declarations (:class:`jaxatt.observers.registry.Gain`); without them
    every floating field of ``params`` (or ``fields``) is written with unit "?"."""
    values = _fields(params)
    out = {}
    if gains is None:
        for f in fields or values:
            v = values[f]
            if v is not None and np.issubdtype(np.asarray(v).dtype, np.floating):
                out[f] = {"value": _tolist(v), "unit": "?", "constraint": "positive", "doc": ""}
        return out
    for g in gains:
        v = np.asarray(values[g.field], float)
        d = {"value": _tolist(v), "unit": g.unit, "constraint": g.constraint, "doc": g.doc}
        if g.constraint == "schedule":
            st = np.asarray(values["switch_times"], float)
            edges = [0.0] + st.tolist() + [None]
            d["switch_times_s"] = st.tolist()
            d["intervals_s"] = [[edges[i], edges[i + 1]] for i in range(len(edges) - 1)]
        if g.rate is not None:
            label, fn = g.rate
            d["as_rate"] = {"label": label, "value": _tolist(v * fn(params))}
        out[g.field] = d
    return out


def write(
    path,
    *,
    observer: str,
    params,
    gains: Optional[Sequence[Any]] = None,
    study: Optional[str] = None,
    fields: Optional[Sequence[str]] = None,
    **extra,
) -> None:
    """Write a gains file atomically (:func:`jaxatt.io.write_json`); ``extra`` keys (start, status, settings,
    history, provenance, resume, ...) are added as they are."""
    payload = {"format": FORMAT, "observer": observer, "study": study, "gains": gains_to_dict(params, gains, fields)}
    payload.update(extra)
    io.write_json(path, payload)


#: statuses of a finished fit; any other status (``running``, ``interrupted``, ``non-finite``) is a fit that
#: stopped early, whose file holds the best gains it had reached
FINISHED = ("done", "early-stopped")


def unfinished_note(d: Mapping[str, Any], path) -> Optional[str]:
    """One line saying that gains file ``path`` (read as ``d``) holds the best gains of a fit that did not finish,
    or None for a finished fit (or a file without a status: written by hand or by jaxatt 0.1)."""
    status = d.get("status")
    if status is None or status in FINISHED or _is_shipped(path):  # shipped files say how they were made (notes)
        return None
    best = d.get("best_step")
    return (
        f"gains file {path}: its fit did not finish (status {status!r}); using the best gains it reached"
        + (f" (step {best})" if best is not None else "")
        + "; continue it with resume"
    )


def _is_shipped(path) -> bool:
    import pathlib

    try:
        return pathlib.Path(path).resolve().parent == pathlib.Path(str(resources.files("jaxatt.data.gains"))).resolve()
    except (OSError, TypeError, ValueError):
        return False


def read(path) -> dict:
    """Read a gains file (this format or jaxatt 0.1's) as this format's dict. ValueError naming the file when it is
    missing, not JSON or not a gains file."""
    d = io.read_json(path, "gains file")
    if not isinstance(d, dict):
        raise ValueError(f"gains file {path}: not a jaxatt gains file (a JSON {type(d).__name__}, want an object)")
    fmt = d.get("format")
    if fmt == FORMAT:
        if not isinstance(d.get("gains"), dict) or not isinstance(d.get("observer"), str) or not d["observer"]:
            raise ValueError(f"gains file {path}: needs 'observer' (a name) and 'gains' (an object)")
        return _checked(d, path)
    if fmt == _OLD and isinstance(d.get("gains"), dict):
        if "experiment" in d:  # jaxatt tune (0.1): its keys under this format's names
            study = d["experiment"]
            if not isinstance(study, str):
                raise ValueError(f"gains file {path}: 'experiment' must be a study name, got {study!r}")
            renamed = {_RENAMED.get(k, k): v for k, v in d.items()}
            out = {**renamed, "format": FORMAT, "observer": STUDY_OBSERVER.get(study, study), "study": study}
            return _checked(out, path)
        if isinstance(d.get("observer"), str):  # jaxatt broad-tune (0.1): {name: number}
            gains = {k: (v if isinstance(v, Mapping) else {"value": v}) for k, v in d["gains"].items()}
            return _checked({**d, "format": FORMAT, "study": None, "gains": gains}, path)
    raise ValueError(f"gains file {path}: not a jaxatt gains file (format {fmt!r}, want {FORMAT!r})")


def _checked(d: dict, path) -> dict:
    """``d`` after the checks every reader relies on (ValueError naming the file and the key)."""
    if not d["gains"]:
        raise ValueError(f"gains file {path}: 'gains' is empty (no gain to apply)")
    for name, entry in d["gains"].items():
        if not isinstance(entry, Mapping) or "value" not in entry:
            raise ValueError(f"gains file {path}: gain {name!r} must be an object with a 'value'")
    if d.get("study") is not None and not isinstance(d["study"], str):
        raise ValueError(f"gains file {path}: 'study' must be a study name or null, got {d['study']!r}")
    if not isinstance(d.get("settings", {}), dict):
        raise ValueError(f"gains file {path}: 'settings' must be an object, got {d['settings']!r}")
    return d


def apply(params, gains: Mapping[str, Any], *, source: str = "gains"):
    """``params`` with the values of a gains dict (this format's ``gains``, or field -> value) put in. Shapes must
    match; a schedule's switch times come from the dict when it carries them. ValueError naming the field.
    Params of another pytree shape (a dataclass, nested fields) take gains named by their leaves, as a fit of them
    writes (:mod:`jaxatt.fitting.flatparams`), and keep their shape."""
    from . import flatparams

    if flatparams.needs_flat_view(params):
        view, rebuild = flatparams.flat_view(params)
        return rebuild(apply(view, gains, source=source))
    values = _fields(params)
    new = {}
    for name, entry in gains.items():
        if name not in values:
            raise ValueError(f"{source}: {name!r} is not a field of the observer's params (fields: {sorted(values)})")
        val = entry["value"] if isinstance(entry, Mapping) else entry
        try:
            arr = np.asarray(val, float)
        except (TypeError, ValueError):
            raise ValueError(f"{source}: {name} is not numeric: {val!r}") from None
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{source}: {name} is not finite: {val!r}")
        ref = jnp.asarray(values[name])
        if isinstance(entry, Mapping) and "switch_times_s" in entry:
            try:
                st = np.asarray(entry["switch_times_s"], float).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"{source}: {name}.switch_times_s must be a list of seconds") from None
            if "switch_times" not in values or not np.all(np.isfinite(st)) or np.any(np.diff(st) <= 0):
                raise ValueError(f"{source}: {name}.switch_times_s must be increasing finite seconds of a schedule")
            if arr.shape[:1] != (st.shape[0] + 1,):
                raise ValueError(f"{source}: {name} has {arr.shape[0]} values for {st.shape[0]} switch times")
            new["switch_times"] = jnp.asarray(st, jnp.asarray(values["switch_times"]).dtype)
        elif arr.shape != ref.shape:
            raise ValueError(f"{source}: {name} has shape {arr.shape}, the observer's params have {ref.shape}")
        new[name] = jnp.asarray(arr, ref.dtype)
    if hasattr(params, "_replace"):
        return params._replace(**new)
    return {**values, **new}


def read_params(path, entry=None, base=None, *, dtype=None):
    """Params from a gains file: ``base`` with the file's gains put in, checked by the entry. Default ``base``: the
    paper's params of the file's study when it names one, else the registry entry's defaults in ``dtype``. The file
    must hold gains of that observer (one of an unfinished fit is used with a warning: :func:`unfinished_note`)."""
    d = read(path)
    if entry is not None:
        from ..observers import registry

        entry = registry.get(entry)
        if d["observer"] != entry.name:
            raise ValueError(f"gains file {path}: holds gains of {d['observer']!r}, not of {entry.name!r}")
        if base is None and d.get("study"):
            from .. import studies

            base = studies.get(d["study"]).setup(entry.name).params
        if base is None:
            base = entry.default_params(dtype=dtype)
    if base is None:
        raise ValueError("read_params needs a registry entry or base params")
    if entry is None:
        _check_base_type(path, d["observer"], base)
    params = apply(base, d["gains"], source=f"gains file {path}")
    if entry is not None and entry.check is not None:
        try:
            entry.check(params)
        except ValueError as e:
            raise ValueError(f"gains file {path}: {e}") from None
    note = unfinished_note(d, path)
    if note:
        import warnings

        warnings.warn(note, stacklevel=2)
    return params


def _check_base_type(path, observer: str, base) -> None:
    """A file of a registered observer read into ``base`` params of another type (e.g. batista-ges gains into
    batista-so3 params: some fields share names and shapes) is refused; a user's own observer is not checked."""
    from ..observers import registry

    if observer not in registry.names():
        return
    want = type(registry.get(observer).default_params())
    if type(base) is not want:
        raise ValueError(
            f"gains file {path}: holds gains of {observer!r}, whose params are {want.__module__}.{want.__qualname__}, "
            f"not {type(base).__module__}.{type(base).__qualname__}"
        )


def shipped_path(name: str):
    """A path-like to a gains file shipped in :mod:`jaxatt.data.gains`."""
    p = resources.files("jaxatt.data.gains") / name
    if not p.is_file():
        avail = sorted(x.name for x in resources.files("jaxatt.data.gains").iterdir() if x.name.endswith(".json"))
        raise ValueError(f"no shipped gains file {name!r}; shipped: {avail}")
    return p


def load_shipped(name: str, entry, *, dtype=None):
    """Params of ``entry`` with a shipped gains file's gains."""
    with resources.as_file(shipped_path(name)) as p:
        return read_params(p, entry, dtype=dtype)
