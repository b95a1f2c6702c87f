"""``make demo``: the main job on the simulated rig (grows as procedures land)."""

from __future__ import annotations

import sys

from rigctl.cli import app


def main() -> int:
    # Until the stand-ins land: plan the head sweep of the example rig (touches nothing).
    try:
        app(["run", "head-sweep", "--rig", "examples/rig.example.yaml", "--dry-run"])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
