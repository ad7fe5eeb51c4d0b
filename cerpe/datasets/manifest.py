"""Dataset manifests: the YAML file that says where a setting's data is and how to read it.

A manifest is validated completely before anything is loaded: :func:`validate`
returns *every* problem it finds (file, dotted field path, what was expected),
and :func:`load_manifest` raises one :class:`ManifestError` carrying them all.

Common fields (adapter-specific ones are checked by the adapter)::

    name: synthetic-cad        # str, the setting name (column group of Table I)
    adapter: mocap             # a registered adapter (see cerpe.datasets.registry)
    enabled: true              # false: the setting is listed as "not supplied";
                               # if-present: enabled when data_root exists, else "not supplied"
    data_root: ../build/x      # relative to the manifest file; ${VAR} expands from the environment
    metric_depth: sensor       # sensor | mono-sim | dataset | metric3d | none
    metric_depth_options: {max_m: 40}   # optional keyword options of that source (numbers, booleans, strings)
    sync_tolerance_s: 0.02     # seconds, > 0 and <= 1 (frames farther apart are not one time step)
    evaluation: {every: 1}     # evaluate every n-th step (n >= 1)
    encounters: [...]          # adapter-specific

See ``datasets_manifest/README.md`` for a guide.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import yaml

from ..errors import CerpeError

METRIC_DEPTH_CHOICES: tuple[str, ...] = ("sensor", "mono-sim", "dataset", "metric3d", "none")
ENABLED_IF_PRESENT = "if-present"  # enabled exactly when data_root exists (e.g. development data)
COMMON_FIELDS: tuple[str, ...] = (
    "name", "adapter", "enabled", "data_root", "metric_depth", "metric_depth_options", "sync_tolerance_s",
    "evaluation", "encounters", "description",
)
_VAR_RE = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}")
SYNC_TOLERANCE_MAX_S = 1.0  # robots' frames farther apart than this are not one time step
# ids that name files or folders of a run (setting, encounter and robot ids): no '/', no leading '.'
SAFE_ID_RE = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*")


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a manifest or the data it points to.

    Attributes:
        file: the file at fault (the manifest, or a data file it names).
        field: dotted path into the manifest (``encounters[2].robots[0].trajectory``),
            optionally followed by a location inside the data file (``line 7``).
        message: what was found and what was expected.
    """

    file: str
    field: str
    message: str

    def __str__(self) -> str:
        where = f"{self.file}: {self.field}" if self.field else self.file
        return f"{where}: {self.message}"


class ManifestError(CerpeError, ValueError):
    """A manifest or the data it names is invalid; ``problems`` lists every problem found."""

    def __init__(self, problems: Iterable[Problem] | str, file: str = "", field: str = "") -> None:
        if isinstance(problems, str):
            problems = [Problem(file, field, problems)]
        self.problems: list[Problem] = list(problems)
        n = len(self.problems)
        if n == 1:
            msg = str(self.problems[0])
        else:
            msg = f"{n} problems:\n" + "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(msg)


@dataclass
class Manifest:
    """A validated manifest.

    Attributes:
        path: the manifest file (absolute).
        name, adapter, metric_depth, sync_tolerance_s: common fields.
        enabled: whether the setting is loaded; for ``enabled: if-present`` it is
            true exactly when ``data_root`` resolves to an existing folder.
        enabled_if_present: the manifest said ``enabled: if-present``.
        metric_depth_options: keyword options of the depth source (``{}`` when absent),
            e.g. ``{min_m: 0.5, max_m: 40}`` for an outdoor ``sensor``.
        data_root: absolute data folder (None when it cannot be resolved, which is
            only allowed for a disabled manifest).
        evaluation_every: evaluate every n-th step.
        encounters: the raw, adapter-specific ``encounters`` value (list or None).
        raw: the whole parsed YAML mapping (adapter-specific top-level fields too).
    """

    path: Path
    name: str
    adapter: str
    enabled: bool
    data_root: Path | None
    metric_depth: str
    sync_tolerance_s: float
    evaluation_every: int
    encounters: Any
    raw: dict = field(default_factory=dict)
    metric_depth_options: dict = field(default_factory=dict)
    enabled_if_present: bool = False

    def resolve(self, rel: str | os.PathLike) -> Path:
        """A path from the manifest, relative to ``data_root`` (absolute paths pass through)."""
        p = Path(expand_vars(str(rel))[0])
        if p.is_absolute():
            return p
        base = self.data_root if self.data_root is not None else self.path.parent
        return (base / p).resolve()

    def problem(self, field_: str, message: str, file: str | os.PathLike | None = None) -> Problem:
        """A :class:`Problem` for this manifest (``file`` defaults to the manifest itself)."""
        return Problem(str(file) if file is not None else str(self.path), field_, message)


