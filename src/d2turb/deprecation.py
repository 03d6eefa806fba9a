"""Deprecated names: each warns once per process (``DeprecationWarning``), then stays silent.

``warn_once(old, message)`` is the one place that warns; ``reset()`` forgets what has warned (tests)."""

from __future__ import annotations

import warnings

_warned: set[str] = set()


def warn_once(old: str, message: str, stacklevel: int = 3) -> None:
    """Warn ``message`` as a ``DeprecationWarning`` the first time ``old`` is used in this process."""
    if old in _warned:
        return
    _warned.add(old)
    warnings.warn(message, DeprecationWarning, stacklevel=stacklevel)


def reset() -> None:
    """Forget which deprecated names have warned (each warns again once)."""
    _warned.clear()
