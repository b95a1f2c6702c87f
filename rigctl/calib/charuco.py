"""ChArUco boards: OpenCV's ``cv2.aruco.CharucoBoard`` and ``CharucoDetector``.

A ChArUco board is a checkerboard of ``rows`` x ``cols`` squares with an ArUco marker in
each white square. Its inner corners are those of the checkerboard (``board_points``:
id ``i * (cols - 1) + j`` at ``((j + 1) s, (i + 1) s, 0)``, OpenCV's own corner ids and
board frame), and each detected corner carries its id, so a view that shows part of the
board still gives its corners, each with its board point, and no view is ambiguous.

A board that is not the configured one is refused by name: markers of another dictionary
(``other_dictionary``), or marker ids the configured board does not have.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

# OpenCV's predefined dictionaries, by the name OpenCV gives them
DICTIONARIES: dict[str, int] = {name: getattr(cv2.aruco, name) for name in dir(cv2.aruco)
                                if name.startswith("DICT_")}
# one of each family whose members share their first markers (a _50's markers are the
# first 50 of the _1000's): searched to name a board's foreign dictionary
_FAMILIES = ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_6X6_1000", "DICT_7X7_1000",
             "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h10",
             "DICT_APRILTAG_36h11", "DICT_ARUCO_MIP_36h12", "DICT_ARUCO_ORIGINAL")
MIN_MARKERS = 1  # a corner is identified from this many of its (up to 2) neighbouring markers
# A board of another dictionary is named when its markers are this many, and this share
# of the square outlines the configured dictionary could not decode. The configured
# board's own markers, too small to decode, read as 2-3 scattered ids of a dictionary of
# many markers (DICT_4X4_1000 ids 24 and 852, 37, 124 and 999 on random worlds 99403 and
# 99405 at 0.9-1.6 m: 2-3 of 34-62 outlines); a board of another dictionary gave 23-35 of
# 69-79 outlines at 0.45-1.2 m.
MIN_FOREIGN_MARKERS = 4
MIN_FOREIGN_SHARE = 0.2
MIN_CORNERS = 6  # fewer identified corners in a view: not used (a pose needs 6)


def known_dictionaries() -> str:
    """The dictionary names a rig or world file may give, comma-separated."""
    return ", ".join(sorted(DICTIONARIES))


def check_dictionary(name: str) -> str:
    """``name`` if OpenCV knows the dictionary, else ``ValueError`` listing those it knows
    (the config's validators turn it into a ``ConfigError`` naming the key)."""
    if name not in DICTIONARIES:
        raise ValueError(f"unknown ArUco dictionary {name!r}; known: {known_dictionaries()}")
    return name


def dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined dictionary of that name."""
    return cv2.aruco.getPredefinedDictionary(DICTIONARIES[check_dictionary(name)])


@dataclass(frozen=True)
class CharucoSpec:
    """One ChArUco board as OpenCV's ``CharucoBoard`` takes it: squares (``cols`` along
    x, ``rows`` along y), square and marker sides (metres), dictionary name, and the
    layout of boards printed by OpenCV before 4.6 (``legacy``)."""

    dictionary: str
    rows: int
    cols: int
    square_m: float
    marker_m: float
    legacy: bool = False

    @classmethod
    def of(cls, target) -> CharucoSpec:
        """The spec of a rig file's target (``TargetConfig`` with ``type: charuco``)."""
        return cls(target.dictionary, target.rows, target.cols, target.square_mm / 1000.0,
                   target.marker_mm / 1000.0, bool(target.legacy_pattern))

    def name(self) -> str:
        return (f"{self.dictionary}, {self.rows} x {self.cols} squares"
                f"{', legacy pattern' if self.legacy else ''}")

    def markers(self) -> int:
        """How many markers the board carries (one per white square)."""
        return self.rows * self.cols // 2


@lru_cache(maxsize=16)
def board(spec: CharucoSpec) -> cv2.aruco.CharucoBoard:
    """OpenCV's board of ``spec``; ``ValueError`` when its dictionary holds too few
    markers for it."""
    d = dictionary(spec.dictionary)
    if spec.markers() > d.bytesList.shape[0]:
        raise ValueError(f"{spec.dictionary} has {d.bytesList.shape[0]} markers; a board of "
                         f"{spec.rows} x {spec.cols} squares needs {spec.markers()}")
    b = cv2.aruco.CharucoBoard((spec.cols, spec.rows), spec.square_m, spec.marker_m, d)
    b.setLegacyPattern(spec.legacy)
    return b


@dataclass
class CharucoDetection:
    """The board's corners in id order (``(rows-1)(cols-1)`` x 2 pixels, NaN where not
    seen; None when too few were), the number identified, and why the view is not used
    (``note``: too few corners, or not the configured board, named)."""

    corners: np.ndarray | None
    found: int
    note: str | None = None


def _detector(spec: CharucoSpec) -> cv2.aruco.CharucoDetector:
    params = cv2.aruco.CharucoParameters()
    params.tryRefineMarkers = True
    params.minMarkers = MIN_MARKERS
    detector_params = cv2.aruco.DetectorParameters()
    detector_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.CharucoDetector(board(spec), params, detector_params)


