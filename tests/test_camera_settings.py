"""Intrinsics carry the camera settings they were calibrated at; a procedure that uses
them refuses another size or focus (exit 2) unless told to allow it, and records that."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import rigctl.drivers.camera as camera_driver
from rigctl.config import load_rig, parse_rig
from rigctl.drivers.v4l2_controls import V4L2Controls
from rigctl.errors import ConfigError, DeviceError
from rigctl.procedures.camera_settings import check_settings, settings_of_run
from rigctl.record_index import RecordIndex
from rigctl.records import RunDirectory
from rigctl.runner import Runner
from tests.doubles import DoubleHead
from tests.test_v4l2_controls import NEW_NAMES, OLD_NAMES, FakeCamera

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


# -- settings recorded the way a real run records them ----------------------------------
#
# A head-sweep through the runner opens the rig's camera with the real driver
# (rigctl.drivers.camera.OpenCVCamera): cv2.VideoCapture is replaced by a capture that keeps what
# is set, and the V4L2 controls go through rigctl.drivers.v4l2_controls to the fake UVC device of
# tests/test_v4l2_controls.py, which has autofocus. versions.json, settings_of_run (what
# active-camera stores as camera_settings) and the check then run unchanged.

RECORD_RIG = """
name: settings-rig
records: {{directory: {records}}}
devices:
  head:
    port: /dev/null
    limits: {{pan: [-30, 30], tilt: [-20, 20], roll: [-180, 180]}}
    park: {{policy: home, angles_deg: [0, 0, 0]}}
  arm: {{host: 127.0.0.1}}
  camera: {{device: /dev/video0, width: 1280, height: 720, {camera}}}
