"""Loading the paper models' weights: what the VGGT, SALAD/DINOv2 and Metric3D adapters share.

The error base of the ``paper`` profile, the device choice and its mixed precision,
weight files read on the CPU with errors that name the file and the fix, key / shape
mismatch reports, and peak VRAM. :mod:`cerpe.backbones.paper_profile` checks and
builds the profile from these; the adapters import them from here, never from the
profile that builds them.
"""
from __future__ import annotations

import logging
import pickle
import zipfile
from pathlib import Path
from typing import Any, Mapping

import torch

from ..errors import CerpeError

logger = logging.getLogger(__name__)

WEIGHTS_ENV = "CERPE_WEIGHTS_DIR"


class PaperModelError(CerpeError, ValueError):
    """A paper model cannot be built or run: missing package/weights, wrong checkpoint, no memory."""


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


def peak_vram_bytes(device: torch.device) -> int | None:
    """``torch.cuda.max_memory_allocated`` on CUDA devices, None elsewhere."""
    return int(torch.cuda.max_memory_allocated(device)) if device.type == "cuda" else None


def reset_peak_vram(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
