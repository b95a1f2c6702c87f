"""active-camera end to end on the simulated rig (default world: distortion, 0.5 px noise,
0.3 deg roll-axis tilt), through the CLI and the real clients."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

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
    assert len(list(Path(run_dirs[0], "captures").glob("*.png"))) == 8
