"""``openmars`` adapter: the OpenMARS multi-agent set (nuScenes table layout), read with plain json.

Layout (``data_root``)::

    <version>/scene.json sample.json sample_data.json calibrated_sensor.json ego_pose.json sensor.json
    samples/<CHANNEL>/...  sweeps/<CHANNEL>/<timestamp_us>.jpg   (paths as in sample_data.filename)

Multi-agent scenes carry ``vehicle_list``; each vehicle's sensors are channels
named ``<CHANNEL>_<vehicle>`` (``CAM_FRONT_CENTER_mike``). Poses:
``calibrated_sensor`` is sensor-to-ego and ``ego_pose`` ego-to-world
(translation in metres, rotation quaternion **w, x, y, z**); so
``T_world_cam = T_world_ego @ T_ego_cam``. All vehicles of a scene share the
world frame. Timestamps are microseconds. Images are already undistorted (the
``distortion_coefficient`` field is ignored). Metric depth comes from the
vehicle's LiDAR sweep nearest in time (``.pcd.bin``: float32 rows of
x, y, z, intensity, ring), projected into the camera with a z-buffer (nearest
return per pixel) -- lazily, by a :class:`LidarDepth` callable.

Manifest fields (besides the common ones)::

    version: v1.0                 # folder holding the json tables
    camera: CAM_FRONT_CENTER      # channel prefix of the camera to use
    lidar: LIDAR_FRONT_CENTER     # channel prefix of the LiDAR; null: no depth
    lidar_tolerance_s: 0.06       # LiDAR sweep must be this close to the image
    encounters:                   # optional; omitted: every scene with >= 2 vehicles
      - scene: 2023_10_04_scene_3_maisy   # scene name or token
        vehicles: [maisy, mike]   # optional subset / order (default: the scene's vehicle_list)
        window_s: [0, 10]         # optional, relative to the first vehicle's first image
        name: mars-s3             # optional encounter name (default: the scene name)
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
import numpy as np

from ..geometry import GeometryError, make_se3, quat_wxyz_to_matrix, se3_inverse
from ..scene import CameraIntrinsics, Encounter, RobotStream, SceneError, Setting
from .manifest import Manifest, Problem, is_number, mapping_problems, not_a_mapping, type_name
from .sync import check_window
from .report import LoadReport
from .sync import nearest, synchronise, window_mask

TABLES: dict[str, tuple[str, ...]] = {
    "scene": ("token", "name", "first_sample_token"),
    "sample": ("token", "timestamp", "scene_token"),
    "sample_data": ("token", "sample_token", "ego_pose_token", "calibrated_sensor_token", "timestamp", "filename"),
    "calibrated_sensor": ("token", "sensor_token", "translation", "rotation"),
    "ego_pose": ("token", "translation", "rotation"),
    "sensor": ("token", "channel"),
}
ENCOUNTER_FIELDS = ("scene", "vehicles", "window_s", "name")
LIDAR_MIN_DEPTH_M = 0.1
LIDAR_COLUMNS = 5  # x, y, z, intensity, ring (as nuScenes .pcd.bin)


class OpenMarsError(SceneError):
    """A LiDAR file or table record cannot be used (names the file / record)."""

    def __init__(self, message: str, file: str = "") -> None:
        super().__init__(message)
        self.file = file


@dataclass(frozen=True)
class LidarDepth:
    """Lazy metric depth: a LiDAR sweep projected into a camera (zero where no return).

    Attributes:
        path: the ``.pcd.bin`` file (float32, ``LIDAR_COLUMNS`` values per point).
        T_cam_lidar: ``[4,4]`` maps LiDAR-frame points into the camera frame at the
            image's time (``inv(T_world_cam) @ T_world_ego(lidar time) @ T_ego_lidar``).
        K: ``[3,3]`` camera calibration.
        width, height: image size in pixels.
    """

    path: Path
    T_cam_lidar: np.ndarray
    K: np.ndarray
    width: int
    height: int

    def __call__(self) -> np.ndarray:
        """``[H,W] float32`` metres; each pixel keeps its nearest LiDAR return (z-buffer)."""
        if not self.path.is_file():
            raise OpenMarsError(f"LiDAR sweep not found: {self.path}")
        raw = np.fromfile(self.path, dtype=np.float32)
        if raw.size % LIDAR_COLUMNS:
            raise OpenMarsError(f"LiDAR sweep {self.path}: {raw.size} floats is not a multiple of "
                                f"{LIDAR_COLUMNS} (x, y, z, intensity, ring); truncated file?")
        return project_points(raw.reshape(-1, LIDAR_COLUMNS)[:, :3], self.T_cam_lidar, self.K, self.width, self.height)


def project_points(p_lidar: np.ndarray, T_cam_lidar: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Project points ``[N,3]`` into a ``[H,W]`` depth map (camera z, metres), z-buffer min, 0 = empty.

    Pixel centres are at integer coordinates (OpenCV), so a point lands on pixel
    ``(round(u), round(v))``. Non-finite points and points closer than
    ``LIDAR_MIN_DEPTH_M`` (or behind the camera) are ignored.
    """
    p = np.asarray(p_lidar, dtype=np.float64)
    p = p[np.all(np.isfinite(p), axis=1)]
    pc = p @ T_cam_lidar[:3, :3].T + T_cam_lidar[:3, 3]
    z = pc[:, 2]
    front = z > LIDAR_MIN_DEPTH_M
    pc, z = pc[front], z[front]
    u = np.round(K[0, 0] * pc[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * pc[:, 1] / z + K[1, 2]).astype(np.int64)
    ok = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    depth = np.full((height, width), np.inf, dtype=np.float64)
    np.minimum.at(depth, (v[ok], u[ok]), z[ok])
    depth[~np.isfinite(depth)] = 0.0
    return depth.astype(np.float32)


# --------------------------------------------------------------------------- tables
class _Tables:
    """The six nuScenes tables, indexed by token; problems collected, not raised."""

    def __init__(self, folder: Path, problems: list[Problem]) -> None:
        self.folder = folder
        self.rows: dict[str, dict[str, dict]] = {}
        for name, keys in TABLES.items():
            path = folder / f"{name}.json"
            self.rows[name] = {}
            if not path.is_file():
                problems.append(Problem(str(path), "version", f"table {name}.json not found in {folder}"))
                continue
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
                problems.append(Problem(str(path), name, f"not valid JSON: {exc}"))
                continue
            if not isinstance(data, list):
                problems.append(Problem(str(path), name, f"expected a JSON list of records, got {type(data).__name__}"))
                continue
            bad = 0
            for k, rec in enumerate(data):
                miss = [key for key in keys if not isinstance(rec, dict) or key not in rec]
                if miss:
                    bad += 1
                    if bad <= 5:
                        problems.append(Problem(str(path), f"{name}[{k}]", f"record lacks field(s) {', '.join(miss)}"))
                    continue
                self.rows[name][rec["token"]] = rec
            if bad > 5:
                problems.append(Problem(str(path), name, f"... and {bad - 5} more records with missing fields"))
        self.channel_of_cs = {}
        for tok, cs in self.rows["calibrated_sensor"].items():
            sensor = self.rows["sensor"].get(cs["sensor_token"])
            if sensor is not None:
                self.channel_of_cs[tok] = sensor["channel"]
        # scene token -> channel -> sample_data records sorted by time
        self.by_scene_channel: dict[str, dict[str, list[dict]]] = {}
        for sd in self.rows["sample_data"].values():
            sample = self.rows["sample"].get(sd["sample_token"])
            ch = self.channel_of_cs.get(sd["calibrated_sensor_token"])
            if sample is None or ch is None:
                continue
            self.by_scene_channel.setdefault(sample["scene_token"], {}).setdefault(ch, []).append(sd)
        for chans in self.by_scene_channel.values():
            for lst in chans.values():
                lst.sort(key=lambda r: r["timestamp"])

    def file(self, name: str) -> str:
        return str(self.folder / f"{name}.json")

    def pose(self, table: str, token: str) -> np.ndarray:
        """``[4,4]`` from a record's translation and w-first quaternion; raises OpenMarsError naming it."""
        rec = self.rows[table].get(token)
        if rec is None:
            raise OpenMarsError(f"{self.file(table)}: no record with token {token!r}", self.file(table))
        t, q = rec["translation"], rec["rotation"]
        if not (isinstance(t, list) and len(t) == 3 and all(is_number(x) for x in t)):
            raise OpenMarsError(f"{self.file(table)}: {token}.translation: expected 3 finite numbers, got {t!r}",
                                self.file(table))
        if not (isinstance(q, list) and len(q) == 4 and all(is_number(x) for x in q)):
            raise OpenMarsError(f"{self.file(table)}: {token}.rotation: expected 4 numbers (w, x, y, z), got {q!r}",
                                self.file(table))
        try:
            return make_se3(quat_wxyz_to_matrix(np.array(q, dtype=np.float64)), np.array(t, dtype=np.float64))
        except GeometryError as exc:
            raise OpenMarsError(f"{self.file(table)}: {token}.rotation: {exc}", self.file(table)) from None


def _intrinsics(tables: _Tables, sd: dict) -> CameraIntrinsics:
    cs = tables.rows["calibrated_sensor"][sd["calibrated_sensor_token"]]
    K = cs.get("camera_intrinsic")
    where = f"{tables.file('calibrated_sensor')}: {cs['token']}.camera_intrinsic"
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise OpenMarsError(f"{where}: expected a 3x3 matrix, got {K!r}", tables.file("calibrated_sensor")) from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise OpenMarsError(f"{where}: expected a finite 3x3 matrix, got shape {K.shape}", tables.file("calibrated_sensor"))
    w, h = sd.get("width"), sd.get("height")
    if not (is_number(w) and is_number(h)):
        raise OpenMarsError(f"{tables.file('sample_data')}: {sd['token']}: width/height missing or not numbers",
                            tables.file("sample_data"))
    return CameraIntrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=int(w), height=int(h))


