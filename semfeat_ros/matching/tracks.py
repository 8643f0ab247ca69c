"""Track bookkeeping: persistent ids, ages and termination of unmatched tracks.

A *track* is one scene point followed through consecutive frames. Its id is a uint32 taken from
a counter that only increases: ids are never reused, not after a track ends and not after
:meth:`TrackManager.reset` (a bag loop or a camera change starts new tracks with new ids).

Per frame the caller does::

    tm.begin_frame()
    tm.extend(track_id)        # a live track observed again in this frame
    new_id = tm.start()        # a new track seen in the previous and in this frame
    terminated = tm.end_frame()

``age`` counts the frames a track has been observed in (2 when it starts, since a track is born
from a match between two frames). ``missed`` counts consecutive frames without an observation; a
track whose ``missed`` exceeds ``max_missed`` is terminated. Tracks with ``missed >= 1`` that are
still alive are *lost* and may be re-acquired with :meth:`TrackManager.extend`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semfeat_ros.matching.errors import MatchingConfigError, MatchingError, TrackIdOverflowError

MAX_TRACK_ID = 2**32 - 1
MAX_AGE = 2**16 - 1  # ages are published as uint16 and saturate there


@dataclass
class TrackState:
    """State of one live track."""

    track_id: int
    age: int
    """Frames the track has been observed in."""
    missed: int
    """Consecutive frames (ending with the last finished one) without an observation."""
    last_frame: int
    """Sequence number (see :attr:`TrackManager.frame`) of the last observation."""


class TrackManager:
    """Persistent track ids, ages and termination (see the module doc)."""

    def __init__(self, max_missed: int = 2, first_id: int = 0) -> None:
        if isinstance(max_missed, bool) or not isinstance(max_missed, int) or max_missed < 0:
            raise MatchingConfigError(f'max_missed: expected an integer >= 0, got {max_missed!r}')
        if not 0 <= first_id <= MAX_TRACK_ID:
            raise MatchingConfigError(
                f'first_id: expected 0..{MAX_TRACK_ID}, got {first_id!r}')
        self.max_missed = max_missed
        self._next_id = int(first_id)
        self._tracks: dict[int, TrackState] = {}
        self._frame = -1
        self._in_frame = False
        self._seen: set[int] = set()

    @property
    def frame(self) -> int:
        """Sequence number of the current (or last finished) frame; -1 before the first."""
        return self._frame

    def __len__(self) -> int:
        return len(self._tracks)

    def __contains__(self, track_id: int) -> bool:
        return int(track_id) in self._tracks

    def get(self, track_id: int) -> TrackState:
        """State of a live track; ``KeyError`` if it does not exist (any more)."""
        return self._tracks[int(track_id)]

    def age(self, track_id: int) -> int:
        """Observed frames of a live track, saturated at 65535 (uint16)."""
        return min(self._tracks[int(track_id)].age, MAX_AGE)

    def ages(self, track_ids: np.ndarray) -> np.ndarray:
        """(N,) uint16 ages of live tracks (saturated at 65535)."""
        tr = self._tracks
        return np.array([min(tr[int(t)].age, MAX_AGE) for t in np.asarray(track_ids)],
                        dtype=np.uint16)

    def lost(self) -> dict[int, TrackState]:
        """Live tracks not observed in the last finished frame (``missed >= 1``)."""
        return {k: v for k, v in self._tracks.items() if v.missed >= 1}

    def lost_since(self, frame: int) -> np.ndarray:
        """(K,) int64 ids of live lost tracks whose last observation was in ``frame``."""
        return np.array([k for k, v in self._tracks.items()
                         if v.missed >= 1 and v.last_frame == frame], dtype=np.int64)

    def reset(self) -> list[int]:
        """End every track (the id counter keeps counting); returns the ended ids."""
        ended = sorted(self._tracks)
        self._tracks.clear()
        self._seen.clear()
        self._in_frame = False
        return ended

    def begin_frame(self) -> int:
        """Start a new frame; returns its sequence number."""
        if self._in_frame:
            raise MatchingError('begin_frame() called twice without end_frame()')
        self._frame += 1
        self._in_frame = True
        self._seen = set()
        return self._frame

    def _require_frame(self) -> None:
        if not self._in_frame:
            raise MatchingError('call begin_frame() before observing tracks')

    def extend(self, track_id: int) -> int:
        """Observe the live track ``track_id`` in the current frame; returns its new age."""
        self._require_frame()
        tid = int(track_id)
        state = self._tracks.get(tid)
        if state is None:
            raise MatchingError(f'track {tid} does not exist (ended or never started)')
        if tid in self._seen:
            raise MatchingError(f'track {tid} observed twice in frame {self._frame}')
        self._seen.add(tid)
        state.age += 1
        state.missed = 0
        state.last_frame = self._frame
        return state.age

    def extend_many(self, track_ids: np.ndarray) -> None:
        """:meth:`extend` for each id (ids must be distinct)."""
        for t in np.asarray(track_ids, dtype=np.int64).tolist():
            self.extend(t)

    def start_many(self, count: int) -> np.ndarray:
        """``count`` new tracks (see :meth:`start`); returns their (count,) int64 ids."""
        return np.array([self.start() for _ in range(int(count))], dtype=np.int64)

    def start(self) -> int:
        """New track observed in the previous and the current frame (age 2); returns its id."""
        self._require_frame()
        if self._next_id > MAX_TRACK_ID:
            raise TrackIdOverflowError(
                f'all {MAX_TRACK_ID + 1} uint32 track ids are used; restart the matcher')
        tid = self._next_id
        self._next_id += 1
        self._tracks[tid] = TrackState(track_id=tid, age=2, missed=0, last_frame=self._frame)
        self._seen.add(tid)
        return tid

    def end_frame(self) -> list[int]:
        """Finish the frame: unobserved tracks miss one frame; returns the terminated ids."""
        self._require_frame()
        ended = []
        for tid, state in list(self._tracks.items()):
            if tid in self._seen:
                continue
            state.missed += 1
            if state.missed > self.max_missed:
                del self._tracks[tid]
                ended.append(tid)
        self._in_frame = False
        return sorted(ended)
