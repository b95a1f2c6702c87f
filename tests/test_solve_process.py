"""``rigctl.calib.solve_process``: a solve's refinements in a second Python process give
the numbers of the same refinements here, bit for bit, and the process is stopped by PID.
Pure math (a synthetic head scene) in a real child process: no mocks. The plots drawn
there are those drawn here, and `rigctl solve` starts one only where it is used."""

from __future__ import annotations

import json
import logging
import os
import signal

import numpy as np
import pytest

from rigctl.calib import active_pipeline
from rigctl.calib.active_plots import draw_active_plots
from rigctl.calib.active_refine import RefineResult, timed_refine
from rigctl.calib.solve_process import SolveProcess
from rigctl.calib.threads import THREADS_VARIABLE
from rigctl.errors import ConfigError, SolveError
from rigctl.procedures import SOLVE_PROCESS_USERS, get_procedure, procedure_names
from tests.test_active_math import CX, CY, FX, _basin_case


@pytest.fixture
def helper():
    """A solve process, stopped and reaped by PID after the test."""
    process = SolveProcess()
    try:
        yield process
    finally:
        process.close()
        assert process.proc.poll() is not None
        with pytest.raises(ProcessLookupError):
            os.kill(process.pid, 0)


def _same(a: RefineResult, b: RefineResult) -> None:
    assert np.array_equal(a.x_all, b.x_all)
    assert np.array_equal(np.asarray(a.covariance), np.asarray(b.covariance))
    assert a.robust_cost == b.robust_cost and a.rms_px == b.rms_px


def test_a_refinement_there_is_the_same_to_the_last_bit(helper):
    motions, starts = _basin_case()
    start = starts["near"]
    future = helper.submit(timed_refine, motions, start, {})
    there, seconds = helper.run(future, timed_refine, motions, start, {})
    here, _ = timed_refine(motions, start, {})
    assert seconds > 0
    _same(there, here)
    # and it is the truth's refinement, not any agreeing pair of numbers
    assert abs(here.cx - CX) < 0.5 and abs(here.cy - CY) < 0.5
    assert here.fx == pytest.approx(FX, rel=2e-3)


@pytest.mark.parametrize("one_basin", [True, False])
def test_the_final_refinements_starts_with_a_helper_end_where_they_end_without(
        helper, monkeypatch, one_basin):
    """The pipeline's starts (``_refine_from_starts``): the first here, the others there,
    the first's refinement on all points taken while the helper scouts; with starts in
    one basin, and in two (every stage through the helper)."""
    if not one_basin:
        monkeypatch.setattr(active_pipeline, "SAME_END_PX", -1.0)
    motions, starts = _basin_case()
    timings_here: dict[str, float] = {}
    timings_there: dict[str, float] = {}
    alone, report_alone = active_pipeline._refine_from_starts(motions, starts, {},
                                                              timings_here)
    shared, report_shared = active_pipeline._refine_from_starts(motions, starts, {},
                                                                timings_there, helper)
    _same(shared, alone)
    assert report_shared == report_alone
    assert set(timings_there) == set(timings_here)
    assert ("final refinement from far" in timings_there) is not one_basin
    assert abs(shared.cx - CX) < 0.5 and abs(shared.cy - CY) < 0.5


def test_a_hopeless_start_is_dropped_with_a_helper_as_without(helper, monkeypatch):
    """With ``HOPELESS_COARSE_RATIO`` at 1 one of two basins is hopeless: the same result
    and report with the helper (which may skip the first start's early refinement on
    all points) as without."""
    monkeypatch.setattr(active_pipeline, "SAME_END_PX", -1.0)
    monkeypatch.setattr(active_pipeline, "HOPELESS_COARSE_RATIO", 1.0)
    motions, starts = _basin_case()
    alone, report_alone = active_pipeline._refine_from_starts(motions, starts, {}, {})
    shared, report_shared = active_pipeline._refine_from_starts(motions, starts, {}, {},
                                                                helper)
    _same(shared, alone)
    assert report_shared == report_alone
    assert sum("hopeless" in report_alone[name] for name in starts) == 1


