"""Contours of the active-camera reference image followed through the other captures
(thesis 5.1.2, automated): the thesis's shift search for a first K, then tracking by
prediction, tier by tier, from the model refined on the tiers before (the tiers'
order is here; the refinements are ``active_pipeline``'s)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from rigctl.calib import active
from rigctl.calib.active import ContourStats
from rigctl.calib.active_refine import Motion, RefineResult
from rigctl.calib.synthetic import intrinsics, rot_x, rot_y, rot_z
from rigctl.calib.threads import map_in_threads
from rigctl.errors import SolveError
from rigctl.vision.contours import EdgeMap, edge_map, extract_contours
from rigctl.vision.tracking import (
    common_shift,
    searchable,
    track_by_prediction,
    track_by_shift,
)

MOTIONS = ("pan+", "pan-", "tilt+", "tilt-")
SHIFT = "shift"  # the capture after the arm moved the camera sideways (scene depths)
# Fewer contours than this in a narrower central window (an operator's choice): look in
# WIDE_WINDOW of the image instead
WANTED_CONTOURS = 6
WIDE_WINDOW = 0.95
TILE_PX = 160  # then cut edge networks that reach beyond it into pieces this size
ROLL_TIER_DEG = 45.0  # rolls are tracked in tiers of this many degrees, smallest first


def pinhole_predictor(K: dict, rel_angles):
    """Maps reference pixels to the moved image with the nominal head (pure rotation,
    thesis eq. 3.3 with a distortion-free K)."""
    Km = intrinsics(K["fx"], K["fy"], K["cx"], K["cy"])
    Kinv = np.linalg.inv(Km)
    p, t, r = rel_angles
    R = rot_y(p) @ rot_x(t) @ rot_z(r)

    def predict(points: np.ndarray) -> np.ndarray:
        rays = (Kinv @ np.c_[points, np.ones(len(points))].T).T
        moved = (Km @ (R.T @ rays.T)).T
        return moved[:, :2] / moved[:, 2:3]

    return predict


def _edge_maps(images: dict, emaps: dict | None) -> dict:
    """Each image's edge map, by label: ``emaps``' where given (taken while the rig moved
    on), the others taken here side by side (``searchable``: with the maps a search in
    them needs)."""
    known = {k: v for k, v in (emaps or {}).items() if k in images}
    missing = [k for k in images if k not in known]
    def taken(label: str) -> EdgeMap:  # the reference is never searched in
        emap = edge_map(images[label])
        return emap if label == "ref" else searchable(emap)

    known.update(zip(missing, map_in_threads(taken, missing), strict=True))
    return {k: known[k] for k in images}


class Tracker:
    """Contours of the reference image followed through the other captures."""

    def __init__(self, images: dict, angles: dict, window: float, min_points: int,
                 assumed_centre: list[float] | None = None,
                 emaps: dict[str, EdgeMap] | None = None) -> None:
        """``emaps``: edge maps already taken of some of ``images`` (``edge_map``, by
        label; e.g. while the rig moved on); the others' are taken here."""
        self.angles = angles
        self.emaps = _edge_maps(images, emaps)
        self.inv_depth: np.ndarray | None = None  # each contour's, once measured (1/m)
        h, w = images["ref"].shape[:2]
        self.size = (w, h)
        self.centre = np.array(assumed_centre or [(w - 1) / 2, (h - 1) / 2], float)
        self.contours = extract_contours(images["ref"], window, min_points,
                                         emap=self.emaps["ref"])
        self.report: dict[str, Any] = {"window": window}
        if len(self.contours) < WANTED_CONTOURS and window < WIDE_WINDOW:
            # a scene filled by one large pattern (e.g. the board close up) leaves few
            # closed contours in the centre: use the whole image rather than fail
            wide = extract_contours(images["ref"], WIDE_WINDOW, min_points,
                                    emap=self.emaps["ref"])
            if len(wide) > len(self.contours):
                self.contours = wide
                self.report["window"] = WIDE_WINDOW
        if len(self.contours) < WANTED_CONTOURS:
            # a board filling the view: its squares' outlines join at the corners into
            # one edge network that reaches the image's border; take it piece by piece
            tiled = extract_contours(images["ref"], WIDE_WINDOW, min_points,
                                     emap=self.emaps["ref"], tile=TILE_PX)
            if len(tiled) > len(self.contours):
                self.contours = tiled
                self.report.update(window=WIDE_WINDOW, tiled_px=TILE_PX)
        if len(self.contours) < 3:
            raise SolveError(f"active-camera: too few contours in the reference image "
                             f"({len(self.contours)} in the central {WIDE_WINDOW:.0%}; "
                             "need 3): point the camera at a scene with separate shapes")
        self.rel = {k: tuple(np.subtract(v, angles["ref"])) for k, v in angles.items()}
        self.matches: dict[str, list] = {}
        # by label: the matches the moved curves were taken from, the curves' points and
        # normals and their k-d tree (``motion``)
        self._moved: dict[str, tuple] = {}
        self.report.update({"contours": len(self.contours), "motions": {}})

    def add_captures(self, images: dict, angles: dict,
                     emaps: dict[str, EdgeMap] | None = None) -> None:
        """Captures taken after the tracker was made (a live run makes it on the captures
        before the rolls, ``active_pipeline.pan_tilt_stage``): their angles and edge
        maps (``emaps``' where given, else taken here), as if they had been given at
        first."""
        new = [k for k in images if k not in self.emaps]
        self.emaps.update(_edge_maps({k: images[k] for k in new}, emaps))
        self.angles = {**self.angles, **{k: angles[k] for k in new}}
        self.rel.update((k, tuple(np.subtract(angles[k], self.angles["ref"]))) for k in new)

    def first_K(self) -> dict:
        """The thesis's shift search through pan+ and tilt+, then Strategy B."""
        w = self.size[0]
        thesis = {}
        for label, direction, theta in (("pan+", "x", self.rel["pan+"][0]),
                                        ("tilt+", "y", self.rel["tilt+"][1])):
            max_shift = abs(theta) * 2.0 * w + 10
            thesis[label] = [track_by_shift(c, self.emaps[label], direction, max_shift)
                             for c in self.contours]
        both = [i for i in range(len(self.contours))
                if thesis["pan+"][i].ok and thesis["tilt+"][i].ok]
        self.report["thesis_shift_tracked"] = len(both)
        if len(both) < 2:
            return self._first_K_one_axis(thesis)
        of = ContourStats.of
        try:
            first = active.strategy_b(
                [of(self.contours[i].points, self.centre) for i in both],
                [of(thesis["tilt+"][i].points, self.centre) for i in both],
                [of(thesis["pan+"][i].points, self.centre) for i in both],
                self.rel["tilt+"][1], self.rel["pan+"][0])
        except SolveError as exc:
            # Strategy B's quadratic has no root when distortion or a wide lens bends
            # the shifts: start from the shifts themselves; the refinement takes over.
            first = {"fx": self._focal_from_shifts(thesis["pan+"], both, 0),
                     "fy": self._focal_from_shifts(thesis["tilt+"], both, 1)}
            self.report["first_K"] = f"from the median shift ({exc})"
        return {"fx": first["fx"], "fy": first["fy"], "cx": self.centre[0],
                "cy": self.centre[1]}

    def _first_K_one_axis(self, thesis: dict) -> dict:
        """When the shift search follows too few contours through both pan+ and tilt+
        (shapes a pure shift cannot follow, e.g. a board close up under strong
        distortion): the focal length from the axis that tracked, the other assumed equal
        (square pixels to within a few per cent); tracking by prediction and the
        refinement then free both."""
        for label, axis in (("pan+", 0), ("tilt+", 1)):
            ok = [i for i, m in enumerate(thesis[label]) if m.ok]
            if len(ok) >= 2:
                f = self._focal_from_shifts(thesis[label], ok, axis)
                self.report["first_K"] = (f"from the {label} shifts alone ({len(ok)} "
                                          "contours), square pixels assumed")
                return {"fx": f, "fy": f, "cx": self.centre[0], "cy": self.centre[1]}
        counts = {label: sum(m.ok for m in thesis[label]) for label in thesis}
        raise SolveError("active-camera: contours lost in the pan/tilt images "
                         f"(tracked by the shift search: {counts}; need 2 in one of them)")

    def _focal_from_shifts(self, matches: list, idx: list[int], axis: int) -> float:
        """Focal length from pure-rotation shifts: a contour at ``u = (x - c) / f`` moves
        by ``f theta (1 + u^2)`` to first order (thesis eq. 3.3 linearised)."""
        theta = abs(self.rel["pan+" if axis == 0 else "tilt+"][axis])
        shifts = np.array([abs(matches[i].offset[axis]) for i in idx])
        centres = np.array([self.contours[i].points[:, axis].mean() for i in idx])
        f = np.median(shifts) / theta
        for _ in range(3):
            u = (centres - self.centre[axis]) / f
            f = float(np.median(shifts / (theta * (1 + u * u))))
        if not np.isfinite(f) or f <= 0:
            raise SolveError("active-camera: no first focal length from the pan/tilt shifts")
        return f

    def track_all(self, labels: list[str], K: dict | RefineResult, window: float,
                  joint_window: float = 0.0) -> None:
        """Follows every reference contour into each of ``labels``' images, from the same
        ``K``: predicted by a pinhole ``K`` or by a refinement's whole model (distortion
        included), then searched +-``window`` px around the prediction; with
        ``joint_window``, the predictions are first moved by the one shift, within
        +-``joint_window`` px, that lays all of them best on the image's edges
        (``common_shift``). The captures side by side in threads (each capture's tracking
        is independent of the others'); matches and report recorded in the labels' order."""
        outcomes = map_in_threads(lambda label: self._tracked(label, K, window, joint_window),
                                  labels)
        for label, (matches, shift) in zip(labels, outcomes, strict=True):
            if joint_window > 0:
                self.report.setdefault("joint_shift_px", {})[label] = shift
            self.matches[label] = matches
            rejected: dict[str, int] = {}
            for m in matches:
                if not m.ok:
                    key = m.reason.split(" (")[0]
                    rejected[key] = rejected.get(key, 0) + 1
            self.report["motions"][label] = {
                "tracked": sum(m.ok for m in matches), "rejected": rejected,
                "angles_deg": np.degrees(self.rel[label]).tolist()}

    def _tracked(self, label: str, K: dict | RefineResult, window: float,
                 joint_window: float) -> tuple[list, list | None]:
        """``label``'s matches, one per reference contour, and the joint shift applied
        (None: none found or none asked); reads the tracker, changes nothing."""
        # each contour's prediction is made once: the model's can be costly (distortion
        # and depths), and the joint shift and the per-contour search both need it
        predicted = self._predict_contours(K, label)
        shift = None
        if joint_window > 0:
            shift = common_shift(predicted, self.emaps[label], joint_window)
            if shift is not None:
                predicted = [q + np.asarray(shift, float) for q in predicted]
        matches = [track_by_prediction(c, self.emaps[label], lambda _points, q=q: q,
                                       window=window)
                   for c, q in zip(self.contours, predicted, strict=True)]
        return matches, None if shift is None else list(shift)

    def _predict_contours(self, K: dict | RefineResult, label: str) -> list[np.ndarray]:
        """Every contour's points predicted into ``label``, in one pass over all of them:
        by the pinhole K, or by the refinement with each contour's inverse depth once the
        scene's are measured (``inv_depth``) and the refinement estimated the offset with
        them. (One pass instead of one per contour: the undistortion's iteration and the
        model's set-up were a fifth of the tracking.)"""
        if not self.contours:
            return []
        points = np.concatenate([c.points for c in self.contours])
        sizes = [len(c.points) for c in self.contours]
        if not isinstance(K, RefineResult):
            pixels = pinhole_predictor(K, self.rel[label])(points)
        else:
            rho = None if self.inv_depth is None or not K.with_depths else \
                np.repeat(np.asarray(self.inv_depth, float)[:len(sizes)], sizes)
            pixels = K.predictor(self.angles["ref"], self.angles[label], rho)(points)
        return np.split(pixels, np.cumsum(sizes)[:-1])

    def motion(self, label: str, stride: int = 1) -> Motion | None:
        """The tracked contours of ``label`` as one refinement motion: every
        ``stride``-th reference point of each (the moved curves stay whole). The moved
        curves and their k-d tree are made once per tracking of ``label``, and shared by
        every refinement's motion of it (each predicting refinement built the trees of
        all the tiers before it again)."""
        matches = self.matches[label]
        idx = [i for i, m in enumerate(matches) if m.ok]
        if not idx:
            return None
        moved = self._moved.get(label)
        if moved is None or moved[0] is not matches:
            points = np.concatenate([matches[i].points for i in idx])
            moved = (matches, points, np.concatenate([matches[i].normals for i in idx]),
                     cKDTree(points))
            self._moved[label] = moved
        refs = [self.contours[i].points[::stride] for i in idx]
        return Motion(self.angles["ref"], self.angles[label], np.concatenate(refs),
                      moved[1], moved[2], label=label,
                      groups=np.concatenate([np.full(len(r), i) for r, i in zip(refs, idx,
                                                                              strict=True)]),
                      _tree=moved[3])

    def stats(self, label: str, idx: list[int]) -> list[ContourStats]:
        if label == "ref":
            return [ContourStats.of(self.contours[i].points, self.centre) for i in idx]
        return [ContourStats.of(self.matches[label][i].points, self.centre) for i in idx]

    def ok_in(self, *labels: str) -> list[int]:
        return [i for i in range(len(self.contours))
                if all(lb in self.matches and self.matches[lb][i].ok for lb in labels)]


