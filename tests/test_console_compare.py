"""The console's comparisons against closed-form truth: pinhole projection differences
and camera-position differences of arm models, with their sigma."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from rigctl.console.compare import arm_difference, hand_eye_difference, projection_difference
from rigctl.console.forms import form_fields
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


def test_form_fields_follow_the_schema_and_the_rig_file():
    from procedures.capture_survey import CaptureSurveyParams
    from procedures.hand_eye import HandEyeParams

    fields = {f["name"]: f for f in form_fields(CaptureSurveyParams.model_json_schema(),
                                                {"views": 7})}
    assert fields["views"]["kind"] == "integer" and fields["views"]["value"] == "7"
    assert fields["views"]["from_rig_file"] and fields["views"]["max"] == 50
    assert fields["pan_deg"]["kind"] == "array"
    assert fields["view_distance_m"]["min"] == 0.1 and fields["view_distance_m"]["max"] == 1.5
    he = {f["name"]: f for f in form_fields(HandEyeParams.model_json_schema())}
    assert he["intrinsics"]["kind"] == "json" and he["intrinsics"]["nullable"]
    assert he["use_controller_model"]["kind"] == "boolean"
