"""`cerpe fit`: fit the files shipped in cerpe/data/ on development data (never the paper-default suite).

  cerpe fit descriptor   the offline descriptor's k-means centres, or (--descriptor-mean) its mean
                         descriptor: cerpe/data/xfeat_salad_centres.npz / xfeat_salad_mean.npz
  cerpe fit projection   the projection and product quantiser of the compressed descriptor codecs:
                         cerpe/data/xfeat_salad_projection.npz
  cerpe fit thresholds   the gate's tau and the memory's tau_m, tau_k against ground-truth
                         co-visibility: cerpe/data/xfeat_salad_thresholds.json

Each writes its file atomically (--out for another one) with the provenance inside. Refit them
on your robots' frames when your world is not ours: `cerpe fit STEP --help` says what each reads.
"""
from __future__ import annotations

import argparse
import functools
import shlex
import sys
from pathlib import Path

from . import FitError

STEPS: dict[str, str] = {  # step -> one-line help
    "descriptor": "the offline descriptor's k-means centres, or (--descriptor-mean) its mean descriptor",
    "projection": "the projection and product quantiser of the compressed descriptor codecs",
    "thresholds": "the gate's tau and the memory's tau_m, tau_k, against ground-truth co-visibility",
}


def _one_line_error(parser: argparse.ArgumentParser, message: str) -> None:
    """A bad argument as one line on stderr and exit code 2, as cerpe prints its errors (no usage block)."""
    parser.exit(2, f"{parser.prog}: error: {message}\n")


class _StepParser(argparse.ArgumentParser):
    """A step's parser: one-line errors, and an unknown argument is one too (not left to ``cerpe``)."""

    def error(self, message: str) -> None:  # argparse's hook
        _one_line_error(self, message)

    def parse_known_args(self, args=None, namespace=None):
        ns, extra = super().parse_known_args(args, namespace)
        if extra:
            self.error(f"unrecognized arguments: {' '.join(extra)}")
        return ns, extra


def _count(lo: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"{v}: must be >= {lo}")
        return v
    return parse


def _descriptor_args(p: argparse.ArgumentParser) -> None:
    from .descriptor import default_conf as c

    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--manifest", type=Path, help="manifest of a development suite (seeds disjoint from evaluation)")
    src.add_argument("--images", help="glob of image files, e.g. 'frames/*.jpg'")
    src.add_argument("--synth", nargs="+", metavar="WORLD:SEED", help="render these encounters in memory")
    p.add_argument("--descriptor-mean", action="store_true",
                   help="fit the descriptor's mean (its centring) instead of the centres")
    p.add_argument("--frames", type=_count(1), default=c["frames"], help="frames per rendered encounter (--synth)")
    p.add_argument("--every", type=_count(1), default=c["every"], help="every n-th frame of each robot")
    p.add_argument("--limit", type=_count(1), default=c["limit"], help="at most this many images")
    p.add_argument("--clusters", type=_count(1), default=c["clusters"], help="k-means centres")
    p.add_argument("--features", choices=("sparse", "dense"), default=c["features"],
                   help="keypoint descriptors (the descriptor's default) or the dense map")
    p.add_argument("--max-keypoints", type=_count(1), default=c["max_keypoints"], help="keypoints per image (sparse)")
    p.add_argument("--seed", type=int, default=c["seed"], help="k-means subsampling and initialisation seed")
    p.add_argument("--source-note", default=c["source_note"], help="free text stored as provenance")
    p.add_argument("--out", type=Path, default=None,
                   help="output .npz (default: cerpe/data/xfeat_salad_centres.npz, or xfeat_salad_mean.npz "
                        "with --descriptor-mean)")


def _projection_args(p: argparse.ArgumentParser) -> None:
    from .projection import Paths, default_conf as c

    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--manifest", type=Path, nargs="+", help="manifests of development sets")
    src.add_argument("--images", help="glob of image files (your own images)")
    p.add_argument("--descriptor", choices=("offline", "salad-dinov2"), default=c["descriptor"],
                   help="offline: XFeat-SALAD (cerpe.backbones.descriptor); salad-dinov2: the paper's SALAD")
    p.add_argument("--checkpoint", help="SALAD checkpoint (dino_salad.ckpt) for --descriptor salad-dinov2")
    p.add_argument("--device", default=c["device"], help="torch device for salad-dinov2")
    p.add_argument("--every", type=_count(1), default=c["every"], help="every n-th frame of each robot (--manifest)")
    p.add_argument("--limit", type=_count(1), default=c["limit"], help="at most this many images")
    p.add_argument("--k", type=_count(1), default=c["k"], help="principal directions kept")
    p.add_argument("--random-dims", type=_count(0), default=c["random_dims"], help="random directions of the residual")
    p.add_argument("--pq-m", type=_count(1), default=c["pq_m"], help="sub-quantisers (bytes) of the pca-pq codec")
    p.add_argument("--seed", type=int, default=c["seed"], help="seed of the random directions and of the PQ k-means")
    p.add_argument("--cache-dir", type=Path, default=Paths.cache_dir,
                   help="descriptor caches per set (--manifest; default: build/dev/codecs)")
    p.add_argument("--out", type=Path, default=Paths.out,
                   help="output .npz (default: cerpe/data/xfeat_salad_projection.npz)")


