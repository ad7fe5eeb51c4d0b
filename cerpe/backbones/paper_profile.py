"""The ``paper`` profile: VGGT + SALAD/DINOv2 + Metric3Dv2 with the paper's parameters.

None of the three models' weights ship with any package, so this profile needs
user-supplied files (see ``docs/PAPER_MODELS.md``). Everything that can be
checked before work starts is checked at once by :func:`check_paper_requirements`
and reported in ONE :class:`PaperModelError` by :func:`require_paper`. It checks for
missing packages, missing / truncated weight files, a local Metric3D clone, and whether
the device has memory enough for VGGT-1B. :func:`build_paper` calls it first.

Where files are looked up: ``<weights_dir>/<release file name>`` (``dino_salad.ckpt``,
``model.pt`` or ``model.safetensors`` for VGGT, ``metric_depth_vit_small_800k.pth``...),
``weights_dir`` being :class:`~cerpe.backbones.config.PaperModelsConfig`'s (default
``$CERPE_WEIGHTS_DIR``); ``$CERPE_METRIC3D_REPO`` for the Metric3D clone.

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

from .config import PaperModelsConfig
from .weights import WEIGHTS_ENV, PaperModelError, select_device, weight_file_problem

logger = logging.getLogger(__name__)

METRIC3D_REPO_ENV = "CERPE_METRIC3D_REPO"
# where a user sets the weights folder (the configuration tree's dotted key)
WEIGHTS_KEY = "backbone.paper.weights_dir"


#: The paper's parameters (Sec. IV): thresholds of the SALAD/DINOv2 descriptor,
#: memory capacity; Delta_k is not given in the paper (our choice, exposed).
PAPER_PARAMETERS: dict[str, float] = {"tau": 0.2, "tau_m": 0.9, "tau_k": 0.2, "L": 5}

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
def weights_dir(conf: PaperModelsConfig) -> Path | None:
    d = conf.weights_dir or os.environ.get(WEIGHTS_ENV)
    return Path(d).expanduser() if d else None


def resolve_weight_file(names: tuple[str, ...], conf: PaperModelsConfig) -> Path:
    """The weight file to use: the first of ``names`` in the weights dir.

    Returns the first candidate even when none exists, so the caller's error names
    what was looked for.
    """
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
def _paths(conf: PaperModelsConfig) -> dict[str, Path | None]:
    m3d_model = conf.metric3d_model
    repo = os.environ.get(METRIC3D_REPO_ENV)
    return {
        "salad": resolve_weight_file(DEFAULT_FILES["salad"], conf),
        "vggt": resolve_weight_file(DEFAULT_FILES["vggt"], conf),
        "metric3d": resolve_weight_file(DEFAULT_FILES.get(m3d_model, (f"{m3d_model}.pth",)), conf),
        "metric3d_repo": Path(repo).expanduser() if repo else None,
    }


def check_paper_requirements(conf: PaperModelsConfig | None = None, depth: str = "metric3d") -> list[str]:
    """Every reason the ``paper`` profile cannot run here, each with its fix (empty: ready).

    Checks packages (``vggt`` and what its model code imports; ``mmengine`` or
    ``mmcv`` for Metric3D), weight files (present, not truncated, plausible
    size), the local Metric3D clone (only with ``depth`` ``metric3d``), and memory
    for VGGT-1B on the chosen device. Nothing is loaded.
    """
    conf = conf or PaperModelsConfig()
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
    for key, what in (("salad", "SALAD (DINOv2) checkpoint"), ("vggt", "VGGT-1B")):
        p = weight_file_problem(paths[key], what, WEIGHTS_KEY, APPROX_BYTES[key])
        if p:
            problems.append(p)

    if depth == "metric3d":
        m3d_model = conf.metric3d_model
        repo = paths["metric3d_repo"]
        if repo is None:
            problems.append(f"Metric3D: no local clone given: git clone https://github.com/YvanYin/Metric3D "
                            f"and set {METRIC3D_REPO_ENV} to it")
        elif not (repo / "hubconf.py").is_file():
            problems.append(f"Metric3D: {repo} has no hubconf.py; it must be a clone of "
                            f"https://github.com/YvanYin/Metric3D")
        if not (module_available("mmengine") or module_available("mmcv")):
            problems.append("Metric3D's code needs mmengine (or mmcv): pip install mmengine")
        p = weight_file_problem(paths["metric3d"], f"Metric3Dv2 ({m3d_model})", WEIGHTS_KEY,
                                APPROX_BYTES.get(m3d_model))
        if p:
            problems.append(p)

    # Memory (VGGT-1B dominates; weights stay fp32, activations under autocast).
    if conf.check_memory:
        try:
            device = select_device(conf.device)
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
                    f"(backbone.paper.check_memory: false skips this check)")
    return problems


def require_paper(conf: PaperModelsConfig | None = None, depth: str = "metric3d") -> None:
    """Raise ONE :class:`PaperModelError` listing every problem of :func:`check_paper_requirements`."""
    problems = check_paper_requirements(conf, depth)
    if problems:
        lines = "\n".join(f"  - {p}" for p in problems)
        raise PaperModelError(
            f"the 'paper' profile cannot start ({len(problems)} problem(s)):\n{lines}\n"
            f"See docs/PAPER_MODELS.md; the default 'offline' profile needs none of these.")


def build_paper(conf: PaperModelsConfig | None = None, depth: str | None = None,
                depth_options: Mapping[str, Any] | None = None) -> tuple[Any, Any, Any]:
    """Build ``(descriptor, backbone, depth)`` of the paper: SALAD/DINOv2, VGGT-1B, Metric3Dv2.

    Checks all requirements first (one error listing all of them), then loads
    the models onto the selected device (CUDA when present); each adapter keeps
    its own architecture settings (``default_conf``). ``depth`` other than
    ``metric3d`` (the default; e.g. ``sensor`` for real robots) is built by
    :func:`cerpe.backbones.depth.build_depth_source` with ``depth_options``.
    """
    conf = conf or PaperModelsConfig()
    depth = depth or "metric3d"
    require_paper(conf, depth)
    from .metric3d import Metric3DDepth
    from .salad_dinov2 import SaladDinoV2Descriptor
    from .vggt import VGGTBackbone

    paths = _paths(conf)
    device = conf.device
    descriptor = SaladDinoV2Descriptor({"checkpoint": str(paths["salad"]), "device": device})
    backbone = VGGTBackbone({"checkpoint": str(paths["vggt"]), "device": device})
    if depth == "metric3d":
        depth_src = Metric3DDepth({**(depth_options or {}), "model": conf.metric3d_model,
                                   "checkpoint": str(paths["metric3d"]), "repo": str(paths["metric3d_repo"]),
                                   "device": device})
    else:
        from .depth import build_depth_source

        depth_src = build_depth_source(depth, dict(depth_options or {}))
    logger.info("paper profile built on %s: SALAD %s, VGGT %s", select_device(device), paths["salad"], paths["vggt"])
    return descriptor, backbone, depth_src
