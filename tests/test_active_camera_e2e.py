"""active-camera end to end on the simulated rig (default world: distortion, 0.5 px noise,
0.3 deg roll-axis tilt), through the CLI and the real clients."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mocks.world import load_world
from tests.mockproc import ROOT

pytestmark = pytest.mark.integration


@pytest.mark.timeout(300)
def test_active_camera_on_default_world(tmp_path, start_sim):
    rig = start_sim(world="default")
    result = subprocess.run(
        [sys.executable, "-m", "rigctl.cli", "run", "active-camera", "--rig",
         str(rig.rig_path), "--json", "--param", "pan_deg=10", "--param", "tilt_deg=10"],
        capture_output=True, text=True, timeout=240, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout)  # stdout is JSON and nothing else
    truth = load_world(ROOT / "mocks/worlds/default.yaml").truth()
    assert abs(out["fx"] / truth["fx"] - 1) < 0.002
    assert abs(out["fy"] / truth["fy"] - 1) < 0.002
    assert abs(out["cx"] - truth["cx"]) < 1.5 and abs(out["cy"] - truth["cy"]) < 1.5
    assert set(out["strategies"]) >= {"A", "B", "C", "D", "refined"}
    assert "fx" in out["strategies"]["D"] and out["sigma"]["fx"] > 0
    # the 0.3 deg roll-axis tilt shows in the recovered roll axis (about -sin(0.3 deg) in y)
    assert out["roll_axis_in_cam"][1] == pytest.approx(truth["roll_axis_in_cam"][1], abs=2e-3)
    run_dirs = list((tmp_path / "records").glob("*active-camera*"))
    assert len(run_dirs) == 1
    for name in ("camera.opencv.yaml", "camera_info.yaml", "plots/contours.png",
                 "plots/residuals.png", "result.json"):
        assert (run_dirs[0] / name).exists(), name
    # eight head poses and one after the arm moved the camera 10 mm sideways
    assert len(list(Path(run_dirs[0], "captures").glob("*.png"))) == 9
    depths = out["tracking"]["scene_depth"]
    assert depths["contours_measured"] >= 6
    assert np.linalg.norm(depths["move_in_camera_mm"]) == pytest.approx(10.0, rel=0.01)
    # the scene (2-6 m in this world) at the depths the world placed it
    assert 1.5 < depths["depth_m"]["min"] < depths["depth_m"]["max"] < 8.0
    # this world's camera sits on the head's axes: the estimated offset says so
    parallax = out["parallax"]
    assert parallax["estimated"]
    for got, sigma in zip(parallax["centre_offset_mm"], parallax["sigma_mm"], strict=True):
        assert abs(got) < max(3 * sigma, 0.3)
    for key in ("fx", "fy", "cx", "cy"):
        assert abs(out[key] - truth[key]) < max(3 * out["sigma"][key], 0.2), key
