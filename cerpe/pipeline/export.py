"""Export a run folder's estimates as COLMAP text models, one per encounter and ego robot.

Usage: ``cerpe export RUNDIR [--manifest M] [--encounter E ...] [--ego R ...] [--out DIR]``

What the ego robot believed, where COLMAP's viewer (or pycolmap, or any tool reading COLMAP's text
format) can show it: its own frames at its metric odometry pose ``X_i^t`` and, at every step with an
estimate ``T_cj_ci``, the other robot's frame of that step at ``X_i^t inv(T_cj_ci)``. Beside it, the
same images at their ground-truth poses in the ego's first ground-truth camera frame, so COLMAP's
``model_comparer`` (which pairs images by name) or an overlay shows where each estimate went wrong::

    DIR/<encounter>/<ego>/estimate/{cameras,images,points3D}.txt
    DIR/<encounter>/<ego>/gt/{cameras,images,points3D}.txt      (frames with ground truth only)
    DIR/<encounter>/images/<robot>/<step>_<file name>           the images (links to plain files)

    colmap gui --import_path DIR/<enc>/<ego>/estimate --image_path DIR/<enc>/images --database_path db.db

Conventions: COLMAP stores ``cam_from_world`` (``QW QX QY QZ TX TY TZ``, scalar-first) and puts the
centre of the top-left pixel at (0.5, 0.5), so ``cx``/``cy`` are cerpe's (OpenCV: pixel centres at
integers) plus 0.5. One ``PINHOLE`` camera per robot; ``points3D.txt`` is empty (cerpe keeps no map).
Image names are ``<robot>/<step, 6 digits>_<file name>``: unique per robot and step even where two
robots read the same file (a sequence played forwards and backwards). Only runs of the cerpe methods
carry odometry; a baseline's run (per-frame estimates, no trajectory) is refused with the reason.

The run folder is read, never re-run: the manifest (``run.json``'s, or ``--manifest`` for a moved
one) gives intrinsics, image files and ground truth only.
"""
from __future__ import annotations

import argparse
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from ..atomicio import atomic_write_text, ensure_dir
from ..errors import CerpeError
from ..geometry import is_finite_transform, matrix_to_quat_wxyz, se3_inverse
from ..scene import CameraIntrinsics, Encounter, Setting
from ..runfolder.provenance import file_digest
from ..runfolder.read import load_run
from .evaluate import poses_from_columns

log = logging.getLogger(__name__)

POINTS3D_HEADER = "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, " \
                  "TRACK[] as (IMAGE_ID, POINT2D_IDX)\n# Number of points: 0, mean track length: 0\n"


class ExportError(CerpeError, ValueError):
    """A run folder or manifest that cannot be exported (names the file and the field)."""


@dataclass(frozen=True)
class ColmapImage:
    """One image of a model: ``T_cam_world`` ``[4,4]`` (COLMAP's cam_from_world) of ``camera_id``."""

    image_id: int
    camera_id: int
    name: str
    T_cam_world: np.ndarray


# --------------------------------------------------------------------------- pure: text
def cameras_text(cameras: dict[int, CameraIntrinsics]) -> str:
    """``cameras.txt``: one ``PINHOLE`` line per camera id, principal point in COLMAP's pixel convention."""
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]", f"# Number of cameras: {len(cameras)}"]
    for cid, K in sorted(cameras.items()):
        lines.append(f"{cid} PINHOLE {int(K.width)} {int(K.height)} "
                     f"{K.fx:.10g} {K.fy:.10g} {K.cx + 0.5:.10g} {K.cy + 0.5:.10g}")
    return "\n".join(lines) + "\n"


def images_text(images: Sequence[ColmapImage]) -> str:
    """``images.txt``: two lines per image (the pose line and an empty keypoint line)."""
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(images)}, mean observations per image: 0"]
    for im in images:
        q = matrix_to_quat_wxyz(im.T_cam_world[:3, :3])
        t = im.T_cam_world[:3, 3]
        lines.append(f"{im.image_id} " + " ".join(f"{v:.12g}" for v in (*q, *t)) + f" {im.camera_id} {im.name}")
        lines.append("")
    return "\n".join(lines) + "\n"


def image_name(robot: str, step: int, ref: object) -> str:
    """``<robot>/<step:06d>_<file name>`` (whitespace, which COLMAP's text format cannot hold, as ``_``).

    A plain file keeps its name; an image the adapter transforms on reading (an undistorted or
    resized :class:`~cerpe.datasets.imageref.ImageFile`) or one held in memory is written as PNG."""
    if isinstance(ref, (str, os.PathLike)):
        base = Path(ref).name
    elif isinstance(getattr(ref, "path", None), (str, os.PathLike)):
        base = Path(ref.path).stem + ".png"
    else:
        base = "frame.png"
    return re.sub(r"\s", "_", f"{robot}/{step:06d}_{base}")