# --------------------------------------------------------------------------- helpers
def project_root() -> Path:
    """The source checkout holding this package (where ``build/`` lives), else the working directory."""
    here = Path(__file__).resolve().parents[2]
    return here if (here / "pyproject.toml").is_file() else Path.cwd()


def cache_base() -> Path:
    """Where derived data is cached: ``$CERPE_CACHE``, else ``build/`` in the checkout."""
    env = os.environ.get("CERPE_CACHE")
    return Path(env).expanduser().resolve() if env else project_root() / "build"


def expand_vars(text: str) -> tuple[str, list[str]]:
    """Expand ``${VAR}`` from the environment; returns the text and the unset names."""
    missing: list[str] = []

    def sub(m: re.Match) -> str:
        val = os.environ.get(m.group(1))
        if val is None:
            missing.append(m.group(1))
            return m.group(0)
        return val

    return _VAR_RE.sub(sub, text), missing


def type_name(v: Any) -> str:
    return "null" if v is None else type(v).__name__


def mapping_problems(obj: Any, f: Path, field: str, known: Iterable[str]) -> list[Problem] | None:
    """Problems of a sub-mapping ``field``: None if it is not a mapping at all (skip it),
    else one problem per unknown key (usually a typo), naming the known ones."""
    if not isinstance(obj, dict):
        return None
    known = list(known)
    return [Problem(f, f"{field}.{k}", f"unknown field; known: {', '.join(known)}") for k in obj if k not in known]


def not_a_mapping(obj: Any, f: Path, field: str) -> Problem:
    return Problem(f, field, f"expected a mapping, got {type_name(obj)}")


def unsafe_id(value: Any, what: str) -> str:
    """Why ``value`` cannot be an id that names files (``""`` when it can): letters, digits, ``_ . -``,
    not starting with a dot (``r/0`` or ``..`` would write outside the run folder)."""
    if isinstance(value, str) and SAFE_ID_RE.fullmatch(value):
        return ""
    return (f"{what} {value!r}: use letters, digits, '_', '.', '-' and do not start with '.' "
            "(it names files and folders of a run)")


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, key: Any, line: int, first_line: int) -> None:
        super().__init__(f"duplicate key {key!r} (first at line {first_line}; YAML keeps only the last)")
        self.key, self.line = key, line


