"""FrameQueue, the image/input matching of blob_features and edge_features (a real rclpy node for its
log): free-running, the newest image once the loop has closed (``loop_wait_s``), with the input
nearest to it in time; lockstep, every image with its own input."""

from __future__ import annotations

import time

import numpy as np
import pytest

from artrack.messages import image_msg, rclpy_factory

MS = 1_000_000


@pytest.fixture
def node(probe):
    return probe[0]


class Clock:
    """The receive-time clock (ns), set by the test."""

    def __init__(self):
        self.now = 0

    def __call__(self) -> int:
        return self.now


def _queue(node, lockstep: bool, loop_wait_s: float = 0.0, clock=time.time_ns):
    from artrack_nodes.common import FrameQueue

    return FrameQueue(node, lockstep, 30.0, 10.0, "prior", loop_wait_s=loop_wait_s, clock_ns=clock)


def _add(queue, stamp_ns: int, received_ns: int = 0) -> None:
    msg = image_msg(rclpy_factory(), np.zeros((2, 3, 3), np.uint8), stamp_ns, "c")
    assert queue.add_image_msg(msg, "/c", received_ns)


def _take(queue, done: list) -> list:
    """Process what is ready: (image stamp, input stamp or None) each; ``done`` counts the frames."""
    out = []
    for stamp, _, found in queue.ready(lambda: not done):
        out.append((stamp, found[0] if found is not None else None))
        done.append(stamp)
    return out


def test_free_running_waits_for_the_loop_then_takes_the_newest_image(node):
    q, done = _queue(node, lockstep=False, loop_wait_s=30.0), []
    _add(q, 100 * MS)
    assert _take(q, done) == [(100 * MS, None)]  # the first frame has no prior
    _add(q, 133 * MS)
    _add(q, 167 * MS)
    q.add_input(100 * MS, "old")  # not after the last frame: the loop has not closed
    assert _take(q, done) == []
    q.add_input(133 * MS, "new")  # the prediction from frame 100 ms
    assert _take(q, done) == [(167 * MS, 133 * MS)] and q.skipped == 1
    _add(q, 200 * MS)
    assert _take(q, done) == []  # nothing newer than 167 ms yet
    q.add_input(240 * MS, "future")
    assert _take(q, done) == [(200 * MS, 240 * MS)]  # the nearest in time, if after the image


def test_free_running_goes_on_without_the_loop_after_loop_wait_s(node):
    q, done = _queue(node, lockstep=False, loop_wait_s=0.05), []
    _add(q, 100 * MS)
    _take(q, done)
    _add(q, 133 * MS)
    assert _take(q, done) == []
    time.sleep(0.06)  # the skeleton never answered (dead, or slower than loop_wait_s)
    assert _take(q, done) == [(133 * MS, None)]


def test_free_running_without_loop_wait_takes_every_newest_image_at_once(node):
    q, done = _queue(node, lockstep=False, loop_wait_s=0.0), []
    for k in (100, 133, 167):
        _add(q, k * MS)
    assert _take(q, done) == [(167 * MS, None)] and q.skipped == 2
    _add(q, 200 * MS)
    q.add_input(100 * MS, "a")
    q.add_input(300 * MS, "b")
    assert _take(q, done) == [(200 * MS, 100 * MS)]  # nearer than 300 ms


def test_lockstep_takes_every_image_with_its_own_input(node):
    q, done = _queue(node, lockstep=True, loop_wait_s=30.0), []
    for k in (100, 133, 167):
        _add(q, k * MS)
    assert _take(q, done) == [(100 * MS, None)]  # the first frame goes without
    q.add_input(167 * MS, "c")
    assert _take(q, done) == []  # 133 ms waits for its own
    q.add_input(133 * MS, "b")
    assert _take(q, done) == [(133 * MS, 133 * MS), (167 * MS, 167 * MS)] and q.skipped == 0


def test_the_image_taken_is_the_newest_received_before_the_input_that_closed_the_loop(node):
    """The same frame in every camera's node, however late each gets the CPU: images received after
    the closing prior are left for the next loop, and only a prior received after the last frame was
    taken closes the loop (not a late one from an older frame, stamped ahead)."""
    clock = Clock()
    q, done = _queue(node, lockstep=False, loop_wait_s=30.0, clock=clock), []
    _add(q, 100 * MS, received_ns=1000)
    clock.now = 1001
    _take(q, done)
    _add(q, 117 * MS, received_ns=1017)
    _add(q, 133 * MS, received_ns=1033)
    q.add_input(117 * MS, "prediction", received_ns=1040)  # the loop closes here ...
    _add(q, 150 * MS, received_ns=1050)  # ... and this node only gets the CPU after a further image
    clock.now = 1055
    assert _take(q, done) == [(133 * MS, 117 * MS)] and q.skipped == 1
    assert [im[0] for im in q.images] == [150 * MS]  # kept: it came after the loop closed
    q.add_input(150 * MS, "next", received_ns=1070)
    clock.now = 1075
    assert _take(q, done) == [(150 * MS, 150 * MS)]
    q.add_input(183 * MS, "fast loop", received_ns=1080)  # closed before any newer image came
    _add(q, 167 * MS, received_ns=1085)
    _add(q, 183 * MS, received_ns=1101)
    clock.now = 1105
    assert _take(q, done) == [(167 * MS, 183 * MS)]  # the first image after it ...
    assert _take(q, done) == [] and [im[0] for im in q.images] == [183 * MS]  # ... and no more
    q.add_input(175 * MS, "late, from an older frame", received_ns=1090)  # received before the pick
    assert _take(q, done) == []
    q.add_input(200 * MS, "from 167 ms", received_ns=1110)
    assert _take(q, done) == [(183 * MS, 183 * MS)]
