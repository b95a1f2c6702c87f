"""Resume's bookkeeping without devices: the plan written and read back, where a
resumed run continues and how it approaches that step, which runs can be resumed, and
the rig changes that refuse a resume, each named."""

from __future__ import annotations

import pytest

from rigctl.errors import ConfigError
from rigctl.procedures.base import CaptureStep, MoveArmJoint, MoveArmJoints, MoveHead, Settle
from rigctl.records import RunDirectory
from rigctl.resume import (
    approach,
    check_resumable,
    device_changes,
    next_step,
    read_plan,
    write_plan,
)

Q0 = (0.0, -1.5, 1.5, -1.5, -1.5, 0.0)
PLAN = [MoveHead(0.0, 0.0, 0.0, "head home"),
        MoveArmJoints(Q0, "base"), Settle(0.1), CaptureStep("base", extra={"kind": "sweep"}),
        MoveArmJoint(5, 0.2, "j6 +"), Settle(0.1), CaptureStep("j6 +"),
        MoveArmJoint(4, -1.2, "j5"), Settle(0.1), CaptureStep("j5")]


def _run(tmp_path, taken: list[int]) -> RunDirectory:
    run = RunDirectory.create(tmp_path, "r1")
    write_plan(run, PLAN)
    for k, step in enumerate(taken):
        run.write_capture(k, None, {"index": k, "step": step})
    return run


def test_the_plan_is_recorded_and_read_back_as_it_was(tmp_path):
    run = _run(tmp_path, [])
    assert read_plan(run) == PLAN
    assert read_plan(run)[3].extra == {"kind": "sweep"}


def test_a_resumed_run_redoes_the_moves_to_its_first_missing_capture(tmp_path):
    assert next_step(_run(tmp_path / "a", []), PLAN) == 0
    assert next_step(_run(tmp_path / "b", [3]), PLAN) == 4  # after the base capture
    assert next_step(_run(tmp_path / "c", [3, 6, 9]), PLAN) == 10  # all taken: solve
    # the approach: the head's last angles, then a joint move to the base (the single-joint
    # move that follows holds the other joints where the plan had them)
    moves = approach(PLAN, 4)
    assert moves == [MoveHead(0.0, 0.0, 0.0, "resume: head approach"),
                     MoveArmJoints(Q0, "resume: arm approach")]
    q = list(Q0)
    q[5] = 0.2
    assert approach(PLAN, 7)[1].q == tuple(q)


def _row(status, reason=None):
    return {"run_id": "r1", "status": status, "reason": reason, "pid": 1, "run_dir": "x"}


@pytest.mark.parametrize("status,reason,refused", [
    ("aborted", "SafetyError: protective stop", None),
    ("interrupted", "process 1 ended", None),
    ("failed", "DeviceError: camera stalled", None),
    ("failed", "SolveError: too few views", "not a device fault"),
    ("failed", "internal error: KeyError: 'x'", "not a device fault"),
    ("succeeded", None, "only an aborted, interrupted or device-failed run"),
    ("running", None, "nothing to resume"),
])
def test_which_runs_can_be_resumed(tmp_path, status, reason, refused):
    run = _run(tmp_path, [])
    row = _row(status, reason) | {"run_dir": str(run.path)}
    if refused is None:
        check_resumable(row, run)
    else:
        with pytest.raises(ConfigError, match=refused):
            check_resumable(row, run)


def test_a_changed_rig_is_named_change_by_change():
    then = {"devices": {"arm": {"model": "ur5e", "serial": "S1", "kinematics_hash": "abc"},
                        "camera": {"serial": "0", "settings": {"width": 1280}}}}
    same = {"arm": {"model": "ur5e", "serial": "S1", "kinematics_hash": "abc", "x": 1},
            "camera": {"serial": "0", "settings": {"width": 1280}}}
    assert device_changes(then, same) == []
    now = {"arm": {**same["arm"], "kinematics_hash": "def"},
           "camera": {"serial": "0", "settings": {"width": 640}}, "head": {}}
    assert device_changes(then, now) == [
        "arm robot kinematics hash changed: abc -> def",
        "camera settings changed: {\"width\": 1280} -> {\"width\": 640}",
        "devices changed: head added"]
