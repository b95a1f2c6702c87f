"""The console's comparisons against closed-form truth: pinhole projection differences
and camera-position differences of arm models, with their sigma."""

from __future__ import annotations

import copy
import datetime as dt
import math
import time

import numpy as np
import pytest
from matplotlib.dates import date2num
from matplotlib.figure import Figure

from rigctl.console import plots
from rigctl.console.compare import arm_difference, hand_eye_difference, projection_difference
from rigctl.console.forms import form_fields
from rigctl.console.pages import _fmt, _when
from rigctl.geometry.kinematics import nominal_ur

W, H = 1280, 720
CAMERA = {"fx": 900.0, "fy": 905.0, "cx": 640.5, "cy": 360.5, "distortion": [0.0] * 5,
          "sigma": {"fx": 0.2, "fy": 0.2, "cx": 0.4, "cy": 0.3}}


def test_identical_cameras_differ_by_nothing():
    pd = projection_difference(CAMERA, CAMERA, W, H)
    assert pd.diff_px.max() < 1e-9
    assert pd.z.max() < 1e-6


def test_principal_point_shift_moves_every_pixel_by_the_shift():
    new = {**CAMERA, "cx": CAMERA["cx"] + 2.0, "cy": CAMERA["cy"] - 1.5}
    pd = projection_difference(new, CAMERA, W, H)
    np.testing.assert_allclose(pd.diff_px, 2.5, atol=1e-6)
    # the difference's sigma at the image centre is the two cx, cy sigmas combined
    centre = np.unravel_index(np.argmin(np.hypot(pd.u - 640.5, pd.v - 360.5)), pd.u.shape)
    expected = math.sqrt(2 * (0.4 ** 2 + 0.3 ** 2))
    assert pd.sigma_px[centre] == pytest.approx(expected, rel=0.01)
    # a small turn of the camera (about 2.5 px / f) takes up a principal point shift near
    # the centre; towards the edges of this 71-degree field a turn is not a shift
    fitted = projection_difference(new, CAMERA, W, H, fit_rotation=True)
    assert fitted.diff_px[centre] < 0.2 * pd.diff_px[centre]
    assert fitted.diff_px.max() < 0.5 * pd.diff_px.max()
    assert 0.7 < fitted.fitted_rotation_deg / math.degrees(2.5 / 900) < 1.0


def test_focal_scale_grows_with_the_distance_from_the_centre():
    new = {**CAMERA, "fx": CAMERA["fx"] * 1.01, "fy": CAMERA["fy"] * 1.01}
    pd = projection_difference(new, CAMERA, W, H)
    r = np.hypot(pd.u - CAMERA["cx"], pd.v - CAMERA["cy"])
    np.testing.assert_allclose(pd.diff_px, 0.01 * r, atol=1e-6)


def test_distortion_change_grows_as_r_cubed_from_the_centre():
    new = {**CAMERA, "distortion": [-0.05, 0.0, 0.0, 0.0, 0.0]}
    pd = projection_difference(new, CAMERA, W, H)
    # with no distortion before, pixel p has x = (p - c) / f; the new camera puts it at
    # c + f x (1 + k1 r^2): it moves by |k1| r^2 |p - c|
    du, dv = pd.u - CAMERA["cx"], pd.v - CAMERA["cy"]
    r2 = (du / CAMERA["fx"]) ** 2 + (dv / CAMERA["fy"]) ** 2
    np.testing.assert_allclose(pd.diff_px, 0.05 * r2 * np.hypot(du, dv), rtol=1e-6,
                               atol=1e-6)


def _arm_result(model, X, sigma_m=None):
    names = ["link2.a", "X.x", "W.x", "camera.fx"]
    cov = np.diag(np.square([sigma_m or 0.0] * 4)).tolist() if sigma_m else None
    return {"links": model.links(), "T_base_link0": model.T_base_link0.tolist(),
            "T_flange_cam": X.tolist(),
            "covariance": {"names": names, "matrix": cov} if cov else {}}


def test_link_length_change_moves_the_camera_by_that_length():
    model = nominal_ur("ur5e")
    X = np.eye(4)
    X[:3, 3] = [0.0, 0.05, 0.08]
    longer = model.copy()
    longer.a[1] += 0.0008
    rng = np.random.default_rng(3)
    q = rng.uniform(-np.pi, np.pi, (40, 6))
    ad = arm_difference(_arm_result(longer, X, 1e-4), _arm_result(model, X, 1e-4), q)
    np.testing.assert_allclose(ad.diff_mm, 0.8, atol=1e-9)
    # link2.a and X.x at 0.1 mm each, in both models: each moves the camera by its own
    # length, so each model's position sigma is 0.1 * sqrt(2) mm and the difference's
    # 0.2 mm; W.x and camera.fx (target, intrinsics) do not move the camera
    np.testing.assert_allclose(ad.sigma_mm, 0.2, rtol=1e-5)


