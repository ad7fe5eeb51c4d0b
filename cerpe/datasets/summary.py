"""The summary ``cerpe check`` prints of a loaded :class:`~cerpe.scene.Setting`.

:func:`summarise` is pure (ground truth and stamps only); the checks of the data
(decoded frames, depth bits and units) are :mod:`cerpe.datasets.verify`'s.
"""
from __future__ import annotations

import numpy as np

from ..scene import Setting

OVERLAP_THRESHOLD = 0.2


def summarise(setting: Setting) -> dict:
    """Counts and ground-truth statistics of a setting.

    Returns a dict with:

    * ``encounters``, ``robots`` (distinct ids), ``frames`` (robot-frames), ``steps``;
    * ``pairs`` (ordered pairs x evaluated steps), ``pairs_with_gt``;
    * ``sync_max_abs_s`` (stamp sync residual), ``index_sync_max_offset_s`` (stamp offset
      between index-synchronised robots);
    * ``overlap_mean``, ``overlap_frac_ge_0_2`` (NaN without ground-truth overlap);
    * ``view_angle_min_deg`` / ``view_angle_max_deg`` (NaN without ground truth);
    * ``per_encounter`` rows.
    """
    every = int(setting.meta.get("evaluation_every", 1))
    rows = []
    ids: set[str] = set()
    angles_all: list[float] = []
    overlaps_all: list[float] = []
    for enc in setting.encounters:
        ids.update(enc.robot_ids)
        steps = range(0, enc.n_steps, every)
        pairs = enc.ordered_pairs()
        angles = [enc.gt_viewing_angle(t, i, j) for t in steps for i, j in pairs]
        angles = [a for a in angles if np.isfinite(a)]
        ov = []
        if enc.overlap is not None:
            ov = [enc.overlap[t, i, j] for t in steps for i, j in pairs]
            ov = [v for v in ov if np.isfinite(v)]
        angles_all += angles
        overlaps_all += ov
        rows.append({
            "encounter": enc.name, "robots": ",".join(enc.robot_ids), "steps": enc.n_steps,
            "pairs": len(steps) * len(pairs), "pairs_with_gt": len(angles),
            "overlap_mean": float(np.mean(ov)) if ov else float("nan"),
            "view_angle_max_deg": float(np.degrees(max(angles))) if angles else float("nan"),
        })
    sync = setting.meta.get("load_report", {}).get("sync", {})
    res = [r["max_abs_s"] for enc in sync.values() for r in enc.values() if r.get("mode", "stamp") == "stamp"]
    offs = [r["max_abs_s"] for enc in sync.values() for r in enc.values() if r.get("mode") == "index"]
    return {
        "setting": setting.name,
        "encounters": len(setting.encounters),
        "robots": len(ids),
        "frames": int(sum(enc.n_steps * len(enc.robots) for enc in setting.encounters)),
        "steps": int(sum(enc.n_steps for enc in setting.encounters)),
        "pairs": int(sum(r["pairs"] for r in rows)),
        "pairs_with_gt": int(sum(r["pairs_with_gt"] for r in rows)),
        "sync_max_abs_s": float(max(res)) if res else float("nan"),
        "index_sync_max_offset_s": float(max(offs)) if offs else float("nan"),
        "overlap_mean": float(np.mean(overlaps_all)) if overlaps_all else float("nan"),
        "overlap_frac_ge_0_2": float(np.mean(np.array(overlaps_all) >= OVERLAP_THRESHOLD)) if overlaps_all else float("nan"),
        "view_angle_min_deg": float(np.degrees(min(angles_all))) if angles_all else float("nan"),
        "view_angle_max_deg": float(np.degrees(max(angles_all))) if angles_all else float("nan"),
        "per_encounter": rows,
    }
