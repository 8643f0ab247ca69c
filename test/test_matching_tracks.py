"""Track bookkeeping: persistent ids, ages, termination (semfeat_ros.matching.tracks)."""
from __future__ import annotations

import pytest

from semfeat_ros.matching.errors import MatchingConfigError, MatchingError, TrackIdOverflowError
from semfeat_ros.matching.tracks import MAX_AGE, MAX_TRACK_ID, TrackManager


def test_ids_ages_and_termination() -> None:
    tm = TrackManager(max_missed=1)
    tm.begin_frame()
    a, b = tm.start(), tm.start()
    assert (a, b) == (0, 1) and tm.age(a) == 2
    assert tm.end_frame() == []
    tm.begin_frame()
    assert tm.extend(a) == 3
    assert tm.end_frame() == []  # b missed once: still alive (lost)
    assert set(tm.lost()) == {b} and tm.get(b).missed == 1
    tm.begin_frame()
    tm.extend(a)
    assert tm.end_frame() == [b]  # missed twice > max_missed
    assert b not in tm and a in tm
    tm.begin_frame()
    c = tm.start()
    assert c == 2  # never reuses 1
    with pytest.raises(MatchingError, match='does not exist'):
        tm.extend(b)
    tm.extend(a)
    with pytest.raises(MatchingError, match='twice'):
        tm.extend(a)
    tm.end_frame()
    assert tm.age(a) == 5 and tm.get(a).last_frame == tm.frame == 3


def test_reacquired_track_keeps_id_and_counts_observations() -> None:
    tm = TrackManager(max_missed=2)
    tm.begin_frame()
    a = tm.start()
    tm.end_frame()
    for _ in range(2):
        tm.begin_frame()
        tm.end_frame()
    assert tm.get(a).missed == 2 and a in tm.lost()
    tm.begin_frame()
    assert tm.extend(a) == 3
    tm.end_frame()
    assert tm.get(a).missed == 0 and not tm.lost()


def test_reset_never_reuses_ids() -> None:
    tm = TrackManager(max_missed=0)
    tm.begin_frame()
    ids = [tm.start() for _ in range(5)]
    tm.end_frame()
    assert tm.reset() == ids and len(tm) == 0
    tm.begin_frame()
    assert tm.start() == 5
    tm.end_frame()


def test_max_missed_zero_ends_immediately_and_ages_saturate() -> None:
    tm = TrackManager(max_missed=0)
    tm.begin_frame()
    a = tm.start()
    tm.end_frame()
    tm.begin_frame()
    assert tm.end_frame() == [a]
    tm.begin_frame()
    b = tm.start()
    tm.get(b).age = MAX_AGE + 10
    assert tm.age(b) == MAX_AGE
    tm.end_frame()


def test_errors() -> None:
    with pytest.raises(MatchingConfigError, match='max_missed'):
        TrackManager(max_missed=-1)
    tm = TrackManager()
    with pytest.raises(MatchingError, match='begin_frame'):
        tm.start()
    tm.begin_frame()
    with pytest.raises(MatchingError, match='twice'):
        tm.begin_frame()
    full = TrackManager(first_id=MAX_TRACK_ID)
    full.begin_frame()
    assert full.start() == MAX_TRACK_ID
    with pytest.raises(TrackIdOverflowError, match='uint32'):
        full.start()
