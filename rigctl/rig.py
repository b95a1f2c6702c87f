"""Builds device drivers from the rig file, and opens only the devices a run needs."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from rigctl.config import RigConfig
from rigctl.drivers.base import Device
from rigctl.errors import ConfigError

log = logging.getLogger(__name__)

DeviceFactory = Callable[[Any], Device]


def _head(cfg) -> Device:
    from rigctl.drivers.dynamixel import DynamixelHead

    return DynamixelHead(cfg)


def _arm(cfg) -> Device:
    from rigctl.drivers.ur import URArm

    return URArm(cfg)


def _camera(cfg) -> Device:
    from rigctl.drivers.camera import OpenCVCamera

    return OpenCVCamera(cfg)


DEFAULT_FACTORIES: dict[str, DeviceFactory] = {"head": _head, "arm": _arm, "camera": _camera}


class Rig:
    """The devices of one rig. Devices are built and opened on demand and closed together."""

    def __init__(self, config: RigConfig,
                 factories: dict[str, DeviceFactory] | None = None) -> None:
        self.config = config
        self.factories = {**DEFAULT_FACTORIES, **(factories or {})}
        self.devices: dict[str, Device] = {}

    def configured(self) -> list[str]:
        return [k for k in ("head", "arm", "camera") if getattr(self.config.devices, k) is not None]

    def device_config(self, kind: str):
        cfg = getattr(self.config.devices, kind)
        if cfg is None:
            raise ConfigError(f"{self.config.name}: devices.{kind}: not configured in the rig file")
        return cfg

    def open(self, kind: str) -> Device:
        """Build and open ``kind`` (head, arm, camera) if it is not open yet."""
        if kind not in self.devices:
            device = self.factories[kind](self.device_config(kind))
            device.open()
            self.devices[kind] = device
        return self.devices[kind]

    def stop_all(self) -> list[str]:
        """Stop every open device; returns the errors met (never raises)."""
        problems = []
        for kind, device in self.devices.items():
            try:
                device.stop()
            except Exception as exc:
                problems.append(f"{kind}: stop failed: {exc}")
                log.error("%s: stop failed: %s", kind, exc)
        return problems

    def close_all(self) -> list[str]:
        """Close (and so park) every open device, in reverse order; never raises."""
        problems = []
        for kind in reversed(list(self.devices)):
            try:
                self.devices[kind].close()
            except Exception as exc:
                problems.append(f"{kind}: close/park failed: {exc}")
                log.error("%s: close/park failed: %s", kind, exc)
        self.devices.clear()
        return problems