# --------------------------------------------------------------------------- run folder -> models
def encounter_models(enc: Encounter, steps: pd.DataFrame, robots: pd.DataFrame, ego: str
                     ) -> tuple[dict[int, CameraIntrinsics], list[ColmapImage], list[ColmapImage], dict[str, int]]:
    """The estimate and ground-truth models of ``ego`` in encounter ``enc``.

    ``steps`` / ``robots``: that encounter's ``steps.csv`` / ``robots.csv`` rows. Returns the cameras
    (id = robot index + 1), the estimate's images (world: the ego's odometry frame), the ground
    truth's (world: the ego's first camera with ground truth; only images that also have ground truth)
    and counts of what was left out (``no-odometry``, ``no-estimate``, ``no-gt``).
    """
    ids = [r.robot_id for r in enc.robots]
    if ego not in ids:
        raise ExportError(f"encounter {enc.name}: no robot {ego!r}; robots: {', '.join(ids)}")
    i = ids.index(ego)
    cameras = {k + 1: r.intrinsics for k, r in enumerate(enc.robots)}
    skipped = {"no-odometry": 0, "no-estimate": 0, "no-gt": 0}
    est: list[ColmapImage] = []
    gt_poses: list[tuple[str, int, np.ndarray | None]] = []  # name, camera id, T_world_cam (GT)
    odo = robots[robots["robot"].astype(str) == ego].drop_duplicates("step", keep="last")
    X_by_step = dict(zip(odo["step"].astype(int), poses_from_columns(odo, "odom")))
    pairs = steps[steps["ego"].astype(str) == ego]
    T_est = poses_from_columns(pairs, "est")
    for t in range(enc.n_steps):
        X = X_by_step.get(t)
        if X is None or not is_finite_transform(X):
            skipped["no-odometry"] += 1
            continue
        name = image_name(ego, t, enc.robots[i].images[t])
        est.append(ColmapImage(len(est) + 1, i + 1, name, se3_inverse(X)))
        gt_poses.append((name, i + 1, enc.robots[i].T_world_cam[t]))
        for k in np.flatnonzero(pairs["step"].to_numpy() == t):
            other = str(pairs["other"].iloc[k])
            if other not in ids:
                raise ExportError(f"steps.csv of {enc.name}: other robot {other!r} is not in the manifest's "
                                  f"encounter (robots: {', '.join(ids)}): another manifest?")
            j = ids.index(other)
            T_cj_ci = T_est[k]
            if not is_finite_transform(T_cj_ci):
                skipped["no-estimate"] += 1
                continue
            name_j = image_name(other, t, enc.robots[j].images[t])
            est.append(ColmapImage(len(est) + 1, j + 1, name_j, T_cj_ci @ se3_inverse(X)))
            gt_poses.append((name_j, j + 1, enc.robots[j].T_world_cam[t]))
    T_world_c0 = next((T for name, cid, T in gt_poses if cid == i + 1 and is_finite_transform(T)), None)
    gt: list[ColmapImage] = []
    for name, cid, T in gt_poses:
        if T_world_c0 is None or not is_finite_transform(T):
            skipped["no-gt"] += 1
            continue
        gt.append(ColmapImage(len(gt) + 1, cid, name, se3_inverse(T) @ T_world_c0))
    return cameras, est, gt, skipped


def _place_images(enc: Encounter, images: Sequence[ColmapImage], folder: Path) -> int:
    """Each model image under ``folder`` by its name: a link to a plain dataset file, else the pixels cerpe
    read, as PNG. Returns how many could not be placed (missing or corrupt: logged, not raised)."""
    import cv2

    from ..atomicio import atomic_write_bytes
    from ..scene import SceneError, load_rgb

    refs = {}
    for r in enc.robots:
        for t, ref in enumerate(r.images):
            refs[image_name(r.robot_id, t, ref)] = (r.robot_id, t, ref)
    failed = 0
    for name in sorted({im.name for im in images}):
        robot, t, ref = refs[name]
        target = folder / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.is_symlink():
            target.unlink()
        if isinstance(ref, (str, os.PathLike)):
            if Path(ref).is_file():
                target.symlink_to(Path(ref).resolve())
                continue
            log.warning("%s: robot %s step %d: image file not found: %s", enc.name, robot, t, ref)
            failed += 1
            continue
        try:
            rgb = load_rgb(ref, what=f"robot {robot} step {t}")
        except SceneError as exc:
            log.warning("%s: %s", enc.name, exc)
            failed += 1
            continue
        atomic_write_bytes(target, cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))[1].tobytes())
    return failed


def _write_model(folder: Path, cameras: dict[int, CameraIntrinsics], images: Sequence[ColmapImage]) -> None:
    ensure_dir(folder, "COLMAP model folder")
    atomic_write_text(folder / "cameras.txt", cameras_text(cameras))
    atomic_write_text(folder / "images.txt", images_text(images))
    atomic_write_text(folder / "points3D.txt", POINTS3D_HEADER)


