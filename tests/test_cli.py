"""The command line end to end on short runs: exit codes, JSON layout, clear errors."""

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxatt
from jaxatt import cli

PROVENANCE_KEYS = {
    "date_utc",
    "versions",
    "jax_backend",
    "jax_devices",
    "x64",
    "git_commit",
    "command_line",
    "xla_flags",
}


def assert_provenance(env: dict) -> None:
    """A result's provenance: versions, devices, git commit (None outside a checkout), command line, XLA_FLAGS."""
    assert PROVENANCE_KEYS <= set(env), PROVENANCE_KEYS - set(env)
    assert env["versions"]["jaxatt"] and env["versions"]["jax"] and isinstance(env["command_line"], list)
    assert env["jax_devices"] and isinstance(env["xla_flags"], str)
    assert env["git_commit"] is None or len(env["git_commit"].split("+")[0]) == 40


def test_reproduce_batista_so3_writes_metrics_json(tmp_path):
    out = tmp_path / "so3.json"
    rc = cli.main(["reproduce", "batista-so3", "--runs", "2", "--duration", "30", "--quiet", "--json", str(out)])
    assert rc == 0
    d = json.loads(out.read_text())
    assert_provenance(d["environment"])
    assert d["complete"] and d["runs_done"] == 2
    m = d["metrics"]
    assert len(m["mean_angle_error_deg"]["per_run"]) == 2
    for key in ("std_m", "std_v", "std_r_err", "final_angle_error_deg"):
        assert np.isfinite(m[key]["mean"])
    assert d["config"]["integrator"] == "lie" and d["config"]["m_init"] == "rescaled"
    # every metric's unit, from the study's (Table 2's std_m in nT; |m~| at the end in the same unit)
    assert set(d["metric_units"]) == set(m)
    assert d["metric_units"]["std_m"] == d["metric_units"]["final_norm_m"] == "nT"
    assert d["metric_units"]["std_v"] == "nT^2/s" and d["metric_units"]["max_angle_error_deg"] == "deg"


def test_metric_units_follow_the_error_each_metric_is_of():
    from jaxatt.studies import base

    per_run = dict.fromkeys(["mean_angle_error_deg", "std_x1", "final_norm_x1", "rmse_steady_bias", "n_rest"])
    got = base.metric_units(per_run, {"std_x1": "nT"}, {"bias": "deg/s", "s": "1"})
    assert got == {"mean_angle_error_deg": "deg", "std_x1": "nT", "final_norm_x1": "nT", "rmse_steady_bias": "deg/s"}


def test_observer_specific_flags_are_checked(capsys):
    assert cli.main(["simulate", "--observer", "batista-so3", "--x2-0", "1,2,3", "--runs", "1", "--duration", "1"]) == 2
    assert "does not apply" in capsys.readouterr().err
    assert (
        cli.main(["simulate", "--observer", "batista-ges", "--integrator", "rk4", "--runs", "1", "--duration", "1"])
        == 2
    )


