"""``rigctl bench arm``: the real ur_rtde client against the controller stand-in.

Measures connect times, distinct timestamps per second seen by RTDEReceiveInterface with
the stream interval p50/p99, zero-length moveJ overhead, and moveJ duration against the
ideal trapezoid.
"""

from __future__ import annotations

import math
import time

import numpy as np

from rigctl.bench.common import StandIn

HOST = "127.0.0.5"


def ideal_trapezoid(distance: float, v: float, a: float) -> float:
    return distance / v + v / a if distance > v * v / a else 2 * math.sqrt(distance / a)


def run(stream_seconds: float = 5.0, zero_moves: int = 100) -> dict:
    import rtde_control
    import rtde_receive

    out: dict = {}
    with StandIn(["-m", "rigctl.mocks.ur_controller", "--host", HOST]):
        t0 = time.perf_counter()
        receive = rtde_receive.RTDEReceiveInterface(HOST)
        out["connect_receive_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        control = rtde_control.RTDEControlInterface(HOST)
        out["connect_control_s"] = time.perf_counter() - t0

        # Stream: poll the receive interface faster than 500 Hz, keep distinct timestamps.
        seen: list[tuple[float, float]] = []
        last = None
        end = time.perf_counter() + stream_seconds
        while time.perf_counter() < end:
            ts = receive.getTimestamp()
            if ts != last:
                seen.append((ts, time.perf_counter()))
                last = ts
            time.sleep(0.0002)  # poll at ~4 kHz without taking a whole core
        stamps = np.array([s for s, _ in seen])
        arrivals = np.array([a for _, a in seen])
        per_second = [int(np.sum((arrivals >= arrivals[0] + k) & (arrivals < arrivals[0] + k + 1)))
                      for k in range(int(stream_seconds) - 1)]
        intervals = np.diff(arrivals) * 1000
        out["stream"] = {
            "distinct_timestamps_per_s_min": min(per_second),
            "distinct_timestamps_per_s_median": float(np.median(per_second)),
            "controller_period_ms": float(np.median(np.diff(stamps)) * 1000),
            "interval_p50_ms": float(np.percentile(intervals, 50)),
            "interval_p99_ms": float(np.percentile(intervals, 99)),
        }

        q = receive.getActualQ()
        times = []
        for _ in range(zero_moves):
            t0 = time.perf_counter()
            control.moveJ(q, 1.05, 1.4)
            times.append(time.perf_counter() - t0)
        out["zero_movej_ms"] = {"median": float(np.median(times) * 1000),
                                "p95": float(np.percentile(times, 95) * 1000)}

        durations = []
        for distance, v, a in ((0.5, 1.05, 1.4), (0.2, 1.05, 1.4), (1.0, 0.5, 2.0)):
            target = list(q)
            target[0] += distance
            t0 = time.perf_counter()
            control.moveJ(target, v, a)
            took = time.perf_counter() - t0
            control.moveJ(q, 3.0, 10.0)
            ideal = ideal_trapezoid(distance, v, a)
            durations.append({"distance_rad": distance, "v": v, "a": a, "measured_s": took,
                              "ideal_s": ideal, "ratio": took / ideal})
        out["movej"] = durations
        t0 = time.perf_counter()
        control.stopScript()
        control.disconnect()
        receive.disconnect()
        out["teardown_s"] = time.perf_counter() - t0
    s = out["stream"]
    out["targets"] = {
        "timestamps_per_s_at_least_495": s["distinct_timestamps_per_s_min"] >= 495,
        "interval_p99_at_most_2.5ms": s["interval_p99_ms"] <= 2.5,
        "zero_movej_median_at_most_10ms": out["zero_movej_ms"]["median"] <= 10,
        "movej_within_2pct": all(abs(d["ratio"] - 1) <= 0.02 for d in durations),
    }
    return out
