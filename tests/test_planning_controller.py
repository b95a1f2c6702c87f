"""Planning with the controller's own kinematics (pure; no stand-ins: the primary
interface's answer is given to the planner): the arm procedures plan their views with the
DH table the controller reports, record it in their inputs, and keep the nominal plan
when there is none (no primary interface, no KINEMATICS_INFO, a world without
factory_errors, use_controller_model=false)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from rigctl.config import load_rig
from rigctl.drivers.ur_primary import ControllerVersion, KinematicsInfo, PrimaryInfo
from rigctl.errors import DeviceError
from rigctl.geometry.kinematics import nominal_ur
from rigctl.mocks.ur_kinematics import ArmModel
from rigctl.mocks.ur_primary import dh_table
from rigctl.mocks.world import WORLDS, load_world
from rigctl.procedures import get_procedure, planning
from rigctl.procedures.planning import nominal_flange_cam, planning_arm, target_centre
from tests.mockproc import rig_without_devices

VERSION = ControllerVersion("URControl", 5, 11, 1, 108318, "01-01-2024, 00:00:00")


def controller_info(arm: dict, status: int = 1) -> PrimaryInfo:
    """What the stand-in reports for a world's ``arm`` section: its factory model's DH
    table (nominal when the world has no ``factory_errors``), as ``rigctl.mocks.ur_controller``
    builds it."""
    model = ArmModel.nominal(arm["model"])
    if arm.get("factory_errors"):
        model = model.with_errors(**arm["factory_errors"])
    dh = dh_table(model)
    k = KinematicsInfo(tuple(range(1, 7)), tuple(dh["theta"]), tuple(dh["a"]), tuple(dh["d"]),
                       tuple(dh["alpha"]), status)
    return PrimaryInfo(VERSION, k)


class FakeController:
    """Stands in for ``read_primary_info``: returns ``answer`` (or raises it), counts
    the reads."""

    def __init__(self, answer):
        self.answer, self.reads = answer, []

    def __call__(self, host, timeout_s=5.0):
        self.reads.append(host)
        if isinstance(self.answer, Exception):
            raise self.answer
        return self.answer


@pytest.fixture
def controller(monkeypatch):
    """Install a fake controller answer; the plan-to-inputs cache starts empty."""
    monkeypatch.setattr(planning, "_primary_reads", {})

    def install(answer) -> FakeController:
        fake = FakeController(answer)
        monkeypatch.setattr(planning, "read_primary_info", fake)
        return fake

    return install


@pytest.fixture
def world_data():
    return yaml.safe_load((WORLDS / "default.yaml").read_text())


def rig_for(tmp_path, world_data):
    world_path = tmp_path / "world.yaml"
    world_path.write_text(yaml.safe_dump(world_data))
    rig = rig_without_devices(world_path, tmp_path, str(tmp_path / "records"),
                              load_world(world_path))
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    return load_rig(tmp_path / "rig.yaml")


def intrinsics(world_data) -> dict:
    cam = world_data["camera"]
    return {k: cam[k] for k in ("fx", "fy", "cx", "cy")} | {"distortion": cam["distortion"]}


def arm_q(steps) -> list[np.ndarray]:
    return [np.array(s.q) for s in steps if type(s).__name__ == "MoveArmJoints"]


def notes(steps) -> list[str]:
    return [s.text for s in steps if type(s).__name__ == "Note"]


def axis_miss_m(config, model, q) -> float:
    """How far the camera's optical axis (arm ``model``, nominal hand-eye) passes from
    the board centre: every planned view looks straight at it."""
    T = model.fk(q) @ nominal_flange_cam(config)
    _, centre = target_centre(config)
    v = centre - T[:3, 3]
    return float(np.linalg.norm(v - (v @ T[:3, 2]) * T[:3, 2]))


def test_hand_eye_views_are_planned_with_the_controllers_model(tmp_path, controller,
                                                                world_data):
    """With the default world's factory model reported, every view's camera looks at the
    board centre under that model (to the IK's tolerance), not under nominal (the mm of
    factory errors); the plan notes the model and hash, and the inputs record it as the
    plan read it, without reading the controller again."""
    config = rig_for(tmp_path, world_data)
    info = controller_info(world_data["arm"])
    fake = controller(info)
    proc = get_procedure("hand-eye")
    params = proc.params_model(poses=6, intrinsics=intrinsics(world_data))
    steps = proc.plan(params, config)
    factory = planning.controller_dh_model(info.kinematics.as_dict())
    nominal = nominal_ur("ur5e")
    views = arm_q(steps)[:-1]  # the last move is home
    assert len(views) == 6
    assert max(axis_miss_m(config, factory, q) for q in views) < 1e-6
    assert max(axis_miss_m(config, nominal, q) for q in views) > 5e-4
    assert any(info.kinematics.ur_hash() in n and "controller's own kinematics" in n
               for n in notes(steps))
    assert len(fake.reads) == 1
    inputs_arm = proc.resolve_inputs(params, config)["arm_model"]
    assert len(fake.reads) == 1  # the inputs record what the plan read
    assert inputs_arm["source"] == "controller"
    assert inputs_arm["robot_hash"] == info.kinematics.ur_hash()
    assert inputs_arm["controller_version"] == "5.11.1.108318"
    assert inputs_arm["controller_kinematics"]["d"] == list(info.kinematics.d)


def test_robot_kinematics_plans_sweeps_and_views_with_the_controllers_model(
        tmp_path, controller, world_data):
    """Sweep bases, training and held-out views all look at the board centre under the
    controller's model; use_controller_model=false plans with nominal and never asks."""
    config = rig_for(tmp_path, world_data)
    info = controller_info(world_data["arm"])
    controller(info)
    proc = get_procedure("robot-kinematics")
    params = proc.params_model(intrinsics=intrinsics(world_data), random_poses=6,
                               heldout_poses=3, sweep_steps=2, sweep_base_candidates=4,
                               pose_selection="random")
    steps = proc.plan(params, config)
    factory = planning.controller_dh_model(info.kinematics.as_dict())
    views = [np.array(s.q) for s in steps if type(s).__name__ == "MoveArmJoints"
             and s.label.split()[0] in ("train", "heldout", "sweep")]
    assert len(views) >= 9
    assert max(axis_miss_m(config, factory, q) for q in views) < 1e-6
    assert "controller's own kinematics" in notes(steps)[0]

    fake = controller(info)
    off = proc.params_model(**{**params.model_dump(), "use_controller_model": False})
    steps_off = proc.plan(off, config)
    assert fake.reads == []
    assert "use_controller_model=false" in notes(steps_off)[0]
    views_off = [np.array(s.q) for s in steps_off if type(s).__name__ == "MoveArmJoints"
                 and s.label.split()[0] in ("train", "heldout", "sweep")]
    assert max(axis_miss_m(config, nominal_ur("ur5e"), q) for q in views_off) < 1e-6
    assert proc.resolve_inputs(off, config)["arm_model"]["source"] == "nominal"
    assert fake.reads == []


