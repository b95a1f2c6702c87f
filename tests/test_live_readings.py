"""The rig's state read now (``GET /rig/live``, the console's rig page): a service on the
simulated rig reads the head through the real ``dynamixel_sdk`` and the arm through the
real ``ur_rtde`` receive interface, against what the stand-ins hold; while a run holds
the rig the newest capture's readings stand in; a device that cannot be read is named;
and a run waits for the console's brief hold of the rig lock instead of failing busy."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
import yaml
from fastapi.testclient import TestClient

from rigctl.config import load_rig
from rigctl.console import live
from rigctl.locks import BRIEF_HOLDER, rig_lock
from rigctl.service import RigService, create_app
from tests.mockproc import control, simulated_rig

# one simulated rig for the module, not one per worker
pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("live-readings")]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    with simulated_rig(tmp_path_factory.mktemp("live-rig"), "ideal") as rig:
        yield rig


@pytest.fixture
def api(sim, monkeypatch):
    monkeypatch.setattr(live, "LIVE_CACHE_S", 0.0)  # every request reads again
    service = RigService(load_rig(sim.rig_path))
    with TestClient(create_app(service)) as client:
        yield client, service


def _arm(sim, request: dict) -> dict:
    return control(sim.ready["arm"]["control"], request)


def _bus(sim, request: dict) -> dict:
    return control(sim.ready["head"]["control"], request)


@pytest.mark.timeout(120)
def test_a_free_rig_is_read_now_in_the_pendants_units(sim, api):
    client, _ = api
    _bus(sim, {"cmd": "set", "id": 2, "temperature": 47.0, "voltage": 11.6})
    try:
        state = client.get("/rig/live").json()
        arm = _arm(sim, {"cmd": "dump"})
        servos = {s["id"]: s for s in _bus(sim, {"cmd": "dump"})["servos"]}
    finally:
        _bus(sim, {"cmd": "set", "id": 2, "temperature": 35.0, "voltage": 12.0})
    assert state["source"] == "read now" and state["errors"] == {}
    # the arm at rest: the joints and the TCP as the controller holds them
    assert np.allclose(state["joints_deg"], np.degrees(arm["q"]), atol=1e-3)
    assert np.allclose(state["tcp_mm"], 1000 * np.array(arm["tcp_pose"][:3]), atol=0.01)
    assert state["safety"] == "normal"
    # the head: each servo's angle as its encoder reads it, within a pulse
    ids = load_rig(sim.rig_path).devices.head.ids.model_dump()
    for axis in ("pan", "tilt", "roll"):
        pulse_deg = 360.0 / servos[ids[axis]]["pulses_per_rev"]
        assert abs(state["head_deg"][axis]) < 90.0
        assert state["head_deg"][axis] == pytest.approx(
            math.degrees(servos[ids[axis]]["actual_rad"]), abs=2 * pulse_deg)
    # the temperature and the supply set on the stand-in just now, in deg C and V
    by_axis = {s["axis"]: s for s in state["servos"]}
    tilt = by_axis[next(a for a, i in ids.items() if i == 2)]
    assert tilt["temperature_c"] == pytest.approx(47.0, abs=1.0)
    assert tilt["voltage_v"] == pytest.approx(11.6, abs=0.1)
    assert client.get("/console/").text.count('id="state-source">read now') == 1


@pytest.mark.timeout(120)
def test_a_protective_stop_shows_without_any_run(sim, api):
    client, _ = api
    _arm(sim, {"cmd": "protective_stop"})
    try:
        assert client.get("/rig/live").json()["safety"] == "protective stop"
    finally:  # the stand-in's safety back to normal (UR's own unlock waits 5 s)
        _arm(sim, {"cmd": "release_estop"})
    assert client.get("/rig/live").json()["safety"] == "normal"


@pytest.mark.timeout(120)
def test_a_held_rig_shows_the_newest_capture_and_the_page_says_so(api):
    client, service = api
    lock = rig_lock(service.config)
    lock.acquire("a-run-on-the-rig")
    try:
        state = client.get("/rig/live").json()
        page = client.get("/console/").text
    finally:
        lock.release()
    assert state["source"] == "newest capture"
    assert "the rig is busy: its run reads the devices" in page or \
        "no readings recorded yet" in page


@pytest.mark.timeout(120)
def test_a_device_that_cannot_be_read_is_named(sim, tmp_path, monkeypatch):
    monkeypatch.setattr(live, "LIVE_CACHE_S", 0.0)
    spec = yaml.safe_load(sim.rig_path.read_text())
    spec["devices"]["arm"]["host"] = "127.0.0.254"  # loopback, nothing listening
    spec["records"] = {"directory": str(tmp_path / "records")}
    rig = tmp_path / "no-arm.yaml"
    rig.write_text(yaml.safe_dump(spec))
    with TestClient(create_app(RigService(load_rig(rig)))) as client:
        state = client.get("/rig/live").json()
        page = client.get("/console/").text
    assert state["source"] == "read now"
    assert "127.0.0.254" in state["errors"]["arm"] and "head_deg" in state
    assert 'data-unread="arm"' in page


@pytest.mark.timeout(60)
def test_a_run_waits_for_the_consoles_brief_hold(tmp_path):
    """The console holds the rig lock while it reads (``BRIEF_HOLDER``): a run asking
    then waits for it; any other holder is refused at once (``BusyError``)."""
    from rigctl.errors import BusyError
    from rigctl.locks import RigLock

    console = RigLock(tmp_path, "rig")
    console.acquire(BRIEF_HOLDER)
    released = threading.Event()

    def release_soon():
        released.wait(0.2)  # any moment: the run below waits on the lock itself
        console.release()

    threading.Thread(target=release_soon, daemon=True).start()
    run = RigLock(tmp_path, "rig")
    run.acquire("run-1")  # waits for the console, then holds
    try:
        assert run.holder()["run_id"] == "run-1"
        with pytest.raises(BusyError, match="held by run run-1"):
            RigLock(tmp_path, "rig").acquire("run-2")
    finally:
        run.release()
