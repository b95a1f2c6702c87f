"""Every UR arm model: the driver's table, the stand-in's own table, and the real ur_rtde
client driving the stand-in as a CB3 UR5, an e-Series UR16e and a UR20.

The expected numbers below are typed here from the sources (ur_description's
``config/<model>/default_kinematics.yaml`` and ``joint_limits.yaml``; UR's DH article),
not read from either table."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import yaml

from rigctl.config import parse_rig
from rigctl.drivers.ur_primary import read_primary_info
from rigctl.errors import ConfigError
from rigctl.exports_ur import joint_limits_of, ur_kinematics, urdf_from_kinematics
from rigctl.geometry.kinematics import nominal_ur
from rigctl.hardware.ur_models import MODELS, ControllerIdentity, check_model
from rigctl.loopback import free_host
from rigctl.mocks import ur_models as stand_in_models
from rigctl.mocks.random_world import ALL_MODELS_FROM, REACH_M, random_world
from rigctl.mocks.ur_kinematics import ArmModel
from rigctl.mocks.world import World, WorldFile
from tests.mockproc import ROOT, MockProcess, control
from tests.waiting import wait_until

THIRTEEN = ("ur3", "ur5", "ur10", "ur3e", "ur5e", "ur7e", "ur10e", "ur12e", "ur16e", "ur15",
            "ur18", "ur20", "ur30")

# (d1, a2, a3, d4, d5, d6) in metres, from default_kinematics.yaml (shoulder.z, forearm.x,
# wrist_1.x, wrist_1.z, -wrist_2.y, wrist_3.y)
PUBLISHED = {
    "ur3": (0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819),
    "ur5": (0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823),
    "ur16e": (0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
    "ur20": (0.2363, -0.862, -0.7287, 0.201, 0.1593, 0.1543),
    "ur30": (0.2363, -0.637, -0.5037, 0.201, 0.1593, 0.1543),
}
# joint_limits.yaml max_velocity, degrees per second, base to wrist 3
SPEEDS_DPS = {"ur5": (180,) * 6, "ur16e": (120, 120, 180, 180, 180, 180),
              "ur20": (120, 120, 150, 210, 210, 210)}
DASHBOARD = {"ur5": "UR5", "ur16e": "UR16", "ur20": "UR20"}
VERSIONS = {"ur5": (3, 15), "ur16e": (5, 11), "ur20": (5, 14)}  # a CB3 reports 3.x
ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
HOME = np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


def dh_lists(model: str) -> tuple[list[float], list[float]]:
    d1, a2, a3, d4, d5, d6 = PUBLISHED[model]
    return [d1, 0, 0, d4, d5, d6], [0, a2, a3, 0, 0, 0]


def fk(q, model: str) -> np.ndarray:
    """Forward kinematics from the published table, written out for this test."""
    d, a = dh_lists(model)
    T = np.eye(4)
    for i in range(6):
        ct, st = math.cos(q[i]), math.sin(q[i])
        ca, sa = math.cos(ALPHA[i]), math.sin(ALPHA[i])
        T = T @ np.array([[ct, -st * ca, st * sa, a[i] * ct], [st, ct * ca, -ct * sa, a[i] * st],
                          [0, sa, ca, d[i]], [0, 0, 0, 1]])
    return T


# -- the tables ---------------------------------------------------------------------------

def test_thirteen_models_in_both_tables_and_their_kinematics_agree():
    assert tuple(MODELS) == THIRTEEN and stand_in_models.MODEL_NAMES == THIRTEEN
    rng = np.random.default_rng(40)
    for name in THIRTEEN:
        ours, sim = nominal_ur(name), ArmModel.nominal(name)
        for q in rng.uniform(-math.pi, math.pi, (5, 6)):
            assert np.allclose(ours.fk(q), sim.flange(q), atol=1e-12), name
        row = MODELS[name]
        assert np.allclose(row.max_speed_rad_s(), stand_in_models.joint_speed_max(name)), name
        limits = [math.inf if lim is None else lim[1] for lim in row.limits_rad()]
        assert np.allclose(limits, stand_in_models.joint_limits_rad(name)), name
        assert row.reach_m == REACH_M[name]
    for name in PUBLISHED:
        d, a = dh_lists(name)
        assert np.allclose(nominal_ur(name).d, d, atol=0) and np.allclose(nominal_ur(name).a, a)
    # the UR3's (and UR3e's) last joint turns without limit; every other joint +-360 deg
    assert MODELS["ur3"].position_limits_deg[5] is None
    assert MODELS["ur5"].position_limits_deg == ((-360.0, 360.0),) * 6
    # siblings share kinematics: UR7e = UR5e, UR12e = UR10e; UR18 has the UR15's wrist
    assert np.array_equal(nominal_ur("ur7e").a, nominal_ur("ur5e").a)
    assert np.array_equal(nominal_ur("ur12e").d, nominal_ur("ur10e").d)
    assert MODELS["ur18"].d4 == MODELS["ur15"].d4 == 0.1824


@pytest.mark.parametrize(("answers", "expected"), [
    (("UR5", "2017350881", "3.15.7.106331"), ["ur5"]),
    (("UR5", "20215500001", "5.11.1.108318"), ["ur5e", "ur7e"]),
    (("UR10", "20215200031", "5.19.0.117337"), ["ur12e"]),  # size digit 2: the 12.5 kg arm
    (("UR10", "20215000001", "5.11.1.108318"), ["ur10e"]),
    (("UR10", None, "3.15.7.106331"), ["ur10"]),
    (("UR30", "20235300071", "5.15.1.113206"), ["ur30"]),
    ((None, None, None), list(THIRTEEN)),  # nothing said, nothing excluded
])
def test_the_controller_s_answers_name_the_model(answers, expected):
    assert ControllerIdentity(*answers).candidates() == expected


def test_a_disagreeing_model_is_refused_naming_both():
    identity = ControllerIdentity("UR5", "2017350881", "3.15.7.106331")
    with pytest.raises(ConfigError, match=r"devices.arm.model is 'ur5e' but the controller at "
                                          r"127.0.0.9 reports get robot model 'UR5'.*ur5"):
        check_model("ur5e", identity, "127.0.0.9")
    assert check_model("ur5", identity, "127.0.0.9") == ["ur5"]


def test_the_rig_file_takes_every_model_and_names_an_unknown_one():
    for name in THIRTEEN:
        assert parse_rig(f"devices:\n  arm: {{model: {name}}}\n").devices.arm.model == name
    with pytest.raises(ConfigError, match=r"rig.yaml: devices.arm.model: unknown UR arm "
                                          r"model 'ur99'; known: ur3, ur5, ur10, ur3e"):
        parse_rig("devices:\n  arm: {model: ur99}\n")
    # soft limits beyond the model's own: the UR3's wrist 3 may turn further
    beyond = "[[-360, 360], [-360, 360], [-360, 361], [-360, 360], [-360, 360], [-363, 363]]"
    with pytest.raises(ConfigError, match=r"joint 3 \[-360, 361\] deg exceeds the ur5's"):
        parse_rig(f"devices:\n  arm: {{model: ur5, joint_limits_deg: {beyond}}}\n")
    free = beyond.replace("[-360, 361]", "[-360, 360]")
    assert parse_rig(f"devices:\n  arm: {{model: ur3, joint_limits_deg: {free}}}\n")


def test_unknown_model_in_the_rig_file_exits_2_naming_the_key(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text("name: r\ndevices:\n  arm: {host: 127.0.0.1, model: ur99}\n")
    proc = subprocess.run([sys.executable, "-m", "rigctl.cli", "run", "arm-sweep", "--rig",
                           str(rig), "--dry-run"], capture_output=True, text=True, timeout=120,
                          cwd=ROOT)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "devices.arm.model" in proc.stderr and "'ur99'" in proc.stderr


# -- exports ------------------------------------------------------------------------------

def test_exports_carry_the_model_s_kinematics_and_limits():
    # ur_description config/ur30/default_kinematics.yaml (and ur3's, a CB3)
    for name, forearm, wrist_1, wrist_2_y, wrist_3_y in (
            ("ur30", -0.637, (-0.5037, 0.201), -0.1593, 0.1543),
            ("ur3", -0.24365, (-0.21325, 0.11235), -0.08535, 0.0819)):
        doc = ur_kinematics(nominal_ur(name), "calib_1")["kinematics"]
        assert doc["forearm"]["x"] == pytest.approx(forearm, abs=1e-12)
        assert (doc["wrist_1"]["x"], doc["wrist_1"]["z"]) == pytest.approx(wrist_1, abs=1e-12)
        assert doc["wrist_2"]["y"] == pytest.approx(wrist_2_y, abs=1e-12)
        assert doc["wrist_3"]["y"] == pytest.approx(wrist_3_y, abs=1e-12)
    limits = joint_limits_of("ur20")
    assert [round(math.degrees(v)) for _, _, v, _ in limits] == list(SPEEDS_DPS["ur20"])
    assert limits[2][:2] == pytest.approx((-math.pi, math.pi))  # ur_description's elbow
    assert [e for *_, e in limits] == [738, 738, 433, 107, 107, 107]
    urdf = urdf_from_kinematics(ur_kinematics(nominal_ur("ur20"), "calib_1"), np.eye(4), None,
                                np.eye(4), model_name="ur20")
    assert 'effort="738.0" velocity="2.0943951023931953"' in urdf


# -- random worlds ------------------------------------------------------------------------

def test_random_worlds_take_every_model_twice_in_26_seeds():
    drawn = {}
    for seed in range(ALL_MODELS_FROM + 5, ALL_MODELS_FROM + 31):
        data = random_world(seed)
        world = World(WorldFile.model_validate(data))
        model = data["arm"]["model"]
        drawn[model] = drawn.get(model, 0) + 1
        T = world.T_base_target
        half = np.array([data["target"]["cols"], data["target"]["rows"], 0]) * \
            data["target"]["square_mm"] / 2000
        centre = T[:3, :3] @ half + T[:3, 3]
        assert 0.4 * REACH_M[model] < np.hypot(*centre[:2]) < 0.8 * REACH_M[model]
    assert drawn == dict.fromkeys(THIRTEEN, 2)
    # the seeds below keep the worlds they always gave
    assert {random_world(s)["arm"]["model"] for s in range(40)} == {"ur3e", "ur5e", "ur10e"}


# -- the real client against the stand-in -------------------------------------------------

@pytest.fixture
def stand_in(tmp_path):
    started = []

    def start(model: str) -> MockProcess:
        host = free_host()
        sock = tmp_path / f"ur-{host}.sock"
        started.append(MockProcess(["-m", "rigctl.mocks.ur_controller", "--host", host,
                                    "--model", model, "--control", str(sock)]))
        started[-1].sock = str(sock)
        return started[-1]

    yield start
    for proc in started:
        proc.stop()


def peak_speed(receive, joint: int, target: float) -> float:
    """Largest |qd| of ``joint`` seen on the stream until it reaches ``target``."""
    peak = [0.0]

    def arrived():
        peak[0] = max(peak[0], abs(receive.getActualQd()[joint]))
        return abs(receive.getActualQ()[joint] - target) < 1e-4 and \
            abs(receive.getActualQd()[joint]) < 1e-9
    wait_until(arrived, timeout=20, what="the move's end", poll=0.001)
    return peak[0]


@pytest.mark.integration
@pytest.mark.parametrize("model", ["ur5", "ur16e", "ur20"])
def test_the_real_client_drives_each_generation(stand_in, model):
    import dashboard_client
    import rtde_control
    import rtde_receive

    proc = stand_in(model)
    host = proc.ready["host"]
    cb3 = model == "ur5"
    # the controller's own kinematics on the primary interface: the published table
    info = read_primary_info(host)
    d, a = dh_lists(model)
    assert np.allclose(info.kinematics.d, d, atol=1e-12)
    assert np.allclose(info.kinematics.a, a, atol=1e-12)
    assert np.allclose(info.kinematics.alpha, ALPHA, atol=1e-12)
    assert (info.version.major, info.version.minor) == VERSIONS[model]
    receive = rtde_receive.RTDEReceiveInterface(host)
    ctrl = rtde_control.RTDEControlInterface(host)
    try:
        seen = control(proc.sock, {"cmd": "dump"})["seen"]
        # ur_rtde took its own path for the generation: 125 Hz and no serial-number or
        # remote-control query on a CB3, 500 Hz on e-Series and UR-Series
        assert set(seen["rtde_frequencies"]) == ({125.0} if cb3 else {500.0})
        assert ("get serial number" in seen["dashboard"]) is not cb3
        assert ("is in remote control" in seen["dashboard"]) is not cb3
        q = receive.getActualQ()
        assert np.allclose(q, HOME, atol=1e-12)
        assert np.allclose(receive.getActualTCPPose()[:3], fk(q, model)[:3, 3], atol=1e-9)
        # joint limits: +-360 deg on every joint of these three
        inside = list(HOME)
        inside[2] = math.radians(359.9)
        outside = list(HOME)
        outside[5] = math.radians(360.1)
        assert ctrl.isJointsWithinSafetyLimits(inside)
        assert not ctrl.isJointsWithinSafetyLimits(outside)
        # joint speeds: a base move asked at 3 rad/s runs at the base's published maximum
        target = list(q)
        target[0] += 0.9
        vmax = math.radians(SPEEDS_DPS[model][0])
        assert ctrl.moveJ(target, 3.0, 20.0, True)
        peak = peak_speed(receive, 0, target[0])
        assert 0.95 * vmax < peak <= vmax + 1e-9, (peak, vmax)
        dash = dashboard_client.DashboardClient(host)
        dash.connect()
        assert dash.getRobotModel().strip() == DASHBOARD[model]
        assert dash.polyscopeVersion().startswith("3.15." if cb3 else "5.")
        dash.disconnect()
    finally:
        ctrl.stopScript()
        ctrl.disconnect()
        receive.disconnect()


@pytest.mark.integration
def test_a_rig_file_naming_another_model_is_refused_and_nothing_moves(stand_in, tmp_path):
    proc = stand_in("ur5")  # a CB3 UR5
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({"name": "mismatch", "devices": {"arm": {
        "host": proc.ready["host"], "model": "ur5e"}}}))
    out = subprocess.run([sys.executable, "-m", "rigctl.cli", "doctor", "--rig", str(rig)],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    text = " ".join((out.stdout + out.stderr).split())
    assert out.returncode == 2, text
    assert "'ur5e'" in text and "'UR5'" in text and "3.15" in text and "ur5" in text
    dump = control(proc.sock, {"cmd": "dump"})
    assert np.allclose(dump["q"], HOME, atol=0)
    # refused before the RTDE interfaces connected: no stream, no control script
    assert dump["seen"]["rtde_frequencies"] == [] and dump["seen"]["script_lines"] == []
    # the same rig file naming the UR5 passes
    rig.write_text(rig.read_text().replace("ur5e", "ur5"))
    out = subprocess.run([sys.executable, "-m", "rigctl.cli", "doctor", "--rig", str(rig),
                          "--json"], capture_output=True, text=True, timeout=120, cwd=ROOT)
    arm = next(r for r in yaml.safe_load(out.stdout) if r["device"] == "arm")
    assert arm["state"] == "ok", arm
    assert arm["describe"]["controller_model"] == "UR5"
    assert arm["describe"]["firmware"].startswith("3.15.")


@pytest.mark.integration
def test_a_planned_arm_run_is_refused_with_exit_2_before_it_is_recorded(stand_in, tmp_path):
    proc = stand_in("ur20")
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({
        "name": "mismatch-plan", "records": {"directory": str(tmp_path / "records")},
        "devices": {"arm": {"host": proc.ready["host"], "model": "ur30"},
                    "camera": {"device": "http://127.0.0.1:9/none.mjpg"}},
        "target": {"rows": 6, "cols": 8, "square_mm": 60,
                   "pose": {"xyz_mm": [-900, 0, 0], "rpy_deg": [180, 0, 0]}}}))
    out = subprocess.run([sys.executable, "-m", "rigctl.cli", "run", "hand-eye", "--rig",
                          str(rig), "--param", "intrinsics={fx: 900, fy: 900, cx: 640, "
                          "cy: 360}"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    text = " ".join(out.stderr.split())
    assert out.returncode == 2, out.stdout + out.stderr
    assert "'ur30'" in text and "'UR20'" in text and "ur20" in text
    assert not (tmp_path / "records").exists() or not any((tmp_path / "records").rglob("*.json"))
    dump = control(proc.sock, {"cmd": "dump"})
    assert np.allclose(dump["q"], HOME, atol=0) and dump["seen"]["script_lines"] == []
