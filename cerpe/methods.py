"""The methods of Table I: names, the paper's row labels, and which cannot run here (and why).

``cerpe`` is Algorithm 1, ``cerpe-wo-em`` the same without ego-motion
propagation; ``cerpe-graph`` (our extension, not in the paper) the same messages with
a robust pose graph per pair instead of the switch (``backend.kind: graph``); ``sift-ransac`` and ``aliked-lightglue`` are per-pair, per-frame
baselines (``aliked-lightglue`` stands in for the paper's SuperGlue row);
``nope`` and ``co-visnet`` have no offline code or weights.

:data:`CODE_ENTRIES` names the modules where each method's code starts: its runs' code fingerprint
covers what they import, transitively (:func:`cerpe.runfolder.provenance.code_hash`).
"""
from __future__ import annotations

from .errors import CerpeError

CERPE_METHODS: tuple[str, ...] = ("cerpe", "cerpe-wo-em", "cerpe-graph")
EXTENSION_METHODS: tuple[str, ...] = ("cerpe-graph",)  # ours, not the paper's
BASELINE_METHODS: tuple[str, ...] = ("sift-ransac", "aliked-lightglue")
UNAVAILABLE: dict[str, str] = {
    "nope": "NOPE needs its object detector and graph-matching code and weights, which are not "
            "published as an installable package and cannot be downloaded here",
    "co-visnet": "Co-VisNet needs its trained regression network, whose weights are not "
                 "shipped by any package and cannot be downloaded here",
}
METHODS: tuple[str, ...] = CERPE_METHODS + BASELINE_METHODS + tuple(UNAVAILABLE)
# The paper's row labels, used by tables and figures (and ours, labelled as such).
METHOD_LABELS: dict[str, str] = {
    "aliked-lightglue": "SuperGlue stand-in (ALIKED+LightGlue)",
    "sift-ransac": "SIFT+RANSAC",
    "nope": "NOPE",
    "co-visnet": "Co-VisNet",
    "cerpe-wo-em": "CERPE w/o EM",
    "cerpe": "CERPE",
    "cerpe-graph": "CERPE + pose graph (our extension, not in the paper)",
}

# Where each method's results are computed and written: the step source (the CERPE one builds the
# configuration tree, the plug-ins and Algorithm 1; the baselines' the per-frame estimators), the
# dataset loader and the run folder writer. Editing a module outside their imports keeps cached runs.
_RUN_CODE = ("cerpe.datasets", "cerpe.pipeline.setting", "cerpe.runfolder.write")
CODE_ENTRIES: dict[str, tuple[str, ...]] = {
    **{m: ("cerpe.pipeline.cerpe_method", *_RUN_CODE) for m in CERPE_METHODS},
    **{m: ("cerpe.pipeline.baseline_method", "cerpe.baselines", *_RUN_CODE) for m in BASELINE_METHODS},
}


class MethodError(CerpeError, ValueError):
    """An unknown method name."""


class MethodUnavailable(MethodError):
    """The method cannot run offline (no code/weights exist here)."""


def check_method(method: str) -> None:
    """Raise :class:`MethodUnavailable` for ``nope`` / ``co-visnet``, :class:`MethodError` for an unknown name."""
    if method in UNAVAILABLE:
        raise MethodUnavailable(f"method {method!r} is not available offline: {UNAVAILABLE[method]}")
    if method not in METHODS:
        raise MethodError(f"unknown method {method!r}; choose one of {list(METHODS)}")
