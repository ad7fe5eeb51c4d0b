"""The gate's ROC AUC with compressed descriptors against the uncompressed one, on development data.

Per development set (synthetic suites of --synth-seeds, rendered as `cerpe dev` renders
them, and the real development sets with ground-truth co-visibility), the samples of
`cerpe fit thresholds`: pairs of views of two robots at any two steps, labelled
with the co-visibility label (overlap >= 0.2 both ways positive, < 0.05 both ways
negative), real sets with cross-scene negatives. Prints, per set, the ROC AUC of the
uncompressed message (`full`: fp16 values) and of each compressed codec of the projection
file, their difference, the frame sizes, and each codec's gate threshold by the
calibration rule (largest tau with recall >= 0.8 on every set); --write-tau stores those
thresholds in the projection file (the robots' gate reads them).

    python -m lab.descriptor_codec_auc                     # seed 2001 + the real dev sets
    python -m lab.descriptor_codec_auc --write-tau
    python -m lab.descriptor_codec_auc --projection my.npz --synth-seeds 2002 --real my-dev.yaml
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _args(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--synth-seeds", type=int, nargs="*", default=[2001])
    ap.add_argument("--real", nargs="*", default=None,
                    help="real development manifests (default: the enabled datasets_manifest/dev-*.yaml)")
    ap.add_argument("--projection", type=Path, default=None, help="projection file (default: the shipped one)")
    ap.add_argument("--dev-out", type=Path, default=ROOT / "build" / "dev")
    ap.add_argument("--stride-synth", type=int, default=2)
    ap.add_argument("--min-recall", type=float, default=0.8)
    ap.add_argument("--write-tau", action="store_true", help="store each codec's tau in the projection file")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    a = _args(argv)
    from cerpe.backbones.descriptor import XFeatSaladDescriptor
    from cerpe.compress import DescriptorCodec, default_projection_path, load_projection, save_projection
    from cerpe.datasets import find_manifests, load_setting
    from cerpe.messages import DescriptorMessage
    from cerpe.fit.descriptor_codecs import codec_figures, describe_setting, labelled_pairs
    from cerpe.pipeline.dev import PAPER_SEED, synthetic_set
    from cerpe.synth import SUITES

    path = a.projection or default_projection_path()
    proj = load_projection(path)
    desc = XFeatSaladDescriptor()
    cache = a.dev_out / "codecs"
    cache.mkdir(parents=True, exist_ok=True)
    todo = []
    for seed in a.synth_seeds:
        if seed == PAPER_SEED:
            raise SystemExit("descriptor_codec_auc: seed 0 is the paper-default suite (test data)")
        for setting in SUITES["paper-default"]:
            s = synthetic_set(setting, seed, "dev", a.dev_out, progress=False)
            todo.append(("synthetic", s.manifest, a.stride_synth))
    reals = a.real if a.real is not None else [
        str(m.path) for m in find_manifests(ROOT / "datasets_manifest") if m.name.startswith("dev-") and m.enabled]
    todo += [("real", Path(p), 1) for p in reals]
    sets = {}
    for kind, manifest, stride in todo:
        setting = load_setting(manifest)
        if any(e.overlap is None for e in setting.encounters):
            print(f"{setting.name}: no ground-truth co-visibility (no depth); skipped", file=sys.stderr)
            continue
        D = describe_setting(desc, setting, cache / f"{setting.name}-every{stride}-desc.npz", every=stride)
        pairs = [labelled_pairs(enc, d, stride, cache / f"{setting.name}-e{k}-pairs.csv")
                 for k, (enc, d) in enumerate(zip(setting.encounters, D))]
        sets[setting.name] = {"kind": kind, "D": D, "pairs": pairs}
    codecs = {"full": None, **{c: DescriptorCodec(c, proj) for c in ("pca-int8", "pca-pq")}}
    df, taus = codec_figures(sets, codecs)
    print(f"projection {path} (codebook {proj.codebook:08x}, {proj.meta.get('n_images')} fitting images: "
          f"{proj.meta.get('source')})")
    print("frame bytes (descriptor + 70 B pose frame): full fp16 "
          f"{DescriptorMessage.wire_bytes(desc.dim, 'fp16')} + 70, "
          + ", ".join(f"{c} {codecs[c].wire_bytes()} + 70 = {codecs[c].wire_bytes() + 70}" for c in codecs if codecs[c]))
    wide = df.pivot(index="set", columns="codec", values="roc_auc")[list(codecs)]
    for c in codecs:
        if c != "full":
            wide[f"{c} - full"] = wide[c] - wide["full"]
    n = df[df["codec"] == "full"].set_index("set")[["n_positive", "n_negative"]]
    print(wide.join(n).to_string(float_format=lambda v: f"{v:.4f}"))
    print("tau (largest with recall >= 0.8 on every set): " + ", ".join(f"{c} {t:.4f}" for c, t in taus.items()))
    if a.write_tau:
        from dataclasses import replace

        th = {c: {"tau": taus[c], "rule": "largest tau with recall >= 0.8 on every set (co-visibility label, "
                  "any-step pairs)", "sets": sorted(sets)} for c in codecs if c != "full"}
        save_projection(replace(proj, thresholds=th), path)
        print(f"wrote the thresholds into {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
