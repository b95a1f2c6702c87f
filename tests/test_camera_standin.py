"""The camera stand-in's economies keep what a client sees: pixel noise from pre-drawn
fields is the world's noise, frames are rendered only while someone watches, and a frame
taken in motion differs from a still one only by its anti-aliasing."""

from __future__ import annotations

import time
import urllib.request

import cv2
import numpy as np
import pytest

from rigctl.mocks.camera_server import PixelNoise
from rigctl.mocks.world import SUPERSAMPLE, load_world, world_file
from rigctl.simrig import SimulatedRig
from tests.mockproc import control
from tests.waiting import wait_until


def test_pixel_noise_has_the_worlds_sigma_and_frames_are_uncorrelated():
    grey = np.full((360, 640), 100, np.uint8)
    noise = PixelNoise(grey.shape, 2.5, seed=7)
    a = noise.add(grey).astype(float) - 100
    b = noise.add(grey).astype(float) - 100
    # rounding to grey levels adds 1/12 to the variance
    assert np.std(a) == pytest.approx(np.sqrt(2.5 ** 2 + 1 / 12), rel=0.02)
    assert abs(np.mean(a)) < 0.02
    assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.02
    # rounding as the world's own noise does: a grey level plus floor(noise + 1/2)
    assert np.all(a == np.round(a))
    assert np.array_equal(PixelNoise(grey.shape, 0.0, seed=7).add(grey), grey)


def test_a_frame_in_motion_differs_from_a_still_one_only_at_edges():
    world = load_world(world_file("ideal"))
    T = world.T_base_cam(world.home_q, (0.0, 0.0, 0.0))
    still = world.render(T, noise=False).astype(float)
    moving = world.render(T, noise=False, supersample=1).astype(float)
    assert SUPERSAMPLE > 1
    differ = np.abs(still - moving) > 1
    assert 0 < differ.mean() < 0.05  # aliasing along the edges, nothing else
    # the same picture: blurred, they differ by edges at most half a pixel apart (a pan
    # of 0.1 deg, 1.6 px here, gives a mean of 0.61 and a maximum of 43 grey levels)
    blur = np.abs(cv2.GaussianBlur(still, (0, 0), 3) - cv2.GaussianBlur(moving, (0, 0), 3))
    assert blur.mean() < 0.3 and blur.max() < 30


@pytest.mark.integration
@pytest.mark.timeout(180)
def test_frames_are_rendered_only_while_someone_watches(tmp_path):
    rig = SimulatedRig("ideal", records=tmp_path / "records", log=tmp_path / "sim-up.log")
    try:
        sock = rig.ready["camera"]["control"]
        url = rig.ready["camera"]["url"].replace("stream.mjpg", "snapshot.jpg")
        before = control(sock, {"cmd": "dump"})["rendered"]
        time.sleep(1.0)  # nobody watches: a second at 15 fps would render 15 frames
        assert control(sock, {"cmd": "dump"})["rendered"] == before
        with urllib.request.urlopen(url, timeout=30) as reply:
            image = cv2.imdecode(np.frombuffer(reply.read(), np.uint8), cv2.IMREAD_GRAYSCALE)
        assert image.shape == (720, 1280)
        assert control(sock, {"cmd": "dump"})["rendered"] > before
        stream = urllib.request.urlopen(rig.ready["camera"]["url"], timeout=30)
        try:
            seen = control(sock, {"cmd": "dump"})["rendered"]
            wait_until(lambda: control(sock, {"cmd": "dump"})["rendered"] >= seen + 5,
                       timeout=60, what="frames rendered for an open stream")
        finally:
            stream.close()
    finally:
        assert not rig.stop(), "stand-ins outlived `sim up`"
    assert not rig.crash, rig.crash
