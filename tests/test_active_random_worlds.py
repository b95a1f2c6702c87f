"""The active-camera solve on random worlds nobody tuned it for, with the procedure's
default plan: each world's own renderer (``rigctl.mocks.world``: OpenCV's projection with its
k1 k2 k3 p1 p2, blur, noise, JPEG) draws what the camera sees at the planned head angles,
the arm's sideways move included, and ``rigctl.calib.active_pipeline`` solves it, as
``rigctl bench active-worlds`` does on many more (seeds 5000-7019 there).

Seeds 24 and 38 are wide lenses (681 and 635 px) with strong barrel distortion, where
Strategies B-D fail; before the refinement started from the pan/tilt refinement and
tracked the wide angles tier by tier, seed 24 came out 2.1 % and 104 px off, and seed 38
0.18 % off. Seed 26 is an ordinary 1000 px lens.

Seed 11015 is a UR3e whose scene is near (0.25 m) and turned away, with the camera
2.6 mm off the head's axes: the pans' and the rolls' centres both carry that parallax
(33 and 22 px). Before the tiers' refinements used the measured depths and the final
refinement tried more than one start, it ended 26 px off with a reported sigma of 0.9 px
(z 29); now 0.3 px.

Seed 70038 is a narrow lens (1497 px) with strong barrel distortion (k1 -0.26): the
refinement on the pans and tilts alone put the centre 22 px off, the rolls of 90 degrees
and more were all predicted from it and lost (0-5 of 56 contours tracked), and the
centre came out 7.4 px off with a sigma of 0.35 px (z 18). Rolls tracked 45 degrees at a
time, each roll's predictions first moved together by one shift for the whole image: 0.4
px. (Tiers alone broke seed 24, whose pans' centre is 30 px off: its +-45 degree rolls
kept 3 of 24 contours, and the model predicting the larger ones came out 1 % off.)

These trials give the solver the commanded head angles (``ideal`` encoders) and let it
take them as exact, as they were written for. Taken as readings of the servos' encoder
sigma (``active_angles``, what the procedure does), the focal length of these five
worlds moves by up to 0.05 % (seed 24: 0.052 %, |z| 1.9) within its grown sigma. The
random worlds' servos read their angles quantized to a pulse with noise
(``head.encoder: hardware``): the last test here."""

from __future__ import annotations

import pytest

from rigctl.bench.active_worlds import summarise, world_trial

pytestmark = pytest.mark.heavy

# A hang guard, not a time limit: the slowest world here (seed 11015, many contours, each
# with its own depth) takes about a minute on a busy host
@pytest.mark.timeout(600)
@pytest.mark.parametrize("seed", [24, 38, 26, 11015, 70038])
def test_default_plan_meets_the_truth_of_an_unseen_world(seed):
    row = world_trial((seed, None, 0.010, 0.0, True, False))
    assert "error" not in row, row.get("error")
    assert row["focal_pct"] < 0.05, row
    assert row["centre_px"] < 1.0, row
    # the reported sigma covers the error (the model-error floor included)
    assert max(abs(z) for z in row["z"].values()) < 4.0, row["z"]
    # the arm's move measured the scene's depths, so the parallax was estimated
    assert row["parallax"]["estimated"], row["parallax"]
    # the head's geometry (``head_geometry``) turns the camera as the world's head does:
    # 0.001-0.005 deg off over pans and tilts of 15-20 deg, 0.01-0.03 deg over rolls,
    # each within its reported covariance (Mahalanobis norm, 3 dof)
    head = row["head_geometry"]
    assert head["pan_tilt"]["rotation_error_deg"] < 0.02, head
    assert head["roll"]["rotation_error_deg"] < 0.1, head
    assert head["pan_tilt"]["mahalanobis"] < 4.0 and head["roll"]["mahalanobis"] < 4.0, head
    # the benchmark times the solve itself (rendering excluded), on the wall and of CPU
    assert row["solve_s"] > 0 and row["solve_cpu_s"] > 0, row
    assert summarise([row])["solve_s"]["median"] == row["solve_s"]


# a hang guard, as above
@pytest.mark.timeout(600)
def test_an_offset_that_one_contour_carries_is_reported_uncertain():
    """Seed 62019 (a UR10e, 1545 px lens): 25 of the 26 contours whose depth the arm's
    move measured lie on a board filling the view at 0.56 m, one at 1.9 m, so that one
    contour carries the centre of projection's offset, and a small model error pulls it.
    The focal length comes out 0.11 % low and the centre 2.2 px off; the per-motion
    clusters reported sigmas 7 times too small (z 6.8). The delete-one-contour jackknife
    sees that one contour carries the offset: |z| < 3. (The error itself is a known
    limitation; the bounds on it catch a regression.) The result names that contour, the
    far one, for the operator. The recorded angles are taken as exact here, as this was
    measured: estimating the head's angles (``active_angles``) spreads what that contour
    carried (its share of fx 0.26, jackknife sigma ratio 1.2; the focal length 0.10 % and
    the centre 1.9 px off, |z| 1.6), and then no contour is named."""
    row = world_trial((62019, None, 0.010, 0.0, True, False))
    assert "error" not in row, row.get("error")
    assert row["focal_pct"] < 0.3 and row["centre_px"] < 5.0, row
    assert max(abs(z) for z in row["z"].values()) < 3.0, row["z"]
    carried = row["parallax"].get("carried_by")
    assert carried, row["parallax"]["influence"]
    assert {"fx", "fy"} <= set(carried["parameters"]), carried
    assert carried["depth_m"] > 1.5 and carried["others_median_depth_m"] < 0.7, carried