def test_hand_eye_difference_in_mm_deg_and_sigma():
    X = np.eye(4)
    turned = copy.deepcopy(X)
    c, s = math.cos(math.radians(0.3)), math.sin(math.radians(0.3))
    turned[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    turned[:3, 3] = [0.003, 0.0, 0.0]
    sigma = [0.0] * 3 + [0.001, 0.001, 0.001] + [0.0] * 6
    d = hand_eye_difference({"T_flange_cam": turned, "sigma": sigma},
                            {"T_flange_cam": X, "sigma": sigma})
    assert d["translation_mm"] == pytest.approx(3.0)
    assert d["rotation_deg"] == pytest.approx(0.3, rel=1e-6)
    assert d["translation_z"] == pytest.approx(3.0 / math.sqrt(2) / 1.0, rel=1e-6)


def test_equal_cameras_show_as_one_flat_colour():
    # rounding leaves ~1e-7 px between two runs of the same camera: the heat map's scale
    # must not stretch that over all its colours
    nudged = {**CAMERA, "fx": CAMERA["fx"] * (1 + 1e-10)}
    pd = projection_difference(nudged, CAMERA, W, H)
    assert 0 < pd.diff_px.max() < 1e-6
    assert plots.heat_map_max_px(pd) == 0.1
    shifted = projection_difference({**CAMERA, "cx": CAMERA["cx"] + 2.0}, CAMERA, W, H)
    assert plots.heat_map_max_px(shifted) == pytest.approx(2.0)
    assert plots.projection_difference_png(pd, W, H).startswith(b"\x89PNG")


def _axis(times: list[dt.datetime]):
    fig = Figure()
    ax = fig.subplots()
    ax.plot(times, range(len(times)), "o")
    plots._time_axis(ax, times)
    fig.canvas.draw()
    lo, hi = ax.get_xlim()
    ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
    labels = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
    return lo, hi, ticks, labels


def test_history_time_axis_with_one_and_with_many_points():
    t0 = dt.datetime(2026, 3, 4, 10, 0, 0)
    # one point: an hour either side, not years; a few readable ticks
    lo, hi, ticks, labels = _axis([t0])
    assert (hi - lo) * 24 == pytest.approx(2.0)
    assert 3 <= len(ticks) <= 7 and len(labels) >= 3
    # a dozen runs over three minutes (a demo, a test, a busy afternoon): they spread over
    # the axis (8 % margin each side) instead of crowding the middle of a two-hour one
    times = [t0 + dt.timedelta(seconds=15 * k) for k in range(12)]
    lo, hi, ticks, labels = _axis(times)
    span = date2num(times[-1]) - date2num(times[0])
    assert span / (hi - lo) == pytest.approx(1 / 1.16)
    assert lo < date2num(times[0]) and date2num(times[-1]) < hi
    assert 3 <= len(ticks) <= 7 and len(set(labels)) == len(labels)
    # two runs a second apart still get an axis of a few seconds (5 s margins)
    lo, hi, _, _ = _axis([t0, t0 + dt.timedelta(seconds=1)])
    assert (hi - lo) * 86400 == pytest.approx(11.0)
    # a year of monthly runs: the axis is the year and a margin
    times = [t0 + dt.timedelta(days=30 * k) for k in range(13)]
    lo, hi, ticks, _ = _axis(times)
    assert (hi - lo) == pytest.approx(1.16 * 360)
    assert 3 <= len(ticks) <= 7


def test_times_in_utc_whatever_the_servers_zone_and_missing_numbers(monkeypatch):
    # SQLite gives the index's times back naive; they were written in UTC
    monkeypatch.setenv("TZ", "America/New_York")
    time.tzset()
    try:
        assert _when(dt.datetime(2026, 1, 2, 3, 4, 5)) == "2026-01-02 03:04:05 UTC"
        plus2 = dt.timezone(dt.timedelta(hours=2))
        assert _when(dt.datetime(2026, 1, 2, 3, 4, 5, tzinfo=plus2)) == \
            "2026-01-02 01:04:05 UTC"
        assert _when("2026-01-02T03:04:05.123+00:00") == "2026-01-02 03:04:05 UTC"
        assert _when("not a time") == "not a time" and _when(None) == ""
        # and a missing number reads as such, not as Python's None
        assert _fmt(None) == "n/a" and _fmt(1.23456) == "1.235"
    finally:
        monkeypatch.undo()
        time.tzset()


def test_form_fields_follow_the_schema_and_the_rig_file():
    from rigctl.procedures.capture_survey import CaptureSurveyParams
    from rigctl.procedures.hand_eye import HandEyeParams

    fields = {f["name"]: f for f in form_fields(CaptureSurveyParams.model_json_schema(),
                                                {"views": 7})}
    assert fields["views"]["kind"] == "integer" and fields["views"]["value"] == "7"
    assert fields["views"]["from_rig_file"] and fields["views"]["max"] == 50
    assert fields["pan_deg"]["kind"] == "array"
    assert fields["view_distance_m"]["min"] == 0.1 and fields["view_distance_m"]["max"] == 1.5
    # a default factory is missing from the JSON schema: the model's own default is shown
    fields = {f["name"]: f for f in form_fields(CaptureSurveyParams.model_json_schema(), {},
                                                CaptureSurveyParams().model_dump(mode="json"))}
    assert fields["pan_deg"]["value"] == "-10, 0, 10"
    assert fields["tilt_deg"]["value"] == "-5, 0, 5"
    he = {f["name"]: f for f in form_fields(HandEyeParams.model_json_schema())}
    assert he["intrinsics"]["kind"] == "json" and he["intrinsics"]["nullable"]
    assert he["use_controller_model"]["kind"] == "boolean"
