"""The server's side of ``privacy=``: clipping, noise, the accountant and the budget.

One :class:`PrivateRounds` per run (built by :func:`fedhpg.server.assembly.check_run`) turns a
round's answers into θ̃ in place of the strategy's own ``aggregate``:

- ``dp``: the server clips each Δ_k = θ_k − θ̃ to C, sums the contributions
  (:mod:`fedhpg.common.privacy.contribution`) and adds N(0, σ²C²) to the sum (central noise);
- ``secagg``: the pool hands over the unmasked sum of the agents' contributions (it never saw
  one alone): the exact average of the included agents' updates;
- ``dp_secagg``: the same sum, to which every agent added its share of the noise.

With DP the average divides by the expected number of participants (public), each round is
accounted (:mod:`fedhpg.common.privacy.accounting`), and a round that would take ε past the
budget is refused before it starts: the run stops in one line, its last checkpoint intact.
The strategy then makes θ̃ from the average (``from_average``: the average itself, or
fedadam's step towards it). Checkpoints keep the rounds accounted, σ and the clip.

Every ε names its party (docs/privacy.md, "Who learns what"):

- ``epsilon``: against readers of the released model, and with ``dp`` of everything the run
  writes. A sampled ``dp`` run is accounted with amplification by sampling, so its sample
  is secret (:mod:`fedhpg.server.participation`) and kept out of the run's records
  (:attr:`PrivateRounds.hides_sample`: no agent rows, no ``selected``, no agent named in the
  pools' log lines while the rounds run);
- ``epsilon_server`` (``dp_secagg``): against the server, which picks and sees each round's
  sample: no amplification, the worst agent's rounds composed.

Account first, release second: a round is accounted, and with a run directory written to a
journal beside the checkpoints (fsynced), before θ̃ leaves :meth:`PrivateRounds.aggregate`
for evaluation, the next round or the final policy. A resumed run accounts the rounds of its
checkpoint or of the journal, whichever is more, so a round released and then lost with its
checkpoint in a crash is counted again when it is drawn again with fresh noise.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import re
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.privacy import accounting, dp
from fedhpg.common.privacy.accounting import Sampling
from fedhpg.common.privacy.contribution import EXTRA, RoundPrivacy, average, contribution
from fedhpg.common.privacy.secagg import fewest_inputs, noise_shares
from fedhpg.common.records.types import RoundResult
from fedhpg.server.checkpoint import write_atomic
from fedhpg.server.pools import FederationError, RoundAnswers, SkippedRound
from fedhpg.server.run_dir import RunDirectoryError

logger = logging.getLogger(__name__)

JOURNAL_NAME = "privacy-journal.json"
"""In the checkpoints' directory: the rounds accounted, written before θ̃ leaves the server."""


class BudgetExhausted(FederationError):
    """The next round would take ε past ``privacy.epsilon``."""


def sampling_of(run: RunConfig) -> Sampling:
    """How the run draws a round's agents, as the accountant sees it (a trace is public and
    not random: every round counts in full, as with ``all``)."""
    participation = run.strategy.participation
    population = run.agents.num_agents
    if participation.mode == "uniform" and participation.per_round is not None:
        return Sampling(kind="fixed", population=population, sample=participation.per_round)
    return Sampling(kind="all", population=population)


