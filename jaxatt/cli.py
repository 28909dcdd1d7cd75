"""Command line: ``jaxatt filter``, ``reproduce``, ``simulate``, ``tune``, ``evaluate``, ``broad``, ``broad-tune``,
``excitation``. Thin: it parses, calls the library (:mod:`jaxatt.api`, :mod:`jaxatt.studies`, :mod:`jaxatt.fitting`),
prints and writes files.

Every command enables float64 in JAX (the library never does): simulated truth and sensors are float64, observers
run in float64 unless ``--float32``. Bad input is one line on stderr naming the flag or file and exit status 2
(``--debug`` shows the traceback); a non-finite result exits 1; Ctrl-C exits 130 keeping what was finished.

Several processes (``jax.distributed``; hosts or processes of one machine): start the same command in every process
with ``JAXATT_COORDINATOR=host:port`` (process 0's address), ``JAXATT_NUM_PROCESSES=n`` and ``JAXATT_PROCESS_ID=k``
(:func:`jaxatt.sharding.initialize_distributed`); the runs split over every process's devices, process 0 prints the
results and writes the files (the others print only errors and progress on stderr). See docs/gpu.md.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import threading
import warnings
from pathlib import Path
from typing import List, Mapping, Optional

import numpy as np

from .frames import ACC_UNITS, FRAMES, GYR_UNITS, TIME_UNITS, unit_spelling
from .types import MAX_RUNS, check_seed

__all__ = ["main"]

#: The registered filters for recorded data that ``simulate`` runs on a simulated IMU (:mod:`jaxatt.studies.ahrs`;
#: kept here as names so that ``--help`` imports no JAX; tests check it against the registry).
AHRS_FILTERS = ("madgwick", "mahony", "mekf", "nlo", "nlio-fg", "nlio", "robust", "vqf", "vqf-6d")
SIMULATE_OBSERVERS = ("batista-ges", "batista-so3", "complementary") + AHRS_FILTERS
PAPER_STUDIES = ("batista-ges", "batista-so3", "nlio-case1", "nlio-case2", "nlio-case3", "nlio-case4", "nlio-simb")
TUNABLE_STUDIES = ("batista-ges", "batista-so3", "complementary", "nlio-case1", "nlio-case2", "nlio-case3")
SCENARIOS = ("rotating", "switching", "constant", "two-constant", "body-fixed")


#: Most optimiser steps one ``tune`` / ``broad-tune`` may ask for (a typo's 10**24 would run forever).
MAX_FIT_STEPS = 10**6
#: The gains file `jaxatt tune` and `jaxatt broad-tune` write when --out is not given.
DEFAULT_GAINS_OUT = "gains.json"


class UserError(Exception):
    """A bad input caught by the CLI (one line, exit 2)."""


# ------------------------------------------------------------------------------------------------------------
# Argument types
# ------------------------------------------------------------------------------------------------------------
def _floats(n: int):
    def parse(s: str):
        try:
            v = [float(x) for x in s.replace(" ", "").split(",")]  # '1,2,3,' has an empty 4th: refused
        except ValueError as e:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {s!r}") from e
        if len(v) != n:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {len(v)}: {s!r}")
        if not all(np.isfinite(v)):
            raise argparse.ArgumentTypeError(f"numbers must be finite, got {s!r}")
        return tuple(v)

    return parse


def _number(s: str, *, low: float, strict: bool, what: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {s!r}") from None
    if not np.isfinite(v) or (v <= low if strict else v < low):
        raise argparse.ArgumentTypeError(f"must be a {what} number, got {s}")
    return v


def _simulated_observer(s: str) -> str:
    """simulate's --observer: a registered name (argparse checks the choices); module:attr is said to be Python's."""
    if ":" in s:
        raise argparse.ArgumentTypeError(
            f"{s}: jaxatt simulate runs the registered observers; your own observer runs on the same simulated IMU "
            "from Python: jaxatt.monte_carlo(observer, params, runs=..., duration=...)"
        )
    return s


def _positive(s: str) -> float:
    return _number(s, low=0.0, strict=True, what="positive")


def _nonneg(s: str) -> float:
    return _number(s, low=0.0, strict=False, what="non-negative")


def _integer(s: str) -> int:
    try:
        return int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {s!r}") from None


def _count(minimum: int, maximum: Optional[int] = None):
    def parse(s: str) -> int:
        v = _integer(s)
        if v < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {s}")
        if maximum is not None and v > maximum:
            raise argparse.ArgumentTypeError(f"must be <= {maximum}, got {s}")
        return v

    return parse


def _seed(s: str) -> int:
    """A PRNG seed: an integer that fits in 64 bits (what ``jax.random.PRNGKey`` takes)."""
    try:
        return check_seed(_integer(s))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must fit in 64 bits (|seed| < 2^63), got {s}") from None


def _latitude(s: str) -> float:
    v = _number(s, low=-np.inf, strict=False, what="finite")
    if not -90.0 <= v <= 90.0:
        raise argparse.ArgumentTypeError(f"must be in [-90, 90] degrees, got {s}")
    return v


# ------------------------------------------------------------------------------------------------------------
# The parser
# ------------------------------------------------------------------------------------------------------------
def _mc_flags(p: argparse.ArgumentParser, *, study_flags: bool = True):
    p.add_argument("--runs", type=_count(1, MAX_RUNS), default=100, help="Monte Carlo runs (default 100)")
    p.add_argument("--duration", type=_positive, default=None, help="simulated time per run, s (default: the paper's)")
    p.add_argument("--seed", type=_seed, default=0, help="base seed; run k uses fold_in(PRNGKey(seed), k)")
    p.add_argument(
        "--hold",
        choices=["zoh", "linear"],
        default=None,
        help="sensor samples held over the RK4 step (zoh) or interpolated to the stage times (linear); "
        "default: the study's",
    )
    if study_flags:
        p.add_argument(
            "--x1-init",
            choices=["first-sample", "zero"],
            default=None,
            help="batista-ges: x1^(0) = first magnetometer sample (default; reproduces the paper) or zero",
        )
        p.add_argument(
            "--m-init",
            choices=["rescaled", "first-sample"],
            default=None,
            help="batista-so3: m^(0) = first sample rescaled to |I_m| (default; Theorem 1) or the raw sample",
        )
        p.add_argument(
            "--integrator",
            choices=["lie", "rk4"],
            default=None,
            help="batista-so3: RKMK-4 on SO(3) (default) or plain RK4 on the 15 numbers (the paper's)",
        )
    prec = p.add_mutually_exclusive_group()
    prec.add_argument("--float32", action="store_true", help="run the observer in float32")
    prec.add_argument("--float64", action="store_true", help="run the observer in float64 (default)")
    p.add_argument("--chunk", type=_count(1), default=250, help="runs vmapped together (memory vs speed)")
    p.add_argument("--json", default=None, help="write results JSON here (updated after every chunk)")
    p.add_argument("--plot", default=None, help="write a PNG of the study's figure here")
    _run_flags(p)


def _run_flags(p: argparse.ArgumentParser):
    """--resume / --quiet / --progress of the Monte Carlo commands."""
    p.add_argument(
        "--resume",
        action="store_true",
        help="run only the runs not yet saved beside --json (<json>.runs.npz) by an interrupted run of the same flags",
    )
    _output_flags(p)


def _trial_source_flags(p: argparse.ArgumentParser):
    """--data-dir (BROAD) or --logs (your own recordings with ground truth) and how to read the logs."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data-dir", help="folder of BROAD .hdf5 trials (needs jaxatt[data])")
    src.add_argument(
        "--logs",
        nargs="+",
        help="your own CSV / NPZ logs with ground truth (quat_w ... quat_z), one trial each "
        "(jaxatt.data.logs.load_trial; group 'own')",
    )
    p.add_argument(
        "--truth-frame",
        choices=FRAMES,
        type=str.upper,
        default=None,
        help="--logs: the navigation frame of every log's ground truth (default ENU; north = magnetic north)",
    )
    p.add_argument("--columns", default=None, help="--logs: the CSV logs' own column names, e.g. t=time,gyr_x=GyroX")
    p.add_argument(
        "--gyr-unit",
        choices=GYR_UNITS,
        type=unit_spelling,
        default=None,
        help="--logs: unit of the gyro columns (rad/s)",
    )
    p.add_argument(
        "--acc-unit",
        choices=ACC_UNITS,
        type=unit_spelling,
        default=None,
        help="--logs: unit of the accelerometer (m/s^2)",
    )
    p.add_argument(
        "--time-unit", choices=TIME_UNITS, type=unit_spelling, default=None, help="--logs: unit of the t column (s)"
    )
    p.add_argument("--dt", type=_positive, default=None, help="--logs: the sample period (s) of logs without t")


#: the flags of :func:`_trial_source_flags` that only --logs takes
_LOG_READING_FLAGS = ("--truth-frame", "--columns", "--gyr-unit", "--acc-unit", "--time-unit", "--dt")


