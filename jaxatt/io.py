"""Files written by jaxatt: one atomic JSON writer, output paths checked before any computation, and the
provenance recorded with every result (machine, versions, git commit, command line, XLA flags, devices, date)."""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import socket
import stat
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Any, Callable, List, Mapping, Optional, Sequence

import numpy as np

__all__ = [
    "write_json",
    "read_json",
    "check_output_path",
    "check_figure_path",
    "environment",
    "summarise",
    "to_jsonable",
    "is_main_process",
]


def to_jsonable(o: Any):
    """numpy / JAX scalars and arrays as Python numbers and lists; NaN and inf stay floats (JSON NaN/Infinity)."""
    if isinstance(o, dict):
        return {str(k): to_jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [to_jsonable(v) for v in o]
    if isinstance(o, (str, bool, int, float)) or o is None:
        return o
    if hasattr(o, "_asdict"):
        return to_jsonable(o._asdict())
    try:
        a = np.asarray(o)
    except Exception:  # noqa: BLE001 - anything else is written by its repr
        return repr(o)
    if a.dtype == object:
        return repr(o)
    return a.tolist() if a.ndim else a.item()


#: the extensions of a JSON output (results, gains files); "" = none
JSON_SUFFIXES = (".json", "")


def check_output_path(
    path,
    flag: str = "output",
    suffixes: Optional[Sequence[str]] = None,
    inputs: Optional[Mapping[str, Any]] = None,
    keep_gains: bool = False,
) -> Optional[Path]:
    """Check, before computing, that ``path`` can be written: its folder exists or can be created (the check
    creates it, probes it and removes what it created) and is writable, and ``path`` is not a folder; with
    ``suffixes`` (such as (".csv", ".npz"), "" for none), that its extension is one of them (a device or FIFO is
    exempt); with ``inputs`` ({flag: path} of the files or folders the command reads), that it is none of those
    files nor an existing file in those folders (writing would destroy an input); with ``keep_gains``, that it is
    not an existing gains file (a fit's result, which a score or result file would replace). Returns the Path
    (None for None). ValueError naming ``flag``."""
    if path is None:
        return None
    if not str(path).strip():
        raise ValueError(f"{flag}: empty path")
    p = Path(path)
    if keep_gains and p.is_file():
        try:
            with open(p, "rb") as f:
                head = f.read(256)
        except OSError:
            head = b""
        if b'"jaxatt-gains/' in head:
            raise ValueError(
                f"{flag} {path}: is a gains file (a fit's result), which this would replace: choose another name"
            )
    for other_flag, other in (inputs or {}).items():
        if other is None or not str(other).strip():
            continue
        if Path(other).is_dir() and p.exists() and _inside(p, Path(other)):
            raise ValueError(f"{flag} {path}: is a file in the {other_flag} folder (writing it would change the input)")
        if _same_file(p, Path(other)):
            raise ValueError(f"{flag} {path}: is the {other_flag} file (writing it would destroy the input)")
    if p.exists() and p.is_dir():
        raise ValueError(f"{flag} {path}: is a folder, expected a file name")
    if suffixes is not None and not is_special(p) and p.suffix.lower() not in suffixes:
        named = ", ".join(x for x in suffixes if x)
        raise ValueError(f"{flag} {path}: unknown extension {p.suffix!r}; this writes {named}")
    if is_special(p):  # /dev/null, a FIFO: written in place (write_atomic), never replaced
        if not os.access(p, os.W_OK):
            raise ValueError(f"{flag} {path}: is not writable")
        return p
    parent = p.parent if str(p.parent) else Path(".")
    created = [a for a in [parent, *parent.parents] if not a.exists()]  # folders the probe makes (deepest first)
    try:
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"{flag} {path}: cannot create its folder ({e.strerror or e})") from None
        if not os.access(parent, os.W_OK):
            raise ValueError(f"{flag} {path}: folder {parent} is not writable")
        if p.exists() and not os.access(p, os.W_OK):
            raise ValueError(f"{flag} {path}: file is not writable")
        try:  # the real test (permissions can say yes where a write fails: /proc, read-only mounts, as root)
            fd, probe = tempfile.mkstemp(prefix=p.name + ".", suffix=".tmp", dir=str(parent))
            os.close(fd)
            os.unlink(probe)
        except OSError as e:
            raise ValueError(f"{flag} {path}: cannot write in folder {parent} ({e.strerror or e})") from None
    finally:  # a check leaves nothing behind: the writer creates the folders when it has something to write
        for folder in created:
            try:
                folder.rmdir()
            except OSError:
                break
    return p


def _inside(a: Path, folder: Path) -> bool:
    try:
        return a.resolve().parent == folder.resolve()
    except OSError:
        return False


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except OSError:
        return False


def check_figure_path(path, flag: str = "--plot", inputs: Optional[Mapping[str, Any]] = None) -> Optional[Path]:
    """:func:`check_output_path` for a figure, and its extension is a format matplotlib writes (png, pdf, svg,
    ...), so that a run is not computed for a figure that cannot be saved. ValueError naming ``flag``."""
    p = check_output_path(path, flag, inputs=inputs)
    if p is None or is_special(p):
        return p
    from matplotlib.backend_bases import FigureCanvasBase

    formats = FigureCanvasBase.get_supported_filetypes()
    ext = p.suffix.lower().lstrip(".")
    if ext not in formats:
        raise ValueError(f"{flag} {path}: unknown figure format {ext!r}; use one of {', '.join(sorted(formats))}")
    return p


