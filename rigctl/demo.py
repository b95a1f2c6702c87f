"""``make demo``: the main job on the simulated rig.

Today: starts the Dynamixel bus stand-in, writes a rig file pointing at it, runs
``head-sweep`` through the runner (recorded under ``demo-records/``), prints the
result, and stops the stand-in. Later issues replace this with the full calibration.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from rich.console import Console

from rigctl.bench.common import StandIn
from rigctl.config import load_rig
from rigctl.runner import Runner

console = Console(stderr=True)


def main() -> int:
    records = Path("demo-records").resolve()
    with tempfile.TemporaryDirectory(prefix="rigctl-demo-") as tmp:
        link = Path(tmp) / "dxl"
        with StandIn(["-m", "mocks.dynamixel_bus", "--link", str(link), "--wire-timing"]):
            rig = Path(tmp) / "rig.yaml"
            rig.write_text(
                "name: demo-rig\n"
                f"records: {{directory: {records}}}\n"
                "devices:\n"
                f"  head: {{port: {link}, speed_cap_dps: 90, accel_cap_dps2: 360}}\n")
            console.rule("rigctl demo: head-sweep on the Dynamixel stand-in")
            outcome = Runner(load_rig(rig)).run(
                "head-sweep", {"pan_deg": [-15, 0, 15], "tilt_deg": [-10, 0, 10],
                               "roll_deg": [0, 90]})
    console.print(f"run {outcome.run_id}: {outcome.status}"
                  + (f" ({outcome.reason})" if outcome.reason else ""))
    console.print(f"records in {outcome.run_dir}")
    if outcome.result:
        for axis, err in outcome.result["axes"].items():
            console.print(f"  {axis:5s} commanded vs encoder: rms {err['rms_deg']:.4f} deg, "
                          f"max {err['max_abs_deg']:.4f} deg (one encoder pulse = 0.0879 deg)")
    return 0 if outcome.status == "succeeded" else 1


if __name__ == "__main__":
    sys.exit(main())
