"""AoI tracking at the edge: newest delivered generation time per camera."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from aoi3d.aoi import AoITracker
from aoi3d.channel import simulate


def test_aoi_is_unknown_until_the_first_delivery() -> None:
    tracker = AoITracker([1, 2, 3])
    assert np.all(np.isnan(tracker.aoi_ms(1_000.0)))
    assert np.all(np.isnan(tracker.newest_ms))
    tracker.deliver(2, 100.0)
    aoi = tracker.aoi_ms(160.0)
    assert math.isnan(aoi[0]) and aoi[1] == 60.0 and math.isnan(aoi[2])
    assert aoi.dtype == np.float64


def test_vector_follows_camera_ids_order() -> None:
    tracker = AoITracker([7, 3, 5])
    tracker.deliver(5, 10.0)
    tracker.deliver(7, 20.0)
    np.testing.assert_array_equal(tracker.newest_ms, [20.0, np.nan, 10.0])
    np.testing.assert_array_equal(tracker.aoi_ms(30.0), [10.0, np.nan, 20.0])
    assert tracker.camera_ids == (7, 3, 5)
    assert tracker.index(3) == 1 and len(tracker) == 3


def test_keeps_the_newest_frame() -> None:
    tracker = AoITracker([1])
    assert tracker.deliver(1, 90.0) is True
    assert tracker.deliver(1, 60.0) is False  # an older frame arriving late changes nothing
    assert tracker.deliver(1, 90.0) is False
    assert tracker.newest_ms[0] == 90.0
    assert tracker.deliver(1, 120.0) is True
    assert tracker.aoi_ms(150.0)[0] == 30.0
    assert tracker.deliveries[0] == 4


def test_newest_ms_is_a_copy() -> None:
    tracker = AoITracker([1])
    tracker.deliver(1, 5.0)
    tracker.newest_ms[0] = 999.0
    assert tracker.newest_ms[0] == 5.0


def test_reset_forgets_everything() -> None:
    tracker = AoITracker([1, 2])
    tracker.deliver(1, 5.0)
    tracker.reset()
    assert np.all(np.isnan(tracker.aoi_ms(10.0)))
    assert tracker.deliveries.sum() == 0


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="unique"):
        AoITracker([1, 1])
    with pytest.raises(TypeError):
        AoITracker(["a"])  # type: ignore[list-item]
    tracker = AoITracker([1, 2])
    with pytest.raises(KeyError, match="unknown camera id 9"):
        tracker.deliver(9, 0.0)
    with pytest.raises(ValueError):
        tracker.deliver(1, math.nan)
    with pytest.raises(ValueError):
        tracker.aoi_ms(math.inf)
    assert AoITracker([]).aoi_ms(5.0).shape == (0,)


def test_agrees_with_the_batch_channel_simulation() -> None:
    """Delivering a run's frames at their delivery slots reproduces the run's AoI vector."""
    run = simulate("exp:60", 30, 4, 3_000, seed=9, phase_ms=[0, 4, 12, 25])
    tracker = AoITracker(range(1, 5))  # link i serves camera i + 1
    events = sorted(
        (int(d), i + 1, int(g))
        for i in range(run.n_cameras)
        for g, d in zip(run.gen_ms[i], run.delivery_ms[i], strict=True)
    )
    trace = run.aoi_trace()
    k = 0
    for t in range(run.duration_ms):
        while k < len(events) and events[k][0] <= t:
            tracker.deliver(events[k][1], events[k][2])
            k += 1
        np.testing.assert_array_equal(tracker.aoi_ms(t), trace[:, t])


def test_concurrent_deliveries_keep_the_maximum() -> None:
    tracker = AoITracker([1])

    def worker(offset: int) -> None:
        for g in range(offset, 20_000, 4):
            tracker.deliver(1, float(g))

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert tracker.newest_ms[0] == 19_999.0
    assert tracker.deliveries[0] == 20_000
