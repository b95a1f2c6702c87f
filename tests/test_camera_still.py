"""The camera driver's stillness measure: frames of a still scene differ by sensor noise
only; a scene that moved by a pixel or two differs by far more than the default
``still_threshold`` (1 grey level). Pure image arithmetic, no device."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rigctl.config import CameraConfig
from rigctl.drivers.base import DeviceError
from rigctl.drivers.camera import Picture, changed_share, mean_change
from rigctl.runner import STALE_CHANGED_SHARE


def scene(rng, shift: float = 0.0) -> np.ndarray:
    img = np.full((360, 640), 118, np.uint8)
    for k in range(25):
        x, y = 40 + 23 * k + shift, 60 + (k * 37) % 240
        cv2.rectangle(img, (int(x * 16), int(y * 16)), (int((x + 18) * 16), int((y + 30) * 16)),
                      20 if k % 2 else 235, -1, cv2.LINE_AA, shift=4)
    return np.clip(img + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)


def test_noise_is_still_and_a_pixel_of_motion_is_not():
    rng = np.random.default_rng(3)
    threshold = CameraConfig(device=0).still_threshold
    assert mean_change(scene(rng), scene(rng)) < 0.3 * threshold
    noisy = [np.clip(scene(rng) + rng.normal(0, 1.7, (360, 640)), 0, 255).astype(np.uint8)
             for _ in range(2)]  # sensor noise of 2 grey levels in all
    assert mean_change(*noisy) < 0.5 * threshold
    assert mean_change(scene(rng), scene(rng, shift=1.5)) > threshold
    colour = cv2.cvtColor(scene(rng), cv2.COLOR_GRAY2BGR)
    assert mean_change(colour, scene(rng)) < 0.3 * threshold


def sparse_scene(rng, shift: int = 0) -> np.ndarray:
    """A few thin outlines on a plain background, as the simulated worlds' contours."""
    img = np.full((720, 1280), 118, np.uint8)
    for k in range(5):
        x, y = 150 + 200 * k + shift, 200 + (k * 53) % 300
        cv2.ellipse(img, (x, y), (50, 35), 0, 0, 360, 20 if k % 2 else 235, 2, cv2.LINE_AA)
    return np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)


def test_a_small_move_of_a_sparse_scene_changes_few_cells_clearly():
    """The arm's 10 mm SHIFT before the depth capture moves a sparse view by a few
    pixels: its mean change is under the default threshold, yet some cells change by
    far more than noise does, which tells it from a stale frame (``runner._same_view``)."""
    rng = np.random.default_rng(5)
    threshold = CameraConfig(device=0).still_threshold
    before, moved = sparse_scene(rng), sparse_scene(rng, shift=8)
    assert mean_change(before, moved) < threshold
    assert changed_share(before, moved) > 2 * STALE_CHANGED_SHARE
    assert changed_share(before, sparse_scene(rng)) == 0.0  # noise only


def test_a_frame_kept_encoded_decodes_to_the_grey_of_its_image():
    """An MJPEG stream's frames are kept as JPEG bytes and decoded to grey on first look:
    the grey of the decoded colour image, and a clear error for bytes that are no JPEG."""
    grey = scene(np.random.default_rng(3))
    colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    ok, jpeg = cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    kept = Picture(jpeg.reshape(1, -1), encoded=True)
    expected = cv2.cvtColor(cv2.imdecode(jpeg, cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)
    assert np.abs(kept.grey.astype(int) - expected).max() <= 1
    assert kept.grey is kept.grey  # decoded once
    assert np.array_equal(Picture(colour, encoded=False).grey, grey)
    with pytest.raises(DeviceError, match="12 bytes from the stream is not a JPEG"):
        _ = Picture(np.frombuffer(b"not an image", np.uint8).reshape(1, -1), True).grey