def _trials_of(args):
    """The trials of ``--data-dir`` (with ``--trials``) or of ``--logs``."""
    given = [f for f in _LOG_READING_FLAGS if getattr(args, f[2:].replace("-", "_")) is not None]
    if args.data_dir is not None:
        if given:
            raise UserError(f"{', '.join(given)}: for --logs (BROAD trials of --data-dir are read as they are)")
        from .data import broad

        return broad.load(args.data_dir, args.trials)
    if args.trials is not None:
        raise UserError("--trials picks trials of --data-dir; with --logs, list the logs to use")
    from .data import logs

    units = {k: getattr(args, k) or v for k, v in _SI_UNITS.items()}
    frame = args.truth_frame or "ENU"
    return [
        logs.load_trial(p, frame=frame, name=n, columns=args.columns, dt=args.dt, **units)
        for p, n in zip(args.logs, _log_names(args.logs))
    ]


def _log_names(paths) -> list:
    """A trial name per log: its stem; where stems repeat, the path without its suffix (logs of other folders);
    where those repeat too, the path as given (walk.csv and walk.npz)."""
    stems = [Path(p).stem for p in paths]
    names = [str(Path(p).with_suffix("")) if stems.count(st) > 1 else st for p, st in zip(paths, stems)]
    return [str(p) if names.count(n) > 1 else n for p, n in zip(paths, names)]


def _trial_inputs(args) -> dict:
    """{flag: path} of what ``--data-dir`` / ``--logs`` read (for the output-path checks)."""
    if args.data_dir is not None:
        return {"--data-dir": args.data_dir}
    return {f"--logs ({p})": p for p in args.logs}


