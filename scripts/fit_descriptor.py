#!/usr/bin/env python
"""Fit the k-means centres of the offline descriptor and ship them in cerpe/data/.

The offline descriptor (cerpe.backbones.descriptor.XFeatSaladDescriptor) needs no
training, only cluster centres of L2-normalised XFeat features (keypoint
descriptors by default, --features dense for the dense map) and their mean. Fit them on images that the evaluation never sees:

    # synthetic encounters rendered in memory with seeds disjoint from the evaluation
    # suites (cerpe.synth.SUITES use seed 0); this is how the shipped file was made:
    python scripts/fit_descriptor.py --synth indoor-team:1001 indoor-team:1002 indoor-team:1003 \
        cad-intersection:1001 cad-intersection:1002 cad-intersection:1003 --frames 16 --every 2
    # or a suite already on disk, or any folder of images
    python scripts/fit_descriptor.py --manifest build/synth-fit/<suite>/manifest.yaml
    # or any folder of images
    python scripts/fit_descriptor.py --images 'some/dir/*.png'

Writes cerpe/data/xfeat_salad_centres.npz (atomically) with fields centres [m,64],
mean [64] and provenance (source, n_images, seed, num_clusters).

--descriptor-mean instead describes the images with the shipped centres and default
settings (no centring) and writes the mean of those unit descriptors, [dim], the vector
the descriptor subtracts (its `centring`), to cerpe/data/xfeat_salad_mean.npz. The
shipped file was made from the same renders as the centres, every frame:

    python scripts/fit_descriptor.py --descriptor-mean --synth indoor-team:1001 indoor-team:1002 \
        indoor-team:1003 cad-intersection:1001 cad-intersection:1002 cad-intersection:1003 --frames 16 --every 1 --limit 1000
"""
from __future__ import annotations

import argparse
import glob
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm


def _frames(encounters, every: int, limit: int):
    """``(name, image)`` of every ``every``-th frame of each robot, at most ``limit`` in all."""
    n = 0
    for enc in encounters:
        for r in enc.robots:
            for t in range(0, len(r), every):
                if n >= limit:
                    return
                n += 1
                yield f"{enc.name}/{r.robot_id}/{t}", r.image(t)


def _images_from_manifest(path: str, every: int, limit: int):
    from cerpe.datasets import load_setting

    yield from _frames(load_setting(path).encounters, every, limit)


def _images_from_synth(specs: list[str], frames: int, every: int, limit: int):
    from cerpe.synth import SUITES, render_encounter

    eval_seeds = {conf.get("seed", 0) for suite in SUITES.values() for _, conf in suite.values()}

    def rendered():
        for spec in specs:
            world, seed = spec.split(":")[0], int(spec.split(":")[1])
            if seed in eval_seeds:
                raise SystemExit(f"fit_descriptor: seed {seed} is used by an evaluation suite; pick another")
            yield render_encounter(world, seed=seed, index=0, conf={"n_frames": frames}, progress=True)

    yield from _frames(rendered(), every, limit)


def _images_from_glob(pattern: str, limit: int):
    from cerpe.scene import load_rgb

    for p in sorted(glob.glob(pattern))[:limit]:
        yield p, load_rgb(p, what=p)


