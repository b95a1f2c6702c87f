"""``head-sweep``: move the head over a grid of angles and read the encoders at each.

The solve reports how closely the head reached its commanded angles (the
thesis's active calibration depends on these readings, section 3.4).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field

from rigctl.errors import SolveError

from .base import CaptureStep, MoveHead, Params, Procedure, Settle, SolveContext


class HeadSweepParams(Params):
    pan_deg: list[float] = Field(default_factory=lambda: [-10.0, 0.0, 10.0])
    tilt_deg: list[float] = Field(default_factory=lambda: [-5.0, 0.0, 5.0])
    roll_deg: list[float] = Field(default_factory=lambda: [0.0])
    settle_s: float = Field(0.1, ge=0)
    image: bool = False


class HeadSweep(Procedure):
    name = "head-sweep"
    summary = "Move the head over a grid and record commanded against reached angles."
    params_model = HeadSweepParams
    devices = ("head",)
    optional_devices = ("camera",)
    moves = ("head",)  # whose settle_s is the default wait before a capture

    def plan(self, params: HeadSweepParams, config) -> list:
        steps: list = []
        for roll in params.roll_deg:
            for tilt in params.tilt_deg:
                for pan in params.pan_deg:
                    label = f"pan{pan:+g}_tilt{tilt:+g}_roll{roll:+g}"
                    steps.append(MoveHead(math.radians(pan), math.radians(tilt),
                                          math.radians(roll), label))
                    steps.append(Settle(params.settle_s))
                    steps.append(CaptureStep(label, image=params.image))
        steps.append(MoveHead(0.0, 0.0, 0.0, "home"))
        return steps

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        """Tracking error of the head: reached minus commanded angle, per axis."""
        rows = [c.meta for c in ctx.captures()
                if c.meta.get("head") and c.meta.get("head_commanded")]
        if not rows:
            raise SolveError("head-sweep: no capture recorded head angles")
        reached = np.array([[r["head"][a] for a in ("pan", "tilt", "roll")] for r in rows])
        commanded = np.array([[r["head_commanded"][a] for a in ("pan", "tilt", "roll")]
                              for r in rows])
        err_deg = np.degrees(reached - commanded)
        per_axis = {
            axis: {"rms_deg": float(np.sqrt(np.mean(err_deg[:, i] ** 2))),
                   "max_abs_deg": float(np.max(np.abs(err_deg[:, i])))}
            for i, axis in enumerate(("pan", "tilt", "roll"))
        }
        worst = max(v["max_abs_deg"] for v in per_axis.values())
        return {"poses": len(rows), "axes": per_axis,
                "summary": {"poses": len(rows), "max_abs_error_deg": worst}}


PROCEDURE = HeadSweep()
