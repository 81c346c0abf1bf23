"""An agent keeps its own privacy settings: a server may not lower them. An agent started with
one privacy setting and a server running another is refused in one line, in both directions,
before any update leaves it."""

from __future__ import annotations

from pathlib import Path

import pytest
from procs import free_port, processes, start

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.run_roles import adopt_settings, dictated_settings
from fedhpg.common.runtime.cli import compose

TIMEOUT_S = 90


def _run(*overrides: str):
    return compose(["agents.virtual_clock=true", *overrides])


@pytest.mark.parametrize(
    ("server", "agent", "key"),
    [
        (["privacy=none"], ["privacy=dp_secagg", "privacy.epsilon=1"], "privacy.mode"),
        (["privacy=dp_secagg", "privacy.epsilon=1"], ["privacy=dp_secagg", "privacy.epsilon=8"],
         "privacy.epsilon"),
        (["privacy=dp_secagg", "privacy.epsilon=4"],
         ["privacy=dp_secagg", "privacy.epsilon=4", "privacy.clip=0.5"], "privacy.clip"),
    ],
)  # fmt: skip
def test_an_agent_refuses_a_server_whose_privacy_differs(
    server: list[str], agent: list[str], key: str
) -> None:
    with pytest.raises(ConfigError) as refused:
        adopt_settings(_run(*agent), dictated_settings(_run(*server)))
    assert refused.value.key == key
    assert "this agent was started with" in str(refused.value)


def test_an_agent_with_the_servers_privacy_adopts_the_rest() -> None:
    server = _run("privacy=dp_secagg", "privacy.epsilon=4", "rounds=7", "seed=3")
    adopted = adopt_settings(
        _run("privacy=dp_secagg", "privacy.epsilon=4"), dictated_settings(server)
    )
    assert (adopted.rounds, adopted.seed, adopted.privacy) == (7, 3, server.privacy)


def test_a_private_agent_joining_a_plain_server_exits_in_one_line(tmp_path: Path) -> None:
    """The agent would otherwise have trained and sent its update in the clear."""
    port = free_port()
    common = [
        "rounds=1", "agents=homogeneous10", "agents.num_agents=1", "agents.virtual_clock=true",
        "eval.every=1", "eval.episodes=1", f"server.port={port}", "server.register_timeout_s=30",
        "server.tensorboard=false",
    ]  # fmt: skip
    with processes() as started:
        start(
            started, "fedhpg-server", [*common, f"server.out_dir={tmp_path / 'run'}"], cwd=tmp_path
        )
        agent = start(
            started,
            "fedhpg-agent",
            [*common, "privacy=dp_secagg", "privacy.epsilon=1", "agent.index=0"],
            cwd=tmp_path,
        )
        assert agent.wait(timeout=TIMEOUT_S) == 1
        error = agent.stderr.read().strip().splitlines()
    assert len(error) == 1 and error[0].startswith("error: agent 0: "), error
    assert "privacy.mode" in error[0] and "'none'" in error[0]