def test_a_step_beyond_rk4s_stability_is_refused_before_computing(tmp_path, capsys):
    """batista-ges at dt = 0.03 s: Table 1's alpha1 = 100 1/s gives alpha1 dt = 3 > 2.78, where RK4 diverges (it
    went non-finite at t = 18.6 s). Refused with one line naming dt, alpha1 and the longest step that works, before
    anything runs (no JSON written)."""
    out = tmp_path / "ges.json"
    argv = ["simulate", "--observer", "batista-ges", "--runs", "1", "--duration", "30", "--json", str(out)]
    assert cli.main([*argv, "--dt", "0.03"]) == 2
    err = capsys.readouterr().err
    assert "dt = 0.03 s is too long for alpha1 = 100" in err and "dt < 0.0278" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_a_run_still_in_its_transient_says_so(tmp_path, capsys):
    """batista-ges's transient lasts far beyond 10 s (the paper's window starts at 2400 s): the window's mean angle
    error is a transient's (~168 deg), and the CLI's first note and the JSON's notes say the observer has not
    settled, naming the window, instead of reporting it silently as a steady state."""
    out = tmp_path / "ges.json"
    argv = ["simulate", "--observer", "batista-ges", "--runs", "1", "--duration", "10", "--window-start", "5"]
    assert cli.main([*argv, "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    d = json.loads(out.read_text())
    assert d["metrics"]["mean_angle_error_deg"]["mean"] > 20.0
    assert d["notes"][0].startswith("batista-ges has not settled") and "t >= 5 s" in d["notes"][0]
    assert "batista-ges has not settled" in printed


def test_simulate_complementary_constant_reference_does_not_converge_rotating_does(tmp_path):
    res = {}
    for scen in ("constant", "rotating"):
        out = tmp_path / f"{scen}.json"
        rc = cli.main(
            [
                "simulate",
                "--observer",
                "complementary",
                "--scenario",
                scen,
                "--runs",
                "1",
                "--duration",
                "60",
                "--noise-scale",
                "0",
                "--quiet",
                "--json",
                str(out),
            ]
        )
        assert rc == 0
        res[scen] = json.loads(out.read_text())["metrics"]["final_angle_error_deg"]["mean"]
    assert res["rotating"] < 0.2 < 5.0 < res["constant"]


def test_excitation_command_flags_unobservable_scenario(tmp_path, capsys):
    out = tmp_path / "exc.json"
    assert cli.main(["excitation", "--scenario", "constant", "--duration", "20", "--json", str(out)]) == 0
    assert "NOT exciting" in capsys.readouterr().out
    d = json.loads(out.read_text())
    assert_provenance(d["environment"])
    assert max(d["measures"]["lambda2"]) < 1e-9
    assert cli.main(["excitation", "--scenario", "two-constant", "--duration", "20"]) == 0
    assert "exciting in every window" in capsys.readouterr().out


def test_excitation_of_a_log_file(tmp_path, capsys):
    from jaxatt.data import logs
    from jaxatt.types import ImuSample

    t = np.arange(0, 20, 0.01)
    # a level sensor spinning about the vertical: gravity alone leaves the heading unobservable; with the field
    # (not vertical) the pair is exciting
    yaw = 0.5 * t
    c, s = np.cos(yaw), np.sin(yaw)
    up = np.tile([0.0, 0.0, -9.81], (len(t), 1))  # specific force of a level sensor in NED body axes
    field = np.array([0.2, 0.0, 0.4])
    mag = np.stack([c * field[0], -s * field[0], np.full_like(t, field[2])], -1)  # R^T field, R = Rz(yaw)
    path = tmp_path / "log.npz"
    logs.save_log(path, ImuSample(t, np.tile([0.0, 0.0, 0.5], (len(t), 1)), up, mag))
    assert cli.main(["excitation", "--log", str(path), "--mag-ref", "0.2,0,0.4", "--window", "2"]) == 0
    assert "exciting in every window" in capsys.readouterr().out
    assert cli.main(["excitation", "--log", str(path), "--window", "2"]) == 2  # mag without --mag-ref
    # a vector starting with a minus sign is a value, not a flag (argparse alone reads "-0.2,0,-0.4" as an option)
    capsys.readouterr()
    assert cli.main(["excitation", "--log", str(path), "--mag-ref", "-0.2,0,-0.4", "--window", "2"]) == 0
    assert "exciting in every window" in capsys.readouterr().out
    # the same log from a logger (ms timestamps, its own column names): --columns and --time-unit give the same
    # measures, written to JSON, as the log in s
    si, ms = tmp_path / "si.json", tmp_path / "ms.json"
    assert cli.main(["excitation", "--log", str(path), "--mag-ref", "0.2,0,0.4", "--json", str(si)]) == 0
    raw = tmp_path / "raw.csv"
    logs.save_log(raw, ImuSample(t * 1e3, np.tile([0.0, 0.0, 0.5], (len(t), 1)), up, mag))
    text = raw.read_text().splitlines()
    raw.write_text("\n".join([text[0].replace("t,", "time_ms,").replace("acc_", "a")] + text[1:]) + "\n")
    cols = "t=time_ms,acc_x=ax,acc_y=ay,acc_z=az"
    argv = ["excitation", "--log", str(raw), "--columns", cols, "--time-unit", "ms", "--mag-ref", "0.2,0,0.4"]
    assert cli.main([*argv, "--json", str(ms)]) == 0
    a, b = json.loads(si.read_text()), json.loads(ms.read_text())
    assert a["window_s"] == b["window_s"] == 5.0
    for k in ("t_start", "t_end", "lambda2", "condition"):
        np.testing.assert_allclose(b["measures"][k], a["measures"][k], rtol=1e-9, atol=1e-12, err_msg=k)
    # a sensor without one valid reading is left out, said on stderr (gravity alone: heading unobservable); without
    # any, the command refuses with one line
    capsys.readouterr()
    logs.save_log(path, ImuSample(t, np.tile([0.0, 0.0, 0.5], (len(t), 1)), up, np.full_like(mag, np.nan)))
    assert cli.main(["excitation", "--log", str(path), "--mag-ref", "0.2,0,0.4", "--window", "2"]) == 0
    out = capsys.readouterr()
    assert "mag has no valid reading (every row non-finite or zero): left out" in out.err
    assert "NOT exciting" in out.out and "(acc; references in NED)" in out.out
    logs.save_log(path, ImuSample(t, np.tile([0.0, 0.0, 0.5], (len(t), 1)), np.zeros_like(up), None))
    assert cli.main(["excitation", "--log", str(path), "--window", "2"]) == 2
    assert "acc has no valid reading (every row non-finite or zero): nothing to analyse" in capsys.readouterr().err
    logs.save_log(path, ImuSample(t[:1], np.zeros((1, 3)), up[:1], None))  # one row: the file is named
    assert cli.main(["excitation", "--log", str(path)]) == 2
    assert f"--log {path}: 1 sample; the excitation analysis needs at least 2" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------------------
# filter, tune / evaluate, broad / broad-tune
# ---------------------------------------------------------------------------------------------------------
def _sim_log(seconds=10.0):
    import jaxatt

    samples, truth = jaxatt.montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=seconds, dt=0.01)
    return jax_to_np(samples), np.asarray(truth.r)


def jax_to_np(s):
    from jaxatt.types import ImuSample

    return ImuSample(*(None if v is None else np.asarray(v) for v in s))


def test_filter_unit_flags_read_a_log_in_deg_per_s_g_and_ms(tmp_path, capsys):
    """A logger's deg/s, g and ms timestamps, read with --gyr-unit deg/s --acc-unit g --time-unit ms, give the
    estimates of the same log in rad/s, m/s^2 and s (t written in s), without the wrong-unit warnings."""
    from jaxatt.data import logs

    samples, _ = _sim_log()
    si, raw = tmp_path / "si.csv", tmp_path / "raw.csv"
    logs.save_log(si, samples)
    logs.save_log(
        raw,
        samples._replace(t=samples.t * 1e3, gyr=np.rad2deg(samples.gyr), acc=np.asarray(samples.acc) / 9.80665),
    )
    out_si, out_raw = tmp_path / "est_si.csv", tmp_path / "est_raw.csv"
    assert cli.main(["filter", "--log", str(si), "--observer", "mahony", "--out", str(out_si)]) == 0
    capsys.readouterr()
    flags = ["--gyr-unit", "deg/s", "--acc-unit", "g", "--time-unit", "ms"]
    assert cli.main(["filter", "--log", str(raw), "--observer", "mahony", *flags, "--out", str(out_raw)]) == 0
    assert "warning" not in capsys.readouterr().err
    a, b = (np.genfromtxt(p, delimiter=",", names=True) for p in (out_si, out_raw))
    np.testing.assert_allclose(b["t"], a["t"], rtol=1e-12, atol=1e-12)
    for c in ("qw", "qx", "qy", "qz"):
        np.testing.assert_allclose(b[c], a[c], atol=1e-9)
    # without the flags the same log is warned about (its g and ms here), with the flag that converts each
    assert cli.main(["filter", "--log", str(raw), "--observer", "mahony", "--out", str(tmp_path / "e3.csv")]) == 0
    err = capsys.readouterr().err
    assert "--acc-unit g in jaxatt filter" in err and "--time-unit ms" in err, err
    # --time-unit with --dt: one clear line, exit 2, before computing
    assert (
        cli.main(["filter", "--log", str(raw), "--time-unit", "ms", "--dt", "0.01", "--out", str(tmp_path / "e4.csv")])
        == 2
    )
    assert "--time-unit ms and --dt" in capsys.readouterr().err
    # the same log with a logger's own column names, read through --columns
    theirs = tmp_path / "theirs.csv"
    names = {"t": "time_ms", "gyr_x": "GyroX", "gyr_y": "GyroY", "gyr_z": "GyroZ", "acc_x": "ax", "mag_z": "Bz"}
    lines = raw.read_text().splitlines()
    theirs.write_text("\n".join([",".join(names.get(h, h) for h in lines[0].split(","))] + lines[1:]) + "\n")
    cols = ",".join(f"{k}={v}" for k, v in names.items())
    out_theirs = tmp_path / "est_theirs.csv"
    argv = ["filter", "--log", str(theirs), "--columns", cols, "--observer", "mahony", *flags, "--out", str(out_theirs)]
    assert cli.main(argv) == 0
    c = np.genfromtxt(out_theirs, delimiter=",", names=True)
    for name in ("t", "qw", "qx", "qy", "qz"):
        np.testing.assert_array_equal(c[name], b[name])


def test_filter_command_writes_estimates_of_a_log(tmp_path, capsys):
    from jaxatt.data import logs

    samples, r_true = _sim_log()
    log = tmp_path / "log.csv"
    logs.save_log(log, samples)
    out = tmp_path / "est.csv"
    assert cli.main(["filter", "--log", str(log), "--observer", "mahony", "--out", str(out)]) == 0
    table = np.genfromtxt(out, delimiter=",", names=True)
    assert table.shape == (len(samples.t),) and table.dtype.names[:5] == ("t", "qw", "qx", "qy", "qz")
    assert "bias_x" in table.dtype.names and "acc_used" in table.dtype.names
    import jaxatt

    est = jaxatt.filter("mahony", samples.gyr, samples.acc, samples.mag, t=samples.t)
    np.testing.assert_allclose(np.column_stack([table[c] for c in ("qw", "qx", "qy", "qz")]), est.quat, atol=1e-15)
    # NED output: the fixed rotation of the ENU one
    out2 = tmp_path / "est_ned.csv"
    assert cli.main(["filter", "--log", str(log), "--observer", "mahony", "--frame", "NED", "--out", str(out2)]) == 0
    ned = np.genfromtxt(out2, delimiter=",", names=True)
    q_ned = np.column_stack([ned[c] for c in ("qw", "qx", "qy", "qz")])
    np.testing.assert_allclose(q_ned, jaxatt.frames.change_frame(est.quat, "NED", "ENU"), atol=1e-15)
    # --offline --frame NED: every attitude column in NED, the backward pass's too (it was written in ENU beside
    # the NED estimate); q_nwu, named with its frame, as it is
    argv = ["filter", "--log", str(log), "--observer", "mahony", "--frame", "NED", "--offline", "--out", str(out2)]
    assert cli.main(argv) == 0
    ned = np.genfromtxt(out2, delimiter=",", names=True)
    off = jaxatt.filter("mahony", samples.gyr, samples.acc, samples.mag, t=samples.t, offline=True)  # ENU
    for k in ("backward_q", "q_forward", "q_nwu"):
        want = off.outputs[k] if k == "q_nwu" else jaxatt.frames.change_frame(off.outputs[k], "NED", "ENU")
        np.testing.assert_allclose(np.column_stack([ned[f"{k}_{ax}"] for ax in "wxyz"]), want, atol=1e-12)
    r_back = np.stack([np.stack([ned[f"backward_r_{i}{j}"] for j in range(3)], -1) for i in range(3)], -2)
    want_r = jaxatt.frames.frame_rotation("NED", "ENU") @ off.outputs["backward_r"]
    np.testing.assert_allclose(r_back, want_r, atol=1e-12)
    # an output that cannot be written (a full disk: /dev/full): one line naming it, exit 2, no traceback
    if Path("/dev/full").exists():
        capsys.readouterr()
        assert cli.main(["filter", "--log", str(log), "--observer", "mahony", "--out", "/dev/full"]) == 2
        err = capsys.readouterr().err
        assert err == "jaxatt: error: /dev/full: No space left on device\n", err
    # --dt that disagrees with the log's timestamps: said on stderr (the t column then restarts at 0)
    capsys.readouterr()
    out4 = tmp_path / "est_dt.csv"
    assert cli.main(["filter", "--log", str(log), "--observer", "mahony", "--dt", "0.02", "--out", str(out4)]) == 0
    assert "jaxatt: warning: --dt 0.02 s replaces the log's timestamps" in capsys.readouterr().err
    # a log without a t column: --dt times it (t = k dt), the same estimates as the API given dt; without --dt the
    # missing column is named with the way out
    no_t = tmp_path / "no_t.csv"
    no_t.write_text("\n".join(line.split(",", 1)[1] for line in log.read_text().splitlines()) + "\n")
    out5 = tmp_path / "est_no_t.csv"
    assert cli.main(["filter", "--log", str(no_t), "--observer", "mahony", "--dt", "0.01", "--out", str(out5)]) == 0
    assert "warning" not in capsys.readouterr().err
    got = np.genfromtxt(out5, delimiter=",", names=True)
    np.testing.assert_array_equal(got["t"], np.arange(len(samples.t)) * 0.01)
    by_dt = jaxatt.filter("mahony", samples.gyr, samples.acc, samples.mag, dt=0.01)
    np.testing.assert_allclose(np.column_stack([got[c] for c in ("qw", "qx", "qy", "qz")]), by_dt.quat, atol=1e-15)
    assert cli.main(["filter", "--log", str(no_t), "--observer", "mahony", "--out", str(out5)]) == 2
    assert "required column 't' missing" in capsys.readouterr().err
    # timestamps that are broken (a repeated time) do not stop --dt, which replaces them (said on stderr), and a
    # time column under another name is said to be unread: both the same estimates as the API given dt
    for text, said in (
        (log.read_text().replace("\n0.01", "\n0", 1), "the log's timestamps are not read, --dt 0.01 s times it: "),
        ("time" + log.read_text()[1:], "column 'time' is not read: dt times the log"),
    ):
        no_t.write_text(text)
        assert cli.main(["filter", "--log", str(no_t), "--observer", "mahony", "--dt", "0.01", "--out", str(out5)]) == 0
        assert said in capsys.readouterr().err
        got = np.genfromtxt(out5, delimiter=",", names=True)
        np.testing.assert_allclose(np.column_stack([got[c] for c in ("qw", "qx", "qy", "qz")]), by_dt.quat, atol=1e-15)
    # --out .npz: the same columns as arrays
    out3 = tmp_path / "est.npz"
    assert cli.main(["filter", "--log", str(log), "--observer", "mahony", "--out", str(out3)]) == 0
    with np.load(out3) as z:
        assert tuple(z.files) == table.dtype.names
        for name in table.dtype.names:
            np.testing.assert_array_equal(z[name], table[name], err_msg=name)


#: a user's own observer module (gyro integration only): --observer my_filter:OBSERVER --params my_filter:PARAMS
MY_FILTER_MODULE = (
    "import jax.numpy as jnp\n"
    "from typing import NamedTuple\n"
    "import jaxatt\n"
    "from jaxatt import so3\n"
    "class P(NamedTuple):\n"
    "    k: jnp.ndarray\n"
    "class S(NamedTuple):\n"
    "    t: jnp.ndarray\n"
    "    q: jnp.ndarray\n"
    "def init(p, s):\n"
    "    return S(jnp.asarray(s.t), so3.quat_canonical(so3.matrix_to_quat(so3.triad(s.acc, s.mag))))\n"
    "def step(p, st, s, dt):\n"
    "    q = st.q + 0.5 * dt * so3.quat_multiply(st.q, jnp.concatenate([jnp.zeros(1), p.k * s.gyr]))\n"
    "    q = q / jnp.linalg.norm(q)\n"
    "    return S(st.t + dt, q), S(st.t + dt, q)\n"
    "OBSERVER = jaxatt.Observer(init, step, 'gyro_only')\n"
    "PARAMS = P(jnp.asarray(1.0))\n"
)


def test_filter_command_with_your_own_observer_module(tmp_path, monkeypatch, capsys):
    """--observer module:attr --params module:attr: an observer defined in the user's own file."""
    from jaxatt.data import logs

    (tmp_path / "my_filter.py").write_text(MY_FILTER_MODULE)
    samples, r_true = _sim_log(5.0)
    log = tmp_path / "log.npz"
    logs.save_log(log, samples)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "est.csv"
    assert (
        cli.main(
            [
                "filter",
                "--log",
                str(log),
                "--observer",
                "my_filter:OBSERVER",
                "--params",
                "my_filter:PARAMS",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    table = np.genfromtxt(out, delimiter=",", names=True)
    assert table.dtype.names == ("t", "qw", "qx", "qy", "qz") and len(table) == len(samples.t)
    assert "(ENU as labelled, not converted: your observer's own frame, float64)" in capsys.readouterr().out
    # --gains of your own observer (a file jaxatt.fit(..., out=) writes) go into --params: k = 0 stops the gyro
    from typing import NamedTuple

    from jaxatt.fitting import gainsfile

    class P(NamedTuple):
        k: float

    gains = tmp_path / "mine.json"
    gainsfile.write(gains, observer="gyro_only", params=P(0.0))
    own = ["filter", "--log", str(log), "--observer", "my_filter:OBSERVER", "--params", "my_filter:PARAMS"]
    out2 = tmp_path / "est_gains.csv"
    assert cli.main([*own, "--gains", str(gains), "--out", str(out2)]) == 0
    held = np.genfromtxt(out2, delimiter=",", names=True)
    q = np.column_stack([held[c] for c in ("qw", "qx", "qy", "qz")])
    np.testing.assert_array_equal(q, np.tile(q[0], (len(q), 1)))  # the start, never turned
    assert not np.allclose(np.column_stack([table[c] for c in ("qw", "qx", "qy", "qz")])[-1], q[-1])
    gainsfile.write(gains, observer="someone_else", params=P(0.0))
    assert cli.main([*own, "--gains", str(gains), "--out", str(out2)]) == 2
    assert cli.main([*own[:-2], "--gains", str(gains), "--out", str(out2)]) == 2
    # a registry Entry of your own with both --params and --gains (one would be dropped), and a module that
    # exits while it is imported (jaxatt exited 0 with no output): refused, exit 2
    (tmp_path / "my_entry.py").write_text(
        "from jaxatt.observers import registry\nENTRY = registry.get('madgwick')\nPARAMS = ENTRY.params()\n"
    )
    (tmp_path / "my_script.py").write_text("import sys\nsys.exit(0)\n")
    capsys.readouterr()
    entry = ["filter", "--log", str(log), "--observer", "my_entry:ENTRY", "--out", str(out2)]
    assert cli.main([*entry, "--params", "my_entry:PARAMS", "--gains", str(gains)]) == 2
    assert (
        "is a registry Entry: give its gains by --gains or its params by --params, not both" in capsys.readouterr().err
    )
    assert cli.main(["filter", "--log", str(log), "--observer", "my_script:OBSERVER", "--out", str(out2)]) == 2
    assert "importing my_script called sys.exit(0): guard its script part" in capsys.readouterr().err


def test_tune_then_evaluate_reads_the_gains_file(tmp_path, capsys, monkeypatch):
    from jaxatt import studies

    assert cli.TUNABLE_STUDIES == studies.TUNABLE  # the command's choices (kept without importing jax for --help)
    gains = tmp_path / "g.json"
    # no step: the command's plumbing (the gradient through the scan is tested in test_tune.py)
    rc = cli.main(
        [
            "tune",
            "--experiment",
            "batista-so3",
            "--steps",
            "0",
            "--train-runs",
            "2",
            "--val-runs",
            "0",
            "--duration",
            "6",
            "--out",
            str(gains),
            "--quiet",
        ]
    )
    assert rc == 0
    d = json.loads(gains.read_text())
    assert_provenance(d["provenance"])
    assert d["format"] == "jaxatt-gains/2" and d["observer"] == d["study"] == "batista-so3" and d["status"] == "done"
    # a second tune to the same file is refused unless resumed or overwritten
    assert cli.main(["tune", "--experiment", "batista-so3", "--steps", "1", "--out", str(gains)]) == 2
    assert f"--out {gains} exists: give --out PATH for a new gains file, --resume" in capsys.readouterr().err
    # the same without --out: the default gains.json of the working folder, said to be the default
    monkeypatch.chdir(tmp_path)
    (tmp_path / "gains.json").write_bytes(gains.read_bytes())
    for cmd in (["tune", "--experiment", "batista-so3"], ["broad-tune", "--observer", "madgwick", "--logs", "x.csv"]):
        assert cli.main([*cmd, "--steps", "1"]) == 2
        assert "--out gains.json (the default) exists: give --out PATH" in capsys.readouterr().err
    out = tmp_path / "e.json"
    assert (
        cli.main(
            [
                "evaluate",
                "--experiment",
                "batista-so3",
                "--gains",
                str(gains),
                "--runs",
                "2",
                "--duration",
                "6",
                "--json",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    e = json.loads(out.read_text())
    assert_provenance(e["environment"])
    assert e["gains_path"] == str(gains) and "comparison" in e and e["complete"]
    # gains of another study are refused; an empty --gains is not the paper's gains (it silently was)
    assert cli.main(["evaluate", "--experiment", "batista-ges", "--gains", str(gains), "--runs", "1"]) == 2
    assert cli.main(["evaluate", "--experiment", "batista-so3", "--gains", "", "--runs", "1"]) == 2
    assert "--gains: empty path" in capsys.readouterr().err


def test_evaluate_runs_the_set_up_the_gains_were_tuned_on(tmp_path, capsys):
    """Gains tuned through the API on a non-default configuration (two constant vectors, noisy sensors) are
    evaluated on that configuration, at the study's duration or --duration; a gains file whose set-up cannot be
    built is refused with a line naming --gains."""
    import jaxatt
    from jaxatt import studies
    from jaxatt.fitting import gainsfile

    gains = tmp_path / "g.json"
    tuned_on = {"scenario": "two_constant", "form": "quaternion", "gyro_noise_std": 0.01, "meas_noise_std": 0.05}
    jaxatt.fit(None, None, "complementary", config={**tuned_on, "duration": 2.0}, steps=0, out=str(gains), quiet=True)
    out = tmp_path / "e.json"
    argv = ["evaluate", "--experiment", "complementary", "--gains", str(gains), "--runs", "2", "--quiet"]
    assert cli.main([*argv, "--duration", "3", "--json", str(out)]) == 0
    cfg = json.loads(out.read_text())["config"]
    assert {k: cfg[k] for k in tuned_on} == tuned_on and cfg["duration"] == 3.0
    # the best gains of a fit that did not finish are used, with a warning
    d = json.loads(gains.read_text())
    gains.write_text(json.dumps({**d, "status": "interrupted"}))
    capsys.readouterr()
    assert cli.main([*argv, "--duration", "3"]) == 0
    err = capsys.readouterr().err
    assert "jaxatt: warning:" in err and "did not finish" in err and "'interrupted'" in err
    # evaluation runs that the fit trained on (its seed 0, runs 0-31) are said, on a line of jaxatt's
    assert cli.main([*argv, "--duration", "3", "--seed", "0"]) == 0
    err = capsys.readouterr().err
    assert "jaxatt: warning: 2 evaluation runs were used for tuning (same seed 0)" in err
    assert "were used for tuning" not in (cli.main([*argv, "--duration", "3"]), capsys.readouterr().err)[1]
    with pytest.warns(UserWarning, match="did not finish"):
        gainsfile.read_params(str(gains), "complementary", base=studies.get("complementary").setup(**tuned_on).params)
    gains.write_text(json.dumps({**d, "settings": {**d["settings"], "config": "two_constant"}}))
    assert cli.main([*argv, "--duration", "3"]) == 2  # a set-up that is not an object was ignored
    assert "settings.config must be an object" in capsys.readouterr().err
    d["settings"]["config"]["no_such_setting"] = 1
    gains.write_text(json.dumps(d))
    capsys.readouterr()
    assert cli.main([*argv, "--duration", "3"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--gains" in err and "no_such_setting" in err


def test_evaluate_at_a_short_duration_scales_the_windows_a_gains_file_recorded(tmp_path, capsys):
    """A gains file of an NLIO study records its set-up's metric windows (0-200 s, 300-500 s); evaluated at
    --duration 2 they scale with the duration as without --gains (they were kept, and every window metric was NaN:
    exit 1 "non-finite")."""
    from jaxatt import studies
    from jaxatt.fitting import gainsfile
    from jaxatt.observers import registry

    s = studies.get("nlio-case1").setup()
    gains = tmp_path / "g.json"
    config = {"windows": [list(w) for w in s.windows], "duration": s.duration}
    gainsfile.write(
        gains,
        observer=s.entry,
        params=s.params,
        gains=registry.get(s.entry).gains,
        study="nlio-case1",
        status="done",
        settings={"config": config},
    )
    out = tmp_path / "e.json"
    argv = ["evaluate", "--experiment", "nlio-case1", "--gains", str(gains), "--runs", "1", "--quiet"]
    assert cli.main([*argv, "--duration", "2", "--json", str(out)]) == 0, capsys.readouterr().err
    d = json.loads(out.read_text())
    assert [w[1:] for w in d["config"]["windows"]] == [[0.0, 0.8], [1.2, 2.0]]
    assert "Transient (0-0.8 s)" in d["tables_text"] and "Steady-State (1.2-2 s)" in d["tables_text"]  # not 0-200
    assert all(np.all(np.isfinite(m["mean"])) for m in d["metrics"].values())


def _write_broad_trial(path, samples, q_true, rate):
    import h5py

    n = len(samples.t)
    with h5py.File(path, "w") as f:
        f.attrs["sampling_rate"] = rate
        f["imu_gyr"], f["imu_acc"], f["imu_mag"] = samples.gyr, samples.acc, samples.mag
        f["opt_quat"] = q_true
        f["movement"] = np.arange(n) > n // 5


def test_broad_and_broad_tune_on_small_trials(tmp_path, capsys, monkeypatch):
    """Two small BROAD-format trials (simulated, ENU): jaxatt broad prints and writes the metric per trial and
    group, for a registered observer and for your own (--observer module:attr --params module:attr); broad-tune
    learns and writes a gains file that jaxatt broad reads back."""
    pytest.importorskip("h5py")
    import jaxatt
    from jaxatt import so3

    d = tmp_path / "broad"
    d.mkdir()
    for name, seed in (("01_undisturbed_sim", 1), ("24_disturbed_sim", 2)):
        s, truth = jaxatt.montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=8.0, dt=0.01, seed=seed)
        q = np.asarray(so3.quat_canonical(so3.matrix_to_quat(truth.r)))
        _write_broad_trial(d / f"{name}.hdf5", jax_to_np(s), q, 100.0)
    out = tmp_path / "b.json"
    assert cli.main(["broad", "--data-dir", str(d), "--observer", "madgwick", "--json", str(out)]) == 0
    b = json.loads(out.read_text())
    assert_provenance(b["environment"])
    assert set(b["trials"]) == {"01_undisturbed_sim", "24_disturbed_sim"}
    assert set(b["groups"]) == {"undisturbed", "disturbed", "all"} and b["observer"] == "madgwick"
    trials = jaxatt.data.broad.load(d)
    score = jaxatt.broad_score("madgwick", None, trials)
    assert b["trials"]["24_disturbed_sim"]["total_rmse_deg"] == pytest.approx(
        score.trials["24_disturbed_sim"].total_rmse_deg, rel=1e-12
    )
    # your own observer, as jaxatt filter takes it
    (tmp_path / "my_filter.py").write_text(MY_FILTER_MODULE)
    monkeypatch.chdir(tmp_path)
    own = tmp_path / "own.json"
    args = ["broad", "--data-dir", str(d), "--observer", "my_filter:OBSERVER", "--params", "my_filter:PARAMS"]
    assert cli.main(args + ["--json", str(own)]) == 0
    mine = json.loads(own.read_text())
    my_filter = sys.modules["my_filter"]  # imported by the command

    ref = jaxatt.broad_score(my_filter.OBSERVER, my_filter.PARAMS, trials)
    assert mine["observer"] == "gyro_only" and mine["gains"] == {"k": 1.0}
    for name, t in ref.trials.items():
        assert mine["trials"][name]["total_rmse_deg"] == pytest.approx(t.total_rmse_deg, rel=1e-12)
    assert cli.main(args[:-2]) == 2  # no --params
    assert "params are required for your own observer" in capsys.readouterr().err
    # broad-tune learns your own observer's gains too (it said "unknown observer"): those of jaxatt.fit, which
    # jaxatt broad reads back with --gains
    own_gains = tmp_path / "own_gains.json"
    tune_own = ["broad-tune", *args[1:], "--steps", "2", "--out", str(own_gains), "--quiet"]
    assert cli.main(tune_own) == 2  # its step computes in float64 (jnp.zeros(1)): said, with the fix
    assert "step returns the state field .q as float64[4], but the observer runs in float32" in capsys.readouterr().err
    assert cli.main([*tune_own, "--float64"]) == 0
    fit = jaxatt.fit(my_filter.OBSERVER, my_filter.PARAMS, trials, steps=2)
    assert json.loads(own_gains.read_text())["gains"]["k"]["value"] == pytest.approx(float(fit.params.k), rel=1e-12)
    assert cli.main([*args, "--gains", str(own_gains), "--json", str(own)]) == 0
    assert json.loads(own.read_text())["gains"]["k"] == pytest.approx(float(fit.params.k), rel=1e-12)
    assert cli.main(["broad-tune", *args[1:-2], "--steps", "1", "--out", str(tmp_path / "x.json")]) == 2
    assert "(your own observer) needs --params module:attr" in capsys.readouterr().err
    g = tmp_path / "g.json"
    assert (
        cli.main(
            ["broad-tune", "--data-dir", str(d), "--observer", "madgwick", "--steps", "2", "--out", str(g), "--quiet"]
        )
        == 0
    )
    saved = json.loads(g.read_text())
    assert_provenance(saved["provenance"])
    assert saved["observer"] == "madgwick" and saved["status"] == "done" and "resume" in saved
    assert cli.main(["broad", "--data-dir", str(d), "--observer", "madgwick", "--gains", str(g)]) == 0
    # a finished cosine-schedule fit cannot be resumed to another step count (its learning-rate schedule would
    # change); the refusal names the setting
    assert (
        cli.main(
            [
                "broad-tune",
                "--data-dir",
                str(d),
                "--observer",
                "madgwick",
                "--steps",
                "3",
                "--out",
                str(g),
                "--resume",
                "--quiet",
            ]
        )
        == 2
    )
    assert "'steps' differs" in capsys.readouterr().err
    # the same two recordings as your own CSV logs, their truth in NED (NaN outside the scored movement): --logs
    # scores them as the BROAD files (one group of your own, no BROAD anchors) and broad-tune learns the same gains
    # (two trials weighted equally)
    from jaxatt import frames
    from jaxatt.data import logs

    paths = []
    for tr in trials:
        paths.append(str(tmp_path / f"{tr.name}.csv"))
        truth = np.where(tr.movement[:, None], frames.change_frame(tr.quat_true, "NED", "ENU"), np.nan)
        logs.save_log(paths[-1], tr.samples, truth)
    mine = tmp_path / "logs.json"
    argv = ["--logs", *paths, "--truth-frame", "NED", "--observer", "madgwick"]
    assert cli.main(["broad", *argv, "--json", str(mine)]) == 0
    m = json.loads(mine.read_text())
    assert set(m["groups"]) == {"own", "all"} and m["anchors"] is None and m["data"] == {"logs": paths}
    for name, t in b["trials"].items():
        assert m["trials"][name]["total_rmse_deg"] == pytest.approx(t["total_rmse_deg"], rel=1e-9)
    g2 = tmp_path / "g2.json"
    assert cli.main(["broad-tune", *argv, "--steps", "2", "--out", str(g2), "--quiet"]) == 0
    got, want = json.loads(g2.read_text())["gains"], saved["gains"]
    assert got.keys() == want.keys()
    for k in want:
        np.testing.assert_allclose(got[k]["value"], want[k]["value"], rtol=1e-5, err_msg=k)
    # resuming it: the same logs read in another frame are other data under the same names; a finished cosine fit
    # cannot be extended; a score written over the gains file is refused; two logs of one name are told apart
    capsys.readouterr()
    tune = ["broad-tune", "--logs", *paths, "--observer", "madgwick", "--steps", "2", "--out", str(g2), "--quiet"]
    assert cli.main([*tune, "--resume"]) == 2  # ENU: the NED truth read as ENU
    assert "the training trials hold other numbers than the saved fit's" in capsys.readouterr().err
    assert cli.main([*tune, "--truth-frame", "NED", "--resume"]) == 2
    assert "already ran 2 steps (its cosine schedule ends there" in capsys.readouterr().err
    assert cli.main(["broad", *argv, "--json", str(g2)]) == 2
    assert "is a gains file (a fit's result), which this would replace" in capsys.readouterr().err
    other = tmp_path / "other"
    other.mkdir()
    twin = str(other / Path(paths[0]).name)
    shutil.copy(paths[0], twin)
    assert cli.main(["broad", "--logs", paths[0], twin, "--truth-frame", "NED", "--json", str(mine)]) == 0
    assert set(json.loads(mine.read_text())["trials"]) == {str(Path(p).with_suffix("")) for p in (paths[0], twin)}
    # the same recording as an NPZ beside its CSV (one stem): named by their paths (it was refused as one name)
    npz = str(Path(paths[0]).with_suffix(".npz"))
    logs.save_log(npz, *logs.load_log(paths[0], with_truth=True))
    assert cli.main(["broad", "--logs", paths[0], npz, "--truth-frame", "NED", "--json", str(mine)]) == 0
    both = json.loads(mine.read_text())["trials"]
    assert set(both) == {paths[0], npz}
    for m in ("total_rmse_deg", "heading_rmse_deg", "inclination_rmse_deg"):  # the CSV's text: the last bit may differ
        assert both[npz][m] == pytest.approx(both[paths[0]][m], rel=1e-12), m
    # a log without timestamps, timed by --dt: the score of the log with them (--dt was only in the hint)
    rows = Path(paths[0]).read_text().splitlines()
    no_t = tmp_path / "no_t.csv"
    no_t.write_text("\n".join(",".join(r.split(",")[1:]) for r in rows) + "\n")
    dt = 1.0 / trials[0].rate_hz
    assert cli.main(["broad", "--logs", str(no_t), "--dt", str(dt), "--truth-frame", "NED", "--json", str(mine)]) == 0
    timed = json.loads(mine.read_text())["trials"]["no_t"]
    assert timed["total_rmse_deg"] == pytest.approx(both[paths[0]]["total_rmse_deg"], rel=1e-6)


def test_cpu_device_count_and_the_command_splits_runs_over_the_cores(tmp_path):
    """The command asks JAX for one CPU device per core unless told otherwise (the user's JAX setting wins); a
    3-run Monte Carlo split over 2 devices (padded to 4) gives the per-run numbers of one device to rounding."""
    assert cli.cpu_device_count({"JAXATT_CPU_DEVICES": "3"}) == 3
    assert cli.cpu_device_count({"JAXATT_NUM_PROCESSES": "2"}) == 1
    assert cli.cpu_device_count({"JAX_NUM_CPU_DEVICES": "1", "JAXATT_CPU_DEVICES": "3"}) is None
    assert cli.cpu_device_count({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}) is None
    assert 1 <= cli.cpu_device_count({}) <= min(os.cpu_count() or 1, cli.MAX_CPU_DEVICES)
    with pytest.raises(ValueError, match="JAXATT_CPU_DEVICES"):
        cli.cpu_device_count({"JAXATT_CPU_DEVICES": "two"})
    with pytest.raises(ValueError, match="JAXATT_CPU_DEVICES must be an integer from 1 to 256, got '100000'"):
        cli.cpu_device_count({"JAXATT_CPU_DEVICES": "100000"})  # a typo took 20 GB and aborted in XLA
    args = ["simulate", "--observer", "batista-ges", "--runs", "3", "--duration", "20", "--quiet"]
    one = tmp_path / "one.json"
    assert cli.main(args + ["--json", str(one)]) == 0
    two = tmp_path / "two.json"
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_NUM_CPU_DEVICES", "XLA_FLAGS")}
    proc = subprocess.run(
        [sys.executable, "-m", "jaxatt", *args, "--json", str(two)],
        env={**env, "JAXATT_CPU_DEVICES": "2"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    d1, d2 = json.loads(one.read_text()), json.loads(two.read_text())
    assert len(d2["environment"]["jax_devices"]) == 2
    for key, m in d1["metrics"].items():
        if isinstance(m, dict) and "per_run" in m:
            np.testing.assert_allclose(d2["metrics"][key]["per_run"], m["per_run"], rtol=1e-9, atol=1e-12)
    proc = subprocess.run(
        [sys.executable, "-m", "jaxatt", *args], env={**env, "JAXATT_CPU_DEVICES": "0"}, capture_output=True, text=True
    )
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        "jaxatt: error: JAXATT_CPU_DEVICES must be an integer from 1 to 256, got '0' (one device per core is the "
        "default)"
    ]


def test_compile_cache_dir(tmp_path):
    """The command keeps compiled programs in the user's cache folder unless told otherwise; JAX's own setting
    wins; a folder that cannot be made turns the cache off instead of failing the run."""
    xdg = tmp_path / "xdg"
    assert cli.compile_cache_dir({"XDG_CACHE_HOME": str(xdg)}) == str(xdg / "jaxatt" / "xla")
    assert (xdg / "jaxatt" / "xla").is_dir()
    assert cli.compile_cache_dir({"XDG_CACHE_HOME": str(xdg), "JAXATT_COMPILE_CACHE": "off"}) is None
    assert cli.compile_cache_dir({"JAX_COMPILATION_CACHE_DIR": "/somewhere", "XDG_CACHE_HOME": str(xdg)}) is None
    mine = tmp_path / "mine"
    assert cli.compile_cache_dir({"JAXATT_COMPILE_CACHE": str(mine)}) == str(mine) and mine.is_dir()
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert cli.compile_cache_dir({"JAXATT_COMPILE_CACHE": str(blocker / "xla")}) is None


class _Terminal:
    """A stream that says it is a terminal (collects what is written)."""

    def __init__(self):
        self.text = ""

    def write(self, s):
        self.text += s

    def flush(self):
        pass

    def isatty(self):
        return True


def test_heartbeat_rewrites_one_line_in_a_terminal_and_writes_whole_lines_to_a_log():
    """``--progress`` while compiling: in a terminal one self-overwriting line (\\r), in a log file whole lines
    at most every ``log_every_s`` (a redirected long tune must not become one endless line)."""
    import io
    import time

    from jaxatt.progress import Heartbeat

    term, log = _Terminal(), io.StringIO()
    with Heartbeat("job", every_s=0.01, file=term):
        time.sleep(0.2)
    with Heartbeat("job", every_s=0.01, file=log, log_every_s=0.1):
        time.sleep(0.35)
    assert term.text.count("\rjob: ") >= 3 and term.text.endswith("\n")
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and 1 <= len(lines) <= 4, lines
    assert all(ln.startswith("job: ") and ln.endswith(" s") for ln in lines)


def test_an_observer_module_that_fails_to_import_is_one_line(tmp_path, monkeypatch, capsys):
    """--observer my_module:X whose import raises (a bug in the user's module): exit 2 and one line naming the flag,
    the module, the line and the error, not the module's traceback."""
    from jaxatt import montecarlo
    from jaxatt.api import ahrs_scenario
    from jaxatt.data import logs

    samples, _ = montecarlo.simulate_log(ahrs_scenario(), duration=0.5, dt=0.01)
    logs.save_csv(tmp_path / "log.csv", samples)
    (tmp_path / "broken_filter.py").write_text("X = 1\nraise RuntimeError('the user\\'s bug')\n")
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    rc = cli.main(["filter", "--log", "log.csv", "--observer", "broken_filter:X", "--out", "est.csv"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0, err
    assert "--observer broken_filter:X: importing broken_filter failed at broken_filter.py:2" in err
    assert "RuntimeError: the user's bug" in err and not (tmp_path / "est.csv").exists()


def test_a_tune_that_ends_on_non_finite_steps_exits_1(tmp_path, capsys):
    """lr 1e300 makes every step after the first non-finite: a 3-step fit must not report done (exit 1, status
    non-finite, the finite start kept as the best gains)."""
    out = tmp_path / "g.json"
    argv = ["tune", "--experiment", "complementary", "--train-runs", "1", "--val-runs", "0", "--duration", "1"]
    rc = cli.main([*argv, "--steps", "2", "--lr", "1e300", "--out", str(out), "--quiet"])
    assert rc == 1 and "not finite" in capsys.readouterr().err
    d = json.loads(out.read_text())
    assert d["status"] == "non-finite" and all(
        np.isfinite(np.asarray(v["value"], float)).all() for v in d["gains"].values()
    )


def test_tune_resume_refuses_another_set_up(tmp_path, capsys):
    """--resume continues the saved fit only with its set-up: the same flags resume; another --val-runs,
    --duration or --refine-schedule is refused naming the setting (the fit would mix two problems)."""
    out = tmp_path / "g.json"
    argv = ["tune", "--experiment", "complementary", "--train-runs", "1", "--val-runs", "0", "--duration", "1"]
    assert cli.main([*argv, "--steps", "1", "--out", str(out), "--quiet"]) == 0
    assert cli.main([*argv, "--steps", "2", "--out", str(out), "--quiet", "--resume"]) == 0
    assert len(json.loads(out.read_text())["history"]) == 2
    capsys.readouterr()
    other = [*argv[:5], "--val-runs", "1", "--duration", "1"]
    assert cli.main([*other, "--steps", "3", "--out", str(out), "--quiet", "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "setting 'val_runs' differs" in err[0], err
    # the API's config: the same duration, another scenario setting
    with pytest.raises(ValueError, match="setting 'config' differs"):
        jaxatt.fit(
            None,
            None,
            "complementary",
            steps=3,
            out=str(out),
            resume=True,
            train_runs=1,
            val_runs=0,
            quiet=True,
            config={"duration": 1.0, "gyro_noise_std": 0.01},
        )


def test_simulate_an_ahrs_filter_is_jaxatt_monte_carlo_on_the_same_imu(tmp_path):
    """``jaxatt simulate --observer <AHRS filter>`` (the ahrs study) runs the Monte Carlo of jaxatt.monte_carlo on
    jaxatt.api.ahrs_scenario with the flags' noise (--mag-noise in nT, the scenario's field in uT): the same
    per-run metrics, run for run. Its filters are the registry's recorded-data observers but complementary, and
    its defaults are ahrs_scenario's."""
    import inspect

    from jaxatt.observers import registry
    from jaxatt.studies import ahrs

    assert cli.AHRS_FILTERS == ahrs.filters()
    assert set(ahrs.filters()) | {"complementary"} == set(registry.names(recorded=True))
    defaults = {k: v.default for k, v in inspect.signature(jaxatt.api.ahrs_scenario).parameters.items()}
    for f in ("gyro_noise_std", "acc_noise_std", "mag_noise_std", "gyro_bias", "rate_scale"):
        assert ahrs.Config._field_defaults[f] == defaults[f], f
    out = tmp_path / "mahony.json"
    flags = ["--mag-noise", "500", "--acc-noise", "0.1", "--gyro-bias=0.02,0,0", "--rate-scale", "2"]
    argv = ["simulate", "--observer", "mahony", "--runs", "5", "--duration", "3", "--dt", "0.02", "--quiet"]
    assert cli.main([*argv, *flags, "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["study"] == "ahrs" and d["complete"] and d["runs_done"] == 5
    assert d["config"]["observer"] == "mahony" and d["config"]["mag_noise_std"] == pytest.approx(0.5)
    scn = jaxatt.api.ahrs_scenario(mag_noise_std=0.5, acc_noise_std=0.1, gyro_bias=(0.02, 0.0, 0.0), rate_scale=2.0)
    ref = jaxatt.monte_carlo("mahony", runs=5, duration=3.0, dt=0.02, scenario=scn)
    for k in ("mean_angle_error_deg", "final_angle_error_deg", "std_roll", "std_yaw", "std_bias"):
        np.testing.assert_allclose(d["metrics"][k]["per_run"], ref.per_run[k], rtol=1e-12, atol=0, err_msg=k)
    assert_provenance(d["environment"])
    # --gains: a gains file of the filter replaces its shipped gains (the same program: the gains are arguments)
    from jaxatt.fitting import gainsfile

    entry = registry.get("mahony")
    tuned = entry.params()._replace(kp=entry.params().kp * 4.0)
    gains = tmp_path / "mahony_gains.json"
    gainsfile.write(gains, observer="mahony", params=tuned, gains=entry.gains, status="done")
    out2 = tmp_path / "mahony_tuned.json"
    assert cli.main([*argv, *flags, "--gains", str(gains), "--json", str(out2)]) == 0
    d2 = json.loads(out2.read_text())
    assert d2["gains_file"] == str(gains)
    assert d["notes"][0].startswith("mahony with its default gains, set up")  # mahony ships none
    assert d2["notes"][0].startswith(f"mahony with the gains of {gains}, set up")  # it said "its shipped gains"
    ref2 = jaxatt.monte_carlo("mahony", str(gains), runs=5, duration=3.0, dt=0.02, scenario=scn)
    np.testing.assert_allclose(
        d2["metrics"]["mean_angle_error_deg"]["per_run"], ref2.per_run["mean_angle_error_deg"], rtol=1e-12, atol=0
    )
    assert d2["metrics"]["mean_angle_error_deg"]["mean"] != d["metrics"]["mean_angle_error_deg"]["mean"]
    assert cli.main([*argv, "--gains", str(gains), "--observer", "madgwick"]) == 2  # gains of another filter


@pytest.mark.parametrize(
    "argv",
    [
        ["--observer", "mahony", "--duration", "3", "--dt", "0.02"],
        [
            "--observer",
            "complementary",
            "--scenario",
            "rotating",
            "--duration",
            "3",
            "--dt",
            "0.01",
            "--vector-noise",
            "0.02",
        ],
    ],
)
def test_simulate_plot_of_an_ahrs_filter_or_the_complementary_observer_draws_the_runs_it_scored(tmp_path, argv):
    """--plot of a study without a figure of its paper's (an AHRS filter, Trumpf et al.'s observer) draws the angle
    error of every run: the traces behind it (saved in the runs file) end at each run's final angle error as the
    metrics reduced it, they sit on a regular grid of at most 500 times, and the figure is a PNG with data drawn."""
    from test_notebooks import check_figures

    out, fig = tmp_path / "sim.json", tmp_path / "sim.png"
    assert cli.main(["simulate", *argv, "--runs", "4", "--quiet", "--json", str(out), "--plot", str(fig)]) == 0
    d = json.loads(out.read_text())
    assert d["plot"] == str(fig)
    check_figures(tmp_path, ["sim"])
    with np.load(f"{out}.runs.npz") as z:
        t, angle = z["0/traces/t"], z["0/traces/angle_error_deg"]
    assert angle.dtype == np.float32 and angle.shape == t.shape and t.shape[0] == 4
    steps = np.diff(t[0])
    assert 3.0 / 500 <= steps[0] and np.allclose(steps, steps[0]) and t[0, -1] == pytest.approx(3.0)
    final = d["metrics"]["final_angle_error_deg"]["per_run"]
    np.testing.assert_allclose(angle[:, -1], final, rtol=1e-6)
    assert np.ptp(final) > 0  # four runs, four noise draws: the comparison is run by run


#: The simulate flags each kind of observer refuses (the set-up flags of the other kinds).
_PAPER_FLAGS = ["trajectory", "latitude", "reference", "gyro_arw", "r0", "x1_init", "m_init", "integrator", "x2_0"]
_PAPER_FLAGS += ["v0", "epsilon"]
_COMPLEMENTARY_FLAGS = ["scenario", "form", "gain", "k_i", "vector_noise"]
SIMULATE_REFUSED = {
    "madgwick": _PAPER_FLAGS + _COMPLEMENTARY_FLAGS + ["r0_euler", "hold"],
    "complementary": _PAPER_FLAGS + ["acc_noise", "mag_noise", "rate_scale", "gains"],
    "batista-ges": _COMPLEMENTARY_FLAGS + ["gyro_noise", "acc_noise", "gains"],
}


@pytest.mark.parametrize("observer", sorted(SIMULATE_REFUSED))
def test_simulate_refuses_each_flag_its_observer_does_not_take(observer):
    """An AHRS filter, the complementary observer and a paper study each refuse the set-up flags of the others in
    one line naming the flag, before anything is computed, and refuse no other flag."""
    base = cli._parser().parse_args(["simulate", "--observer", observer])
    refused = []
    for attr in cli._SIMULATE_FLAGS:
        args = argparse.Namespace(**vars(base))
        setattr(args, attr, "given")
        flag = "--" + attr.replace("_", "-")
        if attr in SIMULATE_REFUSED[observer]:
            with pytest.raises(cli.UserError, match=f"^{flag} does not apply to {observer}$"):
                cli._simulate(args)
            refused.append(attr)
    assert sorted(refused) == sorted(SIMULATE_REFUSED[observer])
    kind = {"madgwick": "ahrs", "complementary": "complementary", "batista-ges": "batista"}[observer]
    assert set(cli._SIMULATE_FLAGS) - cli._SIMULATE_TAKES[kind] == set(SIMULATE_REFUSED[observer])


def test_reproduce_batista_ges_plot_of_a_run_shorter_than_its_trace_interval(tmp_path):
    """The batista-ges figure traces run 0 every 0.1 s; a run of 5 steps is traced at every step (a trace interval
    longer than the run is refused by the Monte Carlo), and the figure is written."""
    png = tmp_path / "ges.png"
    argv = ["reproduce", "batista-ges", "--runs", "1", "--duration", "0.05", "--quiet", "--plot", str(png)]
    assert cli.main(argv) == 0
    assert png.stat().st_size > 10_000


def test_filter_command_writes_a_registry_entry_of_yours_in_the_frame_asked(tmp_path, monkeypatch):
    """--observer module:ENTRY (a registry Entry of your own) with --frame NED --offline: the backward pass's
    quaternion is written in NED, as for a registered name (it stayed in the entry's ENU: 180 deg off)."""
    import jaxatt
    from jaxatt.data import logs

    (tmp_path / "my_entry.py").write_text(
        "from jaxatt.observers import registry\n"
        "ENTRY = registry.get('madgwick')._replace(name='my_madgwick', module='')\n"
    )
    samples, _ = _sim_log(3.0)
    log = tmp_path / "log.npz"
    logs.save_log(log, samples)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "est.csv"
    argv = [
        "filter",
        "--log",
        str(log),
        "--observer",
        "my_entry:ENTRY",
        "--frame",
        "NED",
        "--offline",
        "--out",
        str(out),
    ]
    assert cli.main(argv) == 0
    ned = np.genfromtxt(out, delimiter=",", names=True)
    ref = jaxatt.filter("madgwick", samples.gyr, samples.acc, samples.mag, t=samples.t, offline=True)
    want = jaxatt.frames.change_frame(ref.outputs["backward_q"], "NED", "ENU")
    np.testing.assert_allclose(np.column_stack([ned[f"backward_q_{ax}"] for ax in "wxyz"]), want, atol=1e-12)
