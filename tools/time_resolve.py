"""Time `rigctl solve` of a recorded run as a whole process, against its own solve.

    python tools/time_resolve.py demo-records/<run> --runs 4
    python tools/time_resolve.py demo-records/<run> --runs 4 --json

Issue 43's target: a re-solve as a whole process takes at most 2 s more than its solve
(`rigctl bench solve`'s "to result"). Each run re-solves a copy of the run directory
(without its plots, which are drawn again) in a fresh `python -m rigctl.cli solve`, timed
from its start to its exit. Inside that process the solve's stages are read from
`runner.solve_recorded`'s timings (patched as the module is imported, so the import order
is the command's own): "beyond" is the whole process's seconds less those of the load,
the pipeline and the exports. Prints one line per run and, with --json, a summary. The
copies are removed; the run directory is only read.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOLVE_STAGES = ("load images", "pipeline", "exports")


def _child(copy: Path, out: Path) -> None:
    """In the timed process: `rigctl solve COPY` with ``solve_recorded``'s timings kept,
    written to ``out`` when the process exits."""
    import atexit
    import importlib.abc
    import importlib.util

    stages: dict[str, float] = {}

    class Hook(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name != "rigctl.runner":
                return None
            sys.meta_path.remove(self)
            spec = importlib.util.find_spec(name)
            exec_module = spec.loader.exec_module

            def patched(module):
                exec_module(module)
                solve_recorded = module.solve_recorded

                def timed(*args, **kwargs):
                    return solve_recorded(*args, **{**kwargs, "timings_s": stages})

                module.solve_recorded = timed

            spec.loader.exec_module = patched
            return spec

    sys.meta_path.insert(0, Hook())
    atexit.register(lambda: out.write_text(json.dumps(stages)))
    sys.argv = ["rigctl", "solve", str(copy)]
    from rigctl.cli import app

    app()


def time_once(run_dir: Path, scratch: Path) -> dict:
    copy = scratch / run_dir.name
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(run_dir, copy, ignore=shutil.ignore_patterns("plots"))
    out = scratch / "stages.json"
    out.unlink(missing_ok=True)
    started = time.perf_counter()
    done = subprocess.run([sys.executable, __file__, "--child", str(copy), str(out)],
                          cwd=scratch, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - started
    if done.returncode != 0 or not out.exists():
        raise SystemExit(f"{run_dir}: rigctl solve failed (exit {done.returncode}): "
                         f"{done.stderr[-2000:]}")
    stages = json.loads(out.read_text())
    solve = sum(stages.get(name, 0.0) for name in SOLVE_STAGES)
    return {"whole_s": wall, "solve_s": solve, "beyond_s": wall - solve,
            "plots_s": stages.get("after result: plots", 0.0)}


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        _child(Path(sys.argv[2]), Path(sys.argv[3]))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if not (args.run_dir / "params.json").is_file():
        parser.error(f"{args.run_dir}: not a run directory (no params.json)")
    results = []
    with tempfile.TemporaryDirectory(prefix="rigctl-time-resolve-") as scratch:
        for i in range(args.runs):
            r = time_once(args.run_dir.resolve(), Path(scratch))
            results.append(r)
            print(f"run {i + 1}/{args.runs}: whole {r['whole_s']:.2f} s, solve "
                  f"{r['solve_s']:.2f} s, beyond {r['beyond_s']:.2f} s (plots "
                  f"{r['plots_s']:.2f} s)", file=sys.stderr)
    summary = {"run": str(args.run_dir), "runs": results,
               "beyond_median_s": statistics.median(r["beyond_s"] for r in results),
               "target_beyond_s": 2.0}
    summary["met"] = summary["beyond_median_s"] <= summary["target_beyond_s"]
    if args.json:
        print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
