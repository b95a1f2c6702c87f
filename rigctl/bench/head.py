"""``rigctl bench head``: latency of the real dynamixel_sdk against the bus stand-in with
wire timing, beside the wire-time limit (bytes x 10 / baud).

Mixed buses: XH540-W270 pan and tilt with an XM430-W350 roll share the X control table,
so the driver's one sync read covers them; a DYNAMIXEL-P pan and tilt with an X roll do
not (Present Position at 580 and 132), and the driver bulk-reads them in one packet."""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import dynamixel_sdk as sdk

from rigctl.bench.common import StandIn, stats_ms

IDS = (1, 2, 3)
# Bytes on the wire: instruction + status packets (4-byte data).
WIRE_BYTES = {"read": 14 + 15, "sync_read_x3": 17 + 3 * 15, "fast_sync_read_x3": 17 + 8 + 3 * 8,
              "bulk_read_x3": 10 + 3 * 5 + 3 * 15, "fast_bulk_read_x3": 10 + 3 * 5 + 8 + 3 * 8}
MIXED_X = ("xh540-w270", "xh540-w270", "xm430-w350")
MIXED_XP = ("ph54-100-s500-r", "ph54-100-s500-r", "xm430-w350")


def _transactions(port, ph):
    sync = sdk.GroupSyncRead(port, ph, 132, 4)
    fast = sdk.GroupSyncRead(port, ph, 132, 4)
    for dxl_id in IDS:
        sync.addParam(dxl_id)
        fast.addParam(dxl_id)
    return {
        "read": lambda: ph.read4ByteTxRx(port, 1, 132)[1],
        "sync_read_x3": sync.txRxPacket,
        "fast_sync_read_x3": fast.fastSyncRead,
    }


def bench_baud(baud: int, samples: int, workdir: Path, latency_timer_ms: float = 0.0) -> dict:
    link = workdir / f"dxl-{baud}-{latency_timer_ms:g}"
    with StandIn(["-m", "rigctl.mocks.dynamixel_bus", "--link", str(link), "--baud", str(baud),
                  "--wire-timing", "--latency-timer-ms", str(latency_timer_ms)]):
        port = sdk.PortHandler(str(link))
        port.openPort()
        port.setBaudRate(baud)
        ph = sdk.PacketHandler(2.0)
        for dxl_id in IDS:  # Return Delay Time 0, as the driver configures it
            ph.write1ByteTxRx(port, dxl_id, 9, 0)
        out = {}
        for name, fn in _transactions(port, ph).items():
            times, failures = [], 0
            for _ in range(samples):
                t0 = time.perf_counter()
                ok = fn() == sdk.COMM_SUCCESS
                times.append(time.perf_counter() - t0)
                failures += not ok
            limit_ms = WIRE_BYTES[name] * 10 / baud * 1000
            st = stats_ms(times)
            out[name] = {**st, "wire_limit_ms": limit_ms, "ratio_median": st["median_ms"] /
                         limit_ms, "failures": failures}
        port.closePort()
    return out


def _timed(fn, samples: int, name: str, baud: int) -> dict:
    times, failures = [], 0
    for _ in range(samples):
        t0 = time.perf_counter()
        ok = fn() == sdk.COMM_SUCCESS
        times.append(time.perf_counter() - t0)
        failures += not ok
    limit_ms = WIRE_BYTES[name] * 10 / baud * 1000
    st = stats_ms(times)
    return {**st, "wire_limit_ms": limit_ms, "ratio_median": st["median_ms"] / limit_ms,
            "failures": failures, "transactions": samples}


def bench_mixed(samples: int, workdir: Path, baud: int = 1_000_000) -> dict:
    """Mixed buses at ``baud``: XH540 + XH540 + XM430 (one table: sync reads of Present
    Position 132) and PH54 + PH54 + XM430 (two tables: bulk reads, 580 and 132)."""
    out = {}
    for label, models in (("xh540_xm430", MIXED_X), ("ph54_xm430", MIXED_XP)):
        link = workdir / f"dxl-mixed-{label}"
        with StandIn(["-m", "rigctl.mocks.dynamixel_bus", "--link", str(link), "--baud",
                      str(baud), "--wire-timing", "--model", *models]):
            port = sdk.PortHandler(str(link))
            port.openPort()
            port.setBaudRate(baud)
            ph = sdk.PacketHandler(2.0)
            numbers = {}
            for dxl_id in IDS:
                ph.write1ByteTxRx(port, dxl_id, 9, 0)  # Return Delay Time 0 (same address)
                numbers[dxl_id] = ph.ping(port, dxl_id)[0]
            address = {i: 580 if numbers[i] >= 2000 else 132 for i in IDS}
            kinds = {}
            if len(set(address.values())) == 1:
                sync, fast = (sdk.GroupSyncRead(port, ph, 132, 4) for _ in range(2))
                for dxl_id in IDS:
                    sync.addParam(dxl_id)
                    fast.addParam(dxl_id)
                kinds = {"sync_read_x3": sync.txRxPacket, "fast_sync_read_x3": fast.fastSyncRead}
            else:
                bulk, fast = sdk.GroupBulkRead(port, ph), sdk.GroupBulkRead(port, ph)
                for dxl_id in IDS:
                    bulk.addParam(dxl_id, address[dxl_id], 4)
                    fast.addParam(dxl_id, address[dxl_id], 4)
                kinds = {"bulk_read_x3": bulk.txRxPacket, "fast_bulk_read_x3": fast.fastBulkRead}
            out[label] = {"models": list(models), "baud": baud,
                          **{k: _timed(fn, samples, k, baud) for k, fn in kinds.items()}}
            port.closePort()
    return out


