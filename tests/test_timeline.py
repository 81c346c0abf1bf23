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
