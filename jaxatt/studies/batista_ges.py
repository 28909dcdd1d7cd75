"""Section IV of Batista, Silvestre & Oliveira (2019, GES) as a study: scenario, observer, parameters, errors and
the paper's published numbers (Table 2 and the Monte Carlo mean angle errors). Frames: NED (R maps body to NED);
units: nT, rad/s, s (errors in the units of Table 2)."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, NamedTuple, Optional, Sequence, Union

import jax.numpy as jnp
import numpy as np

from .. import so3
from ..observers import batista_ges as ges
from ..sim import earth, imu, trajectories
from ..types import check_step_count, check_window_start
from . import base

if TYPE_CHECKING:
    from . import batista_so3

NAME = "batista-ges"
DURATION = 3600.0  # s
DT = 0.01  # 100 Hz
WINDOW_START = 2400.0  # s, steady-state window of Section IV

#: Published numbers (batista2019-ges Section IV, Table 2; Monte Carlo of 1000 runs).
PAPER = {
    "slow": {
        "mean_angle_error_deg": 0.38,
        "std_x1": 17.7,
        "std_x2": 0.044,
        "std_earth_rate": 0.182,
        "std_z2": 0.0069,
        "single_run_mean_angle_error_deg": 0.586,
    },
    "aggressive": {"mean_angle_error_deg": 0.47},
}
UNITS = {"std_x1": "nT", "std_x2": "nT/s", "std_earth_rate": "deg/h", "std_z2": "-", "mean_angle_error_deg": "deg"}
TABLE_ROWS = [
    ("mean_angle_error_deg", "mean angle error t>=window"),
    ("std_x1", "std x1~ (Table 2)"),
    ("std_x2", "std x2~ (Table 2)"),
    ("std_earth_rate", "std omega_E~ (Table 2)"),
    ("std_z2", "std z2~ (Table 2)"),
    ("final_angle_error_deg", "final angle error"),
    ("max_angle_error_deg", "max angle error t>=window"),
]
PLOT_PANELS = {
    "norm_x1": "|x1~| (nT)",
    "norm_x2": "|x2~| (nT/s)",
    "norm_earth_rate": "|wE~| (deg/h)",
    "norm_z2": "|z2~|",
}


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
    x1_init: str = "first_sample"  # or "zero" (the paper's literal x1^(0) = 0)
    r_hat_0: Optional[Sequence[float]] = None  # 9 numbers row-major; default diag(-1, -1, 1)
    x2_0: Sequence[float] = (0.0, 0.0, 0.0)
    epsilon: float = 0.5
    hold: str = "zoh"
    duration: float = DURATION
    dt: float = DT
    window_start: float = WINDOW_START


def scenario(cfg: Union[Config, batista_so3.Config]) -> imu.ImuScenario:
    """Section IV: R(0) = I, NED at the given latitude, IGRF-11 field, KVH DSP-3000 gyro, 150 nT magnetometer."""
    if cfg.trajectory not in ("slow", "aggressive"):
        raise ValueError(f"trajectory must be 'slow' or 'aggressive', got {cfg.trajectory!r}")
    rates = (trajectories.batista_slow if cfg.trajectory == "slow" else trajectories.batista_aggressive)(cfg.rate_scale)
    return imu.ImuScenario(
        rates=rates,
        r0=jnp.eye(3),
        earth_rate_nav=earth.earth_rate_ned(cfg.latitude_deg),
        ref_nav=jnp.asarray(cfg.reference_nT, float),
        gyro_arw=jnp.asarray(imu.arw_deg_per_hour_to_rad(cfg.gyro_arw_deg_h_rthz)),
        gyro_bias=jnp.asarray(cfg.gyro_bias, float),
        vec_noise_std=jnp.asarray(cfg.mag_noise_nT, float),
        noise_scale=jnp.asarray(cfg.noise_scale, float),
    )


def params(cfg: Config, dtype=None) -> ges.Params:
    r0 = None if cfg.r_hat_0 is None else np.asarray(cfg.r_hat_0, float).reshape(3, 3)
    p = ges.default_params(
        cfg.reference_nT,
        np.asarray(earth.earth_rate_ned(cfg.latitude_deg)),
        r_hat_0=r0,
        epsilon=cfg.epsilon,
        dtype=dtype,
    )
    return p._replace(x2_0=jnp.asarray(cfg.x2_0, p.x2_0.dtype))


def observer(cfg: Config):
    if cfg.x1_init not in ("first_sample", "zero"):
        raise ValueError(f"x1_init must be 'first_sample' or 'zero', got {cfg.x1_init!r}")
    return ges.make_observer(x1_init="first_sample" if cfg.x1_init == "first_sample" else "params")


check_params = ges.check_params


def notes(cfg: Config):
    return [
        "x1^(0) = first magnetometer sample (reproduces the paper; --x1-init zero is the literal reading)"
        if cfg.x1_init == "first_sample"
        else "x1^(0) = 0 (literal reading of Section IV)",
        f"sensor samples: {'held over each RK4 step' if cfg.hold == 'zoh' else 'interpolated to RK4 stage times'}",
        "Q = 1e5 C2 QD C2^T read literally (QD in the z-space)",
        "metrics over t >= window_start; Table-2 stds are per-run stds averaged over elements, then over runs",
    ]


def errors(truth: imu.Truth, out: ges.Out):
    """Table 2's error vectors: x1~ (nT), x2~ (nT/s), omega_E~ (deg/h), z2~ (9 elements of R - R^)."""
    x2_true = so3.cross(truth.ref_body, truth.earth_rate_body)
    dt = out.x1.dtype
    return {
        "x1": truth.ref_body.astype(dt) - out.x1,
        "x2": x2_true.astype(dt) - out.x2,
        "earth_rate": jnp.rad2deg(truth.earth_rate_body.astype(dt) - out.earth_rate) * 3600.0,
        "z2": (truth.r.astype(dt) - out.r_hat).reshape(9),
    }


