"""Shared helpers of the benchmarks: machine / version metadata, timing, tables and result files.

Every benchmark writes one JSON file ``<out>/<name>-<hostname>-<UTC timestamp>.json`` holding ``meta``
(:func:`metadata`) and its own numbers, so results from different machines and commits can be compared.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import pathlib
import platform
import resource
import socket
import statistics
import subprocess
import sys
import time
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence

__all__ = [
    "RESULTS_DIR",
    "REPO_ROOT",
    "metadata",
    "jax_info",
    "machine_info",
    "versions",
    "git_info",
    "peak_rss_mib",
    "time_it",
    "write_results",
    "format_table",
    "print_table",
    "utc_now",
]

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS_DIR = REPO_ROOT / "benchmarks" / "results"


def utc_now() -> _dt.datetime:
    return _dt.datetime.now(_dt.timezone.utc)


def _read(path: str) -> str:
    try:
        with open(path) as f:
            return f.read()
    except OSError:
        return ""


def _cpu_model() -> Optional[str]:
    from jaxatt import io  # the package's provenance (written once there)

    return io.environment()["cpu_model"]


def _mem_total_gib() -> Optional[float]:
    for line in _read("/proc/meminfo").splitlines():
        if line.startswith("MemTotal:"):
            return round(int(line.split()[1]) / 2**20, 2)
    return None


def machine_info() -> Dict[str, Any]:
    """Platform, CPU model and counts, memory, load average at the time of the call."""
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        affinity = None
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    return {
        "hostname": socket.gethostname(),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": affinity,
        "mem_total_gib": _mem_total_gib(),
        "loadavg_1_5_15": load,
    }


def _version(mod: str) -> Optional[str]:
    try:
        m = __import__(mod)
        return getattr(m, "__version__", None)
    except Exception:  # noqa: BLE001 - metadata must never fail
        return None


def versions() -> Dict[str, Any]:
    return {
        "python": sys.version.split()[0],
        "python_impl": platform.python_implementation(),
        "jax": _version("jax"),
        "jaxlib": _version("jaxlib"),
        "numpy": _version("numpy"),
        "scipy": _version("scipy"),
        "jaxatt": _version("jaxatt"),
    }


def git_info() -> Dict[str, Any]:
    """Commit and whether the working tree differs from it (results of uncommitted code say so)."""

    def git(*args):
        try:
            return subprocess.run(
                ["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=10
            ).stdout.rstrip()
        except Exception:  # noqa: BLE001
            return ""

    commit = git("rev-parse", "HEAD").strip()
    if not commit:
        return {"commit": None, "dirty": None, "modified": []}
    modified = [line[3:] for line in git("status", "--porcelain", "--untracked-files=no").splitlines() if line]
    return {"commit": commit, "dirty": bool(modified), "modified": modified}


def jax_info() -> Dict[str, Any]:
    import jax

    devs = jax.devices()
    return {
        "backend": jax.default_backend(),
        "devices": [str(d) for d in devs],
        "device_kind": devs[0].device_kind if devs else None,
        "x64_enabled": bool(jax.config.jax_enable_x64),
    }


_ENV_KEYS = (
    "XLA_FLAGS",
    "JAX_PLATFORMS",
    "JAX_ENABLE_X64",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "CUDA_VISIBLE_DEVICES",
    "XLA_PYTHON_CLIENT_PREALLOCATE",
)


def metadata(argv: Optional[Sequence[str]] = None) -> Dict[str, Any]:
    """Everything needed to interpret a result: date, machine, versions, git state, JAX backend, env."""
    meta = {
        "date_utc": utc_now().isoformat(timespec="seconds"),
        "machine": machine_info(),
        "versions": versions(),
        "git": git_info(),
        "env": {k: os.environ[k] for k in _ENV_KEYS if k in os.environ},
        "argv": list(sys.argv if argv is None else argv),
    }
    try:
        meta["jax"] = jax_info()
    except Exception as e:  # noqa: BLE001
        meta["jax"] = {"error": repr(e)}
    return meta


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far (MiB; ru_maxrss is KiB on Linux, bytes on macOS)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 1024


def time_it(
    fn: Callable[[], Any], *, repeats: int = 3, min_time: float = 0.0, sync: Callable[[Any], Any] = None
) -> Dict[str, Any]:
    """Wall times (s) of ``repeats`` calls of ``fn`` (already warm), more while their sum < ``min_time``.

    ``sync(result)`` blocks until the result is ready (e.g. ``jax.block_until_ready``).
    """
    times: List[float] = []
    while len(times) < repeats or sum(times) < min_time:
        t0 = time.perf_counter()
        out = fn()
        if sync is not None:
            sync(out)
        times.append(time.perf_counter() - t0)
        if len(times) >= 50:
            break
    return {"best_s": min(times), "median_s": statistics.median(times), "times_s": times}


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:
        pass
    if isinstance(o, pathlib.Path):
        return str(o)
    return repr(o)


def write_results(name: str, data: Dict[str, Any], out_dir=None, meta: Optional[Dict[str, Any]] = None) -> pathlib.Path:
    """Write ``{"benchmark": name, "meta": ..., **data}`` to ``<out_dir>/<name>-<host>-<UTC stamp>.json``."""
    out_dir = pathlib.Path(out_dir) if out_dir is not None else RESULTS_DIR
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = metadata() if meta is None else meta
    host = "".join(c if c.isalnum() or c in "-_." else "_" for c in meta["machine"]["hostname"]) or "host"
    stamp = utc_now().strftime("%Y%m%dT%H%M%SZ")
    path = out_dir / f"{name}-{host}-{stamp}.json"
    with open(path, "w") as f:
        json.dump({"benchmark": name, "meta": meta, **data}, f, indent=2, default=_json_default)
        f.write("\n")
    return path


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        a = abs(v)
        if a != 0 and (a >= 1e6 or a < 1e-3):
            return f"{v:.3e}"
        return f"{v:.4g}" if a < 100 else f"{v:,.0f}"
    if isinstance(v, int) and not isinstance(v, bool):
        return f"{v:,}"
    return str(v)


def format_table(rows: Iterable[Dict[str, Any]], columns: Sequence[str]) -> str:
    rows = list(rows)
    cells = [[_fmt(r.get(c)) for c in columns] for r in rows]
    widths = [max([len(c)] + [len(row[i]) for row in cells]) for i, c in enumerate(columns)]
    line = lambda vals: "  ".join(v.rjust(w) for v, w in zip(vals, widths))  # noqa: E731
    return "\n".join([line(columns), line(["-" * w for w in widths])] + [line(r) for r in cells])


def print_table(rows, columns, title: Optional[str] = None) -> None:
    if title:
        print(f"\n{title}")
    print(format_table(rows, columns), flush=True)
