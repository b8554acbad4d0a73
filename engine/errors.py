"""``ConfigError``, in a module of its own so that modules ``engine.config`` imports can raise it too."""

from __future__ import annotations

__all__ = ["ConfigError"]


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the field and what is allowed."""
