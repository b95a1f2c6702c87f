"""Shared helpers of the benchmarks: percentiles, stand-in processes, table output."""

from __future__ import annotations

import numpy as np
from rich.console import Console
from rich.table import Table

from rigctl.childproc import ChildProcess


def stats_ms(samples_s: list[float]) -> dict[str, float]:
    arr = np.asarray(samples_s) * 1000.0
    return {"median_ms": float(np.median(arr)), "p99_ms": float(np.percentile(arr, 99)),
            "n": len(arr)}


class StandIn(ChildProcess):
    """A stand-in process started for a benchmark and stopped by PID."""

    def __init__(self, args: list[str], timeout: float = 15.0) -> None:
        super().__init__(args, timeout)


def print_table(title: str, columns: list[str], rows: list[list], console: Console) -> None:
    table = Table(title=title)
    for col in columns:
        table.add_column(col)
    for row in rows:
        table.add_row(*[f"{v:.3f}" if isinstance(v, float) else str(v) for v in row])
    console.print(table)