class PrivateRounds:
    """Clip, noise, account and average the rounds of a run with ``privacy.mode`` ≠ none."""

    def __init__(self, run: RunConfig, *, weighted: bool) -> None:
        settings = run.privacy
        self.mode = settings.mode
        self.settings = settings
        self.weighted = weighted
        self.sampling = sampling_of(run)
        population = run.agents.num_agents
        self.delta = (
            settings.delta if settings.delta is not None else accounting.default_delta(population)
        )
        self.target = settings.epsilon
        self.against_server = settings.budget_against == "server"
        """``privacy.epsilon`` caps ε against the server (``dp_secagg``), not the model's."""
        self.clip = settings.clip
        self.accounted = 0
        self.participations: np.ndarray | None = (
            np.zeros(population, dtype=np.int64) if self.mode == "dp_secagg" else None
        )
        """``dp_secagg``: the rounds each agent was drawn for (the server's ε composes them)."""
        self.noise_multiplier = 0.0
        self.count_std: float | None = None
        self.update_multiplier = 0.0
        self.journal: Path | None = None
        """Where each round's accounting is written before its θ̃ leaves (a run directory)."""
        self._journaled: dict[str, Any] = {}
        self._sample: list[int] = []
        self._seed = settings.noise_seed
        self._last: dict[str, Any] = {}
        if self.hides_sample and run.agents.plan != "none":
            raise ConfigError(
                "agents.plan",
                f"got {run.agents.plan!r} with privacy.mode=dp and a sampled participation: a "
                "plan is made from each drawn agent's rounds and would name the sample, which "
                "must stay secret for the accounted ε; use agents.plan=none",
            )
        if self.dp:
            if settings.noise_multiplier is not None:
                self.noise_multiplier = settings.noise_multiplier
            else:
                assert self.target is not None  # validated
                self.noise_multiplier = accounting.calibrate(
                    self.target, self.sampling, run.rounds, self.delta, known=self.against_server
                )
            self._set_count_noise(run)

    def _set_count_noise(self, run: RunConfig) -> None:
        if self.settings.adaptive_clip:
            # Andrew et al.'s m/20, but never below σ: a small round's count would otherwise
            # spend most of the budget (the update's own multiplier is then 2/√3 σ at most)
            self.count_std = self.settings.count_std or max(
                self.sampling.expected / 20, self.noise_multiplier
            )
        try:
            self.update_multiplier = dp.update_noise_multiplier(
                self.noise_multiplier, self.count_std
            )
        except ValueError as error:
            raise ConfigError("privacy.count_std", str(error)) from None

    @property
    def dp(self) -> bool:
        return self.mode in ("dp", "dp_secagg")

    @property
    def secure(self) -> bool:
        """Whether the pools aggregate securely (the server never sees a θ_k)."""
        return self.mode in ("secagg", "dp_secagg")

    @property
    def hides_sample(self) -> bool:
        """Whether the run's records leave out who took part: ``dp`` with a sampled
        participation, whose ε is amplified by a sample only the server knows."""
        return self.mode == "dp" and self.sampling.kind == "fixed"

    def epsilon(self, rounds: int | None = None) -> float:
        """ε against readers of the released model after ``rounds`` accounted rounds
        (default: so far)."""
        spent = self.accounted if rounds is None else rounds
        return accounting.epsilon(self.noise_multiplier, self.sampling, spent, self.delta)

    def epsilon_server(self, participations: int | None = None) -> float:
        """ε against the server (``dp_secagg``), which knows each round's sample: the worst
        agent's ``participations`` rounds (default: so far) without amplification."""
        if participations is None:
            assert self.participations is not None
            participations = int(self.participations.max(initial=0))
        return accounting.epsilon(
            self.noise_multiplier, self.sampling, participations, self.delta, known=True
        )

    def check_budget(self, round_number: int, selected: Sequence[int] = ()) -> None:
        """Refuse ``round_number``, whose agents are ``selected``, if it would take the capped
        ε past the budget."""
        self._sample = sorted(selected)
        if not self.dp or self.target is None:
            return
        if self.against_server:
            assert self.participations is not None  # validated: dp_secagg
            drawn = self.participations.copy()
            drawn[self._sample] += 1
            after, party = self.epsilon_server(int(drawn.max(initial=0))), " against the server"
        else:
            after, party = self.epsilon(self.accounted + 1), ""
        if after > self.target:
            raise BudgetExhausted(
                f"privacy.epsilon: round {round_number} would spend ε = {after:.4g}{party} > the"
                f" budget {self.target:g} (δ = {self.delta:.3g}, σ = {self.noise_multiplier:.4g},"
                f" {self.accounted} rounds accounted): the run stops here, its checkpoint of "
                f"round {round_number - 1} kept"
            )

    def min_inputs(self, participants: int) -> int:
        """The fewest contributions a round's sum may hold: with distributed noise, enough
        shares of it to reach σC (the secure aggregation threshold of the round of
        ``participants``, the agents that run its protocol)."""
        return fewest_inputs(self.mode, self.settings.secagg, participants)

    def round_privacy(self, participants: int) -> RoundPrivacy:
        """What the round's agents (or the server, for central noise) contribute with; with
        distributed noise, each agent's share is sized from the ``participants`` that run the
        round's protocol (:func:`noise_shares`: the pools unmask no fewer than
        :meth:`min_inputs` of them, and colluders' shares do not count)."""
        clip = self.clip if self.dp else 0.0
        noise_std = count_std = 0.0
        if self.mode == "dp_secagg":
            shares = noise_shares(self.settings.secagg, participants)
            noise_std = dp.per_agent_std(self.update_multiplier * clip, shares)
            count_std = dp.per_agent_std(self.count_std or 0.0, shares)
        return RoundPrivacy(
            clip=clip,
            noise_std=noise_std,
            count_std=count_std,
            bound=self.settings.secagg.range if self.secure else math.inf,
            weighted=self.weighted,
        )

    def aggregate(
        self,
        round_number: int,
        theta: torch.Tensor,
        answers: RoundAnswers,
        selected: int,
    ) -> torch.Tensor:
        """θ̄ = θ̃ + the round's private average update (the strategy takes it from there)."""
        if self.secure:
            if answers.secure is None:
                raise FederationError(f"round {round_number}: no secure sum came back")
            if answers.secure.failed is not None:  # nothing was released: nothing to account
                self._last = {"inputs": 0}
                raise SkippedRound(round_number, answers.secure.failed)
            total, inputs = answers.secure.total, answers.secure.inputs
            participants = answers.secure.participants
            fewest = self.min_inputs(participants)
            if inputs < fewest:  # the pools check this before unmasking: never here
                raise FederationError(
                    f"round {round_number}: {inputs} of {participants} agents' inputs were "
                    f"unmasked, fewer than the {fewest} whose noise shares reach σC "
                    "(privacy.secagg.dropout)"
                )
        else:
            total, inputs = self._central_sum(round_number, theta, answers.result, selected)
        denominator = self.sampling.expected if self.dp else None
        step, unclipped = average(total, denominator)
        clip_used = self.clip
        if self.dp:
            self.accounted += 1
            if self.participations is not None:
                self.participations[self._sample] += 1
            self._write_journal(round_number)  # before θ̃ leaves: evaluation, the next round
            if self.settings.adaptive_clip:
                self.clip = dp.next_clip(
                    self.clip, unclipped, self.settings.target_quantile, self.settings.clip_rate
                )
        self._last = {"inputs": inputs, **({"clip": clip_used} if self.dp else {})}
        return theta + torch.from_numpy(step).to(theta.dtype)

    def _central_sum(
        self, round_number: int, theta: torch.Tensor, result: RoundResult, selected: int
    ) -> tuple[np.ndarray, int]:
        settings = self.round_privacy(selected)
        total = np.zeros(theta.numel() + EXTRA)
        for row, trajectories in zip(result.thetas, result.stats.trajectories, strict=True):
            total += contribution(torch.from_numpy(row) - theta, trajectories, settings)
        noise = dp.noise_stream(
            self._seed, round_number, None, secure=self.settings.secure_noise_on
        )
        total[:-EXTRA] += dp.gaussian(noise, theta.numel(), self.update_multiplier * self.clip)
        if self.count_std is not None:
            total[-1] += dp.gaussian(noise, 1, self.count_std)[0]
        return total, len(result)

    def round_stats(self) -> dict[str, Any]:
        """metrics.jsonl's ``epsilon``, ``epsilon_server``, ``delta`` and ``privacy`` of the
        last round."""
        stats: dict[str, Any] = {"mode": self.mode, **self._last}
        if self.dp:
            stats.update(
                epsilon=self.epsilon(),
                delta=self.delta,
                noise_multiplier=self.noise_multiplier,
                rounds_accounted=self.accounted,
            )
            if self.participations is not None:
                stats["epsilon_server"] = self.epsilon_server()
            if self.hides_sample:
                stats["sample"] = "hidden"
        return stats

    def summary(self) -> dict[str, Any]:
        """summary.json's ``privacy``."""
        stats = {"mode": self.mode, "secure_aggregation": self.secure}
        if self.dp:
            stats.update(
                epsilon=self.epsilon(),
                **(
                    {"epsilon_server": self.epsilon_server()}
                    if self.participations is not None
                    else {}
                ),
                delta=self.delta,
                epsilon_budget=self.target,
                budget_against=self.settings.budget_against,
                noise_multiplier=self.noise_multiplier,
                rounds_accounted=self.accounted,
                clip=self.clip,
                neighbouring=self.sampling.relation,
                secure_noise=self.settings.secure_noise_on and self._seed is None,
                **({"sample": "hidden"} if self.hides_sample else {}),
            )
        return stats

    def state(self) -> dict[str, Any]:
        state: dict[str, Any] = {
            "accounted": self.accounted,
            "sigma": self.noise_multiplier,
            "clip": self.clip,
        }
        if self.participations is not None:
            state["participations"] = self.participations.tolist()
        return state

    def restore(self, state: dict[str, Any], run: RunConfig) -> None:
        """Continue the accounting of a resumed run: its σ (never re-calibrated for a longer
        run), rounds accounted and clip; the rounds accounted (and each agent's) are the
        journal's where it is ahead of the checkpoint (a round released, then lost in a
        crash before its checkpoint: it is drawn again, and accounted again)."""
        if not state:
            return
        self.accounted = int(state["accounted"])
        self.clip = float(state["clip"])
        if self.participations is not None and "participations" in state:
            self.participations[:] = state["participations"]
        journaled = int(self._journaled.get("rounds_accounted", 0))
        if journaled > self.accounted:
            logger.warning(
                "privacy: round %d was released before its checkpoint was written; it runs "
                "again with fresh noise and is accounted again (%d rounds accounted so far)",
                int(self._journaled.get("round", 0)),
                journaled,
            )
            self.accounted = journaled
            if self.participations is not None and "participations" in self._journaled:
                self.participations[:] = self._journaled["participations"]
        if self.dp:
            self.noise_multiplier = float(state["sigma"])
            self._set_count_noise(run)

    def keep_journal(self, directory: Path, *, resuming: bool) -> None:
        """Write each round's accounting to ``directory``'s journal before its θ̃ leaves;
        ``resuming``: read the journal a killed run left first (:meth:`restore` takes it)."""
        if not self.dp:
            return
        self.journal = directory / JOURNAL_NAME
        if resuming and self.journal.is_file():
            try:
                self._journaled = dict(json.loads(self.journal.read_text(encoding="utf-8")))
            except (OSError, ValueError) as error:
                raise ConfigError(
                    "resume", f"cannot read the privacy journal {self.journal}: {error}"
                ) from None

    def _write_journal(self, round_number: int) -> None:
        if self.journal is None:
            return
        entry: dict[str, Any] = {"round": round_number, "rounds_accounted": self.accounted}
        if self.participations is not None:
            entry["participations"] = self.participations.tolist()
        try:
            self.journal.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(self.journal, json.dumps(entry).encode())
        except OSError as error:
            raise RunDirectoryError(
                f"cannot write the privacy journal {self.journal}: {error.strerror or error}; "
                f"θ̃ of round {round_number} is not released, the checkpoints are kept"
            ) from None

    def hiding_names(self, names: Sequence[str]) -> contextlib.AbstractContextManager[None]:
        """While the rounds run: the pools' log lines name no agent where the sample is hidden
        (:func:`hidden_agent_names`)."""
        return hidden_agent_names(names) if self.hides_sample else contextlib.nullcontext()


