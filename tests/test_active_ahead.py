"""The active-camera solve's stages up to the rolls taken ahead, on the captures before
the first roll, as a live run takes them while the head rolls
(``active_pipeline.pan_tilt_stage``), and the rolls' tiers as their captures come in
(``PanTiltStage.take_roll``): the solve from them is the solve from scratch, to the last
bit; a stage that does not fit the captures is taken again. A random world's
own renderer draws the views (``rigctl.mocks.world``), as ``rigctl bench active-worlds``
does."""

from __future__ import annotations

import json
import logging
from types import SimpleNamespace

import numpy as np
import pytest

from rigctl.bench.active_worlds import POSES_DEG, render_shift, render_views
from rigctl.calib.active_angles import head_encoder_sigmas
from rigctl.calib.active_pipeline import SHIFT, ActiveSettings, pan_tilt_stage, solve_active
from rigctl.calib.active_tracking import roll_tiers
from rigctl.mocks.random_world import random_world
from rigctl.mocks.world import World, WorldFile
from rigctl.procedures.active_camera import (
    ActiveCameraParams,
    WorkWhileMoving,
    solved_after_captures,
)

pytestmark = pytest.mark.heavy

SEED = 26  # an ordinary 1000 px lens


@pytest.fixture(scope="module")
def views():
    """The world, and its captures in the plan's order: the reference, the sideways move,
    the pans and tilts, then the rolls (in the procedure's order)."""
    spec = WorldFile.model_validate(random_world(SEED))
    world = World(spec)
    true_angles: dict = {}
    images, angles = render_views(world, POSES_DEG, np.random.default_rng([SEED, 7]),
                                  "hardware", true_angles)
    shift = render_shift(world, 0.010, true_angles["ref"], angles["ref"])
    rolls = [f"roll{r:+g}" for r in ActiveCameraParams().rolls_deg]
    assert sorted(rolls) == sorted(k for k in images if k.startswith("roll"))
    order = ["ref", SHIFT, *(k for k in images if k != "ref" and k not in rolls), *rolls]
    images[SHIFT], angles[SHIFT] = shift
    sigma = head_encoder_sigmas(dict(zip(("pan", "tilt", "roll"), spec.head.models,
                                         strict=True)))
    settings = ActiveSettings(shift_m=0.010, encoder_sigma_rad=sigma)
    return ({k: images[k] for k in order}, {k: angles[k] for k in order}, settings,
            world.spec.camera)


def _before_rolls(images: dict, angles: dict):
    kept = [k for k in images if not k.startswith("roll")]
    return {k: images[k] for k in kept}, {k: angles[k] for k in kept}


def _as_json(result: dict) -> str:
    return json.dumps(result, sort_keys=True, default=str)


@pytest.fixture(scope="module")
def from_scratch(views):
    images, angles, settings, _ = views
    return solve_active(images, angles, settings, start_helper=False)


@pytest.mark.timeout(600)
def test_the_solve_from_the_stages_taken_ahead_is_the_solve_from_scratch(views,
                                                                         from_scratch):
    images, angles, settings, camera = views
    # as the procedure takes it while the head rolls: no encoder sigmas yet (they only
    # enter the final refinement)
    ahead = pan_tilt_stage(*_before_rolls(images, angles),
                           ActiveSettings(shift_m=0.010, encoder_sigma_rad=None),
                           rolls_follow=True)
    assert ahead.done[-1] in ahead.images and "roll+45" not in ahead.tracker.emaps
    solution = solve_active(images, angles, settings, start_helper=False, ahead=ahead)
    assert _as_json(solution.result) == _as_json(from_scratch.result)
    # the stages taken ahead are named as such; the solve took only the rest
    assert "while moving: contours and first K" in solution.timings_s
    assert "contours and first K" not in solution.timings_s
    assert "tracking: wide" not in solution.timings_s and "tracking: rolls" in \
        solution.timings_s
    assert "while moving: predicting refinement: K_for_rolls" in solution.timings_s
    assert "predicting refinement: K_for_rolls" not in solution.timings_s
    # and it is the world's camera, within its reported sigma
    result = solution.result
    for key in ("fx", "fy", "cx", "cy"):
        assert abs(result[key] - getattr(camera, key)) < 4 * result["sigma"][key], key
    assert abs(result["fx"] / camera.fx - 1) < 2e-3 and abs(result["cx"] - camera.cx) < 1.5


@pytest.mark.timeout(600)
def test_stages_taken_ahead_that_do_not_fit_are_taken_again(views, from_scratch, caplog):
    images, angles, settings, _ = views
    before_images, before_angles = _before_rolls(images, angles)
    other_window = pan_tilt_stage(before_images, before_angles,
                                  ActiveSettings(shift_m=0.010, window=0.5), rolls_follow=True)
    with caplog.at_level(logging.INFO, logger="rigctl.calib.active_pipeline"):
        solution = solve_active(images, angles, settings, start_helper=False,
                                ahead=other_window)
    assert "not used: the settings differ" in caplog.text
    assert "contours and first K" in solution.timings_s
    assert _as_json(solution.result) == _as_json(from_scratch.result)
    # an image other than the one the stage took (e.g. loaded again from its PNG)
    copied = dict(images, **{"pan+": images["pan+"].copy()})
    ahead = pan_tilt_stage(before_images, before_angles,
                           ActiveSettings(shift_m=0.010), rolls_follow=True)
    assert ahead.fits(copied, angles, settings) == "a capture before the rolls differs"
    missing = {k: v for k, v in images.items() if k != "tilt-25"}
    assert "differ" in ahead.fits(missing, angles, settings)
    no_rolls = {k: v for k, v in images.items() if not k.startswith("roll")}
    assert ahead.fits(no_rolls, angles, settings) == "the rolls were not foreseen"


