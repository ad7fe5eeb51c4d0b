#!/usr/bin/env python
"""Fit the descriptor projection and quantisers of the compressed descriptor codecs (cerpe.compress).

Training-free: the principal directions of global descriptors of development images
(never the paper-default suite, seed 0), then the product-quantisation codebook of the
projected vectors (faiss k-means). Writes (atomically) a .npz with the projection, its
settings and the provenance (sources, image count, command, revision):

    # the shipped file, cerpe/data/xfeat_salad_projection.npz (offline descriptor); the seed-1001
    # suites are rendered by `cerpe dev --seeds 1001` (or cerpe.pipeline.dev.synthetic_set):
    python scripts/fit_descriptor_projection.py --manifest build/dev/manifests/dev-synthetic-cad-s1001.yaml \\
        build/dev/manifests/dev-synthetic-indoor-s1001.yaml datasets_manifest/dev-sun3d-two-fragments.yaml \\
        datasets_manifest/dev-tum-fr1-xyz.yaml datasets_manifest/dev-tum-fr3-office.yaml --every 1
    # the paper's SALAD descriptor on your own images (a folder of frames of your robots' world):
    python scripts/fit_descriptor_projection.py --descriptor salad-dinov2 --checkpoint dino_salad.ckpt \\
        --images 'my_frames/*.jpg' --out salad_projection.npz
    # then: CerpeConfig(descriptor_codec="pca-pq", descriptor_projection="salad_projection.npz"),
    # and calibrate the codec's tau with scripts/dev_descriptor_codecs.py --projection ... --write-tau

--every N takes every N-th frame of each robot of a manifest; descriptors are cached per set in --cache-dir.
"""
from __future__ import annotations

import argparse
import glob
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _args(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--manifest", nargs="+", help="manifests of development sets")
    src.add_argument("--images", help="glob of image files (your own images)")
    ap.add_argument("--descriptor", choices=("offline", "salad-dinov2"), default="offline",
                    help="offline: XFeat-SALAD (cerpe.backbones.descriptor); salad-dinov2: the paper's SALAD")
    ap.add_argument("--checkpoint", help="SALAD checkpoint (dino_salad.ckpt) for --descriptor salad-dinov2")
    ap.add_argument("--device", default="auto", help="torch device for salad-dinov2")
    ap.add_argument("--every", type=int, default=1, help="every n-th frame of each robot (--manifest)")
    ap.add_argument("--limit", type=int, default=5000, help="at most this many images")
    ap.add_argument("--k", type=int, default=384, help="principal directions kept")
    ap.add_argument("--random-dims", type=int, default=512, help="random directions of the residual")
    ap.add_argument("--pq-m", type=int, default=448, help="sub-quantisers (bytes) of the pca-pq codec")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random directions and of the PQ k-means")
    ap.add_argument("--cache-dir", type=Path, default=ROOT / "build" / "dev" / "codecs",
                    help="descriptor caches per set (--manifest; shared with scripts/dev_descriptor_codecs.py)")
    ap.add_argument("--out", type=Path, default=ROOT / "cerpe" / "data" / "xfeat_salad_projection.npz")
    return ap.parse_args(argv)


def _descriptor(a):
    if a.descriptor == "offline":
        from cerpe.backbones.descriptor import XFeatSaladDescriptor

        return XFeatSaladDescriptor()
    if not a.checkpoint:
        raise SystemExit("fit_descriptor_projection: --descriptor salad-dinov2 needs --checkpoint FILE")
    from cerpe.backbones.salad_dinov2 import SaladDinoV2Descriptor

    return SaladDinoV2Descriptor({"checkpoint": a.checkpoint, "device": a.device})


def _descriptors(a, desc):
    """``[n, dim]`` descriptors of the fitting frames (manifests: cached per set in --cache-dir)."""
    from tqdm import tqdm

    from cerpe.protocols import View

    if a.images:
        from cerpe.scene import load_rgb

        paths = sorted(glob.glob(a.images))[: a.limit]
        return np.stack([np.asarray(desc.describe(View(p, load_rgb(p, what=p), None)), np.float32)
                         for p in tqdm(paths, desc="describe", unit="img")]) if paths else np.zeros((0, 1))
    from cerpe.datasets import load_setting
    from cerpe.pipeline.descriptor_codecs import describe_setting

    out = []
    for path in a.manifest:
        setting = load_setting(path)
        if setting.name.startswith("synthetic-") or "paper-default" in str(path):
            raise SystemExit(f"fit_descriptor_projection: {path} is a paper setting (test data); use development sets")
        cache = None if a.cache_dir is None else a.cache_dir / f"{setting.name}-every{a.every}-desc.npz"
        for D in describe_setting(desc, setting, cache, every=a.every):
            X = D[:, :: a.every].reshape(-1, D.shape[-1])
            out.append(X[np.any(X != 0, axis=1)])
    return np.concatenate(out)[: a.limit]


def main(argv=None) -> int:
    a = _args(argv)
    from cerpe.compress import DescriptorCodec, fit_projection, load_projection, save_projection
    from cerpe.pipeline.provenance import git_revision

    t0 = time.perf_counter()
    X = _descriptors(a, _descriptor(a))
    if len(X) < 256:
        print(f"fit_descriptor_projection: {len(X)} images; the product quantiser needs at least 256",
              file=sys.stderr)
        return 2
    proj = fit_projection(X, k=a.k, random_dims=a.random_dims, pq_m=a.pq_m, seed=a.seed)
    src = a.images or " ".join(str(m) for m in a.manifest)
    save_projection(proj, a.out, descriptor=a.descriptor, dim=int(X.shape[1]), n_images=int(len(X)),
                    source=src, every=a.every, revision=git_revision(),
                    command="python scripts/fit_descriptor_projection.py " + " ".join(sys.argv[1:] if argv is None
                                                                                    else argv))
    proj = load_projection(a.out)
    for name in ("pca-int8", "pca-pq"):
        c = DescriptorCodec(name, proj)
        print(f"{name}: {c.dims} directions, code {c.code_bytes} B, descriptor frame {c.wire_bytes()} B, "
              f"with the pose frame {c.wire_bytes() + 70} B")
    Xn = X[np.any(X != 0, axis=1)]
    kept = float(np.sum((Xn @ proj.components.T) ** 2) / max(np.sum(Xn.astype(np.float64) ** 2), 1e-30))
    print(f"fit_descriptor_projection: {len(X)} descriptors of {X.shape[1]} -> {proj.components.shape[0]} "
          f"principal ({kept:.1%} of the fitting descriptors' energy) + {proj.random_dims} random directions, "
          f"codebook {proj.codebook:08x}; wrote {a.out} "
          f"({a.out.stat().st_size} B) in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
