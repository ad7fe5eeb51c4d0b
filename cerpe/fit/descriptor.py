"""Fit the offline descriptor's k-means centres, or its mean descriptor (``cerpe fit descriptor``).

The offline descriptor (:class:`cerpe.backbones.descriptor.XFeatSaladDescriptor`) needs no
training, only cluster centres of L2-normalised XFeat features (keypoint descriptors by
default, ``--features dense`` for the dense map) and their mean. Fit them on images that the
evaluation never sees: synthetic encounters rendered in memory with seeds disjoint from the
evaluation suites (:data:`cerpe.synth.SUITES`, seed 0), a development suite's manifest, or any
folder of images. The shipped centres were made from::

    cerpe fit descriptor --synth indoor-team:1001 indoor-team:1002 indoor-team:1003 \\
        cad-intersection:1001 cad-intersection:1002 cad-intersection:1003 --frames 16 --every 2

and written to ``cerpe/data/xfeat_salad_centres.npz``: ``centres [m,64]``, ``mean [64]`` and
the provenance (source, image count, seed, cluster count).

``--descriptor-mean`` instead describes the images with the shipped centres
and default settings (no centring) and writes the mean of those unit descriptors, ``[dim]``,
the vector the descriptor subtracts (its ``centring``), to ``cerpe/data/xfeat_salad_mean.npz``;
the shipped one from the same renders, every frame (``--every 1 --limit 1000``).
"""
from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from . import DATA_DIR, FitError

OUTPUTS = {"centres": DATA_DIR / "xfeat_salad_centres.npz", "mean": DATA_DIR / "xfeat_salad_mean.npz"}

default_conf: dict[str, Any] = {
    "what": "centres",  # centres | mean
    "frames": 16,  # frames per rendered encounter (synth)
    "every": 5,  # every n-th frame of each robot
    "limit": 200,  # at most this many images
    "clusters": 64,
    "features": "sparse",  # sparse (keypoint descriptors, the descriptor's default) | dense (the dense map)
    "max_keypoints": 1024,  # keypoints per image (sparse)
    "seed": 0,
    "source_note": "",  # free text stored as provenance
}


@dataclass(frozen=True)
class Paths:
    """Where the images come from (exactly one of ``manifest``, ``images``, ``synth``) and where the
    fit goes (``out``; None: the shipped file of ``conf["what"]``, :data:`OUTPUTS`)."""

    manifest: Path | None = None  # a development suite's manifest
    images: str | None = None  # a glob of image files
    synth: tuple[str, ...] = ()  # WORLD:SEED encounters rendered in memory
    out: Path | None = None


def _frames(encounters, every: int, limit: int) -> Iterator[tuple[str, np.ndarray]]:
    """``(name, image)`` of every ``every``-th frame of each robot, at most ``limit`` in all."""
    n = 0
    for enc in encounters:
        for r in enc.robots:
            for t in range(0, len(r), every):
                if n >= limit:
                    return
                n += 1
                yield f"{enc.name}/{r.robot_id}/{t}", r.image(t)


def _images_from_manifest(path: Path, every: int, limit: int):
    from ..datasets import load_setting

    yield from _frames(load_setting(path).encounters, every, limit)


def synth_specs(specs: tuple[str, ...]) -> list[tuple[str, int]]:
    """``WORLD:SEED`` strings -> ``(world, seed)``; the evaluation suites' seeds are refused."""
    from ..synth import SUITES

    eval_seeds = {conf.get("seed", 0) for suite in SUITES.values() for _, conf in suite.values()}
    out = []
    for spec in specs:
        world, sep, seed = spec.partition(":")
        if not sep or not seed.lstrip("-").isdigit():
            raise FitError(f"--synth {spec!r}: expected WORLD:SEED, e.g. indoor-team:1001")
        if int(seed) in eval_seeds:
            raise FitError(f"--synth {spec}: seed {seed} is used by an evaluation suite; pick another")
        out.append((world, int(seed)))
    return out


def _images_from_synth(specs: list[tuple[str, int]], frames: int, every: int, limit: int):
    from ..synth import render_encounter

    rendered = (render_encounter(world, seed=seed, index=0, conf={"n_frames": frames}, progress=True)
                for world, seed in specs)
    yield from _frames(rendered, every, limit)


