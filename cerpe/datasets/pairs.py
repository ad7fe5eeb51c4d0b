"""``pairs`` adapter: image-pair lists of the matching literature (SuperGlue / LoFTR format).

One line per pair (``#`` comments)::

    name0 name1 rot0 rot1 K0(9 numbers) K1(9) T_0to1(16)

``name0``/``name1``: image paths relative to ``images``; ``rot0``/``rot1``: quarter
turns (0..3) to rotate each image counter-clockwise (EXIF-style); ``K0``/``K1``: 3x3
intrinsics of the stored images, row-major; ``T_0to1``: 4x4 row-major, maps points
of camera 0 into camera 1 (``T_c1_c0``). Each pair becomes an encounter of two
single-frame robots ``r0``, ``r1`` with ground truth ``T_world_c0 = I``,
``T_world_c1 = inv(T_0to1)`` (rotations applied to both). Manifest::

    name: scannet-1500
    adapter: pairs
    data_root: /data/scannet_test_1500
    pairs: scannet_test_pairs_with_gt.txt     # relative to data_root
    images: .                                 # folder the names are relative to (default: data_root)
    resize: [640, 480]                        # optional: [width, height] or the longest side; intrinsics scaled
    depth: {replace: [[color, depth], [.jpg, .png]], units_per_m: 1000}   # optional depth path from the image path
    max_pairs: null                           # optional: only the first N pairs
    metric_depth: none                        # dataset with depth
    covisibility: auto                        # with depth: overlap from depth + poses (cached) | off

Images are read as stored (EXIF orientation ignored: ``K`` describes the stored
grid), resized (area), then rotated; depth is resized with nearest neighbours.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..geometry import GeometryError, check_se3, se3_inverse
from ..scene import CameraIntrinsics, Encounter, RobotStream, SceneError, Setting
from . import covisibility
from .formats import image_size
from .imageref import DepthFile, ImageFile, rot90_T, transformed_intrinsics
from .manifest import Manifest, ManifestError, Problem, is_number, type_name
from .report import LoadReport

N_NUMBERS = 36  # rot0 rot1 K0(9) K1(9) T_0to1(16)
FIELDS = ("pairs", "images", "resize", "depth", "max_pairs", "covisibility")
MAX_LINE_PROBLEMS = 10


def _resize_problems(v: Any, f: str) -> list[Problem]:
    if v is None or (isinstance(v, int) and not isinstance(v, bool) and v > 0):
        return []
    if isinstance(v, list) and len(v) == 2 and all(isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in v):
        return []
    return [Problem(f, "resize", f"expected [width, height] or the longest side (positive integers), got {v!r}")]


def _depth_problems(v: Any, f: str) -> list[Problem]:
    if v is None:
        return []
    if not isinstance(v, dict) or set(v) - {"replace", "units_per_m"}:
        return [Problem(f, "depth", f"expected {{replace: [[from, to], ...], units_per_m: n}}, got {v!r}")]
    rep = v.get("replace", [])
    probs = []
    if not (isinstance(rep, list) and all(isinstance(r, list) and len(r) == 2 and all(isinstance(x, str) for x in r)
                                          for r in rep) and rep):
        probs.append(Problem(f, "depth.replace", f"expected a non-empty list of [from, to] string pairs, got {rep!r}"))
    if not is_number(v.get("units_per_m")) or float(v["units_per_m"]) <= 0:
        probs.append(Problem(f, "depth.units_per_m", f"required: a positive number, got {v.get('units_per_m')!r}"))
    return probs


def output_size(size: tuple[int, int], resize: Any) -> tuple[int, int]:
    """Image size after ``resize`` (``[w, h]``, longest side, or None)."""
    if resize is None:
        return size
    if isinstance(resize, list):
        return int(resize[0]), int(resize[1])
    s = resize / max(size)
    return int(round(size[0] * s)), int(round(size[1] * s))


def parse_pair_line(parts: list[str], f: str, field: str) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray]:
    """``(rot0, rot1, K0, K1, T_0to1)`` of one tokenised line (names excluded); errors name the line."""
    nums = parts[2:]
    if len(parts) < 2 or len(nums) != N_NUMBERS:
        raise ManifestError([Problem(f, field, f"expected 2 image names and {N_NUMBERS} numbers "
                                               f"(rot0 rot1 K0(9) K1(9) T_0to1(16)), got {max(len(parts) - 2, 0)} numbers")])
    try:
        vals = np.array([float(x) for x in nums])
    except ValueError:
        raise ManifestError([Problem(f, field, f"not a number among {nums}")]) from None
    if not np.all(np.isfinite(vals)):
        raise ManifestError([Problem(f, field, "non-finite number")])
    rots = vals[:2]
    if not np.all(np.isin(rots, [0, 1, 2, 3])):
        raise ManifestError([Problem(f, field, f"rot0/rot1 must be 0, 1, 2 or 3 (quarter turns), got {rots.tolist()}")])
    K0, K1 = vals[2:11].reshape(3, 3), vals[11:20].reshape(3, 3)
    for K in (K0, K1):
        if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])):
            raise ManifestError([Problem(f, field, f"not a calibration matrix: {K.tolist()}")])
    try:
        T = check_se3(vals[20:].reshape(4, 4), "T_0to1", atol=1e-3)
    except GeometryError as exc:
        raise ManifestError([Problem(f, field, f"T_0to1 is not a rigid transform ({exc})")]) from None
    return int(rots[0]), int(rots[1]), K0, K1, T


class PairsAdapter:
    """SuperGlue/LoFTR pair lists: each pair an encounter of two single-frame robots."""

    name = "pairs"
    top_level_fields: tuple[str, ...] = FIELDS

    def validate(self, manifest: Manifest) -> list[Problem]:
        f, raw = str(manifest.path), manifest.raw
        probs = []
        if not isinstance(raw.get("pairs"), str) or not raw.get("pairs"):
            probs.append(Problem(f, "pairs", f"required: the pair list file, got {type_name(raw.get('pairs'))}"))
        if "images" in raw and not isinstance(raw["images"], str):
            probs.append(Problem(f, "images", f"expected a folder path, got {type_name(raw['images'])}"))
        mp = raw.get("max_pairs")
        if mp is not None and (isinstance(mp, bool) or not isinstance(mp, int) or mp < 1):
            probs.append(Problem(f, "max_pairs", f"expected an integer >= 1 or null, got {mp!r}"))
        probs += covisibility.validate(manifest)
        if manifest.encounters is not None:
            probs.append(Problem(f, "encounters", "not used by the pairs adapter (every line is an encounter); remove it"))
        return probs + _resize_problems(raw.get("resize"), f) + _depth_problems(raw.get("depth"), f)

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        raw = manifest.raw
        path = manifest.resolve(raw["pairs"])
        f = str(path)
        if not path.is_file():
            raise ManifestError([Problem(f, "pairs", "pair list file not found")])
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ManifestError([Problem(f, "pairs", f"cannot read the pair list: {exc}")]) from None
        folder = manifest.resolve(raw.get("images", "."))
        encounters: list[Encounter] = []
        for k, ln in enumerate(text.splitlines(), 1):
            if not ln.strip() or ln.lstrip().startswith("#"):
                continue
            if raw.get("max_pairs") is not None and len(encounters) >= raw["max_pairs"]:
                break
            try:
                enc = self._pair(manifest, ln.split(), folder, f, f"pairs line {k}", len(encounters))
            except ManifestError as exc:
                report.extend(exc.problems)
                if len(report.problems) >= MAX_LINE_PROBLEMS:
                    report.add(Problem(f, "pairs", "too many bad lines; stopped reading"))
                    break
                continue
            covisibility.attach(manifest, enc, report, progress=False)
            encounters.append(enc)
        if not encounters and not report.problems:
            report.add(Problem(f, "pairs", "no pairs in the list"))
        report.raise_if_problems()
        return Setting(name=manifest.name, encounters=encounters, metric_depth=manifest.metric_depth,
                       meta={"manifest": str(manifest.path), "adapter": self.name, "pairs": f})

    def _pair(self, m: Manifest, parts: list[str], folder: Path, f: str, field: str, index: int) -> Encounter:
        rot0, rot1, K0, K1, T_0to1 = parse_pair_line(parts, f, field)
        raw = m.raw
        streams = []
        T_world = [np.eye(4), se3_inverse(T_0to1)]  # camera-to-world with world = camera 0
        for r, (name, rot, K) in enumerate(((parts[0], rot0, K0), (parts[1], rot1, K1))):
            img = (folder / name).resolve()
            size = image_size(img) if img.is_file() else None
            if size is None:
                raise ManifestError([Problem(str(img), field, "image file not found" if not img.is_file()
                                             else "cannot decode image")])
            out = output_size(size, raw.get("resize"))
            try:
                Ks = CameraIntrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=size[0], height=size[1])
            except SceneError as exc:
                raise ManifestError([Problem(f, field, str(exc))]) from None
            depth = None
            if raw.get("depth"):
                dname = name
                for a, b in raw["depth"]["replace"]:
                    dname = dname.replace(a, b)
                dpath = (folder / dname).resolve()
                if not dpath.is_file():
                    raise ManifestError([Problem(str(dpath), field, f"depth file of {name} not found (depth.replace)")])
                depth = [DepthFile(dpath, float(raw["depth"]["units_per_m"]), (), None, out, rot)]
            # T_world_rot = T_world_cam @ inv(T_rot_cam): the rotated camera in the same world
            T_wc = T_world[r] @ se3_inverse(rot90_T(rot))
            streams.append(RobotStream(
                robot_id=f"r{r}", intrinsics=transformed_intrinsics(Ks, None, out, rot), stamps_s=np.zeros(1),
                images=[ImageFile(img, None, out, rot)], T_world_cam=T_wc[None], depth=depth, frame_ids=[name]))
        return Encounter(name=f"pair{index:05d}", robots=streams,
                         meta={"sync": "index", "manifest": str(m.path), "line": field, "names": parts[:2]})

