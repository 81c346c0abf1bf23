"""What an agent program computes for the server: its agents' rounds and evaluations.

:class:`AgentWork` holds the learning side of the logical agents ``first`` .. ``first+count-1``
(one :func:`~fedhpg.common.learning.group.make_agent_group` of them all, as in every placement, so θ̃
never depends on where an agent runs) and their emulated devices, and turns a ``Train`` or an
``Evaluate`` into the messages that answer it.

Device emulation prices the same arithmetic in one of two ways:

- A lone agent whose device sleeps (``agents.virtual_clock=false``) is priced iteration by
  iteration through its own :class:`~fedhpg.common.heterogeneity.device.DeviceModel`, and sleeps
  what the round owes once, before the answer leaves; a superseded request cuts the sleep short.
  Only a process of one agent can sleep its device's time.
- Every other range (an agent host's agents are always on the virtual clock: a host of 500
  agents cannot sleep 500 devices' time on one thread) prices all its agents' iterations at
  once (:class:`~fedhpg.common.heterogeneity.device.DeviceColumns`), to the bit what each agent's
  own ``DeviceModel`` gives.

Either way the group's :class:`~fedhpg.common.records.types.RoundResult` leaves as it is, its device
columns filled in, cut into ceil(A / :func:`~fedhpg.common.wire.transport.answers_per_message`)
slices of itself (the ``update`` message).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.heterogeneity.device import DeviceColumns, DeviceModel, device_for, message_bytes
from fedhpg.common.heterogeneity.variants import range_digest, variant_digest, variants_of
from fedhpg.common.learning.group import AgentGroup, make_agent_group
from fedhpg.common.privacy import fixedpoint
from fedhpg.common.privacy.consent import refusal
from fedhpg.common.privacy.contribution import EXTRA, contribution, redacted
from fedhpg.common.privacy.masks import PeerDataError
from fedhpg.common.privacy.secagg import SEALED_BYTES, SecAggError
from fedhpg.common.privacy.session import LocalSecAgg
from fedhpg.common.privacy.shamir import SHARE_BYTES
from fedhpg.common.privacy.signing import SIGNATURE_BYTES, agent_signing
from fedhpg.common.records.types import RoundResult, UpdateColumns, UpdateStats
from fedhpg.common.runtime import timeline
from fedhpg.common.runtime.memory import tune_malloc_for
from fedhpg.common.wire import secure_rows
from fedhpg.common.wire.codec import MAX_HEADER_BYTES
from fedhpg.common.wire.protocol import (
    KEY_BYTES,
    MAX_BATCH_ANSWERS,
    Evaluate,
    Evaluation,
    KeyShares,
    MaskedUpdate,
    MaskKeys,
    MaskRequest,
    Message,
    Request,
    ShareRequest,
    Train,
    Unmasking,
    UnmaskRequest,
    no_keys,
)
from fedhpg.common.wire.transport import answers_per_message, batch_message_cap

logger = logging.getLogger(__name__)
SECURE_MODES = ("secagg", "dp_secagg")


class Cancelled(Exception):
    """The server moved on (or went away): the job's result is no longer wanted."""


class OutsideRange(ValueError):
    """A request named agents this program does not serve."""


