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


class AliasDict(dict):
    """A dict whose deprecated keys (``aliases``: old → new) still read, warning once per old key.

    Only the new keys are stored (iteration, ``len``, ``set(d)`` and copies see one key per value); ``d[old]``,
    ``d.get(old)`` and ``old in d`` go to the new key. Subclasses set ``aliases`` and ``what`` (for the message)."""

    aliases: dict[str, str] = {}
    what = "dict"

    def __init_subclass__(cls, **kwargs):
        """Each subclass flattens like a dict for torch's pytree tools (DDP's output handling, ``tree_map``, export):
        unregistered, a dict subclass would be one opaque leaf."""
        super().__init_subclass__(**kwargs)
        from torch.utils import _pytree

        _pytree.register_pytree_node(
            cls,
            lambda d: (list(d.values()), list(d.keys())),
            lambda values, keys: cls(zip(keys, values)),
            serialized_type_name=f"{cls.__module__}.{cls.__qualname__}",
        )

    def _new(self, key):
        new = self.aliases.get(key) if isinstance(key, str) else None
        if new is not None and not dict.__contains__(self, key):
            warn_once(f"{self.what}[{key!r}]", f"{self.what}[{key!r}] is deprecated; use {self.what}[{new!r}]", 4)
            return new
        return key

    def __missing__(self, key):
        new = self._new(key)
        if new is key:
            raise KeyError(key)
        return self[new]

    def get(self, key, default=None):
        return dict.get(self, self._new(key), default)

    def __contains__(self, key) -> bool:
        new = self.aliases.get(key) if isinstance(key, str) else None
        return dict.__contains__(self, key) or (new is not None and dict.__contains__(self, new))
