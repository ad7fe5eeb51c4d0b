"""Development pairs for the matcher and scale studies (``lab/matchers.py``, ``lab/scale.py``).

Each set becomes a list of :class:`Case`: an ego robot's current frame and a few of its
earlier frames (standing in for memory keyframes), and one collaborator image to place
against them, with ground truth. Development data only (``../shared/data`` and synthetic
suites rendered with seeds other than the ``paper-default`` seed 0):

* ``tum-fr3-office``: 16 posed RGB frames at ~1 Hz split in two robots (first 8 s /
  the rest); every cross pair; no depth (essential matrix only).
* ``sun3d``: fragment 1 is the ego robot (RGB-D), fragment 2 the collaborator; every
  ``stride``-th frame of each; overlap from the two depth maps.
* ``tum-fr1-xyz``: frames 0-4 ego (RGB-D), 5-9 collaborator; small motion, distorted
  lens (``undistort`` and ``depth_scale`` select the variants the scale study compares).
* a synthetic suite manifest: ordered robot pairs every ``step_every`` steps.

A collaborator image goes through JPEG at quality 90 as a CERPE image reply does.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cerpe.geometry import se3_from_tq_xyzw
from cerpe.scene import CameraIntrinsics, load_depth_m, load_rgb

ROOT = Path(__file__).resolve().parents[1]

DATA = ROOT.parent / "shared" / "data"
K_FR3 = CameraIntrinsics(535.4, 539.2, 320.1, 247.6, 640, 480)
K_FR1 = CameraIntrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)
DIST_FR1 = np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])  # k1 k2 p1 p2 k3 (OpenCV order)
K_SUN3D = CameraIntrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)


@dataclass
class Frame:
    """One image with what the study knows about it.

    Attributes:
        key: a readable name (``"fr1:3"``).
        image: ``[H,W,3] uint8`` RGB.
        K: intrinsics of ``image``.
        T_world_cam: ``[4,4]`` ground-truth camera-to-world (metres).
        depth_m: ``[H,W] float32`` metric depth (0 = unknown) or None.
    """

    key: str
    image: np.ndarray
    K: CameraIntrinsics
    T_world_cam: np.ndarray
    depth_m: np.ndarray | None = None


@dataclass
class Case:
    """One registration problem: place ``collab`` against ``ego[0]`` (current) or ``ego[1:]``.

    ``overlap``: fraction of the ego current frame's pixels that the collaborator sees
    (NaN where no depth tells).
    """

    set: str
    ego: list[Frame]
    collab: Frame
    overlap: float = float("nan")
    meta: dict = field(default_factory=dict)


def jpeg(image: np.ndarray, quality: int = 90) -> np.ndarray:
    """``image`` after a JPEG round trip (what an image reply delivers)."""
    import cv2

    _, buf = cv2.imencode(".jpg", image[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1].copy()


def gt_T_b_a(a: Frame, b: Frame) -> np.ndarray:
    """``T_b_a``: maps points of camera a into camera b (``inv(T_world_b) @ T_world_a``)."""
    return np.linalg.inv(b.T_world_cam) @ a.T_world_cam


def transfer_depth(a: Frame, b: Frame, T_b_a: np.ndarray, stride: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """a's depth pixels (every ``stride``-th) moved into camera b by ``T_b_a``: ``(z predicted in b,
    b's measured depth there)`` per pixel of a with depth; measured 0 outside b or where b has none."""
    H, W = a.depth_m.shape
    v, u = np.mgrid[0:H:stride, 0:W:stride]
    z = a.depth_m[v, u]
    ok = z > 0
    Ka, Kb = a.K.K, b.K.K
    X = np.stack([(u[ok] - Ka[0, 2]) / Ka[0, 0] * z[ok], (v[ok] - Ka[1, 2]) / Ka[1, 1] * z[ok], z[ok]], 1)
    Xb = X @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        ub = np.round(Kb[0, 0] * Xb[:, 0] / Xb[:, 2] + Kb[0, 2])
        vb = np.round(Kb[1, 1] * Xb[:, 1] / Xb[:, 2] + Kb[1, 2])
    Hb, Wb = b.depth_m.shape
    inside = (Xb[:, 2] > 0) & (ub >= 0) & (ub < Wb) & (vb >= 0) & (vb < Hb)
    zb = np.zeros(len(Xb))
    zb[inside] = b.depth_m[vb[inside].astype(int), ub[inside].astype(int)]
    return Xb[:, 2], zb


