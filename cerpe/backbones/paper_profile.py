"""The ``paper`` profile: VGGT + SALAD/DINOv2 + Metric3Dv2 with the paper's parameters.

None of the three models' weights ship with any package, so this profile needs
user-supplied files (see ``docs/PAPER_MODELS.md``). Everything that can be
checked before work starts is checked at once by :func:`check_paper_requirements`
and reported in ONE :class:`PaperModelError` by :func:`require_paper`: missing
packages, missing / truncated weight files, a local Metric3D clone, and whether
the device has memory enough for VGGT-1B. :func:`build_paper` calls it first.

Where files are looked up (first hit wins):

* an explicit path in the config (``salad.checkpoint``, ``vggt.checkpoint``,
  ``metric3d.checkpoint``, ``metric3d.repo``);
* ``$CERPE_WEIGHTS_DIR/<default file name>`` (``dino_salad.ckpt``,
  ``model.pt`` or ``model.safetensors`` for VGGT, ``metric_depth_vit_small_800k.pth``...);
* ``$CERPE_METRIC3D_REPO`` for the Metric3D clone.

What the three adapters share (the error base, the device choice, checkpoint reading
with clear errors, key-mismatch reports) lives in :mod:`cerpe.backbones.weights`.
"""
from __future__ import annotations

import importlib.util
import logging
import os
from pathlib import Path
from typing import Any, Mapping

import torch

from ..config import merge_conf
from .weights import WEIGHTS_ENV, PaperModelError, select_device, weight_file_problem

logger = logging.getLogger(__name__)

METRIC3D_REPO_ENV = "CERPE_METRIC3D_REPO"


#: The paper's parameters (Sec. IV): thresholds of the SALAD/DINOv2 descriptor,
#: memory capacity; Delta_k is not given in the paper (our choice, exposed).
PAPER_PARAMETERS: dict[str, float] = {"tau": 0.2, "tau_m": 0.9, "tau_k": 0.2, "L": 5}

default_conf: dict[str, Any] = {
    "device": "auto",  # auto | cpu | cuda | cuda:N
    "weights_dir": None,  # default: $CERPE_WEIGHTS_DIR
    # each model's own conf, checked by its adapter (open here); a checkpoint not given is looked up:
    "salad": {},  # SaladDinoV2Descriptor; checkpoint: <weights_dir>/dino_salad.ckpt
    "vggt": {},  # VGGTBackbone; checkpoint: <weights_dir>/model.pt | model.safetensors
    "metric3d": {},  # Metric3DDepth; repo: $CERPE_METRIC3D_REPO, model: metric3d_vit_small
    "depth": "metric3d",  # or any cerpe.backbones.depth source name (sensor on real robots)
    "depth_conf": {},
    "check_memory": True,
}

#: Default file names (those of the official releases).
DEFAULT_FILES: dict[str, tuple[str, ...]] = {
    "salad": ("dino_salad.ckpt",),
    "vggt": ("model.pt", "model.safetensors"),
    "metric3d_vit_small": ("metric_depth_vit_small_800k.pth",),
    "metric3d_vit_large": ("metric_depth_vit_large_800k.pth",),
    "metric3d_vit_giant2": ("metric_depth_vit_giant2_800k.pth",),
}

#: Rough sizes of the official fp32 files, for plausibility checks and memory estimates.
APPROX_BYTES: dict[str, float] = {
    "salad": 0.35e9,
    "vggt": 5.0e9,
    "metric3d_vit_small": 0.15e9,
    "metric3d_vit_large": 1.6e9,
    "metric3d_vit_giant2": 5.6e9,
}


# ----------------------------------------------------------------------------- helpers
def weights_dir(conf: Mapping[str, Any]) -> Path | None:
    d = conf.get("weights_dir") or os.environ.get(WEIGHTS_ENV)
    return Path(d).expanduser() if d else None


def resolve_weight_file(explicit: str | os.PathLike | None, names: tuple[str, ...],
                        conf: Mapping[str, Any]) -> Path:
    """The weight file to use: the explicit path, else the first of ``names`` in the weights dir.

    Returns the explicit path (or the first candidate) even when it does not
    exist, so the caller's error names what was looked for.
    """
    if explicit:
        return Path(explicit).expanduser()
    base = weights_dir(conf)
    cands = [base / n for n in names] if base else [Path(n) for n in names]
    for c in cands:
        if c.is_file():
            return c
    return cands[0]


