"""Every plug-in merges its configuration strictly (cerpe.config.merge_conf): nested dicts keep
the defaults they do not override, and an unknown key is refused with the list of known ones."""
from __future__ import annotations

import numpy as np
import pytest
from test_backbone_rgbd_align import T_GT, pair  # noqa: F401  (a fixture)

from cerpe.config import ConfigError
from cerpe.scene import CameraIntrinsics

K = CameraIntrinsics(fx=260.0, fy=260.0, cx=159.5, cy=119.5, width=320, height=240)


def test_offline_backbone_keeps_nested_defaults_and_refuses_typos():
    from cerpe.backbones.offline import OfflineGeometryBackbone
    from cerpe.backbones.rgbd_align import default_conf as dense
    from cerpe.backbones.xfeat import shared_encoder

    enc = shared_encoder()
    bb = OfflineGeometryBackbone({"dense": {"stride": 4}, "min_matches": 20}, encoder=enc)
    assert bb.conf["dense"] == {**dense, "stride": 4, "iterations": 12}  # the backbone's own dense default kept
    assert bb.conf["min_matches"] == 20 and bb.conf["ratio"] == OfflineGeometryBackbone.default_conf["ratio"]
    with pytest.raises(ConfigError, match=r"offline backbone conf: unknown option\(s\) 'min_matchs'; known: .*min_matches"):
        OfflineGeometryBackbone({"min_matchs": 20}, encoder=enc)
    with pytest.raises(ConfigError, match=r"offline backbone conf\.dense: unknown option\(s\) 'strid'; known: .*stride"):
        OfflineGeometryBackbone({"dense": {"strid": 4}}, encoder=enc)
    with pytest.raises(ConfigError, match="offline backbone conf.dense: expected a mapping"):
        OfflineGeometryBackbone({"dense": 4}, encoder=enc)


def test_xfeat_and_descriptor_refuse_typos():
    from cerpe.backbones.descriptor import XFeatSaladDescriptor
    from cerpe.backbones.xfeat import XFeatEncoder, shared_encoder

    with pytest.raises(ConfigError, match=r"xfeat conf: unknown option\(s\) 'topk'; known: .*top_k"):
        XFeatEncoder({"topk": 512})
    with pytest.raises(ConfigError, match="xfeat conf: unknown option"):
        shared_encoder({"topk": 512})
    enc = shared_encoder()
    with pytest.raises(ConfigError, match=r"descriptor conf: unknown option\(s\) 'betta'; known: .*beta"):
        XFeatSaladDescriptor({"betta": 50.0}, encoder=enc)
    d = XFeatSaladDescriptor({"thresholds": {"tau": 0.3, "tau_m": 0.9, "tau_k": 0.2}, "beta": 50.0}, encoder=enc)
    assert d.thresholds["tau"] == 0.3 and d.conf["beta"] == 50.0
    assert d.conf["dustbin_cos"] == XFeatSaladDescriptor.default_conf["dustbin_cos"]


def test_rgbd_align_keeps_defaults_and_refuses_typos(pair):  # noqa: F811
    from cerpe.backbones.rgbd_align import align_rgbd, default_conf

    img0, d0, img1, d1 = pair
    part = align_rgbd(img0, d0, img1, d1, K.K, K.K, T_GT, {"stride": 4})
    full = align_rgbd(img0, d0, img1, d1, K.K, K.K, T_GT, {**default_conf, "stride": 4})
    assert part.ok and np.array_equal(part.T_cur_ref, full.T_cur_ref) and part.iterations == full.iterations
    with pytest.raises(ConfigError, match=r"align_rgbd conf: unknown option\(s\) 'strid'; known: .*stride"):
        align_rgbd(img0, d0, img1, d1, K.K, K.K, T_GT, {"strid": 4})


def test_paper_adapters_merge_strictly():
    import torch

    from cerpe.backbones.paper_profile import check_paper_requirements
    from cerpe.backbones.salad_dinov2 import SaladDinoV2Descriptor, SaladDinoV2Model
    from cerpe.backbones.vggt import VGGTBackbone

    with pytest.raises(ConfigError, match=r"VGGT conf: unknown option\(s\) 'target_sise'; known: .*target_size"):
        VGGTBackbone({"device": "cpu", "target_sise": 112}, model=torch.nn.Identity())
    small = SaladDinoV2Model({"embed_dim": 16, "depth": 1, "num_heads": 2},
                             {"num_clusters": 4, "cluster_dim": 8, "token_dim": 8, "hidden_dim": 16})
    desc = SaladDinoV2Descriptor({"device": "cpu", "dinov2": {"depth": 1}}, model=small)
    assert desc.conf["dinov2"]["depth"] == 1 and desc.conf["dinov2"]["preset"] == "dinov2_vitb14"
    with pytest.raises(ConfigError, match=r"SALAD/DINOv2 conf\.dinov2: unknown option\(s\) 'dept'; known: .*depth"):
        SaladDinoV2Descriptor({"device": "cpu", "dinov2": {"dept": 1}}, model=small)
    with pytest.raises(ConfigError, match=r"paper profile conf: unknown option\(s\) 'weights_dri'; known: .*weights_dir"):
        check_paper_requirements({"weights_dri": "/tmp"})


def test_build_plugins_merges_presets_strictly():
    from cerpe.backbones.build import build_plugins

    pl = build_plugins("offline", {"backbone": {"dense": {"stride": 4}}, "depth": "dataset"})
    assert pl.backbone.conf["dense"]["stride"] == 4 and pl.backbone.conf["dense"]["iterations"] == 12
    assert pl.backbone.encoder.conf["top_k"] == 1024 and pl.descriptor.encoder is pl.backbone.encoder
    with pytest.raises(ConfigError, match=r"preset 'offline' conf: unknown option\(s\) 'backbon'; known: .*backbone"):
        build_plugins("offline", {"backbon": {}})
    with pytest.raises(ConfigError, match=r"offline backbone conf: unknown option\(s\) 'min_matchs'"):
        build_plugins("offline", {"backbone": {"min_matchs": 3}})