class _StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a mapping with the same key twice (PyYAML keeps the last silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base` may be overridden on purpose
                continue
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            try:
                if key in seen:
                    raise _DuplicateKey(key, line, seen[key])
                seen[key] = line
            except TypeError:  # an unhashable key: the base class says so
                continue
        return super().construct_mapping(node, deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _StrictLoader.construct_mapping)


def read_yaml(path: Path, what: str = "manifest", field: str = "") -> Any:
    """Parse a YAML file safely, turning every failure into a :class:`ManifestError` (naming ``field``
    and the line); a key given twice in one mapping is an error (YAML would keep the last silently)."""
    if not path.is_file():
        raise ManifestError(f"{what} file not found", file=str(path), field=field)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(f"cannot read {what}: {exc}", file=str(path), field=field) from None
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 (a SafeLoader subclass)
    except _DuplicateKey as exc:
        where = f"{field} line {exc.line}".strip()
        raise ManifestError(str(exc), file=str(path), field=where) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{field} line {mark.line + 1}".strip() if mark is not None else field
        raise ManifestError(f"not valid YAML: {getattr(exc, 'problem', exc)}", file=str(path), field=where) from None


# --------------------------------------------------------------------------- validation
def validate(raw: Any, path: Path, adapter_fields: Iterable[str] | None = ()) -> list[Problem]:
    """Check the common fields of a parsed manifest; returns every problem found.

    Args:
        raw: the parsed YAML document.
        path: the manifest file (for messages and to resolve ``data_root``).
        adapter_fields: extra top-level fields the adapter accepts; None skips the
            unknown-field check (the adapter itself is unknown, so is its schema).
    """
    f = str(path)
    probs: list[Problem] = []
    if not isinstance(raw, dict):
        return [Problem(f, "", f"expected a YAML mapping at the top level, got {type_name(raw)}")]
    known = set(COMMON_FIELDS) | set(adapter_fields or ())
    for key in raw:
        if adapter_fields is not None and key not in known:
            probs.append(Problem(f, str(key), f"unknown field; known fields: {', '.join(sorted(known))}"))
    name = raw.get("name")
    if not isinstance(name, str) or not name.strip():
        probs.append(Problem(f, "name", f"required: a non-empty string, got {type_name(name)}"))
    elif not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
        probs.append(Problem(f, "name", f"{name!r}: use letters, digits, '-', '_', '.' (it names run folders)"))
    adapter = raw.get("adapter")
    if not isinstance(adapter, str) or not adapter:
        probs.append(Problem(f, "adapter", f"required: the adapter name (a string), got {type_name(adapter)}"))
    enabled = raw.get("enabled", True)
    if not isinstance(enabled, bool) and enabled != ENABLED_IF_PRESENT:
        probs.append(Problem(f, "enabled", f"expected true, false or {ENABLED_IF_PRESENT!r}, got {enabled!r}"))
    md = raw.get("metric_depth", "dataset")
    if md not in METRIC_DEPTH_CHOICES:
        probs.append(Problem(f, "metric_depth", f"expected one of {', '.join(METRIC_DEPTH_CHOICES)}, got {md!r}"))
    opts = raw.get("metric_depth_options", {})
    if not isinstance(opts, dict):
        probs.append(Problem(f, "metric_depth_options",
                             f"expected a mapping of option: value (e.g. {{max_m: 40}}), got {type_name(opts)}"))
    else:
        for k, v in opts.items():
            if not isinstance(k, str) or not (isinstance(v, (bool, str)) or is_number(v)):
                probs.append(Problem(f, f"metric_depth_options.{k}",
                                     f"expected a number, boolean or string, got {type_name(v)}"))
    tol = raw.get("sync_tolerance_s", 0.02)
    if not is_number(tol) or not 0 < float(tol) <= SYNC_TOLERANCE_MAX_S:
        probs.append(Problem(f, "sync_tolerance_s", f"expected a number of seconds > 0 and <= "
                                                    f"{SYNC_TOLERANCE_MAX_S:g} (frames farther apart are not one "
                                                    f"time step), got {tol!r}"))
    ev = raw.get("evaluation", {"every": 1})
    if not isinstance(ev, dict):
        probs.append(Problem(f, "evaluation", f"expected a mapping like {{every: 1}}, got {type_name(ev)}"))
    else:
        for k in ev:
            if k != "every":
                probs.append(Problem(f, f"evaluation.{k}", "unknown field; known: every"))
        every = ev.get("every", 1)
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            probs.append(Problem(f, "evaluation.every", f"expected an integer >= 1, got {every!r}"))
    if "data_root" in raw:
        dr = raw["data_root"]
        if not isinstance(dr, str) or not dr:
            probs.append(Problem(f, "data_root", f"expected a path string, got {type_name(dr)}"))
        elif enabled is True:
            text, missing = expand_vars(dr)
            if missing:
                probs.append(Problem(f, "data_root", f"environment variable(s) {', '.join(missing)} not set (in {dr!r})"))
            else:
                root = (path.parent / text).resolve()
                if not root.is_dir():
                    probs.append(Problem(f, "data_root", f"folder not found: {root}"))
    return probs


def build_manifest(raw: dict, path: Path) -> Manifest:
    """Turn a mapping into a :class:`Manifest`; never raises (invalid values get defaults, see :func:`validate`)."""
    data_root: Path | None = None
    dr = raw.get("data_root")
    if isinstance(dr, str):
        text, missing = expand_vars(dr)
        if not missing:
            data_root = (path.parent / text).resolve()
    elif dr is None:
        data_root = path.parent.resolve()
    ev = raw.get("evaluation")
    every = ev.get("every", 1) if isinstance(ev, dict) else 1
    tol = raw.get("sync_tolerance_s", 0.02)
    if_present = raw.get("enabled", True) == ENABLED_IF_PRESENT
    enabled = raw.get("enabled", True) is True or (if_present and data_root is not None and data_root.is_dir())
    return Manifest(
        path=path,
        name=str(raw.get("name")),
        adapter=str(raw.get("adapter")),
        enabled=enabled,
        enabled_if_present=if_present,
        data_root=data_root,
        metric_depth=str(raw.get("metric_depth", "dataset")),
        # invalid values were reported by validate(); defaults keep adapter checks running
        sync_tolerance_s=float(tol) if is_number(tol) and 0 < float(tol) <= SYNC_TOLERANCE_MAX_S else 0.02,
        evaluation_every=int(every) if isinstance(every, int) and not isinstance(every, bool) and every >= 1 else 1,
        encounters=raw.get("encounters"),
        raw=raw,
        metric_depth_options=dict(raw["metric_depth_options"]) if isinstance(raw.get("metric_depth_options"), dict) else {},
    )


def checked_manifest(raw: Any, path: Path, adapter: Any = None, problems: Iterable[Problem] = ()) -> Manifest:
    """The :class:`Manifest` of ``raw`` (parsed from ``path``), checked against its adapter.

    Args:
        adapter: the manifest's adapter (a :class:`cerpe.datasets.registry.Adapter`: its
            ``top_level_fields`` and ``validate``), or None when it is unknown.
        problems: found before (an unknown adapter); reported with the others.

    Raises:
        ManifestError: listing ``problems`` and every one found here.
    """
    problems = [*problems, *validate(raw, path, adapter.top_level_fields if adapter is not None else None)]
    if not isinstance(raw, dict):
        raise ManifestError(problems)
    manifest = build_manifest(raw, path)
    if adapter is not None:
        problems.extend(adapter.validate(manifest))
    if problems:
        raise ManifestError(problems)
    return manifest
