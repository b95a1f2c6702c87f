"""A busy host descheduling a stand-in: each stand-in is paused (SIGSTOP) for 300 ms in the
middle of a run, through the real clients. With the timing `rigctl sim up` writes, the
run rides through; with the hardware defaults, the head's stall fails the run with a
message that names the time spent, the host's load and the rig-file keys to raise."""

from __future__ import annotations

import logging
import os
import signal
import threading
import time

import pytest
import yaml

from rigctl.config import load_rig
from rigctl.runner import Runner

pytestmark = pytest.mark.integration

STALL_S = 0.3


class Staller:
    """Pauses a process for ``STALL_S`` from a thread when a run reaches given steps; always
    resumes it (also from teardown)."""

    def __init__(self, triggers: dict[int, int]) -> None:
        self.triggers = dict(triggers)  # step index -> pid
        self.done: list[tuple[int, int]] = []
        self.threads: list[threading.Thread] = []
        self.stopped: set[int] = set()

    def on_event(self, event: dict) -> None:
        if event.get("type") != "step" or event.get("index") not in self.triggers:
            return
        pid = self.triggers.pop(event["index"])
        thread = threading.Thread(target=self._stall, args=(event["index"], pid), daemon=True)
        thread.start()
        self.threads.append(thread)

    def _stall(self, index: int, pid: int) -> None:
        time.sleep(0.05)  # let the step's first transaction go out
        os.kill(pid, signal.SIGSTOP)
        self.stopped.add(pid)
        try:
            time.sleep(STALL_S)
        finally:
            os.kill(pid, signal.SIGCONT)
            self.stopped.discard(pid)
        self.done.append((index, pid))

    def resume_all(self) -> None:
        for thread in self.threads:
            thread.join(timeout=5)
        for pid in list(self.stopped):
            os.kill(pid, signal.SIGCONT)


def _survey_steps(config) -> tuple[list[str], Runner]:
    runner = Runner(config, show_progress=False)
    _, _, plan = runner.prepare("capture-survey", PARAMS)
    return [s.describe() for s in plan.steps], runner


PARAMS = {"pan_deg": [-10, 10], "tilt_deg": [0], "views": 2, "settle_s": 0.05}


def _first(steps: list[str], word: str, after: int = 0) -> int:
    return next(i for i, s in enumerate(steps) if i >= after and word in s.lower())


@pytest.mark.timeout(240)
def test_each_stand_in_paused_300ms_mid_run_and_the_run_succeeds(start_sim, caplog):
    caplog.set_level(logging.INFO, logger="rigctl.drivers.dynamixel")
    sim = start_sim(world="ideal")
    config = load_rig(sim.rig_path)
    steps, _ = _survey_steps(config)
    pids = dict(zip(("head", "arm", "camera"), sim.ready["children"], strict=True))
    head_move = _first(steps, "head", after=1)
    capture = _first(steps, "capture", after=head_move)
    arm_move = _first(steps, "arm", after=capture + 1)
    staller = Staller({head_move: pids["head"], capture: pids["camera"],
                       arm_move: pids["arm"]})
    runner = Runner(config, show_progress=False, on_event=staller.on_event)
    try:
        outcome = runner.run("capture-survey", PARAMS)
    finally:
        staller.resume_all()
    assert sorted(pid for _, pid in staller.done) == sorted(pids.values())
    assert outcome.status == "succeeded", outcome.reason
    # the head's stall was felt: transactions timed out and were retried
    assert any("(try " in r.getMessage() for r in caplog.records
               if r.name == "rigctl.drivers.dynamixel")
    assert outcome.result["captures"] == len([s for s in steps if "capture" in s.lower()])


@pytest.mark.timeout(240)
def test_a_stall_past_the_hardware_timing_fails_with_a_load_aware_message(start_sim, tmp_path):
    sim = start_sim(world="ideal")
    text = yaml.safe_load(sim.rig_path.read_text())
    head = text["devices"]["head"]
    for key in ("packet_timeout_ms", "retries", "retry_backoff_s"):
        head.pop(key)  # back to the defaults for real servos
    rig = tmp_path / "hardware-timing.yaml"
    rig.write_text(yaml.safe_dump(text))
    config = load_rig(rig)
    assert config.devices.head.retry_budget_s() < STALL_S
    steps, _ = _survey_steps(config)
    head_move = _first(steps, "head", after=1)
    staller = Staller({head_move: sim.ready["children"][0]})
    runner = Runner(config, show_progress=False, on_event=staller.on_event)
    try:
        outcome = runner.run("capture-survey", PARAMS)
    finally:
        staller.resume_all()
    assert outcome.status == "failed"
    reason = outcome.reason
    assert "failed after 4 tries in" in reason, reason
    assert "host load" in reason and "devices.head.packet_timeout_ms" in reason, reason