def test_a_job_still_queued_is_taken_back_and_computed_here(helper):
    """While the child computes one refinement, the jobs queued behind it can be taken
    back (``take_back``): computed here, never there, to the same numbers; the child
    goes on with the jobs after them."""
    motions, starts = _basin_case()
    jobs = [helper.submit(timed_refine, motions, starts[name], {})
            for name in ("near", "far", "near")]
    taken, _ = helper.take_back(jobs[2], timed_refine, motions, starts["near"], {})
    assert jobs[2].cancelled()  # the child was busy with the first: the third waited
    first, _ = helper.take_back(jobs[0], timed_refine, motions, starts["near"], {})
    assert not jobs[0].cancelled()  # already taken there: its outcome from there
    _same(taken, first)
    later = helper.submit(timed_refine, motions, starts["far"], {})
    there, _ = helper.run(later, timed_refine, motions, starts["far"], {})
    _same(there, helper.run(jobs[1], timed_refine, motions, starts["far"], {})[0])
    assert abs(there.cx - CX) < 0.5 and abs(there.cy - CY) < 0.5


def test_a_solve_error_there_comes_back_as_that_error(helper):
    motions, starts = _basin_case()
    few = [active_pipeline.replace(m, ref_points=m.ref_points[:1], moved_points=
                                   m.moved_points[:1]) for m in motions]
    future = helper.submit(timed_refine, few, starts["near"], {})
    there, _ = helper.run(future, timed_refine, few, starts["near"], {})
    here, _ = timed_refine(few, starts["near"], {})
    assert isinstance(there, SolveError) and isinstance(here, SolveError)
    assert str(there) == str(here) and "too few" in str(here)


def test_a_killed_process_hands_its_job_back_to_the_parent(helper, caplog):
    motions, starts = _basin_case()
    os.kill(helper.pid, signal.SIGKILL)
    helper.proc.wait(30)
    with caplog.at_level(logging.WARNING, logger="rigctl.calib.solve_process"):
        future = helper.submit(timed_refine, motions, starts["near"], {})
        there, _ = helper.run(future, timed_refine, motions, starts["near"], {})
    assert f"solve process {helper.pid}" in caplog.text and "computing its job here" \
        in caplog.text
    _same(there, timed_refine(motions, starts["near"], {})[0])
    # every later job is computed here at once
    again = helper.submit(timed_refine, motions, starts["near"], {})
    with pytest.raises(Exception, match="ended"):
        again.result(timeout=0)


def test_only_the_listed_jobs_are_taken(helper):
    with pytest.raises(ValueError, match="not a job it takes"):
        helper.submit(os.getpid)


@pytest.fixture
def plotter():
    """A solve process that imported the plots' modules, stopped by PID after the test."""
    process = SolveProcess(plots=True)
    try:
        yield process
    finally:
        process.close()
        with pytest.raises(ProcessLookupError):
            os.kill(process.pid, 0)


def _plot_inputs(folder):
    rng = np.random.default_rng(7)
    image = (rng.random((120, 160)) * 255).astype(np.uint8)
    curves = [rng.random((40, 2)) * [160, 120] for _ in range(3)]
    return (folder, image, curves, "roll-180", image[::-1].copy(), curves[:2],
            {"pan+5": 0.12, "roll-180": 0.2}, 0.16)


def test_the_plots_drawn_there_are_the_ones_drawn_here(plotter, tmp_path):
    there, here = tmp_path / "there", tmp_path / "here"
    there.mkdir()
    here.mkdir()
    assert plotter.plots
    plotter.run(plotter.submit(draw_active_plots, *_plot_inputs(there)), lambda *a: None)
    draw_active_plots(*_plot_inputs(here))
    for name in ("contours.png", "residuals.png"):
        drawn = (there / name).read_bytes()
        assert drawn[:8] == b"\x89PNG\r\n\x1a\n" and drawn == (here / name).read_bytes()


def test_rigctl_solve_starts_the_process_only_for_a_procedure_that_uses_one(tmp_path,
                                                                          monkeypatch):
    from rigctl.cli import _solve_process_for

    monkeypatch.setenv(THREADS_VARIABLE, "2")
    users = {name for name in procedure_names() if get_procedure(name).uses_solve_process}
    assert users == SOLVE_PROCESS_USERS
    assert _solve_process_for(tmp_path) is None  # no params.json: the solve says so
    for name in procedure_names():
        (tmp_path / "params.json").write_text(json.dumps({"procedure": name}))
        process = _solve_process_for(tmp_path)
        try:
            assert (process is not None) == (name in SOLVE_PROCESS_USERS), name
            assert process is None or process.plots
        finally:
            if process is not None:
                process.close()
                assert process.proc.poll() is not None
    monkeypatch.setenv(THREADS_VARIABLE, "1")  # a busy controller: no second process
    (tmp_path / "params.json").write_text(json.dumps({"procedure": "active-camera"}))
    assert _solve_process_for(tmp_path) is None
    monkeypatch.setenv(THREADS_VARIABLE, "many")
    with pytest.raises(ConfigError, match=THREADS_VARIABLE):
        _solve_process_for(tmp_path)