def config(**overrides) -> Config:
    """The Config of Section IV with ``overrides`` (field names of :class:`Config`), validated: the steady-state
    window defaults to t >= min(2400 s, 2/3 of the duration) and must start inside the run."""
    return make_config(sys.modules[__name__], overrides)


def make_config(mod, overrides: dict):
    """``mod.Config`` (this module's or batista_so3's) with ``overrides``, checked by :func:`check_config`."""
    overrides = base.check_settings(mod.Config, overrides, mod.NAME, shapes={"r_hat_0": ((9,), (3, 3))})
    dur = float(overrides.get("duration", mod.DURATION))
    overrides.setdefault("window_start", min(mod.WINDOW_START, 2.0 * dur / 3.0))
    cfg = mod.Config(**overrides)
    check_config(cfg)
    return cfg


def check_config(cfg) -> None:
    """ValueError naming the first setting that cannot run (trajectory, times, window, noise, latitude)."""
    if cfg.trajectory not in ("slow", "aggressive"):
        raise ValueError(f"trajectory must be 'slow' or 'aggressive', got {cfg.trajectory!r}")
    for name in ("duration", "dt"):
        v = float(getattr(cfg, name))
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive number of seconds, got {v}")
    if cfg.duration < cfg.dt:
        raise ValueError(f"duration ({cfg.duration} s) must be at least one step dt = {cfg.dt} s")
    check_step_count(cfg.duration, cfg.dt)
    check_window_start(cfg.window_start, cfg.duration)
    if not -90.0 <= cfg.latitude_deg <= 90.0:
        raise ValueError(f"latitude must be in [-90, 90] degrees, got {cfg.latitude_deg}")
    for name in ("gyro_arw_deg_h_rthz", "mag_noise_nT", "noise_scale", "rate_scale"):
        v = float(getattr(cfg, name))
        if not np.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a finite number >= 0, got {v}")
    if cfg.hold not in ("zoh", "linear"):
        raise ValueError(f"hold must be 'zoh' or 'linear', got {cfg.hold!r}")
    ref = np.asarray(cfg.reference_nT, float)
    if ref.shape != (3,) or not np.all(np.isfinite(ref)):
        raise ValueError(f"reference must be 3 finite numbers (nT, NED), got {cfg.reference_nT!r}")
    lo, hi = ges.VECTOR_MAGNITUDE
    if not lo <= np.max(np.abs(ref)) <= hi:
        raise ValueError(
            f"reference must be a non-zero vector whose largest component is {lo:g} to {hi:g} nT in size (the gains "
            "use its powers), "
            f"got {ref.tolist()}"
        )
    if np.linalg.norm(ref) < WEAK_FIELD_NT:
        import warnings

        warnings.warn(
            f"reference: |I_m| = {np.linalg.norm(ref):.4g} nT: the paper's attitude gain (Section IV's Q, written for "
            f"Lisbon's {np.linalg.norm(earth.LISBON_FIELD_NED_NT):.3g} nT) scales with the field, and below about "
            f"{WEAK_FIELD_NT:.0e} nT the attitude does not converge within the paper's 3600 s (measured, noise-free: "
            "2.2e4 nT converges, 1.1e4 nT does not); give the field in nT, or tune the gains for it (jaxatt tune)",
            stacklevel=3,
        )


