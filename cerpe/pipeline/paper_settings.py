"""``cerpe paper``'s settings: every manifest as a Table I column group, and where a profile's outputs go.

Enabled manifests are loaded (synthetic settings are generated on demand with the chosen suite:
:func:`discover_settings` writes a derived manifest with the suite replaced); disabled ones are
listed as "not supplied" with the manifest to fill; real datasets are skipped in the fixture suite.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..atomicio import atomic_write_text
from ..errors import CerpeError

ROOT = Path(__file__).resolve().parents[2]
MODELS: tuple[str, ...] = ("offline", "paper")  # backbone.models of the CERPE runs
SYNTHETIC_ORDER = ("cad-intersection", "indoor-team")


class PaperError(CerpeError, ValueError):
    """The paper build cannot proceed (no manifests folder, unknown profile, failed notebook)."""


@dataclass
class SettingEntry:
    """One column group of Table I.

    ``status`` is ``ok``, ``not supplied`` (disabled manifest), ``skipped`` (a
    real dataset in the fixture profile) or ``error`` (with ``detail``).
    """

    name: str
    manifest: Path
    status: str
    detail: str = ""
    run_manifest: Path | None = None
    world: str = ""
    setting: Any = None


def layout(profile: str, models: str, root: Path) -> dict[str, Path]:
    if profile == "fixture":
        base = root / "build" / "fixture"
        return {"runs": base / "runs" / models, "figures": base / "figures", "tables": base / "tables",
                "notebooks": base / "notebooks", "manifests": base / "manifests"}
    if profile == "paper-default":
        runs = root / "build" / "runs" if models == "offline" else root / "build" / f"runs-{models}"
        return {"runs": runs, "figures": root / "figures", "tables": root / "tables",
                "notebooks": root / "build" / "notebooks", "manifests": root / "build" / "manifests" / profile}
    raise PaperError(f"unknown notebook profile {profile!r}; use 'fixture' or 'paper-default'")


def _derived_manifest(man: Any, suite: str, out_dir: Path) -> Path:
    """A synthetic manifest with its suite replaced, paths made absolute (original untouched)."""
    import yaml

    raw = dict(man.raw)
    if raw.get("suite", "paper-default") == suite:
        return Path(man.path)
    raw["suite"] = suite
    if raw.get("cache_dir"):
        raw["cache_dir"] = str(man.resolve(raw["cache_dir"]))
    if man.data_root is not None:
        raw["data_root"] = str(man.data_root)
    out = out_dir / f"{man.name}.yaml"
    atomic_write_text(out, yaml.safe_dump(raw, sort_keys=False))
    return out


def discover_settings(profile: str, suite: str, manifests_dir: Path, derived_dir: Path,
                      load: bool = True) -> list[SettingEntry]:
    """Every manifest as a Table I column group, synthetic ones first; loads enabled settings."""
    from ..datasets import ManifestError, disabled_reason, find_manifests, load_setting

    if not manifests_dir.is_dir():
        raise PaperError(f"manifest folder not found: {manifests_dir}")
    entries = []
    for man in find_manifests(manifests_dir):
        world = str(man.raw.get("world", "")) if man.adapter == "synthetic" else ""
        e = SettingEntry(man.name, Path(man.path), "ok", world=world)
        if not man.enabled:
            where = man.path.relative_to(ROOT) if man.path.is_relative_to(ROOT) else man.path
            e.status, e.detail = "not supplied", (disabled_reason(man) if man.enabled_if_present
                                                  else f"fill {where} and set enabled: true")
        elif man.adapter != "synthetic" and suite == "fixture":
            e.status, e.detail = "skipped", "real datasets are not run in the fixture suite"
        else:
            e.run_manifest = _derived_manifest(man, suite, derived_dir) if man.adapter == "synthetic" else Path(man.path)
            if load:
                try:
                    e.setting = load_setting(e.run_manifest)
                except ManifestError as exc:
                    e.status, e.detail = "error", str(exc)
        entries.append(e)
    key = lambda e: (0, SYNTHETIC_ORDER.index(e.world)) if e.world in SYNTHETIC_ORDER else (1, 0)
    return sorted(entries, key=key)


def ensure_loaded(e: SettingEntry) -> bool:
    from ..datasets import ManifestError, load_setting

    if e.setting is None and e.status == "ok":
        try:
            e.setting = load_setting(e.run_manifest)
        except ManifestError as exc:
            e.status, e.detail = "error", str(exc)
    return e.status == "ok"