def depth_overlap(a: Frame, b: Frame, rel_tol: float = 0.1, stride: int = 4) -> float:
    """Fraction of a's pixels with depth that land inside b with b's depth agreeing within ``rel_tol``."""
    if a.depth_m is None or b.depth_m is None:
        return float("nan")
    z, zb = transfer_depth(a, b, gt_T_b_a(a, b), stride)
    if len(z) == 0:
        return 0.0
    return float(np.sum((zb > 0) & (np.abs(zb - z) <= rel_tol * z)) / len(z))


def _tum_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps [N], T_world_cam [N,4,4])`` of a TUM file; comment and header lines skipped
    (fr1's file has a header line without ``#``, which the manifest reader refuses)."""
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append([float(x) for x in line.split()])
        except ValueError:
            continue
    rows = [r for r in rows if len(r) == 8]
    A = np.array(rows)
    return A[:, 0], np.stack([se3_from_tq_xyzw(r[1:4], r[4:8]) for r in A])


def _nearest_pose(stamps: np.ndarray, T: np.ndarray, t: float, tol_s: float) -> np.ndarray | None:
    k = int(np.argmin(np.abs(stamps - t)))
    return T[k] if abs(stamps[k] - t) <= tol_s else None


def _with_memory(frames: list[Frame], a: int, memory: int, gap: int) -> list[Frame]:
    """``frames[a]`` then up to ``memory`` earlier frames, ``gap`` apart (newest first)."""
    return [frames[a]] + [frames[a - gap * k] for k in range(1, memory + 1) if a - gap * k >= 0]


def tum_fr3_office(root: Path = DATA / "tum-fr3-office", memory: int = 3) -> list[Case]:
    stamps, T = _tum_poses(root / "groundtruth.txt")
    frames = []
    for p in sorted((root / "rgb").glob("*.png")):
        pose = _nearest_pose(stamps, T, float(p.stem), 0.02)
        if pose is not None:
            frames.append((float(p.stem), Frame(f"fr3:{len(frames)}", load_rgb(p), K_FR3, pose)))
    t0 = frames[0][0]
    ego = [f for t, f in frames if t - t0 < 8.0]
    col = [f for t, f in frames if t - t0 >= 8.0]
    return [Case("tum-fr3-office", _with_memory(ego, a, memory, 1), _jpeg_frame(c))
            for a in range(len(ego)) for c in col]


def _jpeg_frame(f: Frame) -> Frame:
    return Frame(f.key, jpeg(f.image), f.K, f.T_world_cam, None)


def sun3d_fragment(name: str, root: Path = DATA / "sun3d-two-fragments") -> list[Frame]:
    """The 50 RGB-D frames of ``fragment-1`` or ``fragment-2`` (depth in mm, poses camera-to-world)."""
    out = []
    for p in sorted((root / name).glob("*.color.png")):
        stem = p.name[: -len(".color.png")]
        T = np.loadtxt(root / name / f"{stem}.pose.txt").reshape(4, 4)
        D = load_depth_m(root / name / f"{stem}.depth.png", 1000.0)
        out.append(Frame(f"{name[-1]}:{stem[-4:]}", load_rgb(p), K_SUN3D, T, D))
    return out


def sun3d(root: Path = DATA / "sun3d-two-fragments", stride: int = 7, memory: int = 2, gap: int = 10) -> list[Case]:
    f1, f2 = sun3d_fragment("fragment-1", root), sun3d_fragment("fragment-2", root)
    cases = []
    for a in range(0, len(f1), stride):
        for b in range(0, len(f2), stride):
            c = Case("sun3d", _with_memory(f1, a, memory, gap), _jpeg_frame(f2[b]))
            c.overlap = depth_overlap(f1[a], f2[b])
            cases.append(c)
    return cases


def fr1_frames(root: Path = DATA / "tum-fr1-xyz-10", undistort: bool = False,
               depth_scale: float = 1.0) -> list[Frame]:
    """The 10 RGB-D frames of fr1/xyz with motion-capture poses at the colour stamps.

    ``undistort``: remap colour and depth (registered to colour, so the same lens) to the
    pinhole ``K_FR1`` (depth by nearest neighbour); ``depth_scale`` multiplies the depth
    (TUM's published fr1 correction is 1.035).
    """
    import cv2

    stamps, T = _tum_poses(root / "groundtruth.txt")
    maps = cv2.initUndistortRectifyMap(K_FR1.K, DIST_FR1, None, K_FR1.K, (640, 480), cv2.CV_32FC1)
    out = []
    for line in (root / "associations.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        t_rgb, f_rgb, _t_d, f_d = line.split()[:4]
        pose = _nearest_pose(stamps, T, float(t_rgb), 0.005)
        img = load_rgb(root / f_rgb)
        D = load_depth_m(root / f_d, 5000.0) * float(depth_scale)
        if undistort:
            img = cv2.remap(img, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            D = cv2.remap(D, *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        out.append(Frame(f"fr1:{len(out)}", img, K_FR1, pose, D))
    return out


def tum_fr1_xyz(root: Path = DATA / "tum-fr1-xyz-10", memory: int = 2, undistort: bool = False) -> list[Case]:
    frames = fr1_frames(root, undistort=undistort)
    ego, col = frames[:5], frames[5:]
    return [Case("tum-fr1-xyz", _with_memory(ego, a, memory, 1), _jpeg_frame(c), overlap=depth_overlap(ego[a], c))
            for a in range(len(ego)) for c in col]


def synthetic(manifest: Path, step_every: int = 6, first_step: int = 15, memory: int = 3, gap: int = 5,
              name: str | None = None) -> list[Case]:
    """Ordered robot pairs ``(i, j)`` of every encounter at steps ``first_step, +step_every, ...``."""
    from cerpe.datasets import load_setting

    setting = load_setting(manifest)
    cases = []
    for enc in setting.encounters:
        for t in range(first_step, enc.n_steps, step_every):
            for i, j in enc.ordered_pairs():
                ri, rj = enc.robots[i], enc.robots[j]
                frames = [Frame(f"{ri.robot_id}:{s}", ri.image(s), ri.intrinsics, ri.T_world_cam[s], ri.depth_m(s))
                          for s in [t] + [t - gap * k for k in range(1, memory + 1) if t - gap * k >= 0]]
                c = Frame(f"{rj.robot_id}:{t}", jpeg(rj.image(t)), rj.intrinsics, rj.T_world_cam[t])
                ov = float(enc.overlap[t, i, j]) if enc.overlap is not None else float("nan")
                cases.append(Case(name or setting.name, frames, c, overlap=ov, meta={"encounter": enc.name, "t": t}))
    return cases


def load_sets(names: list[str], synth: list[Path]) -> dict[str, list[Case]]:
    """The named real sets present under ``../shared/data`` plus each synthetic manifest given."""
    makers = {"tum-fr3-office": tum_fr3_office, "sun3d": sun3d, "tum-fr1-xyz": tum_fr1_xyz}
    dirs = {"tum-fr3-office": "tum-fr3-office", "sun3d": "sun3d-two-fragments", "tum-fr1-xyz": "tum-fr1-xyz-10"}
    out: dict[str, list[Case]] = {}
    for n in names:
        if n not in makers:
            raise SystemExit(f"unknown set {n!r}; known: {sorted(makers)}")
        if not (DATA / dirs[n]).is_dir():
            print(f"[skip] {n}: {DATA / dirs[n]} not present", file=sys.stderr)
            continue
        out[n] = makers[n]()
    for m in synth:
        cases = synthetic(Path(m), name=Path(m).parent.name)
        out[cases[0].set if cases else Path(m).parent.name] = cases
    return out
