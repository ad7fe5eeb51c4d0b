"""XFeat's precision: the CPU check, the choice, the bfloat16 network against the float32 one, the knob."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.backbones.xfeat_net import BF16_BLOCKS, native_bf16, resolve_precision
from test_backbone_offline import Room, pose


def test_native_bf16_reads_the_cpu_flags(tmp_path):
    with_bf16 = tmp_path / "a"
    with_bf16.write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f avx512_bf16 amx_tile\n")
    with_amx = tmp_path / "b"
    with_amx.write_text("flags\t: fpu amx_bf16\n")
    without = tmp_path / "c"
    without.write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f avx512_vnni\n")
    assert native_bf16(with_bf16) and native_bf16(with_amx)
    assert not native_bf16(without)
    assert not native_bf16(tmp_path / "missing")  # not Linux: never assumed


def test_resolve_precision():
    assert resolve_precision("auto", native=True) == "bf16"
    assert resolve_precision("auto", native=False) == "fp32"
    assert resolve_precision("fp32", native=True) == "fp32"
    assert resolve_precision("bf16", native=False) == "bf16"  # asked for explicitly: kept
    with pytest.raises(ValueError, match="fp32, bf16, auto"):
        resolve_precision("fp16")


def test_encoder_refuses_an_unknown_precision():
    from cerpe.backbones.xfeat import XFeatEncoder, XFeatError

    with pytest.raises(XFeatError, match="'int8'"):
        XFeatEncoder(precision="int8")


def test_bf16_network_is_the_fp32_one_up_to_bfloat16_rounding():
    """The keypoint head stays in float32 (the same logits bit for bit); the deeper blocks run in
    bfloat16, so the dense map differs, by little: mean 1 - cos to the float32 map under 1e-4."""
    import cv2
    import torch
    import torch.nn.functional as F

    from cerpe.backbones.xfeat import XFeatEncoder, _network_input

    fp32 = XFeatEncoder(precision="fp32")
    bf16 = XFeatEncoder(precision="bf16")
    assert (fp32.precision, bf16.precision) == ("fp32", "bf16")
    assert all(next(bf16.net.bf16[name].parameters()).dtype == torch.bfloat16 for name in BF16_BLOCKS)
    img = cv2.resize(Room(1).render(pose((0.2, 0, 0.1), (0, 10, 0)))[0], (640, 480))
    x = _network_input(fp32.model, img)[0]
    with torch.inference_mode():
        (d32, k32, r32), (d16, k16, r16) = fp32.net(x), bf16.net(x)
    assert all(t.dtype == torch.float32 for t in (d16, k16, r16))
    assert torch.equal(k32, k16)
    assert not torch.equal(d32, d16)  # bfloat16 really ran
    cos = (F.normalize(d32, dim=1) * F.normalize(d16, dim=1)).sum(1)
    assert float((1 - cos).mean()) < 1e-4
    assert float((r32 - r16).abs().mean() / r32.abs().mean()) < 0.02
    a, b = fp32.encode_image(img), bf16.encode_image(img)
    common = {tuple(p) for p in np.round(a.keypoints, 3)} & {tuple(p) for p in np.round(b.keypoints, 3)}
    assert len(common) >= 0.95 * a.n  # the same keypoints, but for a few at the score margin


def test_precision_knob_and_preset():
    from cerpe import method_config

    assert method_config.build("paper").backbone.offline.precision == "fp32"  # the tables
    assert method_config.build("robot").backbone.offline.precision == "auto"
    with pytest.raises(method_config.ConfigError, match="precision"):
        method_config.build("paper", sets={"backbone.offline.precision": "fp16"})


def test_backbone_built_alone_takes_the_precision_of_its_conf():
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone

    assert OfflineGeometryBackbone(OfflineConfig(precision="bf16")).encoder.precision == "bf16"
    assert OfflineGeometryBackbone(OfflineConfig()).encoder.precision == "fp32"


def test_bf16_on_a_cpu_without_it_warns_once_and_still_runs(monkeypatch, caplog):
    import logging

    from cerpe.backbones import xfeat_net
    from cerpe.backbones.xfeat import XFeatEncoder

    monkeypatch.setattr(xfeat_net, "native_bf16", lambda cpuinfo="/proc/cpuinfo": False)
    with caplog.at_level(logging.INFO):
        enc = XFeatEncoder(precision="bf16")
        assert XFeatEncoder(precision="auto").precision == "fp32"  # auto never picks an emulated bf16
    assert enc.precision == "bf16"
    warnings = [r for r in caplog.records if "without native bfloat16" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].levelno == logging.WARNING
    assert any(r.getMessage() == "XFeat precision auto: fp32 on this CPU" for r in caplog.records)