def detect_charuco(image: np.ndarray, spec: CharucoSpec) -> CharucoDetection:
    """The corners of the board ``spec`` in ``image`` (``CharucoDetector``), each at its
    id (``rigctl.calib.board.detect_target`` refines them as a checkerboard's). Refused,
    with a note naming what was seen: marker ids beyond the board's, or no marker of the
    configured dictionary where there are markers of another."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    n = (spec.rows - 1) * (spec.cols - 1)
    aruco = cv2.aruco.ArucoDetector(dictionary(spec.dictionary),
                                    _detector(spec).getDetectorParameters())
    marker_corners, marker_ids, rejected = aruco.detectMarkers(gray)
    ids = [] if marker_ids is None else sorted(set(int(i) for i in marker_ids.ravel()))
    foreign = [i for i in ids if i >= spec.markers()]
    if foreign:
        return CharucoDetection(None, 0, f"markers {_id_list(foreign)} of {spec.dictionary} "
                                f"are not on the configured board ({spec.name()}: ids 0-"
                                f"{spec.markers() - 1}); view left out")
    if len(ids) < 2:
        other = other_dictionary(gray, spec.dictionary) \
            if len(rejected) >= MIN_FOREIGN_MARKERS else None
        if other is not None and len(other[1]) >= MIN_FOREIGN_SHARE * len(rejected):
            return CharucoDetection(None, 0, f"markers of {other[0]} (ids {_id_list(other[1])})"
                                    f", not of the configured {spec.dictionary}: not the "
                                    f"configured board ({spec.name()}); view left out")
        return CharucoDetection(None, 0, _not_found_note(spec, len(ids), len(rejected)))
    corners, corner_ids = _board_corners(gray, spec, marker_corners, marker_ids)
    found = 0 if corner_ids is None else len(corner_ids)
    if found < MIN_CORNERS and len(ids) >= 4 and found < len(ids) / 2:
        # the markers are the board's, but their neighbours are not where it puts them
        return CharucoDetection(None, found, _layout_note(gray, spec, marker_corners,
                                                          marker_ids, len(ids)))
    if found < MIN_CORNERS:
        return CharucoDetection(None, found, f"{found} ChArUco corners identified (need "
                                f"{MIN_CORNERS}); board not found")
    out = np.full((n, 2), np.nan)
    out[corner_ids.ravel()] = corners.reshape(-1, 2)
    return CharucoDetection(out, found)


def _not_found_note(spec: CharucoSpec, markers: int, outlines: int) -> str:
    """Why no board was found: the configured dictionary's markers decoded, and the square
    outlines that did not decode (a board too far, blurred or too small in the image
    leaves its markers as such outlines)."""
    note = f"{markers} markers of {spec.dictionary} decoded"
    if outlines >= MIN_FOREIGN_MARKERS:
        note += (f" ({outlines} square outlines did not decode: if the board is in view, its "
                 "markers are too small in the image, blurred, or of another dictionary)")
    return note + "; board not found"


def _board_corners(gray, spec: CharucoSpec, marker_corners, marker_ids):
    """``CharucoDetector.detectBoard`` on markers already found: corners and their ids
    (OpenCV checks that the markers around each corner are the board's neighbours)."""
    corners, corner_ids, _, _ = _detector(spec).detectBoard(
        gray, markerCorners=marker_corners, markerIds=marker_ids)
    return corners, corner_ids


def _layout_note(gray, spec: CharucoSpec, marker_corners, marker_ids, markers: int) -> str:
    """Why markers of the configured dictionary gave no corners: the board's squares are
    laid out otherwise (another size, or the other ``legacy_pattern``, tried here)."""
    if spec.rows % 2 == 0:  # OpenCV's two layouts differ only with an even row count
        other = CharucoSpec(spec.dictionary, spec.rows, spec.cols, spec.square_m,
                            spec.marker_m, not spec.legacy)
        _, ids = _board_corners(gray, other, marker_corners, marker_ids)
        if ids is not None and len(ids) >= MIN_CORNERS:
            return (f"{markers} markers of {spec.dictionary} lie as on a board with "
                    f"legacy_pattern: {str(other.legacy).lower()}, not as on the configured "
                    f"board ({spec.name()}); view left out")
    return (f"{markers} markers of {spec.dictionary} found, but not where the configured "
            f"board ({spec.name()}) puts them: a board of another size or layout; view "
            "left out")


def _id_list(ids: list[int]) -> str:
    shown = ", ".join(str(i) for i in ids[:8])
    return shown + (f" and {len(ids) - 8} more" if len(ids) > 8 else "")


def other_dictionary(gray: np.ndarray, configured: str) -> tuple[str, list[int]] | None:
    """The predefined dictionary (the smallest of its family holding every id seen) whose
    markers are in the image, with their ids, when at least ``MIN_FOREIGN_MARKERS`` of
    one are and the configured dictionary is not it; None otherwise."""
    best: tuple[str, list[int]] | None = None
    params = cv2.aruco.DetectorParameters()
    for family in _FAMILIES:
        if family == configured:
            continue
        _, ids, _ = cv2.aruco.ArucoDetector(dictionary(family), params).detectMarkers(gray)
        found = [] if ids is None else sorted(set(int(i) for i in ids.ravel()))
        if len(found) >= MIN_FOREIGN_MARKERS and (best is None or len(found) > len(best[1])):
            best = (_smallest_member(family, max(found)), found)
    if best is not None and best[0] == configured:
        return None
    return best


def _smallest_member(family: str, top_id: int) -> str:
    """The smallest predefined dictionary of ``family`` (same marker bits, fewer markers)
    that holds id ``top_id``."""
    prefix = family.rsplit("_", 1)[0] + "_"
    if not family.startswith(("DICT_4X4", "DICT_5X5", "DICT_6X6", "DICT_7X7")):
        return family
    sizes = sorted(int(name.rsplit("_", 1)[1]) for name in DICTIONARIES
                   if name.startswith(prefix))
    return prefix + str(next(s for s in sizes if s > top_id))