class AgentWork:
    """The learning side and the devices of the agents ``indices`` of one run."""

    def __init__(self, run: RunConfig, indices: range, *, label: str) -> None:
        self.indices = indices
        self.label = label
        self.variants = variants_of(run, indices)  # the range's rows, drawn in one go
        # the run's spaces: the same for every agent, computed once
        self.signature = self.variants[indices.start].signature()
        self.digest = range_digest([variant_digest(run, self.variants[k]) for k in indices])
        self.devices = self._devices(run)
        self.group: AgentGroup | None = None
        self._columns: DeviceColumns | None = None
        self.private = run.privacy.mode != "none"
        self.secure: SecureAgents | None = None
        if run.privacy.mode in SECURE_MODES:  # channel keys go in the hello
            self.secure = SecureAgents(run, label)
            self.secure.keys.channel_keys(indices)

    def channel_keys(self) -> np.ndarray:
        """The hello's channel public keys of this range (none without secure aggregation)."""
        if self.secure is None:
            return no_keys()
        return self.secure.keys.channel_keys(self.indices)

    @property
    def sleeps(self) -> bool:
        """Whether the round is priced as it runs, on a device that really sleeps."""
        return not self.devices[self.indices.start].virtual_clock

    def _devices(self, run: RunConfig) -> dict[int, DeviceModel]:
        if len(self.indices) == 1:  # a lone agent's device is as the run configures it
            return {k: device_for(run, k) for k in self.indices}
        return {
            k: dataclasses.replace(device_for(run, k), virtual_clock=True) for k in self.indices
        }

    def build(self, run: RunConfig) -> AgentGroup:
        """The group and the devices of the run the server dictates (at registration)."""
        self.close()
        self.private = run.privacy.mode != "none"
        if self.secure is not None:
            self.secure.adopt(run)
        self.devices = self._devices(run)
        # row k - first is agent k's: what a round prices
        self._columns = (
            None if self.sleeps else DeviceColumns([self.devices[k] for k in self.indices])
        )
        group = make_agent_group(run, list(self.indices), variants=self.variants)
        group.prepare()  # every agent's constants now, not inside the rounds that select it
        tune_malloc_for(group)
        self.group = group
        return group

    def close(self) -> None:
        if self.group is not None:
            self.group.close()
            self.group = None

    # -- answering a request ----------------------------------------------------------------

    def answer(self, request: Request, cancel: threading.Event, max_bytes: int) -> list[Message]:
        """The messages that answer ``request``; raises :class:`Cancelled` once ``cancel`` is
        set, :class:`OutsideRange` for agents this program does not serve."""
        group = self.group
        assert group is not None, "answer() before build()"
        agents = sorted(set(request.agents))
        if agents and not (self.indices.start <= agents[0] and agents[-1] < self.indices.stop):
            raise OutsideRange(f"the server asked for agents outside {self.label}'s range")
        if not agents:
            return []
        if isinstance(request, ShareRequest | MaskRequest | UnmaskRequest):
            if self.secure is None:
                raise OutsideRange(f"{self.label} was asked to mask without channel keys")
            if isinstance(request, ShareRequest):
                return self.secure.share_keys(request, max_bytes)
            if isinstance(request, MaskRequest):
                return self.secure.mask(request, max_bytes)
            return self.secure.reveal(request, max_bytes)
        theta = torch.from_numpy(np.array(request.theta))
        if isinstance(request, Evaluate):
            evaluations = group.evaluate(request.round, theta, request.episodes, agents)
            return [
                Evaluation(round=request.round, agents=chunk, stats=[evaluations[k] for k in chunk])
                for chunk in _chunks(agents, MAX_BATCH_ANSWERS)
            ]
        planned = dict(zip(request.agents, request.budgets, strict=True)) if request.budgets else {}
        timeline.mark(self.label, "work-start", request.round)
        started = time.perf_counter()
        if self.sleeps:
            result = self._train_sleeping(group, request, theta, planned, cancel)
        else:
            result = self._train_columns(group, request, theta, agents, planned, cancel, started)
        timeline.mark(self.label, "trained", request.round)
        if self.private:  # what the agents' data decides directly stays here
            result = redacted(result)
        if request.private is not None:
            if self.secure is None:
                raise OutsideRange(f"{self.label} was asked to mask without channel keys")
            return self.secure.share(request, theta, result, max_bytes)
        num_params = result.thetas.shape[1]
        per_message = answers_per_message(batch_message_cap(max_bytes, num_params), num_params)
        if len(result) <= per_message:  # one message (a lone agent's always)
            return [result]
        return [result[start : start + per_message] for start in range(0, len(result), per_message)]

    def _train_columns(
        self,
        group: AgentGroup,
        request: Train,
        theta: torch.Tensor,
        agents: list[int],
        planned: Mapping[int, Mapping[str, int]],
        cancel: threading.Event,
        started: float,
    ) -> RoundResult:
        """The round as columns, every agent's device priced at once (the virtual clock);
        each answer leaves with the batch, so the round's wall time since ``started``
        (``perf_counter``) is each agent's."""
        assert self._columns is not None

        trained = group.train(
            request.round, theta, agents, budgets=planned, interrupt=_raiser(cancel)
        )
        result = trained.result
        num_params = result.thetas.shape[1]
        rows = np.asarray(result.agents, dtype=np.int64) - self.indices.start
        emulated, speeds = self._columns.round(
            rows, request.round, message_bytes(num_params), trained.iterations, num_params
        )
        return result.with_stats(
            emulated_s=emulated.tolist(),
            speed=speeds.tolist(),
            local_wall_s=[time.perf_counter() - started] * len(result),
        )

    def _train_sleeping(
        self,
        group: AgentGroup,
        request: Train,
        theta: torch.Tensor,
        planned: Mapping[int, Mapping[str, int]],
        cancel: threading.Event,
    ) -> RoundResult:
        """A lone agent's round on its own device: its iterations priced in order once it
        trained, and the sleep they owe paid once, at the end, cut short by ``cancel``."""
        k = self.indices.start
        device = self.devices[k]
        device.sleep = lambda seconds: _sleep_unless(cancel, seconds)
        started = time.perf_counter()

        trained = group.train(request.round, theta, [k], budgets=planned, interrupt=_raiser(cancel))
        num_params = group.num_params
        # The counted clock charges θ's float32 bytes plus a fixed header for the request and
        # for the answer (not the encoded lengths), exactly what the in-process pool charges.
        message = message_bytes(num_params)
        device.take_emulated()
        device.transmit(message)  # the request's one-way latency (and transfer)
        for ran in trained.iterations:
            device.spend(
                float(ran.compute_s[0]),
                int(ran.env_steps[0]),
                request.round,
                grad_steps=int(ran.grad_steps[0]),
                num_params=num_params,
            )
        device.transmit(message)  # the answer's
        device.settle()
        return trained.result.with_stats(
            emulated_s=[device.take_emulated()],
            local_wall_s=[time.perf_counter() - started],
            speed=[device.speed_at(request.round)],
        )


