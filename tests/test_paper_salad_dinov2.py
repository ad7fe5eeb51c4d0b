"""SALAD/DINOv2 descriptor: checkpoint mapping with upstream key names, preprocessing, output."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cerpe.backbones.dinov2 import DinoV2Error, DinoVisionTransformer
from cerpe.backbones.weights import PaperModelError
from cerpe.backbones.salad_dinov2 import (
    SaladDinoV2Descriptor,
    SaladDinoV2Error,
    SaladDinoV2Model,
    preprocess_salad,
    split_salad_state_dict,
)
from cerpe.protocols import DescriptorEncoder, View
from test_paper_salad import UPSTREAM_AGGREGATOR_SHAPES


def upstream_dinov2_vitb14_shapes() -> dict[str, tuple[int, ...]]:
    """Key names/shapes of facebookresearch/dinov2 hub ``dinov2_vitb14`` (img 518, patch 14, layerscale)."""
    D, hidden = 768, 3072
    shapes: dict[str, tuple[int, ...]] = {
        "cls_token": (1, 1, D), "pos_embed": (1, 37 * 37 + 1, D), "mask_token": (1, D),
        "patch_embed.proj.weight": (D, 3, 14, 14), "patch_embed.proj.bias": (D,),
        "norm.weight": (D,), "norm.bias": (D,),
    }
    for i in range(12):
        b = f"blocks.{i}."
        shapes.update({
            b + "norm1.weight": (D,), b + "norm1.bias": (D,),
            b + "attn.qkv.weight": (3 * D, D), b + "attn.qkv.bias": (3 * D,),
            b + "attn.proj.weight": (D, D), b + "attn.proj.bias": (D,),
            b + "ls1.gamma": (D,), b + "norm2.weight": (D,), b + "norm2.bias": (D,),
            b + "mlp.fc1.weight": (hidden, D), b + "mlp.fc1.bias": (hidden,),
            b + "mlp.fc2.weight": (D, hidden), b + "mlp.fc2.bias": (D,), b + "ls2.gamma": (D,),
        })
    return shapes


def _upstream_checkpoint(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    sd = {"backbone.model." + k: torch.randn(s, generator=g) * 0.02 for k, s in upstream_dinov2_vitb14_shapes().items()}
    sd.update({"aggregator." + k: torch.randn(s, generator=g) * 0.05 for k, s in UPSTREAM_AGGREGATOR_SHAPES.items()})
    return sd


@pytest.fixture(scope="module")
def official_model_and_ckpt() -> tuple[SaladDinoV2Model, dict[str, torch.Tensor]]:
    ckpt = _upstream_checkpoint()
    model = SaladDinoV2Model()
    model.load_salad_checkpoint({"state_dict": ckpt, "epoch": 3}, "lightning.ckpt")
    return model.eval(), ckpt


def test_dinov2_names_match_hub(official_model_and_ckpt) -> None:
    model, _ = official_model_and_ckpt  # a default DinoVisionTransformer()
    own = {k: tuple(v.shape) for k, v in model.backbone.state_dict().items()}
    assert own == upstream_dinov2_vitb14_shapes()


def test_checkpoint_mapping_loads_every_tensor(official_model_and_ckpt) -> None:
    model, ckpt = official_model_and_ckpt
    assert torch.equal(model.backbone.blocks[11].attn.qkv.weight, ckpt["backbone.model.blocks.11.attn.qkv.weight"])
    assert torch.equal(model.aggregator.score[3].weight, ckpt["aggregator.score.3.weight"])
    assert torch.equal(model.aggregator.dust_bin, ckpt["aggregator.dust_bin"])
    # The released file has the keys at the top level: same mapping.
    b, h = split_salad_state_dict(ckpt)
    assert len(b) == 175 and len(h) == 13


def test_wrong_checkpoints_are_named(official_model_and_ckpt) -> None:
    model, ckpt = official_model_and_ckpt
    with pytest.raises(SaladDinoV2Error, match="aggregator"):
        split_salad_state_dict({k: v for k, v in ckpt.items() if k.startswith("backbone.")}, "x.ckpt")
    with pytest.raises(SaladDinoV2Error, match="unexpected, e.g. classifier.weight"):
        split_salad_state_dict({**ckpt, "classifier.weight": torch.zeros(1)}, "x.ckpt")
    broken = {k: v for k, v in ckpt.items() if "blocks.3.mlp" not in k}
    with pytest.raises(SaladDinoV2Error, match=r"x.ckpt: .*4 missing, e.g. blocks.3.mlp"):
        model.load_salad_checkpoint(broken, "x.ckpt")  # checked before anything is copied
    small = SaladDinoV2Model({"preset": "dinov2_vits14"})
    with pytest.raises(PaperModelError, match="wrong shape"):
        small.load_salad_checkpoint(ckpt, "x.ckpt")


def test_official_descriptor_8448_unit_norm(official_model_and_ckpt) -> None:
    model, _ = official_model_and_ckpt
    desc = SaladDinoV2Descriptor({"device": "cpu"}, model=model)
    assert isinstance(desc, DescriptorEncoder)
    assert desc.dim == 8448 and desc.thresholds == {"tau": 0.2, "tau_m": 0.9, "tau_k": 0.2}
    img = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    d = desc.describe(View("a", img))
    assert d.shape == (8448,) and d.dtype == np.float32
    assert np.isclose(np.linalg.norm(d), 1.0, atol=1e-5)


def test_checkpoint_file_roundtrip(tmp_path: Path) -> None:
    small = {"dinov2": {"embed_dim": 32, "depth": 1, "num_heads": 2},
             "head": {"num_clusters": 4, "cluster_dim": 8, "token_dim": 8, "hidden_dim": 16}}
    torch.manual_seed(0)
    src = SaladDinoV2Model(small["dinov2"], small["head"])
    sd = {**{"backbone.model." + k: v for k, v in src.backbone.state_dict().items()},
          **{"aggregator." + k: v for k, v in src.aggregator.state_dict().items()}}
    path = tmp_path / "dino_salad.ckpt"
    torch.save({"state_dict": sd}, path)
    desc = SaladDinoV2Descriptor({"device": "cpu", "checkpoint": str(path), "image_size": (56, 56), **small})
    img = np.random.default_rng(1).integers(0, 255, (40, 50, 3), dtype=np.uint8)
    with torch.no_grad():
        ref = src.eval()(preprocess_salad([img], (56, 56)))[0].numpy()
    assert np.allclose(desc.describe(View("a", img)), ref, atol=1e-6)
    trunc = tmp_path / "trunc.ckpt"
    trunc.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(PaperModelError, match="truncated or corrupt"):
        SaladDinoV2Descriptor({"device": "cpu", "checkpoint": str(trunc), **small})
    with pytest.raises(PaperModelError, match="not found"):
        SaladDinoV2Descriptor({"device": "cpu", "checkpoint": str(tmp_path / "nope.ckpt")})


def test_preprocess_and_input_errors() -> None:
    x = preprocess_salad([np.full((30, 40, 3), 255, np.uint8)])
    assert x.shape == (1, 3, 322, 322)
    assert torch.allclose(x[0, :, 0, 0], (1 - torch.tensor([0.485, 0.456, 0.406])) / torch.tensor([0.229, 0.224, 0.225]))
    with pytest.raises(SaladDinoV2Error, match="image 0"):
        preprocess_salad([np.zeros((30, 40), np.uint8)])
    with pytest.raises(DinoV2Error, match="multiple of the patch"):
        DinoVisionTransformer(embed_dim=16, depth=1, num_heads=2).forward_tokens(torch.zeros(1, 3, 30, 28))


def test_pos_embed_interpolation_shape() -> None:
    vit = DinoVisionTransformer(embed_dim=16, depth=1, num_heads=2)
    assert vit.interpolate_pos_encoding(1 + 23 * 23, 322, 322).shape == (1, 1 + 23 * 23, 16)
    assert vit.interpolate_pos_encoding(1 + 20 * 26, 280, 364).shape == (1, 1 + 20 * 26, 16)
    assert vit.interpolate_pos_encoding(1 + 37 * 37, 518, 518) is vit.pos_embed
