"""A recorded run re-solves to the same result from a copy of its run directory alone:
no index beside it, no other run reachable, another working directory."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.mockproc import ROOT


def assert_resolves_alone(run_dir: Path, scratch: Path) -> None:
    """Copy ``run_dir`` into ``scratch`` (which holds no index) without its plots, `rigctl
    solve` the copy from ``scratch`` as working directory, and compare the new result with
    the recorded one; the same plots must be drawn again."""
    scratch.mkdir(parents=True, exist_ok=True)
    copy = scratch / run_dir.name
    shutil.copytree(run_dir, copy)
    assert not (scratch / "index.sqlite").exists()
    # the plots are drawn again, into a plots/ folder made again if it was removed
    plots = sorted(p.name for p in (copy / "plots").glob("*.png"))
    shutil.rmtree(copy / "plots", ignore_errors=True)
    done = subprocess.run([sys.executable, "-m", "rigctl.cli", "solve", str(copy), "--json"],
                          capture_output=True, text=True, timeout=300, cwd=scratch,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, f"{run_dir.name}: {done.stderr[-2000:]}"
    assert sorted(p.name for p in (copy / "plots").glob("*.png")) == plots, done.stderr[-2000:]
    recorded = json.loads((run_dir / "result.json").read_text())
    again = json.loads((copy / "result.json").read_text())
    differences = list(_differences(recorded, again))
    assert not differences, f"{run_dir.name}: the re-solve differs: {differences[:5]}"


# The active-camera report of each start of the final refinement: a start that was not
# chosen ends in another, flatter minimum, which rounding moves further (load check, two
# busy cores: the "first K" start's rms_px 0.1102660 live, 0.1102523 re-solved, 1.2e-4
# relative, while the chosen result agreed within 1e-4).
LOOSE_PATHS = ("/tracking/final_starts/",)
LOOSE_REL_TOL = 1e-3
REL_TOL = 1e-4
# Only for numbers that are zero up to rounding (a symmetric matrix's exact zeros, a
# count); every quantity with a size is compared relative to its own scale below.
ABS_TOL = 1e-12


def _differences(a, b, path=""):
    """Paths where two JSON documents differ. Numbers may differ by ``REL_TOL`` (1e-4,
    ``LOOSE_REL_TOL`` under ``LOOSE_PATHS``) of their scale plus ``ABS_TOL``: rounding in
    numerical libraries (threads, the alignment of arrays in memory) moves an iterative
    solve's end point slightly (at load 12 on 2 cores an active-camera re-solve differed
    by 1.3e-5 relative in k1 and 1e-6 absolute in the roll axis); a re-solve from other
    inputs (another intrinsics run, another rig file) moves results by far more. The
    scale is the number itself, except where a quantity's parts share one scale: a
    covariance's (i, j) entry is scaled by sigma_i sigma_j, a transform's rotation by 1
    and its translation by the translation's length, a unit axis's components by 1, a
    capture's head-angle offsets by their vector's length."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                yield f"{path}/{key}: only in one"
            else:
                yield from _differences(a[key], b[key], f"{path}/{key}")
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            yield f"{path}: {len(a)} items against {len(b)}"
            return
        scales = _shared_scales(a, b, path)
        for k, (u, v) in enumerate(zip(a, b, strict=True)):
            if scales is not None and _number(u) and _number(v):
                yield from _compare(u, v, f"{path}[{k}]", scales[k])
            elif scales is not None and isinstance(u, list) and isinstance(v, list) \
                    and len(u) == len(v):
                for m, (x, y) in enumerate(zip(u, v, strict=True)):
                    yield from _compare(x, y, f"{path}[{k}][{m}]", scales[k][m])
            else:
                yield from _differences(u, v, f"{path}[{k}]")
    elif _number(a) and _number(b):
        yield from _compare(a, b, path, max(abs(a), abs(b)))
    elif a != b:
        yield f"{path}: {a!r} against {b!r}"


def _number(x) -> bool:
    return isinstance(x, float | int) and not isinstance(x, bool)


def _compare(a, b, path, scale):
    if not (_number(a) and _number(b)):
        if a != b:
            yield f"{path}: {a!r} against {b!r}"
        return
    rel_tol = LOOSE_REL_TOL if path.startswith(LOOSE_PATHS) else REL_TOL
    if abs(a - b) > rel_tol * scale + ABS_TOL:
        yield f"{path}: {a} against {b} (scale {scale:.3g})"


def _shared_scales(a, b, path):
    """The scale of each number of a quantity whose parts share one (see
    ``_differences``), or None: each number is then its own scale."""
    name = path.rsplit("/", 1)[-1].split("[", 1)[0].lower()
    A, B = _numeric(a), _numeric(b)
    if A is None or B is None or A.shape != B.shape:
        return None
    if A.ndim == 2 and A.shape[0] == A.shape[1] and "covariance" in path.lower():
        sigma = np.sqrt(np.maximum(np.abs(np.diag(A)), np.abs(np.diag(B))))
        return np.outer(sigma, sigma).tolist()
    if A.ndim == 2 and A.shape == (4, 4) and name.startswith("t_"):
        scales = np.ones((4, 4))
        scales[:3, 3] = max(np.linalg.norm(A[:3, 3]), np.linalg.norm(B[:3, 3]))
        return scales.tolist()
    if A.ndim == 1 and ("axis" in name or "/offsets_deg/" in path):
        # a unit axis; a capture's head-angle offsets (pan, tilt, roll), one error of one
        # pose: a component that is zero up to rounding (world default, tilt+20's pan:
        # -1.7770e-6 deg live, -1.7774e-6 re-solved, beside 1e-3 deg) has the vector's scale
        return [max(np.linalg.norm(A), np.linalg.norm(B))] * len(A)
    return None


def _numeric(x):
    """``x`` as a float array if it is a vector or a matrix of numbers, else None."""
    flat = x if x and all(_number(u) for u in x) else None
    if flat is None and x and all(isinstance(r, list) and r and all(_number(u) for u in r)
                                  for r in x):
        flat = x
    if flat is None:
        return None
    try:
        return np.asarray(flat, dtype=float)
    except ValueError:  # ragged rows
        return None
