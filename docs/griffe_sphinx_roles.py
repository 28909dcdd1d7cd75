"""Griffe extension for the API reference: the docstrings' Sphinx roles (``:func:`x```) shown as code spans.

jaxatt's docstrings cross-reference with Sphinx roles (readable in ``help()`` and in editors); Markdown has no
roles, so mkdocstrings would print them raw. Loaded by mkdocs.yml (mkdocstrings' ``extensions`` option).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:func|class|mod|data|meth|attr|obj|exc):`~?([^`]+)`")


class SphinxRoles(griffe.Extension):
    """Rewrite ``:role:`target``` as ``target`` in every docstring when griffe loads an object."""

    def on_instance(self, *, node: Any, obj: griffe.Object, agent: Any, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(r"`\1`", obj.docstring.value)
