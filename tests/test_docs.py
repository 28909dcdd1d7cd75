"""The documentation derives from the code: the README's observer table lists every registered observer with its
module, every observer module has a docs page, and the concepts page's example runs."""

import pkgutil
import re
from pathlib import Path

import numpy as np

from jaxatt.observers import registry

ROOT = Path(__file__).resolve().parents[1]


def test_readme_observer_table_is_the_registry():
    """The README's observers table is the registry's (jaxatt.observers.registry.markdown_table()), and every
    observer module has a docs page."""
    text = (ROOT / "README.md").read_text()
    assert registry.markdown_table() in text, "paste this table into README.md:\n" + registry.markdown_table()
    for n in registry.names():
        assert f"| `{n}` | `jaxatt.observers.{registry.INDEX[n]}` |" in text
    for mod in set(registry.INDEX.values()):
        assert (ROOT / "docs" / "observers" / f"{mod}.md").is_file(), mod


def test_concepts_example_runs():
    """The user-observer example at the end of docs/concepts.md runs as written."""
    code = (ROOT / "docs" / "concepts.md").read_text().split("```python")[-1].split("```")[0]
    code = code.replace("duration=30.0", "duration=3.0").replace("runs=8", "runs=2")
    ns = {}
    exec(compile(code, "concepts.md", "exec"), ns)
    assert ns["est"].quat.shape == (301, 4) and np.all(np.isfinite(ns["res"].per_run["mean_angle_error_deg"]))
    # the same observer in float32 (as for BROAD fits): its constants follow the state's dtype, and the estimate
    # agrees with the float64 run to float32 rounding
    s = ns["samples"]
    est32 = ns["jaxatt"].filter(ns["mine"], s.gyr, s.acc, s.mag, dt=0.01, params=ns["Params"](1.0), dtype="float32")
    assert est32.quat.dtype == np.float32 and ns["est"].quat.dtype == np.float64
    np.testing.assert_allclose(np.abs(np.sum(est32.quat * ns["est"].quat, axis=-1)), 1.0, atol=1e-5)


#: 0.1's module names kept as aliases of their 0.2 places (not reference pages of their own).
OLD_ALIASES = {"jaxatt.experiments", "jaxatt.parametrize"}


def test_reference_covers_every_public_module():
    """The API reference pages (docs/reference/*.md, rendered by mkdocstrings) name every public module of jaxatt
    once, the site's nav lists every page and notebook, and every module in the reference exists."""
    import jaxatt

    public = {"jaxatt"} | {
        m.name
        for m in pkgutil.walk_packages(jaxatt.__path__, "jaxatt.")
        if not any(part.startswith("_") for part in m.name.split(".")[1:])
    } - OLD_ALIASES

    pages = sorted((ROOT / "docs" / "reference").glob("*.md"))
    named = [m for page in pages for m in re.findall(r"^::: (\S+)$", page.read_text(), flags=re.M)]
    assert sorted(named) == sorted(public), (sorted(public - set(named)), sorted(set(named) - public))
    nav = (ROOT / "mkdocs.yml").read_text()
    for page in pages:
        assert f"reference/{page.name}" in nav, page.name
    for nb in (ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"):
        assert f"notebooks/{nb.name}" in nav, nb.name
    for md in (ROOT / "docs" / "observers").glob("*.md"):
        assert f"observers/{md.name}" in nav, md.name


def test_the_0_1_readmes_python_example_still_runs_through_the_aliases():
    """Version 0.1's README imported the studies from jaxatt.experiments and the transforms from
    jaxatt.parametrize: both still import (the same modules as jaxatt.studies / jaxatt.fitting.parametrize), with
    a DeprecationWarning naming the new place, and the 0.1 example gives the 0.2 numbers."""
    import importlib
    import sys

    import pytest

    from jaxatt import montecarlo
    from jaxatt.fitting import parametrize as new_parametrize
    from jaxatt.studies import batista_ges

    for name, new in (("jaxatt.experiments", "jaxatt.studies"), ("jaxatt.parametrize", "jaxatt.fitting.parametrize")):
        sys.modules.pop(name, None)
        with pytest.warns(DeprecationWarning, match=f"{name} is {new} since 0.2"):
            old = importlib.import_module(name)
    assert old.Positive is new_parametrize.Positive
    import jaxatt.experiments.nlio  # 0.1's submodule imports  # noqa: F401
    from jaxatt.experiments import batista_ges as E  # the 0.1 README's lines

    assert sys.modules["jaxatt.experiments.nlio"] is importlib.import_module("jaxatt.studies.nlio")

    assert E is batista_ges
    cfg = E.Config()
    samples, _ = montecarlo.simulate_log(E.scenario(cfg), duration=0.5, dt=0.01)
    assert montecarlo.run(E.observer(cfg), E.params(cfg), samples).r.shape == (51, 3, 3)
