"""The ``privacy`` and ``security`` sections: differential privacy, secure aggregation and
the transport's encryption (read by :mod:`fedhpg.common.privacy` and the server).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from fedhpg.common.configuration.settings.checks import (
    check_choice,
    check_int,
    check_number,
    require,
)

PRIVACY_MODES = ("none", "dp", "secagg", "dp_secagg")
BUDGET_PARTIES = ("model", "server")


@dataclass(kw_only=True)
class SecurityConfig:
    """CURVE encryption and agent authentication. Off by default: plaintext on the wire."""

    curve: bool = False
    """Encrypt every connection with CURVE and admit only agents whose public key is allowed."""
    keys_dir: str | None = None
    """Directory written by ``fedhpg-keys``: the default location of every key file below."""
    server_secret_key: str | None = None
    """Server: its secret key file; None = ``<keys_dir>/server.key_secret``."""
    allowed_keys_dir: str | None = None
    """Server: directory of allowed agent public keys, one ``<agent id>.key`` file per agent;
    None = ``<keys_dir>/allowed``."""
    server_public_key: str | None = None
    """Agent: the server's public key file; None = ``<keys_dir>/server.key``."""
    agent_secret_key: str | None = None
    """Agent: its own secret key file; None = ``<keys_dir>/<agent id>.key_secret``."""
    signing_key: str | None = None
    """Agent, secure aggregation: its secret signing key file; None =
    ``<keys_dir>/<agent id>.sign_secret``. Needed wherever a roster is."""
    signers_dir: str | None = None
    """Agent, secure aggregation: the roster of every agent's public signing key; None =
    ``<keys_dir>/signers`` where it exists. Without one, key advertisements are not signed and
    the server is trusted to relay keys unchanged."""


@dataclass(kw_only=True)
class SecAggConfig:
    """Secure aggregation: agents mask their encoded updates so that the server learns only
    the sum (docs/privacy.md)."""

    corruption: float = 0.1
    """γ: the fraction of a round's agents that may collude with the server (which may also
    deviate from the protocol) without exposing any other agent's input: the round's graph
    and threshold are derived from it (docs/privacy.md)."""
    dropout: float = 0.1
    """δ: the fraction of a round's agents that may stop answering (besides the colluders)
    with the round still completing."""
    threshold: float | None = None
    """t = ⌊threshold · k⌋ + 1 of an agent's k neighbours rebuild its secrets; None = the
    smallest t that meets ``corruption`` and ``dropout``. A value that does not meet them is
    refused, saying which would."""
    neighbours: int | None = None
    """k, the agents each one masks with and shares its secrets with (SecAgg+); None = every
    other agent up to 64 a round, beyond that the fewest that meet ``corruption`` and
    ``dropout``. Cost per agent grows with k, not with the round."""
    range: float = 1.0e4
    """Each coordinate of an update is clipped to [−range, range] before its fixed-point
    encoding (resolution about n · range / 2⁶², n the round's agents)."""


@dataclass(kw_only=True)
class PrivacyConfig:
    """Agent-level differential privacy and secure aggregation (docs/privacy.md)."""

    mode: str = "none"
    """'none'; 'dp' (each update clipped, Gaussian noise added by the server, ε accounted);
    'secagg' (the server sees only the sum of masked updates); 'dp_secagg' (both: each agent
    adds its share of the noise to its clipped update before masking)."""
    epsilon: float | None = None
    """The run's budget ε: without ``noise_multiplier``, σ is chosen so that ``rounds`` rounds
    spend exactly this; with it, the run stops before a round would exceed it. Which party's ε
    it caps: ``budget_against``."""
    budget_against: str = "model"
    """'model': ``epsilon`` caps ε against readers of the released model (and, with 'dp', of
    the run directory); 'server': with 'dp_secagg', it caps ε against the server, which picks
    and sees each round's sample (no amplification by sampling; σ calibrated as if one agent
    took part in every round)."""
    delta: float | None = None
    """δ of the guarantee; None = min(1/(10·K), 10⁻⁵) (K = agents.num_agents)."""
    noise_multiplier: float | None = None
    """σ: the noise's std over the clip C; None = calibrated from ``epsilon``."""
    clip: float = 1.0
    """C, the L2 bound of each agent's update θ_k − θ̃ (the first round's, with adaptive
    clipping)."""
    adaptive_clip: bool = False
    """Follow a quantile of the update norms (Andrew et al. 2021) instead of a fixed C."""
    target_quantile: float = 0.5
    """Adaptive clipping: the fraction of updates C should leave unclipped."""
    clip_rate: float = 0.2
    """Adaptive clipping: the geometric step η of C ← C·exp(−η(b̄ − quantile))."""
    count_std: float | None = None
    """Adaptive clipping: std of the noise on the count of unclipped updates (above σ/2);
    None = the expected agents per round / 20, or σ where that is more."""
    noise_seed: int | None = None
    """Seed the DP noise, and the sample of a sampled DP run (reproducible experiments only:
    whoever knows it can remove the noise and knows the sample, so it protects nothing);
    None = the operating system's entropy."""
    secure_noise: bool | None = None
    """Unseeded DP noise from the operating system's CSPRNG, each draw a sum of four Gaussians
    (the floating-point mitigation of Opacus's secure mode); false: numpy's PCG64 seeded from
    the operating system. None = on unless ``noise_seed`` is set."""
    secagg: SecAggConfig = field(default_factory=SecAggConfig)
    """Secure aggregation's settings ('secagg', 'dp_secagg')."""

    @property
    def secure_noise_on(self) -> bool:
        """Whether unseeded noise is drawn as :class:`~fedhpg.common.privacy.dp.SecureNoise`."""
        return self.secure_noise if self.secure_noise is not None else self.noise_seed is None