@pytest.mark.parametrize("answer, why", [
    (DeviceError("arm 127.0.0.1:30001: primary interface: connection refused"),
     "no controller model (arm 127.0.0.1:30001"),
    (PrimaryInfo(VERSION, None), "reports no KINEMATICS_INFO"),
])
def test_without_a_controller_model_the_nominal_plan_is_kept(tmp_path, controller,
                                                             world_data, answer, why):
    """No primary interface, or no KINEMATICS_INFO: the plan is the nominal one, step
    for step, with a note saying why; the inputs say nominal."""
    config = rig_for(tmp_path, world_data)
    proc = get_procedure("hand-eye")
    controller(answer)
    params = proc.params_model(poses=5, intrinsics=intrinsics(world_data))
    steps = proc.plan(params, config)
    controller(DeviceError("unused"))
    nominal_steps = proc.plan(params.model_copy(update={"use_controller_model": False}),
                              config)
    assert [s for s in steps if type(s).__name__ != "Note"] == \
        [s for s in nominal_steps if type(s).__name__ != "Note"]
    assert why in notes(steps)[0]
    controller(answer)
    proc.plan(params, config)
    recorded = planning_arm(config, fresh=False).record()
    assert recorded["source"] == "nominal" and recorded["controller_kinematics"] is None
    assert why in recorded["note"]


def test_a_world_without_factory_errors_plans_as_nominal(tmp_path, controller, world_data):
    """The stand-in of a world without factory_errors reports the nominal table: the
    plan (validate-arm's here) is the nominal plan, move for move."""
    del world_data["arm"]["factory_errors"]
    config = rig_for(tmp_path, world_data)
    info = controller_info(world_data["arm"])
    assert np.array_equal(planning.controller_dh_model(info.kinematics.as_dict()).d,
                          nominal_ur("ur5e").d)
    proc = get_procedure("validate-arm")
    params = proc.params_model(poses=4, intrinsics=intrinsics(world_data))
    controller(info)
    with_controller = proc.plan(params, config)
    controller(DeviceError("no primary interface"))
    without = proc.plan(params, config)
    assert "controller's own kinematics" in notes(with_controller)[0]
    assert "up to 0.00 mm and 0.000 deg from the nominal" in notes(with_controller)[0]
    assert [s for s in with_controller if type(s).__name__ != "Note"] == \
        [s for s in without if type(s).__name__ != "Note"]


def test_a_fresh_plan_reads_the_controller_again(tmp_path, controller, world_data):
    """Each plan reads the controller (a recalibrated robot is seen at the next plan);
    only the inputs that follow a plan reuse its answer."""
    config = rig_for(tmp_path, world_data)
    first = controller(controller_info(world_data["arm"]))
    assert planning_arm(config).source == "controller"
    second = controller(DeviceError("gone"))
    assert planning_arm(config, fresh=False).source == "controller" and second.reads == []
    assert planning_arm(config).source == "nominal" and len(second.reads) == 1
    assert planning_arm(config, fresh=False).source == "nominal"
    assert len(first.reads) == 1


def test_no_primary_interface_on_a_real_socket_plans_nominal(tmp_path, world_data,
                                                            monkeypatch):
    """Nothing listening on the arm's address: the read is refused at once and the plan
    is nominal, saying why."""
    from rigctl.loopback import free_host

    monkeypatch.setattr(planning, "_primary_reads", {})
    config = rig_for(tmp_path, world_data)
    config = config.model_copy(update={"devices": config.devices.model_copy(update={
        "arm": config.devices.arm.model_copy(update={"host": free_host(),
                                                     "primary_timeout_s": 2.0})})})
    arm = planning_arm(config)
    assert arm.source == "nominal" and "no controller model" in arm.note
    assert np.array_equal(arm.model.d, nominal_ur("ur5e").d)
