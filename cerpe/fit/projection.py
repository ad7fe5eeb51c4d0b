"""Fit the projection and quantisers of the compressed descriptor codecs (``cerpe fit projection``).

Training-free: the principal directions of global descriptors of development images (never
the paper-default suite, seed 0), then the product-quantisation codebook of the projected
vectors (faiss k-means; :func:`cerpe.compress.fit_projection`). Writes (atomically) a ``.npz``
with the projection, its settings and the provenance (sources, image count, command,
revision); by default ``cerpe/data/xfeat_salad_projection.npz``, which was made from the
seed-1001 development suites (``cerpe dev --seeds 1001`` renders them) and the real
development sets::

    cerpe fit projection --manifest build/dev/manifests/dev-synthetic-cad-s1001.yaml \\
        build/dev/manifests/dev-synthetic-indoor-s1001.yaml datasets_manifest/dev-sun3d-two-fragments.yaml \\
        datasets_manifest/dev-tum-fr1-xyz.yaml datasets_manifest/dev-tum-fr3-office.yaml --every 1

The paper's SALAD descriptor on your own images (a folder of frames of your robots' world)::

    cerpe fit projection --descriptor salad-dinov2 --checkpoint dino_salad.ckpt \\
        --images 'my_frames/*.jpg' --out salad_projection.npz

then ``CerpeConfig(descriptor_codec="pca-pq", descriptor_projection="salad_projection.npz")``;
the codec's ``tau`` is measured by the development study ``lab/descriptor_codec_auc.py``.
Descriptors of manifests are cached per set in ``--cache-dir``.
"""
from __future__ import annotations

import glob
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import DATA_DIR, FitError
from ..pipeline.dev import ROOT

DEFAULT_OUT = DATA_DIR / "xfeat_salad_projection.npz"
MIN_DESCRIPTORS = 256  # the product quantiser's k-means needs at least one point per centroid

default_conf: dict[str, Any] = {
    "descriptor": "offline",  # offline: XFeat-SALAD (cerpe.backbones.descriptor); salad-dinov2: the paper's SALAD
    "checkpoint": None,  # SALAD checkpoint (dino_salad.ckpt) for salad-dinov2
    "device": "auto",  # torch device for salad-dinov2
    "every": 1,  # every n-th frame of each robot (manifests)
    "limit": 5000,  # at most this many images
    "k": 384,  # principal directions kept
    "random_dims": 512,  # random directions of the residual
    "pq_m": 448,  # sub-quantisers (bytes) of the pca-pq codec
    "seed": 0,  # seed of the random directions and of the PQ k-means
    "command": "",  # what made the file, recorded in its provenance
}


@dataclass(frozen=True)
class Paths:
    """The fitting images (``manifests`` of development sets, or ``images``, a glob), the descriptor
    cache (None: none) and the file written."""

    manifests: tuple[Path, ...] = ()
    images: str | None = None
    cache_dir: Path | None = ROOT / "build" / "dev" / "codecs"  # shared with lab/descriptor_codec_auc.py
    out: Path = DEFAULT_OUT


def _descriptor(conf: dict):
    if conf["descriptor"] == "offline":
        from ..backbones.descriptor import XFeatSaladDescriptor

        return XFeatSaladDescriptor()
    if conf["descriptor"] != "salad-dinov2":
        raise FitError(f"--descriptor {conf['descriptor']!r}: offline or salad-dinov2")
    if not conf["checkpoint"]:
        raise FitError("--descriptor salad-dinov2 needs --checkpoint FILE")
    from ..backbones.salad_dinov2 import SaladDinoV2Descriptor

    return SaladDinoV2Descriptor({"checkpoint": conf["checkpoint"], "device": conf["device"]})


def _descriptors(conf: dict, paths: Paths, desc) -> np.ndarray:
    """``[n, dim]`` descriptors of the fitting frames (manifests: cached per set in ``paths.cache_dir``)."""
    from tqdm import tqdm

    from ..protocols import View

    if paths.images:
        from ..scene import load_rgb

        files = sorted(glob.glob(paths.images))[: conf["limit"]]
        return np.stack([np.asarray(desc.describe(View(p, load_rgb(p, what=p), None)), np.float32)
                         for p in tqdm(files, desc="describe", unit="img")]) if files else np.zeros((0, 1))
    from ..datasets import load_setting
    from .descriptor_codecs import describe_setting

    every, out = conf["every"], []
    for path in paths.manifests:
        setting = load_setting(path)
        if setting.name.startswith("synthetic-") or "paper-default" in str(path):
            raise FitError(f"{path} is a paper setting (test data); use development sets")
        cache = None if paths.cache_dir is None else paths.cache_dir / f"{setting.name}-every{every}-desc.npz"
        for D in describe_setting(desc, setting, cache, every=every):
            X = D[:, ::every].reshape(-1, D.shape[-1])
            out.append(X[np.any(X != 0, axis=1)])
    return np.concatenate(out)[: conf["limit"]]


def main(conf: dict, paths: Paths) -> Path:
    """Describe the fitting images, fit the projection, write it and print each codec's sizes and the
    energy the principal directions keep; returns the file written."""
    conf = {**default_conf, **conf}
    if bool(paths.manifests) == bool(paths.images):
        raise FitError("give exactly one image source: --manifest or --images")
    from ..compress import DescriptorCodec, fit_projection, load_projection, save_projection
    from ..runfolder.provenance import git_revision

    t0 = time.perf_counter()
    X = _descriptors(conf, paths, _descriptor(conf))
    if len(X) < MIN_DESCRIPTORS:
        raise FitError(f"{len(X)} images; the product quantiser needs at least {MIN_DESCRIPTORS}")
    proj = fit_projection(X, k=conf["k"], random_dims=conf["random_dims"], pq_m=conf["pq_m"], seed=conf["seed"])
    src = paths.images or " ".join(str(m) for m in paths.manifests)
    save_projection(proj, paths.out, descriptor=conf["descriptor"], dim=int(X.shape[1]), n_images=int(len(X)),
                    source=src, every=conf["every"], revision=git_revision(), command=conf["command"])
    proj = load_projection(paths.out)
    for name in ("pca-int8", "pca-pq"):
        c = DescriptorCodec(name, proj)
        print(f"{name}: {c.dims} directions, code {c.code_bytes} B, descriptor frame {c.wire_bytes()} B, "
              f"with the pose frame {c.wire_bytes() + 70} B")
    Xn = X[np.any(X != 0, axis=1)]
    kept = float(np.sum((Xn @ proj.components.T) ** 2) / max(np.sum(Xn.astype(np.float64) ** 2), 1e-30))
    print(f"cerpe fit projection: {len(X)} descriptors of {X.shape[1]} -> {proj.components.shape[0]} "
          f"principal ({kept:.1%} of the fitting descriptors' energy) + {proj.random_dims} random directions, "
          f"codebook {proj.codebook:08x}; wrote {paths.out} "
          f"({paths.out.stat().st_size} B) in {time.perf_counter() - t0:.0f} s")
    return Path(paths.out)
