"""Left/right pairing by the nearest stamp within a tolerance (estimator.formats.stereo_sync)."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.formats.stereo_sync import default_tolerance_ns, pair_stamps

MS = 1_000_000


def test_equal_stamps_pair_as_before() -> None:
    stamps = np.arange(10) * 50 * MS
    pairing = pair_stamps(stamps, stamps)
    assert pairing.left_ns.tolist() == pairing.right_ns.tolist() == stamps.tolist()
    assert pairing.dropped == 0 and pairing.summary("x") == ""
    assert pairing.tolerance_ns == 5 * MS  # a tenth of the 50 ms period


def test_jittered_stamps_pair_one_to_one_and_far_ones_are_dropped() -> None:
    left = np.arange(8) * 50 * MS
    right = left + np.array([1, -2, 3, 0, -4, 2, 30, 1]) * MS  # frame 6 is 30 ms off
    right = np.append(right, 125 * MS)  # a stray image half way between frames 2 and 3
    pairing = pair_stamps(left, right)
    assert pairing.left_ns.tolist() == [t for k, t in enumerate(left) if k != 6]
    assert (pairing.right_ns - pairing.left_ns).tolist() == [
        d * MS for d in (1, -2, 3, 0, -4, 2, 1)]
    assert (pairing.unpaired_left, pairing.unpaired_right) == (1, 2)
    summary = pairing.summary("bag")
    assert "skipping 3 image(s) without a partner within 5 ms" in summary
    assert "(1 left, 2 right)" in summary
    # 0 = equal stamps only: only frame 3 is exact.
    assert pair_stamps(left, right, 0).left_ns.tolist() == [150 * MS]


def test_one_right_image_never_serves_two_left_images() -> None:
    """Two left images both nearest the same right one: only the mutually nearest pairs."""
    pairing = pair_stamps(np.array([0, 4 * MS]), np.array([3 * MS]), tolerance_ns=5 * MS)
    assert pairing.left_ns.tolist() == [4 * MS] and pairing.right_ns.tolist() == [3 * MS]
    assert (pairing.unpaired_left, pairing.unpaired_right) == (1, 0)


def test_tolerance_bounds_and_bad_values() -> None:
    left = np.array([0, 100 * MS])
    assert pair_stamps(left, left + 10 * MS, 10 * MS).dropped == 0  # inclusive
    assert pair_stamps(left, left + 10 * MS + 1, 10 * MS).dropped == 4
    assert default_tolerance_ns(np.array([7])) == 0  # one image: no period known
    assert pair_stamps(np.array([], dtype=np.int64), left).unpaired_right == 2
    with pytest.raises(ValueError, match=">= 0"):
        pair_stamps(left, left, -1)
