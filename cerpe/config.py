"""One strict merge for every plug-in configuration.

Each model or step keeps a ``default_conf`` dict (LightGlue's habit). A user's
overrides are merged into it with :func:`merge_conf`:

* nested dicts merge deeply: ``{"dense": {"stride": 4}}`` changes only the
  stride and keeps the other ``dense`` defaults;
* a key the defaults do not have is an error that lists the known ones (a typo
  must not be accepted silently);
* a default that is an empty dict (``"xfeat": {}``) is open: its keys belong to
  another plug-in, which validates them with its own ``default_conf``;
* a default of ``None`` takes any value, including a dict.

Nothing here knows about models, files or the command line.
"""
from __future__ import annotations

import copy
from typing import Any, Mapping

from .errors import CerpeError

__all__ = ["ConfigError", "merge_conf"]


class ConfigError(CerpeError, ValueError):
    """An unknown configuration key, or a dict given where a value belongs (or the reverse)."""


def merge_conf(default: Mapping[str, Any], override: Mapping[str, Any] | None, where: str = "conf") -> dict[str, Any]:
    """Deep copy of ``default`` with ``override`` merged in, strictly.

    Args:
        default: the defaults; their keys are the only ones allowed.
        override: the user's values (None or empty: the defaults).
        where: the name of this configuration in error messages, e.g.
            ``"offline backbone conf"``; nested keys are appended as ``where.key``.

    Raises:
        ConfigError: an unknown key (the message lists the known ones), or a
            mapping given for a key whose default is a plain value or the reverse.
    """
    out = copy.deepcopy(dict(default))
    if override is None:
        return out
    if not isinstance(override, Mapping):
        raise ConfigError(f"{where}: expected a mapping of options, got {type(override).__name__}")
    unknown = [k for k in override if k not in out]
    if unknown:
        known = ", ".join(sorted(map(str, out))) or "(none)"
        raise ConfigError(f"{where}: unknown option(s) {', '.join(map(repr, unknown))}; known: {known}")
    for key, value in override.items():
        base = out[key]
        path = f"{where}.{key}"
        if isinstance(base, Mapping) and base:
            if not isinstance(value, Mapping):
                raise ConfigError(f"{path}: expected a mapping of options, got {type(value).__name__}")
            out[key] = merge_conf(base, value, path)
        elif isinstance(base, Mapping):  # open: validated by the plug-in it is passed to
            if not isinstance(value, Mapping):
                raise ConfigError(f"{path}: expected a mapping of options, got {type(value).__name__}")
            out[key] = copy.deepcopy(dict(value))
        elif isinstance(value, Mapping) and base is not None:
            raise ConfigError(f"{path}: expected a single value like {base!r}, got a mapping")
        else:
            out[key] = copy.deepcopy(value)
    return out
