"""Readers for the small text files datasets come with; every error names file, field and line.

* trajectories: TUM (``stamp_s tx ty tz qx qy qz qw``; a first row of column names is skipped);
  EuRoC ground truth CSV (``#timestamp [ns], p_RS_R_x, p_RS_R_y, p_RS_R_z, q_RS_w, q_RS_x,
  q_RS_y, q_RS_z, ...``); plain CSV with a header naming at least ``stamp_s,tx,ty,tz,qx,qy,qz,qw``;
* camera intrinsics YAML (``width height fx fy cx cy [distortion]``, or EuRoC's
  ``sensor.yaml`` with ``resolution`` / ``intrinsics`` / ``distortion_coefficients``);
* small matrix text files (3x3 ``camera-intrinsics.txt``, 4x4 ``frame-*.pose.txt``);
* a 4x4 extrinsic (``identity``, a 4x4 nested list, or a YAML file with ``T_BS``);
* image lists: a folder of ``<stamp>.png|jpg`` or a text file of ``stamp path`` lines;
* image headers (PNG size and bit depth without decoding).

Readers raise :class:`~cerpe.datasets.manifest.ManifestError` with one
:class:`~cerpe.datasets.manifest.Problem` per bad line (up to a cap).
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..geometry import GeometryError, check_se3, se3_from_tq_xyzw
from ..scene import CameraIntrinsics, SceneError
from ..tum import format_tum  # noqa: F401  (re-exported: the one TUM writer)
from .manifest import ManifestError, Problem, is_number, read_yaml, type_name

TRAJECTORY_FORMATS: tuple[str, ...] = ("tum", "euroc", "csv")
CSV_COLUMNS: tuple[str, ...] = ("stamp_s", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
NONFINITE_ROWS = "ground-truth trajectory rows with NaN or inf (skipped)"  # the counted reason
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES: tuple[str, ...] = (".png", ".npy", ".exr", ".tif", ".tiff")
STAMP_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
MAX_LINE_PROBLEMS = 10
QUAT_NORM_TOL = 0.05  # a quaternion further than this from unit norm is a format error, not noise
DISTORTION_COUNTS: tuple[int, ...] = (0, 4, 5, 8, 12, 14)  # what OpenCV's distortion models take


@dataclass
class Trajectory:
    """Poses read from a file.

    Attributes:
        stamps_s: ``[N]`` strictly increasing seconds.
        T_world_body: ``[N,4,4]`` body-to-world poses.
        n_nan_rows: rows skipped because they hold NaN or inf (e.g. tracking lost).
    """

    stamps_s: np.ndarray
    T_world_body: np.ndarray
    n_nan_rows: int = 0


def _rows_tum(text: str) -> list[tuple[int, list[str]]]:
    return [(k, ln.split()) for k, ln in enumerate(text.splitlines(), 1)
            if ln.strip() and not ln.lstrip().startswith("#")]


def _rows_csv(text: str) -> list[tuple[int, list[str]]]:
    out = []
    for k, row in enumerate(csv.reader(io.StringIO(text)), 1):
        if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
            continue
        out.append((k, [c.strip() for c in row]))
    return out


def read_trajectory(path: Path, fmt: str, field: str) -> Trajectory:
    """Read a trajectory file (see module doc for the formats).

    Rows holding NaN or inf are skipped and counted (``Trajectory.n_nan_rows``); a wrong
    column count, an unparsable number, a zero-norm or far-from-unit quaternion,
    non-increasing stamps or an empty file raise :class:`ManifestError`.
    """
    f = str(path)
    if fmt not in TRAJECTORY_FORMATS:
        raise ManifestError([Problem(f, field, f"unknown trajectory format {fmt!r}; expected one of {', '.join(TRAJECTORY_FORMATS)}")])
    if not path.is_file():
        raise ManifestError([Problem(f, field, "trajectory file not found")])
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError([Problem(f, field, f"cannot read trajectory: {exc}")]) from None
    probs: list[Problem] = []
    cols: list[int]
    scale = 1.0
    wxyz = False
    if fmt == "tum":
        rows = _rows_tum(text)
        if rows and rows[0][1] and rows[0][1][0].lower().lstrip("#") in ("timestamp", "stamp", "stamp_s", "time"):
            rows = rows[1:]  # an uncommented column-name header ("timestamp tx ty tz qx qy qz qw")
        cols = list(range(8))
    elif fmt == "euroc":
        rows = _rows_csv(text)
        cols, scale, wxyz = list(range(8)), 1e-9, True
    else:
        rows = _rows_csv(text)
        if not rows:
            raise ManifestError([Problem(f, field, f"empty CSV trajectory; expected a header {','.join(CSV_COLUMNS)}")])
        k0, header = rows[0]
        header = [h.lower() for h in header]
        missing = [c for c in CSV_COLUMNS if c not in header]
        if missing:
            raise ManifestError([Problem(f, f"{field} line {k0}", f"CSV header lacks column(s) {', '.join(missing)}; expected {','.join(CSV_COLUMNS)}")])
        cols = [header.index(c) for c in CSV_COLUMNS]
        rows = rows[1:]
    need = max(cols) + 1
    stamps, ts, qs = [], [], []
    n_nan = 0
    for k, parts in rows:
        if len(parts) < need:
            probs.append(Problem(f, f"{field} line {k}", f"expected at least {need} columns ({fmt}), got {len(parts)}"))
        else:
            try:
                vals = [float(parts[c]) for c in cols]
            except ValueError:
                probs.append(Problem(f, f"{field} line {k}", f"not a number in {parts[:need]}"))
            else:
                if not all(np.isfinite(vals)):
                    n_nan += 1
                    continue
                q = np.array(vals[4:8])
                if wxyz:
                    q = np.array([q[1], q[2], q[3], q[0]])
                n = float(np.linalg.norm(q))
                if n < 1e-9:
                    probs.append(Problem(f, f"{field} line {k}", "zero-norm quaternion"))
                elif abs(n - 1.0) > QUAT_NORM_TOL:
                    probs.append(Problem(f, f"{field} line {k}", f"quaternion norm {n:.4f} is not 1 (wrong column order or format?)"))
                else:
                    if stamps and vals[0] * scale <= stamps[-1][0]:
                        probs.append(Problem(f, f"{field} line {k}", f"stamp {parts[cols[0]]} is not after the previous row's (stamps must increase)"))
                    stamps.append((vals[0] * scale, k))
                    ts.append(vals[1:4])
                    qs.append(q / n)
        if len(probs) >= MAX_LINE_PROBLEMS:
            probs.append(Problem(f, field, "too many bad lines; stopped reading"))
            break
    if probs:
        raise ManifestError(probs)
    if not stamps:
        msg = "trajectory has no poses" + (f" ({n_nan} rows with NaN or inf skipped)" if n_nan else "")
        raise ManifestError([Problem(f, field, msg)])
    T = se3_from_tq_xyzw(np.array(ts), np.array(qs))
    return Trajectory(np.array([s for s, _ in stamps], dtype=np.float64), T, n_nan)


def read_camera(path: Path, field: str) -> tuple[CameraIntrinsics, list[float]]:
    """Read ``camera.yaml`` (``width height fx fy cx cy [distortion]``) or EuRoC ``sensor.yaml``.

    Returns the pinhole intrinsics and the distortion coefficients as written
    (OpenCV order ``k1 k2 p1 p2 [k3 ...]``; ``[]`` when absent).
    """
    f = str(path)
    doc = read_yaml(path, "camera intrinsics", field)
    if not isinstance(doc, dict):
        raise ManifestError([Problem(f, field, f"expected a YAML mapping with width, height, fx, fy, cx, cy; got {type_name(doc)}")])
    if "intrinsics" in doc and "resolution" in doc:  # EuRoC sensor.yaml
        intr, res = doc.get("intrinsics"), doc.get("resolution")
        if not (isinstance(intr, list) and len(intr) == 4 and isinstance(res, list) and len(res) == 2):
            raise ManifestError([Problem(f, field, "EuRoC sensor.yaml: expected intrinsics [fu, fv, cu, cv] and resolution [w, h]")])
        vals = dict(zip(("fx", "fy", "cx", "cy"), intr)) | {"width": res[0], "height": res[1]}
        dist = doc.get("distortion_coefficients", [])
    else:
        vals = {k: doc.get(k) for k in ("width", "height", "fx", "fy", "cx", "cy")}
        dist = doc.get("distortion", [])
    probs = []
    for k, v in vals.items():
        if not is_number(v):
            probs.append(Problem(f, f"{field}.{k}", f"expected a finite number, got {v!r}"))
        elif k in ("width", "height") and (float(v) != int(v) or int(v) <= 0):
            probs.append(Problem(f, f"{field}.{k}", f"expected a positive integer, got {v!r}"))
    if dist is None:
        dist = []
    if not isinstance(dist, list) or not all(is_number(d) for d in dist):
        probs.append(Problem(f, f"{field}.distortion", f"expected a list of numbers, got {dist!r}"))
    elif len(dist) not in DISTORTION_COUNTS:
        probs.append(Problem(f, f"{field}.distortion", f"{len(dist)} coefficients; OpenCV's models take "
                                                       f"{', '.join(map(str, DISTORTION_COUNTS[1:]))} "
                                                       "(k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]])"))
    if probs:
        raise ManifestError(probs)
    try:
        K = CameraIntrinsics(fx=float(vals["fx"]), fy=float(vals["fy"]), cx=float(vals["cx"]), cy=float(vals["cy"]),
                             width=int(vals["width"]), height=int(vals["height"]))
    except SceneError as exc:
        raise ManifestError([Problem(f, field, str(exc))]) from None
    why = intrinsics_problem(K)
    if why:
        raise ManifestError([Problem(f, field, why)])
    return K, [float(d) for d in dist]


def intrinsics_problem(K: CameraIntrinsics) -> str:
    """Why ``K`` cannot describe its image (``""`` when it can): the principal point must lie in the
    image (``0 <= cx <= width``, ``0 <= cy <= height``); ``CameraIntrinsics`` itself refuses focal
    lengths <= 0. A principal point far outside means a wrong unit, a swapped field or another camera."""
    if 0 <= K.cx <= K.width and 0 <= K.cy <= K.height:
        return ""
    return (f"principal point (cx, cy) = ({K.cx:g}, {K.cy:g}) px lies outside the {K.width}x{K.height} image "
            f"(expected 0 <= cx <= {K.width}, 0 <= cy <= {K.height})")


def read_intrinsics(path: Path, field: str) -> CameraIntrinsics:
    """Read a pinhole camera file (see :func:`read_camera`).

    Non-zero distortion raises: every consumer assumes undistorted pinhole images
    (the ``tum-rgbd`` adapter undistorts itself and reads :func:`read_camera`).
    """
    K, dist = read_camera(path, field)
    if any(abs(d) > 1e-12 for d in dist):
        raise ManifestError([Problem(str(path), f"{field}.distortion", f"non-zero distortion {dist}: images must be undistorted first (cerpe assumes pinhole images)")])
    return K


def read_matrix(path: Path, field: str, shape: tuple[int, int], what: str) -> np.ndarray:
    """A whitespace-separated ``rows x cols`` matrix file (``#`` comments); errors name file and line.

    E.g. 3DMatch/SUN3D ``camera-intrinsics.txt`` (3x3) and 7-Scenes ``frame-*.pose.txt`` (4x4).
    Non-finite entries are kept (callers decide what they mean).
    """
    f = str(path)
    if not path.is_file():
        raise ManifestError([Problem(f, field, f"{what} file not found")])
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError([Problem(f, field, f"cannot read {what}: {exc}")]) from None
    rows, cols = shape
    out: list[list[float]] = []
    for k, ln in enumerate(text.splitlines(), 1):
        if not ln.strip() or ln.lstrip().startswith("#"):
            continue
        parts = ln.split()
        if len(out) == rows:
            raise ManifestError([Problem(f, f"{field} line {k}", f"{what}: more than {rows} rows (expected a {rows}x{cols} matrix)")])
        if len(parts) != cols:
            raise ManifestError([Problem(f, f"{field} line {k}", f"{what}: expected {cols} numbers, got {len(parts)}")])
        try:
            out.append([float(x) for x in parts])
        except ValueError:
            raise ManifestError([Problem(f, f"{field} line {k}", f"{what}: not a number in {parts}")]) from None
    if len(out) != rows:
        n_lines = len(text.splitlines())
        raise ManifestError([Problem(f, f"{field} line {n_lines + 1}", f"{what}: {len(out)} rows, expected a {rows}x{cols} matrix")])
    return np.array(out, dtype=np.float64)


def parse_transform(value: Any, field: str, manifest_file: str, resolve=None) -> np.ndarray:
    """A 4x4 rigid transform from ``identity``, a 4x4 nested list, or a YAML file with ``T_BS``.

    Args:
        value: the manifest value.
        field: dotted field path for messages.
        manifest_file: the manifest, for messages.
        resolve: ``str -> Path`` for relative file names.
    """
    if value is None or value == "identity":
        return np.eye(4)
    src = manifest_file
    if isinstance(value, str):
        path = resolve(value) if resolve else Path(value)
        src = str(path)
        doc = read_yaml(path, "extrinsic", field)
        data = None
        if isinstance(doc, dict):
            for key in ("T_BS", "T_body_cam"):
                if key in doc:
                    data = doc[key]
                    data = data.get("data") if isinstance(data, dict) else data
                    break
        if data is None:
            raise ManifestError([Problem(src, field, "expected a YAML file with T_BS: {data: [16 numbers, row-major]}")])
        value = data
    arr = None
    if isinstance(value, list):
        flat = value
        if all(isinstance(r, list) for r in value):
            flat = [x for r in value for x in r]
        if len(flat) == 16 and all(is_number(x) for x in flat):
            arr = np.array(flat, dtype=np.float64).reshape(4, 4)
        elif len(flat) == 12 and all(is_number(x) for x in flat):
            arr = np.vstack([np.array(flat, dtype=np.float64).reshape(3, 4), [0, 0, 0, 1]])
    if arr is None:
        raise ManifestError([Problem(src, field, f"expected 'identity' or a 4x4 list of finite numbers, got {value!r}")])
    try:
        return check_se3(arr, "T", atol=1e-4)
    except GeometryError as exc:
        raise ManifestError([Problem(src, field, f"not a rigid transform ({str(exc).removeprefix('T: ')})")]) from None


def ground_truth_problems(rob: dict, f: str, fr: str,
                          positive: Sequence[str] = ("gt_tolerance_s", "interpolate_max_gap_s")) -> list[Problem]:
    """Problems of a robot's ground-truth fields, no file access: ``positive`` numbers, ``interpolate`` a
    boolean, ``T_body_cam`` ``identity``, a 4x4 list (checked) or a YAML file name."""
    probs = [Problem(f, f"{fr}.{k}", f"expected a positive number, got {rob[k]!r}") for k in positive
             if k in rob and (not is_number(rob[k]) or float(rob[k]) <= 0)]
    if "interpolate" in rob and not isinstance(rob["interpolate"], bool):
        probs.append(Problem(f, f"{fr}.interpolate", f"expected true or false, got {rob['interpolate']!r}"))
    tb = rob.get("T_body_cam", "identity")
    if not (tb == "identity" or isinstance(tb, (list, str))):
        probs.append(Problem(f, f"{fr}.T_body_cam", f"expected 'identity', a 4x4 list or a YAML file, got {type_name(tb)}"))
    elif isinstance(tb, list):
        try:
            parse_transform(tb, f"{fr}.T_body_cam", f)
        except ManifestError as exc:
            probs += exc.problems
    return probs


def parse_stamp(text: str, units: str) -> float:
    return float(text) * STAMP_UNITS[units]


def read_list_file(path: Path, field: str, units: str = "s") -> tuple[np.ndarray, list[Path], list[int]]:
    """A text file of ``stamp path`` lines (TUM's ``rgb.txt``/``depth.txt``; ``#`` comments).

    Paths are relative to the file's folder; stamps must increase. Returns the
    stamps (seconds), the resolved paths and each entry's line number.
    """
    f = str(path)
    if not path.is_file():
        raise ManifestError([Problem(f, field, "list file not found")])
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError([Problem(f, field, f"cannot read image list: {exc}")]) from None
    probs: list[Problem] = []
    stamps: list[float] = []
    paths: list[Path] = []
    lines: list[int] = []
    for k, ln in enumerate(text.splitlines(), 1):
        if not ln.strip() or ln.lstrip().startswith("#"):
            continue
        parts = ln.split()
        if len(parts) < 2:
            probs.append(Problem(f, f"{field} line {k}", "expected 'stamp path'"))
            continue
        try:
            s = parse_stamp(parts[0], units)
        except ValueError:
            probs.append(Problem(f, f"{field} line {k}", f"stamp {parts[0]!r} is not a number"))
            continue
        if not np.isfinite(s):
            probs.append(Problem(f, f"{field} line {k}", f"stamp {parts[0]!r} is not finite"))
            continue
        if stamps and s <= stamps[-1]:
            probs.append(Problem(f, f"{field} line {k}", f"stamp {parts[0]} is not after the previous line's (stamps must increase)"))
        stamps.append(s)
        paths.append((path.parent / parts[1]).resolve())
        lines.append(k)
        if len(probs) >= MAX_LINE_PROBLEMS:
            break
    if probs:
        raise ManifestError(probs)
    if not stamps:
        raise ManifestError([Problem(f, field, "no 'stamp path' lines found")])
    return np.array(stamps, dtype=np.float64), paths, lines


def list_images(path: Path, field: str, units: str = "s") -> tuple[np.ndarray, list[Path]]:
    """Image stamps and files, sorted by stamp.

    Args:
        path: a folder of ``<stamp>.png|jpg|jpeg`` (the stem is the stamp) or a text
            file with ``stamp path`` per line (see :func:`read_list_file`).
        field: dotted field path for messages.
        units: unit of the stamps in names/lines: ``s``, ``ms``, ``us`` or ``ns``.
    """
    f = str(path)
    if path.is_file():
        stamps, paths, _ = read_list_file(path, field, units)
        return stamps, paths
    if not path.is_dir():
        raise ManifestError([Problem(f, field, "image folder or list file not found")])
    probs: list[Problem] = []
    items = []
    for p in sorted(path.iterdir()):
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        try:
            items.append((parse_stamp(p.stem, units), p))
        except ValueError:
            probs.append(Problem(str(p), field, f"image file name must be its stamp in {units} (like 1341847980.722988.png)"))
    if probs:
        raise ManifestError(probs[:MAX_LINE_PROBLEMS])
    items.sort(key=lambda x: x[0])
    for (a, pa), (b, pb) in zip(items, items[1:]):
        if b == a:
            probs.append(Problem(f, field, f"two images with the same stamp: {pa.name}, {pb.name}"))
    if probs:
        raise ManifestError(probs)
    if not items:
        raise ManifestError([Problem(f, field, f"no images ({', '.join(IMAGE_SUFFIXES)}) found")])
    return np.array([s for s, _ in items], dtype=np.float64), [p for _, p in items]


def find_depth_files(folder: Path, stems: Sequence[str]) -> list[Path | None]:
    """Depth file per image stem in ``folder`` (first existing suffix), None where absent."""
    present: dict[str, Path] = {}
    for p in folder.iterdir():
        if p.suffix.lower() in DEPTH_SUFFIXES and p.stem not in present:
            present[p.stem] = p
    return [present.get(s) for s in stems]


def image_size(path: Path) -> tuple[int, int] | None:
    """``(width, height)`` of an image file without keeping it, or None if undecodable."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        return None
    return int(img.shape[1]), int(img.shape[0])


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_header(path: Path) -> tuple[int, int, int, int] | None:
    """``(width, height, bit_depth, colour_type)`` from a PNG's IHDR chunk (24 bytes read), None if not a PNG."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(26)
    except OSError:
        return None
    if len(head) < 26 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big"), head[24], head[25]


def file_problems(items: Sequence[tuple[Path, str]], what: str, size: tuple[int, int], min_bits: int = 0,
                  cap: int = 5) -> list[Problem]:
    """Files among ``(path, field)`` that are missing, or whose PNG header says another size or too few bits.

    Reads 26 bytes per PNG (other formats are checked when decoded, by ``cerpe check``);
    stops after ``cap`` problems.
    """
    probs = []
    for p, field in items:
        hdr = png_header(p) if p.is_file() else None
        if not p.is_file():
            probs.append(Problem(str(p), field, f"{what} file not found"))
        elif hdr is not None and hdr[:2] != tuple(size):
            probs.append(Problem(str(p), field, f"{what} is {hdr[0]}x{hdr[1]}, expected {size[0]}x{size[1]}"))
        elif hdr is not None and hdr[2] < min_bits:
            probs.append(Problem(str(p), field, f"{what} is a {hdr[2]}-bit PNG, expected {min_bits}-bit"))
        if len(probs) >= cap:
            break
    return probs


def depth_bits(path: Path) -> int | None:
    """Bits per depth value stored in an image file (PNG header, else decoded); None for arrays or undecodable files."""
    if Path(path).suffix.lower() == ".npy":
        return None
    hdr = png_header(path)
    if hdr is not None:
        return hdr[2]
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return None if img is None else int(img.dtype.itemsize * 8)