# a hang guard, as above
@pytest.mark.timeout(600)
def test_quantized_head_encoders_are_estimated_within_their_sigma():
    """Seed 26 with its servos' own encoders (XM540 pan and tilt, XH430 roll: readings
    quantized to 0.088 deg, with about half a pulse of noise). Taking the recorded angles
    as exact, an error of a few hundredths of a degree on a 3-25 degree rotation moved
    the focal length by about 0.5 % and the centre by a few px (0.003 % and 0.1 px with
    the commanded angles). The refinement now estimates each capture's offset from its
    reading within the servo model's encoder sigma (``active_angles``): 0.07 % and
    0.22 px, |z| 1.2."""
    row = world_trial((26, None, 0.010))
    assert "error" not in row, row.get("error")
    assert row["encoders"] == "hardware"
    assert row["focal_pct"] < 0.2 and row["centre_px"] < 1.0, row
    assert max(abs(z) for z in row["z"].values()) < 3.0, row["z"]


# a hang guard, as above
@pytest.mark.timeout(600)
def test_rolls_are_tracked_where_the_pans_could_not_tell_the_roll_axis():
    """Seed 120013 (an 865 px lens, k1 -0.26, the camera 2.8 mm off the axes, hardware
    encoders). While the refinements on the pans and tilts let the roll axis's tilts
    move, they drifted 5 degrees, the rolls were predicted 50-150 px off, and the
    larger ones were tracked to the wrong contours: the roll axis came out 2.4 degrees
    off with a sigma of 0.03 degrees (the rotation from home at the rolls 4.8 degrees
    off, Mahalanobis norm 91). Held until a tier rolls: 0.03 degrees, norm 0.5."""
    row = world_trial((120013, None, 0.010))
    assert "error" not in row, row.get("error")
    assert row["encoders"] == "hardware"
    head = row["head_geometry"]
    assert head["roll"]["rotation_error_deg"] < 0.1, head
    assert head["roll"]["mahalanobis"] < 4.0 and head["pan_tilt"]["mahalanobis"] < 4.0, head
    assert row["focal_pct"] < 0.05 and row["centre_px"] < 1.0, row
    assert max(abs(z) for z in row["z"].values()) < 3.0, row["z"]


# a hang guard, as above
@pytest.mark.timeout(600)
def test_the_final_refinement_starts_from_the_offset_the_rolls_told():
    """Seed 140052 (a 929 px lens, the scene at 1.4-3.8 m, the camera 2.2 mm off the
    axes, hardware encoders). Started with the centre's offset at zero, the final
    refinement stopped in a local minimum with the offset at 0.08 mm (2.4 mm off at a
    sigma of 0.06 mm) and cy 1.2 px off (z -5.0). Started where the last predicting
    refinement, which saw the rolls, put the offset and the roll axis: 0.4 mm and
    0.4 px, at a third less robust cost."""
    row = world_trial((140052, None, 0.010))
    assert "error" not in row, row.get("error")
    assert row["focal_pct"] < 0.05 and row["centre_px"] < 0.8, row
    assert max(abs(z) for z in row["z"].values()) < 3.0, row["z"]
    assert row["head_geometry"]["offset_error_mm"] < 1.0, row["head_geometry"]


def _offset_errors(row: dict) -> tuple[list[float], list[float]]:
    """The centre of projection's offset error per axis (mm) and its error / sigma."""
    parallax = row["parallax"]
    error = [g - t for g, t in zip(parallax["centre_offset_mm"], row["camera_offset_mm"],
                                   strict=True)]
    return error, [e / s for e, s in zip(error, parallax["sigma_mm"], strict=True)]


# a hang guard, as above
@pytest.mark.timeout(600)
def test_a_start_that_ends_at_another_offset_is_another_basin():
    """Seed 130046 (a 994 px lens, the scene at 1.8-5.3 m, the camera 1.4 mm off the
    axes, hardware encoders). From zero offset the final refinement stopped where the
    captures' angle offsets carried the parallax: the offset at 0.02 mm, claimed to
    0.03 mm (error / sigma 27-40). The rolls' start ended at the true offset, its centre
    0.5 px from that end, and was merged into its basin by the centre alone; refined on
    every point too, it has the lower robust cost."""
    row = world_trial((130046, None, 0.010))
    assert "error" not in row, row.get("error")
    error_mm, z = _offset_errors(row)
    assert max(abs(e) for e in error_mm) < 0.5, row["parallax"]
    assert max(abs(v) for v in z) < 4.0, row["parallax"]
    assert max(abs(z) for z in row["z"].values()) < 3.0, row["z"]
    assert row["centre_px"] < 0.8, row
    refined = [name for name, start in row["final_starts"].items() if "refined_to" in start]
    assert len(refined) >= 2, row["final_starts"]


# a hang guard, as above
@pytest.mark.timeout(600)
def test_the_offsets_sigma_counts_the_measured_depths_error():
    """Seed 130005 (an 829 px lens, the scene at 0.4-4 m, hardware encoders). With the
    depths the arm's move measured held as exact, the centre of projection's offset
    claimed 0.012-0.019 mm across the optical axis and was 0.05-0.10 mm off (error /
    sigma -4.5 and 5.4); with their measurement error and scale as consider terms,
    within 3."""
    row = world_trial((130005, None, 0.010))
    assert "error" not in row, row.get("error")
    error_mm, z = _offset_errors(row)
    assert max(abs(e) for e in error_mm) < 0.3, row["parallax"]
    assert max(abs(v) for v in z) < 4.0, row["parallax"]
    assert max(abs(z) for z in row["z"].values()) < 3.0, row["z"]
