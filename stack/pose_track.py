"""A trajectory that grows one stamped pose at a time, kept compactly.

Two NumPy arrays (stamps, and 4x4 poses) that double their room when full: a pose costs its 136
bytes, not a Python float and a NumPy array object per pose (about 300 bytes), and reading the
trajectory back is a view, not a list converted to an array at every lookup. The doubled room's
pages stay untouched until poses arrive in them, so memory follows the poses kept.
"""
from __future__ import annotations

import numpy as np


class PoseTrack:
    """Stamped 4x4 poses appended in time order. ``stamps`` and ``poses`` are read-only views of what
    is kept so far (valid until the next ``append``); ``arrays()`` gives copies."""

    def __init__(self, capacity: int = 1024):
        self._stamps = np.empty(max(1, int(capacity)))
        self._poses = np.empty((len(self._stamps), 4, 4))
        self._n = 0

    def append(self, stamp: float, T: np.ndarray) -> None:
        if self._n == len(self._stamps):
            stamps, poses = np.empty(2 * self._n), np.empty((2 * self._n, 4, 4))
            stamps[:self._n], poses[:self._n] = self._stamps, self._poses
            self._stamps, self._poses = stamps, poses
        self._stamps[self._n] = stamp
        self._poses[self._n] = T
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def __bool__(self) -> bool:
        return self._n > 0

    @property
    def stamps(self) -> np.ndarray:
        v = self._stamps[:self._n]
        v.flags.writeable = False
        return v

    @property
    def poses(self) -> np.ndarray:
        v = self._poses[:self._n]
        v.flags.writeable = False
        return v

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (N,), poses (N, 4, 4)), new arrays."""
        return self._stamps[:self._n].copy(), self._poses[:self._n].copy()