class SecureAgents:
    """The agents' side of secure aggregation for this program's range: each round's
    contributions, masked and unmasked as the server's exchanges ask (server/pools/secure.py).

    Every request is read with its fields checked
    (:mod:`~fedhpg.common.wire.secure_rows`). A row the protocol refuses (a round this
    program has no keys for, after a restart; a request that does not fit the round) is left
    out of the answer: the server then counts that agent as dropped out. A neighbour whose
    sealed shares do not open (altered, replayed, or not shares at all) is that neighbour's
    drop-out as far as this agent's shares go: the agent answers for itself, logs it once,
    and never exits over another party's data."""

    def __init__(self, run: RunConfig, agent_id: str) -> None:
        signing = agent_signing(run.security, agent_id)
        if signing is None:
            logger.info(
                "%s: no signing roster (security.signers_dir): the mask keys it advertises are "
                "not signed, and the server is trusted to relay every agent's keys unchanged",
                agent_id,
            )
        self.keys = LocalSecAgg(run, signing)
        self.label = agent_id
        self.run = run
        self._inputs: dict[int, np.ndarray] = {}
        self._stats: dict[int, UpdateStats] = {}
        self._channel_keys: dict[int, bytes] = {}
        self._planned = 0
        self._round = -1
        self._num_params = 1

    def adopt(self, run: RunConfig) -> None:
        """The run as the server dictates it (its privacy settings are this program's own)."""
        self.run = run
        self.keys.settings = run.privacy

    def share(
        self, request: Train, theta: torch.Tensor, result: RoundResult, max_bytes: int
    ) -> list[Message]:
        """After training: each agent's contribution kept, its round mask key advertised."""
        private = request.private
        assert private is not None
        try:
            keys = secure_rows.train_participants(request)
        except secure_rows.RowError as error:
            logger.warning("round %d: no agent takes part: %s", request.round, error)
            return []
        refused = refusal(
            self.run.privacy,
            private,
            participants=len(keys),
            population=self.run.agents.num_agents,
            rounds=self.run.rounds,
        )
        if refused is not None:
            logger.error(
                "round %d: %s refuses to contribute as the server asks: %s",
                request.round,
                self.label,
                refused,
            )
            return []
        bound = max(private.bound, 1.0)
        scale = fixedpoint.scale_for(len(keys), bound)
        agents, thetas, records = result.agents, result.thetas, result.stats.records()
        self._round, self._inputs, self._stats = request.round, {}, {}
        self._channel_keys, self._planned = keys, len(keys)
        self._num_params = thetas.shape[1]
        mask_keys = np.zeros((len(agents), KEY_BYTES), dtype=np.uint8)
        commitments = np.zeros((len(agents), KEY_BYTES), dtype=np.uint8)
        signatures = np.zeros((len(agents), SIGNATURE_BYTES), dtype=np.uint8)
        for i, k in enumerate(agents):
            row = contribution(
                torch.from_numpy(thetas[i]) - theta,
                records[i].trajectories,
                private,
                self.keys.noise(request.round, k),
            )
            self._inputs[k] = fixedpoint.encode(row, scale, bound)
            self._stats[k] = records[i]
            mask_key, commitment, signature = self.keys.advertise(request.round, k)
            mask_keys[i] = np.frombuffer(mask_key, dtype=np.uint8)
            commitments[i] = np.frombuffer(commitment, dtype=np.uint8)
            signatures[i] = np.frombuffer(signature, dtype=np.uint8)
        per = _rows_per_message(max_bytes, self._num_params, 2 * KEY_BYTES + SIGNATURE_BYTES)
        return _in_messages(
            MaskKeys,
            request.round,
            agents,
            per,
            mask_keys=mask_keys,
            seed_commitments=commitments,
            signatures=signatures,
        )

    def share_keys(self, request: ShareRequest, max_bytes: int) -> list[Message]:
        """Each agent's secrets shared among its neighbours of the graph drawn from every
        advertised mask key (checked against the roster, where there is one)."""
        if request.round != self._round:
            logger.warning("round %d: no keys advertised for it", request.round)
            return []
        try:
            mask_keys, commitments, signatures = secure_rows.share_request(request)
            setup = self.keys.setup(
                request.round,
                self._planned,
                self._num_params + EXTRA,
                self._channel_keys,
                mask_keys,
                commitments,
                signatures,
            )
        except (secure_rows.RowError, SecAggError) as error:
            logger.warning("round %d: %s refuses the round: %s", request.round, self.label, error)
            return []
        shared = {}
        for k in request.agents:
            if k not in self._inputs:
                continue
            try:
                shared[k] = self.keys.agent(k).share_keys(setup)
            except SecAggError as error:
                logger.warning("round %d: agent %d takes no part: %s", request.round, k, error)
        if not shared:
            return []
        agents = sorted(shared)
        width = max(len(shares.sealed) for shares in shared.values())
        own_keys = np.zeros((len(agents), KEY_BYTES), dtype=np.uint8)
        recipients = np.full((len(agents), width), -1, dtype=np.int64)
        sealed = np.zeros((len(agents), width, SEALED_BYTES), dtype=np.uint8)
        for i, k in enumerate(agents):
            shares = shared[k]
            own_keys[i] = np.frombuffer(shares.mask_key, dtype=np.uint8)
            for j, (v, box) in enumerate(sorted(shares.sealed.items())):
                recipients[i, j] = v
                sealed[i, j] = np.frombuffer(box, dtype=np.uint8)
        per = _rows_per_message(max_bytes, self._num_params, KEY_BYTES + width * (8 + SEALED_BYTES))
        return _in_messages(
            KeyShares,
            request.round,
            agents,
            per,
            mask_keys=own_keys,
            recipients=recipients,
            sealed=sealed,
        )

    def mask(self, request: MaskRequest, max_bytes: int) -> list[Message]:
        """Each agent's contribution, masked with its neighbours that shared keys."""
        done, rows = [], []
        for i, k in enumerate(request.agents):
            if request.round != self._round or k not in self._inputs:
                logger.warning("round %d: no input of agent %d to mask", request.round, k)
                continue
            agent = self.keys.agent(k)
            try:
                keys, sealed = secure_rows.mask_request(request, i)
                masked = agent.mask(request.round, self._inputs[k], keys, sealed)
            except (secure_rows.RowError, SecAggError) as error:
                logger.warning("round %d: agent %d drops out: %s", request.round, k, error)
                continue
            unreadable = agent.unreadable(request.round)
            if unreadable:
                logger.warning(
                    "round %d: the shares agent(s) %s sealed for agent %d do not open: they "
                    "count as dropped out for its shares",
                    request.round,
                    ", ".join(map(str, sorted(unreadable))),
                    k,
                )
            done.append(k)
            rows.append(masked.view(np.int64))
        if not done:
            return []
        masked_rows = np.stack(rows)
        stats = UpdateColumns.of([self._stats[k] for k in done])
        per = _rows_per_message(max_bytes, self._num_params, 8 * masked_rows.shape[1] + 3 * 1024)
        return _in_messages(MaskedUpdate, request.round, done, per, masked=masked_rows, stats=stats)

    def reveal(self, request: UnmaskRequest, max_bytes: int) -> list[Message]:
        """Each agent's shares of its dropped neighbours' mask keys and of its included
        neighbours' self-mask seeds."""
        answers: dict[int, dict] = {}
        for k in request.agents:
            try:
                answers[k] = self.keys.agent(k).reveal(
                    request.round, request.dropped, request.included
                )
            except (SecAggError, PeerDataError) as error:
                logger.warning("round %d: agent %d reveals nothing: %s", request.round, k, error)
        if not answers:
            return []
        done = sorted(answers)
        width = max(len(a) for a in answers.values())
        owners = np.full((len(done), width), -1, dtype=np.int64)
        kinds = np.zeros((len(done), width), dtype=np.uint8)
        shares = np.zeros((len(done), width, SHARE_BYTES), dtype=np.uint8)
        for i, k in enumerate(done):
            for j, (owner, (kind, share)) in enumerate(sorted(answers[k].items())):
                owners[i, j], kinds[i, j] = owner, int(kind)
                shares[i, j] = np.frombuffer(share, dtype=np.uint8)
        per = _rows_per_message(max_bytes, self._num_params, width * (9 + SHARE_BYTES))
        return _in_messages(
            Unmasking, request.round, done, per, owners=owners, kinds=kinds, shares=shares
        )