# --------------------------------------------------------------------------- adapter
class OpenMarsAdapter:
    """OpenMARS multi-agent scenes (nuScenes json tables) -> encounters of 2..3 vehicles."""

    name = "openmars"
    top_level_fields: tuple[str, ...] = ("version", "camera", "lidar", "lidar_tolerance_s")

    def validate(self, manifest: Manifest) -> list[Problem]:
        f, raw = str(manifest.path), manifest.raw
        probs: list[Problem] = []
        for k in ("version", "camera"):
            if k in raw and (not isinstance(raw[k], str) or not raw[k]):
                probs.append(Problem(f, k, f"expected a non-empty string, got {type_name(raw[k])}"))
        if raw.get("lidar") is not None and not isinstance(raw["lidar"], str):
            probs.append(Problem(f, "lidar", f"expected a channel prefix string or null, got {type_name(raw['lidar'])}"))
        if "lidar_tolerance_s" in raw and (not is_number(raw["lidar_tolerance_s"]) or raw["lidar_tolerance_s"] <= 0):
            probs.append(Problem(f, "lidar_tolerance_s", f"expected a positive number, got {raw['lidar_tolerance_s']!r}"))
        encs = manifest.encounters
        if encs is None:
            return probs
        if not isinstance(encs, list) or not encs:
            got = "an empty list" if isinstance(encs, list) else type_name(encs)
            return probs + [Problem(f, "encounters", f"expected a non-empty list (or omit it for every scene), got {got}")]
        names: set[str] = set()
        for e, enc in enumerate(encs):
            fe = f"encounters[{e}]"
            unknown = mapping_problems(enc, f, fe, ENCOUNTER_FIELDS)
            if unknown is None:
                probs.append(not_a_mapping(enc, f, fe))
                continue
            probs += unknown
            if not isinstance(enc.get("scene"), str) or not enc.get("scene"):
                probs.append(Problem(f, f"{fe}.scene", f"required: a scene name or token, got {type_name(enc.get('scene'))}"))
            v = enc.get("vehicles")
            if v is not None and not (isinstance(v, list) and len(v) >= 2 and all(isinstance(x, str) for x in v)
                                      and len(set(v)) == len(v)):
                probs.append(Problem(f, f"{fe}.vehicles", f"expected a list of at least 2 distinct vehicle names, got {v!r}"))
            probs += check_window(enc.get("window_s"), f, f"{fe}.window_s")
            nm = enc.get("name", enc.get("scene"))
            if isinstance(nm, str):
                if nm in names:
                    probs.append(Problem(f, f"{fe}.name", f"duplicate encounter name {nm!r}"))
                names.add(nm)
        return probs

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        raw = manifest.raw
        folder = manifest.resolve(raw.get("version", "v1.0"))
        if not folder.is_dir():
            report.add(manifest.problem("version", f"table folder not found: {folder}"))
            report.raise_if_problems()
        tables = _Tables(folder, report.problems)
        report.raise_if_problems()
        scenes_by_key = {s["name"]: s for s in tables.rows["scene"].values()}
        scenes_by_key.update(tables.rows["scene"])
        specs: list[tuple[str, dict]] = []
        if manifest.encounters is None:
            for s in sorted(tables.rows["scene"].values(), key=lambda s: s["name"]):
                vl = s.get("vehicle_list")
                if isinstance(vl, list) and len(vl) >= 2:
                    specs.append(("", {"scene": s["token"]}))
                else:
                    report.count(s["name"], "scene skipped: fewer than 2 vehicles in vehicle_list")
        else:
            specs = [(f"encounters[{e}]", enc) for e, enc in enumerate(manifest.encounters)]
        encounters = []
        for fe, spec in specs:
            scene = scenes_by_key.get(spec["scene"])
            if scene is None:
                report.add(manifest.problem(f"{fe}.scene", f"no scene named {spec['scene']!r} in {tables.file('scene')}"))
                continue
            try:
                enc = self._encounter(manifest, tables, scene, spec, fe, report)
            except SceneError as exc:  # bad table record or LiDAR/intrinsics inconsistency
                report.add(manifest.problem(fe or scene["name"], str(exc), getattr(exc, "file", None) or None))
                continue
            if enc is not None:
                encounters.append(enc)
        report.raise_if_problems()
        return Setting(name=manifest.name, encounters=encounters, metric_depth=manifest.metric_depth,
                       meta={"manifest": str(manifest.path), "adapter": self.name, "tables": str(folder)})

    def _encounter(self, m: Manifest, tables: _Tables, scene: dict, spec: dict, fe: str,
                   report: LoadReport) -> Encounter | None:
        name = spec.get("name") or scene["name"]
        vl = scene.get("vehicle_list")
        vehicles = spec.get("vehicles") or vl
        if not isinstance(vehicles, list) or len(vehicles) < 2:
            report.add(Problem(tables.file("scene"), f"{scene['token']}.vehicle_list",
                               f"scene {scene['name']!r} lists no vehicles (or one); name them in {fe}.vehicles"))
            return None
        camera = m.raw.get("camera", "CAM_FRONT_CENTER")
        lidar = m.raw.get("lidar", "LIDAR_FRONT_CENTER")
        lidar_tol = float(m.raw.get("lidar_tolerance_s", 0.06))
        chans = tables.by_scene_channel.get(scene["token"], {})
        per_vehicle: list[tuple[str, list[dict]]] = []
        for v in vehicles:
            ch = f"{camera}_{v}"
            if ch not in chans:
                report.add(Problem(tables.file("sample_data"), f"{fe}.vehicles" if fe else scene["name"],
                                   f"scene {scene['name']!r} has no images for channel {ch}; "
                                   f"channels there: {', '.join(sorted(chans)) or 'none'}"))
                return None
            per_vehicle.append((v, chans[ch]))
        stamps = [np.array([sd["timestamp"] for sd in sds], dtype=np.float64) / 1e6 for _, sds in per_vehicle]
        if spec.get("window_s") is not None:
            keep0 = window_mask(stamps[0], spec["window_s"])
            if not keep0.any():
                report.add(m.problem(f"{fe}.window_s", "no image of the first vehicle inside the window"))
                return None
            lo, hi = stamps[0][keep0][0] - m.sync_tolerance_s, stamps[0][keep0][-1] + m.sync_tolerance_s
            for k in range(len(per_vehicle)):
                sel = (stamps[k] >= lo) & (stamps[k] <= hi)
                per_vehicle[k] = (per_vehicle[k][0], [sd for sd, s in zip(per_vehicle[k][1], sel) if s])
                stamps[k] = stamps[k][sel]
        idx, res, dropped = synchronise(stamps, m.sync_tolerance_s, "stamp")
        if len(idx[0]) == 0:
            report.add(m.problem(fe or scene["name"], f"no time steps where all vehicles have an image within "
                                                     f"sync_tolerance_s={m.sync_tolerance_s}"))
            return None
        report.count(name, "reference frames without partner frames within sync_tolerance_s (dropped)", dropped)
        report.sync[name] = {}
        streams = []
        for (v, sds), ix, r, st in zip(per_vehicle, idx, res, stamps):
            chosen = [sds[k] for k in ix]
            intr = _intrinsics(tables, chosen[0])
            for sd in chosen[1:]:
                if _intrinsics(tables, sd) != intr:
                    raise OpenMarsError(f"{tables.file('calibrated_sensor')}: vehicle {v}: camera intrinsics change "
                                        f"within the scene (at {sd['token']})")
            T_wc = np.stack([tables.pose("ego_pose", sd["ego_pose_token"]) @
                             tables.pose("calibrated_sensor", sd["calibrated_sensor_token"]) for sd in chosen])
            images = [m.resolve(sd["filename"]) for sd in chosen]
            missing = [p for p in images if not p.is_file()]
            for p in missing[:5]:
                report.add(Problem(str(p), f"{name}/{v}", "image file not found"))
            if len(missing) > 5:
                report.add(Problem(str(m.data_root), f"{name}/{v}", f"... and {len(missing) - 5} more missing images"))
            depth = None
            if lidar:
                depth = self._lidar_depth(tables, chans.get(f"{lidar}_{v}", []), chosen, T_wc, intr, lidar_tol, m)
                report.count(name, f"{v}: frames without a LiDAR sweep within {lidar_tol} s", sum(d is None for d in depth))
            report.sync[name][v] = {"max_abs_s": float(np.max(np.abs(r))), "mean_abs_s": float(np.mean(np.abs(r))),
                                    "mode": "stamp"}
            streams.append(RobotStream(robot_id=v, intrinsics=intr, stamps_s=st[ix], images=images, T_world_cam=T_wc,
                                       depth=depth, depth_units_per_m=1.0, frame_ids=[sd["token"] for sd in chosen]))
        if any(p.field.startswith(f"{name}/") for p in report.problems):
            return None
        return Encounter(name=name, robots=streams, meta={"scene": scene["name"], "scene_token": scene["token"],
                                                          "camera": camera, "lidar": lidar})

    @staticmethod
    def _lidar_depth(tables: _Tables, lidar_sds: list[dict], cam_sds: list[dict], T_world_cam: np.ndarray,
                     intr: CameraIntrinsics, tol_s: float, m: Manifest) -> list[LidarDepth | None]:
        if not lidar_sds:
            return [None] * len(cam_sds)
        l_stamps = np.array([sd["timestamp"] for sd in lidar_sds], dtype=np.float64) / 1e6
        c_stamps = np.array([sd["timestamp"] for sd in cam_sds], dtype=np.float64) / 1e6
        idx, _ = nearest(c_stamps, l_stamps, tol_s)
        out: list[LidarDepth | None] = []
        for k, li in enumerate(idx):
            if li < 0:
                out.append(None)
                continue
            lsd = lidar_sds[li]
            T_world_lidar = tables.pose("ego_pose", lsd["ego_pose_token"]) @ tables.pose(
                "calibrated_sensor", lsd["calibrated_sensor_token"])
            out.append(LidarDepth(path=m.resolve(lsd["filename"]), T_cam_lidar=se3_inverse(T_world_cam[k]) @ T_world_lidar,
                                  K=intr.K, width=intr.width, height=intr.height))
        return out