def available_memory_bytes(device: torch.device) -> int | None:
    """Free memory for a model on ``device``: GPU total memory, or ``MemAvailable`` on Linux."""
    if device.type == "cuda":
        return int(torch.cuda.get_device_properties(device).total_memory)
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def module_available(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


# ----------------------------------------------------------------------------- requirements
def _paths(conf: Mapping[str, Any]) -> dict[str, Path | None]:
    m3d_model = conf["metric3d"].get("model", "metric3d_vit_small")
    repo = conf["metric3d"].get("repo") or os.environ.get(METRIC3D_REPO_ENV)
    return {
        "salad": resolve_weight_file(conf["salad"].get("checkpoint"), DEFAULT_FILES["salad"], conf),
        "vggt": resolve_weight_file(conf["vggt"].get("checkpoint"), DEFAULT_FILES["vggt"], conf),
        "metric3d": resolve_weight_file(conf["metric3d"].get("checkpoint"),
                                        DEFAULT_FILES.get(m3d_model, (f"{m3d_model}.pth",)), conf),
        "metric3d_repo": Path(repo).expanduser() if repo else None,
    }


def check_paper_requirements(conf: Mapping[str, Any] | None = None) -> list[str]:
    """Every reason the ``paper`` profile cannot run here, each with its fix (empty: ready).

    Checks packages (``vggt`` and what its model code imports; ``mmengine`` or
    ``mmcv`` for Metric3D), weight files (present, not truncated, plausible
    size), the local Metric3D clone, and memory for VGGT-1B on the chosen device.
    Nothing is loaded.
    """
    conf = merge_conf(default_conf, conf, "paper profile conf")
    problems: list[str] = []
    paths = _paths(conf)

    # Packages.
    if not module_available("vggt"):
        problems.append(
            "package vggt is not installed: git clone https://github.com/facebookresearch/vggt && "
            "pip install --no-deps -e vggt && pip install huggingface_hub einops safetensors "
            "(--no-deps keeps our torch; never install its pinned torch/torchvision)")
    for dep in ("huggingface_hub", "einops"):
        if not module_available(dep):
            problems.append(f"package {dep} (imported by vggt's model code) is missing: pip install {dep}")
    if paths["vggt"] is not None and paths["vggt"].suffix == ".safetensors" and not module_available("safetensors"):
        problems.append("package safetensors is needed to read model.safetensors: pip install safetensors")

    # Weight files.
    for key, what, ck in (("salad", "SALAD (DINOv2) checkpoint", "salad.checkpoint"),
                          ("vggt", "VGGT-1B", "vggt.checkpoint")):
        p = weight_file_problem(paths[key], what, ck, APPROX_BYTES[key])
        if p:
            problems.append(p)

    if conf.get("depth", "metric3d") == "metric3d":
        m3d_model = conf["metric3d"].get("model", "metric3d_vit_small")
        repo = paths["metric3d_repo"]
        if repo is None:
            problems.append(f"Metric3D: no local clone given: git clone https://github.com/YvanYin/Metric3D "
                            f"and set metric3d.repo or {METRIC3D_REPO_ENV} to it")
        elif not (repo / "hubconf.py").is_file():
            problems.append(f"Metric3D: {repo} has no hubconf.py; it must be a clone of "
                            f"https://github.com/YvanYin/Metric3D")
        if not (module_available("mmengine") or module_available("mmcv")):
            problems.append("Metric3D's code needs mmengine (or mmcv): pip install mmengine")
        p = weight_file_problem(paths["metric3d"], f"Metric3Dv2 ({m3d_model})", "metric3d.checkpoint",
                                APPROX_BYTES.get(m3d_model))
        if p:
            problems.append(p)

    # Memory (VGGT-1B dominates; weights stay fp32, activations under autocast).
    if conf.get("check_memory", True):
        try:
            device = select_device(conf.get("device", "auto"))
        except PaperModelError as exc:
            problems.append(str(exc))
        else:
            need = APPROX_BYTES["vggt"] + APPROX_BYTES["salad"] + 2.0e9
            have = available_memory_bytes(device)
            if have is not None and have < need:
                where = "GPU" if device.type == "cuda" else "CPU RAM"
                problems.append(
                    f"device {device}: {where} has {have / 2**30:.1f} GiB available, VGGT-1B + SALAD need "
                    f"about {need / 2**30:.1f} GiB; use a GPU with >= 8 GiB (device: cuda) or free memory "
                    f"(check_memory: false skips this check)")
    return problems


def require_paper(conf: Mapping[str, Any] | None = None) -> None:
    """Raise ONE :class:`PaperModelError` listing every problem of :func:`check_paper_requirements`."""
    problems = check_paper_requirements(conf)
    if problems:
        lines = "\n".join(f"  - {p}" for p in problems)
        raise PaperModelError(
            f"the 'paper' profile cannot start ({len(problems)} problem(s)):\n{lines}\n"
            f"See docs/PAPER_MODELS.md; the default 'offline' profile needs none of these.")


def build_paper(conf: Mapping[str, Any] | None = None) -> tuple[Any, Any, Any]:
    """Build ``(descriptor, backbone, depth)`` of the paper: SALAD/DINOv2, VGGT-1B, Metric3Dv2.

    Checks all requirements first (one error listing all of them), then loads
    the models onto the selected device (CUDA when present). ``conf["depth"]``
    other than ``metric3d`` (e.g. ``sensor`` for real robots) is built by
    :func:`cerpe.backbones.depth.build_depth_source`.
    """
    conf = merge_conf(default_conf, conf, "paper profile conf")
    require_paper(conf)
    from .metric3d import Metric3DDepth
    from .salad_dinov2 import SaladDinoV2Descriptor
    from .vggt import VGGTBackbone

    paths = _paths(conf)
    device = conf.get("device", "auto")
    descriptor = SaladDinoV2Descriptor({**conf["salad"], "checkpoint": str(paths["salad"]), "device": device})
    backbone = VGGTBackbone({**conf["vggt"], "checkpoint": str(paths["vggt"]), "device": device})
    if conf.get("depth", "metric3d") == "metric3d":
        depth = Metric3DDepth({**conf["metric3d"], "checkpoint": str(paths["metric3d"]),
                               "repo": str(paths["metric3d_repo"]), "device": device})
    else:
        from .depth import build_depth_source

        depth = build_depth_source(conf["depth"], conf.get("depth_conf"))
    logger.info("paper profile built on %s: SALAD %s, VGGT %s", select_device(device), paths["salad"], paths["vggt"])
    return descriptor, backbone, depth
