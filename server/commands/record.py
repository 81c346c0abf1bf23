"""``fedhpg-record``: a video of a run's unified policy acting greedily in one agent's
environment variant, written by gymnasium's ``RecordVideo`` (which needs ``moviepy``: pip
install 'fedhpg[video]').

The policy is :func:`fedhpg.server.commands.api.load_policy`'s (the newest checkpoint, or
``--best``), its actions :func:`fedhpg.server.commands.api.act`'s; the episodes are one video, moved
into place once complete, so a failed recording leaves nothing behind.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import sys
import tempfile
from pathlib import Path
from typing import NoReturn

from fedhpg.common.runtime.cli import EXIT_USAGE, limit_threads, setup_logging, version_text
from fedhpg.server.run_dir import RunDirectoryError

logger = logging.getLogger(__name__)

RECORD_MODE = "rgb_array"


class RecordError(ValueError):
    """What cannot be recorded, in one line."""


def record(
    run_dir: Path, agent: int, *, episodes: int = 1, out: Path | None = None, best: bool = False
) -> Path:
    """Record ``episodes`` greedy episodes of the run's policy in agent ``agent``'s environment
    as one MP4 (default ``<run_dir>/agent-<agent>.mp4``); the path written."""
    from gymnasium.wrappers import RecordVideo

    from fedhpg.common.heterogeneity.variants import variant_of
    from fedhpg.server.commands import api

    if not (run_dir / "config.json").is_file():
        raise RecordError(f"{run_dir} is not a run directory (it holds no config.json)")
    if episodes < 1:
        raise RecordError(f"--episodes must be at least 1, got {episodes}")
    out = out if out is not None else run_dir / f"agent-{agent}.mp4"
    if out.suffix != ".mp4":
        raise RecordError(f"--out must name an .mp4 file, got {out}")
    if not out.parent.is_dir():
        raise RecordError(f"--out: no directory {out.parent}")
    try:
        config = api.load_run_config(run_dir)
        if not 0 <= agent < config.agents.num_agents:
            raise RecordError(
                f"--agent must be in [0, {config.agents.num_agents}) for the run in {run_dir}, "
                f"got {agent}"
            )
        policy = api.load_policy(run_dir, best=best)
    except RunDirectoryError as error:
        raise RecordError(str(error)) from None
    if importlib.util.find_spec("moviepy") is None:
        raise RecordError(
            "recording needs the optional moviepy package: pip install 'fedhpg[video]'"
        )
    variant = variant_of(config, agent)
    probe = variant.make_env()
    modes = probe.metadata.get("render_modes", [])
    probe.close()
    if RECORD_MODE not in modes:
        raise RecordError(
            f"env.family={config.env.family} renders no {RECORD_MODE} frames (its render "
            f"modes: {', '.join(modes) or 'none'}): nothing to record"
        )
    horizon = config.eval.horizon or variant.max_episode_steps
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame draws off-screen: no display
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as folder:
        env = RecordVideo(
            variant.make_env(render_mode=RECORD_MODE),
            video_folder=str(Path(folder) / "video"),
            episode_trigger=lambda episode: episode == 0,
            video_length=episodes * (horizon + 1),  # one video across every episode
            name_prefix="record",
            disable_logger=True,
        )
        try:
            for episode in range(episodes):
                observation, _ = env.reset(seed=config.seed + episode)
                for _ in range(horizon):
                    observation, _, terminated, truncated, _ = env.step(
                        api.act(policy, observation)
                    )
                    if terminated or truncated:
                        break
        finally:
            env.close()
        (video,) = (Path(folder) / "video").glob("*.mp4")
        os.replace(video, out)
    logger.info(
        "recorded %d episode(s) of agent %d's environment to %s", episodes, agent, out.resolve()
    )
    return out


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        """One line, exit 2 (argparse's default prints the whole usage first)."""
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(
        prog="fedhpg-record",
        description="An MP4 of a run's unified policy acting greedily in one agent's "
        "environment (gymnasium's RecordVideo; needs moviepy).",
    )
    parser.add_argument("run_dir", type=Path, help="the run directory")
    parser.add_argument("--agent", type=int, required=True, help="whose environment variant")
    parser.add_argument("--episodes", type=int, default=1, help="episodes in the video")
    parser.add_argument(
        "--out", type=Path, help="the MP4 to write (default: <run_dir>/agent-<k>.mp4)"
    )
    parser.add_argument(
        "--best",
        action="store_true",
        help="the best evaluation's checkpoint (checkpoint.keep_best) instead of the newest",
    )
    parser.add_argument(
        "-V", "--version", action="version", version=version_text(parser.prog).strip()
    )
    args = parser.parse_args(argv)
    setup_logging()
    limit_threads()
    try:
        record(args.run_dir, args.agent, episodes=args.episodes, out=args.out, best=args.best)
    except RecordError as error:
        sys.stderr.write(f"fedhpg-record: error: {error}\n")
        return EXIT_USAGE
    return 0


def entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry()
