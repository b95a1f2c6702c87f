"""Procedures: one module each. ``get_procedure(name)`` looks one up by name."""

from __future__ import annotations

from importlib import import_module

from rigctl.errors import ConfigError

from .base import Procedure

_MODULES = {
    "head-sweep": "rigctl.procedures.head_sweep",
    "arm-sweep": "rigctl.procedures.arm_sweep",
    "capture-survey": "rigctl.procedures.capture_survey",
    "active-camera": "rigctl.procedures.active_camera",
    "hand-eye": "rigctl.procedures.hand_eye",
    "robot-kinematics": "rigctl.procedures.robot_kinematics",
    "validate-arm": "rigctl.procedures.validate_arm",
}

# the procedures with ``uses_solve_process``, by name: ``rigctl solve`` starts the process
# before it imports the procedure's module (checked against each in the tests)
SOLVE_PROCESS_USERS = frozenset({"active-camera"})


def procedure_names() -> list[str]:
    return sorted(_MODULES)


def get_procedure(name: str) -> Procedure:
    """The procedure called ``name``; ``ConfigError`` lists the known ones otherwise."""
    module_name = _MODULES.get(name)
    if module_name is None:
        raise ConfigError(f"unknown procedure {name!r}; known: {', '.join(procedure_names())}")
    module = import_module(module_name)
    return module.PROCEDURE