def is_main_process() -> bool:
    """False only in the processes other than process 0 of a multi-process JAX run (``jax.distributed``), which
    write no files: every process computes the same results, process 0 saves them. True in a single process (and
    before JAX is imported)."""
    jax = sys.modules.get("jax")
    if jax is None:
        return True
    initialized = getattr(getattr(jax, "distributed", None), "is_initialized", None)
    if initialized is None or not initialized():
        return True
    return jax.process_index() == 0


def is_special(p) -> bool:
    """True for an existing path that is neither a regular file nor a folder (a character device, a FIFO)."""
    try:
        mode = os.stat(p).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


#: Every path :func:`write_atomic` has written in this process (in order, repeats kept once): what an interrupted
#: command says it saved.
WRITTEN: List[str] = []


def _written(p: Path) -> None:
    if str(p) not in WRITTEN:
        WRITTEN.append(str(p))


def write_atomic(path, write: Callable[[Any], None], binary: bool = False) -> None:
    """Write a file atomically: ``write(file_object)`` fills a temporary file in the same folder, which is synced
    and renamed onto ``path``; an interrupted write never leaves a broken or partial file (nor a stray temporary).
    In a multi-process run only process 0 writes (:func:`is_main_process`); the others return at once."""
    if not is_main_process():
        return
    p = Path(path)
    try:
        _write_atomic(p, write, binary)
    except OSError as e:  # a full disk, no permission: the error names the file it was writing
        if getattr(e, "filename", None) == str(p):
            raise
        raise OSError(e.errno, e.strerror or str(e), str(p)) from e  # not the temporary file's name


def _write_atomic(p: Path, write: Callable[[Any], None], binary: bool) -> None:
    if is_special(p):  # a device or FIFO (/dev/null): write into it; renaming over it would replace the device
        with open(p, "wb" if binary else "w") as f:
            write(f)
        _written(p)
        return
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=p.name + ".", suffix=".tmp", dir=str(p.parent))
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, p)
        _written(p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json(path, payload: dict) -> None:
    """Write ``payload`` as JSON atomically (:func:`write_atomic`). Nothing is written for ``path`` None."""
    if not path:
        return

    def write(f):
        json.dump(to_jsonable(payload), f, indent=1)
        f.write("\n")

    write_atomic(path, write)


def write_npz(path, arrays: Mapping[str, Any]) -> None:
    """Write numpy arrays as an uncompressed NPZ atomically (:func:`write_atomic`), at ``path`` exactly."""
    contents: dict[str, Any] = {k: np.asarray(v) for k, v in arrays.items()}
    write_atomic(path, lambda f: np.savez(f, **contents), binary=True)


def read_json(path, what: str = "file") -> dict:
    """Read a JSON file; ValueError naming the file on a missing, unreadable or malformed file."""
    if not str(path).strip():
        raise ValueError(f"{what}: empty path")
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{what} {path}: " + ("is a folder, expected a file" if p.is_dir() else "not found"))
    try:
        with open(p, encoding="utf-8") as f:
            d = json.load(f)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{what} {path}: not readable JSON ({' '.join(str(e).split())})") from None
    if not isinstance(d, dict):
        raise ValueError(f"{what} {path}: expected a JSON object")
    return d


def summarise(per_run) -> dict:
    """metric -> {mean, std, min, max, per_run} over runs (NaN-aware for per-run arrays of any shape): the layout
    of every Monte Carlo JSON (``metrics.<name>.mean`` ...)."""
    out = {}
    for k, v in per_run.items():
        v = np.asarray(v, float)
        if v.size == 0:
            continue
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN metrics give NaN (reported as non-finite)

            def stat(f, v=v):
                return f(v, axis=0).tolist() if v.ndim > 1 else float(f(v))

            out[k] = {
                "mean": stat(np.nanmean),
                "std": stat(np.nanstd),
                "min": stat(np.nanmin),
                "max": stat(np.nanmax),
                "per_run": v.tolist(),
            }
    return out


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _git_commit() -> Optional[str]:
    """The commit of the checkout jaxatt runs from (with "+dirty" when modified), or None (an installed copy)."""
    here = Path(__file__).resolve().parent.parent
    if not (here / ".git").exists():
        return None
    try:
        rev = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (rev + ("+dirty" if dirty else "")) if rev else None


def environment() -> dict:
    """Provenance as a JSON-ready dict: date (UTC), machine, versions, JAX devices and x64, the git commit (when
    run from a checkout), the command line and XLA_FLAGS."""
    import jax
    import jaxlib

    from . import __version__

    return {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "host": socket.gethostname(),
        "platform": platform.platform(),
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "versions": {
            "jaxatt": __version__,
            "jax": jax.__version__,
            "jaxlib": jaxlib.__version__,
            "numpy": np.__version__,
        },
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "x64": bool(jax.config.values["jax_enable_x64"]),
        "git_commit": _git_commit(),
        "command_line": list(sys.argv),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def finite_or_none(x) -> Optional[float]:
    x = float(x)
    return x if math.isfinite(x) else None
