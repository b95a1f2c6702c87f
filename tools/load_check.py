"""Run tests while busy loops occupy cores: does the suite hold on a busy machine?

    python tools/load_check.py --busy 2 --runs 3                 # whole suite, two busy cores
    python tools/load_check.py --busy 1 --runs 10 --e2e          # end-to-end tests, one busy core

Each busy loop is its own process (a pure-Python spin), started before the first run and
stopped by PID when the check ends, whatever happens. Prints one line per run and a JSON
summary; exits 0 only when every run passed. A failed run keeps its pytest temporary
folder (the stand-ins' ``sim-up.log``, the run records; its path is in the summary), a
passed one's is removed. The folder is a short one under the system's temp folder: the
tests make Unix sockets in it, whose paths may not exceed 107 bytes.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
E2E = ["tests/test_e2e_default_world.py", "tests/test_stalls.py",
       "tests/test_signals.py"]


def start_busy_loops(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                             stdin=subprocess.DEVNULL, start_new_session=True)
            for _ in range(n)]


def stop(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)


MARKER = "RIGCTL_LOAD_CHECK_RUN"


def stop_marked(value: str) -> list[int]:
    """SIGKILL every process whose environment carries ``MARKER=value``; their PIDs."""
    needle = f"{MARKER}={value}".encode()
    stopped = []
    for entry in Path("/proc").iterdir() if Path("/proc").is_dir() else []:
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if needle in (entry / "environ").read_bytes().split(b"\0"):
                os.kill(int(entry.name), signal.SIGKILL)
                stopped.append(int(entry.name))
        except (OSError, ProcessLookupError):
            continue  # gone meanwhile, or not ours to read
    return stopped


def _interrupt(*_) -> None:
    """SIGTERM ends the check like Ctrl-C: the running pytest and the busy loops are
    stopped on the way out."""
    raise KeyboardInterrupt


def run_once(tests: list[str], extra: list[str], log_path: Path
             ) -> tuple[int, float, Path | None]:
    """One pytest run; interrupted, its pytest is stopped by PID (SIGINT first, so that
    pytest's own teardown stops what the tests started, then SIGKILL). Its temporary
    folder (``--basetemp``) is kept, and returned, only when it failed."""
    t0 = time.monotonic()
    basetemp = Path(tempfile.mkdtemp(prefix="rigctl-load-"))
    # every process of this run inherits the marker, those in sessions of their own too
    # (`sim up` starts its stand-ins so): what a killed pytest could not stop is found by it
    env = {**os.environ, MARKER: basetemp.name}
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # as `make test` runs (Makefile: unexport)
    with log_path.open("w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                                 "--basetemp", str(basetemp), *tests, *extra], cwd=ROOT,
                                stdout=log, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True)  # its workers and stand-ins: one group
        try:
            code = proc.wait()
        except BaseException:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)
            left = stop_marked(basetemp.name)
            if left:
                print(f"stopped {len(left)} processes the run left: {left}", file=sys.stderr)
            raise
    seconds = time.monotonic() - t0
    if code == 0:
        shutil.rmtree(basetemp, ignore_errors=True)
        return code, seconds, None
    return code, seconds, basetemp


def last_line(path: Path) -> str:
    lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
    return lines[-1] if lines else ""


def make_test_workers() -> int:
    """The pytest workers `make test` starts: the Makefile's ``TEST_WORKERS`` default."""
    for line in (ROOT / "Makefile").read_text().splitlines():
        if line.startswith("TEST_WORKERS ?="):
            return int(line.split("=", 1)[1])
    raise SystemExit("tools/load_check.py: no `TEST_WORKERS ?= N` line in the Makefile")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--busy", type=int, default=2, help="busy loops (cores kept busy)")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--e2e", action="store_true", help="only the end-to-end tests")
    parser.add_argument("--logs", default="load-check-logs", help="one pytest log per run")
    parser.add_argument("pytest_args", nargs="*", help="passed to pytest (after --)")
    args = parser.parse_args(argv)
    # the whole suite as `make test` runs it (its workers), the end-to-end files in one
    tests = E2E if args.e2e else ["-n", str(make_test_workers()), "--dist", "loadgroup"]
    logs = Path(args.logs)
    logs.mkdir(parents=True, exist_ok=True)
    busy = start_busy_loops(args.busy)
    results = []
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        for k in range(1, args.runs + 1):
            log_path = logs / f"{'e2e' if args.e2e else 'suite'}-busy{args.busy}-run{k}.log"
            code, seconds, kept = run_once(tests, args.pytest_args, log_path)
            results.append({"run": k, "exit": code, "seconds": round(seconds, 1),
                            "log": str(log_path), "summary": last_line(log_path),
                            "tmp_kept": str(kept) if kept else None})
            print(f"run {k}/{args.runs}: {'PASS' if code == 0 else 'FAIL'} in {seconds:.0f} s "
                  f"- {results[-1]['summary']}", file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        print("load check interrupted", file=sys.stderr)
        return 130
    finally:
        stop(busy)
    passed = sum(r["exit"] == 0 for r in results)
    print(json.dumps({"what": "e2e" if args.e2e else "suite", "busy_cores": args.busy,
                      "runs": len(results), "passed": passed, "results": results}, indent=2))
    return 0 if passed == len(results) == args.runs else 1


if __name__ == "__main__":
    sys.exit(main())
