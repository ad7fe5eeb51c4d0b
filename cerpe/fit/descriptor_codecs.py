"""Descriptors of development sets, cached, and the gate's ROC AUC per descriptor codec.

Used by ``cerpe fit projection`` (the fitting descriptors) and the development study
``lab/descriptor_codec_auc.py`` (the co-visibility ROC AUC of the compressed score against the
uncompressed one, per set, and each codec's ``tau`` by the rule of ``cerpe fit thresholds``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .. import knobs
from ..atomicio import atomic_write_npz
from .calibrate import cross_scene_negatives, largest_tau_with_recall, pair_samples
from ..pipeline.evaluate import roc_auc


def descriptor_fingerprint(desc: Any) -> str:
    """CRC32 of what a descriptor's values depend on: its settings and fitted arrays (centres, mean,
    the subtracted mean descriptor). A cache written by another descriptor is not reused."""
    import zlib

    conf = getattr(desc, "conf", {})
    conf = knobs.as_dict(conf) if isinstance(conf, knobs.Group) else dict(conf)
    crc = zlib.crc32(repr(sorted(conf.items())).encode())
    for name in ("centres", "mean", "descriptor_mean"):
        arr = getattr(desc, name, None)
        if arr is not None:
            crc = zlib.crc32(np.ascontiguousarray(arr, np.float32).tobytes(), crc)
    return f"{crc:08x}"


def describe_setting(desc: Any, setting: Any, cache: Path | None = None, every: int = 1,
                     progress: bool = True) -> list[np.ndarray]:
    """``[N, T, dim] float32`` raw descriptors of every robot frame (every ``every``-th step; others
    zero) of each encounter of ``setting``, cached in ``cache`` (``.npz``, one array per encounter,
    reused only when written by the same descriptor: :func:`descriptor_fingerprint`)."""
    from tqdm import tqdm

    from ..protocols import View

    fingerprint = descriptor_fingerprint(desc)
    if cache is not None and cache.is_file():
        with np.load(cache) as z:
            arrays = [f for f in z.files if f.startswith("e")]
            same = "fingerprint" in z.files and str(z["fingerprint"]) == fingerprint
            if same and len(arrays) == len(setting.encounters):
                return [z[f"e{k}"] for k in range(len(arrays))]
    out = []
    for enc in setting.encounters:
        D = np.zeros((len(enc.robots), enc.n_steps, int(desc.dim)), np.float32)
        for i, r in enumerate(enc.robots):
            for t in tqdm(range(0, enc.n_steps, every), desc=f"describe {enc.name}/{r.robot_id}", leave=False,
                          disable=not progress):
                D[i, t] = desc.describe(View((r.robot_id, t), r.image(t), r.intrinsics))
        out.append(D)
    if cache is not None:
        atomic_write_npz(cache, fingerprint=np.array(fingerprint), **{f"e{k}": D for k, D in enumerate(out)})
    return out


def unit(D: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(D, axis=-1, keepdims=True)
    return np.where(n > 0, D / np.maximum(n, 1e-30), 0.0).astype(np.float32)


def wire_values(D: np.ndarray, codec: Any | None) -> np.ndarray:
    """``[..., dim]`` raw descriptors -> the unit vectors the gate scores: the fp16 wire values
    (``codec`` None, the current message) or the codec's decoded values."""
    flat = D.reshape(-1, D.shape[-1])
    if codec is None:
        W = flat.astype(np.float16).astype(np.float32)
    else:
        W = np.stack([codec.wire(d) if np.any(d) else np.zeros(codec.dims, np.float32) for d in flat])
    return unit(W).reshape(*D.shape[:-1], W.shape[-1])


def labelled_pairs(enc: Any, D: np.ndarray, stride: int, cache: Path | None = None) -> pd.DataFrame:
    """:func:`~cerpe.fit.calibrate.pair_samples` (any step), cached as CSV (overlaps are the cost)."""
    if cache is not None and cache.is_file():
        return pd.read_csv(cache)
    df = pair_samples(enc, unit(D), stride=stride, any_step=True, progress=False)
    df = df[df["label"].notna()].reset_index(drop=True)
    if cache is not None:
        df.to_csv(cache, index=False)
    return df


def rescore(df: pd.DataFrame, W: np.ndarray) -> np.ndarray:
    """The cosine of each labelled pair's views under wire values ``W [N, T, k]``."""
    a, b, t, u = (df[c].to_numpy(int) for c in ("a", "b", "t", "u"))
    return np.sum(W[a, t] * W[b, u], axis=-1)


def codec_figures(sets: dict[str, dict], codecs: dict[str, Any | None],
                  cross_stride: int = 1) -> tuple[pd.DataFrame, dict[str, float]]:
    """Per set and codec: ROC AUC with the co-visibility label (real sets with cross-scene negatives, as the
    calibration), its difference to ``full``; and per codec the calibration rule's ``tau``.

    ``sets``: name -> ``{"kind": "synthetic"|"real", "D": [encounter [N,T,dim]], "pairs": [DataFrame]}``.
    ``codecs``: name -> codec (None: the uncompressed fp16 message, which must be named ``full``).
    """
    rows, per_codec = [], {c: {} for c in codecs}
    for c, codec in codecs.items():
        for name, s in sets.items():
            W = [wire_values(D, codec) for D in s["D"]]
            sc = np.concatenate([rescore(df, w) for df, w in zip(s["pairs"], W)])
            y = np.concatenate([df["label"].to_numpy(float) > 0.5 for df in s["pairs"]])
            if s["kind"] == "real":
                others = [wire_values(D, codec) for n, o in sets.items() if n != name and o["kind"] == "real"
                          for D in o["D"]]
                neg = np.concatenate([cross_scene_negatives(w, others, cross_stride) for w in W])
                sc, y = np.r_[sc, neg], np.r_[y, np.zeros(neg.size, bool)]
            per_codec[c][name] = (sc, y)
            rows.append({"set": name, "codec": c, "n_positive": int(y.sum()), "n_negative": int((~y).sum()),
                         "roc_auc": roc_auc(sc, y)})
    df = pd.DataFrame(rows)
    full = df[df["codec"] == "full"].set_index("set")["roc_auc"]
    df["auc_minus_full"] = df["roc_auc"] - df["set"].map(full)
    taus = {c: largest_tau_with_recall(v) for c, v in per_codec.items()}
    return df, taus
