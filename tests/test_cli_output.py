"""What the entry points say and where they listen: help generated from the config's
docstrings, one log format, a progress bar only on a terminal, the named port, a busy port in
one line, and ``fedhpg-run resume=DIR`` continuing a run from its own config.json."""

from __future__ import annotations

import io
import json
import logging
import os
import re
import select
import socket
import subprocess
from pathlib import Path

import pytest

from fedhpg.common.records.types import EvaluationStats
from fedhpg.common.runtime.progress import Progress
from fedhpg.server.report import evaluation_table
from tests.procs import BIN, free_port

LOG_LINE = re.compile(r"^\d\d:\d\d:\d\d (DEBUG|INFO|WARNING|ERROR|CRITICAL) [\w.]+: ")
SMALL = [
    "seed=5", "agents.num_agents=2", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
    "eval.every=2", "eval.episodes=2",
]  # fmt: skip


def _run(args: list[str], cwd: Path, level: str = "INFO") -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(BIN / "fedhpg-run"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "FEDHPG_LOG_LEVEL": level},
    )


def _listening_port(stderr: str) -> int:
    found = re.search(r"server listening on tcp://\S+:(\d+)", stderr)
    assert found, stderr[-2000:]
    return int(found.group(1))


def test_help_comes_from_the_config_docstrings_and_starts_nothing(tmp_path: Path) -> None:
    scripts = ("fedhpg-run", "fedhpg-server", "fedhpg-agent")
    started = [
        subprocess.Popen(
            [str(BIN / script), "--help"], cwd=tmp_path, stdout=subprocess.PIPE, text=True
        )
        for script in scripts
    ]
    outputs = [process.communicate(timeout=60)[0] for process in started]
    for script, process, text in zip(scripts, started, outputs, strict=True):
        assert process.returncode == 0, script
        assert text.startswith(f"usage: {script}")
        assert "T, the number of communication rounds" in text  # RunConfig.rounds' docstring
        assert "server.port=5555" in text and "rounds=60" in text  # conf/config.yaml defaults
        assert re.search(r"algo=\s+fedhpg \(default\), fedhpgvr", text)
        assert "More: docs/configuration.md" in text
    assert list(tmp_path.iterdir()) == [], "help writes nothing"


@pytest.mark.parametrize("columns", [60, 80, 132])
def test_help_wraps_at_words_within_the_terminal(columns: int, tmp_path: Path) -> None:
    from fedhpg.common.runtime.help import _key_docs, help_text

    text = help_text("fedhpg-run", width=min(columns, 120))
    lines = text.splitlines()
    assert not [line for line in lines if line.endswith("…")], "nothing cut"
    too_long = [
        line for line in lines if len(line) > min(columns, 120) and not re.match(r"  \S+=\S", line)
    ]
    assert not too_long, too_long  # only a key=default wider than the screen may run past
    words = " ".join(" ".join(lines).split())
    for key, doc in _key_docs().items():
        if key.startswith("cluster."):
            continue
        assert " ".join(doc.split()) in words, key
    for referred in re.findall(r"docs/[\w.-]+\.md", text):
        assert (Path(__file__).parents[1] / referred).is_file(), referred


def test_progress_is_plain_log_lines_off_a_terminal(caplog: pytest.LogCaptureFixture) -> None:
    stream = io.StringIO()
    with caplog.at_level(logging.INFO, logger="fedhpg.common.runtime.progress"):
        progress = Progress(3, "rounds", stream=stream, log_every_s=0.0)
        for _ in range(3):
            progress.update(1, "round 0.10s")
        progress.close()
    assert stream.getvalue() == "", "nothing drawn on a non-terminal"
    lines = [r.getMessage() for r in caplog.records]
    assert [line.split(" [")[0] for line in lines] == [
        "progress 1/3 rounds",
        "progress 2/3 rounds",
        "progress 3/3 rounds",
    ]


def test_progress_is_a_bar_on_a_terminal() -> None:
    leader, follower = os.openpty()
    with open(follower, "w") as terminal:
        progress = Progress(4, "rounds", stream=terminal, done=1)  # a resumed run: 1 done
        for _ in range(3):
            progress.update(1, "round 0.10s")
        progress.close()
    chunks = []
    while select.select([leader], [], [], 0.2)[0]:
        try:
            chunks.append(os.read(leader, 65536))
        except OSError:  # EIO: the terminal's other end is closed and everything was read
            break
    os.close(leader)
    drawn = b"".join(chunks).decode(errors="replace")
    assert "4/4" in drawn and "━" in drawn, drawn  # rich's bar, redrawn in place