def export_colmap(rundir: Path | str, out: Path | str | None = None, manifest: Path | str | None = None,
                  encounters: Sequence[str] = (), egos: Sequence[str] = (), link_images: bool = True,
                  setting: Setting | None = None) -> list[Path]:
    """Write the COLMAP models of a run folder (module docstring); returns the model folders written.

    ``setting``: the loaded data the run read, instead of loading the manifest (programmatic runs,
    tests). Raises :class:`ExportError` naming the file and field for a run without odometry, an
    encounter or robot the run or manifest lacks, or a manifest that no longer loads.
    """
    from ..datasets import ManifestError, load_setting

    run = load_run(rundir)
    rundir = Path(rundir)
    out = Path(out) if out is not None else rundir / "colmap"
    mpath = Path(manifest) if manifest is not None else Path(str(run.meta.get("manifest", "")))
    if setting is None and not mpath.is_file():
        where = "--manifest" if manifest is not None else f"{rundir / 'run.json'}: field 'manifest'"
        raise ExportError(f"{where}: manifest {mpath} not found (pass --manifest with the manifest the run read)")
    if "odom_tx" not in run.robots.columns or not np.isfinite(run.robots["odom_tx"].to_numpy(float)).any():
        raise ExportError(f"{rundir}: method {run.method!r} writes no odometry (robots.csv has no finite "
                          f"odom_* columns): only the cerpe methods' runs can be exported")
    if setting is None:
        sha = run.meta["config"].get("manifest_sha")
        if sha and file_digest(mpath) != sha:
            log.warning("%s changed since the run read it (sha %s, run.json says %s): check that its encounters, "
                        "intrinsics and images are still the run's", mpath, file_digest(mpath), sha)
        try:
            setting = load_setting(mpath)
        except ManifestError as exc:
            raise ExportError(f"{mpath}: the manifest does not load: {exc}") from None
    by_name = {e.name: e for e in setting.encounters}
    run_encs = sorted(set(run.steps["encounter"]))
    for name in encounters:
        if name not in run_encs:
            raise ExportError(f"{rundir}: no encounter {name!r}; the run has: {', '.join(run_encs)}")
    written: list[Path] = []
    for name in encounters or run_encs:
        enc = by_name.get(name)
        if enc is None:
            raise ExportError(f"{mpath}: no encounter {name!r} in the manifest (the run has it): another manifest?")
        steps = run.steps[run.steps["encounter"] == name]
        robots = run.robots[run.robots["encounter"] == name]
        all_images: list[ColmapImage] = []
        # by default the robots the run has odometry of (one, in an online robot's run folder)
        has_odom = set(robots.loc[np.isfinite(robots["odom_tx"].to_numpy(float)), "robot"].astype(str))
        for ego in egos or [r.robot_id for r in enc.robots if r.robot_id in has_odom]:
            cameras, est, gt, skipped = encounter_models(enc, steps, robots, ego)
            base = out / name / ego
            _write_model(base / "estimate", cameras, est)
            _write_model(base / "gt", cameras, gt)
            written += [base / "estimate", base / "gt"]
            all_images += est
            left = ", ".join(f"{k} {v}" for k, v in skipped.items() if v)
            log.info("%s/%s: %d images estimated, %d with ground truth%s", name, ego, len(est), len(gt),
                     f" (left out: {left})" if left else "")
        if link_images:
            failed = _place_images(enc, all_images, out / name / "images")
            if failed:
                log.warning("%s: %d images could not be placed beside the models (COLMAP shows their cameras "
                            "without a picture)", name, failed)
    return written


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("rundir", type=Path, help="a run folder written by `cerpe run` with a cerpe method")
    p.add_argument("--format", choices=("colmap",), default="colmap", help="output format (COLMAP text models)")
    p.add_argument("--manifest", type=Path, default=None,
                   help="the manifest the run read (default: the path in run.json)")
    p.add_argument("--encounter", nargs="+", default=(), help="only these encounters (default: all)")
    p.add_argument("--ego", nargs="+", default=(),
                   help="only these ego robots (default: every robot the run has odometry of)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: RUNDIR/colmap)")
    p.add_argument("--no-images", action="store_true", help="do not place the images beside the models")


def main(args: argparse.Namespace) -> int:
    written = export_colmap(args.rundir, args.out, args.manifest, args.encounter, args.ego,
                            link_images=not args.no_images)
    for path in written:
        print(f"written: {path}")
    if written:
        est = written[0]
        print(f"view one: colmap gui --import_path {est} --image_path {est.parent.parent / 'images'} "
              f"--database_path /tmp/cerpe-colmap.db")
    return 0
