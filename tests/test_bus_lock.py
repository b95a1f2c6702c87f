"""Two processes on one Dynamixel bus take turns (``rigctl.drivers.bus_lock``).

A paused run polls its servos while ``rigctl head reboot`` (the pause's advice) runs in
another process on the same port; without a lock across processes each read the other's
replies, and a reboot once reported "overheating, motor encoder, electrical shock,
overload" for a servo whose status was clear."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.test_dynamixel import bus  # noqa: F401  (the stand-in bus fixture)

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

# each process connects through the real driver and reads one 1-byte item of servo 1
# many times, counting the reads that are not that item's value
READER = """
import sys
from rigctl.config import parse_rig
from rigctl.drivers.dynamixel import DynamixelHead
from rigctl.mocks.sim import STAND_IN_TIMING
link, item, reads = sys.argv[1], sys.argv[2], int(sys.argv[3])
text = f"devices:\\n  head:\\n    port: {link}\\n    park: {{policy: hold}}\\n"
for key, value in STAND_IN_TIMING["head"].items():
    text += f"    {key}: {value}\\n"
head = DynamixelHead(parse_rig(text).devices.head)
head.connect()
address = head._addr(1, item)
first = head._read1(1, address, item, check=False)
wrong = sum(head._read1(1, address, item, check=False) != first for _ in range(reads))
head.disconnect()
print(first, wrong)
"""


def test_two_processes_reading_one_bus_each_get_their_own_replies(bus):  # noqa: F811
    """Two driver processes read different items of the same servo at once, 300 times
    each: every read returns its own item's value (servo 1's ID, 1, and its clear
    hardware error status, 0). With the flock taken out (the thread lock alone), 3 runs
    of 3 failed: corrupt replies and a port gone EIO under the other's traffic."""
    link = bus.ready["link"]
    procs = [subprocess.Popen([sys.executable, "-c", READER, link, item, "300"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for item in ("id", "hardware_error_status")]
    try:
        outs = [p.communicate(timeout=200) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-2000:]
    (ident, wrong_ident), (status, wrong_status) = (map(int, out.split()) for out, _ in outs)
    assert (ident, status) == (1, 0)
    assert wrong_ident == 0 and wrong_status == 0, (wrong_ident, wrong_status)
