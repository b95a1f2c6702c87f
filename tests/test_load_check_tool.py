"""tools/load_check.py: what an interrupted run leaves is stopped by its marker."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

from tests.mockproc import ROOT


def _tool():
    spec = importlib.util.spec_from_file_location("load_check", ROOT / "tools" / "load_check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_process_in_its_own_session_carrying_the_marker_is_stopped():
    tool = _tool()
    env = {**os.environ, tool.MARKER: "rigctl-load-test-marker"}
    marked = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], env=env,
                              start_new_session=True)
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"],
                             start_new_session=True)
    try:
        assert tool.stop_marked("rigctl-load-test-marker") == [marked.pid]
        assert marked.wait(timeout=10) == -9
        assert other.poll() is None
    finally:
        for proc in (marked, other):
            if proc.poll() is None:
                proc.kill()
            proc.wait(timeout=10)
