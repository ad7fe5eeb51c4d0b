"""The robots of one ``cerpe online`` team, evaluated together as the team.

``cerpe online`` writes one run folder per robot: the rows of ``steps.csv`` whose ego is
that robot, and ``run.json`` with ``config.online`` (robot, team, roster, network
options). Given together to ``cerpe eval``, the folders of one team (same team name,
roster and configuration apart from each robot's own id and network options) become one
:class:`~cerpe.runfolder.read.Run`, whose rows are those ``cerpe run`` writes for the
same team; a robot's folder given alone stays a run of its own rows.
"""
from __future__ import annotations

import logging
from typing import Sequence

import pandas as pd

from .provenance import fingerprint
from .read import EvalError, Run

log = logging.getLogger(__name__)


def team_key(run: Run) -> tuple[str, str, tuple[str, ...]] | None:
    """``(configuration fingerprint without the online part, team, roster)`` of an online robot's run, else None."""
    config = run.meta.get("config", {})
    online = config.get("online")
    if not isinstance(online, dict) or not isinstance(online.get("robot"), str):
        return None
    shared = {k: v for k, v in config.items() if k != "online"}
    return fingerprint(shared), str(online.get("team")), tuple(map(str, online.get("robots", ())))


def merge_teams(runs: Sequence[Run]) -> list[Run]:
    """``runs`` with the online robots of each team merged into one run (others unchanged, order kept)."""
    groups: dict[tuple, list[Run]] = {}
    out: list[Run | tuple] = []
    for r in runs:
        key = team_key(r)
        if key is None:
            out.append(r)
            continue
        if key not in groups:
            groups[key] = []
            out.append(key)
        groups[key].append(r)
    return [merge_team(groups[k]) if isinstance(k, tuple) else k for k in out]


def merge_team(runs: Sequence[Run]) -> Run:
    """One run of the robots ``runs`` of one team (:func:`team_key` equal): their rows in ``cerpe run``'s
    order (encounter, step, robot in roster order). A single robot's run is returned unchanged."""
    if len(runs) == 1:
        return runs[0]
    _, team, roster = team_key(runs[0])
    by_robot: dict[str, Run] = {}
    for r in runs:
        robot = r.meta["config"]["online"]["robot"]
        if robot in by_robot:
            raise EvalError(f"team {team!r}: robot {robot!r} given twice ({by_robot[robot].path} and {r.path}); "
                            "pass one run folder per robot")
        by_robot[robot] = r
    order = [rid for rid in roster if rid in by_robot] + sorted(set(by_robot) - set(roster))
    missing = [rid for rid in roster if rid not in by_robot]
    if missing:
        log.warning("team %s: evaluating robots %s without %s (their run folders were not given)",
                    team, order, missing)
    encounters = list(runs[0].meta["config"].get("encounters", []))

    def cat(frames: list[pd.DataFrame]) -> pd.DataFrame:
        df = pd.concat(frames, ignore_index=True)
        rank = df["encounter"].map({e: k for k, e in enumerate(encounters)}).fillna(len(encounters))
        return df.assign(_enc=rank).sort_values(["_enc", "step"], kind="stable").drop(columns="_enc") \
            .reset_index(drop=True)

    members = [by_robot[rid] for rid in order]
    peers = [r.peer_overlap for r in members if r.peer_overlap is not None]
    first = members[0]
    config = {k: v for k, v in first.meta["config"].items() if k != "online"}
    config["online"] = {"team": team, "robots": list(roster), "robots_given": order}
    meta = {**first.meta, "config": config, "fingerprint": fingerprint({"team": team, "roster": list(roster),
                                                                           "config": team_key(first)[0]})}
    return Run(first.path, meta, cat([r.steps for r in members]), cat([r.robots for r in members]),
               pd.concat(peers, ignore_index=True) if peers else None, tuple(r.path for r in members))
