"""bench.perf1m_parallelism's quiet-machine model: its arithmetic and its /proc reading."""

from __future__ import annotations

import os

import pytest

from bench.perf1m_parallelism import _thread_states, quiet_estimate, slot_order


def test_two_runnable_threads_on_two_cores_take_half_their_cpu() -> None:
    samples = [(0.0, 2), (5.0, 2), (10.0, 0)]
    estimate = quiet_estimate(samples, cpu_seconds=2.0, window=None)
    assert estimate["quiet_seconds"] == pytest.approx(1.0)
    assert estimate["serial_cpu_share"] == 0.0


def test_a_serial_stretch_takes_its_cpu_and_more_threads_than_cores_share_them() -> None:
    # 1 s with one runnable thread, 1 s with three: 4 thread-seconds for 4 CPU seconds
    samples = [(0.0, 1), (1.0, 3), (2.0, 0)]
    estimate = quiet_estimate(samples, cpu_seconds=4.0, window=None)
    assert estimate["quiet_seconds"] == pytest.approx(1.0 + 3.0 / 2.0)
    assert estimate["serial_cpu_share"] == pytest.approx(0.25)
    # only the second half: 3 thread-seconds of 3 CPU seconds on two cores
    late = quiet_estimate(samples, cpu_seconds=3.0, window=(1.0, 2.0))
    assert late["quiet_seconds"] == pytest.approx(1.5)


def test_stretches_without_a_runnable_thread_count_as_waiting_not_work() -> None:
    samples = [(0.0, 0), (1.0, 1), (2.0, 0)]
    estimate = quiet_estimate(samples, cpu_seconds=1.0, window=None)
    assert estimate["quiet_seconds"] == pytest.approx(1.0)
    assert estimate["no_runnable_share"] == pytest.approx(0.5)


def test_the_calling_thread_is_seen_running() -> None:
    runnable, ticks = _thread_states(os.getpid())
    assert runnable >= 1 and ticks >= 0
    assert _thread_states(2**22 + 12345) is None  # no such process


def test_the_command_and_the_baseline_swap_slots_every_round() -> None:
    orders = [slot_order(["compare", "baseline"], round_index) for round_index in range(4)]
    assert orders == [["compare", "baseline"], ["baseline", "compare"]] * 2
    # each run in each slot equally often over an even number of rounds
    for run in ("compare", "baseline"):
        assert sorted(order.index(run) for order in orders) == [0, 0, 1, 1]
    assert slot_order(["compare"], 1) == ["compare"]