POOL_LOGGERS = tuple(
    f"fedhpg.server.pools{suffix}"
    for suffix in (
        "",
        ".arrivals",
        ".collection",
        ".inprocess",
        ".links",
        ".rounds",
        ".secure",
        ".zmq_pool",
    )
)
"""The loggers whose lines may name an agent of a round (a straggler, a rejected update)."""
HIDDEN_NAME = "an agent"


class _AgentNames(logging.Filter):
    """Rewrites a log record's message with every agent name in it replaced."""

    def __init__(self, names: Sequence[str]) -> None:
        super().__init__()
        spelled = sorted({re.escape(name) for name in names if name}, key=len, reverse=True)
        alternatives = "|".join([*spelled, r"agent-\d+"])
        self.pattern = re.compile(r"(?<![\w-])(?:" + alternatives + r")(?![\w-])")

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        hidden = self.pattern.sub(HIDDEN_NAME, message)
        if hidden != message:
            record.msg, record.args = hidden, ()
        return True


@contextlib.contextmanager
def hidden_agent_names(names: Sequence[str]) -> Iterator[None]:
    """Within: the pools' log lines say "an agent" for every agent of ``names`` (and every
    default id ``agent-<k>``), so that a log of a run whose sample is secret does not name who
    straggled or was rejected in a round."""
    loggers = [
        logging.getLogger(name)
        for name in {*POOL_LOGGERS, *logging.root.manager.loggerDict}
        if name == "fedhpg.server.pools" or name.startswith("fedhpg.server.pools.")
    ]
    hiding = _AgentNames(names)
    for each in loggers:
        each.addFilter(hiding)
    try:
        yield
    finally:
        for each in loggers:
            each.removeFilter(hiding)
