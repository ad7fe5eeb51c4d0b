"""One robot's topics read out of a ROS bag for the ``rosbag`` adapter: frames cached as files, the rest in memory.

Images and depth maps of a bag are decoded once (:mod:`cerpe.rosio.decode`, the same decoder a live
robot uses) and kept as files under ``<cache>/<key>/`` (``rgb/<k>.png`` lossless, ``depth/<k>.npy``
float32 metres, ``index.json`` written last), ``key`` a hash of the bag file(s) (path, size, time)
and the topics; a second load reads the files. Camera info, odometry and ground truth are small: read
on every load. A message that does not decode is counted and skipped; what cannot be used at all
(a topic the bag does not hold, no camera info, a bag that does not open) is a :class:`Problem`.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..rosio import decode
from ..rosio.bags import BagError, BagReader, BagTruncated
from ..rosio.types import CAMERA_INFO, IMAGE, IMAGE_TYPES, POSE_TYPES, RosInputError
from ..scene import CameraIntrinsics
from .manifest import Problem

INDEX = "index.json"
CACHE_FORMAT = 1


@dataclass
class Topics:
    """The topics one robot reads, the bag holding them, and the bag holding its ground truth."""

    bag: Path
    image: str
    camera_info: str
    depth: str | None = None
    odometry: str | None = None
    gt: str | None = None
    gt_bag: Path | None = None


@dataclass
class BagData:
    """What :func:`read_robot` got: frames (stamps, files), depth (stamps, files), camera, poses, counts."""

    stamps_s: np.ndarray
    rgb: list[Path]
    depth_stamps_s: np.ndarray
    depth: list[Path]
    K: CameraIntrinsics
    dist: tuple[float, ...]
    odometry: tuple[np.ndarray, np.ndarray]  # (stamps, T_odom_base [N,4,4])
    gt: tuple[np.ndarray, np.ndarray] | None  # (stamps, T_world_body [N,4,4])
    counts: dict[str, int] = field(default_factory=dict)


def cache_key(t: Topics) -> str:
    h = hashlib.sha1(f"{CACHE_FORMAT}|{t.image}|{t.depth}".encode())
    for p in sorted((t.bag.rglob("*") if t.bag.is_dir() else [t.bag])):
        if p.is_file():
            st = p.stat()
            h.update(f"|{p.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def _missing_topics(r: BagReader, wanted: dict[str, str | None], field_of: dict[str, str], f: str) -> list[Problem]:
    have = r.topics
    holds = ", ".join(f"{k} ({v})" for k, v in sorted(have.items())) or "nothing"
    return [Problem(f, field_of[role], f"topic {topic} is not in bag {r.path}; it holds {holds}")
            for role, topic in wanted.items() if topic and topic not in have]


def _bump(counts: dict[str, int], what: str) -> None:
    counts[what] = counts.get(what, 0) + 1


def _poses(r: BagReader, topic: str, what: str, counts: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
    stamps, poses = [], []
    for _, kind, _, msg in r.messages([topic]):
        try:
            T = decode.pose(msg, what)
        except RosInputError:
            _bump(counts, f"{what}: messages with NaN or an unusable pose (skipped)")
            continue
        s = decode.stamp_s(msg)
        if stamps and s <= stamps[-1]:
            _bump(counts, f"{what}: messages not after the one before (skipped)")
            continue
        stamps.append(s)
        poses.append(T)
    return np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)


def _extract(r: BagReader, t: Topics, out: Path, counts: dict[str, int], fields: dict[str, str]) -> None:
    """Decode the image and depth topics of ``r`` into ``out`` (a fresh folder), ``index.json`` last."""
    import cv2

    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    index: dict[str, list] = {"rgb": [], "depth": []}
    topics = [t.image] + ([t.depth] if t.depth else [])
    for topic, kind, _, msg in r.messages(topics):
        role = "rgb" if topic == t.image else "depth"
        what = f"{fields['image' if role == 'rgb' else 'depth']} {topic}"
        try:
            s = decode.stamp_s(msg)
            arr = decode.image_rgb(msg, what) if role == "rgb" else decode.depth_m(msg, what)
        except RosInputError as exc:
            _bump(counts, f"{what}: messages that do not decode (skipped): {str(exc).split(': ', 1)[-1][:80]}")
            continue
        k = len(index[role])
        name = f"{role}/{k:06d}.{'png' if role == 'rgb' else 'npy'}"
        if role == "rgb":
            cv2.imwrite(str(out / name), np.ascontiguousarray(arr[:, :, ::-1]))
        else:
            np.save(out / name, arr)
        index[role].append([s, name])
    (out / INDEX).write_text(json.dumps({"format": CACHE_FORMAT, **index}))


def _frames(r: BagReader, t: Topics, cache: Path, counts: dict[str, int], fields: dict[str, str]) -> dict:
    """The cached frames of ``t`` (extracted now if the cache has none); index.json's content."""
    folder = cache / cache_key(t)
    if (folder / INDEX).is_file():
        try:
            idx = json.loads((folder / INDEX).read_text())
            if idx.get("format") == CACHE_FORMAT:
                return {**idx, "folder": folder}
        except (OSError, ValueError):
            pass  # unreadable: extracted again
    tmp = folder.with_name(f"{folder.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _extract(r, t, tmp, counts, fields)
        shutil.rmtree(folder, ignore_errors=True)
        os.replace(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {**json.loads((folder / INDEX).read_text()), "folder": folder}


def read_robot(t: Topics, cache: Path, f: str, fields: dict[str, str]) -> tuple[BagData | None, list[Problem]]:
    """Everything one robot reads from its bag(s). ``fields``: role -> manifest field (for problems)."""
    counts: dict[str, int] = {}
    try:
        with BagReader(t.bag, fields["bag"]) as r:
            probs = _missing_topics(r, {"image": t.image, "camera_info": t.camera_info, "depth": t.depth,
                                        "odometry": t.odometry, "gt": t.gt if t.gt_bag is None else None},
                                    fields, f)
            kinds = r.topics
            for role, allowed in (("image", IMAGE_TYPES), ("camera_info", (CAMERA_INFO,)), ("depth", (IMAGE,)),
                                  ("odometry", POSE_TYPES), ("gt", POSE_TYPES)):
                topic = getattr(t, role)
                if topic in kinds and kinds[topic] not in allowed and not (role == "gt" and t.gt_bag is not None):
                    probs.append(Problem(f, fields[role], f"topic {topic} of {t.bag} carries {kinds[topic]}; "
                                                          f"expected {' or '.join(allowed)}"))
            if probs:
                return None, probs
            cam = None
            for _, _, _, msg in r.messages([t.camera_info]):
                try:
                    got = decode.camera(msg, f"{fields['camera_info']} {t.camera_info}")
                except RosInputError as exc:
                    counts[f"{t.camera_info}: CameraInfo that cannot be used (skipped): {exc}"[:160]] = 1
                    continue
                if cam is None:
                    cam = got
                elif got != cam:
                    _bump(counts, f"{t.camera_info}: CameraInfo that differs from the first (the first is used)")
            if cam is None:
                return None, [Problem(f, fields["camera_info"], f"no usable CameraInfo on {t.camera_info} in {t.bag}"
                                                                f"{''.join(f'; {k}' for k in counts)}")]
            idx = _frames(r, t, cache, counts, fields)
            odo = _poses(r, t.odometry, f"{fields['odometry']} {t.odometry}", counts) if t.odometry else \
                (np.zeros(0), np.zeros((0, 4, 4)))
            gt = _poses(r, t.gt, f"{fields['gt']} {t.gt}", counts) if t.gt and t.gt_bag is None else None
        if t.gt and t.gt_bag is not None:
            with BagReader(t.gt_bag, fields["gt_bag"]) as g:
                probs = _missing_topics(g, {"gt": t.gt}, fields, f)
                if probs:
                    return None, probs
                gt = _poses(g, t.gt, f"{fields['gt']} {t.gt}", counts)
    except BagTruncated as exc:
        return None, [Problem(str(t.bag), fields["bag"], str(exc))]
    except BagError as exc:
        return None, [Problem(str(t.bag), fields["bag"], str(exc))]
    folder = idx["folder"]
    if not idx["rgb"]:
        return None, [Problem(f, fields["image"], f"no image on {t.image} in {t.bag} decodes"
                                                  f"{''.join(f'; {k}: {n}' for k, n in counts.items())}")]
    return BagData(np.array([s for s, _ in idx["rgb"]]), [folder / p for _, p in idx["rgb"]],
                   np.array([s for s, _ in idx["depth"]], dtype=np.float64), [folder / p for _, p in idx["depth"]],
                   cam[0], cam[1], odo, gt, counts), []
