"""Params of any pytree shape seen as a flat NamedTuple of named gains, for the fitter and gains files.

The fitter and gains files name gains by field (``params.kp``, ``{"kp": {"value": ...}}``). Your own observer's
params may be any JAX pytree: a NamedTuple, a dict, a registered dataclass, a tuple, nested ones. A
:func:`flat_view` of them is a NamedTuple with one field per leaf, named by the leaf's path (``kp`` for
``{"kp": ...}``, ``acc_k`` for ``Params(acc=AccGains(k=...))``, ``k_0`` for ``k=(k_acc, k_mag)``), and a function
that rebuilds the params of your shape from it. Params that are already a flat NamedTuple or dict of arrays are
their own view (:func:`needs_flat_view` is False), so the registered observers' gains keep their field names.
"""

from __future__ import annotations

import collections
import dataclasses
import keyword
import re
from typing import Any, Callable, Tuple

import jax

__all__ = ["needs_flat_view", "flat_view", "leaf_names", "observer_on_view"]


def _is_container(v) -> bool:
    """Whether a field holds a pytree node (a tuple, a dict, a dataclass, a registered class) rather than one leaf."""
    if v is None:
        return False
    return (
        isinstance(v, (tuple, list, dict))
        or dataclasses.is_dataclass(v)
        or not jax.tree_util.treedef_is_leaf(jax.tree_util.tree_structure(v))
    )


def needs_flat_view(params) -> bool:
    """True unless ``params`` is a NamedTuple or dict whose every field is one array, number or None."""
    if hasattr(params, "_fields"):
        values = [getattr(params, f) for f in params._fields]
    elif isinstance(params, dict):
        values = list(params.values())
        if not all(isinstance(k, str) and k.isidentifier() and not keyword.iskeyword(k) for k in params):
            return True
    else:
        return True
    return any(_is_container(v) for v in values)


def _part(key) -> str:
    for attr in ("key", "name", "idx"):
        if hasattr(key, attr):
            return str(getattr(key, attr))
    return str(key)


def leaf_names(params) -> Tuple[list, Any]:
    """(names, treedef): one identifier per leaf of ``params`` from its path (parts joined by ``_``; characters
    that cannot be in a name become ``_``). ValueError when two leaves read as one name (``{"a_b": ..}`` beside
    ``{"a": {"b": ..}}``): a gain name must say which leaf it is."""
    paths, treedef = jax.tree_util.tree_flatten_with_path(params)
    names: list = []
    where: dict = {}
    for path, _ in paths:
        name = re.sub(r"[^0-9A-Za-z_]", "_", "_".join(_part(k) for k in path)) or "value"
        if name[0].isdigit() or name[0] == "_" or keyword.iskeyword(name):  # not a NamedTuple field name
            name = "g_" + name
        shown = jax.tree_util.keystr(path) or "(params)"
        if name in where:
            raise ValueError(
                f"params: the leaves {where[name]} and {shown} both read as the gain name {name!r}: rename one"
            )
        where[name] = shown
        names.append(name)
    return names, treedef


def flat_view(params) -> Tuple[Any, Callable[[Any], Any]]:
    """(view, rebuild): ``view`` a NamedTuple ``Gains`` with one field per leaf of ``params`` (:func:`leaf_names`),
    ``rebuild(view)`` the params of ``params``'s pytree shape with the view's values (traceable: the fitter calls
    it inside the scan)."""
    names, treedef = leaf_names(params)
    gains_type = collections.namedtuple("Gains", names)  # type: ignore[misc]
    view = gains_type(*jax.tree_util.tree_leaves(params))

    def rebuild(v):
        return jax.tree_util.tree_unflatten(treedef, [getattr(v, n) for n in names])

    return view, rebuild


def observer_on_view(observer, rebuild):
    """``observer`` taking the flat view's params: its init, step, output and time_reversed get ``rebuild(view)``."""

    def init(p, sample):
        return observer.init(rebuild(p), sample)

    def step(p, state, u, dt):
        return observer.step(rebuild(p), state, u, dt)

    def output(p, state):
        return observer.output(rebuild(p), state)

    def time_reversed(p):
        return type(p)(*jax.tree_util.tree_leaves(observer.time_reversed(rebuild(p))))

    return observer._replace(
        init=init,
        step=step,
        output=None if observer.output is None else output,
        time_reversed=None if observer.time_reversed is None else time_reversed,
    )
