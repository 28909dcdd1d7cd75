"""The command line end to end on short runs: exit codes, JSON layout, clear errors."""
import json

import numpy as np

from jaxatt import cli


def test_reproduce_batista_so3_writes_metrics_json(tmp_path):
    out = tmp_path / "so3.json"
    rc = cli.main(["reproduce", "batista-so3", "--runs", "2", "--duration", "30", "--quiet", "--json", str(out)])
    assert rc == 0
    d = json.loads(out.read_text())
    assert d["complete"] and d["runs_done"] == 2
    m = d["metrics"]
    assert len(m["mean_angle_error_deg"]["per_run"]) == 2
    for key in ("std_m", "std_v", "std_r_err", "final_angle_error_deg"):
        assert np.isfinite(m[key]["mean"])
    assert d["config"]["integrator"] == "lie" and d["config"]["m_init"] == "rescaled"


def test_observer_specific_flags_are_checked(capsys):
    assert cli.main(["simulate", "--observer", "batista-so3", "--x2-0", "1,2,3", "--runs", "1", "--duration", "1"]) == 2
    assert "does not apply" in capsys.readouterr().err
    assert cli.main(["simulate", "--observer", "batista-ges", "--integrator", "rk4", "--runs", "1", "--duration", "1"]) == 2


def test_simulate_complementary_constant_reference_does_not_converge_rotating_does(tmp_path):
    res = {}
    for scen in ("constant", "rotating"):
        out = tmp_path / f"{scen}.json"
        rc = cli.main(["simulate", "--observer", "complementary", "--scenario", scen, "--runs", "1", "--duration", "60",
                       "--noise-scale", "0", "--quiet", "--json", str(out)])
        assert rc == 0
        res[scen] = json.loads(out.read_text())["metrics"]["final_angle_error_deg"]["mean"]
    assert res["rotating"] < 0.2 < 5.0 < res["constant"]


def test_excitation_command_flags_unobservable_scenario(tmp_path, capsys):
    out = tmp_path / "exc.json"
    assert cli.main(["excitation", "--scenario", "constant", "--duration", "20", "--json", str(out)]) == 0
    assert "NOT exciting" in capsys.readouterr().out
    d = json.loads(out.read_text())
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
