"""The AHRS filters made for recorded data (Madgwick, Mahony, VQF, the robust AHRS, MEKF, NLO / NLIO, ...) on a
simulated IMU, as a study for ``jaxatt simulate --observer <filter>``: the Monte Carlo of :func:`jaxatt.monte_carlo`
with the study runner's JSON, resume and interrupt handling.

The scenario is :func:`jaxatt.api.ahrs_scenario` (ENU; gyro rad/s with a constant bias and white noise per sample,
accelerometer m/s^2, magnetometer uT; the rotation rates of the NLIO paper's Section 5, true start = identity).
Each filter sets itself up from the first sample, as on a recording, with its shipped (or default) gains. The
errors are :func:`jaxatt.api.ahrs_errors`: roll, pitch, yaw (deg, ZYX) and, for a filter that estimates it, the
gyro bias (deg/s). No paper publishes Monte Carlo numbers for this set-up. The figure (``--plot``) is every run's
rotation-angle error (deg) against time (s): median, 25-75 % and 5-95 % bands
(:meth:`jaxatt.studies.base.Study.angle_error_figure`).
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

from .. import api
from ..observers import registry
from ..types import check_step_count, check_window_start
from . import base

NAME = "ahrs"
#: Said of a 6D filter's Monte Carlo (the CLI's notes, a warning of jaxatt.monte_carlo).
SIX_D_NOTE = (
    "{name} does not use the magnetometer: its heading is not observable and drifts with the gyro, so the angle "
    "errors (mean / max / final) and std_yaw include that drift; compare std_roll and std_pitch"
)
DURATION = 60.0  # s
DT = 0.01  # s
UNITS = {
    "std_roll": "deg",
    "std_pitch": "deg",
    "std_yaw": "deg",
    "std_bias": "deg/s",
    "mean_angle_error_deg": "deg",
}
TABLE_ROWS = [
    ("mean_angle_error_deg", "mean angle error t>=window"),
    ("final_angle_error_deg", "final angle error"),
    ("max_angle_error_deg", "max angle error t>=window"),
    ("std_roll", "std roll error t>=window"),
    ("std_pitch", "std pitch error t>=window"),
    ("std_yaw", "std yaw error t>=window"),
    ("std_bias", "std bias error t>=window"),
]


class Config(NamedTuple):
    """The filter and the simulated IMU (the defaults are :func:`jaxatt.api.ahrs_scenario`'s)."""

    observer: str = "robust"  # a registered observer for recorded data (jaxatt.observers.registry)
    gyro_noise_std: float = 1e-3  # rad/s per sample
    acc_noise_std: float = 0.05  # m/s^2 per sample
    mag_noise_std: float = 0.3  # uT per sample
    gyro_bias: Sequence[float] = (0.01, -0.01, 0.005)  # rad/s, body
    rate_scale: float = 1.0  # multiplies the angular-velocity profile
    noise_scale: float = 1.0  # multiplies every noise std
    duration: float = DURATION
    dt: float = DT
    window_start: float = 2.0 * DURATION / 3.0


def filters() -> tuple:
    """The registered observers this study runs: every one made for recorded data but ``complementary``, whose
    ``jaxatt simulate`` is Trumpf et al.'s study on its own scenarios."""
    from ..observers import registry

    return tuple(n for n in registry.names(recorded=True) if n != "complementary")


def config(**overrides) -> Config:
    """The Config with ``overrides``, validated (the filter's name, non-negative noise, times, window)."""
    overrides = base.check_settings(Config, overrides, NAME)
    dur = float(overrides.get("duration", DURATION))
    overrides.setdefault("window_start", 2.0 * dur / 3.0)
    cfg = Config(**overrides)
    if cfg.observer not in filters():
        raise ValueError(f"observer must be one of {', '.join(filters())}, got {cfg.observer!r}")
    for f in ("gyro_noise_std", "acc_noise_std", "mag_noise_std", "rate_scale", "noise_scale"):
        if not getattr(cfg, f) >= 0:
            raise ValueError(f"{f} must be >= 0, got {getattr(cfg, f)}")
    if not (cfg.dt > 0 and cfg.duration >= cfg.dt):
        raise ValueError(f"need dt > 0 and duration >= dt, got dt = {cfg.dt}, duration = {cfg.duration}")
    check_step_count(cfg.duration, cfg.dt)
    check_window_start(cfg.window_start, cfg.duration)
    return cfg


def scenario(cfg: Config):
    """:func:`jaxatt.api.ahrs_scenario` with the Config's noise (times ``noise_scale``), bias and rates (ENU)."""
    s = float(cfg.noise_scale)
    return api.ahrs_scenario(
        gyro_noise_std=cfg.gyro_noise_std * s,
        acc_noise_std=cfg.acc_noise_std * s,
        mag_noise_std=cfg.mag_noise_std * s,
        gyro_bias=tuple(cfg.gyro_bias),
        rate_scale=cfg.rate_scale,
    )


class AhrsStudy(base.Study):
    """A registered AHRS filter, with its shipped or default gains, on a simulated IMU (no published numbers)."""

    name = NAME
    paper = "no paper: the rotation rates of the sensors2020 NLIO paper, Section 5, on a simulated ENU IMU"
    units = UNITS
    rows = TABLE_ROWS

    def config(self, **overrides):
        return config(**overrides)

    def scenario(self, cfg):
        return scenario(cfg)

    def observers(self, cfg, dtype=None):
        from ..observers import registry

        entry = registry.get(cfg.observer)
        return {entry.name: (registry.recorded_observer(entry), entry.params(dtype=base.paper_dtype()))}

    #: :func:`jaxatt.api.ahrs_errors` itself (not a method wrapping it), so that the compiled Monte Carlo is the one
    #: :func:`jaxatt.monte_carlo` runs
    errors = staticmethod(api.ahrs_errors)

    def hold(self, cfg) -> str:
        from ..observers import registry

        return registry.hold_of(cfg.observer)

    def notes(self, cfg, gains_file=None):
        """The set-up in words; ``gains_file``: the gains file the filter runs with (``jaxatt simulate --gains``)."""
        shipped = registry.get(cfg.observer).shipped
        gains = (
            f"the gains of {gains_file}"
            if gains_file
            else (f"its shipped gains ({shipped})" if shipped else "its default gains")
        )
        return [
            f"{cfg.observer} with {gains}, set up from the first sample as on a recording; ENU, true start = identity",
            f"noise per sample: gyro {cfg.gyro_noise_std * cfg.noise_scale:g} rad/s, accelerometer "
            f"{cfg.acc_noise_std * cfg.noise_scale:g} m/s^2, magnetometer {cfg.mag_noise_std * cfg.noise_scale:g} uT; "
            f"gyro bias {tuple(cfg.gyro_bias)} rad/s; rates x{cfg.rate_scale:g}",
        ] + ([SIX_D_NOTE.format(name=cfg.observer)] if "mag" not in registry.get(cfg.observer).needs else [])

    def setup(self, observer=None, **overrides):
        raise ValueError(
            "the ahrs study is for jaxatt simulate / studies.reproduce; tune an AHRS filter on recordings with "
            "jaxatt.fit or jaxatt broad-tune"
        )

    def format_report(self, payload):
        return base.table(self.rows, payload, self.units)

    trace = base.Study.angle_error_trace
    plot = base.Study.angle_error_figure


STUDY = AhrsStudy()
