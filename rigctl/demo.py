"""``make demo``: the main job on the simulated rig.

Starts the whole simulated rig (`rigctl sim up` on ``mocks/worlds/default.yaml``), runs
``capture-survey`` through the runner (recorded under ``demo-records/``), prints what it
saw, and stops the rig. Later issues replace it with the full calibration pipeline.
"""

from __future__ import annotations

import sys
from pathlib import Path

from rich.console import Console

from mocks.world import WORLDS
from rigctl.config import load_rig
from rigctl.runner import Runner
from rigctl.simrig import SimulatedRig

console = Console(stderr=True)


def main() -> int:
    records = Path("demo-records").resolve()
    console.rule("rigctl demo: capture-survey on the simulated rig (default world)")
    with SimulatedRig(WORLDS / "default.yaml", host="127.0.0.1", records=records) as rig_path:
        outcome = Runner(load_rig(rig_path)).run("capture-survey", {})
    console.print(f"run {outcome.run_id}: {outcome.status}"
                  + (f" ({outcome.reason})" if outcome.reason else ""))
    console.print(f"records in {outcome.run_dir}")
    if outcome.result:
        console.print(outcome.result["summary"])
    return 0 if outcome.status == "succeeded" else 1


if __name__ == "__main__":
    sys.exit(main())