def validate_privacy(privacy: PrivacyConfig) -> None:
    check_choice(privacy.mode, "privacy.mode", PRIVACY_MODES)
    if privacy.epsilon is not None:
        check_number(privacy.epsilon, "privacy.epsilon", low=0.0, low_open=True)
    if privacy.delta is not None:
        check_number(privacy.delta, "privacy.delta", low=0.0, low_open=True)
        require(privacy.delta < 1, "privacy.delta", f"got {privacy.delta!r}, must be in (0, 1)")
    if privacy.noise_multiplier is not None:
        check_number(privacy.noise_multiplier, "privacy.noise_multiplier", low=0.0, low_open=True)
    if privacy.mode in ("dp", "dp_secagg"):
        require(
            privacy.epsilon is not None or privacy.noise_multiplier is not None,
            "privacy.epsilon",
            f"privacy.mode={privacy.mode} needs a budget ε (privacy.epsilon) or a noise "
            "multiplier (privacy.noise_multiplier)",
        )
    check_number(privacy.clip, "privacy.clip", low=0.0, low_open=True)
    require(
        isinstance(privacy.adaptive_clip, bool),
        "privacy.adaptive_clip",
        f"got {privacy.adaptive_clip!r}, must be true or false",
    )
    check_number(privacy.target_quantile, "privacy.target_quantile", low=0.0)
    require(
        privacy.target_quantile <= 1,
        "privacy.target_quantile",
        f"got {privacy.target_quantile!r}, must be in [0, 1]",
    )
    check_number(privacy.clip_rate, "privacy.clip_rate", low=0.0, low_open=True)
    if privacy.count_std is not None:
        check_number(privacy.count_std, "privacy.count_std", low=0.0, low_open=True)
    if privacy.noise_seed is not None:
        check_int(privacy.noise_seed, "privacy.noise_seed", low=0)
    require(
        not (privacy.secure_noise and privacy.noise_seed is not None),
        "privacy.secure_noise",
        f"got true with privacy.noise_seed={privacy.noise_seed}: seeded noise is numpy's, "
        "reproducible and known to whoever knows the seed; drop one of them",
    )
    check_choice(privacy.budget_against, "privacy.budget_against", BUDGET_PARTIES)
    require(
        privacy.budget_against == "model" or privacy.mode == "dp_secagg",
        "privacy.budget_against",
        f"got 'server' with privacy.mode={privacy.mode}: only dp_secagg's noise holds against "
        "the server (with 'dp' it is trusted: it sees every update); use 'model', or "
        "privacy=dp_secagg",
    )
    secagg = privacy.secagg
    if secagg.threshold is not None:
        check_number(secagg.threshold, "privacy.secagg.threshold", low=0.0, low_open=True)
        require(
            secagg.threshold < 1,
            "privacy.secagg.threshold",
            f"got {secagg.threshold!r}, must be in (0, 1)",
        )
    check_number(secagg.corruption, "privacy.secagg.corruption", low=0.0)
    require(
        secagg.corruption < 0.5,
        "privacy.secagg.corruption",
        f"got {secagg.corruption!r}, must be in [0, 0.5): a server with half the agents "
        "colluding learns every input from their shares",
    )
    check_number(secagg.dropout, "privacy.secagg.dropout", low=0.0)
    require(
        secagg.corruption + secagg.dropout < 1,
        "privacy.secagg.dropout",
        f"got {secagg.dropout!r}; corruption + dropout must be below 1",
    )
    if secagg.neighbours is not None:
        check_int(secagg.neighbours, "privacy.secagg.neighbours", low=2)
    check_number(secagg.range, "privacy.secagg.range", low=0.0, low_open=True)