def _gains_out_flags(p: argparse.ArgumentParser) -> None:
    """--out, and --resume / --overwrite (one or the other: continue the fit in --out, or replace it)."""
    p.add_argument("--out", default=None, help=f"the gains file, rewritten after every step ({DEFAULT_GAINS_OUT})")
    existing = p.add_mutually_exclusive_group()
    existing.add_argument("--resume", action="store_true", help="continue the fit saved in --out")
    existing.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def _output_flags(p: argparse.ArgumentParser):
    """--quiet / --progress: progress lines on stderr (default: only when stderr is a terminal)."""
    out = p.add_mutually_exclusive_group()
    out.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    out.add_argument("--progress", action="store_true", help="progress lines even when stderr is not a terminal")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block): ``jaxatt tune: error: argument --steps: ... (see --help)``."""

    #: command -> its parser (the top-level parser's; main reports an unknown flag through the command's)
    subparsers: Mapping[str, argparse.ArgumentParser] = {}

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _parser() -> _Parser:
    ap = _Parser(prog="jaxatt", description="Batched, differentiable attitude observers in JAX.")
    ap.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = ap.add_subparsers(dest="command", required=True)
    ap.subparsers = sub.choices

    fp = sub.add_parser("filter", help="run an observer on your own log (CSV / NPZ / BROAD HDF5) and write estimates")
    fp.add_argument("--log", required=True, help="CSV or NPZ log (jaxatt.data.logs) or a BROAD .hdf5 trial")
    fp.add_argument(
        "--columns",
        default=None,
        help="the CSV log's own column names, e.g. t=time,gyr_x=GyroX,gyr_y=GyroY,gyr_z=GyroZ (the format's names: "
        "t, gyr_*, acc_*, mag_*, quat_*; units are set by the unit flags; quote it if a name has spaces)",
    )
    fp.add_argument(
        "--observer",
        default="robust",
        help="a registered observer (robust, mahony, mekf, nlio, ...) or module:attr of your own "
        "Observer / registry Entry (default robust)",
    )
    fp.add_argument("--params", default=None, help="module:attr of the params of your own observer")
    fp.add_argument(
        "--gains",
        default=None,
        help="gains file (jaxatt tune / broad-tune / fit) to use; with your own observer, put into --params",
    )
    fp.add_argument(
        "--frame",
        choices=FRAMES,
        type=str.upper,
        default="ENU",
        help="navigation frame of the written quaternions and rotation matrices (default ENU; north is magnetic "
        "north, no declination applied): a registered observer's estimate is converted to it; your own "
        "observer's (module:attr) is written as it is and only labelled with it",
    )
    fp.add_argument(
        "--dt",
        type=_positive,
        default=None,
        help="sample period, s (default: the log's timestamps; a log without t needs it)",
    )
    fp.add_argument(
        "--gyr-unit",
        choices=GYR_UNITS,
        type=unit_spelling,
        default="rad/s",
        help="unit of the log's gyro columns (default rad/s)",
    )
    fp.add_argument(
        "--acc-unit",
        choices=ACC_UNITS,
        type=unit_spelling,
        default="m/s^2",
        help="unit of the log's accelerometer columns (default m/s^2)",
    )
    fp.add_argument(
        "--time-unit",
        choices=TIME_UNITS,
        type=unit_spelling,
        default="s",
        help="unit of the log's t column (default s); the estimates' t is written in s",
    )
    fp.add_argument("--float32", action="store_true", help="run the filter in float32")
    fp.add_argument(
        "--offline",
        action="store_true",
        help="forward-backward smoothing over the whole log (jaxatt.smoothing): q is the fused estimate, the "
        "columns backward_* and weight_* are added",
    )
    fp.add_argument(
        "--out",
        required=True,
        help="CSV (.csv, .txt) of t, qw, qx, qy, qz and the observer's flags, or the same columns as arrays in "
        "an NPZ (.npz)",
    )
    _output_flags(fp)

    rp = sub.add_parser("reproduce", help="run a paper's simulation study and compare with its published numbers")
    rp.add_argument("experiment", choices=PAPER_STUDIES)
    rp.add_argument("--aggressive", action="store_true", help="batista-*: the 20x faster angular velocity")
    _mc_flags(rp)

    sp = sub.add_parser("simulate", help="run an observer on a scenario you define with flags")
    sp.add_argument(
        "--observer",
        type=_simulated_observer,
        choices=SIMULATE_OBSERVERS,
        required=True,
        help="a paper's observer on its scenario, or an AHRS filter (madgwick, mahony, vqf, robust, ...) with its "
        "shipped or default gains on a simulated IMU (ENU; jaxatt.monte_carlo in Python, for your own observer too)",
    )
    g = sp.add_argument_group("batista-ges / batista-so3 (Section IV / 4 platform)")
    g.add_argument("--trajectory", choices=["slow", "aggressive"], default=None)
    g.add_argument(
        "--rate-scale", type=_nonneg, default=None, help="multiplies the angular-velocity profile (AHRS filters too)"
    )
    g.add_argument("--latitude", type=_latitude, default=None, help="latitude in degrees (north positive)")
    g.add_argument(
        "--reference",
        type=_floats(3),
        default=None,
        help="inertial vector measured by the vector sensor, X,Y,Z in nT, NED (default IGRF-11 Lisbon)",
    )
    g.add_argument("--gyro-arw", type=_nonneg, default=None, help="gyro angle random walk, deg/h/sqrt(Hz) (default 4)")
    g.add_argument(
        "--mag-noise",
        type=_nonneg,
        default=None,
        help="vector-sensor (magnetometer) noise std, nT (default 150; AHRS filters 300)",
    )
    g.add_argument("--r0", type=_floats(9), default=None, help="initial R^ (9 numbers, row-major)")
    g.add_argument("--x2-0", type=_floats(3), default=None, help="batista-ges: initial x2^, nT/s")
    g.add_argument("--v0", type=_floats(3), default=None, help="batista-so3: initial v^, nT^2 rad/s")
    g.add_argument(
        "--epsilon",
        type=_positive,
        default=None,
        help="batista-ges: Theorem-3 threshold on ||R^T R - I||_F, in (0, 1) (default 0.5)",
    )
    c = sp.add_argument_group("complementary (Trumpf et al. 2012) observer")
    c.add_argument("--scenario", choices=SCENARIOS, default=None, help="vector-measurement scenario (default rotating)")
    c.add_argument("--form", choices=["matrix", "quaternion"], default=None, help="eq. (10) or eq. (18)")
    c.add_argument("--gain", type=_positive, default=None, help="gain k_i = l_j of every measurement, 1/s (0.6)")
    c.add_argument("--k-i", type=_nonneg, default=None, help="gyro-bias integral gain, 1/s (0 = no bias estimate)")
    c.add_argument(
        "--gyro-noise",
        type=_nonneg,
        default=None,
        help="gyro white noise per sample, rad/s (complementary: default 0, noise-free; AHRS filters: default 0.001)",
    )
    c.add_argument(
        "--vector-noise", type=_nonneg, default=None, help="noise per component of the unit vectors (default 0)"
    )
    a = sp.add_argument_group(
        "AHRS filters (madgwick, mahony, mekf, nlo, nlio, nlio-fg, robust, vqf, vqf-6d)",
        "a simulated IMU in ENU (jaxatt.api.ahrs_scenario): also --gyro-noise, --mag-noise (nT), --rate-scale and "
        "the flags below; each filter starts from the first sample, as on a recording",
    )
    a.add_argument(
        "--acc-noise", type=_nonneg, default=None, help="accelerometer noise per sample, m/s^2 (default 0.05)"
    )
    a.add_argument(
        "--gains",
        default=None,
        help="a gains file of the filter (jaxatt broad-tune, jaxatt.fit) instead of its shipped gains",
    )
    s = sp.add_argument_group("all")
    s.add_argument(
        "--gyro-bias", type=_floats(3), default=None, help="gyro bias X,Y,Z, rad/s (AHRS filters: 0.01,-0.01,0.005)"
    )
    s.add_argument("--noise-scale", type=_nonneg, default=None, help="multiplies all noise (0 = noise-free)")
    s.add_argument("--dt", type=_positive, default=None, help="sample period, s")
    s.add_argument("--window-start", type=_nonneg, default=None, help="start of the steady-state window, s")
    s.add_argument(
        "--r0-euler",
        type=_floats(3),
        default=None,
        help="initial R^ as ZYX roll,pitch,yaw in degrees (not the AHRS filters: they start from the first sample)",
    )
    _mc_flags(sp)

    tp = sub.add_parser("tune", help="tune a study's gains by gradient descent through the Monte Carlo scan")
    tp.add_argument("--experiment", required=True, choices=TUNABLE_STUDIES)
    tp.add_argument("--steps", type=_count(0, MAX_FIT_STEPS), default=100, help="optimiser steps")
    # default None: given or not is told apart (--objective varfree draws no runs and refuses them)
    tp.add_argument("--train-runs", type=_count(1, MAX_RUNS), default=None, help="training seeds (default 32)")
    tp.add_argument(
        "--val-runs", type=_count(0, MAX_RUNS), default=None, help="validation seeds (early stopping; default 16)"
    )
    tp.add_argument("--duration", type=_positive, default=None, help="simulated time per run, s")
    tp.add_argument("--seed", type=_seed, default=0)
    tp.add_argument("--lr", type=_positive, default=None, help="step size (default 0.05 for adam, 1 for lbfgs)")
    tp.add_argument(
        "--refine-schedule",
        type=_positive,
        nargs="+",
        default=(),
        metavar="T",
        help="extra switch times (s) for the study's gain schedules, tuned from the paper's values",
    )
    tp.add_argument(
        "--objective",
        choices=("montecarlo", "varfree"),
        default="montecarlo",
        help="montecarlo: the loss over minibatches of simulated runs; varfree: its expectation over the noise by "
        "covariance propagation along the noise-free run (no runs, no sampling noise)",
    )
    tp.add_argument(
        "--optimizer",
        choices=("adam", "lbfgs"),
        default="adam",
        help="adam; or lbfgs (quasi-Newton with a line search, --lr caps its step): needs --objective varfree",
    )
    _gains_out_flags(tp)
    _output_flags(tp)

    vp = sub.add_parser("evaluate", help="Monte Carlo of a study with a gains file (same JSON as reproduce)")
    vp.add_argument("--experiment", required=True, choices=TUNABLE_STUDIES)
    vp.add_argument("--gains", default=None, help="gains file (default: the paper's gains)")
    vp.add_argument("--runs", type=_count(1, MAX_RUNS), default=100)
    vp.add_argument("--seed", type=_seed, default=1)
    vp.add_argument("--duration", type=_positive, default=None)
    vp.add_argument("--json", default=None)
    _run_flags(vp)

    bp = sub.add_parser("broad", help="run an observer on BROAD trials (or your own logs) and print the BROAD metric")
    _trial_source_flags(bp)
    bp.add_argument(
        "--observer",
        default="robust",
        help="a registered observer (default robust), or module:attr of your own Observer (sensor-to-ENU)",
    )
    bp.add_argument("--gains", default=None, help="gains file (default: the observer's shipped or default gains)")
    bp.add_argument("--params", default=None, help="module:attr of the params of your own observer")
    bp.add_argument("--trials", nargs="*", default=None, help="trial names, numbers, groups or fold1/fold2")
    bp.add_argument("--json", default=None, help="write the metric per trial and group here (deg)")
    bp.add_argument("--float32", action="store_true", help="run the filter in float32 (default float64)")
    bp.add_argument("--offline", action="store_true", help="score the forward-backward smoothed estimate")
    _output_flags(bp)

    bt = sub.add_parser("broad-tune", help="learn an observer's gains on BROAD trials (or your own logs)")
    _trial_source_flags(bt)
    bt.add_argument(
        "--observer",
        default="robust",
        help="a registered observer to tune (default robust), or module:attr of your own Observer (with --params)",
    )
    bt.add_argument("--params", default=None, help="module:attr of the start params of your own observer")
    bt.add_argument("--trials", nargs="*", default=None, help="training trials (default: all)")
    bt.add_argument("--steps", type=_count(0, MAX_FIT_STEPS), default=150, help="Adam steps (default 150)")
    bt.add_argument("--lr", type=_positive, default=0.05, help="Adam learning rate on log-gains")
    bt.add_argument(
        "--init-gains",
        default=None,
        help="start from this gains file (default: the observer's shipped gains, or its defaults if none are shipped)",
    )
    bt.add_argument("--float64", action="store_true", help="tune in float64 (default float32: faster)")
    _gains_out_flags(bt)
    _output_flags(bt)

    ep = sub.add_parser(
        "excitation",
        help="excitation / observability measures (Trumpf et al. Defs 3.3, 4.1, "
        "Lemmas 3.4, 4.2, conditions 6, 13) of a scenario or a log",
    )
    src = ep.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", choices=SCENARIOS)
    src.add_argument("--log", help="CSV or NPZ log (jaxatt.data.logs): acc and mag vs constant references")
    ep.add_argument(
        "--columns",
        default=None,
        help="the CSV log's own column names, e.g. t=time,acc_x=AccX,... (the format's names: t, gyr_*, acc_*, mag_*)",
    )
    ep.add_argument(
        "--time-unit",
        choices=TIME_UNITS,
        type=unit_spelling,
        default=None,
        help="unit of the log's t column (default s)",
    )
    ep.add_argument("--duration", type=_positive, default=None, help="simulated duration of a scenario, s (60)")
    ep.add_argument("--dt", type=_positive, default=None, help="sample period of a scenario, s (0.01)")
    ep.add_argument("--window", type=_positive, default=5.0, help="sliding window length T, s (default 5)")
    ep.add_argument(
        "--mag-ref",
        type=_floats(3),
        default=None,
        help="log: magnetic reference in the log's navigation frame (any unit; only its direction is used)",
    )
    ep.add_argument(
        "--frame", choices=FRAMES, type=str.upper, default=None, help="log: navigation frame of --mag-ref (NED)"
    )
    ep.add_argument(
        "--threshold",
        type=_nonneg,
        default=0.05,
        help="a window is reported as not exciting when lambda2 / T falls below this (default 0.05)",
    )
    ep.add_argument("--json", default=None, help="write the measures per window here")
    ep.add_argument("--plot", default=None, help="write a PNG of the measures over time here")
    _output_flags(ep)
    for command in sub.choices.values():  # --debug after the command too (it keeps the top level's default)
        command.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    return ap


# ------------------------------------------------------------------------------------------------------------
# reproduce / simulate
# ------------------------------------------------------------------------------------------------------------
def _dtype(args):
    import jax.numpy as jnp

    return jnp.float32 if getattr(args, "float32", False) else jnp.float64


def _given(args, mapping) -> dict:
    """{config field: value} of the flags the user gave (None = not given)."""
    return {field: getattr(args, attr) for attr, field in mapping.items() if getattr(args, attr, None) is not None}


_BATISTA_FLAGS = {
    "x1_init": "x1_init",
    "m_init": "m_init",
    "integrator": "integrator",
    "x2_0": "x2_0",
    "v0": "v_hat_0",
    "epsilon": "epsilon",
}
_FLAG = {
    "x1_init": "--x1-init",
    "m_init": "--m-init",
    "integrator": "--integrator",
    "x2_0": "--x2-0",
    "v0": "--v0",
    "epsilon": "--epsilon",
    "trajectory": "--trajectory",
    "rate_scale": "--rate-scale",
    "latitude": "--latitude",
    "reference": "--reference",
    "gyro_arw": "--gyro-arw",
    "mag_noise": "--mag-noise",
    "r0": "--r0",
    "scenario": "--scenario",
    "form": "--form",
    "gain": "--gain",
    "k_i": "--k-i",
    "gyro_noise": "--gyro-noise",
    "vector_noise": "--vector-noise",
    "aggressive": "--aggressive",
    "hold": "--hold",
    "plot": "--plot",
}


def _refuse(args, attrs, name):
    for a in attrs:
        v = getattr(args, a, None)
        if v not in (None, False, ()):
            raise UserError(f"{_FLAG.get(a, '--' + a.replace('_', '-'))} does not apply to {name}")


def _study_config(study, args, extra: dict):
    """The study's Config from the flags; a flag of another study is refused."""
    fields = set(study.config().__class__._fields)
    kw = dict(extra)
    for attr, field in _BATISTA_FLAGS.items():
        v = getattr(args, attr, None)
        if v is None:
            continue
        if field not in fields:
            raise UserError(f"{_FLAG[attr]} does not apply to {study.name}")
        kw[field] = v.replace("-", "_") if isinstance(v, str) else v
    if args.duration is not None:
        kw["duration"] = args.duration
    if args.hold is not None:
        kw["hold"] = args.hold
    try:
        return study.config(**kw)
    except ValueError as e:
        raise UserError(str(e)) from None


