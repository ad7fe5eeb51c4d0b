"""The backbone's configuration tree (cerpe.backbones.config): every knob described, overrides keep the
defaults they do not change, and an unknown key or a value of the wrong type is refused naming its
dotted key; the paper adapters still merge their own architecture confs strictly."""
from __future__ import annotations

import pytest

from cerpe import knobs
from cerpe.backbones.config import BackboneConfig, CrossConfig, DenseConfig, OfflineConfig, PaperModelsConfig
from cerpe.config import ConfigError
from cerpe.knobs import KnobError


def test_every_knob_has_a_description_and_the_defaults_pass_their_own_checks():
    listed = list(knobs.knobs(BackboneConfig))
    assert 25 <= len(listed) <= 35 and len({k.path for k in listed}) == len(listed)
    for k in listed:
        assert k.doc and len(k.doc.splitlines()) == 1 and k.value == k.default, k.path
    assert {p for p, _ in knobs.groups(BackboneConfig)} == {
        "offline", "offline.descriptor", "offline.dense", "offline.cross", "paper"}
    assert all(doc for _, doc in knobs.groups(BackboneConfig))
    # a tree rebuilt from its own dict is the same tree
    conf = knobs.override(BackboneConfig(), {"offline.cross.enabled": True, "paper.device": "cpu"})
    assert knobs.from_dict(BackboneConfig, knobs.as_dict(conf)) == conf


@pytest.mark.parametrize("values, key", [
    ({"offline.min_matchs": 20}, "offline.min_matchs"),
    ({"offline.dense.strid": 4}, "offline.dense.strid"),
    ({"backbon": {}}, "backbon"),
    ({"paper.weights_dri": "/tmp"}, "paper.weights_dri"),
])
def test_an_unknown_key_is_refused_naming_it_and_the_known_ones(values, key):
    with pytest.raises(KnobError, match=rf"unknown key '{key}'; known"):
        knobs.override(BackboneConfig(), values)


@pytest.mark.parametrize("values, key", [
    ({"offline.dense": 4}, "offline.dense"),
    ({"offline.keypoints": "many"}, "offline.keypoints"),
    ({"offline.keypoints": 0}, "offline.keypoints"),
    ({"offline.mask_moving": 1}, "offline.mask_moving"),
    ({"offline.cross.enabled": "sometimes"}, "offline.cross.enabled"),
    ({"offline.cross.fallback": "yes"}, "offline.cross.fallback"),
    ({"offline.cross.min_inliers_pnp": 0}, "offline.cross.min_inliers_pnp"),
    ({"offline.cross.appearance_min_ncc_highpass": 1.5}, "offline.cross.appearance_min_ncc_highpass"),
    ({"offline.cross.matcher": "sift"}, "offline.cross.matcher"),
    ({"paper.metric3d_model": "metric3d_vit_huge"}, "paper.metric3d_model"),
    ({"models": "nope"}, "models"),
])
def test_a_value_of_the_wrong_type_or_out_of_range_is_refused_naming_its_dotted_key(values, key):
    with pytest.raises(KnobError, match=rf"^{key}: "):
        knobs.override(BackboneConfig(), values)


def test_overrides_keep_the_defaults_they_do_not_change():
    conf = knobs.override(BackboneConfig(), {"offline": {"dense": {"stride": 4}}, "offline.min_inliers": 20})
    assert conf.offline.dense == DenseConfig(stride=4) and conf.offline.dense.iterations == 12
    assert conf.offline.min_inliers == 20 and conf.offline.pnp_px == OfflineConfig().pnp_px
    assert conf.offline.cross == CrossConfig() and conf.paper == PaperModelsConfig()
    assert OfflineConfig(cross={"enabled": True}).cross.enabled is True  # a mapping builds the sub-group


def test_paper_adapters_merge_strictly():
    import torch

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


def test_build_plugins_reads_the_tree():
    from cerpe.backbones.build import build_plugins

    conf = knobs.override(BackboneConfig(), {"offline.dense.stride": 4, "offline.descriptor.mean": "none"})
    pl = build_plugins(conf, depth="dataset")
    assert pl.models == "offline" and pl.backbone.conf is conf.offline and pl.depth.name == "dataset"
    assert pl.backbone.conf.dense.stride == 4 and pl.backbone.conf.dense.iterations == 12
    assert pl.descriptor.descriptor_mean is None  # mean: none
    assert pl.backbone.encoder.top_k == 1024 and pl.descriptor.encoder is pl.backbone.encoder
