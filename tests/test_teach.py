"""Teach mode (free drive) through the real ur_rtde client: the stand-in serves ur_rtde's
teachMode()/endTeachMode() (control-script commands 18 and 19), its control socket plays
the operator's hand (``freedrive``, refused with teach mode off), and the driver leaves
teach mode explicitly."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.drivers.ur import URArm
from rigctl.errors import ConfigError, DeviceError
from rigctl.teach import DESK, TeachStep
from tests.mockproc import control
from tests.test_ur import HOME, arm_config, start_arm
from tests.waiting import wait_until

pytestmark = pytest.mark.integration


@pytest.fixture
def arm_proc(tmp_path):
    proc = start_arm(tmp_path)
    yield proc
    proc.stop()


def _sock(proc) -> str:
    return proc.ready["control"]


@pytest.mark.timeout(120)
def test_free_drive_moves_only_in_teach_mode(arm_proc):
    target = np.degrees(HOME) + np.array([20.0, -10.0, 15.0, 5.0, -30.0, 40.0])
    refused = control(_sock(arm_proc), {"cmd": "freedrive", "q_deg": target.tolist()})
    assert not refused["ok"] and "teach mode is off" in refused["error"]
    with URArm(arm_config(arm_proc.ready["host"])) as arm:
        arm.teach_mode()
        assert control(_sock(arm_proc), {"cmd": "dump"})["teach_mode"] is True
        moved = control(_sock(arm_proc), {"cmd": "freedrive", "q_deg": target.tolist(),
                                          "speed_dps": 90}, timeout=30)
        assert moved["ok"], moved
        # the joints the arm reports are where the hand put it (RTDE, not the socket; the
        # client's newest packet may be a few ticks older than the answer above)
        wait_until(lambda: np.degrees(np.abs(np.asarray(arm.read_state().q)
                                             - np.radians(target))).max() < 1e-6,
                   timeout=10, what="the RTDE joints at the free-drive target")
        # the controller ignores a programmed move while the arm is in the operator's hands
        with pytest.raises(DeviceError, match="short of its target"):
            arm.move_joints(HOME).wait(20)
        assert arm.end_teach_mode() is True
        dump = control(_sock(arm_proc), {"cmd": "dump"})
        assert dump["teach_mode"] is False
        assert "teach mode off: end_teach_mode()" in dump["messages"]
        again = control(_sock(arm_proc), {"cmd": "freedrive", "q_deg": np.degrees(HOME).tolist()})
        assert not again["ok"]
        arm.move_joints(HOME).wait(30)  # programmed motion works again
        assert np.abs(np.asarray(arm.read_state().q) - HOME).max() < 1e-3


@pytest.mark.timeout(60)
def test_the_desk_refuses_presses_without_a_teach_step():
    with pytest.raises(ConfigError, match="no teach step under way"):
        DESK.press("no-such-run", "capture", timeout=1)
    with pytest.raises(ConfigError, match="unknown action"):
        DESK.press(None, "jump", timeout=1)
    session = DESK.open("run-x", TeachStep())
    try:
        assert DESK.active("run-x") == {"run_id": "run-x", "captures": 0, "min_poses": 3,
                                        "max_poses": 100}
    finally:
        DESK.close("run-x", "test over")
    assert DESK.active() is None and not session.presses
