"""Boundaries that never lose work: every bad input is one clear line (CLI exit 2, no traceback) and leaves existing
output files untouched; a non-finite result exits 1 saying where it appeared; Ctrl-C exits 130 keeping what was
finished; a run killed outright is resumed with ``--resume`` to the same numbers as an uninterrupted run."""

import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import jaxatt
from jaxatt import cli, montecarlo

REPO = Path(__file__).parents[1]
KEEP = b'{"complete": true, "precious": "an earlier result"}\n'


# ------------------------------------------------------------------------------------------------------------
# Files: good and broken logs, gains files and HDF5 trials (made here: no ../shared needed)
# ------------------------------------------------------------------------------------------------------------
def _log_rows(n=1000, dt=0.01, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    gyr = rng.normal(0, 0.3, (n, 3))
    acc = np.tile([0.0, 0.0, 9.81], (n, 1)) + rng.normal(0, 0.05, (n, 3))
    mag = np.tile([20.0, 0.0, -40.0], (n, 1))
    return t, gyr, acc, mag


def _write_csv(path, t, gyr, acc, mag):
    header = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z"
    np.savetxt(path, np.column_stack([t, gyr, acc, mag]), delimiter=",", header=header, comments="")


def _write_trial(path, n=600, rate=100.0, drop=(), truncate=False, truth=True, inf=False, truth_norm=1.0):
    h5py = pytest.importorskip("h5py")
    t, gyr, acc, mag = _log_rows(n)
    if inf:
        gyr = np.array(gyr)
        gyr[5, 0] = np.inf
    with h5py.File(path, "w") as f:
        for k, v in {
            "imu_gyr": gyr,
            "imu_acc": acc,
            "imu_mag": mag,
            "opt_quat": np.tile([truth_norm, 0, 0, 0] if truth else [np.nan] * 4, (n, 1)),
            "movement": np.ones(n),
        }.items():
            if k not in drop:
                f[k] = v
        f.attrs["sampling_rate"] = rate
    if truncate:
        data = Path(path).read_bytes()
        Path(path).write_bytes(data[: len(data) // 3])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("boundaries")
    make_files(d)
    return d


def make_files(d: Path) -> None:
    """The input files of the cases in folder ``d`` (also used by research/boundaries/table.py)."""
    t, gyr, acc, mag = _log_rows()
    _write_csv(d / "log.csv", t, gyr, acc, mag)
    _write_csv(d / "huge_gyr.csv", t, gyr * 1e300, acc, mag)
    _write_csv(d / "backwards.csv", t[::-1], gyr, acc, mag)
    (d / "no_header.csv").write_text("0,0,0,0\n0.01,0,0,0\n")
    (d / "dated.csv").write_text("t,gyr_x,gyr_y,gyr_z\n2024-05-01 12:00:00.00,0,0,0\n2024-05-01 12:00:00.01,0,0,0\n")
    # float32 Unix times: 1.7e9 s in float32 steps by 128 s, so the 0.01-s samples collide
    np.savez(d / "unix_float32.npz", t=(1.7e9 + t).astype(np.float32), gyr=gyr, acc=acc, mag=mag)
    (d / "empty.csv").write_text("")
    (d / "one_row.csv").write_text(
        "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z\n0,0,0,0,0,0,9.8,20,0,-40\n"
    )
    bad_inf = np.column_stack([t, gyr, acc, mag]).astype(object)
    bad_inf[5, 1] = "inf"
    (d / "inf.csv").write_text(
        "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z\n" + "\n".join(",".join(map(str, r)) for r in bad_inf)
    )
    shipped = REPO / "jaxatt" / "data" / "gains"
    robust = json.loads((shipped / "robust_broad_all.json").read_text())
    for name, value in (("nan", float("nan")), ("negative", -1.0)):
        g = json.loads(json.dumps(robust))
        g["gains"]["tau_acc"]["value"] = value
        (d / f"robust_{name}.json").write_text(json.dumps(g))
    (d / "robust_ok.json").write_text(json.dumps(robust))
    (d / "so3_study.json").write_text((shipped / "batista-so3.json").read_text())
    so3 = json.loads((shipped / "batista-so3.json").read_text())
    so3["gains"]["alpha1"]["value"][0], so3["status"] = -1.0, "done"  # a schedule: its message shows an array
    (d / "so3_negative.json").write_text(json.dumps(so3))
    (d / "broken.json").write_text('{"format": "jaxatt-gains/2", "observer": ')
    (d / "not_gains.json").write_text('{"hello": 1}')
    for name, kw in {
        "ok": {},
        "no_mag": {"drop": ("imu_mag",)},
        "rate0": {"rate": 0.0},
        "truncated": {"truncate": True},
        "no_truth": {"truth": False},
        "inf": {"inf": True},
        "norm2": {"truth_norm": 2.0},
        "rate_bool": {"rate": True},
    }.items():
        (d / f"trials_{name}").mkdir()
        _write_trial(d / f"trials_{name}" / f"01_{name}.hdf5", **kw)
    (d / "trials_empty").mkdir()
    (d / "folder").mkdir()
    novalue = json.loads(json.dumps(robust))
    novalue["gains"]["tau_acc"] = {"val": 1.0}
    (d / "robust_novalue.json").write_text(json.dumps(novalue))
    for name, info in (("info", {"trials": {"01_info": {"groups": ["all_trials", "undisturbed"]}}}), ("badinfo", [1])):
        (d / f"trials_{name}").mkdir()
        _write_trial(d / f"trials_{name}" / f"01_{name}.hdf5")
        (d / f"trials_{name}" / "trials.json").write_text(json.dumps(info))
    (d / "empty_runs.json.runs.npz").write_bytes(b"")
    (d / "runs_folder.json.runs.npz").mkdir()
    (d / "partial_folder.json.partial.json").mkdir()


def _run(argv, files, capsys):
    """cli.main in this process (argparse errors leave by SystemExit); returns (rc, stderr lines)."""
    argv = [a.format(d=files) for a in argv]
    try:
        rc = cli.main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err
    return rc, [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("\r")]


# ------------------------------------------------------------------------------------------------------------
# Bad input on every command: exit 2, one line naming what is wrong, existing output untouched
# ------------------------------------------------------------------------------------------------------------
MC = ["--runs", "1", "--duration", "5", "--quiet"]
BAD_INPUT = [
    # top level
    ([], r"the following arguments are required: command|invalid choice|command"),
    (["frobnicate"], r"invalid choice: 'frobnicate'"),
    # filter
    (["filter", "--log", "{d}/missing.csv", "--out", "{d}/keep.csv"], r"--log .*missing\.csv: not found"),
    (["filter", "--log", "{d}/folder", "--out", "{d}/keep.csv"], r"folder"),
    (["filter", "--log", "{d}", "--out", "{d}/keep.csv"], r"--log .*: not a file"),  # not "--out in the --log folder"
    (["filter", "--log", "{d}/log.csv", "--out", "{d}/folder"], r"--out .*folder: is a folder"),
    (["filter", "--log", "{d}/log.csv", "--out", " "], r"--out: empty path"),
    (["filter", "--log", "{d}/log.csv", "--out", "/proc/est.csv"], r"--out /proc/est\.csv: cannot write"),
    (["filter", "--log", "{d}/log.csv", "--observer", "nope", "--out", "{d}/keep.csv"], r"unknown observer 'nope'"),
    (["filter", "--log", "{d}/log.csv", "--observer", "nomodule:X", "--out", "{d}/keep.csv"], r"cannot import"),
    (["filter", "--log", "{d}/log.csv", "--params", "a:b", "--out", "{d}/keep.csv"], r"--params applies"),
    (["filter", "--log", "{d}/log.csv", "--columns", "gx", "--out", "{d}/keep.csv"], r"--columns must be 'name="),
    (
        ["filter", "--log", "{d}/dated.csv", "--time-unit", "ms", "--out", "{d}/keep.csv"],
        r"dated\.csv: time_unit 'ms' \(--time-unit\) applies to numeric timestamps, and its t column holds date-t",
    ),
    (
        ["filter", "--log", "{d}/trials_ok/01_ok.hdf5", "--gyr-unit", "deg/s", "--out", "{d}/keep.csv"],
        r"--gyr-unit deg/s: a BROAD trial is in rad/s, m/s\^2 and s already",
    ),
    (["filter", "--log", "{d}/log.csv", "--gyr-unit", "rpm", "--out", "{d}/keep.csv"], r"argument --gyr-unit: inva"),
    (["filter", "--log", "{d}/log.csv", "--columns", "w_x=gx", "--out", "{d}/keep.csv"], r"--columns: 'w_x' is not"),
    (["filter", "--log", "{d}/log.csv", "--columns", "t=time", "--out", "{d}/keep.csv"], r"column 'time' \(given in"),
    (
        ["filter", "--log", "{d}/unix_float32.npz", "--columns", "t=time", "--out", "{d}/keep.csv"],
        r"--columns applies to a CSV log, not to unix_float32\.npz",
    ),
    (["filter", "--log", "{d}/log.csv", "--gains", "{d}/missing.json", "--out", "{d}/keep.csv"], r"not found"),
    (["filter", "--log", "{d}/log.csv", "--gains", "{d}/broken.json", "--out", "{d}/keep.csv"], r"broken\.json"),
    (["filter", "--log", "{d}/log.csv", "--gains", "{d}/so3_study.json", "--out", "{d}/keep.csv"], r"so3_study"),
    (["filter", "--log", "{d}/log.csv", "--gains", "{d}/robust_nan.json", "--out", "{d}/keep.csv"], r"tau_acc"),
    (["filter", "--log", "{d}/log.csv", "--dt", "0", "--out", "{d}/keep.csv"], r"argument --dt"),
    (["filter", "--log", "{d}/log.csv", "--dt", "nan", "--out", "{d}/keep.csv"], r"argument --dt"),
    (["filter", "--log", "{d}/log.csv", "--frame", "XYZ", "--out", "{d}/keep.csv"], r"argument --frame"),
    (["filter", "--log", "{d}/no_header.csv", "--out", "{d}/keep.csv"], r"header"),
    (["filter", "--log", "{d}/empty.csv", "--out", "{d}/keep.csv"], r"empty\.csv"),
    (
        ["filter", "--log", "{d}/one_row.csv", "--out", "{d}/keep.csv"],
        r"--log .*one_row\.csv: 1 sample; a filter needs",
    ),
    (["filter", "--log", "{d}/inf.csv", "--out", "{d}/keep.csv"], r"inf"),
    (["filter", "--log", "{d}/backwards.csv", "--out", "{d}/keep.csv"], r"increasing"),
    (["filter", "--log", "{d}/unix_float32.npz", "--out", "{d}/keep.csv"], r"float32 timestamps near 1\.7e\+09 s"),
    (["filter", "--log", "{d}/trials_no_mag/01_no_mag.hdf5", "--out", "{d}/keep.csv"], r"imu_mag"),
    (["filter", "--log", "{d}/trials_rate0/01_rate0.hdf5", "--out", "{d}/keep.csv"], r"sampling_rate"),
    (
        ["filter", "--log", "{d}/trials_inf/01_inf.hdf5", "--out", "{d}/keep.csv"],
        r"01_inf\.hdf5: imu_gyr contains \+-inf",
    ),
    (["filter", "--log", "{d}/trials_truncated/01_truncated.hdf5", "--out", "{d}/keep.csv"], r"truncated|read"),
    # reproduce / simulate
    (["reproduce", "batista-ges", *MC, "--json", "{d}/folder"], r"--json .*folder: is a folder"),
    (["reproduce", "batista-ges", *MC, "--json", "/proc/x.json"], r"--json /proc/x\.json: cannot write"),
    (["reproduce", "batista-ges", *MC, "--plot", "/proc/x.png", "--json", "{d}/keep.json"], r"--plot /proc"),
    (["reproduce", "batista-ges", "--runs", "0"], r"argument --runs"),
    (["reproduce", "batista-ges", "--runs", "many"], r"argument --runs"),
    (["reproduce", "batista-ges", "--duration", "-5"], r"argument --duration"),
    (["reproduce", "batista-ges", *MC, "--m-init", "rescaled", "--json", "{d}/keep.json"], r"does not apply"),
    (["reproduce", "nlio-case1", *MC, "--aggressive", "--json", "{d}/keep.json"], r"does not apply"),
    (["reproduce", "batista-so3", *MC, "--resume"], r"--resume needs --json"),
    (["reproduce", "batista-so3", "--quiet", "--progress"], r"not allowed with argument"),
    (["simulate", "--observer", "complementary", "--latitude", "45", *MC], r"--latitude.*does not apply"),
    (["simulate", "--observer", "batista-ges", "--gain", "5", *MC], r"--gain.*does not apply"),
    (["simulate", "--observer", "batista-so3", "--x2-0", "1,2,3", *MC], r"does not apply"),
    (["simulate", "--observer", "batista-ges", "--window-start", "50", "--duration", "10", "--runs", "1"], r"window"),
    (["simulate", "--observer", "batista-ges", "--latitude", "95", *MC], r"argument --latitude"),
    (["simulate", "--observer", "mahony", "--hold", "zoh", *MC], r"--hold does not apply to mahony"),
    (["simulate", "--observer", "robust", "--latitude", "45", *MC], r"--latitude does not apply to robust"),
    (["simulate", "--observer", "vqf", "--r0-euler", "1,2,3", *MC], r"--r0-euler does not apply to vqf"),
    (["simulate", "--observer", "batista-ges", "--acc-noise", "0.1", *MC], r"--acc-noise does not apply"),
    (["simulate", "--observer", "complementary", "--gains", "{d}/keep.json", *MC], r"--gains does not apply"),
    (["simulate", "--observer", "robust", "--gains", "{d}/keep.json", *MC], r"keep\.json"),
    (["simulate", "--observer", "madgwick", "--acc-noise", "-1", *MC], r"argument --acc-noise"),
    (["simulate", "--observer", "madgwick", "--window-start", "9", "--duration", "3", "--runs", "1"], r"window"),
    # tune / evaluate
    (["tune", "--experiment", "batista-so3", "--out", "{d}/folder", "--steps", "1"], r"--out .*folder: is a folder"),
    (["tune", "--experiment", "batista-so3", "--out", "/proc/g.json", "--steps", "1"], r"--out /proc/g\.json"),
    (["tune", "--experiment", "batista-so3", "--steps", "-1"], r"argument --steps"),
    (["tune", "--experiment", "batista-so3", "--refine-schedule", "-5"], r"argument --refine-schedule"),
    (["tune", "--experiment", "batista-so3", "--lr", "0"], r"argument --lr"),
    (["tune", "--experiment", "batista-so3", "--objective", "nope"], r"argument --objective: invalid choice"),
    (["tune", "--experiment", "batista-so3", "--optimizer", "sgd"], r"argument --optimizer: invalid choice"),
    (["tune", "--experiment", "batista-so3", "--optimizer", "lbfgs"], r"--optimizer lbfgs needs .*--objective varfree"),
    (["tune", "--experiment", "nope"], r"argument --experiment"),
    (["tune", "--experiment", "batista-so3", "--steps", "1", "--out", "{d}/keep.json"], r"not a gains file"),
    (["tune", "--experiment", "batista-so3", "--steps", "1", "--out", "{d}/absent.json", "--resume"], r"no gains"),
    (["evaluate", "--experiment", "batista-so3", "--gains", "{d}/missing.json", "--json", "{d}/keep.json"], r"found"),
    (["evaluate", "--experiment", "batista-so3", "--gains", "{d}/broken.json", "--json", "{d}/keep.json"], r"broken"),
    (
        ["evaluate", "--experiment", "batista-so3", "--gains", "{d}/robust_ok.json", "--json", "{d}/keep.json"],
        r"robust",
    ),
    (["evaluate", "--experiment", "batista-so3", "--gains", "{d}/not_gains.json", "--json", "{d}/keep.json"], r"gains"),
    (["evaluate", "--experiment", "batista-so3", "--json", "/proc/e.json"], r"--json /proc/e\.json"),
    # broad / broad-tune
    (["broad", "--data-dir", "{d}/nowhere"], r"nowhere.*not found|not found.*nowhere"),
    (["broad", "--data-dir", "{d}/trials_ok/01_ok.hdf5"], r"01_ok\.hdf5: is a file; give the folder"),
    (["broad", "--data-dir", "{d}/trials_empty"], r"trials_empty"),
    (["broad", "--data-dir", "{d}/trials_no_mag"], r"imu_mag"),
    (["broad", "--data-dir", "{d}/trials_rate0"], r"sampling_rate"),
    (["broad", "--data-dir", "{d}/trials_truncated"], r"truncated|read"),
    (["broad", "--data-dir", "{d}/trials_ok", "--trials", "99_nope"], r"99_nope"),
    (["broad", "--data-dir", "{d}/trials_ok", "--gains", "{d}/robust_nan.json"], r"tau_acc"),
    (["broad", "--data-dir", "{d}/trials_ok", "--gains", "{d}/robust_negative.json"], r"tau_acc"),
    (["broad", "--data-dir", "{d}/trials_ok", "--gains", "{d}/broken.json"], r"broken\.json"),
    (["broad", "--data-dir", "{d}/trials_ok", "--gains", "{d}/so3_study.json"], r"batista-so3|so3_study"),
    (["broad", "--data-dir", "{d}/trials_ok", "--gains", "{d}/missing.json"], r"missing\.json"),
    (["broad", "--data-dir", "{d}/trials_ok", "--json", "/proc/b.json"], r"--json /proc/b\.json"),
    (["broad", "--data-dir", "{d}/trials_ok", "--truth-frame", "NED"], r"--truth-frame: for --logs \(BROAD trials"),
    (["reproduce", "batista-ges", *MC, "--json", "{d}/robust_ok.json"], r"robust_ok\.json: is a gains file \(a fit"),
    (["broad", "--logs", "{d}/log.csv", "--trials", "01"], r"--trials picks trials of --data-dir; with --logs, list"),
    (["broad", "--logs", "{d}/log.csv"], r"log\.csv: no ground truth \(columns quat_w"),
    (["broad", "--logs", "{d}/missing.csv"], r"log .*missing\.csv: not found"),
    (["broad", "--logs", "{d}/log.csv", "--data-dir", "{d}/trials_ok"], r"not allowed with argument"),
    (["broad"], r"one of the arguments --data-dir --logs is required"),
    (["broad", "--logs", "{d}/log.csv", "--json", "{d}/log.csv"], r"--json .*log\.csv: is the --logs .* file"),
    (["broad-tune", "--logs", "{d}/log.csv", "--time-unit", "ms", "--out", "{d}/g.json"], r"no ground truth"),
    (["broad-tune", "--data-dir", "{d}/trials_ok", "--steps", "-1"], r"argument --steps"),
    (["broad-tune", "--data-dir", "{d}/trials_ok", "--out", "/proc/g.json"], r"--out /proc/g\.json"),
    (["broad-tune", "--data-dir", "{d}/trials_empty", "--out", "{d}/g.json"], r"trials_empty"),
    (
        ["broad-tune", "--data-dir", "{d}/trials_ok", "--init-gains", "{d}/broken.json", "--out", "{d}/g.json"],
        r"broken",
    ),
    # excitation
    (["excitation", "--log", "{d}/missing.csv"], r"--log .*missing\.csv: not found"),
    (["excitation", "--log", "{d}/log.csv"], r"--mag-ref"),
    (["excitation", "--log", "{d}/log.csv", "--mag-ref", "1,2"], r"argument --mag-ref"),
    (["excitation", "--log", "{d}/log.csv", "--mag-ref", "20,0,-40", "--window", "0"], r"argument --window"),
    (["excitation", "--log", "{d}/log.csv", "--mag-ref", "20,0,-40", "--window", "500"], r"longer than the log"),
    (["excitation", "--scenario", "rotating", "--json", "/proc/x.json"], r"--json /proc/x\.json"),
    (["excitation", "--scenario", "rotating", "--plot", "{d}/folder"], r"--plot .*folder"),
    (["excitation", "--scenario", "nope"], r"argument --scenario"),
    (["excitation", "--scenario", "rotating", "--columns", "t=time"], r"--columns does not apply to a scenario"),
    (["excitation", "--scenario", "rotating", "--time-unit", "ms"], r"--time-unit does not apply to a scenario"),
    (["excitation", "--log", "{d}/log.csv", "--mag-ref", "20,0,-40", "--columns", "acc_x=ax"], r"column 'ax' \(given"),
    (
        ["excitation", "--scenario", "rotating", "--plot", "{d}/fig.txt"],
        r"--plot .*fig\.txt: unknown figure format 'txt'",
    ),
    # seeds, empty paths, figure formats: refused before any work
    (["reproduce", "batista-so3", *MC, "--seed", "99999999999999999999"], r"argument --seed: must fit in 64 bits"),
    (["tune", "--experiment", "batista-so3", "--seed", "1.5"], r"argument --seed: must be an integer"),
    (["reproduce", "batista-so3", *MC, "--json", ""], r"--json: empty path"),
    (["reproduce", "batista-so3", *MC, "--plot", "{d}/fig.txt"], r"--plot .*fig\.txt: unknown figure format"),
    # output extensions, observer specs, folders as files, degenerate references, absurd counts
    (["filter", "--log", "{d}/log.csv", "--out", "{d}/est.json"], r"--out .*est\.json: unknown extension '\.json'"),
    (["filter", "--log", "{d}/log.csv", "--observer", ":x", "--out", "{d}/keep.csv"], r"--observer ':x'.*module:attr"),
    (["filter", "--log", "{d}/log.csv", "--gains", "{d}/folder", "--out", "{d}/keep.csv"], r"folder.*is a folder"),
    (["excitation", "--log", "{d}/log.csv", "--mag-ref", "0,0,0"], r"--mag-ref: .*non-zero"),
    (["excitation", "--log", "{d}/log.csv", "--mag-ref", "1,0,0", "--dt", "0.1"], r"--dt does not apply to a log"),
    (["excitation", "--scenario", "rotating", "--mag-ref", "1,0,0"], r"--mag-ref does not apply to a scenario"),
    (["excitation", "--scenario", "rotating", "--dt", "100"], r"dt \(100 s\) must be shorter than the duration"),
    (["excitation", "--scenario", "rotating", "--dt", "0.5", "--window", "0.1"], r"shorter than the sample interval"),
    (["reproduce", "batista-so3", "--runs", "1" + "0" * 20], r"argument --runs: must be <= 4294967296"),
    (["filter", "--log", "{d}/log.csv", "--out", "{d}/log.csv"], r"--out .*log\.csv: is the --log file"),
    (["filter", "--log", "{d}/log.csv", "--gains", "", "--out", "{d}/keep.csv"], r"empty path"),
    (
        ["tune", "--experiment", "batista-so3", "--steps", "1", "--out", "{d}/g.txt"],
        r"--out .*g\.txt: unknown extension",
    ),
    (["reproduce", "batista-so3", *MC, "--json", "{d}/r.csv"], r"--json .*r\.csv: unknown extension '\.csv'"),
    (["filter", "--log", "{d}/log.csv", "--out", "{d}/../{d.name}/log.csv"], r"is the --log file"),
    (["excitation", "--log", "{d}/log.csv", "--mag-ref", "1,0,0", "--json", "{d}/log.csv"], r"is the --log file"),
    (
        ["broad-tune", "--data-dir", "{d}/trials_ok", "--init-gains", "{d}/keep.json", "--out", "{d}/keep.json"],
        r"the --init-gains file",
    ),
    # malformed gains files and BROAD folders, absurd step counts, inputs that the output would overwrite
    (["filter", "--log", "{d}/log.csv", "--gains", "{d}/robust_novalue.json", "--out", "{d}/keep.csv"], r"'value'"),
    (["broad", "--data-dir", "{d}/trials_badinfo", "--trials", "01"], r"trials\.json: not BROAD's trials\.json"),
    (["broad", "--data-dir", "{d}/trials_info", "--json", "{d}/trials_info/trials.json"], r"--data-dir folder"),
    (["broad", "--data-dir", "{d}/trials_ok", "--trials", ""], r"no trial named"),
    (["simulate", "--observer", "batista-ges", *MC, "--dt", "1e-300"], r"steps per run"),
    # the reference's square enters the gains: zero, underflowing and overflowing vectors are named by their flag
    (["simulate", "--observer", "batista-ges", *MC, "--reference=0,0,0"], r"error: reference must be a non-zero"),
    (["simulate", "--observer", "batista-so3", *MC, "--reference=1e-300,0,0"], r"error: reference must be a non-zero"),
    (["simulate", "--observer", "batista-ges", *MC, "--reference=1e300,1,0"], r"error: reference must be a non-zero"),
    (["simulate", "--observer", "batista-ges", *MC, "--reference=1,2,3,"], r"--reference: expected 3 comma-separated"),
    (["evaluate", "--experiment", "batista-so3", "--runs", "1", "--duration", "1e300"], r"steps per run"),
    (["excitation", "--scenario", "rotating", "--duration", "1e300"], r"steps per run"),
    (["tune", "--experiment", "batista-so3", "--val-runs", "1" + "0" * 20], r"argument --val-runs: must be <="),
    (["filter", "--log", "{d}/missing.csv", "--out", "{d}/new_folder/a.csv"], r"not found"),
    (["broad-tune", "--data-dir", "{d}/trials_ok", "--steps", "1" + "0" * 24], r"argument --steps: must be <="),
    (["reproduce", "batista-so3", *MC, "--json", "{d}/empty_runs.json", "--resume"], r"not a runs file of jaxatt"),
    (["reproduce", "batista-so3", *MC, "--json", "{d}/runs_folder.json"], r"runs file saved beside it.*is a folder"),
    (["reproduce", "batista-so3", *MC, "--json", "/dev/null", "--resume"], r"--resume needs --json of a file"),
    (
        ["tune", "--experiment", "batista-so3", "--steps", "1", "--out", "{d}/partial_folder.json"],
        r"out .*partial_folder\.json\.partial\.json: is a folder",
    ),
    # a study's gains file with a value its theorem refuses: named by the file, the array on the same line
    (["evaluate", "--experiment", "batista-so3", "--gains", "{d}/so3_negative.json"], r"so3_negative.*alpha1.*-1"),
    # a BROAD file read with the checks every trial gets (a truth of norm 2 was accepted), a boolean rate
    (["broad", "--data-dir", "{d}/trials_norm2"], r"01_norm2: quat_true\[0\] has norm 2"),
    (["broad", "--data-dir", "{d}/trials_rate_bool"], r"sampling_rate attribute must be one number"),
    # an initial R^ of rank < 3: R_f's start, its nearest rotation, is not defined (it silently became the truth)
    (["simulate", "--observer", "batista-ges", *MC, "--r0", "0,0,0,0,0,0,0,0,0"], r"r_hat_0 must have rank 3"),
    # your own observer on the simulated IMU is Python's jaxatt.monte_carlo (it was "invalid choice")
    (
        ["simulate", "--observer", "my_filters:OBSERVER", "--runs", "2"],
        r"--observer: my_filters:OBSERVER: .*monte_carlo",
    ),
    (["--nonsense", "broad", "--data-dir", "{d}/trials_ok"], r"^jaxatt: error: .* --nonsense \(see jaxatt --help\)"),
    # an unknown flag is said by the command, pointing to its own help
    (
        ["broad", "--data-dir", "{d}/trials_ok", "--nonsense"],
        r"^jaxatt broad: error: .* --nonsense \(see jaxatt broad --help\)",
    ),
    # continue the fit in --out, or replace it: not both
    (["tune", "--experiment", "batista-so3", "--out", "{d}/keep.json", "--resume", "--overwrite"], r"not allowed"),
    (["broad-tune", "--data-dir", "{d}/trials_ok", "--out", "{d}/keep.json", "--resume", "--overwrite"], r"--resume"),
]


@pytest.mark.parametrize("argv, match", BAD_INPUT, ids=[" ".join(a[:4]) for a, _ in BAD_INPUT])
def test_bad_input_is_one_line_exit_2_and_touches_no_output(files, capsys, argv, match):
    for name in ("keep.json", "keep.csv"):
        (files / name).write_bytes(KEEP)
    before = sorted(p.name for p in files.iterdir())
    rc, err = _run(argv, files, capsys)
    assert rc == 2, (rc, err)
    assert len(err) == 1, err
    assert re.search(match, err[0]), err[0]
    assert "Traceback" not in err[0]
    for name in ("keep.json", "keep.csv"):
        assert (files / name).read_bytes() == KEEP, f"{name} was changed"
    assert sorted(p.name for p in files.iterdir()) == before, "a file was left behind"


# ------------------------------------------------------------------------------------------------------------
# Non-finite results: exit 1 naming where they first appeared
# ------------------------------------------------------------------------------------------------------------
NON_FINITE = [
    (
        ["simulate", "--observer", "batista-ges", "--runs", "1", "--duration", "3", "--quiet", "--rate-scale", "1e6"],
        r"run 0.*t = ",
    ),
    (
        ["simulate", "--observer", "batista-ges", "--runs", "1", "--duration", "3", "--quiet", "--noise-scale", "1e30"],
        r"run 0.*t = ",
    ),
    (  # an AHRS filter's Monte Carlo (the program of test_cli's mahony simulate: the same runs, length and rate)
        ["simulate", "--observer", "mahony", "--runs", "5", "--duration", "3", "--dt", "0.02", "--quiet"]
        + ["--noise-scale", "1e300"],
        r"mahony: run 0.*t = ",
    ),
    (["filter", "--log", "{d}/huge_gyr.csv", "--observer", "madgwick", "--out", "{d}/est.csv"], r"sample \d+ \(t = "),
    (["filter", "--log", "{d}/huge_gyr.csv", "--observer", "robust", "--out", "{d}/est.csv"], r"sample \d+ \(t = "),
]


@pytest.mark.parametrize("argv, match", NON_FINITE, ids=[" ".join(a[:3]) + " " + a[-2] for a, _ in NON_FINITE])
def test_non_finite_result_exits_1_saying_where(files, capsys, argv, match):
    rc, err = _run(argv, files, capsys)
    assert rc == 1, (rc, err)
    warned = [line for line in err if line.startswith("jaxatt: warning: ")]
    err = [line for line in err if line not in warned]
    assert len(err) == 1 and err[0].startswith("jaxatt: error: non-finite result"), err
    assert re.search(match, err[0]), err[0]
    if "huge_gyr" in argv[2]:  # 1e300 rad/s: the units warning comes first, on its own line
        assert any("gyr reaches" in w and "deg/s" in w for w in warned), warned


def test_an_output_that_is_a_device_or_fifo_is_written_into_not_replaced(tmp_path):
    """``--out /dev/null`` must keep /dev/null a device (as root a rename onto it would replace it with a file):
    a path that exists and is neither a file nor a folder passes the output check and is written in place.
    Checked on a FIFO (same code path, harmless if it regressed)."""
    import stat
    import threading

    from jaxatt import io

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    assert io.check_output_path(str(fifo), "--out") == fifo
    io.write_json(fifo, {"a": 1})
    reader.join(timeout=10)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert json.loads(got[0]) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe"]  # no temporary left behind


def test_broad_trial_without_ground_truth_is_said_not_failed(files, tmp_path, capsys):
    """NaN ground truth is BROAD's documented 'no reference here': a trial with none is NaN, said, and left out of
    the means (exit 0); a trial with truth is scored. With no trial to score, there is no result: exit 2 before
    running (it printed a table of NaN and exited 0)."""
    import shutil

    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for folder in ("trials_no_truth", "trials_ok"):
        for f in (files / folder).glob("*.hdf5"):
            shutil.copy(f, mixed / f.name)
    argv = ["broad", "--observer", "madgwick", "--json", str(tmp_path / "b.json")]
    assert cli.main([*argv, "--data-dir", str(mixed)]) == 0
    assert "01_no_truth has no ground truth" in capsys.readouterr().out
    d = json.loads((tmp_path / "b.json").read_text())
    assert np.isnan(d["trials"]["01_no_truth"]["total_rmse_deg"]) and d["groups"]["all"]["n_trials"] == 1
    (tmp_path / "b.json").unlink()
    assert cli.main([*argv, "--data-dir", str(files / "trials_no_truth")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "jaxatt: error: no trial has a scored sample (movement with a finite ground truth): 01_no_truth has no "
        "ground truth to score against"
    )
    assert not (tmp_path / "b.json").exists()
    trials = jaxatt.data.broad.load(files / "trials_no_truth") + jaxatt.data.broad.load(files / "trials_ok")
    with pytest.warns(UserWarning, match=r"no scored sample .* in trial 01_no_truth: its metrics are NaN"):
        score = jaxatt.broad_score("madgwick", None, trials)
    assert np.isnan(score.trials["01_no_truth"].total_rmse_deg)
    assert np.isfinite(score.trials["01_ok"].total_rmse_deg) and score.groups["all"].n_trials == 1


# ------------------------------------------------------------------------------------------------------------
# The public API: one-line ValueError naming the argument
# ------------------------------------------------------------------------------------------------------------
def _imu(n=100):
    t, gyr, acc, mag = _log_rows(n)
    return gyr, acc, mag


API_BAD = [
    (lambda g, a, m: jaxatt.filter("madgwick", g, a, m, dt=float("nan")), r"dt must be a finite positive"),
    (lambda g, a, m: jaxatt.filter("madgwick", g, a, m, dt=0.0), r"dt must be a finite positive"),
    (lambda g, a, m: jaxatt.filter("madgwick", g, a, m, dt=-0.01), r"dt must be a finite positive"),
    (
        lambda g, a, m: jaxatt.filter("madgwick", g, a, m, dt=1e-300, dtype="float32"),
        r"sample period \(1e-300 s\) is not a positive number in float32",
    ),
    (lambda g, a, m: jaxatt.filter("madgwick", [0.0, 0.0, 0.0], a, m, dt=0.01), r"gyr must have shape \(T, 3\)"),
    (lambda g, a, m: jaxatt.filter("madgwick", g[:10], a, m, dt=0.01), r"acc has 100 samples, gyr has 10"),
    (lambda g, a, m: jaxatt.filter("madgwick", g, a, m, dt=0.01, params={"beta": np.nan}), r"beta"),
    (lambda g, a, m: jaxatt.filter("madgwick", g, a, m, dt=0.01, params={"gamma": 1.0}), r"no field 'gamma'"),
    # a gain shown in the message stays on the message's line (numpy prints a matrix over several lines)
    (lambda g, a, m: jaxatt.filter("mekf", g, a, m, dt=0.01, params={"b_hat_0": np.full((2, 3), np.nan)}), r"\[\["),
    (lambda g, a, m: jaxatt.filter("mekf", g, a, m, dt=0.01, params={"r_acc": np.eye(3) * np.nan}), r"r_acc.*nan"),
    (lambda g, a, m: jaxatt.filter("madgwick", g, a, m, dt=0.01, params="/nonexistent.json"), r"nonexistent"),
    (lambda g, a, m: jaxatt.monte_carlo("madgwick", {"beta": np.nan}, runs=1, duration=1.0), r"beta"),
    (lambda g, a, m: jaxatt.monte_carlo("madgwick", runs=0, duration=1.0), r"runs must be >= 1"),
    (lambda g, a, m: jaxatt.fit("madgwick", None, "nonsense"), r"unknown study 'nonsense'"),
    (lambda g, a, m: jaxatt.fit("madgwick", None, [1, 2]), r"Trial"),
    (  # another study's Config (an AttributeError deep inside)
        lambda g, a, m: jaxatt.studies.reproduce(
            jaxatt.studies.get("batista-ges"), jaxatt.studies.get("batista-so3").config(), runs=1
        ),
        r"cfg must be the batista-ges study's Config .*got jaxatt.studies.batista_so3.Config",
    ),
    (lambda g, a, m: jaxatt.broad_score("madgwick", None, "/nonexistent"), r"Trial"),
    # the lower-level montecarlo functions of the README
    (lambda g, a, m: montecarlo.simulate_log("rotating", duration=1.0, dt=0.01), r"scenario must be a simulated .*str"),
    (lambda g, a, m: montecarlo.run(*_madgwick(), None), r"samples must be a jaxatt.types.ImuSample"),
    (
        lambda g, a, m: montecarlo.run(_madgwick()[0], {"x": 1.0}, _log(g, a, m)),
        r"observer 'madgwick': init or step failed on these params and samples: AttributeError",
    ),
    (
        lambda g, a, m: montecarlo.run(*_madgwick(), _log(g, a, m)._replace(gyr=g[:10])),
        r"samples.t and samples.gyr must have one row per sample: t has shape \(100,\), gyr \(10, 3\)",
    ),
    # a name where an Observer goes, complex readings, a dt array (printed over many lines), a negative run
    (lambda g, a, m: montecarlo.run("madgwick", None, _log(g, a, m)), r"observer must be a jaxatt.Observer.*get\("),
    (
        lambda g, a, m: montecarlo.run(*_madgwick(), _log(g + 0j, a, m)),
        r"samples.gyr must be real numbers, got dtype c",
    ),
    (lambda g, a, m: montecarlo.run(*_madgwick(), _log(g, a, m), dt=np.full(99, 0.01)), r"dt must be a number of sec"),
    (
        lambda g, a, m: montecarlo.simulate_log(jaxatt.ahrs_scenario(), duration=1.0, dt=0.01, run_index=-1),
        r"run_index must be",
    ),
    (
        lambda g, a, m: montecarlo.monte_carlo(
            jaxatt.ahrs_scenario(), "madgwick", None, runs=1, duration=1.0, dt=0.01, errors_fn=jaxatt.api.ahrs_errors
        ),
        r"observer must be a jaxatt.Observer",
    ),
    # a scenario built by hand: a NaN noise level (every magnetometer sample NaN: silently "no magnetometer"), a
    # start that is not a rotation, a negative noise level, a field of the wrong shape (a JAX traceback)
    (lambda g, a, m: montecarlo.simulate_log(_ges(vec_noise_std=np.nan), **SHORT), r"vec_noise_std must be finite"),
    (lambda g, a, m: montecarlo.simulate_log(_ges(r0=2 * np.eye(3)), **SHORT), r"r0 must be a rotation matrix"),
    (lambda g, a, m: montecarlo.simulate_log(_ges(gyro_arw=-1.0), **SHORT), r"gyro_arw must be >= 0"),
    (
        lambda g, a, m: montecarlo.simulate_log(_ges(ref_nav=np.ones(2)), **SHORT),
        r"scenario ImuScenario: its first simulated step failed \(check the shapes",
    ),
]
SHORT = dict(duration=0.1, dt=0.01)


def _ges(**change):
    return jaxatt.studies.get("batista-ges").setup(duration=1.0).scenario._replace(**change)


def _madgwick():
    e = jaxatt.observers.registry.get("madgwick")
    return jaxatt.observers.registry.recorded_observer(e), e.default_params()


def _log(g, a, m):
    return jaxatt.ImuSample(np.arange(len(g)) * 0.01, g, a, m)


@pytest.mark.parametrize("call, match", API_BAD)
def test_public_api_bad_input_is_one_line(call, match):
    with pytest.raises(ValueError, match=match) as e:
        call(*_imu())
    assert "\n" not in str(e.value)


def test_api_takes_lists_and_partial_gains():
    g, a, m = _imu()
    ref = jaxatt.filter("madgwick", g, a, m, dt=0.01, params={"beta": 0.2})
    lists = jaxatt.filter("madgwick", g.tolist(), a.tolist(), m.tolist(), dt=0.01, params={"beta": 0.2})
    np.testing.assert_array_equal(lists.quat, ref.quat)
    default = jaxatt.filter("madgwick", g, a, m, dt=0.01)
    assert not np.allclose(default.quat, ref.quat)  # the dict's beta was used


def test_montecarlo_run_refuses_non_finite_params():
    from jaxatt import montecarlo
    from jaxatt.observers import registry
    from jaxatt.types import ImuSample

    entry = registry.get("madgwick")
    g, a, m = _imu()
    samples = ImuSample(np.arange(100) * 0.01, g, a, m)
    with pytest.raises(ValueError, match="not finite|beta"):
        montecarlo.run(entry.make(), entry.default_params()._replace(beta=np.nan), samples, 0.01)


# ------------------------------------------------------------------------------------------------------------
# Subprocesses: what a user at a terminal sees (no traceback; --debug shows it)
# ------------------------------------------------------------------------------------------------------------
def _cli(*args, **kw):
    env = dict(os.environ, PYTHONUNBUFFERED="1", **kw.pop("env", {}))
    return subprocess.Popen(
        [sys.executable, "-m", "jaxatt", *args],
        cwd=kw.pop("cwd", None),
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def test_subprocess_bad_input_has_no_traceback_and_debug_shows_it(files):
    p = _cli("reproduce", "batista-ges", "--runs", "1", "--duration", "5", "--json", "/proc/x.json")
    out, err = p.communicate(timeout=120)
    assert p.returncode == 2 and err.strip().splitlines() == [err.strip()], (
        err
    )  # one line, nothing computed or printed before it
    assert "Traceback" not in err and "/proc/x.json" in err
    p = _cli(
        "simulate", "--observer", "batista-ges", "--runs", "1", "--duration", "3", "--quiet", "--rate-scale", "1e6"
    )
    out, err = p.communicate(timeout=120)
    assert p.returncode == 1 and len(err.strip().splitlines()) == 1, err  # no warnings before the line
    assert "first non-finite at t = " in err
    p = _cli("filter", "--log", str(files / "missing.csv"), "--out", str(files / "e.csv"), "--debug")
    out, err = p.communicate(timeout=120)
    assert p.returncode != 0 and "Traceback" in err


def _wait_for(p, pattern, timeout=120.0):
    """Read p's stderr (raw, as it arrives) until it matches ``pattern``; returns what was read."""
    seen = b""
    fd = p.stderr.fileno()
    t0 = time.time()
    while time.time() - t0 < timeout:
        ready, _, _ = select.select([fd], [], [], 0.1)
        if ready:
            chunk = os.read(fd, 65536)
            if not chunk:
                break
            seen += chunk
            if re.search(pattern, seen.decode(errors="replace")):
                return seen.decode(errors="replace")
    raise AssertionError(f"never saw {pattern!r}; stderr so far: {seen[-500:]!r}")


SO3 = ["reproduce", "batista-so3", "--runs", "6", "--chunk", "1", "--duration", "20", "--seed", "3"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The reference: the same Monte Carlo run once, uninterrupted, in this process."""
    d = tmp_path_factory.mktemp("uninterrupted")
    assert cli.main([*SO3, "--quiet", "--json", str(d / "ref.json")]) == 0
    return d / "ref.json"


@pytest.mark.parametrize("moment", ["while importing", "while compiling", "after the first chunk"])
def test_sigint_exits_130_and_keeps_a_finished_result(tmp_path, uninterrupted, moment):
    out = tmp_path / "mc.json"
    out.write_bytes(uninterrupted.read_bytes())  # a finished result at --json
    # after the first chunk: 60 runs of one chunk each, so the rest cannot finish before the signal lands on a
    # loaded machine (with 6, a descheduled test let the run complete and rewrite the file: a race, not the property)
    argv = [*SO3[:3], "60", *SO3[4:]] if moment == "after the first chunk" else SO3
    p = _cli(*argv, "--progress", "--json", str(out))
    if moment == "while importing":
        time.sleep(0.3)
    elif moment == "while compiling":
        time.sleep(3.0)
    else:
        _wait_for(p, r"runs [1-9]\d*/60")
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, (p.returncode, err[-800:])
    assert "Traceback" not in err and "Segmentation" not in err
    assert out.read_bytes() == uninterrupted.read_bytes(), "a finished result was replaced"


def test_sigint_inside_an_atomic_npz_write_lands_after_it(tmp_path):
    """The CLI's Ctrl-C handler defers an interrupt that arrives inside ``io.write_atomic``: raised inside
    ``np.savez`` it left a half-closed ZipFile whose ``__del__`` printed a traceback at exit (a CI failure)."""
    from jaxatt import io

    arrays = {f"a{i}": np.arange(1000.0) + i for i in range(50)}
    sent = []

    def write(f):
        np.savez(f, **{k: v for k, v in list(arrays.items())[:25]})
        if not sent:
            sent.append(True)
            os.kill(os.getpid(), signal.SIGINT)  # delivered at the next bytecode, inside the write
        f.write(b"")

    previous = signal.signal(signal.SIGINT, cli._on_sigint)
    try:
        with pytest.raises(KeyboardInterrupt):
            io.write_atomic(tmp_path / "runs.npz", write, binary=True)
            time.sleep(2.0)  # the re-sent signal lands here, after the write
    finally:
        signal.signal(signal.SIGINT, previous)
        cli._INTERRUPTED.clear()
        cli._DEFERRED.clear()
    with np.load(tmp_path / "runs.npz") as z:
        assert sorted(z.files) == sorted(list(arrays)[:25])


def test_sigkill_then_resume_equals_the_uninterrupted_run(tmp_path, uninterrupted, capsys):
    out = tmp_path / "mc.json"
    runs = tmp_path / "mc.json.runs.npz"
    # one CPU device, as the in-process runs: split over another number of devices the numbers agree only to
    # rounding (1e-15), and this test asks for the same bits
    p = _cli(*SO3, "--progress", "--json", str(out), env={"JAXATT_CPU_DEVICES": "1"})
    t0 = time.time()
    while not (runs.exists() and out.exists()) and p.poll() is None and time.time() - t0 < 120:
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.communicate(timeout=60)
    assert runs.exists(), "no runs were saved before the kill"
    saved = json.loads(out.read_text())
    assert saved["complete"] is False and 1 <= saved["runs_done"] < 6
    assert cli.main([*SO3, "--quiet", "--json", str(out), "--resume"]) == 0
    got, ref = json.loads(out.read_text()), json.loads(uninterrupted.read_text())
    assert got["complete"] and got["runs_done"] == 6
    for name, m in ref["metrics"].items():
        np.testing.assert_array_equal(got["metrics"][name]["per_run"], m["per_run"], err_msg=name)


def test_resume_with_plot_added_is_refused_before_computing(tmp_path):
    """The NLIO studies keep finer traces for --plot: runs saved without it cannot be resumed with it (their
    averaged curves would mix spacings); refused at the start, naming --plot."""
    from jaxatt import studies

    study = studies.get("nlio-case1")
    cfg = study.config(duration=2.0)
    obs = dict(list(study.observers(cfg).items())[:1])  # one observer: the cheapest runs file
    out = tmp_path / "r.json"
    studies.reproduce(study, cfg, runs=1, json_path=str(out), quiet=True, observers=obs)
    with pytest.raises(ValueError, match=r"--resume: .*another set-up.*--plot"):
        studies.reproduce(
            study,
            cfg,
            runs=1,
            json_path=str(out),
            quiet=True,
            observers=obs,
            plot_path=str(tmp_path / "p.png"),
            resume=True,
        )
    assert not (tmp_path / "p.png").exists()


def test_an_interrupted_command_says_what_it_saved(tmp_path, monkeypatch, capsys):
    """The CLI's last word on an interrupt names the files the command wrote, or says it wrote none (an interrupt
    before the first chunk of a Monte Carlo used to claim that finished work was saved)."""
    from jaxatt import io

    out = tmp_path / "partial.json"

    def command(args, write=True):
        if write:
            io.write_json(out, {"runs_done": 1})
        raise KeyboardInterrupt

    for write, said in ((False, "nothing had finished, so nothing was saved"), (True, f"saved so far: {out}")):
        monkeypatch.setattr(io, "WRITTEN", [])
        monkeypatch.setitem(cli._COMMANDS, "reproduce", lambda args, w=write: command(args, w))
        assert cli.main(["reproduce", "batista-ges", "--runs", "2"]) == 130
        assert f"jaxatt: interrupted ({said})" in capsys.readouterr().err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_sigint_without_an_earlier_result_writes_the_partial_json(tmp_path, sig):
    """Ctrl-C, or SIGTERM (kill, a batch scheduler's time limit), after the first chunk: the partial result is
    written, the status is 128 + the signal (130, 143), and no temporary file is left beside the outputs."""
    out = tmp_path / "mc.json"
    # 60 one-run chunks of a few ms each: the signal sent after the first few lands well before the last
    # (with 6 chunks and a warm compile cache the last chunk could finish before the signal arrived)
    p = _cli(*SO3[:2], "--runs", "60", *SO3[4:], "--progress", "--json", str(out))
    _wait_for(p, r"runs [1-9]/60")
    p.send_signal(sig)
    stdout, err = p.communicate(timeout=120)
    assert p.returncode == 128 + sig and "Traceback" not in err, (p.returncode, err[-800:])
    d = json.loads(out.read_text())
    assert d["complete"] is False and 1 <= d["runs_done"] < 60
    assert "rerun with --resume" in stdout
    assert not list(tmp_path.glob("*.tmp")), sorted(x.name for x in tmp_path.iterdir())


def test_sigint_in_an_overwriting_tune_keeps_the_finished_gains_file(tmp_path):
    gains = tmp_path / "g.json"
    shipped = json.loads((REPO / "jaxatt" / "data" / "gains" / "batista-so3.json").read_text())
    gains.write_text(json.dumps({**shipped, "status": "done"}))  # a finished fit
    finished = gains.read_bytes()
    # the complementary study: the same command, a gradient that compiles in a fraction of batista-so3's time
    tune = ["tune", "--experiment", "complementary", "--train-runs", "2", "--val-runs", "0", "--duration", "6"]
    p = _cli(*tune, "--steps", "500", "--out", str(gains), "--overwrite", "--progress")
    _wait_for(p, r"step +1/500")
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130 and "Traceback" not in err, err[-800:]
    assert gains.read_bytes() == finished, "the finished gains file was replaced by an unfinished fit"
    partial = json.loads((tmp_path / "g.json.partial.json").read_text())
    assert partial["status"] == "interrupted"
    # the study's default k_i = 0 (no bias integrator) is a switched-off term: the fit keeps it off
    assert partial["gains"]["k_i"]["value"] == 0.0 and partial["settings"]["config"]["k_i"] == 0.0


def test_overwriting_fit_lives_in_partial_until_it_finishes_and_resume_continues_it(files, tmp_path):
    trials = jaxatt.data.broad.load(files / "trials_ok")
    out = tmp_path / "g.json"
    first = jaxatt.fit("madgwick", None, trials, steps=1, out=str(out))
    assert first.status == "done"
    finished = out.read_bytes()

    def interrupt_at_step_2(info):
        if info.get("step") == 2:
            raise KeyboardInterrupt

    res = jaxatt.fit(
        "madgwick", None, trials, steps=4, lr=0.1, out=str(out), overwrite=True, callback=interrupt_at_step_2
    )
    partial = jaxatt.fitting.fitter.partial_path(out)
    assert res.status == "interrupted" and res.path == str(partial)
    assert out.read_bytes() == finished
    # a damaged resume state (hand-edited, another version) is one line, not a KeyError / TypeError traceback or
    # a restart from step -5
    for damage, match in (
        ({"theta": {}}, r"damaged \(theta holds \[\], not the gains"),
        ({"opt_state": None}, r"damaged \(the saved optimizer state does not match"),
        ({"best_theta": "garbage"}, r"damaged \(best_theta holds str"),
        ({"step": -5}, r"damaged \(step -5 is not a number of steps\)"),
        ({"step": 1}, r"damaged \(step 1 is not the last step of its history \(2\)\)"),
        ({"sampler": None}, r"damaged \("),
    ):
        saved = json.loads(partial.read_text())
        saved["resume"].update(damage)
        broken = tmp_path / "broken.json"
        broken.write_text(json.dumps(saved))
        with pytest.raises(ValueError, match=match) as e:
            jaxatt.fit("madgwick", None, trials, steps=4, lr=0.1, out=str(broken), resume=True)
        assert "\n" not in str(e.value) and f"resume: the saved fit state in {broken} is damaged" in str(e.value)
    # the arithmetic is a setting of the fit: resuming a float64 fit in float32 mixed the two in one history
    with pytest.raises(
        ValueError, match=r"resume: setting 'dtype' differs from the saved fit \('float64' vs 'float32'\)"
    ):
        jaxatt.fit("madgwick", None, trials, steps=4, lr=0.1, out=str(out), resume=True, dtype="float32")
    resumed = jaxatt.fit("madgwick", None, trials, steps=4, lr=0.1, out=str(out), resume=True)
    assert resumed.status == "done" and resumed.path == str(out) and not partial.exists()
    assert len(resumed.history) == 4  # steps 1-2 before the interrupt, 3-4 after (equality: tests/test_tune.py)
    assert json.loads(out.read_text())["status"] == "done"


def test_a_complete_result_survives_an_interrupted_resume_and_a_study_of_several_observers_has_no_stale_metrics(
    tmp_path, monkeypatch, capsys
):
    """A complete JSON is replaced only by a complete one, with --resume too (an interrupted resume replaced it with
    its partial result). A study of several observers has metrics per observer only (the top-level ``metrics``
    were the first observer's, written while it alone had runs, and a resumed file had none)."""
    from jaxatt import montecarlo, studies

    study = studies.get("nlio-case1")
    cfg = study.config(duration=2.0)
    obs = dict(list(study.observers(cfg).items())[:2])
    out = tmp_path / "r.json"
    kw = dict(cfg=cfg, json_path=str(out), quiet=True, observers=obs, chunk=1)
    studies.reproduce(study, runs=1, **kw)
    done = json.loads(out.read_text())
    assert done["complete"] and "metrics" not in done and all("metrics" in e for e in done["observers"].values())
    finished = out.read_bytes()
    real, calls = montecarlo.monte_carlo, []

    def interrupt_after_a_chunk_of(call):  # Ctrl-C once the call-th Monte Carlo has finished a chunk
        def mc(*a, **k):
            calls.append(1)
            if len(calls) == call:
                inner = k["on_chunk"]

                def on_chunk(res):
                    inner(res)
                    raise KeyboardInterrupt

                k = {**k, "on_chunk": on_chunk}
            return real(*a, **k)

        return mc

    monkeypatch.setattr(montecarlo, "monte_carlo", interrupt_after_a_chunk_of(2))  # in the second observer
    assert not studies.reproduce(study, runs=2, **kw)["complete"]
    assert out.read_bytes() == finished
    calls.clear()
    monkeypatch.setattr(montecarlo, "monte_carlo", interrupt_after_a_chunk_of(1))  # the first left to run
    capsys.readouterr()
    assert not studies.reproduce(study, runs=2, resume=True, **{**kw, "quiet": False})["complete"]
    first, second = obs  # the resume says what each observer had (it said 0/2 unless every one had runs)
    assert f"resuming: runs already saved in {out}.runs.npz: {first} 2/2, {second} 1/2" in capsys.readouterr().err
    assert out.read_bytes() == finished
    monkeypatch.setattr(montecarlo, "monte_carlo", real)
    assert studies.reproduce(study, runs=2, resume=True, **kw)["complete"]
    resumed = json.loads(out.read_text())
    assert resumed["complete"] and resumed["runs_done"] == 2 and "metrics" not in resumed


def test_runs_saved_by_an_earlier_version_are_resumed_after_an_upgrade(tmp_path):
    """A runs file whose spec lacks a key added since (0.2.0 wrote no trace_every, no config field added later,
    no program fingerprints) is resumed when this run uses that key's old value: an upgrade mid-study keeps every
    finished run. A key that does differ is named."""
    from jaxatt import montecarlo, studies

    study = studies.get("nlio-case1")
    cfg = study.config(duration=2.0)
    obs = dict(list(study.observers(cfg).items())[:1])
    out = tmp_path / "r.json"
    runs = Path(str(out) + ".runs.npz")

    def run(**kw):
        return studies.reproduce(study, cfg, runs=2, json_path=str(out), quiet=True, observers=obs, **kw)

    run()
    spec, saved = montecarlo.load_runs(runs, "test")
    old = json.loads(spec)
    del old["trace_every"], old["config"][sorted(old["config"])[0]]  # as an earlier version wrote it
    montecarlo.save_runs(runs, json.dumps(old, sort_keys=True), saved)
    out.write_text(out.read_text().replace('"complete": true', '"complete": false'))
    before = json.loads(out.read_text())["metrics"] if "metrics" in json.loads(out.read_text()) else None
    assert run(resume=True)["complete"]  # resumed, not refused
    assert (json.loads(out.read_text()).get("metrics") if before is not None else None) == before
    old["seed"] = 7  # a key that differs is named
    montecarlo.save_runs(runs, json.dumps(old, sort_keys=True), saved)
    with pytest.raises(ValueError, match=r"another set-up \(.*seed.* differs?\)"):
        run(resume=True)
    assert montecarlo.spec_differences(json.dumps({"a": 1}), json.dumps({"a": 1, "b": 2}), {"b": 3}) == ["b"]
    assert montecarlo.spec_differences(json.dumps({"c": {"x": 1}}), json.dumps({"c": {"x": 2}})) == ["c.x"]
    programs = json.dumps({"a": 1, "programs": {"observer": "5e1f"}})  # jaxatt.monte_carlo's files of 0.2.0: none
    assert montecarlo.spec_differences(json.dumps({"a": 1}), programs, {"programs": montecarlo.ANY}) == []
