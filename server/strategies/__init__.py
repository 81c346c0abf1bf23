"""The server half of a federated method: which agents a round asks, and how their updates
become θ̃ (in the spirit of Flower's ``configure_fit`` / ``aggregate_fit``).

A strategy is one module of this package (or of a plugin) and a YAML in ``conf/strategy/``::

    @register_strategy
    class MyStrategy(Strategy[MyParams]):
        name = "mine"
        Params = MyParams            # its options, from strategy.params

        def aggregate(self, round_index, theta, result, failures) -> torch.Tensor: ...

A rule of the θ_k alone subclasses :class:`CoordinateRule` and writes ``combine(rows)`` on the
round's [K, d] matrix of updates (on ``strategy.device``: a GPU where K·d is large), without
a second matrix of that size: a rule that needs one per column (a sort) works through
:func:`by_columns`.
A strategy declares what it can take instead of being named in checks elsewhere:
:attr:`Strategy.takes` (the kind of update it aggregates, matched against what the run's
algorithm sends, :func:`sent_by`) and :attr:`Strategy.buffered` (whether it can aggregate
buffered, asynchronous rounds' updates).
``result`` is the round's accepted updates, one :class:`~fedhpg.common.records.types.RoundResult`
whose rows are in agent-index order (arrival order never changes a bit of θ̃; :func:`rows_of`
gives its θ_k as a [K, d] tensor); ``failures`` names the agents whose update was rejected,
and why. A strategy with state across rounds (fedadam's moments) returns it from
:meth:`Strategy.state`; checkpoints save it and :meth:`Strategy.restore` takes it back on
resume.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Generic, TypeVar

import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import Registry, import_plugins, parse_options
from fedhpg.common.configuration.settings.strategy import StrategyConfig
from fedhpg.common.learning.algorithms import ALGORITHMS, PARAMETERS
from fedhpg.common.learning.components import resolve_algorithm
from fedhpg.common.learning.engine.devices import device_problem
from fedhpg.common.records.types import RoundResult, SavedState
from fedhpg.server.participation import validate_participation
from fedhpg.server.tolerance import REMEDY, tolerance_shortfall

if TYPE_CHECKING:
    from fedhpg.common.learning.algorithms import Algorithm

P = TypeVar("P")


@dataclass(frozen=True, kw_only=True)
class NoParams:
    """For strategies without options."""


class Strategy(abc.ABC, Generic[P]):
    """Select the round's agents, aggregate their updates, keep state across rounds."""

    name: ClassVar[str]
    Params: ClassVar[type[Any]] = NoParams
    takes: ClassVar[str] = PARAMETERS
    """The kind of update the rule aggregates, matched against ``Algorithm.sends``:
    :data:`~fedhpg.common.learning.algorithms.PARAMETERS` (each agent's θ_k) or
    :data:`~fedhpg.common.learning.algorithms.GRADIENTS` (fedpgbr's)."""
    buffered: ClassVar[bool] = True
    """Whether it can aggregate buffered rounds' updates (``server.round_policy=buffered``:
    each from its own θ̃ version, weighted by staleness); False for a rule that needs every
    agent's update at one θ̃."""

    device = torch.device("cpu")
    """Where the rule computes (``strategy.device``)."""

    def __init__(self, params: P) -> None:
        self.params = params

    def select(self, round_index: int, agents: Sequence[int]) -> list[int]:
        """The agent indices asked to train in ``round_index``, chosen among ``agents``, those
        that participate this round (``strategy.participation``, applied first): all of them."""
        return list(agents)

    @abc.abstractmethod
    def aggregate(
        self,
        round_index: int,
        theta: torch.Tensor,
        result: RoundResult,
        failures: Mapping[str, str],
    ) -> torch.Tensor:
        """θ̃_{t+1} from θ̃_t and the accepted updates (never none)."""

    def bind(self, run: RunConfig) -> None:
        """Called once with the run before the first round, for a strategy that needs more of
        the run than its own options (fedpgbr's environment); ConfigError for a run it cannot
        serve."""

    def averaging(self) -> str | None:
        """Whether θ̃ comes from an average of the updates, which privacy can replace by a
        clipped, noisy or securely summed one: 'uniform' (each update counts once), 'weighted'
        (by the trajectories it sampled), or None for a rule that needs each update alone
        (median, trimmed mean, a filter)."""
        return None

    def from_average(
        self, round_index: int, theta: torch.Tensor, average: torch.Tensor
    ) -> torch.Tensor:
        """θ̃_{t+1} from θ̃_t and the round's average θ̄ (privacy's, in place of
        :meth:`aggregate`): θ̄ itself, for the averages."""
        return average

    def tolerance(self, rows: int) -> int | None:
        """How many of ``rows`` aggregated updates may be arbitrary (Byzantine) while each
        coordinate of θ̃ stays within the range of the honest rows' values; None: the rule
        claims no tolerance (a mean: one row moves it anywhere). A robust rule's claim holds
        per aggregated set, not per federation: with participation or a deadline it is that
        of the round's rows (:mod:`fedhpg.server.tolerance` checks it at start)."""
        return None

    def round_stats(self) -> dict[str, Any]:
        """What the strategy reports of the last :meth:`aggregate` (``metrics.jsonl``'s
        ``strategy``; nothing, for most rules)."""
        return {}

    def sampled_trajectories(self) -> int:
        """Trajectories the strategy sampled itself in the last :meth:`aggregate` (fedpgbr's
        inner loop, b·N_t); ``trajectories_per_agent`` counts them beside the agents' own,
        divided by K like theirs. 0 for a rule that only aggregates."""
        return 0

    def state(self) -> SavedState:
        """What a checkpoint must keep to continue exactly (nothing, for stateless rules)."""
        return SavedState()

    def restore(self, state: SavedState) -> None:
        """Take back what :meth:`state` returned (on resume)."""