def tiers(images: dict) -> tuple[list[str], list[str], list[str]]:
    """The captures in the order they are tracked: the small pan/tilt motions
    (``MOTIONS``, tracked from the first K), any wider pan/tilt motions (any other label
    but ``ref``, ``SHIFT`` and the rolls, tracked by prediction from a refinement on the
    small ones), then the rolls (tracked from a refinement on all of those, in the
    tiers of ``roll_tiers``)."""
    small = [m for m in MOTIONS if m in images]
    rolls = [m for m in images if m.startswith("roll")]
    wide = [m for m in images if m not in small and m not in rolls and m not in ("ref", SHIFT)]
    return small, wide, rolls


def roll_tiers(rolls: list[str], rel: dict) -> list[list[str]]:
    """The rolls grouped by how far they turn (to the nearest ``ROLL_TIER_DEG``),
    smallest first, each group tracked from a refinement on everything before it. A
    centre ``e`` px off moves a contour by ``2 e sin(r / 2)`` under a roll ``r``: the
    pans' centre on a narrow lens can be 20 px off (p1, p2 and the mounting trade with
    it), which the +-45 degree rolls survive and the larger ones do not (random world
    70038, f 1497 px, k1 -0.26: rolls of 90 degrees and more tracked 0-5 of 56 contours,
    and without them the centre came out 7 px off)."""
    groups: dict[int, list[str]] = {}
    for label in rolls:
        step = round(abs(math.degrees(rel[label][2])) / ROLL_TIER_DEG)
        groups.setdefault(step, []).append(label)
    return [groups[k] for k in sorted(groups)]


def tier_key(tier: list[str], wide: list[str], roll_groups: list[list[str]]) -> str:
    """The tracking report's name for the model that predicted ``tier``."""
    if tier is wide:
        return "K_for_wide"
    if tier is roll_groups[0]:
        return "K_for_rolls"
    return "K_for_rolls_" + "_".join(label.removeprefix("roll") for label in tier)
