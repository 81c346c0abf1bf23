"""The round timeline's marks (``FEDHPG_TIMELINE``, read by ``benchmarks.timeline``)."""

from __future__ import annotations

import logging

import pytest

from fedhpg.common.runtime import timeline


@pytest.fixture(autouse=True)
def _restore_levels():
    level, root = timeline.logger.level, logging.getLogger().level
    yield
    timeline.logger.setLevel(level)
    logging.getLogger().setLevel(root)


def test_marks_are_off_unless_asked_for(monkeypatch, caplog) -> None:
    monkeypatch.delenv(timeline.ENV, raising=False)
    timeline.logger.setLevel(logging.NOTSET)
    timeline.configure()
    with caplog.at_level(logging.INFO):
        timeline.mark("server", "round-start", 3)
    assert not [r for r in caplog.records if r.name == timeline.logger.name]


def test_a_mark_is_one_line_of_stamp_who_event_round(monkeypatch, caplog) -> None:
    monkeypatch.setenv(timeline.ENV, "1")
    timeline.configure()
    logging.getLogger().setLevel(logging.INFO)  # the run's level: the marks need no DEBUG root
    timeline.mark("host-0-499", "trained", 7)
    (record,) = [r for r in caplog.records if r.name == timeline.logger.name]
    stamp, who, event, round_index = record.getMessage().split()
    assert float(stamp) > 0 and (who, event, round_index) == ("host-0-499", "trained", "7")


def test_the_round_befores_record_is_read_against_the_round_it_ran_in() -> None:
    """The server writes round t's record while round t + 1 trains: ``benchmarks.timeline``
    places its start and end on round t + 1's axis, and the next round's start on round t's."""
    from benchmarks.timeline import parse

    def line(stamp: float, who: str, event: str, round_index: int) -> str:
        return f"12:00:00 DEBUG fedhpg.timeline: {stamp:.6f} {who} {event} {round_index}"

    marks = [(100.0, 1), (100.2, 2)]  # each round's start
    lines = []
    for start, number in marks:
        lines += [
            line(start, "server", "round-start", number),
            line(start + 0.001, "server", "train-sent", number),
            line(start + 0.050, "host-0-499", "trained", number),
            line(start + 0.060, "host-500-999", "trained", number),
            line(start + 0.070, "server", "train-collected", number),
            line(start + 0.075, "server", "answers-in", number),
            line(start + 0.080, "server", "aggregated", number),
        ]
    lines += [line(100.205, "server", "recording", 1), line(100.215, "server", "recorded", 1)]
    rounds = parse("\n".join(["unrelated line", *lines]))
    assert rounds[2]["recording"] == pytest.approx(0.005)
    assert rounds[2]["recorded"] == pytest.approx(0.015)
    assert "recording" not in rounds[1] and rounds[1]["next-start"] == pytest.approx(0.2)
    assert rounds[2]["first-trained"] == pytest.approx(0.05)
    assert rounds[2]["last-trained"] == pytest.approx(0.06)


def test_cpu_share_reads_a_process_cpu_time_from_proc() -> None:
    """``benchmarks.cpu_share`` reads user + system CPU time from ``/proc/<pid>/stat``: it
    follows this process's own CPU clock across a busy spell (to the kernel's 10 ms ticks)."""
    import os
    import time

    from benchmarks.cpu_share import _cpu_s

    before, clock = _cpu_s(os.getpid()), time.process_time()
    while time.process_time() - clock < 0.5:
        sum(range(10_000))
    used = _cpu_s(os.getpid()) - before
    assert abs(used - (time.process_time() - clock)) < 0.05