def _images_from_glob(pattern: str, limit: int):
    from ..scene import load_rgb

    for p in sorted(glob.glob(pattern))[:limit]:
        yield p, load_rgb(p, what=p)


def _fit_mean(images, conf: dict, source: str, dst: Path) -> Path:
    """Mean of the uncentred unit descriptors of ``images`` -> ``dst`` (``mean [dim]`` + provenance)."""
    from tqdm import tqdm

    from ..atomicio import atomic_write_npz
    from ..backbones.descriptor import XFeatSaladDescriptor
    from ..protocols import View

    from ..backbones.config import DescriptorConfig

    desc = XFeatSaladDescriptor(DescriptorConfig(mean="none"), thresholds={"tau": 0.0, "tau_m": 0.0, "tau_k": 0.0})
    D = []
    for name, img in tqdm(images, desc="descriptor", unit="img"):
        h, w = img.shape[:2]
        K = np.array([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1]], float)  # unused by the descriptor
        if "low-texture" not in desc.flags(View(name, img, K)):
            D.append(desc.describe(View(name, img, K)))
    if not D:
        raise FitError(f"{source}: no textured images found")
    atomic_write_npz(dst, mean=np.mean(D, axis=0).astype(np.float32), source=np.array(source),
                     n_images=np.array(len(D)), dim=np.array(desc.dim),
                     centres_file="shipped (cerpe/data/xfeat_salad_centres.npz)")
    print(f"cerpe fit descriptor: {len(D)} images -> mean descriptor [{desc.dim}], wrote {dst} "
          f"({dst.stat().st_size} B)")
    return dst


def main(conf: dict, paths: Paths) -> Path:
    """Fit the centres (or, with ``conf["what"] == "mean"``, the mean descriptor) and write them
    atomically; returns the file written."""
    conf = {**default_conf, **conf}
    if conf["what"] not in OUTPUTS:
        raise FitError(f"what {conf['what']!r}: one of {', '.join(OUTPUTS)}")
    if sum(bool(x) for x in (paths.manifest, paths.images, paths.synth)) != 1:
        raise FitError("give exactly one image source: --manifest, --images or --synth")
    dst = Path(paths.out or OUTPUTS[conf["what"]])
    if paths.synth:
        it = _images_from_synth(synth_specs(paths.synth), conf["frames"], conf["every"], conf["limit"])
        source = "cerpe.synth.render_encounter " + " ".join(paths.synth)
    elif paths.manifest:
        it = _images_from_manifest(paths.manifest, conf["every"], conf["limit"])
        source = str(paths.manifest)
    else:
        it = _images_from_glob(paths.images, conf["limit"])
        source = paths.images
    source = f"{source} {conf['source_note']}".strip()
    if conf["what"] == "mean":
        return _fit_mean(it, conf, source, dst)

    from tqdm import tqdm

    from ..atomicio import atomic_write_npz
    from ..backbones.descriptor import fit_centres
    from ..backbones.xfeat import TOP_K, XFeatEncoder

    enc = XFeatEncoder(max(conf["max_keypoints"], TOP_K))

    def local(feats):  # [64, n] either way: fit_centres flattens all but the first axis
        return feats.descriptors[: conf["max_keypoints"]].T if conf["features"] == "sparse" else feats.dense

    maps = [local(enc.encode_image(img, what=name)) for name, img in tqdm(it, desc="XFeat", unit="img")]
    if not maps:
        raise FitError(f"{source}: no images found")
    out = fit_centres(maps, num_clusters=conf["clusters"], seed=conf["seed"])
    atomic_write_npz(dst, centres=out["centres"], mean=out["mean"], source=np.array(source),
                     n_images=np.array(len(maps)), seed=np.array(conf["seed"]),
                     num_clusters=np.array(conf["clusters"]), features=np.array(conf["features"]),
                     max_keypoints=np.array(conf["max_keypoints"]))
    print(f"cerpe fit descriptor: {len(maps)} images -> {conf['clusters']} centres, wrote {dst} "
          f"({dst.stat().st_size} B)")
    return dst
