"""Data: BROAD trials and their metric (:mod:`jaxatt.data.broad`), plain IMU logs in CSV / NPZ
(:mod:`jaxatt.data.logs`)."""

from . import broad, logs  # noqa: F401
