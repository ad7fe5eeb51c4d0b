"""The ``paper`` profile: VGGT + SALAD/DINOv2 + Metric3Dv2 with the paper's parameters.

None of the three models' weights ship with any package, so this profile needs
user-supplied files (see ``docs/PAPER_MODELS.md``). Everything that can be
checked before work starts is checked at once by :func:`check_paper_requirements`
and reported in ONE :class:`PaperModelError` by :func:`require_paper`: missing
packages, missing / truncated weight files, a local Metric3D clone, and whether
the device has memory enough for VGGT-1B. :func:`build_paper` calls it first.

Where files are looked up: ``<weights_dir>/<release file name>`` (``dino_salad.ckpt``,
``model.pt`` or ``model.safetensors`` for VGGT, ``metric_depth_vit_small_800k.pth``...),
``weights_dir`` being :class:`~cerpe.backbones.config.PaperModelsConfig`'s (default
``$CERPE_WEIGHTS_DIR``); ``$CERPE_METRIC3D_REPO`` for the Metric3D clone.

This module also holds what the three adapters share: the error base, the
device choice, checkpoint reading with clear errors, and key-mismatch reports.
"""
from __future__ import annotations

import importlib.util
import logging
import os
import pickle
import zipfile
from pathlib import Path
from typing import Any, Mapping

import torch

from ..errors import CerpeError
from .config import PaperModelsConfig

logger = logging.getLogger(__name__)

WEIGHTS_ENV = "CERPE_WEIGHTS_DIR"
METRIC3D_REPO_ENV = "CERPE_METRIC3D_REPO"
# where a user sets the weights folder (the configuration tree's dotted key)
WEIGHTS_KEY = "backbone.paper.weights_dir"


class PaperModelError(CerpeError, ValueError):
    """A paper model cannot be built or run: missing package/weights, wrong checkpoint, no memory."""


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
def select_device(name: str = "auto") -> torch.device:
    """``auto`` -> CUDA when available, else CPU; otherwise ``torch.device(name)``.

    Raises:
        PaperModelError: a CUDA device was asked for but none is usable.
    """
    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise PaperModelError(f"device {name!r} requested but CUDA is not available; use device: auto or cpu")
    return dev


def autocast_dtype(device: torch.device) -> torch.dtype | None:
    """Mixed precision used on ``device``: bf16 on Ampere+ GPUs, fp16 on older ones, none (fp32) on CPU."""
    if device.type != "cuda":
        return None
    major, _ = torch.cuda.get_device_capability(device)
    return torch.bfloat16 if major >= 8 else torch.float16


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


def weight_file_problem(path: Path, what: str, config_key: str, approx_bytes: float | None = None) -> str | None:
    """Cheap pre-flight check of a weight file; a message naming cause and fix, or None.

    Detects a missing file, an empty one, a torch zip archive whose central
    directory is gone (the usual sign of an interrupted download), and a file
    far smaller than the official one.
    """
    fix = (f"put it there, or set {config_key} or {WEIGHTS_ENV} to the folder holding it "
           f"(see docs/PAPER_MODELS.md)")
    if not path.exists():
        return f"{what}: weight file {path} not found; {fix}"
    if not path.is_file():
        return f"{what}: {path} is not a file; {fix}"
    size = path.stat().st_size
    if size == 0:
        return f"{what}: weight file {path} is empty; download it again"
    if path.suffix in (".pt", ".pth", ".ckpt") and _looks_like_zip(path):
        try:
            with zipfile.ZipFile(path) as zf:
                zf.infolist()
        except (zipfile.BadZipFile, OSError) as exc:
            return f"{path}: {what} weight file is truncated or corrupt ({exc}); download it again"
    if approx_bytes and size < 0.5 * approx_bytes:
        return (f"{path}: {what} weight file has {size / 1e6:.1f} MB, the official one about "
                f"{approx_bytes / 1e6:.0f} MB: truncated download or a different model? Download it again")
    return None


def _looks_like_zip(path: Path) -> bool:
    with open(path, "rb") as fh:
        return fh.read(4) == b"PK\x03\x04"


def load_checkpoint(path: Path, what: str) -> dict[str, Any]:
    """Read a weight file (torch zip/pickle or safetensors) on the CPU, with errors naming the file.

    ``weights_only=True`` is tried first; Lightning checkpoints carrying
    hyper-parameter objects need the full unpickler, which is used only as a
    fallback for a file the user supplied (logged).
    """
    problem = weight_file_problem(path, what, "the config")
    if problem:
        raise PaperModelError(problem)
    if path.suffix == ".safetensors":
        try:
            from safetensors.torch import load_file
        except ModuleNotFoundError:
            raise PaperModelError(f"{path}: reading .safetensors needs the package safetensors "
                                  f"(pip install safetensors), or use the .pt file") from None
        try:
            return dict(load_file(str(path)))
        except Exception as exc:  # safetensors raises its own SafetensorError
            raise PaperModelError(f"{path}: cannot read {what} weights ({exc}); download it again") from None
    try:
        try:
            obj = torch.load(path, map_location="cpu", weights_only=True, mmap=_looks_like_zip(path))
        except Exception as exc:
            if "Unsupported global" not in str(exc):  # only a Lightning/pickled object, not a bad file
                raise
            logger.warning("%s: not loadable with weights_only=True (%s); using the full unpickler",
                           path, type(exc).__name__)
            obj = torch.load(path, map_location="cpu", weights_only=False)
    except (RuntimeError, EOFError, OSError, ValueError, pickle.UnpicklingError) as exc:
        raise PaperModelError(f"{path}: {what} weight file is truncated or corrupt ({exc}); "
                              f"download it again") from None
    if not isinstance(obj, dict):
        raise PaperModelError(f"{path}: expected a state dict for {what}, got {type(obj).__name__}")
    return obj


def describe_key_mismatch(missing: list[str], unexpected: list[str], path: Path | str, what: str,
                          n_show: int = 5) -> str:
    """One message listing a few missing and unexpected keys."""
    parts = [f"{path}: not a {what} checkpoint (keys do not match)"]
    if missing:
        parts.append(f"{len(missing)} missing, e.g. {', '.join(missing[:n_show])}")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected, e.g. {', '.join(unexpected[:n_show])}")
    return "; ".join(parts)


def load_state_dict_strict(module: torch.nn.Module, state: Mapping[str, torch.Tensor], path: Path | str,
                           what: str, allow_missing: tuple[str, ...] = ()) -> None:
    """``load_state_dict`` that reports mismatching keys or shapes as one :class:`PaperModelError`.

    ``allow_missing``: key suffixes a module may lack in the file (non-persistent caches).
    """
    own = module.state_dict()
    missing = [k for k in own if k not in state and not k.endswith(allow_missing)]
    unexpected = [k for k in state if k not in own]
    if missing or unexpected:
        raise PaperModelError(describe_key_mismatch(missing, unexpected, path, what))
    bad = [f"{k} {tuple(state[k].shape)} != {tuple(v.shape)}" for k, v in own.items()
           if k in state and tuple(state[k].shape) != tuple(v.shape)]
    if bad:
        raise PaperModelError(f"{path}: {what} checkpoint has tensors of the wrong shape "
                              f"(another model size?), e.g. {'; '.join(bad[:5])}")
    module.load_state_dict(dict(state), strict=False)


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


def peak_vram_bytes(device: torch.device) -> int | None:
    """``torch.cuda.max_memory_allocated`` on CUDA devices, None elsewhere."""
    return int(torch.cuda.max_memory_allocated(device)) if device.type == "cuda" else None


def reset_peak_vram(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


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
