"""The queue's doorbell: a ring wakes one idle listener; ringing never blocks nor raises."""

from __future__ import annotations

import os
import stat

from app.jobs.doorbell import Doorbell, doorbell_path, ring


def test_ringing_without_a_listener_is_a_quiet_no(tmp_path):
    path = doorbell_path(tmp_path)
    assert not ring(path)  # no pipe yet
    path.parent.mkdir(parents=True)
    os.mkfifo(path)
    assert not ring(path)  # a pipe nobody has open
    regular = tmp_path / "not-a-pipe"
    regular.write_bytes(b"")
    assert not ring(regular)
    assert regular.read_bytes() == b""


def test_a_ring_wakes_one_listener_and_is_taken_once(tmp_path):
    path = doorbell_path(tmp_path)
    first, second = Doorbell(path), Doorbell(path)
    try:
        assert first.open() and second.open()
        assert stat.S_ISFIFO(path.stat().st_mode)
        assert not first.wait(0.0)  # nothing rang
        assert ring(path)
        assert first.wait(5.0)
        assert not second.wait(0.0)  # the ring was taken
        assert ring(path, times=3)
        assert second.drain() == 3
        assert not first.wait(0.0)
    finally:
        first.close()
        second.close()


def test_a_listener_that_cannot_open_the_pipe_sleeps_the_delay(tmp_path):
    blocked = tmp_path / "run" / "queue-doorbell"
    blocked.mkdir(parents=True)  # a directory where the pipe should be
    doorbell = Doorbell(blocked)
    assert not doorbell.open()
    assert not doorbell.wait(0.01)
    assert doorbell.drain() == 0
