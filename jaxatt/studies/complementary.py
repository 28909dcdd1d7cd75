"""Trumpf et al. 2012 (eq. 10 / 18) on the vector-measurement scenarios of :mod:`jaxatt.sim.references`, as a
study for ``jaxatt simulate --observer complementary`` and ``jaxatt excitation``.

Scenarios (Sections III-IV of the paper): ``rotating`` and ``switching`` (one time-varying inertial reference:
persistently exciting), ``constant`` (one constant reference: the rotation about it is unobservable),
``two_constant`` (two non-collinear constant references), ``body_fixed`` (one compatible measurement of a
body-fixed reference while the body rotates about other axes). Frames: R maps body to inertial; references
are unit vectors. The figure (``--plot``) is every run's rotation-angle error (deg) against time (s): median,
25-75 % and 5-95 % bands (:meth:`jaxatt.studies.base.Study.angle_error_figure`).
"""

from __future__ import annotations

import re
from typing import NamedTuple, Sequence

import jax.numpy as jnp
import numpy as np

from .. import so3
from ..observers import complementary as comp
from ..sim import references as refs
from ..types import check_step_count, check_window_start
from . import base

NAME = "complementary"
DURATION = 120.0  # s
DT = 0.01
WINDOW_START = 80.0
PAPER: dict = {"slow": {}, "aggressive": {}}  # the paper reports no Monte Carlo numbers
UNITS = {"std_bias": "deg/s", "mean_angle_error_deg": "deg"}
TABLE_ROWS = [
    ("mean_angle_error_deg", "mean angle error t>=window"),
    ("final_angle_error_deg", "final angle error"),
    ("max_angle_error_deg", "max angle error t>=window"),
    ("final_norm_bias", "final |bias~| (deg/s)"),
    ("std_bias", "std bias~ t>=window"),
]
PLOT_PANELS = {"norm_bias": "|bias~| (deg/s)"}
SCENARIO_NAMES = tuple(refs.SCENARIOS)


class Config(NamedTuple):
    """Scenario and observer settings (CLI flags map onto these)."""

    scenario: str = "rotating"
    form: str = "matrix"  # "matrix" (eq. 10) or "quaternion" (eq. 18)
    gain: float = 0.6  # k_i = l_j (1/s) for every measurement
    k_i: float = 0.0  # gyro-bias integral gain (1/s); 0 = the paper's observer without bias
    r_hat_0_euler_deg: Sequence[float] = (150.0, 0.0, 0.0)  # initial estimate, ZYX roll, pitch, yaw (deg)
    true_r0_euler_deg: Sequence[float] = (20.0, -10.0, 30.0)
    gyro_bias_deg_s: Sequence[float] = (0.0, 0.0, 0.0)
    gyro_noise_std: float = 0.0  # rad/s per sample
    meas_noise_std: float = 0.0  # per component of the unit vectors
    noise_scale: float = 1.0
    hold: str = "zoh"
    duration: float = DURATION
    dt: float = DT
    window_start: float = WINDOW_START


def scenario(cfg: Config) -> refs.VectorScenario:
    name = cfg.scenario.replace("-", "_")
    return refs.make_scenario(
        name,
        r0_euler_deg=cfg.true_r0_euler_deg,
        gyro_bias_deg_s=cfg.gyro_bias_deg_s,
        gyro_noise_std=cfg.gyro_noise_std * cfg.noise_scale,
        meas_noise_std=cfg.meas_noise_std * cfg.noise_scale,
    )


def params(cfg: Config, dtype=None) -> comp.Params:
    scn = scenario(cfg)
    e = np.deg2rad(np.asarray(cfg.r_hat_0_euler_deg, float))
    r0 = np.asarray(so3.euler_zyx_to_matrix(e[0], e[1], e[2]))
    return comp.default_params(scn.n_body, scn.n_inertial, k=cfg.gain, l=cfg.gain, k_i=cfg.k_i, r_hat_0=r0, dtype=dtype)


def observer(cfg: Config):
    return comp.make_observer(form=cfg.form)


check_params = comp.check_params


def notes(cfg: Config):
    doc = refs.SCENARIOS[cfg.scenario.replace("-", "_")].__doc__ or ""  # None under python -OO
    paragraph = " ".join(doc.strip().split("\n\n")[0].split())
    sentence = re.split(r"\.\s+(?=[A-Z])", paragraph)[0].rstrip(".") + "." if paragraph else ""
    noise_free = float(cfg.gyro_noise_std) == 0.0 and float(cfg.meas_noise_std) == 0.0
    return [
        f"scenario {cfg.scenario}: {sentence}",
        *(
            ["noise-free (gyro and vector noise std 0): every run is the same; --gyro-noise / --vector-noise add noise"]
            if noise_free
            else []
        ),
        f"form {cfg.form} (eq. {'10' if cfg.form == 'matrix' else '18'}), gain {cfg.gain} 1/s, k_I {cfg.k_i} 1/s",
        f"sensor samples: {'held over each step' if cfg.hold == 'zoh' else 'interpolated to RK4 stage times'}",
    ]


def errors(truth: refs.VectorTruth, out: comp.Out):
    """The gyro-bias error (deg/s, body)."""
    return {"bias": jnp.rad2deg(out.bias - truth.gyro_bias.astype(out.bias.dtype))}


def config(**overrides) -> Config:
    """The Config with ``overrides``, validated (scenario, form, gains, times, window)."""
    overrides = base.check_settings(Config, overrides, NAME)
    dur = float(overrides.get("duration", DURATION))
    overrides.setdefault("window_start", 2.0 * dur / 3.0 if dur != DURATION else WINDOW_START)
    cfg = Config(**overrides)
    if cfg.scenario.replace("-", "_") not in refs.SCENARIOS:
        raise ValueError(f"scenario must be one of {', '.join(SCENARIO_NAMES)}, got {cfg.scenario!r}")
    if cfg.form not in comp.FORMS:
        raise ValueError(f"form must be one of {comp.FORMS}, got {cfg.form!r}")
    if not (cfg.dt > 0 and cfg.duration >= cfg.dt):
        raise ValueError(f"need dt > 0 and duration >= dt, got dt = {cfg.dt}, duration = {cfg.duration}")
    check_step_count(cfg.duration, cfg.dt)
    check_window_start(cfg.window_start, cfg.duration)
    return cfg


class ComplementaryStudy(base.Study):
    """Trumpf et al.'s observer on a vector-measurement scenario (no published Monte Carlo numbers)."""

    name = NAME
    paper = "Trumpf, Mahony, Hamel, Lageman 2012, Sections III-IV (scenarios of jaxatt.sim.references)"
    tuned = entry = "complementary"
    units = UNITS
    rows = TABLE_ROWS

    def config(self, **overrides):
        return config(**overrides)

    def scenario(self, cfg):
        return scenario(cfg)

    def observers(self, cfg, dtype=None):

        return {self.tuned: (observer(cfg), params(cfg, dtype=base.paper_dtype()))}

    def errors(self, truth, out):
        return errors(truth, out)

    def notes(self, cfg):
        return notes(cfg)

    def check_params(self, p):
        check_params(p)

    def format_report(self, payload):
        return base.table(self.rows, payload, self.units)

    trace = base.Study.angle_error_trace
    plot = base.Study.angle_error_figure


STUDY = ComplementaryStudy()
