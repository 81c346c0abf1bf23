"""Checkpoints on real files: round trips, torn and corrupt files detected and skipped with a
warning, nothing but plain numbers ever loaded (no pickle), and resume refusing a changed run."""

from __future__ import annotations

import hashlib
import json
import logging
import pickle
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch

from fedhpg.common.configuration.config import to_dict
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.records.types import SavedState
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import resume_point
from fedhpg.server.checkpoint import (
    Checkpoint,
    CheckpointError,
    checkpoint_path,
    completed_round,
    interrupted_message,
    latest_valid_checkpoint,
    load_checkpoint,
    save_checkpoint,
    write_atomic,
)
from fedhpg.server.run_dir import RunDirectory
from fedhpg.server.strategies import make_strategy


def _checkpoint(round_number: int) -> Checkpoint:
    return Checkpoint(
        round=round_number,
        theta=torch.arange(6, dtype=torch.float32) * round_number,
        config={"seed": 1},
        metrics_lines=round_number,
        state={"trajectories_per_agent": 12.0 * round_number},
        strategy=SavedState(
            scalars={"steps": 3, "inner": {}},
            arrays={"first": np.full(6, 0.5, dtype=np.float32)},
        ),
    )


def test_round_trip_keeps_every_field(tmp_path: Path) -> None:
    saved = _checkpoint(3)
    loaded = load_checkpoint(save_checkpoint(tmp_path, saved))
    assert loaded.round == 3 and loaded.metrics_lines == 3 and loaded.config == {"seed": 1}
    assert torch.equal(loaded.theta, saved.theta)
    assert loaded.state == saved.state
    assert loaded.strategy.scalars == saved.strategy.scalars
    assert np.array_equal(loaded.strategy.arrays["first"], np.full(6, 0.5))


def test_only_the_newest_checkpoints_are_kept(tmp_path: Path) -> None:
    for round_number in range(1, 6):
        save_checkpoint(tmp_path, _checkpoint(round_number))
    assert sorted(p.name for p in tmp_path.glob("round-*")) == [
        "round-000004.safetensors",
        "round-000005.safetensors",
    ]


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(lambda raw: raw[: len(raw) // 2], id="torn"),
        pytest.param(lambda raw: raw[:40] + bytes([raw[40] ^ 0xFF]) + raw[41:], id="bit-flip"),
        pytest.param(lambda raw: b"", id="empty"),
    ],
)
def test_a_damaged_newest_checkpoint_falls_back_to_the_previous(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, damage
) -> None:
    save_checkpoint(tmp_path, _checkpoint(1))
    newest = save_checkpoint(tmp_path, _checkpoint(2))
    newest.write_bytes(damage(newest.read_bytes()))
    with caplog.at_level(logging.WARNING):
        loaded = latest_valid_checkpoint(tmp_path)
    assert loaded is not None and loaded.round == 1
    assert f"skipping checkpoint: {newest}" in caplog.text
    assert "torn or corrupt file" in caplog.text


