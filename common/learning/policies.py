"""Stochastic policies π_θ(a|s) and the flat parameter vector θ the server averages.

Every policy offers two things, in torch:

- :meth:`Policy.log_prob` — batched, differentiable log π_θ(a|s) over any leading shape; the
  estimators differentiate it once per batch of trajectories;
- :meth:`Policy.act` — actions from uniforms the caller draws (the engine's counter-based
  streams), so a trajectory is the same in any process and on any device.

The engine evaluates them for many agents' θ at once (:meth:`Policy.log_prob_with`,
:meth:`Policy.act_with` with parameters that carry a leading row dimension).
"""

from __future__ import annotations

import abc
import importlib
import importlib.metadata
import itertools
from collections.abc import Callable, Sequence
from typing import ClassVar, Literal

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torch.func import functional_call

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.policy import LOG_STDS, PolicyConfig
from fedhpg.envs.spaces import is_image

Params = dict[str, torch.Tensor]
"""Parameter name → tensor: a policy's own (``named_parameters``), or several agents' at once
with a leading row dimension [A, *shape] (what the engine passes)."""


class Policy(nn.Module, abc.ABC):
    """A parameterised stochastic policy.

    The contract a custom policy (``policy.name``) keeps: θ is ``parameters()`` in their
    order, float32 (the server averages the flat vector); :meth:`log_prob` is differentiable
    in θ; :meth:`act` draws every random number from the uniforms it is handed (so runs are
    reproducible in any process and on any device). Build it deterministically from
    ``torch``'s RNG: every process seeds it with the run seed.

    The engine evaluates many agents' θ at once through :meth:`log_prob_with` and
    :meth:`act_with`, which take the parameters explicitly. By default they call the module
    under ``torch.func`` (the engine vmaps them over agents); a policy whose maths broadcast
    over a leading row dimension of its parameters says so with ``rows_batched = True`` and
    is then called with all rows in one go (the built-in policies do).
    """

    rows_batched: ClassVar[bool] = False
    """Whether :meth:`log_prob_with` / :meth:`act_with` accept row-batched parameters
    [A, *shape] with inputs [A, R, ...] (else the engine vmaps them over rows)."""

    def own_params(self) -> Params:
        return dict(self.named_parameters())

    def log_prob_with(self, params: Params, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """log π(act | obs) under ``params``."""
        return functional_call(self, params, (obs, act))

    def act_with(
        self, params: Params, obs: torch.Tensor, noise: torch.Tensor | None
    ) -> torch.Tensor:
        """:meth:`act` under ``params``."""
        return functional_call(
            _Acting(self), {f"policy.{k}": v for k, v in params.items()}, (obs, noise)
        )

    @abc.abstractmethod
    def log_prob(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """log π_θ(act | obs), shape = the leading shape shared by ``obs`` and ``act``."""

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.log_prob(obs, act)

    noise_size: int = 1
    """Uniforms in [0, 1) one decision consumes (:meth:`act`'s ``noise`` last dimension)."""

    @abc.abstractmethod
    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        """Actions for ``obs`` [..., *obs_shape] from ``noise`` [..., noise_size] uniforms in
        [0, 1) (every random number comes from there), or the greedy ones where ``noise`` is
        None."""

    @property
    def num_params(self) -> int:
        return sum(p.numel() for p in self.parameters())


class _Acting(nn.Module):
    """A policy's ``act`` as a module call (what ``functional_call`` calls)."""

    def __init__(self, policy: Policy) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        return self.policy.act(obs, noise)


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """x Wᵀ + b for one layer [out, in] or rows of layers [A, out, in] (x [A, R, in])."""
    return torch.matmul(x, weight.transpose(-1, -2)) + bias.unsqueeze(-2)


def mlp_with(params: Params, prefix: str, depth: int, x: torch.Tensor) -> torch.Tensor:
    """The tanh MLP of :func:`_mlp` (``depth`` Linear layers under ``prefix``) under
    ``params``, for one θ or rows of θ."""
    for i in range(depth):
        x = linear(x, params[f"{prefix}.{2 * i}.weight"], params[f"{prefix}.{2 * i}.bias"])
        if i < depth - 1:
            x = torch.tanh(x)
    return x


def categorical_log_prob(logits: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    """log softmax(logits)[act]: logits [..., n], act [...] → [...]."""
    log_pi = torch.log_softmax(logits, dim=-1)
    return log_pi.gather(-1, act.long().unsqueeze(-1)).squeeze(-1)


def categorical_act(logits: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
    """Draw from softmax(logits) by inverting its CDF with one uniform (``noise[..., 0]``);
    the argmax where ``noise`` is None. The last action is never past the end: rounding in
    the CDF's last entry cannot yield an action beyond it."""
    if noise is None:
        return logits.argmax(dim=-1)
    weights = torch.exp(logits - logits.max(dim=-1, keepdim=True).values)
    cumulative = weights.cumsum(dim=-1)
    thresholds = noise[..., :1] * cumulative[..., -1:]
    return (thresholds > cumulative[..., :-1]).sum(dim=-1)


def _last_linear(net: nn.Sequential) -> nn.Linear:
    layer = net[-1]
    assert isinstance(layer, nn.Linear)
    return layer


class _Categorical(Policy):
    """A softmax over the logits :meth:`_logits` computes from the parameters."""

    @abc.abstractmethod
    def _logits(self, params: Params, obs: torch.Tensor) -> torch.Tensor: ...

    def log_prob_with(self, params: Params, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return categorical_log_prob(self._logits(params, obs), act)

    def act_with(
        self, params: Params, obs: torch.Tensor, noise: torch.Tensor | None
    ) -> torch.Tensor:
        return categorical_act(self._logits(params, obs), noise)


class TabularSoftmaxPolicy(_Categorical):
    """π(a|s) = softmax(θ[s])_a for discrete states; θ starts at zero (uniform policy)."""

    def __init__(self, *, num_states: int, num_actions: int) -> None:
        super().__init__()
        self.logits = nn.Parameter(torch.zeros(num_states, num_actions))

    rows_batched = True

    def _logits(self, params: Params, obs: torch.Tensor) -> torch.Tensor:
        """θ[s] for every state of ``obs`` [..., R] ([A, S, n] rows with obs [A, R])."""
        table = params["logits"]
        index = obs.long().unsqueeze(-1)
        return torch.take_along_dim(table, index, dim=-2)

    def log_prob(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.log_prob_with(self.own_params(), obs.reshape(-1), act.reshape(-1)).reshape(
            obs.shape
        )

    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        return self.act_with(
            self.own_params(), obs.reshape(-1), None if noise is None else noise.reshape(-1, 1)
        ).reshape(obs.shape)


def _mlp(sizes: Sequence[int], activation: type[nn.Module] = nn.Tanh) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(n_in, n_out))
        if i < len(sizes) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


class MLPCategoricalPolicy(_Categorical):
    """Box observations, discrete actions: logits = MLP(s) with tanh hidden layers."""

    def __init__(self, *, obs_dim: int, num_actions: int, hidden: Sequence[int] = (64, 64)) -> None:
        super().__init__()
        self.net = _mlp([obs_dim, *hidden, num_actions])
        self.depth = len(hidden) + 1
        with torch.no_grad():  # small last layer: a near-uniform initial policy
            _last_linear(self.net).weight.mul_(0.01)
            _last_linear(self.net).bias.zero_()

    rows_batched = True

    def _logits(self, params: Params, obs: torch.Tensor) -> torch.Tensor:
        return mlp_with(params, "net", self.depth, obs.float())

    def log_prob(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.log_prob_with(self.own_params(), obs, act)

    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        return self.act_with(self.own_params(), obs, noise)


class MLPMultiCategoricalPolicy(_Categorical):
    """Box observations, several discrete choices per step (MultiDiscrete, MultiBinary): one
    independent softmax per component over its ``nvec[i]`` values, logits = MLP(s) with tanh
    hidden layers. log π(a|s) sums the components'; each component is drawn from its own
    uniform (``noise_size`` = the number of components) as :func:`categorical_act` draws. A
    MultiBinary action is the case ``nvec`` = 2, …, 2: a Bernoulli per component."""

    slots: torch.Tensor
    """Where each entry of the [components, width] grid of logits is in the MLP's output."""
    padding: torch.Tensor
    """[components, width]: True past a component's last value (its logit is −∞)."""
    start: torch.Tensor
    """[components]: each component's first value (MultiDiscrete's ``start``)."""

    def __init__(
        self,
        *,
        obs_dim: int,
        nvec: Sequence[int],
        start: Sequence[int] | None = None,
        hidden: Sequence[int] = (64, 64),
    ) -> None:
        super().__init__()
        sizes = [int(n) for n in nvec]
        if not sizes or min(sizes) < 1:
            raise ValueError(f"every component needs at least one value, got nvec={sizes}")
        self.components, self.width = len(sizes), max(sizes)
        self.net = _mlp([obs_dim, *hidden, sum(sizes)])
        self.depth = len(hidden) + 1
        with torch.no_grad():  # small last layer: a near-uniform initial policy
            _last_linear(self.net).weight.mul_(0.01)
            _last_linear(self.net).bias.zero_()
        # component i's logits at slots [i, :nvec[i]] of a [components, width] grid; the
        # rest padded with −∞ (probability 0: never drawn, never the argmax)
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        columns = np.arange(self.width)
        padding = columns[None, :] >= np.asarray(sizes)[:, None]
        slots = np.where(padding, 0, offsets[:, None] + columns[None, :])
        self.register_buffer("slots", torch.as_tensor(slots.reshape(-1)), persistent=False)
        self.register_buffer("padding", torch.as_tensor(padding), persistent=False)
        first = torch.as_tensor(np.zeros(len(sizes)) if start is None else np.asarray(start))
        self.register_buffer("start", first.long(), persistent=False)

    rows_batched = True

    @property
    def noise_size(self) -> int:  # type: ignore[override]
        return self.components

    def _logits(self, params: Params, obs: torch.Tensor) -> torch.Tensor:
        """[..., components, width]."""
        flat = mlp_with(params, "net", self.depth, obs.float())
        grid = flat.index_select(-1, self.slots).unflatten(-1, (self.components, self.width))
        return grid.masked_fill(self.padding, float("-inf"))

    def log_prob_with(self, params: Params, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return categorical_log_prob(self._logits(params, obs), act.long() - self.start).sum(-1)

    def act_with(
        self, params: Params, obs: torch.Tensor, noise: torch.Tensor | None
    ) -> torch.Tensor:
        per_component = None if noise is None else noise.unsqueeze(-1)
        return categorical_act(self._logits(params, obs), per_component) + self.start

    def log_prob(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.log_prob_with(self.own_params(), obs, act)

    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        return self.act_with(self.own_params(), obs, noise)


LogStdMode = Literal["state_independent", "state_dependent"]


def gaussian_log_prob(mean: torch.Tensor, log_std: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    """log N(act; mean, diag exp(log_std)²), summed over the last dimension."""
    z = (act.float() - mean) / log_std.exp()
    per_dim = -0.5 * z.pow(2) - log_std - 0.5 * float(np.log(2.0 * np.pi))
    return per_dim.sum(dim=-1)


def gaussian_act(
    mean: torch.Tensor, log_std: torch.Tensor, noise: torch.Tensor | None
) -> torch.Tensor:
    """mean + σ·z, z a standard normal per dimension from ``noise`` by inverting its CDF
    (the uniform kept off 0 and 1); the mean where ``noise`` is None."""
    if noise is None:
        return mean
    z = torch.special.ndtri(noise.double().clamp(2.0**-54, 1.0 - 2.0**-53)).to(mean.dtype)
    return mean + log_std.exp() * z


class GaussianMLPPolicy(Policy):
    """Continuous actions: a ~ N(μ_θ(s), diag σ²).

    ``log_std="state_independent"`` learns one log σ per action dimension (the usual choice
    for policy gradient on locomotion); ``"state_dependent"`` adds a second head so σ depends
    on s. log σ is clamped to [-5, 2] so the score function stays bounded (Assumption 2).
    Actions are not squashed: the batch envs clip them to the action bounds before the env and
    its action cost (envs/gym_adapter.py); the log-probability is that of the raw sample.
    """

    LOG_STD_MIN = -5.0
    LOG_STD_MAX = 2.0

    def __init__(
        self,
        *,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int] = (64, 64),
        log_std: LogStdMode = "state_independent",
        init_log_std: float = -0.5,
    ) -> None:
        super().__init__()
        self.mode: LogStdMode = log_std
        self.mean_net = _mlp([obs_dim, *hidden, act_dim])
        self.depth = len(hidden) + 1
        with torch.no_grad():
            _last_linear(self.mean_net).weight.mul_(0.01)
            _last_linear(self.mean_net).bias.zero_()
        if log_std == "state_independent":
            self.log_std = nn.Parameter(torch.full((act_dim,), float(init_log_std)))
        elif log_std == "state_dependent":
            self.log_std_net = _mlp([obs_dim, *hidden, act_dim])
            with torch.no_grad():
                _last_linear(self.log_std_net).weight.mul_(0.01)
                _last_linear(self.log_std_net).bias.fill_(float(init_log_std))
        else:
            raise ValueError(
                f"log_std must be 'state_independent' or 'state_dependent', got {log_std!r}"
            )

    rows_batched = True

    def _mean_and_log_std_with(
        self, params: Params, obs: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        obs = obs.float()
        mean = mlp_with(params, "mean_net", self.depth, obs)
        if self.mode == "state_independent":
            raw = (
                params["log_std"].unsqueeze(-2)
                if params["log_std"].dim() > 1
                else params["log_std"]
            )
        else:
            raw = mlp_with(params, "log_std_net", self.depth, obs)
        return mean, raw.clamp(self.LOG_STD_MIN, self.LOG_STD_MAX).expand_as(mean)

    def _mean_and_log_std(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self._mean_and_log_std_with(self.own_params(), obs)

    def log_prob_with(self, params: Params, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        mean, log_std = self._mean_and_log_std_with(params, obs)
        return gaussian_log_prob(mean, log_std, act)

    def act_with(
        self, params: Params, obs: torch.Tensor, noise: torch.Tensor | None
    ) -> torch.Tensor:
        return gaussian_act(*self._mean_and_log_std_with(params, obs), noise)

    def log_prob(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.log_prob_with(self.own_params(), obs, act)

    @property
    def noise_size(self) -> int:  # type: ignore[override]
        return int(_last_linear(self.mean_net).out_features)

    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        return self.act_with(self.own_params(), obs, noise)


class CNNPolicy(Policy):
    """Image observations (a 3-D uint8 Box, channels last or first): two strided ReLU
    convolutions (8 filters 8×8 stride 4, 16 filters 4×4 stride 2: a 96×96 image becomes 1,600
    features), then ``head``, the MLP policy the action space takes, on those features.

    The convolutions' parameters come first in θ, the head's after them. Its maths are the
    head's on the features, so every head keeps its contract (log π differentiable, actions
    from the caller's uniforms); the engine vmaps it over agents (``rows_batched`` False).
    """

    def __init__(self, *, image_shape: Sequence[int], head: Callable[[int], Policy]) -> None:
        super().__init__()
        shape = tuple(int(n) for n in image_shape)
        if len(shape) != 3:
            raise ValueError(f"an image is height × width × channels, got shape {shape}")
        self.channels_last = shape[-1] <= shape[0]
        channels, height, width = (shape[2], *shape[:2]) if self.channels_last else shape
        self.image_shape = shape
        self.conv = nn.Sequential(
            nn.Conv2d(channels, 8, kernel_size=8, stride=4),
            nn.ReLU(),
            nn.Conv2d(8, 16, kernel_size=4, stride=2),
            nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            features = int(self.conv(torch.zeros(1, channels, height, width)).shape[-1])
        self.head = head(features)

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        """[..., *image_shape] uint8 → [..., features]; pixels scaled to [0, 1]."""
        leading = obs.shape[:-3]
        images = obs.reshape(-1, *self.image_shape).float() / 255.0
        if self.channels_last:
            images = images.permute(0, 3, 1, 2)
        return self.conv(images).reshape(*leading, -1)

    @property
    def noise_size(self) -> int:  # type: ignore[override]
        return int(self.head.noise_size)

    def log_prob(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.head.log_prob(self.features(obs), act)

    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        return self.head.act(self.features(obs), noise)


PolicyFactory = Callable[[gym.Space, gym.Space, PolicyConfig], Policy]
"""``factory(observation_space, action_space, config) -> Policy``: a Policy subclass whose
``__init__`` takes these three arguments is one."""

POLICY_ENTRY_POINTS = "fedhpg.policies"
"""Entry-point group through which an installed package offers policies by name."""

AUTO_POLICY = "auto"


def _tabular(observation_space: gym.Space, action_space: gym.Space, _: PolicyConfig) -> Policy:
    if not (
        isinstance(observation_space, gym.spaces.Discrete)
        and isinstance(action_space, gym.spaces.Discrete)
    ):
        raise ValueError("policy 'tabular' needs Discrete observations and actions")
    return TabularSoftmaxPolicy(
        num_states=int(observation_space.n), num_actions=int(action_space.n)
    )


def _box_dim(observation_space: gym.Space, policy: str | None = None) -> int:
    if not isinstance(observation_space, gym.spaces.Box) or len(observation_space.shape) != 1:
        if policy is not None:
            raise ValueError(
                f"policy {policy!r} needs 1-D Box observations, got {observation_space}"
            )
        raise ValueError(
            f"unsupported observation space {observation_space}: need Discrete, a 1-D Box or "
            "an image (a 3-D uint8 Box)"
        )
    return int(observation_space.shape[0])


def _features_space(size: int) -> gym.spaces.Box:
    return gym.spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)


def _mlp_categorical(
    observation_space: gym.Space, action_space: gym.Space, config: PolicyConfig
) -> Policy:
    obs_dim = _box_dim(observation_space, "mlp_categorical")
    if not isinstance(action_space, gym.spaces.Discrete):
        raise ValueError(f"policy 'mlp_categorical' needs Discrete actions, got {action_space}")
    return MLPCategoricalPolicy(
        obs_dim=obs_dim, num_actions=int(action_space.n), hidden=config.hidden
    )


def _gaussian_mlp(
    observation_space: gym.Space, action_space: gym.Space, config: PolicyConfig
) -> Policy:
    obs_dim = _box_dim(observation_space, "gaussian_mlp")
    if not isinstance(action_space, gym.spaces.Box) or len(action_space.shape) != 1:
        raise ValueError(f"policy 'gaussian_mlp' needs 1-D Box actions, got {action_space}")
    if config.log_std not in LOG_STDS:
        raise ValueError(
            "policy.log_std must be 'state_independent' or 'state_dependent', "
            f"got {config.log_std!r}"
        )
    return GaussianMLPPolicy(
        obs_dim=obs_dim,
        act_dim=int(action_space.shape[0]),
        hidden=config.hidden,
        log_std=config.log_std,  # type: ignore[arg-type]
        init_log_std=config.init_log_std,
    )


def _mlp_multi_categorical(
    observation_space: gym.Space, action_space: gym.Space, config: PolicyConfig
) -> Policy:
    obs_dim = _box_dim(observation_space, "mlp_multi_categorical")
    if not isinstance(action_space, gym.spaces.MultiDiscrete) or action_space.nvec.ndim != 1:
        raise ValueError(
            f"policy 'mlp_multi_categorical' needs 1-D MultiDiscrete actions, got {action_space}"
        )
    return MLPMultiCategoricalPolicy(
        obs_dim=obs_dim,
        nvec=action_space.nvec.tolist(),
        start=action_space.start.tolist(),
        hidden=config.hidden,
    )


def _mlp_multi_binary(
    observation_space: gym.Space, action_space: gym.Space, config: PolicyConfig
) -> Policy:
    obs_dim = _box_dim(observation_space, "mlp_multi_binary")
    if not isinstance(action_space, gym.spaces.MultiBinary) or len(action_space.shape) != 1:
        raise ValueError(
            f"policy 'mlp_multi_binary' needs 1-D MultiBinary actions, got {action_space}"
        )
    components = int(action_space.shape[0])
    return MLPMultiCategoricalPolicy(obs_dim=obs_dim, nvec=[2] * components, hidden=config.hidden)


def _cnn(observation_space: gym.Space, action_space: gym.Space, config: PolicyConfig) -> Policy:
    if not is_image(observation_space):
        raise ValueError(
            f"policy 'cnn' needs image observations (a 3-D uint8 Box), got {observation_space}"
        )
    head_name = _auto_name(_features_space(1), action_space)

    def head(size: int) -> Policy:
        return POLICIES[head_name](_features_space(size), action_space, config)

    return CNNPolicy(image_shape=observation_space.shape or (), head=head)


MLP_CATEGORICAL = "mlp_categorical"
POLICIES: dict[str, PolicyFactory] = {
    "tabular": _tabular,
    MLP_CATEGORICAL: _mlp_categorical,
    "gaussian_mlp": _gaussian_mlp,
    "mlp_multi_categorical": _mlp_multi_categorical,
    "mlp_multi_binary": _mlp_multi_binary,
    "cnn": _cnn,
}


def register_policy(name: str) -> Callable[[PolicyFactory], PolicyFactory]:
    """Decorator: ``@register_policy("mine")`` on a Policy subclass (or a factory) taking
    ``(observation_space, action_space, config)``; then ``policy.name=mine`` picks it."""

    def add(factory: PolicyFactory) -> PolicyFactory:
        known = POLICIES.get(name)
        if name == AUTO_POLICY or (known is not None and known is not factory):
            raise ValueError(f"policy {name!r} is already registered")
        POLICIES[name] = factory
        return factory

    return add


def _auto_name(observation_space: gym.Space, action_space: gym.Space) -> str:
    """The built-in policy for the spaces: tabular for Discrete observations and actions, a
    CNN for images, else the MLP the action space takes (categorical, multi-categorical,
    Bernoulli or Gaussian)."""
    if isinstance(observation_space, gym.spaces.Discrete) and isinstance(
        action_space, gym.spaces.Discrete
    ):
        return "tabular"
    if isinstance(observation_space, gym.spaces.Discrete):
        raise ValueError(
            f"Discrete observations take Discrete actions (a table of logits per state), got "
            f"{action_space}"
        )
    if is_image(observation_space):
        return "cnn"
    _box_dim(observation_space)
    if isinstance(action_space, gym.spaces.Discrete):
        return "mlp_categorical"
    if isinstance(action_space, gym.spaces.MultiDiscrete) and action_space.nvec.ndim == 1:
        return "mlp_multi_categorical"
    if isinstance(action_space, gym.spaces.MultiBinary) and len(action_space.shape) == 1:
        return "mlp_multi_binary"
    if isinstance(action_space, gym.spaces.Box) and len(action_space.shape) == 1:
        return "gaussian_mlp"
    raise ValueError(
        f"unsupported action space {action_space}: need Discrete, a 1-D Box, a 1-D "
        "MultiDiscrete or a 1-D MultiBinary"
    )


def check_spaces(
    config: PolicyConfig, observation_space: gym.Space, action_space: gym.Space
) -> None:
    """ValueError where ``policy.name=auto`` finds no built-in policy for the spaces (a
    policy named by the user is checked when it is built)."""
    if config.name == AUTO_POLICY:
        _auto_name(observation_space, action_space)


def resolve_policy(name: str) -> PolicyFactory:
    """A registered name, one offered by an installed package (entry-point group
    ``fedhpg.policies``), or a dotted path ``package.module:Class``; else a ConfigError."""
    factory = POLICIES.get(name)
    if factory is None and ":" in name:
        factory = _import_dotted(name)
    if factory is None:
        factory = _from_entry_points(name)
    if factory is None:
        raise ConfigError(
            "policy.name",
            f"no policy {name!r}; known: {', '.join([AUTO_POLICY, *sorted(POLICIES)])} (or "
            "a dotted path package.module:Class, or a plugin that registers one)",
        )
    return factory


def _import_dotted(path: str) -> PolicyFactory:
    module_name, _, attribute = path.partition(":")
    try:
        found = getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as error:
        raise ConfigError("policy.name", f"cannot import {path!r}: {error}") from None
    if not callable(found):
        raise ConfigError("policy.name", f"{path!r} is not a class or a factory")
    return found


def _from_entry_points(name: str) -> PolicyFactory | None:
    for entry in importlib.metadata.entry_points(group=POLICY_ENTRY_POINTS, name=name):
        try:
            factory = entry.load()
        except (ImportError, AttributeError) as error:
            raise ConfigError(
                "policy.name", f"cannot load entry point {entry.value!r}: {error}"
            ) from None
        POLICIES.setdefault(name, factory)
        return POLICIES[name]
    return None


def make_policy(
    observation_space: gym.Space, action_space: gym.Space, config: PolicyConfig
) -> Policy:
    """The policy ``config.name`` names, built for the spaces; 'auto' = the built-in one that
    fits them (:func:`_auto_name`)."""
    name = config.name
    if name == AUTO_POLICY:
        name = _auto_name(observation_space, action_space)
    factory = resolve_policy(name)
    try:
        policy = factory(observation_space, action_space, config)
    except ConfigError:
        raise
    except ValueError as error:
        if config.name == AUTO_POLICY:  # the spaces fit no built-in policy: not a config key
            raise
        # a chosen policy that does not fit the run's spaces: the user's choice, one line
        raise ConfigError("policy.name", str(error)) from None
    if not isinstance(policy, Policy):
        raise ConfigError(
            "policy.name",
            f"{config.name!r} built a {type(policy).__name__}, not a fedhpg Policy subclass",
        )
    return policy


def get_flat_params(policy: nn.Module) -> torch.Tensor:
    """All parameters as one detached float32 vector (the order of ``parameters()``)."""
    return torch.nn.utils.parameters_to_vector(policy.parameters()).detach().clone()


def set_flat_params(policy: nn.Module, theta: torch.Tensor | np.ndarray) -> None:
    """Load a flat vector into the policy, checking its length and finiteness."""
    vector = torch.as_tensor(theta, dtype=torch.float32)
    expected = sum(p.numel() for p in policy.parameters())
    if vector.ndim != 1 or vector.numel() != expected:
        raise ValueError(
            f"parameter vector has shape {tuple(vector.shape)}, expected ({expected},)"
        )
    if not torch.isfinite(vector).all():
        raise ValueError("parameter vector contains NaN or Inf")
    with torch.no_grad():
        torch.nn.utils.vector_to_parameters(vector, policy.parameters())


def flat_grad(loss: torch.Tensor, policy: nn.Module) -> torch.Tensor:
    """∇ loss as one flat vector in the order of ``parameters()``."""
    params = list(policy.parameters())
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    return torch.cat(
        [
            (g if g is not None else torch.zeros_like(p)).reshape(-1)
            for g, p in zip(grads, params, strict=True)
        ]
    )
