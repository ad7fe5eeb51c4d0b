"""The setting a run reads: its manifest loaded, and the evaluation stride the manifest asks for."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from ..runfolder.layout import RunError


def load_manifest_setting(manifest: Path) -> Any:
    """The :class:`~cerpe.scene.Setting` of ``manifest`` (a RunError if the file is missing)."""
    from .. import datasets

    if not Path(manifest).is_file():
        raise RunError(f"manifest not found: {manifest}")
    return datasets.load_setting(Path(manifest))


def evaluation_every(setting: Any, manifest: Path | None = None) -> int:
    """``evaluation.every`` of a setting (from its meta, else the manifest YAML), default 1."""
    meta = getattr(setting, "meta", {}) or {}
    if "evaluation_every" in meta:
        return int(meta["evaluation_every"])
    ev = meta.get("evaluation")
    if ev is None and manifest is not None:
        import yaml

        try:
            ev = (yaml.safe_load(Path(manifest).read_text()) or {}).get("evaluation")
        except (OSError, yaml.YAMLError):
            ev = None
    every = int((ev or {}).get("every", 1)) if isinstance(ev, dict) else int(ev or 1)
    if every < 1:
        raise RunError(f"{manifest}: evaluation.every must be >= 1, got {every}")
    return every
