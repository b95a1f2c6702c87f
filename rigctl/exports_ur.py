"""Arm-model exports that UR and ROS users load: the UR ROS 2 driver's kinematics YAML
(``kinematics_params_file``, ur_description's ``default_kinematics.yaml`` keys) and a
URDF from ``base_link`` to the camera's optical frame, with the target as a fixed frame.

The model is rigctl's (thesis 1.2.1 with Hayati's beta)::

    T_base_cam(q) = T_base_link0 A_1(q_1) ... A_6(q_6) T_flange_cam,
    A_i = Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i).

Each kinematics entry is the fixed transform from one link frame to the next joint's
origin, about whose z the joint turns: ``passive_{i-1} . active_i`` with
``active_i = Rz(theta_i) Tz(d_i)`` and ``passive_i = Tx(a_i) Rx(alpha_i) Ry(beta_i)``
(the first entry carries ``T_base_link0``). As ur_calibration does, the frames of the
upper arm and forearm are moved onto the physical links: the ``d`` of joints 2 and 3 is
set to zero and the passive segment's end slides along the next joint's axis to the
plane that keeps (``correct_joint``); forward kinematics are unchanged. The last link's
passive part has no entry in the YAML (ur_description fixes wrist_3 -> flange -> tool0);
it goes into the camera's transform in the URDF. Beta terms survive: every entry is a
full 6-DOF transform.
"""

from __future__ import annotations

import math
import warnings
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from rigctl.errors import RigError
from rigctl.geometry.kinematics import KinematicModel
from rigctl.geometry.transforms import inv_T, make_T

LINKS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
          "wrist_2_joint", "wrist_3_joint")
# ur_description's fixed frames after wrist_3_link, and base_link -> base_link_inertia
FLANGE_RPY = (0.0, -math.pi / 2, -math.pi / 2)
TOOL0_RPY = (math.pi / 2, 0.0, math.pi / 2)
BASE_INERTIA_RPY = (0.0, 0.0, math.pi)


def _rz(theta: float) -> np.ndarray:
    return make_T(Rotation.from_euler("z", theta).as_matrix())


def _active(theta: float, d: float) -> np.ndarray:
    T = _rz(theta)
    T[2, 3] = d
    return T


def _passive(a: float, alpha: float, beta: float) -> np.ndarray:
    return make_T(Rotation.from_euler("XY", [alpha, beta]).as_matrix(), [a, 0.0, 0.0])


def rpy_to_T(xyz, rpy) -> np.ndarray:
    """URDF origin: translation, then fixed-axis roll, pitch, yaw (Rz Ry Rx)."""
    return make_T(Rotation.from_euler("xyz", rpy).as_matrix(), xyz)