def test_the_evaluation_table_shows_success_only_with_a_goal() -> None:
    stats = {
        "agent-0": EvaluationStats(
            return_mean=200.0,
            return_std=0.0,
            discounted_return_mean=80.0,
            success_rate=0.0,
            length_mean=200.0,
            episodes=5,
        )
    }
    without = evaluation_table(stats, {}, has_goal=False).splitlines()[2]
    with_goal = evaluation_table(stats, {}, has_goal=True).splitlines()[2]
    assert without.split()[:3] == ["agent-0", "—", "200.000"]
    assert with_goal.split()[:3] == ["agent-0", "0.00", "200.000"]


def test_named_port_one_log_format_and_resume_from_the_run_directory(tmp_path: Path) -> None:
    port = free_port()
    first = _run([*SMALL, "rounds=2", f"server.port={port}", "server.out_dir=run",
                  f"hydra.run.dir={tmp_path / 'hydra'}"], tmp_path)  # fmt: skip
    assert first.returncode == 0, first.stderr[-2000:]
    assert _listening_port(first.stderr) == port, "fedhpg-run listens on the port it is given"
    for line in first.stderr.splitlines():  # the launcher, the server and agent children
        assert LOG_LINE.match(line), line
    assert not (tmp_path / "outputs").exists()

    resumed = _run(["resume=run", "rounds=4"], tmp_path)  # no other override: config.json
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "resuming run after round 2" in resumed.stderr
    assert _listening_port(resumed.stderr) != port, "unnamed: a free port"
    metrics = (tmp_path / "run/metrics.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in metrics]
    assert [r["round"] for r in records] == [1, 2, 3, 4]
    assert [a["id"] for a in records[-1]["agents"]] == ["agent-0", "agent-1"], "its num_agents"
    config = json.loads((tmp_path / "run/config.json").read_text())
    assert (config["seed"], config["rounds"], config["agents"]["num_agents"]) == (5, 4, 2)
    assert not (tmp_path / "outputs").exists(), "a resume leaves no Hydra directory"

    refused = _run(["resume=run", "rounds=6", "agents.budget.batch_size=[8]"], tmp_path)
    assert refused.returncode == 2
    assert refused.stderr.splitlines() == [
        "error: agents.budget.batch_size: the run has [4], this invocation [8]; a resume keeps "
        "agents as it was (resuming run)"
    ]


def test_a_busy_port_is_one_line_and_exit_1(tmp_path: Path) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        busy = holder.getsockname()[1]
        result = _run([*SMALL, f"server.port={busy}"], tmp_path, level="WARNING")
    assert result.returncode == 1
    assert result.stderr.splitlines() == [
        f"error: server.port: cannot listen on 127.0.0.1:{busy}: Address already in use "
        "(choose another port, or leave server.port unset for a free one)"
    ]
    assert list(tmp_path.iterdir()) == []


def test_a_busy_port_leaves_no_run_directory_behind(tmp_path: Path) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        busy = holder.getsockname()[1]
        result = subprocess.run(
            [str(BIN / "fedhpg-server"), *SMALL, f"server.port={busy}"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "FEDHPG_LOG_LEVEL": "WARNING"},
        )
    assert result.returncode == 1
    assert list(tmp_path.iterdir()) == [], "no runs/<time>/ left"
    assert result.stderr.splitlines() == [
        f"error: server.port: cannot listen on 127.0.0.1:{busy}: Address already in use "
        "(choose another port; server.port=0 takes a free one)"
    ]


def test_resuming_a_complete_run_says_so_and_starts_nothing(tmp_path: Path) -> None:
    from fedhpg.server.commands import api

    api.run(overrides=[*SMALL, "rounds=2"], out_dir=tmp_path / "done")
    before = (tmp_path / "done/metrics.jsonl").read_text()
    for script in ("fedhpg-run", "fedhpg-server"):
        args = ["resume=done"] if script == "fedhpg-run" else ["resume=true", "server.out_dir=done"]
        result = subprocess.run(
            [str(BIN / script), *args],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "FEDHPG_LOG_LEVEL": "INFO"},
        )
        assert result.returncode == 0, result.stderr[-2000:]
        assert result.stdout == (
            "done is complete: round 2 of rounds=2, nothing to run (resume with rounds=N "
            "above 2 to continue it)\n"
        ), script
        assert "listening" not in result.stderr and "registered" not in result.stderr
    assert (tmp_path / "done/metrics.jsonl").read_text() == before