#: |I_m| (nT) below which the paper's attitude gain does not converge within 3600 s (noise-free, measured between
#: 2.2e4 nT, which converges, and 1.1e4 nT, which does not): warned about
WEAK_FIELD_NT = 2e4


def comparable(cfg) -> "str | None":
    """None when ``cfg`` is the set-up of the published numbers of its trajectory, else the settings that differ."""
    ref = Config(trajectory=cfg.trajectory, hold=cfg.hold, x1_init=cfg.x1_init)
    diff = [
        f"{k} = {getattr(cfg, k)!r} (paper: {getattr(ref, k)!r})"
        for k in Config._fields
        if np.any(np.asarray(getattr(cfg, k), dtype=object) != np.asarray(getattr(ref, k), dtype=object))
    ]
    return "; ".join(diff) if diff else None


#: The rate gain whose product with dt RK4 must keep below :data:`RK4_REAL_LIMIT` in this study ("alpha1": x1~'s
#: decay rate in eq. (15); the SO3 study's alpha1 multiplies |I_m|^2 and is not checked).
RK4_RATE_GAIN = "alpha1"
#: RK4's stability limit on the negative real axis (h lambda > -2.785), rounded down.
RK4_REAL_LIMIT = 2.78


class BatistaStudy(base.Study):
    """Section IV / 4 of either Batista et al. (2019) paper; ``mod`` is the study module (this one or
    :mod:`jaxatt.studies.batista_so3`), whose functions define the set-up."""

    def __init__(self, mod, paper: str):
        self.mod = mod
        self.name = mod.NAME
        self.paper = paper
        self.tuned = self.entry = mod.NAME
        self.units = mod.UNITS
        self.rows = mod.TABLE_ROWS

    def config(self, **overrides):
        return self.mod.config(**overrides)

    def scenario(self, cfg):
        return self.mod.scenario(cfg)

    def observers(self, cfg, dtype=None):

        return {self.tuned: (self.mod.observer(cfg), self.mod.params(cfg, dtype=base.paper_dtype()))}

    def errors(self, truth, out):
        return self.mod.errors(truth, out)

    def published(self, cfg):
        return dict(self.mod.PAPER.get(cfg.trajectory, {}))

    def comparable(self, cfg):
        return self.mod.comparable(cfg)

    def notes(self, cfg):
        return self.mod.notes(cfg)

    def check_params(self, p):
        self.mod.check_params(p)

    def check_step(self, cfg, p):
        """RK4 on the Earth-rate block's x1~' = -alpha1 x1~ is stable for alpha1 dt < 2.78 (its real-axis limit,
        2.785): a longer step diverges (dt = 0.03 s with Table 1's alpha1 = 100 1/s went non-finite at 18.6 s)."""
        a1 = getattr(p, "alpha1", None)
        if a1 is None or getattr(self.mod, "RK4_RATE_GAIN", None) != "alpha1":
            return
        a_max = float(np.max(np.asarray(a1, float)))
        if a_max * cfg.dt >= RK4_REAL_LIMIT:
            raise ValueError(
                f"dt = {cfg.dt:g} s is too long for alpha1 = {a_max:g} 1/s: RK4 is stable for alpha1 dt < "
                f"{RK4_REAL_LIMIT} (here {a_max * cfg.dt:.3g}); use dt < {RK4_REAL_LIMIT / a_max:.4g} s"
            )

    def plot(self, cfg, payload, results, path, dtype=None):
        """The paper's convergence figure (run 0, every 0.1 s)."""
        from .. import montecarlo, plot

        obs, p = self.observers(cfg)[self.tuned]
        _, trace, _ = montecarlo.simulate(
            self.scenario(cfg),
            obs,
            p,
            duration=cfg.duration,
            dt=cfg.dt,
            seed=payload["config"]["seed"],
            errors_fn=self.errors,
            window_start=cfg.window_start,
            hold=cfg.hold,
            trace_every=10 if cfg.duration >= 10 * cfg.dt else 1,  # every 0.1 s; every step of a shorter run
            dtype=dtype,
        )
        plot.convergence_figure(
            trace,
            path,
            title=f"{payload['experiment']} (run 0)",
            panels=self.mod.PLOT_PANELS,
            steady_from_s=cfg.window_start,
        )


STUDY = BatistaStudy(
    sys.modules[__name__],
    "Batista, Silvestre, Oliveira 2019 (GES attitude observer with Earth velocity estimation), Section IV",
)