def T_to_rpy(T: np.ndarray) -> tuple[list[float], list[float]]:
    """Translation and fixed-axis roll, pitch, yaw. At pitch +-90 deg (the flange frame)
    any roll/yaw split of the same rotation is exact; scipy picks yaw 0 and warns."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Gimbal lock detected")
        rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz")
    return T[:3, 3].tolist(), rpy.tolist()


def correct_joint(active: list[np.ndarray], passive: list[np.ndarray], i: int) -> None:
    """Move joint ``i``'s frame to ``d = 0`` (ur_calibration's correction): the passive
    segment's end slides along joint ``i+1``'s axis to the plane ``z = 0`` of the frame
    before joint ``i``; the length and angle of the segment and joint ``i+1``'s ``d``
    absorb the move, so forward kinematics stay exactly as they were."""
    if active[i][2, 3] == 0.0:
        return
    end = active[i] @ passive[i]
    p, z_next = end[:3, 3], end[:3, 2]
    if abs(z_next[2]) < 1e-9:
        raise RigError(f"joint {i + 2}'s axis lies in joint {i + 1}'s plane; "
                       "cannot place the link frames as ur_calibration does")
    t = -p[2] / z_next[2]
    meet = p + t * z_next
    theta = math.atan2(-meet[1], -meet[0])  # UR arm segments have negative length
    active[i] = _rz(theta)
    passive[i] = make_T(_rz(-theta)[:3, :3] @ end[:3, :3], [-math.hypot(meet[0], meet[1]),
                                                              0.0, 0.0])
    active[i + 1] = active[i + 1].copy()
    active[i + 1][2, 3] -= t


def joint_origins(model: KinematicModel) -> tuple[list[np.ndarray], np.ndarray]:
    """The six joint origins (each relative to the previous link frame, the first to the
    controller's base) and the last link's passive part ``T_wrist3_flange``."""
    if model.n != 6:
        raise RigError(f"a UR export needs 6 links; the model has {model.n}")
    active = [_active(model.theta_offset[i], model.d[i]) for i in range(6)]
    active[0] = model.T_base_link0 @ active[0]
    passive = [_passive(model.a[i], model.alpha[i], model.beta[i]) for i in range(6)]
    for i in (1, 2):
        correct_joint(active, passive, i)
    origins = [active[0]] + [passive[i - 1] @ active[i] for i in range(1, 6)]
    return origins, passive[5]


def ur_kinematics(model: KinematicModel, robot_hash: str) -> dict[str, Any]:
    """The ``kinematics`` document of the UR ROS 2 driver's ``kinematics_params_file``."""
    origins, _ = joint_origins(model)
    doc: dict[str, Any] = {}
    for name, T in zip(LINKS, origins, strict=True):
        xyz, rpy = T_to_rpy(T)
        doc[name] = {"x": xyz[0], "y": xyz[1], "z": xyz[2], "roll": rpy[0], "pitch": rpy[1],
                     "yaw": rpy[2]}
    doc["hash"] = robot_hash
    return {"kinematics": doc}


def tool0_in_wrist3() -> np.ndarray:
    return rpy_to_T([0, 0, 0], FLANGE_RPY) @ rpy_to_T([0, 0, 0], TOOL0_RPY)


def _origin(T: np.ndarray) -> str:
    xyz, rpy = T_to_rpy(T)
    return (f'<origin xyz="{" ".join(repr(float(v)) for v in xyz)}" '
            f'rpy="{" ".join(repr(float(v)) for v in rpy)}"/>')


def _fixed(name: str, parent: str, child: str, T: np.ndarray) -> str:
    return (f'  <joint name={quoteattr(name)} type="fixed"><parent link={quoteattr(parent)}/>'
            f'<child link={quoteattr(child)}/>{_origin(T)}</joint>')


def joint_limits_of(model_name: str | None) -> list[tuple[float, float, float, float]]:
    """Per joint (lower, upper, velocity, effort) for the URDF of arm model ``model_name``
    (``rigctl.hardware.ur_models``), as ur_description's ``joint_limits.yaml`` gives them:
    the elbow held to +-180 deg, a joint without limit at +-360 deg. Generic (+-360 deg,
    pi rad/s, 150 N m) for an unknown model."""
    from rigctl.hardware.ur_models import ELBOW_PLANNING_LIMIT_DEG, MODELS

    row = MODELS.get(model_name or "")
    if row is None:
        return [(-2 * math.pi, 2 * math.pi, math.pi, 150.0)] * 6
    out = []
    for i, lim in enumerate(row.position_limits_deg):
        lo, hi = lim if lim is not None else (-360.0, 360.0)
        if i == 2:
            lo, hi = max(lo, -ELBOW_PLANNING_LIMIT_DEG), min(hi, ELBOW_PLANNING_LIMIT_DEG)
        out.append((math.radians(lo), math.radians(hi), math.radians(row.max_speed_dps[i]),
                    float(row.max_effort_nm[i])))
    return out


def urdf_from_kinematics(kinematics: dict[str, Any], T_flange_cam: np.ndarray | None,
                         T_base_target: np.ndarray | None, T_wrist3_flange: np.ndarray,
                         name: str = "rigctl_ur", limits_rad=None,
                         model_name: str | None = None, T_base_cam: np.ndarray | None = None,
                         T_flange_target: np.ndarray | None = None) -> str:
    """A URDF with ur_description's frames, its joints placed from a kinematics document
    exactly as ur_description's xacro places them, then the camera's optical frame on
    ``tool0`` and the target fixed to the base; or, for a camera standing beside the arm
    (``T_base_cam``, eye-to-hand), the camera's optical frame fixed to ``base_link`` and
    the target (``T_flange_target``) on ``tool0``. Joint limits, speeds and efforts are
    arm model ``model_name``'s (``joint_limits_of``); ``limits_rad`` overrides the
    positions."""
    kin = kinematics["kinematics"]
    limits = joint_limits_of(model_name)
    if limits_rad:
        limits = [(lo, hi, v, e) for (lo, hi), (_, _, v, e) in zip(limits_rad, limits,
                                                                     strict=True)]
    links = ["base_link", "base_link_inertia", "base"] + [f"{n}_link" for n in LINKS] + \
        ["flange", "tool0", "camera_optical_frame", "target"]
    lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(name)}>"]
    lines += [f"  <link name={quoteattr(n)}/>" for n in links]
    T_inertia = rpy_to_T([0, 0, 0], BASE_INERTIA_RPY)
    lines.append(_fixed("base_link-base_link_inertia", "base_link", "base_link_inertia",
                        T_inertia))
    lines.append(_fixed("base_link-base_fixed_joint", "base_link", "base", T_inertia))
    parent = "base_link_inertia"
    for i, (link, joint) in enumerate(zip(LINKS, JOINTS, strict=True)):
        e = kin[link]
        T = rpy_to_T([e["x"], e["y"], e["z"]], [e["roll"], e["pitch"], e["yaw"]])
        lo, hi, velocity, effort = limits[i]
        lines.append(f'  <joint name={quoteattr(joint)} type="revolute">'
                     f'<parent link={quoteattr(parent)}/><child link="{link}_link"/>'
                     f'{_origin(T)}<axis xyz="0 0 1"/>'
                     f'<limit lower="{lo!r}" upper="{hi!r}" effort="{effort!r}" '
                     f'velocity="{velocity!r}"/></joint>')
        parent = f"{link}_link"
    lines.append(_fixed("wrist_3-flange", "wrist_3_link", "flange",
                        rpy_to_T([0, 0, 0], FLANGE_RPY)))
    lines.append(_fixed("flange-tool0", "flange", "tool0", rpy_to_T([0, 0, 0], TOOL0_RPY)))
    T_tool0_flange = inv_T(tool0_in_wrist3()) @ T_wrist3_flange
    if T_base_cam is not None:  # eye-to-hand: the camera on the base, the board on tool0
        lines.append(_fixed("base_link-camera_optical_frame", "base_link",
                            "camera_optical_frame", T_inertia @ np.asarray(T_base_cam)))
        if T_flange_target is not None:
            lines.append(_fixed("tool0-target", "tool0", "target",
                                T_tool0_flange @ np.asarray(T_flange_target)))
        lines.append("</robot>")
        return "\n".join(lines) + "\n"
    lines.append(_fixed("tool0-camera_optical_frame", "tool0", "camera_optical_frame",
                        T_tool0_flange @ np.asarray(T_flange_cam)))
    if T_base_target is not None:
        lines.append(_fixed("base_link-target", "base_link", "target",
                            T_inertia @ np.asarray(T_base_target)))
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def model_of(result: dict[str, Any], run_id: str) -> KinematicModel:
    if "links" not in result or not ("T_flange_cam" in result or "T_base_cam" in result):
        raise RigError(f"run {run_id}: result has no arm kinematics to export "
                       "(a robot-kinematics run has)")
    return KinematicModel.from_export(result)