def bench_latency_timer(samples: int, workdir: Path) -> dict:
    """What a USB-serial adapter's latency timer costs at 1 Mbaud: the FTDI default of
    16 ms against the 1 ms ``rigctl doctor`` asks for (stand-in ``--latency-timer-ms``)."""
    out = {}
    for ms in (1.0, 16.0):
        kinds = bench_baud(1_000_000, samples, workdir, latency_timer_ms=ms)
        out[f"{ms:g}ms"] = {k: v["median_ms"] for k, v in kinds.items()}
    added = out["16ms"]["fast_sync_read_x3"] - out["1ms"]["fast_sync_read_x3"]
    out["added_s_per_1000_transactions"] = added
    return out


def bench_failures(n: int, workdir: Path) -> dict:
    link = workdir / "dxl-fail"
    with StandIn(["-m", "rigctl.mocks.dynamixel_bus", "--link", str(link), "--wire-timing"]):
        port = sdk.PortHandler(str(link))
        port.openPort()
        port.setBaudRate(1_000_000)
        ph = sdk.PacketHandler(2.0)
        fns = list(_transactions(port, ph).values())
        failures = sum(fns[i % 3]() != sdk.COMM_SUCCESS for i in range(n))
        port.closePort()
    return {"transactions": n, "failures": failures,
            "failures_per_10000": failures * 10000 / n}


def bench_settle(workdir: Path) -> dict:
    from rigctl.config import parse_rig
    from rigctl.drivers.dynamixel import DynamixelHead

    link = workdir / "dxl-move"
    with StandIn(["-m", "rigctl.mocks.dynamixel_bus", "--link", str(link), "--wire-timing"]):
        cfg = parse_rig(f"devices:\n  head: {{port: {link}, park: {{policy: hold}}}}\n"
                        ).devices.head
        with DynamixelHead(cfg) as head:
            t0 = time.perf_counter()
            head.move_to(math.radians(10), 0.0, 0.0).wait(10)
            settle = time.perf_counter() - t0
            error = abs(head.read_angles().pan - math.radians(10))
    v, a = cfg.speed_cap_dps, cfg.accel_cap_dps2
    ideal = 10 / v + v / a if v * v / a < 10 else 2 * math.sqrt(10 / a)
    return {"move_deg": 10.0, "settle_s": settle, "profile_ideal_s": ideal,
            "speed_cap_dps": v, "accel_cap_dps2": a, "final_error_deg": math.degrees(error)}


def run(samples: int = 500, failure_transactions: int = 10000, mixed: int = 2000) -> dict:
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-") as tmp:
        workdir = Path(tmp)
        result = {"bauds": {}}
        for baud in (57_600, 1_000_000, 4_000_000):
            n = max(samples // 5, 50) if baud < 100_000 else samples
            result["bauds"][str(baud)] = bench_baud(baud, n, workdir)
        result["latency_timer"] = bench_latency_timer(max(samples // 5, 50), workdir)
        result["failures"] = bench_failures(failure_transactions, workdir)
        result["settle"] = bench_settle(workdir)
        result["mixed"] = bench_mixed(mixed, workdir)
    ratio = result["bauds"]["1000000"]["sync_read_x3"]["ratio_median"]
    mixed_sync = result["mixed"]["xh540_xm430"]["sync_read_x3"]
    result["targets"] = {
        "sync_read_x3_at_1M_within_1.5x_wire": ratio <= 1.5,
        "no_failures_in_10000": result["failures"]["failures"] == 0,
        f"mixed_xh540_xm430_sync_read_x3_at_1M_within_1.5x_wire_0_failures_in_{mixed}":
            mixed_sync["ratio_median"] <= 1.5 and mixed_sync["failures"] == 0,
    }
    return result


def run_mixed(transactions: int = 2000) -> dict:
    """Only the mixed buses at 1 Mbaud (``rigctl bench head --mixed-only``)."""
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-") as tmp:
        result = {"bauds": {}, "mixed": bench_mixed(transactions, Path(tmp))}
    sync = result["mixed"]["xh540_xm430"]["sync_read_x3"]
    result["targets"] = {
        f"mixed_xh540_xm430_sync_read_x3_at_1M_within_1.5x_wire_0_failures_in_{transactions}":
            sync["ratio_median"] <= 1.5 and sync["failures"] == 0}
    return result


def rows(result: dict) -> list[list]:
    out = []
    for baud, kinds in result["bauds"].items():
        for name, st in kinds.items():
            out.append([baud, name, st["median_ms"], st["p99_ms"], st["wire_limit_ms"],
                        st["ratio_median"], st["failures"]])
    for label, mixed in result.get("mixed", {}).items():
        for name, st in mixed.items():
            if isinstance(st, dict):
                out.append([f"{mixed['baud']} {label}", name, st["median_ms"], st["p99_ms"],
                            st["wire_limit_ms"], st["ratio_median"], st["failures"]])
    return out