"""


class FakeCapture:
    """cv2.VideoCapture on a V4L2 device, as much as OpenCVCamera uses of it."""

    def __init__(self, device, api, *params):
        assert (device, api) == ("/dev/video0", cv2.CAP_V4L2)
        self.props: dict[int, float] = {}
        self.opened = True

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        self.props[prop] = float(value)
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def getBackendName(self):
        return "V4L2"

    def read(self):
        time.sleep(0.01)  # a frame period
        shape = (int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]),
                 int(self.props[cv2.CAP_PROP_FRAME_WIDTH]), 3)
        return True, np.zeros(shape, np.uint8)

    def release(self):
        self.opened = False


@pytest.fixture
def fake_v4l2_camera(monkeypatch):
    """Route the camera driver to FakeCapture and a fake UVC device with the given table
    of controls; yields a function that installs a table and returns the fake device."""
    devices = []

    def install(table):
        fake = FakeCamera(table)
        devices.append(fake)
        monkeypatch.setattr(V4L2Controls, "open",
                            classmethod(lambda cls, path: cls(99, path, fake.ioctl)))
        monkeypatch.setattr(V4L2Controls, "close", lambda self: None)  # fd 99 is no file
        return fake

    monkeypatch.setattr(camera_driver.cv2, "VideoCapture", FakeCapture)
    yield install


def write_rig(tmp_path, camera: str, name: str = "rig.yaml"):
    path = tmp_path / name
    path.write_text(RECORD_RIG.format(records=tmp_path / "records", camera=camera))
    return path


def recorded_settings(tmp_path, camera: str) -> dict:
    """Run head-sweep with the camera configured as ``camera``; the settings its
    versions.json holds, as active-camera takes them into its result."""
    config = load_rig(write_rig(tmp_path, camera, "calibration-rig.yaml"))
    outcome = Runner(config, factories={"head": DoubleHead}, show_progress=False).run(
        "head-sweep", {"pan_deg": [0], "tilt_deg": [0], "settle_s": 0.0})
    assert outcome.status == "succeeded", outcome.reason
    return settings_of_run(RunDirectory(outcome.run_dir))


def no_arm(cfg):
    raise DeviceError("no arm in this test")


def hand_eye_inputs(rig, intrinsics: dict, **params) -> dict:
    """Start hand-eye with ``intrinsics`` on ``rig``: the inputs the runner recorded
    (inputs.json) before the run failed on the arm this test does not have."""
    outcome = Runner(load_rig(rig), factories={"arm": no_arm}, show_progress=False).run(
        "hand-eye", {"intrinsics": intrinsics, **params})
    assert outcome.status == "failed" and "no arm in this test" in outcome.reason
    return json.loads((Path(outcome.run_dir) / "inputs.json").read_text())


CALIBRATED = "v4l2_controls: {focus_absolute: 300, exposure_time_absolute: 200}"


@pytest.mark.parametrize("table, autofocus", [(NEW_NAMES, "focus_automatic_continuous"),
                                              (OLD_NAMES, "focus_auto")],
                         ids=["linux>=5.16", "linux<5.16"])
@pytest.mark.parametrize("same", [
    CALIBRATED,
    # the same settings under the other side of the 5.16 renames, autofocus spelled out
    "v4l2_controls: {focus_absolute: 300, exposure_absolute: 200, focus_auto: 0}",
    "v4l2_controls: {exposure_time_absolute: 200, focus_absolute: 300,"
    " focus_automatic_continuous: 0}",
], ids=["same-file", "old-names", "new-names"])
def test_a_real_runs_settings_pass_under_the_same_rig_file(tmp_path, fake_v4l2_camera,
                                                           table, autofocus, same):
    fake = fake_v4l2_camera(table)
    recorded = recorded_settings(tmp_path, CALIBRATED)
    # auto_off turned the device's autofocus off, and the record says so
    assert fake.values[0x009A090C] == 0 and fake.values[0x009A090A] == 300
    assert recorded == {"width": 1280, "height": 720, autofocus: 0, "focus_absolute": 300}
    intrinsics = {**INTR, "settings": recorded}
    inputs = hand_eye_inputs(write_rig(tmp_path, same), intrinsics)
    assert inputs["intrinsics"]["settings"] == recorded
    assert "settings_change_allowed" not in inputs["intrinsics"]


def test_a_camera_without_autofocus_records_none_and_passes(tmp_path, fake_v4l2_camera):
    """auto_off turns autofocus off only on a device that has it: a fixed-focus camera
    records no such control, and the same rig file (auto_off on) still passes."""
    fake_v4l2_camera([c for c in NEW_NAMES if c[0] != 0x009A090C])
    recorded = recorded_settings(tmp_path, CALIBRATED)
    assert recorded == {"width": 1280, "height": 720, "focus_absolute": 300}
    inputs = hand_eye_inputs(write_rig(tmp_path, CALIBRATED), {**INTR, "settings": recorded})
    assert "settings_change_allowed" not in inputs["intrinsics"]


@pytest.mark.parametrize("table", [NEW_NAMES, OLD_NAMES], ids=["linux>=5.16", "linux<5.16"])
@pytest.mark.parametrize("changed, said", [
    ("v4l2_controls: {focus_absolute: 250, exposure_time_absolute: 200}",
     "focus_absolute 300 at calibration, 250 now"),
    # automatics left on: the camera may refocus; the calibration had autofocus off
    ("auto_off: false, v4l2_controls: {focus_absolute: 300}",
     "focus_automatic_continuous 0 at calibration, unset now"),
    ("v4l2_controls: {focus_auto: 1}",
     "focus_absolute 300 at calibration, unset now; "
     "focus_automatic_continuous 0 at calibration, 1 now"),
], ids=["focus-absolute", "automatics-on", "autofocus-on"])
def test_a_changed_focus_is_refused_with_exit_2(tmp_path, fake_v4l2_camera, table,
                                                 changed, said):
    fake_v4l2_camera(table)
    intrinsics = {**INTR, "settings": recorded_settings(tmp_path, CALIBRATED)}
    rig = write_rig(tmp_path, changed)
    done = subprocess.run([sys.executable, "-m", "rigctl.cli", "run", "hand-eye", "--rig",
                           str(rig), "--param", f"intrinsics={json.dumps(intrinsics)}"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert said in " ".join(done.stderr.split())
    # nothing recorded beyond the head-sweep that recorded the settings
    assert [r["procedure"] for r in RecordIndex(load_rig(rig).database_url()).list()] == \
        ["head-sweep"]


def test_allowed_change_is_recorded_in_the_runs_inputs(tmp_path, fake_v4l2_camera):
    fake_v4l2_camera(NEW_NAMES)
    recorded = recorded_settings(tmp_path, CALIBRATED)
    rig = write_rig(tmp_path, "v4l2_controls: {focus_absolute: 250}")
    intrinsics = {**INTR, "settings": recorded}
    with pytest.raises(ConfigError, match="allow_settings_change=true"):
        hand_eye_inputs(rig, intrinsics)
    inputs = hand_eye_inputs(rig, intrinsics, allow_settings_change=True)
    assert inputs["intrinsics"]["settings"] == recorded
    assert inputs["intrinsics"]["settings_change_allowed"] == {
        "focus_absolute": {"calibrated": 300, "now": 250}}
