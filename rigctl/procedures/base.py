"""What a procedure is: parameters, a plan of steps, and a solve.

Procedures never touch hardware (Bluesky's plans-versus-RunEngine split): ``plan``
returns the list of steps the runner executes, and ``solve`` works only on what
was recorded, so any recorded run can be solved again offline.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, ValidationError

from rigctl.config import RigConfig
from rigctl.errors import ConfigError, SolveError
from rigctl.records import Capture, RunDirectory
from rigctl.timing import stage_timer


@dataclass(frozen=True)
class MoveHead:
    """Move the head to pan, tilt, roll (rad)."""

    pan: float
    tilt: float
    roll: float
    label: str = ""
    device: ClassVar[str] = "head"

    def describe(self) -> str:
        return (f"head -> pan {math.degrees(self.pan):+.2f}, tilt {math.degrees(self.tilt):+.2f},"
                f" roll {math.degrees(self.roll):+.2f} deg")


@dataclass(frozen=True)
class MoveArmJoints:
    """Move all six arm joints to ``q`` (rad)."""

    q: tuple[float, ...]
    label: str = ""
    device: ClassVar[str] = "arm"

    def describe(self) -> str:
        return "arm -> q [" + ", ".join(f"{math.degrees(v):+.1f}" for v in self.q) + "] deg"


@dataclass(frozen=True)
class MoveArmJoint:
    """Move one arm joint (0-based ``index``) to ``angle`` (rad), holding the others."""

    index: int
    angle: float
    label: str = ""
    device: ClassVar[str] = "arm"

    def describe(self) -> str:
        return f"arm joint {self.index + 1} -> {math.degrees(self.angle):+.2f} deg"


@dataclass(frozen=True)
class MoveArmLinear:
    """Straight-line TCP move to ``pose`` (x, y, z m; rotation vector rad)."""

    pose: tuple[float, ...]
    label: str = ""
    device: ClassVar[str] = "arm"

    def describe(self) -> str:
        x, y, z = (1000 * v for v in self.pose[:3])
        return f"arm linear -> ({x:.1f}, {y:.1f}, {z:.1f}) mm"


@dataclass(frozen=True)
class Settle:
    """Wait for vibrations to die out before capturing."""

    seconds: float
    label: str = ""
    device: ClassVar[str | None] = None

    def describe(self) -> str:
        return f"settle {self.seconds:.2f} s"


@dataclass(frozen=True)
class CaptureStep:
    """Record the head angles, arm joints and (if ``image``) a fresh camera frame."""

    label: str = ""
    image: bool = True
    extra: dict[str, Any] = field(default_factory=dict, hash=False, compare=False)
    device: ClassVar[str | None] = None

    def describe(self) -> str:
        return f"capture {self.label}" + ("" if self.image else " (readings only)")


@dataclass(frozen=True)
class Note:
    """A planning remark (e.g. a pose skipped as unreachable): logged, shown in dry runs."""

    text: str
    label: str = ""
    device: ClassVar[str | None] = None

    def describe(self) -> str:
        return f"note: {self.text}"


Step = MoveHead | MoveArmJoints | MoveArmJoint | MoveArmLinear | Settle | CaptureStep | Note


class Params(BaseModel):
    """Base of procedure parameter models: unknown keys are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


@dataclass
class SolveContext:
    """What a solve may read: the recorded run, its rig file, parameters and the inputs
    resolved when the run was planned (``inputs.json``: e.g. the intrinsics in use and the
    run they came from). A solve reads nothing else, so a run directory re-solves the same
    anywhere, with or without the index it was recorded in."""

    run: RunDirectory
    config: RigConfig
    params: Any
    inputs: dict[str, Any] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)  # per stage, see ``stage``
    deferred: list[tuple[str, Callable[[], None]]] = field(default_factory=list)
    # in a live run, the outcome of the procedure's ``capture_work`` on each capture's
    # image, by capture index, done while the rig moved on (empty offline: the solve
    # does that work itself, with the same outcome)
    prefetched: dict[int, Any] = field(default_factory=dict)
    # in a live run of a procedure with ``uses_solve_process``, the second process for
    # its solve (``calib.solve_process``), started while the rig moved; in ``rigctl
    # solve``, the one the command started with the plots' modules; else None (the solve
    # starts its own)
    solve_process: Any = None
    # in a live run whose ``capture_work`` has ``after_last_capture``: its outcome, taken
    # on the capture worker once the last capture was in, while the rig made its last
    # moves (active-camera: the whole solve, which ``solve`` uses when it fits the
    # recorded captures); None offline
    after_captures: Any = None

    def stage(self, name: str):
        """Time one stage of the solve (``rigctl bench solve`` prints them)."""
        return stage_timer(self.timings_s)(name)

    def defer(self, name: str, work: Callable[[], None]) -> None:
        """Work the result does not depend on (plots): the runner does it after the
        result is recorded, so it does not delay the recorded result, and a failure in it
        does not fail the calibration (the run still holds the rig until it is done)."""
        self.deferred.append((name, work))

    def run_deferred(self) -> list[str]:
        """The deferred work, each timed as ``after result: NAME``; returns what failed,
        with the reason (a plot that fails is logged, the result stands)."""
        problems = []
        for name, work in self.deferred:
            try:
                with self.stage(f"after result: {name}"):
                    work()
            except Exception as exc:  # any failure here is only reported
                problems.append(f"{name}: {type(exc).__name__}: {exc}")
        self.deferred.clear()
        return problems

    def input(self, key: str) -> Any:
        """One recorded input; a run recorded without it fails with a clear error."""
        if key not in self.inputs:
            raise SolveError(f"{self.run.path / 'inputs.json'}: no {key!r} recorded (the run "
                             "predates recorded inputs); give it as a parameter and re-run")
        return self.inputs[key]

    def captures(self) -> list[Capture]:
        return self.run.captures()

    @property
    def plots_dir(self) -> Path:
        return self.run.plots_dir


