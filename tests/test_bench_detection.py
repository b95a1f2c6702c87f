"""``rigctl bench detection``: the half-scale first search against the whole image's, on
a random world's rendered views (no stand-ins), judged against the world's truth."""

from __future__ import annotations

import pytest

from rigctl.bench import detection

pytestmark = pytest.mark.timeout(120)


def test_both_searches_find_every_view_and_agree_with_the_truth():
    """Seed 1000 (measured: 0.105 px RMS for either search, corners 0.0003 px apart)."""
    result = detection.run(n=1, first_seed=1000, views=4)
    summary = result["summary"]
    assert summary["views"] == 4 and summary["worlds"] == 1
    half, whole = summary["half_scale_first"], summary["whole_image"]
    assert half["found"] == whole["found"] == 4
    assert summary["largest_change_px"] < 0.002
    for search in (half, whole):
        assert 0.03 < search["rms_px_median"] < 0.2, search
        assert search["shared_px_rms"] < 0.05, search
        assert search["cpu_s_per_view"] > 0
    assert abs(half["rms_px_median"] - whole["rms_px_median"]) < 0.002
