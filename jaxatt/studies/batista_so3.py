"""Section 4 of Batista, Silvestre & Oliveira (2019, SO(3)) as a study: the same platform, sensors and trajectory as
the GES paper's Section IV (the scenario is shared with :mod:`jaxatt.studies.batista_ges`), the observer on SO(3),
its errors and the paper's published numbers (Table 2 and the Monte Carlo mean angle errors). Frames: NED."""

from __future__ import annotations

import sys
from typing import NamedTuple, Optional, Sequence

import jax.numpy as jnp
import numpy as np

from .. import so3
from ..observers import batista_so3 as so3obs
from ..sim import earth, imu
from . import batista_ges

NAME = "batista-so3"
DURATION = 3600.0  # s
DT = 0.01  # 100 Hz
WINDOW_START = 2400.0  # s, "computed for t >= 2400 s"

#: Published numbers (batista2019-so3 Section 4, Table 2, Monte Carlo of 1000 runs; single run 0.636 deg).
PAPER = {
    "slow": {
        "mean_angle_error_deg": 0.42,
        "std_m": 16.6,
        "std_v": 1738.0,
        "std_r_err": 0.004,
        "std_r_err_offdiag": 0.004,
        "single_run_mean_angle_error_deg": 0.636,
    },
    "aggressive": {"mean_angle_error_deg": 0.51},
}
UNITS = {
    "std_m": "nT",
    "std_v": "nT^2/s",
    "std_r_err": "-",
    "std_r_err_offdiag": "-",
    "std_earth_rate": "deg/h",
    "mean_angle_error_deg": "deg",
}
TABLE_ROWS = [
    ("mean_angle_error_deg", "mean angle error t>=window"),
    ("std_m", "std m~ (Table 2)"),
    ("std_v", "std v~ (Table 2)"),
    ("std_r_err", "std R~-I, 9 elements (Table 2)"),
    ("std_r_err_offdiag", "std R~-I, 6 off-diagonal"),
    ("std_earth_rate", "std omega_E~"),
    ("final_angle_error_deg", "final angle error"),
    ("max_angle_error_deg", "max angle error t>=window"),
]
PLOT_PANELS = {"norm_m": "|m~| (nT)", "norm_v": "|v~| (nT^2/s)", "norm_r_err": "|R~ - I|"}
_OFFDIAG = np.array([1, 2, 3, 5, 6, 7])


class Config(NamedTuple):
    """Every setting of the scenario and the observer (CLI flags map 1:1 onto these)."""

    trajectory: str = "slow"  # "slow" or "aggressive"
    rate_scale: float = 1.0
    latitude_deg: float = earth.LISBON_LATITUDE_DEG
    reference_nT: Sequence[float] = earth.LISBON_FIELD_NED_NT  # inertial vector, NED
    gyro_arw_deg_h_rthz: float = 4.0
    mag_noise_nT: float = 150.0
    noise_scale: float = 1.0
    gyro_bias: Sequence[float] = (0.0, 0.0, 0.0)  # rad/s
    m_init: str = "rescaled"  # "rescaled" (default), "first_sample" (literal) or "params"
    integrator: str = "lie"  # "lie" (RKMK-4 on SO(3)) or "rk4" (the paper's plain RK4)
    r_hat_0: Optional[Sequence[float]] = None  # 9 numbers row-major; default 179 deg about z
    v_hat_0: Sequence[float] = (0.0, 0.0, 0.0)
    hold: str = "zoh"
    duration: float = DURATION
    dt: float = DT
    window_start: float = WINDOW_START


def scenario(cfg: Config) -> imu.ImuScenario:
    """The platform of Section 4 (identical to batista2019-ges Section IV)."""
    return batista_ges.scenario(cfg)


def params(cfg: Config, dtype=None) -> so3obs.Params:
    r0 = None if cfg.r_hat_0 is None else np.asarray(cfg.r_hat_0, float).reshape(3, 3)
    return so3obs.default_params(
        cfg.reference_nT,
        np.asarray(earth.earth_rate_ned(cfg.latitude_deg)),
        r_hat_0=r0,
        v_hat_0=cfg.v_hat_0,
        dtype=dtype,
    )


def observer(cfg: Config):
    return so3obs.make_observer(m_init=cfg.m_init, integrator=cfg.integrator)


check_params = so3obs.check_params


def notes(cfg: Config):
    return [
        {
            "rescaled": "m^(0) = first magnetometer sample rescaled to |I_m| (Theorem 1; default)",
            "first_sample": "m^(0) = first magnetometer sample (the paper's literal reading)",
            "params": "m^(0) = params.m_hat_0",
        }[cfg.m_init],
        f"sensor samples: {'held over each RK4 step' if cfg.hold == 'zoh' else 'interpolated to RK4 stage times'}",
        f"integrator: {'RKMK-4 on SO(3) (R^ stays a rotation)' if cfg.integrator == 'lie' else 'plain RK4 (paper)'}",
        "Table 1 read as alpha1 |I_m|^2 and alpha2; alpha0 = 0.1/|I_m|^2, alpha3 = 0.02/|I_m|^2, alpha4 = 0.4/|I_v|^2",
        "metrics over t >= window_start; Table-2 stds are per-run stds averaged over elements, then over runs",
    ]


def errors(truth: imu.Truth, out: so3obs.Out):
    """Table 2's error vectors: m~ (nT), v~ (nT^2/s), R~ - I (9 elements and the 6 off-diagonal ones) with
    R~ = R R^^T, and omega_E~ (deg/h)."""
    dt = out.m_hat.dtype
    v_true = so3.cross(truth.ref_body, so3.cross(truth.ref_body, truth.earth_rate_body)).astype(dt)
    r_err = (so3.mm(truth.r.astype(dt), jnp.swapaxes(out.r, -1, -2)) - jnp.eye(3, dtype=dt)).reshape(9)
    return {
        "m": truth.ref_body.astype(dt) - out.m_hat,
        "v": v_true - out.v_hat,
        "r_err": r_err,
        "r_err_offdiag": r_err[_OFFDIAG],
        "earth_rate": jnp.rad2deg(truth.earth_rate_body.astype(dt) - out.earth_rate) * 3600.0,
    }


def config(**overrides) -> Config:
    """The Config of Section 4 with ``overrides``, validated (see :func:`jaxatt.studies.batista_ges.config`)."""
    return batista_ges.make_config(sys.modules[__name__], overrides)


def comparable(cfg) -> "str | None":
    """None when ``cfg`` is the set-up of the published numbers of its trajectory, else the settings that differ."""
    ref = Config(trajectory=cfg.trajectory, hold=cfg.hold, m_init=cfg.m_init, integrator=cfg.integrator)
    diff = [
        f"{k} = {getattr(cfg, k)!r} (paper: {getattr(ref, k)!r})"
        for k in Config._fields
        if np.any(np.asarray(getattr(cfg, k), dtype=object) != np.asarray(getattr(ref, k), dtype=object))
    ]
    return "; ".join(diff) if diff else None


STUDY = batista_ges.BatistaStudy(
    sys.modules[__name__],
    "Batista, Silvestre, Oliveira 2019 (attitude observer on SO(3) with Earth velocity estimation), Section 4",
)
