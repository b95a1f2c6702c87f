"""A procedure's plan, checked before anything moves: every head and arm move against
the rig file's soft limits (a linear move along its whole straight line), and every
device the procedure needs present. Used by the runner, the service and a resume."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rigctl import procedures
from rigctl.config import HEAD_AXES, RigConfig
from rigctl.drivers.base import check_axis_limit
from rigctl.errors import ConfigError, RigError, SafetyError
from rigctl.procedures.base import (
    MoveArmJoint,
    MoveArmJoints,
    MoveArmLinear,
    MoveHead,
    Procedure,
    Step,
)


@dataclass
class PlanCheck:
    """A plan with every move checked against the soft limits."""

    procedure: str
    params: dict[str, Any]
    steps: list[Step]
    violations: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {
            "procedure": self.procedure,
            "params": self.params,
            "steps": [{"n": i + 1, "kind": type(s).__name__, "device": s.device,
                       "description": s.describe()} for i, s in enumerate(self.steps)],
            "limits_ok": not self.violations,
            "violations": self.violations,
        }


def prepare_run(config: RigConfig, name: str, overrides: dict[str, Any]
                ) -> tuple[Procedure, Any, PlanCheck]:
    """Procedure, parsed parameters and the plan checked against the soft limits; raises
    ``ConfigError`` for an unknown procedure or bad parameters. Touches no device."""
    procedure = procedures.get_procedure(name)
    params = procedure.parse_params(config, overrides)
    missing = check_plan(config, [], procedure.devices)
    if missing:  # nothing to plan with: say which devices the rig file lacks
        return procedure, params, PlanCheck(name, params.model_dump(), [], missing)
    try:
        steps = procedure.plan(params, config)
    except (ValueError, ArithmeticError) as exc:  # parameters the planner cannot use
        raise ConfigError(f"{name}: cannot plan with these parameters: {exc}") from None
    violations = check_plan(config, steps, procedure.devices)
    return procedure, params, PlanCheck(name, params.model_dump(), steps, violations)


def refuse_violations(plan: PlanCheck) -> None:
    """``SafetyError`` listing every move of ``plan`` outside the soft limits."""
    if plan.violations:
        raise SafetyError("plan refused before any motion:\n" + "\n".join(plan.violations))


def linear_path_q(arm, q_from: list[float], pose, samples: int = 24) -> list[float]:
    """The joints along a straight TCP line (``moveL``) from ``q_from`` to the UR
    ``pose`` (flange, nominal model; position interpolated, rotation slerped), each
    checked against the soft limits; the final joints. ``SafetyError`` names the first
    point out of reach or out of limits."""
    from scipy.spatial.transform import Rotation, Slerp

    from rigctl.geometry.kinematics import nominal_ur
    from rigctl.geometry.transforms import make_T, rotvec_to_R

    model = nominal_ur(arm.model)
    limits = arm.joint_limits_rad()
    T0 = model.fk(q_from)
    R1 = rotvec_to_R(pose[3:6])
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], R1])))
    q = np.asarray(q_from, float)
    for s in np.linspace(0.0, 1.0, samples + 1)[1:]:
        T = make_T(slerp(s).as_matrix(), (1 - s) * T0[:3, 3] + s * np.asarray(pose[:3]))
        try:
            q = model.ik(T, q)
        except RigError:
            raise SafetyError(f"arm: the straight line leaves the arm's reach at "
                              f"{100 * s:.0f} % of the way") from None
        for i, value in enumerate(q):
            lo, hi = limits[i]
            if not lo <= value <= hi:
                raise SafetyError(f"arm.joint{i + 1} would reach {math.degrees(value):.1f} deg "
                                  f"at {100 * s:.0f} % of the straight line, outside the soft "
                                  f"limits [{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg")
    return q.tolist()


def check_plan(config: RigConfig, steps: list[Step], needs: tuple[str, ...]) -> list[str]:
    """Every soft-limit violation and missing device of a plan, as operator messages."""
    problems = []
    for kind in needs:
        if getattr(config.devices, kind) is None:
            problems.append(f"devices.{kind}: the procedure needs it but the rig file has none")
    head, arm = config.devices.head, config.devices.arm
    arm_q: list[float] | None = list(arm.home_rad()) if arm else None
    for n, step in enumerate(steps, start=1):
        try:
            if isinstance(step, MoveHead) and head is not None:
                limits = head.limits_rad()
                for axis, value in zip(HEAD_AXES, (step.pan, step.tilt, step.roll), strict=True):
                    check_axis_limit(f"head.{axis}", value, *limits[axis])
            elif isinstance(step, (MoveArmJoints, MoveArmJoint)) and arm is not None:
                if isinstance(step, MoveArmJoints):
                    arm_q = list(step.q)
                    targets = list(enumerate(step.q))
                else:
                    if arm_q is not None:
                        arm_q[step.index] = step.angle
                    targets = [(step.index, step.angle)]
                limits = arm.joint_limits_rad()
                for i, value in targets:
                    check_axis_limit(f"arm.joint{i + 1}", value, *limits[i])
            elif isinstance(step, MoveArmLinear) and arm is not None and arm_q is not None:
                arm_q = linear_path_q(arm, arm_q, step.pose)
        except SafetyError as exc:
            problems.append(f"step {n} ({step.describe()}): {exc}")
    return problems