def _fit_mean(images, a: argparse.Namespace, source: str) -> int:
    """Mean of the uncentred unit descriptors of ``images`` -> ``a.out`` (``mean [dim]`` + provenance)."""
    from cerpe.atomicio import atomic_write_npz
    from cerpe.backbones.config import DescriptorConfig
    from cerpe.backbones.descriptor import XFeatSaladDescriptor
    from cerpe.protocols import View

    desc = XFeatSaladDescriptor(DescriptorConfig(mean="none"), thresholds={"tau": 0.0, "tau_m": 0.0, "tau_k": 0.0})
    D = []
    for name, img in tqdm(images, desc="descriptor", unit="img"):
        h, w = img.shape[:2]
        K = np.array([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1]], float)  # unused by the descriptor
        if "low-texture" not in desc.flags(View(name, img, K)):
            D.append(desc.describe(View(name, img, K)))
    if not D:
        print("fit_descriptor: no textured images found", file=sys.stderr)
        return 2
    dst = Path(a.out)
    atomic_write_npz(dst, mean=np.mean(D, axis=0).astype(np.float32), source=np.array(source), n_images=np.array(len(D)),
             dim=np.array(desc.dim), centres_file="shipped (cerpe/data/xfeat_salad_centres.npz)")
    print(f"fit_descriptor: {len(D)} images -> mean descriptor [{desc.dim}], wrote {dst} ({dst.stat().st_size} B)")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--manifest", help="manifest of a fitting suite (seeds disjoint from evaluation)")
    src.add_argument("--images", help="glob of image files")
    src.add_argument("--synth", nargs="+", metavar="WORLD:SEED", help="render these encounters in memory")
    ap.add_argument("--frames", type=int, default=16, help="frames per rendered encounter (--synth)")
    ap.add_argument("--every", type=int, default=5, help="use every n-th frame of each robot (manifest)")
    ap.add_argument("--limit", type=int, default=200, help="at most this many images")
    ap.add_argument("--clusters", type=int, default=64)
    ap.add_argument("--features", choices=("sparse", "dense"), default="sparse",
                    help="keypoint descriptors (the descriptor's default) or the dense map")
    ap.add_argument("--max-keypoints", type=int, default=1024, help="keypoints per image (sparse)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--source-note", default="", help="free text stored as provenance")
    ap.add_argument("--descriptor-mean", action="store_true",
                    help="fit the descriptor's mean (its centring) instead of the centres")
    ap.add_argument("--out", default=None,
                    help="output .npz (default: cerpe/data/xfeat_salad_centres.npz, or xfeat_salad_mean.npz "
                         "with --descriptor-mean)")
    a = ap.parse_args(argv)
    data_dir = Path(__file__).resolve().parents[1] / "cerpe" / "data"
    a.out = a.out or str(data_dir / ("xfeat_salad_mean.npz" if a.descriptor_mean else "xfeat_salad_centres.npz"))

    from cerpe.atomicio import atomic_write_npz
    from cerpe.backbones.descriptor import fit_centres
    from cerpe.backbones.xfeat import TOP_K, XFeatEncoder

    enc = XFeatEncoder(max(a.max_keypoints, TOP_K))
    if a.synth:
        it = _images_from_synth(a.synth, a.frames, a.every, a.limit)
    elif a.manifest:
        it = _images_from_manifest(a.manifest, a.every, a.limit)
    else:
        it = _images_from_glob(a.images, a.limit)
    source = ("cerpe.synth.render_encounter " + " ".join(a.synth)) if a.synth else (a.manifest or a.images)
    if a.descriptor_mean:
        return _fit_mean(it, a, f"{source} {a.source_note}".strip())
    def local(feats):  # [64, n] either way: fit_centres flattens all but the first axis
        return feats.descriptors[: a.max_keypoints].T if a.features == "sparse" else feats.dense

    maps = [local(enc.encode_image(img, what=name)) for name, img in tqdm(it, desc="XFeat", unit="img")]
    if not maps:
        print("fit_descriptor: no images found", file=sys.stderr)
        return 2
    out = fit_centres(maps, num_clusters=a.clusters, seed=a.seed)
    dst = Path(a.out)
    atomic_write_npz(dst, centres=out["centres"], mean=out["mean"], source=np.array(f"{source} {a.source_note}".strip()),
             n_images=np.array(len(maps)), seed=np.array(a.seed), num_clusters=np.array(a.clusters),
             features=np.array(a.features), max_keypoints=np.array(a.max_keypoints))
    print(f"fit_descriptor: {len(maps)} images -> {a.clusters} centres, wrote {dst} ({dst.stat().st_size} B)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