def test_hydras_info_prints_each_line_once(tmp_path: Path) -> None:
    result = subprocess.run(
        [str(BIN / "fedhpg-run"), "--info"], cwd=tmp_path, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    both = (result.stdout + result.stderr).splitlines()
    assert sum("Installed Hydra Plugins" in line for line in both) == 1, both[:6]


def test_a_search_path_adds_config_groups(tmp_path: Path) -> None:
    (tmp_path / "mine/env").mkdir(parents=True)
    (tmp_path / "mine/env/short_cartpole.yaml").write_text(
        "# @package _global_\nenv:\n  family: cartpole\n  level: 0.2\n  horizon: 20\n"
    )
    result = _run(
        [*SMALL, "rounds=1", f"hydra.searchpath=[file://{tmp_path / 'mine'}]",
         "env=short_cartpole", "server.out_dir=run"],
        tmp_path,
        level="WARNING",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    config = json.loads((tmp_path / "run/config.json").read_text())
    assert (config["env"]["family"], config["env"]["horizon"]) == ("cartpole", 20)


def test_a_slow_wait_is_announced_and_a_quick_one_is_not(caplog: pytest.LogCaptureFixture) -> None:
    import time

    from fedhpg.common.runtime.progress import announced_if_slow

    with caplog.at_level(logging.INFO, logger="fedhpg.common.runtime.progress"):
        with announced_if_slow("quick", after_s=0.5):
            pass
        with announced_if_slow("compiling …", after_s=0.05):
            time.sleep(0.3)
        time.sleep(0.6)  # the quick one's timer would have fired by now
    assert [r.getMessage() for r in caplog.records] == ["compiling …"]


@pytest.mark.slow
def test_the_first_cartpole_run_says_it_compiles_before_the_server_waits(tmp_path: Path) -> None:
    """An empty numba cache, as right after an install: the ~20 s are announced, and spent
    before the server listens, so a register timeout far below them does not end the run."""
    result = subprocess.run(
        [str(BIN / "fedhpg-run"), "env=cartpole", "rounds=1", "eval.episodes=1",
         "agents.budget.batch_size=[2]", "server.register_timeout_s=2", "server.out_dir=run"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600,
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    lines = result.stderr.splitlines()
    (compiling,) = [i for i, line in enumerate(lines) if "compiling the compiled engine's" in line]
    (listening,) = [i for i, line in enumerate(lines) if "server listening on" in line]
    assert compiling < listening, lines


def test_the_demo_says_it_sleeps_and_a_preset_says_what_it_changed(tmp_path: Path) -> None:
    demo = _run(["rounds=1", "eval.episodes=1", "server.out_dir=demo"], tmp_path)
    assert demo.returncode == 0, demo.stderr[-2000:]
    said = [line for line in demo.stderr.splitlines() if "sleep" in line]
    assert len(said) == 1 and "agents.virtual_clock=true" in said[0], said
    preset = _run(
        ["env=cartpole", "rounds=1", "eval.episodes=1", "agents.budget.batch_size=[2]",
         "server.out_dir=cartpole"],
        tmp_path,
    )  # fmt: skip
    assert preset.returncode == 0, preset.stderr[-2000:]
    assert not [line for line in preset.stderr.splitlines() if "sleep" in line]
    (changes,) = [line for line in preset.stderr.splitlines() if "env=cartpole also sets" in line]
    parts = ["strategy=fedadam (was mean)", "algo.step_size=1.0 (was 0.5)",
             "agents.virtual_clock=true (was false)", "agents.budget.local_iters=[1]"]  # fmt: skip
    for part in parts:
        assert part in changes, changes
    assert "batch_size" not in changes, "what the command line set is its own"


def test_fedpgbr_brings_its_strategy_unless_one_is_named() -> None:
    from fedhpg.common.configuration.config_error import ConfigError
    from fedhpg.common.runtime.cli import compose

    assert compose(["algo=fedpgbr"]).strategy.name == "fedpgbr"
    assert compose(["env=cartpole", "algo=fedpgbr"]).strategy.name == "fedpgbr"
    assert compose(["-m", "env=cartpole", "algo=fedpgbr"][1:]).strategy.params["step_size"] == 0.01
    with pytest.raises(ConfigError, match="algo=fedpgbr sends what only strategy=fedpgbr"):
        compose(["env=cartpole", "algo=fedpgbr", "strategy=median"])


def test_a_server_of_very_many_agents_says_what_it_computes_before_listening(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The agents' digests are O(K) before the server listens (half an hour at K = 10⁷): from
    DIGESTS_SHOWN_FROM agents on, a line says so and a progress line follows, the digests
    unchanged."""
    from fedhpg.common.runtime.cli import compose
    from fedhpg.server import serving

    run = compose(["agents=population", "agents.num_agents=50"])
    quiet = serving.run_digests(run)
    monkeypatch.setattr(serving, "DIGESTS_SHOWN_FROM", 50)
    monkeypatch.setattr(serving, "DIGESTS_PER_UPDATE", 20)
    with caplog.at_level(logging.INFO):
        assert serving.run_digests(run) == quiet
    said = [r.getMessage() for r in caplog.records]
    assert said[0].startswith("computing the environment digests of 50 agents"), said
    assert said[-1].startswith("progress 50/50 agents' digests"), said
