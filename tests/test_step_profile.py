"""benchmarks/step_profile.py: the HLO reading it reports from (ops and bytes of the time loop's body) on a
hand-written module, and the script's smallest run: one study, a few runs and steps, its numbers consistent."""

import json
import pathlib
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import step_profile  # noqa: E402

HLO = """HloModule m

%fused_computation (p: f64[128,3]) -> f64[128,3] {
  %p = f64[128,3]{1,0} parameter(0)
  ROOT %e = f64[128,3]{1,0} exponential(%p)
}

%small_body (t: (s32[], f64[4])) -> (s32[], f64[4]) {
  %t = (s32[], f64[4]{0}) parameter(0)
  %a = f64[4]{0} get-tuple-element(%t), index=1
  ROOT %r = (s32[], f64[4]{0}) tuple(%i, %a)
}

%big_body (t: (s32[], f64[128,3])) -> (s32[], f64[128,3]) {
  %t = (s32[], f64[128,3]{1,0}) parameter(0)
  %x = f64[128,3]{1,0} get-tuple-element(%t), index=1
  %f1 = f64[128,3]{1,0} fusion(%x), kind=kLoop, calls=%fused_computation
  %f2 = (f64[128,3]{1,0}, f32[128]{0}) fusion(%f1), kind=kLoop, calls=%fused_computation
  %s = (f64[128,3,3]{2,1,0}, s32[]) custom-call(%f1), custom_call_target="lapack_dgesvd"
  %c = f64[128,3]{1,0} copy(%f1)
  %k = f64[] constant(1)
  ROOT %r = (s32[], f64[128,3]{1,0}) tuple(%i, %c)
}

ENTRY %main (x: f64[128,3]) -> f64[128,3] {
  %w1 = (s32[], f64[4]{0}) while(%a), condition=%cond, body=%small_body
  %w2 = (s32[], f64[128,3]{1,0}) while(%b), condition=%cond, body=%big_body
}
"""


def test_loop_body_profile_counts_the_largest_while_body():
    p = step_profile.loop_body_profile(HLO)
    assert p["body"] == "big_body"
    assert (p["fusions"], p["custom_calls"], p["other_ops"]) == (2, 1, 1)
    # f1: 128*3*8; f2: 128*3*8 + 128*4; the custom call: 128*9*8 + 4; the copy: 128*3*8 (parameters, tuples,
    # get-tuple-element and constants write nothing)
    assert p["bytes_written"] == 3072 + (3072 + 512) + (9216 + 4) + 3072
    with pytest.raises(ValueError, match="no while loop"):
        step_profile.loop_body_profile("HloModule m\n")


def test_smallest_run_writes_consistent_numbers(tmp_path, capsys):
    assert (
        step_profile.main(
            ["--studies", "complementary", "--batch", "4", "--steps", "20", "--repeats", "1", "--out", str(tmp_path)]
        )
        == 0
    )
    assert "results written to" in capsys.readouterr().out
    (path,) = tmp_path.glob("step_profile-*.json")
    d = json.loads(path.read_text())
    assert {"date_utc", "machine", "versions"} <= set(d["meta"])
    (row,) = d["rows"]
    assert row["study"] == "complementary" and row["batch"] == 4 and row["steps"] == 20
    assert row["fusions"] > 0 and row["bytes_written_per_run_step"] > 0
    assert row["ops_per_step"] == row["fusions"] + row["custom_calls"] + row["other_ops"]
    assert row["run_steps_per_s"] == pytest.approx(1e6 / row["us_per_run_step"], rel=1e-12)
    assert row["ns_per_op_per_run"] == pytest.approx(1e3 * row["us_per_run_step"] / row["ops_per_step"], rel=1e-12)