def robot_hash_of(versions: dict | None, run_id: str) -> str:
    arm = ((versions or {}).get("devices") or {}).get("arm") or {}
    value = arm.get("kinematics_hash")
    if not value:
        raise RigError(f"run {run_id}: versions.json has no devices.arm.kinematics_hash "
                       "(the controller sent no KINEMATICS_INFO, or the run predates it); "
                       "the UR driver checks this hash, so no kinematics file is written")
    return str(value)


def export_ur_kinematics(result: dict, path, run_id: str, versions: dict | None) -> None:
    """``--format ur-kinematics``: the UR ROS 2 driver's ``kinematics_params_file``."""
    doc = ur_kinematics(model_of(result, run_id), robot_hash_of(versions, run_id))
    header = (f"# rigctl run {run_id}: calibrated kinematics for the UR ROS 2 driver "
              "(kinematics_params_file)\n")
    path.write_text(header + yaml.safe_dump(doc, sort_keys=False))


def export_urdf(result: dict, path, run_id: str, versions: dict | None) -> None:
    """``--format urdf``: base_link to the camera's optical frame, target fixed."""
    model = model_of(result, run_id)
    arm = ((versions or {}).get("devices") or {}).get("arm") or {}
    _, T_wrist3_flange = joint_origins(model)
    kinematics = ur_kinematics(model, arm.get("kinematics_hash") or "")
    T_base_target = result.get("T_base_target")
    fixed = "T_base_cam" in result  # eye-to-hand: the camera beside the arm
    path.write_text(urdf_from_kinematics(
        kinematics, None if fixed else np.asarray(result["T_flange_cam"]),
        None if T_base_target is None else np.asarray(T_base_target), T_wrist3_flange,
        name=f"rigctl_{result.get('arm_model', 'ur')}_{run_id}",
        model_name=result.get("arm_model"),
        T_base_cam=np.asarray(result["T_base_cam"]) if fixed else None,
        T_flange_target=np.asarray(result["T_flange_target"]) if fixed else None))


def export_ros_static(result: dict, path, run_id: str) -> None:
    """``--format ros-static``: ``T_base_cam`` of a camera standing beside the arm as a
    ROS static transform (YAML: ``frame_id`` base_link, ``child_frame_id``
    camera_optical_frame, translation in metres and rotation as a quaternion x, y, z, w,
    the arguments of tf2_ros ``static_transform_publisher``), from a hand-eye or
    robot-kinematics result of an eye-to-hand rig. ``base_link`` is ur_description's
    (turned half a turn about z from the D-H base, ``BASE_INERTIA_RPY``)."""
    if "T_base_cam" not in result:
        raise RigError(f"run {run_id}: result has no T_base_cam (a hand-eye or "
                       "robot-kinematics run with the head beside the arm has); a camera on "
                       "the flange moves with the arm: export --format urdf")
    T = rpy_to_T([0, 0, 0], BASE_INERTIA_RPY) @ np.asarray(result["T_base_cam"], float)
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    doc = {"frame_id": "base_link", "child_frame_id": "camera_optical_frame",
           "translation": dict(zip("xyz", map(float, T[:3, 3]), strict=True)),
           "rotation": {"x": float(qx), "y": float(qy), "z": float(qz), "w": float(qw)},
           "eye_on_hand": False, "run_id": run_id}
    header = (f"# rigctl run {run_id}: the fixed camera's pose (camera with the head at "
              "home), a static transform base_link -> camera_optical_frame\n")
    path.write_text(header + yaml.safe_dump(doc, sort_keys=False))
