"""What an adapter found while loading: fatal problems, counted degradations and warnings.

Adapters never print and never silently drop data. Every frame they cannot use
(no ground-truth pose within tolerance, no partner frame within the sync
tolerance, no depth) is counted here under a named reason. Every fatal
problem is collected so that ``cerpe check`` lists them all at once. Warnings are
what is legal but probably wrong (a median depth a camera rarely sees). ``cerpe
check`` prints counts and warnings; a run logs them (:meth:`LoadReport.log`).
"""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field

from .manifest import ManifestError, Problem

log = logging.getLogger("cerpe.datasets")


@dataclass
class LoadReport:
    """Collects problems (fatal) and degradations (counted) while loading one manifest.

    Attributes:
        problems: fatal problems; :meth:`raise_if_problems` turns them into one
            :class:`ManifestError`.
        counts: ``(encounter, reason) -> n`` of counted degradations, e.g.
            ``("cad-l0-s0", "r1: frames without ground-truth pose") -> 3``.
        sync: ``encounter -> {robot: residuals}`` summaries, filled by adapters:
            ``{"max_abs_s", "mean_abs_s", "dropped"}`` per robot.
        warnings: legal but suspicious findings (file, field, message with the figure).
    """

    problems: list[Problem] = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)
    sync: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    warnings: list[Problem] = field(default_factory=list)

    def add(self, problem: Problem) -> None:
        self.problems.append(problem)

    def warn(self, problem: Problem) -> None:
        self.warnings.append(problem)

    def extend(self, problems: list[Problem]) -> None:
        self.problems.extend(problems)

    def count(self, encounter: str, reason: str, n: int = 1) -> None:
        """Record ``n`` frames degraded for ``reason`` (logged once per call)."""
        if n > 0:
            self.counts[(encounter, reason)] += int(n)
            log.debug("%s: %s: %d", encounter, reason, n)

    def raise_if_problems(self) -> None:
        if self.problems:
            raise ManifestError(self.problems)

    def log(self, setting: str) -> None:
        """Log every warning, and the counted degradations in one line (what ``cerpe check`` prints)."""
        for w in self.warnings:
            log.warning("%s: %s", setting, w)
        if self.counts:
            log.warning("%s: counted while loading: %s", setting,
                        "; ".join(f"{e}: {r}: {n}" for (e, r), n in sorted(self.counts.items())))

    def as_dict(self) -> dict:
        return {
            "problems": [str(p) for p in self.problems],
            "counts": {f"{e}: {r}": n for (e, r), n in sorted(self.counts.items())},
            "warnings": [str(w) for w in self.warnings],
            "sync": self.sync,
        }
