"""The configuration tree a cerpe-method run was made with, read back from its ``run.json``.

``run.json`` records the resolved tree as nested dicts (``config.method_config.tree``, run format 2);
:func:`run_tree` rebuilds the :class:`~cerpe.method_config.CerpeConfig` from it, so a replay study
starts from exactly what the run used and changes only what it is asked to (dotted keys).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from cerpe import knobs
from cerpe.errors import CerpeError
from cerpe.method_config import CerpeConfig


class RunConfigError(CerpeError, ValueError):
    """A run folder whose ``run.json`` holds no configuration tree, or a bad override (names it)."""


def run_tree(run_dir: Path | str, sets: Mapping[str, Any] | None = None) -> CerpeConfig:
    """The tree of the cerpe-method run in ``run_dir``, with ``sets`` (dotted keys) applied, checked."""
    path = Path(run_dir) / "run.json"
    try:
        meta = json.loads(path.read_text())
        tree = meta["config"]["method_config"]["tree"]
    except (OSError, ValueError, KeyError, TypeError):
        raise RunConfigError(f"{path}: no config.method_config.tree (not a cerpe-method run of run format 2; "
                             f"run it again)") from None
    try:
        conf = knobs.from_dict(CerpeConfig, tree)
    except knobs.KnobError as exc:
        raise RunConfigError(f"{path}: {exc}") from None
    try:
        return conf.override(dict(sets or {}))
    except knobs.KnobError as exc:
        raise RunConfigError(f"--set: {exc}") from None
