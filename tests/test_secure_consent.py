"""What an honest agent will not do for a server that lies: contribute with less noise or
another clip than its own privacy settings give, or use keys its peers did not sign (a
server that substitutes a mask key could otherwise agree the masks itself). The server's
side and every agent's own code, each message through the codec (tests/secure_peers.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from secure_peers import HonestSide, secure_round

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.privacy import masks
from fedhpg.common.privacy.consent import least_noise_multiplier
from fedhpg.common.privacy.contribution import RoundPrivacy
from fedhpg.common.privacy.secagg import noise_shares
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.protocol import ShareRequest
from fedhpg.server.privacy import PrivateRounds

K = 5


def _run(*extra: str, mode: str = "dp_secagg") -> RunConfig:
    base = [f"privacy={mode}", "agents=homogeneous10", f"agents.num_agents={K}", "rounds=3"]
    return compose([*base, *extra], report=False)


def _servers_own(run: RunConfig) -> RoundPrivacy:
    """What an honest server asks of a round of all K agents."""
    return PrivateRounds(run, weighted=False).round_privacy(K)


@pytest.mark.parametrize(
    "extra",
    [
        ["privacy.noise_multiplier=1.5"],
        ["privacy.epsilon=4", "privacy.budget_against=server"],
        ["privacy.epsilon=4", "privacy.budget_against=server", "privacy.adaptive_clip=true"],
    ],
)
def test_an_honest_servers_round_is_accepted_and_a_quieter_one_refused(extra: list[str]) -> None:
    run = _run(*extra)
    asked = _servers_own(run)
    sigma = least_noise_multiplier(run.privacy, K, run.rounds)
    assert sigma is not None
    least = sigma * asked.clip / np.sqrt(noise_shares(run.privacy.secagg, K))
    assert asked.noise_std >= least
    honest = secure_round(run, {k: HonestSide(run, k) for k in range(K)}, private=asked)
    assert honest.secure is not None and honest.secure.failed is None
    assert honest.result.agents == list(range(K))
    quieter = dataclasses.replace(asked, noise_std=least * 0.99)
    refused = secure_round(run, {k: HonestSide(run, k) for k in range(K)}, private=quieter)
    assert refused.secure is not None and refused.secure.failed is not None
    assert "0 agents advertised keys" in refused.secure.failed
    assert refused.result.agents == []


def test_an_agent_refuses_another_clip_or_no_noise_at_all() -> None:
    run = _run("privacy.noise_multiplier=1", "privacy.clip=0.5")
    asked = _servers_own(run)
    for lie in (
        dataclasses.replace(asked, clip=5.0, noise_std=asked.noise_std * 10),  # C ten-fold
        dataclasses.replace(asked, noise_std=0.0),
        dataclasses.replace(asked, bound=1.0),
    ):
        answers = secure_round(run, {k: HonestSide(run, k) for k in range(K)}, private=lie)
        assert answers.secure is not None and answers.secure.failed is not None, lie


def test_a_budget_against_the_model_binds_no_server() -> None:
    """With amplification by the server's own sample, the agent cannot check σ: documented,
    and the floor is None rather than a wrong one."""
    run = _run("privacy.epsilon=4")
    assert least_noise_multiplier(run.privacy, K, run.rounds) is None


# -- signed key advertisements --------------------------------------------------------------


@pytest.fixture(scope="module")
def keys_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from fedhpg.server.commands.keys import run as fedhpg_keys

    directory = tmp_path_factory.mktemp("keys") / "keys"
    assert fedhpg_keys([str(directory), "--agents", str(K)]) == 0
    return directory


class _Substituting(HonestSide):
    """An agent side whose requests pass through a server that swaps agent 2's advertised
    mask key for one of its own (or drops every signature)."""

    def __init__(self, run: RunConfig, k: int, how: str) -> None:
        super().__init__(run, k)
        self.how = how

    def answer(self, request):  # type: ignore[no-untyped-def]
        if isinstance(request, ShareRequest):
            if self.how == "key":
                keys = request.mask_keys.copy()
                position = list(request.participants).index(2)
                server_key = masks.public_key(masks.new_private_key())
                keys[position] = np.frombuffer(server_key, dtype=np.uint8)
                request = dataclasses.replace(request, mask_keys=keys)
            else:
                request = dataclasses.replace(request, signatures=np.zeros_like(request.signatures))
        return super().answer(request)


def test_signed_rounds_complete_and_a_substituted_key_is_refused(keys_dir: Path) -> None:
    run = _run(f"security.keys_dir={keys_dir}", mode="secagg")
    honest = secure_round(run, {k: HonestSide(run, k) for k in range(K)})
    assert honest.secure is not None and honest.secure.failed is None
    assert honest.result.agents == list(range(K))
    for how in ("key", "signatures"):
        sides = {k: _Substituting(run, k, how) for k in range(K)}
        answers = secure_round(run, sides)
        assert answers.secure is not None and answers.secure.failed is not None, how
        assert "0 agents shared keys" in answers.secure.failed


def test_without_a_roster_the_same_substitution_goes_unseen() -> None:
    """The control: unsigned agents take the substituted key (the server is trusted)."""
    run = _run(mode="secagg")
    sides = {k: _Substituting(run, k, "key") for k in range(K)}
    answers = secure_round(run, sides)
    assert answers.secure is not None and answers.secure.failed is None
    # the others masked with a key only the server holds, and their round went through
    # (agent 2 alone saw its own key replaced and dropped out)
    assert answers.result.agents == [0, 1, 3, 4]
