"""Intrinsics carry the camera settings they were calibrated at; a procedure that uses
them refuses another size or focus (exit 2) unless told to allow it, and records that."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from procedures.camera_settings import check_settings
from rigctl.config import parse_rig
from rigctl.errors import ConfigError

RIG = """
name: settings-rig
devices:
  arm: {host: 127.0.0.1}
  camera: {device: /dev/video0, width: 1280, height: 720,
           v4l2_controls: {focus_absolute: 300, exposure_time_absolute: 200}}
"""
INTR = {"fx": 900.0, "fy": 905.0, "cx": 640.0, "cy": 360.0, "source": "run X"}


def test_same_size_and_focus_pass_unchanged():
    config = parse_rig(RIG)
    intr = {**INTR, "settings": {"width": 1280, "height": 720, "focus_absolute": 300}}
    assert check_settings(intr, config, allow_change=False) == intr
    # intrinsics that recorded no settings (given by hand, older runs): nothing to compare
    assert check_settings(INTR, config, allow_change=False) == INTR


@pytest.mark.parametrize("settings, said", [
    ({"width": 1920, "height": 1080, "focus_absolute": 300},
     "width 1920 at calibration, 1280 now; height 1080 at calibration, 720 now"),
    ({"width": 1280, "height": 720, "focus_absolute": 250},
     "focus_absolute 250 at calibration, 300 now"),
])
def test_other_size_or_focus_is_refused_then_allowed_and_recorded(settings, said):
    config = parse_rig(RIG)
    intr = {**INTR, "settings": settings}
    with pytest.raises(ConfigError) as refused:
        check_settings(intr, config, allow_change=False)
    assert said in str(refused.value) and "allow_settings_change=true" in str(refused.value)
    allowed = check_settings(intr, config, allow_change=True)
    assert allowed["settings_change_allowed"]
    assert all(d["calibrated"] != d["now"] for d in allowed["settings_change_allowed"].values())


def test_cli_refuses_with_exit_2_before_anything_is_recorded(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text(RIG + f"records: {{directory: {tmp_path / 'records'}}}\n")
    intr = {**INTR, "settings": {"width": 640, "height": 480}}
    done = subprocess.run([sys.executable, "-m", "rigctl.cli", "run", "hand-eye", "--rig",
                           str(rig), "--param", f"intrinsics={json.dumps(intr)}"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "width 640 at calibration, 1280 now" in done.stderr
    assert not (tmp_path / "records").exists() or not any((tmp_path / "records").rglob("*.json"))
