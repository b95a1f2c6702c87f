"""The benchmark's error / sigma of the identified link parameters compares like with
like: offsets along the parallel joints 2-4 are one identified sum."""

from __future__ import annotations

import pytest

from rigctl.bench.truth import identified_value, link_z


def _links(d):
    return [{"theta_offset": 0.0, "d": v, "a": 0.0, "alpha": 0.0, "beta": 0.0} for v in d]


def test_d2_left_at_its_start_and_d4_carrying_the_rest_is_no_error():
    truth = {"arm": {"links": _links([0.1807, 0.0003, -0.0001, 0.17415, 0.11985, 0.11655])}}
    # the refinement kept link-by-link's d2 = 4 mm (not identified) and put the rest in d4
    d4 = 0.0003 - 0.0001 + 0.17415 - 0.004
    result = {"links": _links([0.1807, 0.004, 0.0, d4 + 0.00002, 0.11985, 0.11655]),
              "uncertainty": {"parameters": {"link4.d": 0.00001, "link5.d": 0.00001,
                                             "T_flange_cam.x": 0.00001}}}
    z = link_z(result, truth)
    assert set(z) == {"link4.d", "link5.d"}
    assert z["link4.d"] == pytest.approx(2.0)  # the 20 um it is really off, over 10 um
    assert z["link5.d"] == pytest.approx(0.0, abs=1e-9)
    assert identified_value(result["links"], "link4.d") == pytest.approx(0.17437, abs=1e-12)


def test_bench_worlds_reports_each_arm_model_and_the_solve_over_the_motion():
    from rigctl.bench.worlds import summarise

    def row(seed, model, rms, failed=False, motion=30.0, solve=3.0):
        return {"seed": seed, "model": model, "failed": failed, "procedures": {
            "robot-kinematics": {"model_rms_mm": rms},
            "active-camera": {"timings_s": {"motion_s": motion, "solve_s": solve}}}}

    rows = [row(1, "ur5e", 0.05), row(2, "ur5e", 0.11, solve=6.0), row(3, "ur10", 0.2, True)]
    summary = summarise(rows)
    per_model = summary["by_arm_model"]
    assert per_model["ur5e"]["worlds"] == 2 and per_model["ur5e"]["failed"] == 0
    assert per_model["ur5e"]["model_rms_mm"]["median"] == pytest.approx(0.08)
    assert per_model["ur5e"]["model_rms_mm"]["max"] == pytest.approx(0.11)
    assert per_model["ur10"]["failed_seeds"] == [3]
    ratio = summary["solve_over_motion"]["active-camera"]
    assert ratio["median"] == pytest.approx(0.1) and ratio["max"] == pytest.approx(0.2)
    assert summary["solve_over_motion"]["hand-eye"] is None


def test_bench_worlds_until_runs_a_chain_prefix_and_judges_it_alone():
    from rigctl.bench.worlds import PIPELINE, _failed, chain_until, summarise
    from rigctl.errors import ConfigError

    assert chain_until(None) == PIPELINE
    assert chain_until("active-camera") == ("active-camera",)
    assert chain_until("robot-kinematics") == ("active-camera", "hand-eye",
                                               "robot-kinematics")
    with pytest.raises(ConfigError, match=r"--until 'hand_eye'.*hand-eye"):
        chain_until("hand_eye")
    done = {"status": "succeeded", "timings_s": {"motion_s": 30.0, "solve_s": 1.5}}
    row = {"seed": 1, "model": "ur5e", "procedures": {"active-camera": done}}
    assert not _failed(row, chain_until("active-camera"))
    assert _failed(row)  # the whole chain stopped after its first procedure
    assert _failed({**row, "procedures": {"active-camera": {**done, "status": "failed"}}},
                   chain_until("active-camera"))
    summary = summarise([{**row, "failed": False}], chain_until("active-camera"))
    assert list(summary["solve_over_motion"]) == ["active-camera"]
    assert summary["solve_over_motion"]["active-camera"]["max"] == pytest.approx(0.05)
    assert list(summary["times_s"]) == ["active-camera"]


@pytest.mark.parametrize("args, named", [(["--until", "nope"], "--until 'nope'"),
                                         (["--combination", "nope"], "--combination 'nope'")])
def test_bench_worlds_refuses_a_bad_option_before_any_world_runs(args, named, tmp_path):
    import json

    from typer.testing import CliRunner

    from rigctl.cli import app

    result = CliRunner().invoke(app, ["bench", "worlds", "--n", "1", "--json",
                                      "--keep", str(tmp_path / "kept"), *args])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)
    assert named in error["error"] and error["type"] == "ConfigError"
    assert not (tmp_path / "kept").exists()  # nothing started