def _ahead_with_rolls(images: dict, angles: dict, rolls: list[str]):
    """The stages up to the rolls, planned with the rolls' nominal angles, then ``rolls``
    taken as a live run takes them; how many tiers were tracked after each."""
    ahead = pan_tilt_stage(*_before_rolls(images, angles),
                           ActiveSettings(shift_m=0.010, encoder_sigma_rad=None),
                           rolls_follow=True)
    planned = [k for k in images if k.startswith("roll")]
    ahead.roll_plan = roll_tiers(planned, {k: np.radians(POSES_DEG[k]) for k in planned})
    tracked = []
    for label in rolls:
        ahead.take_roll(label, images[label], angles[label])
        tracked.append(ahead.rolls_tracked)
    return ahead, tracked


def _roll_stages(timings: dict) -> list[str]:
    """The stages of the rolls' tiers after the first tier's prediction."""
    return [k for k in timings if "K_for_rolls_" in k or "tracking: rolls" in k]


@pytest.mark.timeout(600)
def test_rolls_taken_as_they_come_in_leave_the_solve_only_the_rest(views, from_scratch):
    """A live run tracks each tier of rolls as its captures come in (the last tier with
    the last capture, in the end-to-end test); the solve takes only what is left, to
    the result from scratch."""
    images, angles, settings, _ = views
    rolls = [k for k in images if k.startswith("roll")]
    ahead, tracked = _ahead_with_rolls(images, angles, rolls[:-1])  # -180 not yet in
    # +45, +90, +135, then -45, -90, -135 (-180 last): each tier (+-45, +-90, +-135) is
    # tracked as its second roll comes in, and the next tier's prediction taken then
    assert [len(t) for t in ahead.roll_plan] == [2, 2, 2, 1]
    assert tracked == [0, 0, 0, 1, 2, 3] and ahead.failed is None
    assert ahead.rolls_predicted_tiers == 4
    # a roll capture other than the one taken would not fit
    copied = dict(images, **{rolls[0]: images[rolls[0]].copy()})
    assert ahead.fits(copied, angles, settings) == "a roll capture differs"
    other_plan = {k: v for k, v in images.items() if k != "roll-90"}
    assert ahead.fits(other_plan, angles, settings) == \
        "the rolls' tiers differ from the planned ones"
    solution = solve_active(images, angles, settings, start_helper=False, ahead=ahead)
    assert _as_json(solution.result) == _as_json(from_scratch.result)
    # the last tier's prediction came while moving; its tracking is the solve's own
    assert [k for k in _roll_stages(solution.timings_s)
            if not k.startswith("while moving: ")] == ["tracking: rolls_-180"]
    assert "while moving: predicting refinement: K_for_rolls_-180" in solution.timings_s


@pytest.mark.timeout(600)
def test_the_solve_after_the_last_capture_is_the_solve_from_scratch(views, from_scratch,
                                                                    monkeypatch, caplog):
    """A live run hands each capture to ``WorkWhileMoving`` as it comes in and, once the
    last is in, takes the whole solve there while the head goes home
    (``after_last_capture``); the procedure's solve uses it when it holds the recorded
    captures, and that is the solve from scratch, to the last bit."""
    monkeypatch.setenv("RIGCTL_SOLVE_THREADS", "1")  # no second process in this test
    images, angles, settings, _ = views
    models = dict(zip(("pan", "tilt", "roll"), WorldFile.model_validate(
        random_world(SEED)).head.models, strict=True))
    work = WorkWhileMoving(ActiveCameraParams())
    for label, image in images.items():
        head = dict(zip(("pan", "tilt", "roll"), angles[label], strict=True))
        work(image, {"label": label, "head": head,
                     "head_health": {axis: {"model": m} for axis, m in models.items()}})
    after = work.after_last_capture(SimpleNamespace(config=None, solve_process=None))
    assert after.differs(images, angles, settings) is None
    with caplog.at_level(logging.INFO, logger="rigctl.procedures.active_camera"):
        solution = solved_after_captures(after, images, angles, settings)
    assert "solved from the last capture on" in caplog.text
    assert _as_json(solution.result) == _as_json(from_scratch.result)
    assert "after the last capture: strategies A-D" in solution.timings_s
    assert "while moving: tracking: rolls_-180" in solution.timings_s
    # captures other than the ones it took, or other settings: the solve takes them all
    copied = dict(images, **{"tilt+": images["tilt+"].copy()})
    assert solved_after_captures(after, copied, angles, settings) is None
    assert after.differs(copied, angles, settings) == "a capture differs"
    fewer = {k: v for k, v in images.items() if k != "roll-90"}
    assert after.differs(fewer, angles, settings).startswith("the captures differ")
    exact = ActiveSettings(shift_m=0.010, encoder_sigma_rad=None)
    assert after.differs(images, angles, exact) == "the settings differ"
