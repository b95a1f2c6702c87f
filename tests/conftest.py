from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest

# One BLAS thread and one OpenCV thread in every test process and in everything the
# tests start (stand-ins, `rigctl run`, the service): the suite runs two pytest workers
# per core, and OpenBLAS's spinning helper threads and OpenCV's thread pool only compete
# with the other workers (the solves' own ``one_blas_thread`` covers a run, not the tests
# that call the math directly). OpenCV's pool cost 7 % more CPU in a robot-kinematics
# run on the default world, and 10 % in an active-camera trial on random world 24, for
# the same result.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
             "OPENCV_FOR_THREADS_NUM"):
    os.environ.setdefault(_var, "1")

import cv2  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

cv2.setNumThreads(1)  # a plugin may have loaded OpenCV before this file

from rigctl.config import load_rig  # noqa: E402

threadpool_limits(limits=1, user_api="blas")  # numpy may be loaded before this file

ROOT = Path(__file__).resolve().parents[1]


def pytest_configure(config):
    """``--dist loadgroup`` under pytest 9 splits every ``xdist_group`` (see
    ``pytest_collection_modifyitems``): refused here, by name, before anything starts."""
    if config.getoption("dist", None) == "loadgroup" and \
            int(pytest.__version__.split(".")[0]) >= 9:
        raise pytest.UsageError(
            f"--dist loadgroup needs pytest < 9 (this is {pytest.__version__}): pytest-xdist "
            "names a test's group in its id, which pytest 9 ignores, so every xdist_group "
            "would be split over the workers; `make test` installs the dev extra's pytest")


@pytest.hookimpl(trylast=True)  # after pytest-xdist has named each test's group
def pytest_collection_modifyitems(config, items):
    """Tests marked ``heavy`` (minutes each: random-world trials, the end-to-end chain)
    run first, in their file order. ``make test`` runs pytest-xdist with ``--dist
    loadgroup``, which hands one unit of work (a test, or an ``xdist_group``) at a time to
    whichever worker is free, in this order: started last, a heavy test would leave the
    other worker idle while it runs.

    A group's tests share their module's simulated rig or service, so they must run on
    one worker. pytest-xdist 3.8 marks them by appending ``@group`` to each test's id,
    which pytest 9 no longer reads: every group was split over the workers, and each
    worker started its own rig (hence ``pytest<9`` in the dev extra). A test of a group
    without the mark stops the run here rather than split silently again."""
    if getattr(config.option, "loadgroup", False):
        split = [item.nodeid for item in items
                 if item.get_closest_marker("xdist_group") and "@" not in item.nodeid]
        if split:
            raise pytest.UsageError(
                f"--dist loadgroup: {len(split)} tests of an xdist_group carry no group "
                f"(e.g. {split[0]}): pytest-xdist cannot group them under this pytest")
    items.sort(key=lambda item: item.get_closest_marker("heavy") is None)


@pytest.fixture
def start_sim(tmp_path: Path):
    """Start ``rigctl sim up`` (``rigctl.simrig.SimulatedRig`` keywords, world "ideal" by
    default); every rig started is stopped, with its stand-ins, by PID in teardown, and
    teardown fails if one had crashed (its stderr is kept in ``sim-up.log``)."""
    from rigctl.simrig import SimulatedRig

    started = []

    def start(world: str = "ideal", **kwargs):
        kwargs.setdefault("records", tmp_path / "records")
        kwargs.setdefault("rig_out", tmp_path / "sim-rig.yaml")
        kwargs.setdefault("log", tmp_path / "sim-up.log")
        started.append(SimulatedRig(world, **kwargs))
        return started[-1]

    yield start
    orphans = [pid for rig in started for pid in rig.stop()]
    assert not orphans, f"stand-ins {orphans} outlived `sim up`"
    crashes = [rig.crash for rig in started if rig.crash]
    assert not crashes, "\n".join(crashes)


@pytest.fixture
def rig_file(tmp_path: Path):
    """Write a rig file with a head (and optionally arm/camera) into tmp_path."""

    def make(extra: str = "", head: bool = True, arm: bool = False, camera: bool = False) -> Path:
        text = "name: test-rig\nrecords:\n  directory: records\ndevices:\n"
        if head:
            text += textwrap.indent(textwrap.dedent("""\
                head:
                  port: /dev/null
                  limits: {pan: [-30, 30], tilt: [-20, 20], roll: [-180, 180]}
                  park: {policy: home, angles_deg: [0, 0, 0]}
                  move_timeout_s: 5
                """), "  ")
        if arm:
            text += "  arm: {host: 127.0.0.1}\n"
        if camera:
            text += "  camera: {device: 0, width: 64, height: 48}\n"
        path = tmp_path / "rig.yaml"
        path.write_text(text + extra)
        return path

    return make


@pytest.fixture
def rig_config(rig_file):
    return load_rig(rig_file())
