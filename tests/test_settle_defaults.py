"""The devices' ``settle_s`` keys are the procedures' default wait before a capture."""

from __future__ import annotations

import pytest

from rigctl.config import load_rig
from rigctl.errors import ConfigError
from rigctl.procedures import get_procedure


def _rig(rig_file, head_settle=None, arm_settle=None, procedures: str = ""):
    extra = ""
    if procedures:
        extra += "procedures:\n" + procedures
    path = rig_file(extra=extra, arm=True, camera=True)
    text = path.read_text()
    if head_settle is not None:
        text = text.replace("  head:\n", f"  head:\n    settle_s: {head_settle}\n", 1)
    if arm_settle is not None:
        text = text.replace("  arm: {host: 127.0.0.1}",
                            f"  arm: {{host: 127.0.0.1, settle_s: {arm_settle}}}", 1)
    path.write_text(text)
    return load_rig(path)


def _settle(procedure: str, config, **overrides) -> float:
    return get_procedure(procedure).parse_params(config, overrides).settle_s


def test_without_device_settles_each_procedure_keeps_its_own_default(rig_file):
    config = _rig(rig_file)
    assert _settle("active-camera", config) == 0.3
    assert _settle("head-sweep", config) == 0.1
    assert _settle("hand-eye", config) == 0.2


def test_a_procedure_waits_the_settle_of_the_devices_it_moves(rig_file):
    config = _rig(rig_file, head_settle=0.07, arm_settle=0.45)
    assert _settle("head-sweep", config) == 0.07       # moves the head only
    assert _settle("hand-eye", config) == 0.45         # the arm
    assert _settle("robot-kinematics", config) == 0.45
    assert _settle("validate-arm", config) == 0.45
    assert _settle("active-camera", config) == 0.45    # head and arm: the longer
    # a device that states nothing keeps the procedure's own wait after its moves
    head_stated = _rig(rig_file, head_settle=0.07)
    assert _settle("active-camera", head_stated) == 0.3  # its own 0.3 for the arm's moves
    assert _settle("head-sweep", head_stated) == 0.07
    assert _settle("hand-eye", head_stated) == 0.2       # the head does not move there
    arm_stated = _rig(rig_file, arm_settle=0.01)
    assert _settle("active-camera", arm_stated) == 0.3   # its own 0.3 for the head's moves
    assert _settle("robot-kinematics", arm_stated) == 0.01


def test_a_device_the_rig_lacks_does_not_count(rig_file):
    path = rig_file()  # a head, no arm
    path.write_text(path.read_text().replace("  head:\n", "  head:\n    settle_s: 0.07\n", 1))
    config = load_rig(path)
    assert config.devices.arm is None
    assert _settle("head-sweep", config.model_copy(update={"procedures": {}})) == 0.07


def test_the_procedures_section_and_the_run_override_the_device_settle(rig_file):
    config = _rig(rig_file, head_settle=0.07, procedures="  head-sweep: {settle_s: 0.5}\n")
    assert _settle("head-sweep", config) == 0.5
    assert _settle("head-sweep", config, settle_s=0.0) == 0.0
    assert _settle("head-sweep", config.model_copy(update={"procedures": {}})) == 0.07


def test_a_negative_device_settle_is_refused_by_its_key(rig_file):
    with pytest.raises(ConfigError, match=r"devices\.head\.settle_s"):
        _rig(rig_file, head_settle=-1)
