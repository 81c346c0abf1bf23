"""Round policies: when a request's answers are complete enough to go on, or the run fails.

``wait_all`` (Algorithm 1 as written): every selected agent's answer; a dead agent is waited
for until it rejoins, up to ``server.rejoin_timeout_s``. ``deadline``: what arrived by
``server.round_deadline_s`` once at least ``server.min_agents`` answered (or as soon as every
live selected agent did). Either way ``server.round_timeout_s`` caps a request. ``buffered``
(asynchronous rounds) is not a request policy for training (server/buffered.py and, with agent
processes, server/buffered_zmq.py run it); its evaluations close once every live agent
answered (a dead agent is not waited for: the others are not held up by it either).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping

from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.configuration.vocabularies import ROUND_POLICIES
from fedhpg.server.pools import FederationError


def request_complete(
    *,
    settings: ServerConfig,
    what: str,
    expected: Collection[int],
    answered: Collection[int],
    accepted: int,
    live: Collection[int],
    absent_since: Mapping[int, float],
    elapsed_s: float,
    now: float,
    name: Callable[[int], str],
) -> bool:
    """Whether the request for ``what`` (e.g. 'round 7') may close now.

    ``expected``: the agents asked; ``answered``: those that answered (accepted or rejected);
    ``accepted``: how many answers were accepted; ``live``: registered agents;
    ``absent_since``: when each dead agent was lost. Raises FederationError when the run
    cannot go on.
    """
    pending = [k for k in expected if k not in answered]
    if not pending:
        return True
    policy = ROUND_POLICIES.get(settings.round_policy)
    if policy.quorum and accepted >= settings.min_agents:
        live_done = all(k in answered for k in expected if k in live)
        if live_done or elapsed_s >= settings.round_deadline_s:
            return True
    if policy.asynchronous and all(k in answered for k in expected if k in live):
        return True
    if policy.waits_for_every_agent:
        for index in pending:
            since = absent_since.get(index)
            if since is not None and now - since > settings.rejoin_timeout_s:
                raise FederationError(
                    f"{what}: {name(index)} died and did not rejoin within "
                    f"{settings.rejoin_timeout_s:g} s (server.rejoin_timeout_s)"
                )
    if elapsed_s > settings.round_timeout_s:
        raise FederationError(
            f"timed out after {settings.round_timeout_s:g} s (server.round_timeout_s) "
            f"waiting for {what} from {[name(k) for k in pending]}"
        )
    return False
