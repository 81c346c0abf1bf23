"""The one error a wrong setting raises: :class:`ConfigError`, naming the setting's key.

A leaf module (pure Python, no imports of the package) so that the config, the registries
and the vocabularies they hold can all raise it without importing one another.
"""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration value is wrong; ``key`` is its dotted path."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key
