"""The documentation derives from the code: the README's observer table lists every registered observer with its
module, every observer module has a docs page, and the concepts page's example runs."""

from pathlib import Path

import numpy as np

from jaxatt.observers import registry

ROOT = Path(__file__).resolve().parents[1]


def test_readme_observer_table_is_the_registry():
    """The README's observers table is generated from the registry (python docs/build_api.py), and every observer
    module has a docs page."""
    text = (ROOT / "README.md").read_text()
    assert registry.markdown_table() in text
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