def _reproduce(args) -> int:
    from . import studies

    study = studies.get(args.experiment)
    extra = {}
    if args.experiment.startswith("batista"):
        extra["trajectory"] = "aggressive" if args.aggressive else "slow"
    elif args.aggressive:
        raise UserError(f"--aggressive does not apply to {args.experiment}")
    cfg = _study_config(study, args, extra)
    title = f"{args.experiment} reproduce" + (f" ({cfg.trajectory})" if hasattr(cfg, "trajectory") else "")
    from .progress import Heartbeat

    with Heartbeat(f"jaxatt {args.command} {study.name}", bool(_progress(args))):
        payload = studies.reproduce(
            study,
            cfg,
            runs=args.runs,
            seed=args.seed,
            chunk=args.chunk,
            dtype=_dtype(args),
            json_path=args.json,
            plot_path=args.plot,
            quiet=args.quiet,
            progress=_progress(args),
            title=title,
            resume=args.resume,
        )
    return _finish_study(payload)


#: The flags of ``simulate`` that depend on what is simulated (in the order a refusal names them), and the ones
#: each kind of observer takes: an AHRS filter on the ahrs study, the complementary observer, a Batista / NLIO
#: paper study (whose own Config refuses the paper flags of the others, :func:`_study_config`). The rest is refused.
_PAPER_SETUP_FLAGS = (
    "trajectory",
    "latitude",
    "reference",
    "gyro_arw",
    "r0",
    "x1_init",
    "m_init",
    "integrator",
    "x2_0",
    "v0",
    "epsilon",
)
_COMPLEMENTARY_SETUP_FLAGS = ("scenario", "form", "gain", "k_i", "vector_noise")
_SIMULATE_FLAGS = (
    *_PAPER_SETUP_FLAGS,
    *_COMPLEMENTARY_SETUP_FLAGS,
    "gyro_noise",
    "acc_noise",
    "mag_noise",
    "rate_scale",
    "r0_euler",
    "hold",
    "gains",
)
_SIMULATE_TAKES = {
    "ahrs": {"gyro_noise", "acc_noise", "mag_noise", "rate_scale", "gains"},
    "complementary": {*_COMPLEMENTARY_SETUP_FLAGS, "gyro_noise", "r0_euler", "hold"},
    "batista": {*_PAPER_SETUP_FLAGS, "mag_noise", "rate_scale", "r0_euler", "hold"},
}


def _simulate(args) -> int:
    from . import so3, studies

    name = args.observer
    study = studies.get("ahrs" if name in AHRS_FILTERS else name)
    r0_euler = getattr(args, "r0_euler", None)
    observers, extra = None, None  # the study's own observers and gains unless --gains replaces them
    kind = "ahrs" if name in AHRS_FILTERS else ("complementary" if name == "complementary" else "batista")
    _refuse(args, [a for a in _SIMULATE_FLAGS if a not in _SIMULATE_TAKES[kind]], name)
    if kind == "ahrs":
        kw = _given(
            args,
            {
                "gyro_noise": "gyro_noise_std",
                "acc_noise": "acc_noise_std",
                "rate_scale": "rate_scale",
                "noise_scale": "noise_scale",
                "gyro_bias": "gyro_bias",
                "dt": "dt",
                "window_start": "window_start",
            },
        )
        if args.mag_noise is not None:
            kw["mag_noise_std"] = args.mag_noise * 1e-3  # nT -> uT, the scenario's unit
        kw["observer"] = name
        title = f"{name} simulate (AHRS)"
        if args.gains is not None:
            from .fitting import gainsfile
            from .observers import registry

            entry = registry.get(name)
            gains = gainsfile.read_params(args.gains, entry, base=entry.params(dtype=studies.base.paper_dtype()))
            observers = {name: (registry.recorded_observer(entry), gains)}
            assert isinstance(study, studies.ahrs.AhrsStudy)
            extra = {"gains_file": args.gains, "notes": study.notes(_study_config(study, args, kw), args.gains)}
    elif kind == "complementary":
        kw = _given(
            args,
            {
                "scenario": "scenario",
                "form": "form",
                "gain": "gain",
                "k_i": "k_i",
                "gyro_noise": "gyro_noise_std",
                "vector_noise": "meas_noise_std",
                "noise_scale": "noise_scale",
                "dt": "dt",
                "window_start": "window_start",
            },
        )
        if "scenario" in kw:
            kw["scenario"] = kw["scenario"].replace("-", "_")
        if args.gyro_bias is not None:
            kw["gyro_bias_deg_s"] = tuple(np.rad2deg(args.gyro_bias))
        if r0_euler is not None:
            kw["r_hat_0_euler_deg"] = r0_euler
        title = f"complementary simulate ({kw.get('scenario', 'rotating')})"
    else:
        kw = _given(
            args,
            {
                "trajectory": "trajectory",
                "rate_scale": "rate_scale",
                "latitude": "latitude_deg",
                "reference": "reference_nT",
                "gyro_arw": "gyro_arw_deg_h_rthz",
                "mag_noise": "mag_noise_nT",
                "noise_scale": "noise_scale",
                "gyro_bias": "gyro_bias",
                "dt": "dt",
                "window_start": "window_start",
            },
        )
        if args.r0 is not None and r0_euler is not None:
            raise UserError("give --r0 or --r0-euler, not both")
        if args.r0 is not None:
            kw["r_hat_0"] = args.r0
        if r0_euler is not None:
            kw["r_hat_0"] = tuple(np.asarray(so3.euler_zyx_to_matrix(*np.deg2rad(r0_euler))).reshape(9))
        title = f"{name} simulate"
    cfg = _study_config(study, args, kw)
    from .progress import Heartbeat

    with Heartbeat(f"jaxatt {args.command} {study.name}", bool(_progress(args))):
        payload = studies.reproduce(
            study,
            cfg,
            runs=args.runs,
            seed=args.seed,
            chunk=args.chunk,
            dtype=_dtype(args),
            json_path=args.json,
            plot_path=args.plot,
            quiet=args.quiet,
            progress=_progress(args),
            title=title,
            observers=observers,
            extra=extra,
            resume=args.resume,
        )
    return _finish_study(payload)


def _progress(args):
    """Progress lines: on a terminal unless --quiet; elsewhere only with --progress."""
    if getattr(args, "quiet", False):
        return None
    return True if getattr(args, "progress", False) or sys.stderr.isatty() else None


def _finish_study(payload: dict) -> int:
    if payload.get("nonfinite"):
        print(f"jaxatt: error: non-finite result: {payload['nonfinite']}", file=sys.stderr)
        return 1
    return 0 if payload["complete"] else 130


# ------------------------------------------------------------------------------------------------------------
# tune / evaluate
# ------------------------------------------------------------------------------------------------------------
def _default_gains_out(args) -> None:
    """``args.out`` = :data:`DEFAULT_GAINS_OUT` when not given; a default that exists (without --resume or
    --overwrite) is refused here, saying it is the default, so the message does not read as the user's path."""
    if args.out is not None:
        return
    args.out = DEFAULT_GAINS_OUT
    if os.path.exists(args.out) and not (args.resume or args.overwrite):
        raise UserError(
            f"--out {args.out} (the default) exists: give --out PATH for a new gains file, --resume to continue that "
            "fit or --overwrite to replace it"
        )


def _existing_gains_out(args) -> None:
    """An --out gains file that exists, without --resume or --overwrite, refused in the flags' words before the fit
    starts (after the output-path checks, which name a folder, a data file or the --init-gains file)."""
    if not (args.out and os.path.isfile(args.out)) or args.resume or args.overwrite:
        return
    from .fitting import gainsfile

    try:
        gainsfile.read(args.out)
    except ValueError as e:
        raise UserError(f"--out {args.out}: exists and is not a gains file, so it is not replaced ({e})") from None
    raise UserError(
        f"--out {args.out} exists: give --out PATH for a new gains file, --resume to continue that fit or "
        "--overwrite to replace it"
    )


