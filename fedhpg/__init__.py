"""fedhpg: federated policy gradient where agents differ in environment and in compute.

The package's parts are :mod:`fedhpg.server` (entry points, the round loop, strategies),
:mod:`fedhpg.agent` (the agent program), :mod:`fedhpg.common` (what both sides share: configs,
algorithms, the engine, the wire) and :mod:`fedhpg.envs` (heterogeneous environment families).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("fedhpg")
except PackageNotFoundError:  # the sources without an install
    __version__ = "0+unknown"

__all__ = ["__version__"]
