"""The adapter protocol and the registry that maps a manifest's ``adapter:`` to code.

Built-in adapters are imported lazily by name. Third-party packages add adapters
through the ``cerpe.adapters`` entry-point group, e.g. in their ``pyproject.toml``::

    [project.entry-points."cerpe.adapters"]
    kitti = "my_package.kitti:KittiAdapter"

The entry point names a class (instantiated without arguments) or an instance.
Tests and notebooks can also call :func:`register_adapter` directly.
"""
from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Callable, Protocol, runtime_checkable

from ..scene import Setting
from .manifest import Manifest, ManifestError, Problem
from .report import LoadReport

ENTRY_POINT_GROUP = "cerpe.adapters"


@runtime_checkable
class Adapter(Protocol):
    """Turns a validated :class:`Manifest` into a :class:`cerpe.scene.Setting`.

    Attributes:
        name: the value of ``adapter:`` in manifests.
        top_level_fields: extra top-level manifest fields this adapter accepts
            (beyond ``manifest.COMMON_FIELDS``).
    """

    name: str
    top_level_fields: tuple[str, ...]

    def validate(self, manifest: Manifest) -> list[Problem]:
        """Check adapter-specific fields (``encounters`` ...) without reading data; all problems."""
        ...

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        """Read the data. Add fatal problems to ``report`` (and keep going where
        possible, so that all are listed), count degradations, and raise
        ``report.raise_if_problems()`` before returning."""
        ...


# name -> "module:attribute" for the built-ins (imported on first use)
_BUILTIN: dict[str, str] = {
    "mocap": "cerpe.datasets.mocap:MocapAdapter",
    "openmars": "cerpe.datasets.openmars:OpenMarsAdapter",
    "synthetic": "cerpe.datasets.synthetic:SyntheticAdapter",
    "example": "cerpe.datasets.example:KittiStyleAdapter",
    "tum-rgbd": "cerpe.datasets.tum_rgbd:TumRgbdAdapter",
    "frames": "cerpe.datasets.frames:FramesAdapter",
    "pairs": "cerpe.datasets.pairs:PairsAdapter",
    "rosbag": "cerpe.datasets.rosbag:RosbagAdapter",
}
_REGISTERED: dict[str, Callable[[], Adapter] | Adapter] = {}


def register_adapter(name: str, adapter: Callable[[], Adapter] | Adapter) -> None:
    """Register an adapter class/factory or instance under ``name`` (overrides others)."""
    _REGISTERED[name] = adapter


def _entry_points() -> dict[str, object]:
    try:
        eps = entry_points(group=ENTRY_POINT_GROUP)
    except TypeError:  # Python < 3.10 API; kept for safety
        eps = entry_points().get(ENTRY_POINT_GROUP, [])  # type: ignore[attr-defined]
    return {ep.name: ep for ep in eps}


def known_adapters() -> list[str]:
    """Every adapter name: built-ins, registered ones and entry points."""
    return sorted(set(_BUILTIN) | set(_REGISTERED) | set(_entry_points()))


def _instantiate(obj: object, name: str) -> Adapter:
    inst = obj() if isinstance(obj, type) or (callable(obj) and not hasattr(obj, "load")) else obj
    if not isinstance(inst, Adapter):
        raise ManifestError(f"adapter {name!r} ({obj!r}) does not implement the Adapter protocol "
                            "(name, top_level_fields, validate, load)", field="adapter")
    return inst


def get_adapter(name: str, manifest_file: str = "") -> Adapter:
    """The adapter registered as ``name``; unknown names raise, listing the known ones."""
    if name in _REGISTERED:
        return _instantiate(_REGISTERED[name], name)
    if name in _BUILTIN:
        mod, attr = _BUILTIN[name].split(":")
        return _instantiate(getattr(importlib.import_module(mod), attr), name)
    eps = _entry_points()
    if name in eps:
        try:
            obj = eps[name].load()  # type: ignore[attr-defined]
        except Exception as exc:  # a broken third-party package must not crash `cerpe check` deep inside
            raise ManifestError(f"adapter {name!r}: entry point {eps[name]} failed to load: {exc}",
                                file=manifest_file, field="adapter") from None
        return _instantiate(obj, name)
    raise ManifestError(f"unknown adapter {name!r}; known adapters: {', '.join(known_adapters())}",
                        file=manifest_file, field="adapter")
