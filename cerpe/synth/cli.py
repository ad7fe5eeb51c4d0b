"""Render a synthetic encounter world to a mocap-style dataset (manifest + files).

Worlds: `cad-intersection` (2-3 vehicles meeting at one of 4 junction layouts,
forward camera 1.5 m high, 10 Hz) and `indoor-team` (3 ground robots in a
furnished room, camera 0.2 m high). `all` renders both, one setting folder per
world (OUT/synthetic-cad, OUT/synthetic-indoor). A --preset fills every argument
(`fixture`: 160x120, 12 frames, 1 encounter per world; `paper-default`: 640x480,
8 cad + 4 indoor encounters); explicit options override it.

Output follows docs/formats.md "Dataset manifests": per encounter and robot
rgb/<stamp>.png, depth/<stamp>.png (uint16 mm), groundtruth.txt (TUM,
camera-to-world), camera.yaml; per encounter overlap.npy [T,N,N] and meta.json
(viewing angles); OUT/manifest.yaml and OUT/meta.json. Rerunning with the same
arguments renders nothing; an OUT made with other arguments needs --force.

Examples:
  cerpe synth all --preset fixture --out build/synth
  cerpe synth cad-intersection --out build/synth/cad --seed 3 --encounters 2 --size 320x240
"""
from __future__ import annotations

import argparse
from pathlib import Path


WORLD_CHOICES = ("cad-intersection", "indoor-team", "all")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 640x480, got {text!r}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("world", choices=WORLD_CHOICES, help="world generator, or `all` for one setting per world")
    p.add_argument("--out", required=True, type=Path,
                   help="output folder (a setting folder; with `all`, the parent of one folder per setting)")
    p.add_argument("--preset", choices=("fixture", "paper-default"), default=None,
                   help="named argument set (see above); explicit options below override it")
    p.add_argument("--seed", type=int, default=None, help="world seed (default 0)")
    p.add_argument("--robots", type=int, default=None, help="robots per encounter (default 2 vehicles / 3 indoor robots)")
    p.add_argument("--frames", type=int, default=None, help="steps per encounter (default 40)")
    p.add_argument("--fps", type=float, default=None, help="frame rate in Hz (default 10)")
    p.add_argument("--size", type=_size, default=None, help="image size WxH (default 640x480)")
    p.add_argument("--encounters", type=int, default=None, help="number of encounters (default 1)")
    p.add_argument("--three", type=int, default=None, help="cad-intersection: how many encounters get 3 vehicles")
    p.add_argument("--workers", type=int, default=None, help="parallel processes (default 1; 2 in paper-default)")
    p.add_argument("--force", action="store_true", help="replace an output folder made with other arguments")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    from .writer import SETTING_OF_WORLD, SUITES, generate_suite

    overrides = {k: v for k, v in {
        "seed": args.seed, "n_robots": args.robots, "n_frames": args.frames, "fps": args.fps, "size": args.size,
        "n_encounters": args.encounters, "n_three": args.three, "workers": args.workers}.items() if v is not None}
    worlds = ("cad-intersection", "indoor-team") if args.world == "all" else (args.world,)
    for world in worlds:
        setting = SETTING_OF_WORLD[world]
        base = dict(SUITES[args.preset][setting][1]) if args.preset else {}
        out = args.out / setting if args.world == "all" else args.out
        manifest = generate_suite(world, out, {**base, **overrides}, force=args.force,
                                  progress=not args.no_progress, setting=setting)
        print(f"{setting}: {manifest}")
    return 0