def _tune(args) -> int:
    _default_gains_out(args)
    from . import io
    from .fitting import fitter

    if args.optimizer == "lbfgs" and args.objective != "varfree":
        raise UserError("--optimizer lbfgs needs the same loss at every step: use it with --objective varfree")
    if args.objective == "varfree":
        given = [
            flag for flag, v in (("--train-runs", args.train_runs), ("--val-runs", args.val_runs)) if v is not None
        ]
        if given:  # 0.2.0 took them (its README's usage line names --train-runs): said, not refused
            two = len(given) > 1
            warnings.warn(
                f"{' and '.join(given)} {'do' if two else 'does'} not apply to --objective varfree (the variance-free "
                f"loss draws no runs): ignored; leave {'them' if two else 'it'} out, or use --objective montecarlo",
                stacklevel=2,
            )
    io.check_output_path(args.out, "--out", suffixes=io.JSON_SUFFIXES)
    _existing_gains_out(args)
    config = {"duration": args.duration} if args.duration is not None else None
    from .progress import Heartbeat

    with Heartbeat(f"jaxatt tune {args.experiment}", bool(_progress(args))), warnings.catch_warnings():
        warnings.simplefilter("ignore", fitter.NonFiniteFit)  # said as an error line, exit 1 (_fit_status)
        res = fitter.fit(
            None,
            None,
            args.experiment,
            steps=args.steps,
            train_runs=fitter.TRAIN_RUNS if args.train_runs is None else args.train_runs,
            val_runs=fitter.VAL_RUNS if args.val_runs is None else args.val_runs,
            out=args.out,
            seed=args.seed,
            lr=args.lr,
            config=config,
            refine_schedule=args.refine_schedule,
            resume=args.resume,
            overwrite=args.overwrite,
            quiet=not _progress(args),
            objective=args.objective,
            optimizer=args.optimizer,
        )
    print(f"gains written to {res.path} ({res.status})")
    return _fit_status(res)


def _fit_status(res) -> int:
    if res.status == "interrupted":
        return 130
    if res.status == "non-finite":
        print(
            "jaxatt: error: the loss or its gradient was not finite (three steps in a row, or at the last step)",
            file=sys.stderr,
        )
        return 1
    return 0


#: study settings that follow the evaluation's length, not the gains file (the steady window, and the NLIO
#: studies' metric windows, scale with it)
_LENGTH_SETTINGS = ("duration", "window_start", "windows")


def _evaluation_config(args, gains) -> dict:
    """Config overrides of ``jaxatt evaluate``: the set-up the gains were tuned on (the gains file's
    ``settings.config``: scenario, noise, form, ...) at the study's own duration, or ``--duration``."""
    if (gains or {}).get("study") not in (None, args.experiment):
        return {"duration": args.duration} if args.duration is not None else {}  # refused after the set-up
    stored = (gains or {}).get("settings", {}).get("config")  # gainsfile.read checked that settings is an object
    if not isinstance(stored, (dict, type(None))):
        raise UserError(
            f"--gains {args.gains}: settings.config must be an object (the study set-up the gains were tuned on), "
            f"got {type(stored).__name__}"
        )
    stored = stored or {}
    over = {k: tuple(v) if isinstance(v, list) else v for k, v in stored.items() if k not in _LENGTH_SETTINGS}
    if args.duration is not None:
        over["duration"] = args.duration
    return over


def _evaluate(args) -> int:
    from . import io, studies
    from .fitting import gainsfile

    study = studies.get(args.experiment)
    io.check_output_path(args.json, "--json", suffixes=io.JSON_SUFFIXES, inputs={"--gains": args.gains})
    if args.gains is not None and not args.gains.strip():
        raise UserError("--gains: empty path (leave --gains out to evaluate the paper's gains)")
    d = gainsfile.read(args.gains) if args.gains else None
    try:
        cfg = study.config(**_evaluation_config(args, d))
    except ValueError as e:
        raise UserError(f"--gains {args.gains}: the set-up its gains were tuned on: {e}" if d else str(e)) from None
    s = study.setup(**{k: v for k, v in cfg._asdict().items()})
    params, source = s.params, "paper"
    if d is not None:
        if d.get("study") not in (None, study.name) or d["observer"] != s.entry:
            raise UserError(
                f"--gains {args.gains}: holds gains of {d['observer']!r} "
                f"({d.get('study') or 'recorded data'}), not of {study.name}"
            )
        note = gainsfile.unfinished_note(d, args.gains)
        if note:
            warnings.warn(note, stacklevel=1)
        params = gainsfile.apply(s.params, d["gains"], source=f"--gains {args.gains}")
        try:
            study.check_params(params)
        except ValueError as e:
            raise UserError(f"--gains {args.gains}: {e}") from None
        source = args.gains
        tun = d.get("settings", {})
        if tun.get("seed") == args.seed:
            try:
                used = set(range(*tun.get("train_run_indices", [0, 0]))) | set(
                    range(*tun.get("val_run_indices", [0, 0]))
                )
            except (TypeError, ValueError):
                raise UserError(
                    f"--gains {args.gains}: settings.train_run_indices / val_run_indices must be [start, stop] "
                    "run numbers"
                ) from None
            if used & set(range(args.runs)):
                warnings.warn(  # a warning, not a progress line: --quiet keeps it
                    f"{len(used & set(range(args.runs)))} evaluation runs were used for tuning "
                    f"(same seed {args.seed}); use another --seed for held-out numbers",
                    stacklevel=1,
                )
    from .progress import Heartbeat

    with Heartbeat(f"jaxatt evaluate {study.name}", bool(_progress(args))):
        payload = studies.evaluate(
            study,
            params,
            runs=args.runs,
            seed=args.seed,
            json_path=args.json,
            cfg=cfg,
            gains_source=source,
            quiet=args.quiet,
            progress=_progress(args),
            resume=args.resume,
        )
    return _finish_study(payload)


# ------------------------------------------------------------------------------------------------------------
# BROAD
# ------------------------------------------------------------------------------------------------------------
def _broad_table(title: str, score, anchors: bool = True) -> None:
    from .data.broad import ANCHORS

    print(f"\n{title}")
    print(f"{'trial':48s} {'group':11s} {'total':>7s} {'heading':>8s} {'incl':>7s}")
    for n, v in score.trials.items():
        print(f"{n:48s} {v.group:11s} {v.total_rmse_deg:7.2f} {v.heading_rmse_deg:8.2f} {v.inclination_rmse_deg:7.2f}")
    unscored = [n for n, v in score.trials.items() if not np.isfinite(v.total_rmse_deg)]
    if unscored:
        print(
            f"nan: {', '.join(unscored)} {'has' if len(unscored) == 1 else 'have'} no ground truth in the movement "
            "samples (nothing to score; not in the means)"
        )
    for g, v in score.groups.items():
        print(
            f"{'mean ' + g + ' (' + str(v.n_trials) + ' trials)':60s} {v.total_rmse_deg:7.2f} "
            f"{v.heading_rmse_deg:8.2f} {v.inclination_rmse_deg:7.2f}"
        )
    if anchors:  # the published numbers on BROAD (not for your own logs)
        print(
            "anchors (mean total RMSE, deg): "
            + "; ".join(f"{k}: {v['undisturbed']:.2f} / {v['disturbed']:.2f}" for k, v in ANCHORS.items())
            + "  (undisturbed / disturbed)"
        )


def _gains_json(params) -> dict:
    """{gain name: value as nested lists} of a Params NamedTuple (every field, None as null) or any pytree of your
    own observer (its leaves by path)."""
    if hasattr(params, "_asdict"):
        return {k: np.asarray(v).tolist() for k, v in params._asdict().items()}
    import jax

    return {
        jax.tree_util.keystr(k).strip("[]'.") or "params": np.asarray(v).tolist()
        for k, v in jax.tree_util.tree_flatten_with_path(params)[0]
    }


def _broad(args) -> int:
    from . import api, io
    from .data import broad

    io.check_output_path(
        args.json,
        "--json",
        suffixes=io.JSON_SUFFIXES,
        inputs={"--gains": args.gains, **_trial_inputs(args)},
        keep_gains=True,
    )
    from .progress import Heartbeat

    observer, params = _observer_and_params(args)
    trials = _trials_of(args)
    if not any(np.any(broad.scored_samples(tr)) for tr in trials):  # nothing to score: not a table of NaN, exit 0
        raise UserError(
            "no trial has a scored sample (movement with a finite ground truth): "
            f"{', '.join(tr.name for tr in trials)} {'has' if len(trials) == 1 else 'have'} no ground truth to score "
            "against"
        )
    dtype = "float32" if args.float32 else "float64"
    with Heartbeat(f"running {args.observer} on {len(trials)} trials", bool(_progress(args))):
        score = api.broad_score(observer, params, trials, dtype=dtype, offline=args.offline)
    shipped = getattr(api.registry.get(args.observer), "shipped", None) if args.observer in api.registry.INDEX else None
    source = args.gains or (f"--params {args.params}" if args.params else None)
    source = source or (f"shipped gains {shipped}" if shipped else "default gains")
    what = "BROAD" if args.data_dir is not None else f"BROAD metric on {len(trials)} logs"
    _broad_table(f"{what}, observer {score.observer} ({source}), {dtype}", score, anchors=args.data_dir is not None)
    params = api.resolve_observer(observer, params)[1]
    io.write_json(
        args.json,
        {
            "observer": score.observer,
            "gains": _gains_json(params),
            "gains_source": source,
            "dtype": dtype,
            "offline": bool(args.offline),
            "wall_s": score.wall_s,
            "anchors": broad.ANCHORS if args.data_dir is not None else None,
            "data": broad.ATTRIBUTION if args.data_dir is not None else {"logs": list(args.logs)},
            "environment": io.environment(),
            "trials": {
                n: {"group": s.group, **{m: getattr(s, m) for m in broad.METRICS}} for n, s in score.trials.items()
            },
            "groups": {
                g: {"n_trials": s.n_trials, **{m: getattr(s, m) for m in broad.METRICS}}
                for g, s in score.groups.items()
            },
        },
    )
    return 0


