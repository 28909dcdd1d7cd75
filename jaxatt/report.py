"""Provenance recorded with every result: machine, versions, date."""
from __future__ import annotations

import datetime
import os
import platform
import socket


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def environment() -> dict:
    """Machine, library versions, JAX devices and the date (UTC), as a JSON-ready dict."""
    import jax
    import jaxlib
    import numpy

    from . import __version__

    return {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "host": socket.gethostname(),
        "platform": platform.platform(),
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "versions": {"jaxatt": __version__, "jax": jax.__version__, "jaxlib": jaxlib.__version__,
                     "numpy": numpy.__version__},
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "x64": bool(jax.config.jax_enable_x64),
    }
