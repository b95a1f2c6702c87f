"""``arm-sweep``: move the arm through joint offsets about home, one joint at a time, and
record commanded against reached joints and the controller's TCP pose."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field

from rigctl.errors import SolveError

from .base import CaptureStep, MoveArmJoint, MoveArmJoints, Params, Procedure, Settle, SolveContext


class ArmSweepParams(Params):
    joints: list[int] = Field(default_factory=lambda: [6, 5, 4], description="1-based")
    offsets_deg: list[float] = Field(default_factory=lambda: [-10.0, 10.0])
    settle_s: float = Field(0.1, ge=0)
    image: bool = False


class ArmSweep(Procedure):
    name = "arm-sweep"
    summary = "Move single arm joints about home; record commanded vs reached joints."
    params_model = ArmSweepParams
    devices = ("arm",)
    optional_devices = ("camera",)
    moves = ("arm",)  # whose settle_s is the default wait before a capture

    def plan(self, params: ArmSweepParams, config) -> list:
        home = config.devices.arm.home_rad()
        steps: list = [MoveArmJoints(home, "home")]
        for joint in params.joints:
            if not 1 <= joint <= 6:
                raise SolveError(f"arm-sweep: joint {joint} is not 1-6")
            for offset in params.offsets_deg:
                label = f"joint{joint}{offset:+g}"
                steps += [MoveArmJoint(joint - 1, home[joint - 1] + math.radians(offset), label),
                          Settle(params.settle_s), CaptureStep(label, image=params.image)]
            steps.append(MoveArmJoint(joint - 1, home[joint - 1], f"joint{joint} home"))
        return steps

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        """Per capture: the largest joint error between commanded and encoder angles."""
        errors = []
        for capture in ctx.captures():
            cmd, arm = capture.meta.get("arm_commanded"), capture.meta.get("arm")
            if not cmd or not arm or cmd.get("index") is None:
                continue
            errors.append(abs(arm["q"][cmd["index"]] - cmd["angle"]))
        if not errors:
            raise SolveError("arm-sweep: no capture recorded arm joints")
        worst = math.degrees(float(np.max(errors)))
        return {"poses": len(errors), "max_joint_error_deg": worst,
                "summary": {"poses": len(errors), "max_joint_error_deg": worst}}


PROCEDURE = ArmSweep()