def _broad_tune(args) -> int:
    from . import io
    from .fitting import fitter

    _default_gains_out(args)

    io.check_output_path(
        args.out,
        "--out",
        suffixes=io.JSON_SUFFIXES,
        inputs={"--init-gains": args.init_gains, **_trial_inputs(args)},
    )
    _existing_gains_out(args)
    observer, params = _observer_to_tune(args)
    trials = _trials_of(args)
    from .progress import Heartbeat

    with Heartbeat(f"jaxatt broad-tune {args.observer}", bool(_progress(args))), warnings.catch_warnings():
        warnings.simplefilter("ignore", fitter.NonFiniteFit)  # said as an error line, exit 1 (_fit_status)
        res = fitter.fit(
            observer,
            params,
            trials,
            steps=args.steps,
            lr=args.lr,
            start=args.init_gains,
            out=args.out,
            resume=args.resume,
            overwrite=args.overwrite,
            quiet=not _progress(args),
            dtype="float64" if args.float64 else "float32",
        )
    print(f"gains written to {res.path} ({res.status})")
    return _fit_status(res)


# ------------------------------------------------------------------------------------------------------------
# filter
# ------------------------------------------------------------------------------------------------------------
def _import_attr(spec: str, flag: str):
    import importlib
    import os

    if ":" not in spec:
        raise UserError(f"{flag} {spec!r}: expected a registered name or module:attr")
    mod_name, attr = spec.split(":", 1)
    if not mod_name.strip() or not attr.strip():
        raise UserError(f"{flag} {spec!r}: expected module:attr, e.g. my_filters:OBSERVER (both parts named)")
    sys.path.insert(0, os.getcwd())
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as e:
        raise UserError(f"{flag} {spec}: cannot import {mod_name} ({e})") from None
    except SystemExit as e:  # the module runs a script's sys.exit when imported: jaxatt would exit with its code
        raise UserError(
            f"{flag} {spec}: importing {mod_name} called sys.exit({e.code!r}): guard its script part with "
            "if __name__ == '__main__':"
        ) from None
    except Exception as e:  # the user's module fails while it is imported: one line, not its traceback
        where = ""
        tb = e.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        if tb is not None:
            where = f" at {Path(tb.tb_frame.f_code.co_filename).name}:{tb.tb_lineno}"
        msg = " ".join(str(e).split())
        raise UserError(f"{flag} {spec}: importing {mod_name} failed{where}: {type(e).__name__}: {msg}") from None
    finally:
        sys.path.pop(0)
    if not hasattr(mod, attr):
        raise UserError(f"{flag} {spec}: {mod_name} has no attribute {attr!r}")
    return getattr(mod, attr)


def _check_log_path(path: str) -> None:
    """UserError unless ``--log`` names a file (checked before the output paths, whose checks assume it)."""
    from pathlib import Path

    if not Path(path).is_file():
        raise UserError(f"--log {path}: " + ("not a file" if Path(path).exists() else "not found"))


def _load_any_log(path: str, dt: Optional[float] = None, columns: Optional[str] = None, **units):
    """(samples, rate in Hz or None) of a CSV / NPZ log or a BROAD trial; ``dt`` (s) times a log without ``t``;
    ``columns`` (``--columns``): the CSV log's own column names; ``units``: ``gyr_unit``, ``acc_unit``,
    ``time_unit`` of a CSV / NPZ log (``--gyr-unit``, ...), converted to rad/s, m/s^2 and s."""
    from pathlib import Path

    from .data import broad, logs

    _check_log_path(path)
    if Path(path).suffix.lower() in (".hdf5", ".h5"):
        given = [f"--{k.replace('_', '-')} {v}" for k, v in units.items() if v != _SI_UNITS[k]]
        if given:
            raise UserError(f"{', '.join(given)}: a BROAD trial is in rad/s, m/s^2 and s already")
    names = None
    if columns is not None:
        if Path(path).suffix.lower() != ".csv":
            raise UserError(f"--columns applies to a CSV log, not to {Path(path).name}")
        try:
            names = logs.check_columns(columns)
        except ValueError as e:
            raise UserError(f"--{e}") from None
    if Path(path).suffix.lower() in (".hdf5", ".h5"):
        tr = broad.load_trial(path)
        return tr.samples, tr.rate_hz
    try:
        return logs.load_log(path, dt=dt, columns=names, **units), None
    except ValueError as e:
        if dt is None:
            raise
        try:  # --dt times the log: timestamps that are broken need not stop it
            samples = logs.load_log(path, dt=dt, replace_t=True, columns=names, **units)
        except ValueError:
            raise e from None
        warnings.warn(f"the log's timestamps are not read, --dt {dt:g} s times it: {e}", stacklevel=1)
        return samples, None


#: jaxatt's own units: the defaults of the unit flags
_SI_UNITS = {"gyr_unit": "rad/s", "acc_unit": "m/s^2", "time_unit": "s"}

#: what ``jaxatt filter --out`` writes, by extension ("" = no extension: CSV)
FILTER_OUTPUTS = (".csv", ".txt", ".npz", "")


def _observer_to_tune(args):
    """(observer, start params) of broad-tune's ``--observer`` (a registered name; or module:attr of your own
    Observer, with ``--params`` module:attr, or of a registry Entry) and ``--params``."""
    from .observers import registry

    if ":" not in args.observer:
        if args.params:
            raise UserError(
                "--params applies to your own observer (module:attr); a registered one starts from its gains"
            )
        return args.observer, None
    observer = _import_attr(args.observer, "--observer")
    if isinstance(observer, registry.Entry):
        if args.params:
            raise UserError(
                f"--observer {args.observer} is a registry Entry: it starts from its own params (no --params)"
            )
        return observer, None
    if not args.params:
        raise UserError(f"--observer {args.observer} (your own observer) needs --params module:attr (its start gains)")
    return observer, _import_attr(args.params, "--params")


def _observer_and_params(args):
    """(observer, params) of ``--observer`` (a registered name, or module:attr of your own Observer or registry
    Entry), ``--gains`` (a gains file: of a registered observer, or of your own put into ``--params``) and
    ``--params`` (module:attr, your own)."""
    from .observers import registry

    if ":" in args.observer:
        observer = _import_attr(args.observer, "--observer")
        params = _import_attr(args.params, "--params") if args.params else None
        if args.gains and isinstance(observer, registry.Entry):
            if params is not None:
                raise UserError(
                    f"--observer {args.observer} is a registry Entry: give its gains by --gains or its params by "
                    "--params, not both"
                )
            params = args.gains
        elif args.gains:  # gains fitted for your own observer (jaxatt.fit(..., out=)) put into --params
            if params is None:
                raise UserError("--gains with your own observer needs --params module:attr (the params they go into)")
            from .fitting import gainsfile

            held = gainsfile.read(args.gains)["observer"]
            if held != getattr(observer, "name", held):
                raise UserError(f"--gains {args.gains}: holds gains of {held!r}, not of {observer.name!r}")
            params = gainsfile.read_params(args.gains, base=params)
        return observer, params
    if args.params:
        raise UserError("--params applies to your own observer (module:attr); use --gains for a registered one")
    return args.observer, args.gains


#: Outputs of jaxatt's observers that are sensor-to-navigation attitudes in the observer's own frame (also with
#: ``backward_`` before them: the offline mode's backward pass); ``jaxatt filter --frame`` writes them in its frame,
#: as the estimate. Outputs named with a frame (``q_nwu``) and gains (``k1``) are written as they are.
ATTITUDE_OUTPUTS = ("q", "r", "q6d", "q9d", "r_hat")


def _observer_frame(observer, frame: str) -> str:
    """The navigation frame of a registered observer's outputs; ``frame`` for one of your own (as given)."""
    from .observers import registry

    return registry.get(observer).frame if isinstance(observer, (str, registry.Entry)) else frame


def _in_frame(name: str, v, frame: str, own: str):
    """Output ``name`` (T, 4) / (T, 3, 3) in ``frame`` when it is an attitude in the observer's frame ``own``."""
    from . import frames

    base = name[len("backward_") :] if name.startswith("backward_") else name
    if frame == own or base not in ATTITUDE_OUTPUTS or not np.issubdtype(v.dtype, np.floating):
        return v
    if v.ndim == 2 and v.shape[1] == 4:
        return frames.change_frame(v, frame, own)
    if v.ndim == 3 and v.shape[1:] == (3, 3):
        return np.einsum("ij,tjk->tik", frames.frame_rotation(frame, own), v)
    return v


