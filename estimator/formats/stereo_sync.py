"""Left/right pairing by the nearest stamp within a tolerance.

Rigs without hardware-triggered cameras (and drivers that stamp on arrival) give left and
right images a few hundred microseconds to a few milliseconds apart, so exact stamp equality
pairs nothing. Here each left image takes the right image nearest in time, when the two are
each other's nearest neighbour (a one-to-one pairing) and within the tolerance. The frame is
stamped with the left image's time, as with exact pairs.

The default tolerance is a tenth of the frame period (5 ms at 20 Hz, 10 ms at 10 Hz): well
above trigger jitter, well below the half period at which a neighbouring frame could be taken.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DEFAULT_TOLERANCE_PERIODS", "StereoPairing", "default_tolerance_ns", "pair_stamps"]

# Default tolerance as a fraction of the median left frame period.
DEFAULT_TOLERANCE_PERIODS = 0.1


@dataclass(frozen=True)
class StereoPairing:
    """Paired stamps (left, right), in time order, and what could not be paired."""

    left_ns: np.ndarray
    right_ns: np.ndarray
    tolerance_ns: int
    unpaired_left: int
    unpaired_right: int

    @property
    def dropped(self) -> int:
        return self.unpaired_left + self.unpaired_right

    def summary(self, where: str) -> str:
        """One warning line for the images left out (empty when every image was paired)."""
        if not self.dropped:
            return ""
        return (
            f"{where}: skipping {self.dropped} image(s) without a partner within "
            f"{self.tolerance_ns / 1e6:g} ms in the other camera ({self.unpaired_left} left, "
            f"{self.unpaired_right} right); see --stereo-sync-tolerance"
        )


def default_tolerance_ns(left_ns: np.ndarray) -> int:
    """A tenth of the median left frame period (0 with fewer than two images: exact only)."""
    stamps = np.unique(np.asarray(left_ns, dtype=np.int64))
    if len(stamps) < 2:
        return 0
    return int(DEFAULT_TOLERANCE_PERIODS * float(np.median(np.diff(stamps))))


def _nearest(stamps: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Index of the stamp nearest each query (``stamps`` sorted, non-empty; ties: earlier)."""
    after = np.clip(np.searchsorted(stamps, queries), 0, len(stamps) - 1)
    before = np.clip(after - 1, 0, len(stamps) - 1)
    closer_before = np.abs(queries - stamps[before]) <= np.abs(stamps[after] - queries)
    return np.where(closer_before, before, after)


def pair_stamps(
    left_ns: np.ndarray, right_ns: np.ndarray, tolerance_ns: int | None = None
) -> StereoPairing:
    """Mutually nearest left/right stamps no more than ``tolerance_ns`` apart.

    ``None`` uses :func:`default_tolerance_ns`; 0 pairs equal stamps only.
    """
    left = np.unique(np.asarray(left_ns, dtype=np.int64))
    right = np.unique(np.asarray(right_ns, dtype=np.int64))
    tolerance = default_tolerance_ns(left) if tolerance_ns is None else int(tolerance_ns)
    if tolerance < 0:
        raise ValueError(f"the stereo sync tolerance must be >= 0, got {tolerance} ns")
    if len(left) == 0 or len(right) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return StereoPairing(empty, empty, tolerance, len(left), len(right))
    partner = _nearest(right, left)
    mutual = _nearest(left, right[partner]) == np.arange(len(left))
    close = np.abs(right[partner] - left) <= tolerance
    keep = mutual & close
    return StereoPairing(
        left[keep],
        right[partner[keep]],
        tolerance,
        unpaired_left=int(len(left) - keep.sum()),
        unpaired_right=int(len(right) - keep.sum()),
    )