def _thresholds_args(p: argparse.ArgumentParser) -> None:
    from .thresholds import Paths, default_conf as c

    p.add_argument("--synth-seeds", type=int, nargs="*", default=list(c["synth_seeds"]),
                   help="synthetic development seeds (default: 2001; 0 is the paper-default suite and refused)")
    p.add_argument("--synth-preset", default=c["synth_preset"], choices=("dev", "fixture"),
                   help="synthetic suite sizes (as `cerpe dev --synth`)")
    p.add_argument("--real", type=Path, nargs="*", default=None,
                   help="real development manifests (default: the enabled datasets_manifest/dev-*.yaml)")
    p.add_argument("--dev-out", type=Path, default=Paths.dev_out,
                   help="where the synthetic suites are rendered (the `cerpe dev` cache, default build/dev)")
    p.add_argument("--stride-synth", type=_count(1), default=c["stride_synth"],
                   help="step stride of synthetic any-step pairs")
    p.add_argument("--stride-real", type=_count(1), default=c["stride_real"], help="step stride of real any-step pairs")
    p.add_argument("--no-cross-scene", action="store_true", help="no cross-scene negatives for the real sets")
    p.add_argument("--min-recall", type=float, default=c["min_recall"], help="the recall tau keeps on every set")
    p.add_argument("--q-m", type=float, default=c["q_m"], help="quantile of consecutive-frame similarity for tau_m")
    p.add_argument("--q-k", type=float, default=c["q_k"], help="quantile of consecutive-frame similarity for tau_k")
    p.add_argument("--memory-from", choices=("synth", "all"), default=c["memory_from"],
                   help="the sets tau_m and tau_k are taken from (default: synth)")
    p.add_argument("--out", type=Path, default=Paths.out,
                   help="output .json (default: cerpe/data/xfeat_salad_thresholds.json)")
    p.add_argument("--samples", type=Path, default=None,
                   help="also write every labelled pair (set, sample, scores, overlaps, label) to this CSV")
    p.add_argument("--dry-run", action="store_true", help="print, do not write")


ARGS = {"descriptor": _descriptor_args, "projection": _projection_args, "thresholds": _thresholds_args}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    import importlib

    parser.error = functools.partial(_one_line_error, parser)  # an unknown STEP: one line too
    sub = parser.add_subparsers(dest="fit_step", metavar="STEP", parser_class=_StepParser)
    for step, help_ in STEPS.items():
        doc = importlib.import_module(f"{__package__}.{step}").__doc__.strip()
        p = sub.add_parser(step, help=help_, description=doc,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        ARGS[step](p)
        p.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS, help="more log output")
        p.add_argument("-q", "--quiet", action="count", default=argparse.SUPPRESS, help="less log output")


def _command() -> str:
    return " ".join(["cerpe", *map(shlex.quote, sys.argv[1:])])


def main(args: argparse.Namespace) -> int:
    step = getattr(args, "fit_step", None)
    if step is None:
        raise FitError(f"choose what to fit: {', '.join(STEPS)} (`cerpe fit STEP --help`)")
    if step == "descriptor":
        from . import descriptor

        conf = {"what": "mean" if args.descriptor_mean else "centres", "frames": args.frames, "every": args.every,
                "limit": args.limit, "clusters": args.clusters, "features": args.features,
                "max_keypoints": args.max_keypoints, "seed": args.seed, "source_note": args.source_note}
        descriptor.main(conf, descriptor.Paths(args.manifest, args.images, tuple(args.synth or ()), args.out))
    elif step == "projection":
        from . import projection

        conf = {"descriptor": args.descriptor, "checkpoint": args.checkpoint, "device": args.device,
                "every": args.every, "limit": args.limit, "k": args.k, "random_dims": args.random_dims,
                "pq_m": args.pq_m, "seed": args.seed, "command": _command()}
        projection.main(conf, projection.Paths(tuple(args.manifest or ()), args.images, args.cache_dir, args.out))
    else:
        from . import thresholds

        conf = {"synth_seeds": tuple(args.synth_seeds), "synth_preset": args.synth_preset,
                "stride_synth": args.stride_synth, "stride_real": args.stride_real,
                "cross_scene": not args.no_cross_scene, "min_recall": args.min_recall, "q_m": args.q_m,
                "q_k": args.q_k, "memory_from": args.memory_from, "dry_run": args.dry_run, "command": _command()}
        real = None if args.real is None else tuple(args.real)
        thresholds.main(conf, thresholds.Paths(real, args.dev_out, args.out, args.samples))
    return 0
