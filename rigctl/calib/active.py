"""Active camera calibration from known pan, tilt and roll rotations (thesis chapter 3).

Conventions (erratum 2: written down once, checked against the exact model in tests):

- image coordinates ``x, y`` are pixels measured from the *assumed* image centre, y down;
- pan ``theta_p`` rotates the camera about its own +y axis, tilt ``theta_t`` about its +x,
  roll ``theta_r`` about its +z (optical frame: z forward, x right, y down);
- a scene point then moves as ``x' ~ K R^T K^-1 x`` (Lemma 3.1, no translation) where
  ``R`` is the camera's rotation. With these signs (3.3)-(3.8) hold as printed.
- ``(dx, dy)`` is the offset of the true centre from the assumed one.

All angles in radians. A bar is a mean over the points of one contour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rigctl.errors import SolveError

MIN_ANGLE = math.radians(0.5)


@dataclass(frozen=True)
class ContourStats:
    """Per-contour means of x, y, xy, x^2, y^2 (pixels from the assumed centre)."""

    n: int
    mx: float
    my: float
    mxy: float
    mxx: float
    myy: float

    @classmethod
    def of(cls, points: np.ndarray, centre=(0.0, 0.0)) -> ContourStats:
        pts = np.asarray(points, float) - np.asarray(centre, float)
        if len(pts) == 0:
            raise SolveError("contour has no points")
        x, y = pts[:, 0], pts[:, 1]
        return cls(len(pts), float(x.mean()), float(y.mean()), float((x * y).mean()),
                   float((x * x).mean()), float((y * y).mean()))

    def recentred(self, dx: float, dy: float) -> ContourStats:
        """The same statistics about a centre moved by (dx, dy) (erratum 6)."""
        return ContourStats(self.n, self.mx - dx, self.my - dy,
                            self.mxy - dx * self.my - dy * self.mx + dx * dy,
                            self.mxx - 2 * dx * self.mx + dx * dx,
                            self.myy - 2 * dy * self.my + dy * dy)


def _check_angle(name: str, theta: float) -> None:
    if not math.isfinite(theta) or abs(theta) < MIN_ANGLE:
        raise SolveError(f"{name} angle {math.degrees(theta):.3f} deg is too small "
                         f"(need at least {math.degrees(MIN_ANGLE):.1f} deg)")


def _check_contours(name: str, *groups, need: int = 1) -> None:
    sizes = {len(g) for g in groups}
    if len(sizes) != 1:
        raise SolveError(f"{name}: contour lists differ in length {sorted(sizes)} "
                         "(contours lost between images)")
    if sizes.pop() < need:
        raise SolveError(f"{name}: too few contours (need {need})")


def _finite(name: str, **values: float) -> dict[str, float]:
    for key, value in values.items():
        if not math.isfinite(value):
            raise SolveError(f"{name}: {key} is not finite (degenerate contours or motion)")
    return values


# -- Strategy A (3.9)-(3.12) ----------------------------------------------------------


def strategy_a_centre(ref: list[ContourStats], moved: list[ContourStats], theta: float,
                      axis: str = "tilt") -> tuple[float, float]:
    """(dx, dy) from three or more contours and one tilt (or pan), eqs. (3.11)-(3.12).

    With tilt, ``K_j = (mean x_t - mean x) on contour j / the same on contour 1``
    (erratum 3); with pan the y means are used instead (from (3.9)). With more than three
    contours the equations of every contour j >= 2 against contour 1 are solved in the
    least-squares sense."""
    _check_angle(axis, theta)
    _check_contours("strategy A", ref, moved, need=3)
    shift = [(m.mx - r.mx) if axis == "tilt" else (m.my - r.my) for r, m in zip(ref, moved,
                                                                                strict=True)]
    if abs(shift[0]) < 1e-9:
        raise SolveError("strategy A: contour 1 did not move across the motion")
    rows, rhs = [], []
    r1 = ref[0]
    for j in range(1, len(ref)):
        k = shift[j] / shift[0]
        rj = ref[j]
        rows.append([rj.my - k * r1.my, rj.mx - k * r1.mx])  # coefficients of (dx, dy)
        rhs.append(rj.mxy - k * r1.mxy)
    A, b = np.array(rows), np.array(rhs)
    if np.linalg.matrix_rank(A) < 2 or np.linalg.cond(A) > 1e12:
        raise SolveError("strategy A: contours give dependent equations for the centre")
    (dx, dy), *_ = np.linalg.lstsq(A, b, rcond=None)
    return float(dx), float(dy)


def strategy_a(ref, tilted, panned, theta_t: float, theta_p: float) -> dict[str, float]:
    """Strategy A: centre from (3.11)-(3.12) on the tilt, then f_x from (3.9) with the pan
    and f_y from (3.10) with the tilt, on one contour each (the median over contours)."""
    _check_angle("pan", theta_p)
    _check_angle("tilt", theta_t)
    _check_contours("strategy A", ref, tilted, panned, need=3)
    dx, dy = strategy_a_centre(ref, tilted, theta_t, "tilt")
    fxs, fys = [], []
    for r, t, p in zip(ref, tilted, panned, strict=True):
        common = r.mxy - r.mx * dy - r.my * dx
        if abs(p.my - r.my) > 1e-9:
            fxs.append(-theta_p * common / (p.my - r.my))           # (3.9)
        if abs(t.mx - r.mx) > 1e-9:
            fys.append(theta_t * common / (t.mx - r.mx))            # (3.10)
    if not fxs or not fys:
        raise SolveError("strategy A: no contour moved across the motion")
    return _finite("strategy A", fx=float(np.median(fxs)), fy=float(np.median(fys)),
                   dx=dx, dy=dy)


# -- Strategy B (3.16)-(3.22) ---------------------------------------------------------


def focal_from_quadratic(B: float, mean_sq: float, name: str) -> float:
    """The large root of ``f^2 - B f + mean_sq = 0`` (3.21)/(3.22), erratum 5."""
    disc = B * B - 4 * mean_sq
    if B <= 0 or disc < 0:
        raise SolveError(f"{name}: no feasible focal length (B = {B:.3g}, B^2 - 4 m = "
                         f"{disc:.3g}); the motion sign or the contour tracking is wrong")
    return B / 2 + math.sqrt(disc) / 2


def focal_x(r: ContourStats, p: ContourStats, theta_p: float) -> float:
    """f_x from one contour and a pan, eqs. (3.16), (3.22) with erratum 4 (mean of x^2)."""
    B = (p.mx - r.mx * (1 + theta_p ** 2)) / -theta_p
    return focal_from_quadratic(B, r.mxx, "f_x (3.22)")


def focal_y(r: ContourStats, t: ContourStats, theta_t: float) -> float:
    """f_y from one contour and a tilt, eqs. (3.17), (3.21) with erratum 4 (mean of y^2)."""
    B = (t.my - r.my * (1 + theta_t ** 2)) / theta_t
    return focal_from_quadratic(B, r.myy, "f_y (3.21)")


def centre_from_focal(ref, tilted, fy: float, theta_t: float) -> tuple[float, float]:
    """(dx, dy) from contours and a tilt given f_y, eqs. (3.19)-(3.20) (Corollary 3.1);
    two contours solve it exactly, more in the least-squares sense."""
    _check_contours("centre (3.19)-(3.20)", ref, tilted, need=2)
    A = np.array([[r.my, r.mx] for r in ref])
    b = np.array([r.mxy - fy * (t.mx - r.mx) / theta_t for r, t in zip(ref, tilted,
                                                                          strict=True)])
    if np.linalg.matrix_rank(A) < 2:
        raise SolveError("centre (3.19)-(3.20): contours give dependent equations")
    (dx, dy), *_ = np.linalg.lstsq(A, b, rcond=None)
    return float(dx), float(dy)


def strategy_b(ref, tilted, panned, theta_t: float, theta_p: float) -> dict[str, float]:
    """Strategy B: f_x, f_y from (3.21)-(3.22) per contour (median), centre from
    (3.19)-(3.20)."""
    _check_angle("pan", theta_p)
    _check_angle("tilt", theta_t)
    _check_contours("strategy B", ref, tilted, panned, need=2)
    fx = float(np.median([focal_x(r, p, theta_p) for r, p in zip(ref, panned, strict=True)]))
    fy = float(np.median([focal_y(r, t, theta_t) for r, t in zip(ref, tilted, strict=True)]))
    dx, dy = centre_from_focal(ref, tilted, fy, theta_t)
    return _finite("strategy B", fx=fx, fy=fy, dx=dx, dy=dy)


# -- Strategy C (3.23)-(3.26) and D (3.27)-(3.28) --------------------------------------


def centre_from_roll(pairs: list[tuple[ContourStats, ContourStats, float]], fx: float,
                     fy: float) -> tuple[float, float]:
    """(dx, dy) from rolls, eqs. (3.25)-(3.26): each (reference, rolled, theta_r) gives a
    2x2 linear system; several are stacked in the least-squares sense."""
    if not pairs:
        raise SolveError("roll centre: no rolled contours")
    rows, rhs = [], []
    for r, o, theta in pairs:
        _check_angle("roll", theta)
        c, s = math.cos(theta), math.sin(theta)
        rows += [[1 - c, -fx / fy * s], [fy / fx * s, 1 - c]]
        rhs += [o.mx - c * r.mx - fx / fy * s * r.my, o.my - c * r.my + fy / fx * s * r.mx]
    A, b = np.array(rows), np.array(rhs)
    if np.linalg.matrix_rank(A) < 2:
        raise SolveError("roll centre: degenerate roll angles")
    (dx, dy), *_ = np.linalg.lstsq(A, b, rcond=None)
    return float(dx), float(dy)


def strategy_c(ref, tilted, panned, theta_t, theta_p, roll_pairs) -> dict[str, float]:
    """Strategy C: focal lengths by Strategy B, centre from a roll (3.25)-(3.26)."""
    b = strategy_b(ref, tilted, panned, theta_t, theta_p)
    dx, dy = centre_from_roll(roll_pairs, b["fx"], b["fy"])
    return _finite("strategy C", fx=b["fx"], fy=b["fy"], dx=dx, dy=dy)


def centre_from_half_turn(pairs: list[tuple[ContourStats, ContourStats]]) -> tuple[float, float]:
    """(dx, dy) from a 180-degree roll, eqs. (3.27)-(3.28): the midpoint of each contour
    mean and its rolled mean (averaged over contours)."""
    if not pairs:
        raise SolveError("strategy D: no contour tracked across the 180-degree roll")
    dx = float(np.mean([(o.mx + r.mx) / 2 for r, o in pairs]))
    dy = float(np.mean([(o.my + r.my) / 2 for r, o in pairs]))
    return dx, dy


def strategy_d(ref, tilted, panned, theta_t, theta_p, half_turn_pairs) -> dict[str, float]:
    """Strategy D: centre from the 180-degree roll (3.27)-(3.28), then f_x, f_y from
    (3.16)-(3.17) on statistics re-centred on that centre (erratum 6)."""
    _check_angle("pan", theta_p)
    _check_angle("tilt", theta_t)
    _check_contours("strategy D", ref, tilted, panned, need=1)
    dx, dy = centre_from_half_turn(half_turn_pairs)
    fx = float(np.median([focal_x(r.recentred(dx, dy), p.recentred(dx, dy), theta_p)
                          for r, p in zip(ref, panned, strict=True)]))
    fy = float(np.median([focal_y(r.recentred(dx, dy), t.recentred(dx, dy), theta_t)
                          for r, t in zip(ref, tilted, strict=True)]))
    return _finite("strategy D", fx=fx, fy=fy, dx=dx, dy=dy)
