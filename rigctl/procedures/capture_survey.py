"""``capture-survey``: move the head over a grid and the arm through a few views of the
target, capturing at each; the solve reports what was seen."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field

from rigctl.errors import SolveError

from .base import (
    CaptureStep,
    MoveArmJoints,
    MoveHead,
    Note,
    Params,
    Procedure,
    Settle,
    SolveContext,
)
from .planning import plan_target_views


class CaptureSurveyParams(Params):
    pan_deg: list[float] = Field(default_factory=lambda: [-10.0, 0.0, 10.0])
    tilt_deg: list[float] = Field(default_factory=lambda: [-5.0, 0.0, 5.0])
    views: int = Field(4, ge=0, le=50, description="arm views of the target")
    view_distance_m: float = Field(0.45, gt=0.1, le=1.5)
    settle_s: float = Field(0.2, ge=0)
    seed: int = 0


class CaptureSurvey(Procedure):
    name = "capture-survey"
    summary = "Head grid at home, then arm views of the target; capture at each."
    params_model = CaptureSurveyParams
    devices = ("head", "camera")
    optional_devices = ("arm",)
    moves = ("head", "arm")  # whose settle_s is the default wait before a capture
    detects_board = True

    def plan(self, params: CaptureSurveyParams, config) -> list:
        steps: list = []
        arm = config.devices.arm
        home = arm.home_rad() if arm else None
        if home is not None:
            steps.append(MoveArmJoints(home, "arm home"))
        for tilt in params.tilt_deg:
            for pan in params.pan_deg:
                label = f"head pan{pan:+g} tilt{tilt:+g}"
                steps += [MoveHead(math.radians(pan), math.radians(tilt), 0.0, label),
                          Settle(params.settle_s), CaptureStep(label, extra={"kind": "head"})]
        steps.append(MoveHead(0.0, 0.0, 0.0, "head home"))
        if arm is not None and params.views:
            poses, notes = plan_target_views(config, params.views, params.view_distance_m,
                                             seed=params.seed)
            steps += [Note(n) for n in notes]
            for k, q in enumerate(poses):
                label = f"target view {k + 1}"
                steps += [MoveArmJoints(tuple(float(v) for v in q), label),
                          Settle(params.settle_s),
                          CaptureStep(label, extra={"kind": "target"})]
            steps.append(MoveArmJoints(home, "arm home"))
        return steps

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        """Counts what was captured and where the board was detected."""
        captures = ctx.captures()
        if not captures:
            raise SolveError("capture-survey: nothing was captured")
        tg = ctx.config.target
        detections, sharpness = 0, []
        targets = [c for c in captures if c.meta.get("extra", {}).get("kind") == "target"]
        for capture in captures:
            if capture.image_path is None:
                continue
            image = capture.load_image()
            import cv2

            sharpness.append(float(cv2.Laplacian(image, cv2.CV_64F).var()))
        for capture in targets:
            if capture.board_corners(tg) is not None:
                detections += 1
        summary = {"captures": len(captures), "target_views": len(targets),
                   "board_detected": detections,
                   "median_sharpness": float(np.median(sharpness)) if sharpness else None}
        return {**summary, "summary": summary}


PROCEDURE = CaptureSurvey()