def _in_messages(
    kind: Callable[..., Message], round_index: int, agents: list[int], per: int, **rows: Any
) -> list[Message]:
    """One answer of ``kind`` per ``per`` of ``agents``, every array (or columns) in ``rows``
    cut alike: row i is agent ``agents[i]``'s."""
    return [
        kind(
            round=round_index,
            agents=agents[start : start + per],
            **{name: value[start : start + per] for name, value in rows.items()},
        )
        for start in range(0, len(agents), per)
    ]


def _rows_per_message(max_bytes: int, num_params: int, row_bytes: int) -> int:
    """Rows of ``row_bytes`` each that fit one message of a run of ``num_params`` parameters
    (the cap the server computes alike), one at least and at most ``MAX_BATCH_ANSWERS``."""
    room = batch_message_cap(max_bytes, num_params) - MAX_HEADER_BYTES - 4096
    return max(1, min(MAX_BATCH_ANSWERS, room // max(row_bytes, 1)))


def _raiser(cancel: threading.Event) -> Callable[[], None]:
    """Called between local iterations: raises :class:`Cancelled` once ``cancel`` is set."""

    def interrupt() -> None:
        if cancel.is_set():
            raise Cancelled

    return interrupt


def _sleep_unless(cancel: threading.Event, seconds: float) -> None:
    if cancel.wait(seconds):
        raise Cancelled


def _chunks(agents: Sequence[int], size: int) -> list[list[int]]:
    return [list(agents[i : i + size]) for i in range(0, len(agents), size)]