def _filter(args) -> int:
    from . import api, io

    _check_log_path(args.log)
    out = io.check_output_path(
        args.out, "--out", suffixes=FILTER_OUTPUTS, inputs={"--log": args.log, "--gains": args.gains}
    )
    assert out is not None  # --out is required
    observer, params = _observer_and_params(args)
    from .progress import Heartbeat

    if args.dt is not None and args.time_unit != "s":
        raise ValueError(
            f"--time-unit {args.time_unit} and --dt: --time-unit is the unit of the log's t column, and --dt (s) "
            "times the log instead of it; give one of them"
        )
    units = {"gyr_unit": args.gyr_unit, "acc_unit": args.acc_unit, "time_unit": args.time_unit}
    samples, rate = _load_any_log(args.log, args.dt, args.columns, **units)
    if len(samples.t) < 2:
        raise UserError(f"--log {args.log}: {len(samples.t)} sample; a filter needs at least 2")
    dt = args.dt if args.dt is not None else (1.0 / rate if rate else None)
    if args.dt is not None and len(samples.t) > 1:
        d = np.diff(np.asarray(samples.t, float))
        if np.max(np.abs(d - args.dt)) > 0.01 * args.dt:
            warnings.warn(
                f"--dt {args.dt:g} s replaces the log's timestamps (their intervals run from {d.min():.6g} to "
                f"{d.max():.6g} s); the t column restarts at 0",
                stacklevel=1,
            )
    with Heartbeat(f"filtering {len(samples.t)} samples", bool(_progress(args))):
        est = api.filter(
            observer,
            samples.gyr,
            samples.acc,
            samples.mag,
            dt=dt,
            t=None if dt is not None else samples.t,
            params=params,
            frame=args.frame,
            dtype="float32" if args.float32 else None,
            offline=args.offline,
        )
    cols, names = [est.t, est.quat[:, 0], est.quat[:, 1], est.quat[:, 2], est.quat[:, 3]], ["t", "qw", "qx", "qy", "qz"]
    own_frame = _observer_frame(observer, args.frame)
    for k, v in est.outputs.items():
        if k in ("t", "q", "r"):
            continue
        v = _in_frame(k, np.asarray(v), args.frame, own_frame)
        if v.ndim == 1:
            cols.append(v.astype(float))
            names.append(k)
        elif v.ndim == 2 and v.shape[1] in (3, 4):  # vectors x, y, z; quaternions w, x, y, z
            for i, ax in enumerate("xyz" if v.shape[1] == 3 else "wxyz"):
                cols.append(v[:, i].astype(float))
                names.append(f"{k}_{ax}")
        elif v.ndim == 3 and v.shape[1:] == (3, 3):  # matrices, row-major
            for i in range(9):
                cols.append(v[:, i // 3, i % 3].astype(float))
                names.append(f"{k}_{i // 3}{i % 3}")
    if out.suffix.lower() == ".npz":
        io.write_npz(out, dict(zip(names, cols)))
    else:
        table = np.column_stack(cols)

        def write(f):
            f.write(",".join(names) + "\n")
            np.savetxt(f, table, delimiter=",", fmt="%.17g")

        io.write_atomic(out, write)
    from .observers import registry

    own = not isinstance(observer, (str, registry.Entry))  # your Observer: its estimate is not converted
    frame = f"{est.frame} as labelled, not converted: your observer's own frame" if own else est.frame
    print(
        f"{est.observer}: {len(est.t)} estimates ({frame}, {est.quat.dtype}) written to {args.out} "
        f"with columns {', '.join(names)}"
    )
    return 0


# ------------------------------------------------------------------------------------------------------------
# excitation
# ------------------------------------------------------------------------------------------------------------
def _excitation(args) -> int:
    from . import analysis, frames, io

    io.check_output_path(args.json, "--json", suffixes=io.JSON_SUFFIXES, inputs={"--log": args.log})
    io.check_figure_path(args.plot, "--plot", inputs={"--log": args.log, "--json": args.json})
    ignored = ("--duration", "--dt") if args.log else ("--mag-ref", "--frame", "--columns", "--time-unit")
    given = [flag for flag in ignored if getattr(args, flag[2:].replace("-", "_")) is not None]
    if given:
        what = "a log (it has its own timestamps)" if args.log else "a scenario (its references are built in)"
        raise UserError(f"{' and '.join(given)} do{'es' if len(given) == 1 else ''} not apply to {what}")
    if args.scenario:
        args.duration = 60.0 if args.duration is None else args.duration
        args.dt = 0.01 if args.dt is None else args.dt
        from .progress import Heartbeat
        from .sim import references

        scn = references.make_scenario(args.scenario.replace("-", "_"))
        with Heartbeat(f"simulating {args.scenario}", bool(_progress(args))):
            res = analysis.excitation_of_scenario(scn, duration=args.duration, dt=args.dt, window=args.window)
        source = f"scenario {args.scenario}, {args.duration:g} s at {1 / args.dt:g} Hz"
    else:
        from .observers import complementary as comp

        samples = _load_any_log(args.log, columns=args.columns, time_unit=args.time_unit or "s")[0]
        if len(samples.t) < 2:
            raise UserError(f"--log {args.log}: {len(samples.t)} sample; the excitation analysis needs at least 2")
        if samples.acc is None and samples.mag is None:
            raise UserError(f"--log {args.log}: the log has neither acc nor mag columns")
        args.frame = args.frame or "NED"
        fields = tuple(f for f in ("acc", "mag") if getattr(samples, f) is not None)
        empty = [f for f in fields if not analysis.valid_readings(getattr(samples, f)).any()]
        if empty and len(empty) == len(fields):
            raise UserError(f"--log {args.log}: {' and '.join(empty)} {'has' if len(empty) == 1 else 'have'} no "
                            "valid reading (every row non-finite or zero): nothing to analyse")  # fmt: skip
        if empty:
            print(f"jaxatt excitation: {empty[0]} has no valid reading (every row non-finite or zero): left out",
                  file=sys.stderr)  # fmt: skip
            fields = tuple(f for f in fields if f not in empty)
        if "mag" in fields and args.mag_ref is None:
            raise UserError("--mag-ref X,Y,Z is needed to analyse a magnetometer log")
        if args.mag_ref is not None and not np.any(np.asarray(args.mag_ref, float)):
            raise UserError("--mag-ref: the magnetic reference must be a non-zero vector (its direction is used)")
        refs_ = [frames.up(args.frame)] if "acc" in fields else []
        if "mag" in fields:
            m = np.asarray(args.mag_ref, float)
            m = m / np.max(np.abs(m))  # only the direction is used: scaled first, so 1e300 or 1e-320 stay finite
            refs_.append(m / np.linalg.norm(m))
        p = comp.default_params(len(refs_), 0, ref_inertial=np.stack(refs_))
        res = analysis.excitation_from_samples(samples, window=args.window, params=p, imu_fields=fields)
        source = f"log {args.log} ({', '.join(fields)}; references in {args.frame})"
        for f in fields:
            ok = analysis.valid_readings(getattr(samples, f))
            print(f"{f}: {100 * ok.mean():.1f} % of the samples are valid readings (finite, non-zero); only they count")
        d, longest = np.diff(np.asarray(samples.t, float)), analysis.gap_threshold(samples.t)
        gaps = d > longest
        if gaps.any():
            print(
                f"{gaps.sum()} gaps in the timestamps longer than {longest:.3g} s "
                f"({d[gaps].sum():.6g} s in all) count as no data"
            )
    T = args.window
    lam = np.asarray(res.lambda2) / T
    bad = lam < args.threshold
    print(f"excitation of {source}: {len(lam)} windows of T = {T:g} s")
    rows = [
        ("lambda2 / T  (Def. 3.3/4.1)", lam),
        ("lambda_min projector / T (Lemma 3.4/4.2)", np.asarray(res.lambda_min_projector) / T),
        ("condition (6)/(13) / T", np.asarray(res.condition) / T),
    ]
    print(f"{'measure':42s} {'min':>10s} {'median':>10s} {'max':>10s}")
    for label, v in rows:
        print(f"{label:42s} {np.min(v):10.4g} {np.median(v):10.4g} {np.max(v):10.4g}")
    if bad.any():
        t0 = np.asarray(res.t_start)[bad]
        print(
            f"NOT exciting (lambda2/T < {args.threshold:g}) in {bad.mean() * 100:.1f} % of the windows, "
            f"first at t = {t0[0]:.2f} s, last at t = {t0[-1]:.2f} s"
        )
    else:
        print(f"exciting in every window (lambda2/T >= {args.threshold:g})")
    if args.json:
        io.write_json(
            args.json,
            {
                "source": source,
                "window_s": T,
                "threshold": args.threshold,
                "measures": {k: np.asarray(v).tolist() for k, v in res._asdict().items()},
                "environment": io.environment(),
            },
        )
        print(f"results written to {args.json}")
    if args.plot:
        from . import plot

        plt = plot._plt()
        fig, ax = plt.subplots(figsize=(7, 3.2), constrained_layout=True)
        analysis.plot_excitation(res, ax=ax, threshold=args.threshold, title=f"excitation: {source}")
        plot.save(fig, args.plot, close=True)
        print(f"plot written to {args.plot}")
    return 0


# ------------------------------------------------------------------------------------------------------------
_COMMANDS = {
    "filter": _filter,
    "reproduce": _reproduce,
    "simulate": _simulate,
    "tune": _tune,
    "evaluate": _evaluate,
    "broad": _broad,
    "broad-tune": _broad_tune,
    "excitation": _excitation,
}


_INTERRUPTED: List[int] = []  # signal numbers
_DEFERRED: List[int] = []
#: non-empty while main() imports JAX and the library: a KeyboardInterrupt raised inside the import of a compiled
#: extension can leave it half-initialised and crash the interpreter (SIGSEGV), so a Ctrl-C then leaves at once
_IMPORTING: List[bool] = []
#: functions in which a Ctrl-C is re-sent 50 ms later instead of raised: those that swallow an exception ("Exception
#: ignored in ...") and the atomic file write (a KeyboardInterrupt inside ``np.savez`` leaves a half-closed ZipFile
#: whose ``__del__`` prints a traceback at exit; the write takes milliseconds, then the interrupt lands)
_DEFERRING_CALLS = {"__del__", "_xla_gc_callback", "write_atomic"}


def _in_deferring_call(frame) -> bool:
    while frame is not None:
        if frame.f_code.co_name in _DEFERRING_CALLS:
            return True
        frame = frame.f_back
    return False


def _on_sigint(signum, frame):
    """Ctrl-C (SIGINT) or SIGTERM (``kill``, a batch scheduler): remember it and raise KeyboardInterrupt where Python
    runs next, so that finished work is saved and no temporary file is left (a second signal leaves at once); the
    exit status is then 128 + the signal's number (130, 143).

    Inside a garbage-collector callback or ``__del__`` the exception would be printed and dropped, and inside an
    atomic file write it would leave a half-written archive object behind, so the signal is sent again 50 ms later
    instead."""
    if _IMPORTING or (_INTERRUPTED and not _DEFERRED):  # nothing computed yet, or a second signal
        os.write(2, b"jaxatt: interrupted\n")
        os._exit(128 + signum)
    if not _INTERRUPTED:
        _INTERRUPTED.append(signum)
    if _in_deferring_call(frame):
        _DEFERRED.append(signum)
        threading.Timer(0.05, os.kill, (os.getpid(), signum)).start()
        return
    _DEFERRED.clear()
    raise KeyboardInterrupt


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"jaxatt: warning: {message}", file=sys.stderr)


_NEGATIVE_LIST = re.compile(r"^-(\d|\.\d)[^,]*,")


def _join_negative_lists(argv: List[str]) -> List[str]:
    """``--mag-ref -5,20,-40`` as ``--mag-ref=-5,20,-40``: argparse takes a value that starts with "-" and is
    not one number for a flag."""
    out: List[str] = []
    for tok in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and _NEGATIVE_LIST.match(tok):
            out[-1] = f"{out[-1]}={tok}"
        else:
            out.append(tok)
    return out


def main(argv: Optional[List[str]] = None) -> int:
    parser = _parser()
    words = _join_negative_lists(list(sys.argv[1:] if argv is None else argv))
    args, unknown = parser.parse_known_args(words)
    if unknown:  # said by the parser of the part they are in, so the message points to its --help
        before = words.index(args.command) if args.command in words else len(words)
        first = any(words.index(u) < before for u in unknown if u in words)
        (parser if first else parser.subparsers[args.command]).error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        _IMPORTING.append(True)
        import jax

        jax.config.update("jax_enable_x64", True)  # the entry point decides the precision (the library never does)
        from .sharding import initialize_distributed

        # several processes when JAXATT_COORDINATOR / JAXATT_NUM_PROCESSES / JAXATT_PROCESS_ID are set (before
        # any other JAX call); every process runs the same command, process 0 writes the files
        if initialize_distributed():
            from .io import is_main_process

            if not is_main_process():  # process 0 prints the results (and writes the files); errors still show
                sys.stdout = open(os.devnull, "w")
        from . import api, studies  # noqa: F401 - imported before any work: an interrupt in an import is not lost

        _IMPORTING.clear()
        if _INTERRUPTED:
            raise KeyboardInterrupt
        with warnings.catch_warnings():  # warnings as one line each: "jaxatt: warning: ..."
            warnings.showwarning = _show_warning
            return _COMMANDS[args.command](args)
    except KeyboardInterrupt:
        written = getattr(sys.modules.get("jaxatt.io"), "WRITTEN", [])
        saved = f"saved so far: {', '.join(written)}" if written else "nothing had finished, so nothing was saved"
        print(f"jaxatt: interrupted ({saved})", file=sys.stderr)
        return 130
    except (UserError, ValueError, FileNotFoundError, ImportError) as e:
        if args.debug:
            raise
        print(f"jaxatt: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except FloatingPointError as e:
        if args.debug:
            raise
        print(f"jaxatt: error: non-finite result: {_one_line(e)}", file=sys.stderr)
        return 1
    except OSError as e:  # a file that cannot be read or written (permissions, a full disk, /dev/full)
        if args.debug:
            raise
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"jaxatt: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2


def _one_line(error: BaseException) -> str:
    """An error's message on one line (a message that shows an array may hold line breaks)."""
    return re.sub(r"\s*\n\s*", " ", str(error)).strip()


def compile_cache_dir(environ=os.environ) -> Optional[str]:
    """Where the ``jaxatt`` command keeps compiled XLA programs between runs (JAX's persistent compilation cache):
    ``$JAXATT_COMPILE_CACHE`` if set (``off`` disables it), else ``$XDG_CACHE_HOME/jaxatt/xla`` or
    ``~/.cache/jaxatt/xla``; None when off, when ``JAX_COMPILATION_CACHE_DIR`` is already set (JAX's own setting
    wins) or when the folder cannot be created. A program is reused only if its HLO, compile options, backend and
    jax version are identical, so results do not change; only the second run starts sooner."""
    if environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None
    choice = environ.get("JAXATT_COMPILE_CACHE", "")
    if choice.lower() in ("off", "0", "no", "false"):
        return None
    try:
        if choice:
            path = Path(choice)
        else:
            path = Path(environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "jaxatt" / "xla"
        path.mkdir(parents=True, exist_ok=True)
    except (OSError, RuntimeError):  # no home folder, read-only file system, a file in the way
        return None
    return str(path) if os.access(path, os.W_OK) else None


#: Most CPU devices the ``jaxatt`` command asks for (one per core, up to this many).
MAX_CPU_DEVICES = 32
#: the most CPU devices ``JAXATT_CPU_DEVICES`` may ask for (each is a thread pool: 100000 took 20 GB and aborted)
MAX_USER_CPU_DEVICES = 256


def cpu_device_count(environ=os.environ) -> Optional[int]:
    """How many CPU devices the ``jaxatt`` command asks JAX for, so that Monte Carlo and tuning split their runs
    over every core (:mod:`jaxatt.sharding`): ``$JAXATT_CPU_DEVICES`` if set (1 to 256), else the cores
    this process may use (at most :data:`MAX_CPU_DEVICES`; 1 when ``JAXATT_NUM_PROCESSES`` starts several
    processes, :func:`jaxatt.sharding.initialize_distributed`); None when JAX is told already
    (``JAX_NUM_CPU_DEVICES``, or ``--xla_force_host_platform_device_count`` in ``XLA_FLAGS``: the user's setting
    wins). Results do not depend on it beyond rounding; on a GPU machine the CPU devices are not used.
    Raises ValueError (one line) for a bad ``JAXATT_CPU_DEVICES``."""
    if environ.get("JAX_NUM_CPU_DEVICES") or "xla_force_host_platform_device_count" in environ.get("XLA_FLAGS", ""):
        return None
    choice = environ.get("JAXATT_CPU_DEVICES", "").strip()
    if choice:
        if not choice.isdigit() or not 1 <= int(choice) <= MAX_USER_CPU_DEVICES:
            raise ValueError(
                f"JAXATT_CPU_DEVICES must be an integer from 1 to {MAX_USER_CPU_DEVICES}, got {choice!r} (one "
                "device per core is the default)"
            )
        return int(choice)
    if environ.get("JAXATT_NUM_PROCESSES"):  # several processes (jax.distributed): one device each
        return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, MAX_CPU_DEVICES))


def entry() -> None:
    """The ``jaxatt`` command: :func:`main` with Ctrl-C handled (exit status 130, what was finished is saved; the
    process then leaves without the interpreter's teardown, which can crash while XLA threads are busy), and
    compiled programs kept between runs (:func:`compile_cache_dir`), and one CPU device per core
    (:func:`cpu_device_count`)."""
    cache = compile_cache_dir()
    if cache is not None:  # read by JAX when it is imported (main imports it)
        os.environ["JAX_COMPILATION_CACHE_DIR"] = cache
    try:
        n_cpu = cpu_device_count()
    except ValueError as e:
        print(f"jaxatt: error: {e}", file=sys.stderr)
        sys.exit(2)
    if n_cpu is not None:  # every core: the runs of a Monte Carlo chunk are split over the CPU devices
        os.environ["JAX_NUM_CPU_DEVICES"] = str(n_cpu)
    previous = {sig: signal.signal(sig, _on_sigint) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        rc = main()
    except KeyboardInterrupt:
        rc = 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if _INTERRUPTED or rc == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(128 + _INTERRUPTED[0] if _INTERRUPTED else 130)
    sys.exit(rc)


if __name__ == "__main__":  # pragma: no cover
    entry()
