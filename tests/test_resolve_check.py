"""The re-solve comparison of tests/resolve_check.py: 1e-4 of each quantity's own scale,
so that a change a regression would make in a small quantity is seen."""

from __future__ import annotations

import copy

from tests.resolve_check import _differences

RESULT = {
    "fx": 900.03, "distortion": [-0.0807, 0.0528, 3.443e-4, -1.2e-4, 0.0],
    "roll_axis_in_cam": [-5.43e-5, -0.00507, 0.99998],
    "covariance": {"matrix": [[1.0e-2, 2.2e-3, 1.1e-9], [2.2e-3, 1.1e-2, 4.3e-10],
                              [1.1e-9, 4.3e-10, 3.0e-8]]},
    "T_flange_cam": [[1.0, 0.0, 0.0, 0.0123], [0.0, 1.0, 0.0, -0.0457],
                     [0.0, 0.0, 1.0, 0.0612], [0.0, 0.0, 0.0, 1.0]],
    "views": 8,
    "head_angles": {"offsets_deg": {"tilt+20": [-1.7770e-6, 3.9e-4, -1.3e-3]}},
}


def changed(path, value):
    doc = copy.deepcopy(RESULT)
    *parents, last = path
    target = doc
    for key in parents:
        target = target[key]
    target[last] = value
    return doc


def test_rounding_below_1e4_of_each_quantity_is_equal():
    again = changed(("fx",), 900.03 * (1 + 5e-5))
    again["distortion"][2] *= 1 + 5e-5
    again["roll_axis_in_cam"][0] += 1e-6  # the axis is a unit vector: 1e-4 of 1
    again["covariance"]["matrix"][2][2] *= 1 + 5e-5
    again["T_flange_cam"][0][3] += 1e-6  # under 1e-4 of the 77 mm translation
    # a head-angle offset zero up to rounding, beside the capture's others (measured)
    again["head_angles"]["offsets_deg"]["tilt+20"][0] = -1.7774e-6
    assert list(_differences(RESULT, again)) == []


def test_changes_in_small_quantities_are_differences():
    """Each of these passed the former comparison (1e-4 relative or 1e-5 absolute)."""
    cases = {
        ("distortion", 2): 3.443e-4 * 1.01,  # p1 by 1 %
        ("distortion", 4): 1e-9,  # k3 off its zero
        ("T_flange_cam", 1, 3): -0.0457 + 9e-6,  # 9 um in metres
        ("head_angles", "offsets_deg", "tilt+20", 0): 5e-7,  # 2e-3 of the capture's offsets
    }
    for path, value in cases.items():
        doc = copy.deepcopy(RESULT)
        target = doc
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
        found = list(_differences(RESULT, doc))
        assert len(found) == 1, (path, found)
    sigma = copy.deepcopy(RESULT)
    sigma["covariance"]["matrix"][2][2] = 3.0e-8 * 1.5  # a variance 50 % larger
    # and a correlation by 2.4e-4
    sigma["covariance"]["matrix"][0][2] = sigma["covariance"]["matrix"][2][0] = 6e-9
    assert len(list(_differences(RESULT, sigma))) == 3
