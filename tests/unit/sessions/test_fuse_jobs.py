"""The mapping thread's job queue (server/sessions/runtime/fusion.py ``FuseJobs``): a keyframe
never waits behind plain frames for a mapper that is behind, it takes the oldest plain frame's
place; it waits only when every waiting job is a keyframe; the end comes after the jobs."""

from __future__ import annotations

import queue
import threading
import time

import numpy as np
import pytest

from server.sessions.runtime.fusion import FuseJob, FuseJobs


def job(seq: int, keyframe: bool = False) -> FuseJob:
    return FuseJob(
        seq, np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.float32), np.eye(4), keyframe
    )


def drain(jobs: FuseJobs) -> list[int]:
    seqs = []
    while True:
        try:
            j = jobs.get(0.0)
        except queue.Empty:
            return seqs
        seqs.append(-1 if j is None else j.seq)


def test_a_keyframe_takes_the_place_of_the_oldest_plain_frame():
    jobs = FuseJobs(3)
    for seq, key in ((1, False), (2, True), (3, False)):
        assert jobs.put(job(seq, key), 0.0) == (True, None)
    # Full: a plain frame is refused (SessionFusion.queue gives it no wait).
    assert jobs.put(job(4), 0.0) == (False, None)
    # A keyframe goes in at once, though it may wait; frame 1, the oldest plain one, gives way.
    t0 = time.monotonic()
    queued, evicted = jobs.put(job(5, True), 1.0)
    assert queued and evicted is not None and evicted.seq == 1
    assert time.monotonic() - t0 < 0.5
    assert drain(jobs) == [2, 3, 5]


def test_a_keyframe_waits_only_behind_keyframes():
    jobs = FuseJobs(2)
    jobs.put(job(1, True), 0.0)
    jobs.put(job(2, True), 0.0)
    t0 = time.monotonic()
    assert jobs.put(job(3, True), 0.3) == (False, None)  # no room within its wait
    assert time.monotonic() - t0 >= 0.25

    # Room made while it waits (the mapping thread takes one): in it goes.
    def take() -> None:
        time.sleep(0.2)
        jobs.get(1.0)

    threading.Thread(target=take).start()
    assert jobs.put(job(4, True), 5.0) == (True, None)
    assert drain(jobs) == [2, 4]


def test_the_end_comes_after_the_jobs_even_when_full():
    jobs = FuseJobs(1)
    jobs.put(job(1), 0.0)
    jobs.close()
    assert drain(jobs) == [1, -1]
    with pytest.raises(queue.Empty):
        jobs.get(0.05)
