"""``solve_recorded`` without the captures an operator excluded, for any procedure: the
solve reads the run without them, the result names them, who excluded which and why is
appended to the run's decisions, the previous result is kept, and an index the run does
not have is refused before anything is solved or written."""

from __future__ import annotations

import json
import math

import pytest

from rigctl.errors import ConfigError
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory
from rigctl.runner import solve_recorded
from tests.test_runner import make_runner

# four captures: pan -10 and 10 deg at tilt 0 and 5 deg
SWEEP = {"pan_deg": [-10, 10], "tilt_deg": [0, 5], "settle_s": 0.0}


def test_excluded_captures_are_left_out_named_and_recorded(rig_config, monkeypatch):
    monkeypatch.setenv("LOGNAME", "ada")  # the user, as getpass finds it
    outcome = make_runner(rig_config)[0].run("head-sweep", SWEEP)
    assert outcome.status == "succeeded" and outcome.result["poses"] == 4
    run = RunDirectory(outcome.run_dir)
    index = RecordIndex(rig_config.database_url())
    again = solve_recorded(run.path, index, exclude=[2, 1, 2], reason="head bumped")
    assert again["poses"] == 2 and again["summary"]["poses"] == 2
    assert again["excluded"] == [1, 2]
    # a procedure that names no captures itself: those it was given, rejections unknown
    assert again["captures"] == {"used": [0, 3], "excluded": [1, 2], "rejected": None}
    assert json.loads((run.path / "result.1.json").read_text()) == outcome.result
    assert index.get(outcome.run_id)["result_summary"]["poses"] == 2
    entry = run.decisions()[-1]
    assert (entry["decision"], entry["by"], entry["comment"], entry["excluded"],
            entry["previous_result"]) == ("excluded", "ada", "head bumped", [1, 2],
                                          "result.1.json")
    # commanded pan of the captures kept: -10 deg at tilt 0, then 10 deg at tilt 5
    kept = [c.meta["head_commanded"]["pan"] for c in run.captures() if c.index in (0, 3)]
    assert [round(math.degrees(p)) for p in kept] == [-10, 10]

    # an index the run lacks: refused, nothing solved, written or recorded
    with pytest.raises(ConfigError, match=r"no capture 4, 9 to exclude \(this run's "
                                          r"captures: 000-003\)"):
        solve_recorded(run.path, index, exclude=[0, 4, 9])
    assert not (run.path / "result.2.json").exists() and len(run.decisions()) == 1

    # a plain re-solve uses every capture again and is the run's own result once more
    assert solve_recorded(run.path, index) == outcome.result
    assert len(run.decisions()) == 1


def test_a_run_without_a_result_keeps_none_and_says_so(rig_config):
    outcome = make_runner(rig_config)[0].run("head-sweep", SWEEP)
    run = RunDirectory(outcome.run_dir)
    (run.path / "result.json").unlink()  # as a failed run leaves it
    again = solve_recorded(run.path, exclude=[0], by="grace")
    assert again["captures"]["used"] == [1, 2, 3]
    assert not list(run.path.glob("result.*.json"))
    assert run.decisions()[-1]["previous_result"] is None
    assert run.decisions()[-1]["by"] == "grace"