def test_a_damaged_checkpoint_is_reported_once_per_resume(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A resume reads the checkpoints more than once (is the run complete? then its resume
    point; on an interrupt, where to continue): each damaged file is one warning."""
    directory = tmp_path / "checkpoints"
    save_checkpoint(directory, _checkpoint(1))
    newest = save_checkpoint(directory, _checkpoint(2))
    newest.write_bytes(newest.read_bytes()[:-7])
    with caplog.at_level(logging.WARNING):
        assert completed_round(directory, 5) is None  # the entry point, before serving
        loaded = latest_valid_checkpoint(directory)  # the server's resume point
        interrupted_message(tmp_path, "fedhpg-run resume=...")
    assert loaded is not None and loaded.round == 1
    assert caplog.text.count("skipping checkpoint") == 1, caplog.text
    caplog.clear()
    newest.write_bytes(newest.read_bytes()[:-7])  # damaged again, differently
    with caplog.at_level(logging.WARNING):
        latest_valid_checkpoint(directory)
    assert caplog.text.count("skipping checkpoint") == 1, "a new damage is a new warning"


def _sealed(path: Path, body: bytes) -> Path:
    """A file of the msgpack format (``.ckpt``) with a correct checksum around any body: only
    the format check can refuse it."""
    path = path.with_suffix(".ckpt")
    write_atomic(path, hashlib.sha256(body).digest() + body)
    return path


class Trap:
    def __reduce__(self):  # unpickling this would run code
        return (print, ("unpickled!",))


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (pickle.dumps(Trap()), "malformed checkpoint"),
        (msgpack.packb({"format": "something-else", "version": 2}), "not a fedhpg-checkpoint"),
        (
            msgpack.packb(
                {
                    "format": "fedhpg-checkpoint",
                    "version": 2,
                    "round": 1,
                    "theta": {"dtype": "|O", "shape": [1], "data": pickle.dumps([1])},
                    "config": {},
                    "metrics_lines": 1,
                }
            ),
            "dtype object is not allowed",
        ),
    ],
    ids=["pickle", "other-format", "object-dtype"],
)
def test_only_plain_numbers_are_ever_loaded(
    tmp_path: Path, capsys: pytest.CaptureFixture, body: bytes, message: str
) -> None:
    path = _sealed(checkpoint_path(tmp_path, 1), body)
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)
    assert "unpickled!" not in capsys.readouterr().out


def test_resume_refuses_a_changed_run_and_a_missing_checkpoint(tmp_path: Path) -> None:
    run = compose(["rounds=5", "seed=3"])
    strategy = make_strategy(run.strategy)
    run_dir = RunDirectory(tmp_path)
    (tmp_path / "metrics.jsonl").write_text(
        "".join(json.dumps({"round": r}) + "\n" for r in (1, 2, 3))  # round 3: after the kill
    )
    with pytest.raises(ConfigError, match=r"no valid checkpoint .* but the run has recorded"):
        resume_point(run, run_dir, strategy)
    checkpoint = _checkpoint(2)
    save_checkpoint(
        tmp_path / "checkpoints",
        Checkpoint(
            round=2,
            theta=checkpoint.theta,
            config=to_dict(run),
            metrics_lines=2,
            state={"trajectories_per_agent": 24.0, "elapsed_s": 1.5},
        ),
    )
    # rounds above the checkpoint but below the run's own: "kept or raised", never lowered
    with pytest.raises(ConfigError, match=r"has rounds=5 \(checkpointed at round 2\)") as error:
        resume_point(compose(["rounds=4", "seed=3"]), run_dir, strategy)
    assert error.value.key == "rounds"
    theta, progress, _ = resume_point(run, run_dir, strategy)
    assert torch.equal(theta, checkpoint.theta)
    assert (tmp_path / "metrics.jsonl").read_text().count("\n") == 2, "cut back to round 2"
    assert (progress.next_round, progress.trajectories_per_agent) == (3, 24.0)
    assert progress.elapsed_s == 1.5
    with pytest.raises(ConfigError, match="the run has 3, this invocation 4") as error:
        resume_point(compose(["rounds=5", "seed=4"]), run_dir, strategy)
    assert error.value.key == "seed"
    with pytest.raises(ConfigError, match="the run has 'mean', this invocation 'median'") as error:
        resume_point(compose(["rounds=5", "seed=3", "strategy=median"]), run_dir, strategy)
    assert error.value.key == "strategy.name", "the exact dotted key"
    fedadam = compose(["rounds=5", "seed=3", "strategy=fedadam"])
    save_checkpoint(
        tmp_path / "checkpoints",
        Checkpoint(round=3, theta=checkpoint.theta, config=to_dict(fedadam), metrics_lines=3,
                   state={}),
    )  # fmt: skip
    with pytest.raises(ConfigError, match="holds no state of strategy 'fedadam'"):
        resume_point(fedadam, run_dir, make_strategy(fedadam.strategy))


def test_a_run_stopped_before_its_first_round_was_saved_resumes_from_round_0(
    tmp_path: Path,
) -> None:
    """Nothing recorded (an empty metrics.jsonl, no checkpoints/): nothing to lose, so the
    resume starts the run from round 0 instead of refusing; a checkpoint file, even a corrupt
    one, or a privacy journal counts as recorded."""
    run = compose(["rounds=5", "seed=3"])
    strategy = make_strategy(run.strategy)
    (tmp_path / "config.json").write_text(json.dumps(to_dict(run)))
    (tmp_path / "metrics.jsonl").write_text("")
    (tmp_path / "checkpoints").mkdir()
    said = interrupted_message(tmp_path, "fedhpg-run resume=DIR")
    assert said.endswith("start it again from round 0 with: fedhpg-run resume=DIR"), said
    assert resume_point(run, RunDirectory(tmp_path), strategy) is None
    (tmp_path / "checkpoints" / "privacy_journal.json").write_text("{}")
    with pytest.raises(ConfigError, match="no valid checkpoint"):
        resume_point(run, RunDirectory(tmp_path), strategy)


def test_a_checkpoint_of_a_non_finite_theta_is_never_valid(tmp_path: Path) -> None:
    save_checkpoint(tmp_path, _checkpoint(1))
    bad = _checkpoint(2)
    save_checkpoint(
        tmp_path,
        Checkpoint(round=2, theta=bad.theta * float("nan"), config={}, metrics_lines=2, state={}),
    )
    with pytest.raises(CheckpointError, match="not a finite float32 vector"):
        load_checkpoint(checkpoint_path(tmp_path, 2))
    loaded = latest_valid_checkpoint(tmp_path)
    assert loaded is not None and loaded.round == 1


def test_version_2_files_give_their_server_optimizer_state_to_the_strategy(tmp_path: Path) -> None:
    """Files written before strategies kept the server Adam's state beside the counters."""
    theta = np.arange(4, dtype=np.float32)
    packed = {"dtype": "<f4", "shape": [4], "data": theta.tobytes()}
    body = msgpack.packb(
        {
            "format": "fedhpg-checkpoint", "version": 2, "round": 7, "theta": packed,
            "config": {}, "metrics_lines": 7,
            "state": {"trajectories_per_agent": 5.0, "server_optimizer": {"steps": 7}},
            "arrays": {"server_optimizer.first": packed, "server_optimizer.second": packed},
        }
    )  # fmt: skip
    loaded = load_checkpoint(_sealed(checkpoint_path(tmp_path, 7), body))
    assert loaded.version == 2 and loaded.state == {"trajectories_per_agent": 5.0}
    assert loaded.strategy.scalars == {"steps": 7}
    assert sorted(loaded.strategy.arrays) == ["first", "second"]


def test_a_checkpoint_is_safetensors_that_torch_tools_read(tmp_path: Path) -> None:
    from safetensors.torch import load_file

    path = save_checkpoint(tmp_path, _checkpoint(4))
    assert path.suffix == ".safetensors"
    tensors = load_file(str(path))  # no fedhpg involved
    assert torch.equal(tensors["theta"], _checkpoint(4).theta)
    assert torch.equal(tensors["strategy/first"], torch.full((6,), 0.5))


def test_a_changed_header_fails_the_checksum(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path, _checkpoint(2))
    raw = path.read_bytes()
    forged = raw.replace(b'{\\"seed\\": 1}', b'{\\"seed\\": 7}')  # the config, in the header
    assert forged != raw and len(forged) == len(raw)
    path.write_bytes(forged)
    with pytest.raises(CheckpointError, match="checksum mismatch"):
        load_checkpoint(path)


def _version_3_file(directory: Path, checkpoint: Checkpoint) -> Path:
    """A checkpoint as fedhpg wrote them before safetensors: SHA-256, then msgpack."""

    def packed(array: np.ndarray) -> dict:
        return {"dtype": array.dtype.str, "shape": list(array.shape), "data": array.tobytes()}

    body = msgpack.packb(
        {
            "format": "fedhpg-checkpoint", "version": 3, "round": checkpoint.round,
            "theta": packed(checkpoint.theta.numpy()), "config": checkpoint.config,
            "metrics_lines": checkpoint.metrics_lines, "state": checkpoint.state,
            "strategy": {
                "scalars": checkpoint.strategy.scalars,
                "arrays": {k: packed(v) for k, v in checkpoint.strategy.arrays.items()},
            },
        },
        use_bin_type=True,
    )  # fmt: skip
    path = directory / f"round-{checkpoint.round:06d}.ckpt"
    directory.mkdir(parents=True, exist_ok=True)
    write_atomic(path, hashlib.sha256(body).digest() + body)
    return path


def test_a_run_checkpointed_in_the_previous_format_resumes_exactly(tmp_path: Path) -> None:
    """A run whose newest checkpoint is a version-3 msgpack file continues from it, bit for
    bit, and its next checkpoints are safetensors."""
    from fedhpg.server.commands import api

    keys = ["rounds=4", "seed=2", "agents=homogeneous4", "eval.every=4", "eval.episodes=2",
            "strategy=fedadam"]  # fmt: skip
    straight = api.run(overrides=keys)
    out_dir = tmp_path / "run"
    api.run(overrides=[*keys[1:], "rounds=2"], out_dir=out_dir)
    (newest,) = [p for p in (out_dir / "checkpoints").iterdir() if "000002" in p.name]
    current = load_checkpoint(newest)
    for path in (out_dir / "checkpoints").iterdir():
        path.unlink()
    _version_3_file(out_dir / "checkpoints", current)  # as the previous fedhpg left it
    resumed = api.run(overrides=[*keys, "resume=true"], out_dir=out_dir)
    assert torch.equal(resumed.theta, straight.theta)
    names = sorted(p.name for p in (out_dir / "checkpoints").iterdir())
    assert names == ["round-000003.safetensors", "round-000004.safetensors"], names


def test_a_checkpoint_of_an_unknown_format_version_is_refused_in_one_line(tmp_path: Path) -> None:
    from safetensors.numpy import save

    path = tmp_path / "round-000001.safetensors"
    path.write_bytes(
        save(
            {"theta": np.zeros(3, np.float32)},
            metadata={"format": "fedhpg-checkpoint", "version": "9"},
        )
    )
    with pytest.raises(CheckpointError) as caught:
        load_checkpoint(path)
    assert "version '9' of the checkpoint format; this fedhpg reads version 4" in str(caught.value)
    assert "\n" not in str(caught.value)