class CoordinateRule(Strategy[P]):
    """A strategy whose θ̃ depends on the θ_k alone: :meth:`combine` maps the [K, d] matrix of
    the accepted updates (rows in agent-index order) to θ̃."""

    _aggregated: int | None = None

    def aggregate(
        self,
        round_index: int,
        theta: torch.Tensor,
        result: RoundResult,
        failures: Mapping[str, str],
    ) -> torch.Tensor:
        self._aggregated = len(result)
        return self.combine(rows_of(result).to(self.device)).cpu()

    @abc.abstractmethod
    def combine(self, rows: torch.Tensor) -> torch.Tensor:
        """θ̃ from the [K, d] matrix of updates (read it, never write it: it may be the
        received updates' own memory)."""

    def round_stats(self) -> dict[str, Any]:
        """A robust rule's last aggregated set: its rows and the arbitrary rows it tolerated."""
        rows = self._aggregated
        tolerates = self.tolerance(rows) if rows is not None else None
        if rows is None or tolerates is None:
            return {}
        return {"aggregated": rows, "tolerates": tolerates}


STRATEGIES: Registry[type[Strategy[Any]]] = Registry("strategy", "strategy.name", __name__)

S = TypeVar("S", bound=type[Strategy[Any]])


def register_strategy(cls: S) -> S:
    """Class decorator: register ``cls`` under ``cls.name``."""
    STRATEGIES.register(cls.name)(cls)
    return cls


def make_strategy(
    config: StrategyConfig, key: str = "strategy", run: RunConfig | None = None
) -> Strategy[Any]:
    """A fresh strategy from its config (bound to ``run`` where given); ConfigError naming the
    key when it is wrong."""
    cls = STRATEGIES.get(config.name)
    strategy = cls(parse_options(cls.Params, config.params, f"{key}.params"))
    strategy.device = torch.device(config.device)
    if run is not None:
        strategy.bind(run)
    return strategy


def sent_by(algorithm: Algorithm[Any, Any]) -> str:
    """What an algorithm's updates are (its ``sends``)."""
    return algorithm.sends


def check_takes(run: RunConfig, cls: type[Strategy[Any]]) -> None:
    """ConfigError unless the run's algorithm sends what the strategy ``cls`` takes."""
    algorithm, _ = resolve_algorithm(run)
    sent = sent_by(algorithm)
    if sent == cls.takes:
        return
    senders = [name for name in ALGORITHMS.names() if sent_by(ALGORITHMS.get(name)) == cls.takes]
    raise ConfigError(
        "strategy",
        f"{cls.name} aggregates {cls.takes}: it runs with an algorithm that sends them "
        f"({', '.join(f'algo={n}' for n in senders) or 'none is registered'}), not "
        f"algo={algorithm.name}, which sends {sent}",
    )


def validate_strategy(run: RunConfig) -> Strategy[Any]:
    """The server-side checks of a run config (the agents never see ``strategy``): the
    strategy built once, bound to the run and returned."""

    import_plugins(run.plugins)
    if run.strategy.device != "cpu":
        # in a fresh interpreter where this process has not used CUDA: the launcher forks
        # the server after this check
        problem = device_problem(run.strategy.device, before_fork=not torch.cuda.is_initialized())
        if problem is not None:
            raise ConfigError("strategy.device", problem)
    check_takes(run, STRATEGIES.get(run.strategy.name))
    strategy = make_strategy(run.strategy, run=run)
    validate_participation(run)
    shortfall = tolerance_shortfall(run, strategy)
    if shortfall is not None and run.strategy.tolerance_check == "refuse":
        raise ConfigError("strategy", f"{shortfall}: {REMEDY}")
    return strategy


COLUMN_BYTES = 1 << 28
"""What :func:`by_columns` lets a rule's temporaries of one slice of columns take."""


def by_columns(
    rows: torch.Tensor, rule: Callable[[torch.Tensor], torch.Tensor], budget: int = COLUMN_BYTES
) -> torch.Tensor:
    """θ̃[j] = rule(rows[:, j]) for slices of columns whose temporaries (a sort's values and
    indices: 12 bytes an entry) stay within ``budget`` bytes, into one [d] vector: a rule per
    coordinate never holds a second [K, d] matrix."""
    count, width = rows.shape
    step = max(budget // max(12 * count, 1), 1)
    out = rows.new_empty(width)
    for start in range(0, width, step):
        out[start : start + step] = rule(rows[:, start : start + step])
    return out


def rows_of(result: RoundResult) -> torch.Tensor:
    """The result's θ_k as the rows of a [K, d] tensor, in agent-index order: the result's own
    memory (a strategy reads it, never writes it), a copy only of a read-only array."""
    thetas = result.thetas
    return torch.from_numpy(thetas if thetas.flags.writeable else thetas.copy())