class Procedure:
    """Base class. Subclasses set ``name``, ``params_model``, ``devices`` and implement
    ``plan`` and ``solve``."""

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    params_model: ClassVar[type[Params]] = Params
    devices: ClassVar[tuple[str, ...]] = ()  # devices that must be configured
    optional_devices: ClassVar[tuple[str, ...]] = ()
    moves: ClassVar[tuple[str, ...]] = ()  # devices moved before captures
    # the solve reads the checkerboard in its captures: the runner detects it in each
    # capture while the rig moves on, so that solving waits less after the motion
    detects_board: ClassVar[bool] = False
    # the solve hands independent refinements to a second process
    # (``calib.solve_process``): the runner starts it while the rig moves, ``rigctl
    # solve`` as it begins (by name: ``procedures.SOLVE_PROCESS_USERS``)
    uses_solve_process: ClassVar[bool] = False

    def resolve_inputs(self, params: Params, config: RigConfig) -> dict[str, Any]:
        """Inputs from outside the run (earlier calibrations), resolved once when the run
        is planned and recorded in ``inputs.json``; raise ``ConfigError`` if one is missing."""
        return {}

    def device_defaults(self, config: RigConfig) -> dict[str, Any]:
        """Parameter defaults the devices' own keys set. ``settle_s``: the longest wait
        any device this procedure moves before its captures asks, each configured device
        by its ``devices.<device>.settle_s``, or the procedure's own default where that
        key is null; none when no such device states one (the procedure's own)."""
        field = self.params_model.model_fields.get("settle_s")
        if field is None:
            return {}
        devices = [device for name in self.moves
                   if (device := getattr(config.devices, name, None)) is not None]
        if all(device.settle_s is None for device in devices):
            return {}
        return {"settle_s": max(field.default if device.settle_s is None else device.settle_s
                                for device in devices)}

    def parse_params(self, config: RigConfig, overrides: dict[str, Any]) -> Params:
        """The devices' defaults (``device_defaults``), the rig file's ``procedures``
        section, then ``overrides``; errors name the parameter."""
        merged = {**self.device_defaults(config), **config.procedures.get(self.name, {}),
                  **overrides}
        try:
            return self.params_model.model_validate(merged)
        except ValidationError as exc:
            lines = []
            for err in exc.errors():
                key = ".".join(str(p) for p in err["loc"]) or "(params)"
                msg = err["msg"].removeprefix("Value error, ")
                if err["type"] == "extra_forbidden":
                    known = ", ".join(self.params_model.model_fields)
                    msg = f"unknown parameter (known: {known})"
                lines.append(f"{self.name}: param {key}: {msg}")
            raise ConfigError("\n".join(lines)) from None

    def plan(self, params: Any, config: RigConfig) -> list[Step]:
        raise NotImplementedError

    def capture_work(self, params: Any) -> Callable[[Any, dict], Any] | None:
        """Work the solve would do anyway, on each capture's image and its metadata as
        recorded (e.g. its edge map), called in the captures' order: in a live run the
        runner does it on one worker thread while the rig moves on, and the solve finds
        the outcomes in ``SolveContext.prefetched``. The function is made anew for each
        run and may keep what earlier captures gave (active-camera takes its first stages
        on the captures before the rolls). None: no such work. An outcome must be what
        the solve computes from the recorded captures, so a re-solve gives the same
        result.

        The function may have an ``after_last_capture(ctx)`` method: the runner calls it
        on the same worker, once, after the last capture's work, while the rig makes the
        moves after the last capture (e.g. home); its outcome is
        ``SolveContext.after_captures``. A resumed run does not call it (the worker saw
        only the captures since the resume)."""
        return None

    def solve(self, ctx: SolveContext) -> dict[str, Any]:
        raise NotImplementedError
