"""XFeat encoder (weights, cache, errors) and the SALAD-style descriptor (size, invariances, gate safety)."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cerpe.protocols import DescriptorEncoder, View
from test_backbone_offline import K, Room, pose


@pytest.fixture(scope="module")
def room() -> Room:
    return Room(1)


@pytest.fixture(scope="module")
def encoder():
    from cerpe.backbones.xfeat import XFeatEncoder

    return XFeatEncoder()


@pytest.fixture(scope="module")
def descriptor(encoder, room, tmp_path_factory):
    """Descriptor with centres fitted on this test's own renders (independent of the shipped file)."""
    from cerpe.backbones.config import DescriptorConfig
    from cerpe.backbones.descriptor import XFeatSaladDescriptor, fit_centres

    maps = [encoder.encode_image(room.render(pose((0.5 * i, 0, 0.3 * i), (0, 25 * i, 0)))[0]).descriptors.T
            for i in range(4)]
    path = tmp_path_factory.mktemp("centres") / "c.npz"
    np.savez(path, **fit_centres(maps, num_clusters=16, seed=0))
    return XFeatSaladDescriptor(DescriptorConfig(centres=str(path), mean="none"), encoder=encoder,
                                thresholds={"tau": 0.5, "tau_m": 0.9, "tau_k": 0.2})


def test_features_shapes_and_cache(encoder, room):
    img = room.render(pose())[0]
    n0 = encoder.n_encoded
    f = encoder.encode(View(("x", 0), img, K))
    assert f.keypoints.shape[1] == 2 and f.descriptors.shape == (f.n, 64) and f.n > 200
    assert np.allclose(np.linalg.norm(f.descriptors, axis=1), 1, atol=1e-4)
    assert np.all(np.diff(f.scores) <= 1e-7)
    assert f.dense.shape == (64, 240 // 32 * 32 // 8, 320 // 8)
    assert (f.keypoints[:, 0] < 320).all() and (f.keypoints[:, 1] < 240).all()
    assert encoder.encode(View(("x", 0), img, K)) is f and encoder.n_encoded == n0 + 1
    # same key, other pixels (a JPEG-decoded copy): encoded anew, never a stale cache hit
    g = encoder.encode(View(("x", 0), np.ascontiguousarray(img[:, ::-1]), K))
    assert g is not f and encoder.n_encoded == n0 + 2


def test_features_keep_the_grey_std_the_descriptor_measured(descriptor, encoder, room):
    """The descriptor measures the grey level's spread before encoding and hands it over: the
    features keep the value the encoder computes itself."""
    from cerpe.backbones.xfeat import grey_std

    img = room.render(pose((0.1, 0, 0.2), (0, 15, 0)))[0]
    descriptor.describe(View(("std", 0), img, K))
    assert encoder.encode(View(("std", 0), img, K)).grey_std == grey_std(img) > 0
    assert encoder.encode_image(img).grey_std == grey_std(img)


def test_truncated_or_missing_weights(tmp_path):
    from cerpe.backbones.xfeat import XFeatEncoder, XFeatError, default_weights_path

    bad = tmp_path / "xfeat.pt"
    bad.write_bytes(default_weights_path().read_bytes()[:5000])
    with pytest.raises(XFeatError, match="xfeat.pt"):
        XFeatEncoder(weights=bad)
    with pytest.raises(XFeatError, match="not found"):
        XFeatEncoder(weights=tmp_path / "none.pt")


def test_descriptor_protocol_size_and_unit_norm(descriptor, room):
    from cerpe.messages import DescriptorMessage, decode

    assert isinstance(descriptor, DescriptorEncoder)
    d = descriptor.describe(View(("d", 0), room.render(pose())[0], K))
    assert d.shape == (descriptor.dim,) == (16 * 64 + 32 * 16 * 8,) and d.dtype == np.float32
    assert abs(np.linalg.norm(d) - 1) < 1e-5
    wb = descriptor.wire_bytes()
    for dt in ("fp32", "fp16", "int8"):
        frame = DescriptorMessage(0, 0, d, dt).encode()
        assert len(frame) == wb[dt]
        assert float(decode(frame).descriptor @ d) > 0.999
    assert set(descriptor.last_timings_s) == {"encode", "descriptor"}


def test_descriptor_ranks_overlap(descriptor, room):
    base = descriptor.describe(View(("o", 0), room.render(pose((0, 0, 0), (0, 0, 0)))[0], K))
    near = descriptor.describe(View(("o", 1), room.render(pose((0.2, 0, 0.2), (0, 4, 0)))[0], K))
    away = descriptor.describe(View(("o", 2), room.render(pose((0, 0, 0), (0, 180, 0)))[0], K))
    other = descriptor.describe(View(("o", 3), Room(9).render(pose((0, 0, 0), (0, 60, 0)))[0], K))
    assert base @ near > base @ away
    assert base @ near > base @ other


@pytest.mark.parametrize("value", [0, 255])
def test_blank_images_cannot_open_gate(descriptor, room, value):
    tau = descriptor.thresholds["tau"]
    a = descriptor.describe(View(("blank", value), np.full((240, 320, 3), value, np.uint8), K))
    b = descriptor.describe(View(("blank2", value), np.full((240, 320, 3), value, np.uint8), K))
    good = descriptor.describe(View(("g", 0), room.render(pose())[0], K))
    assert abs(np.linalg.norm(a) - 1) < 1e-5 and np.all(np.isfinite(a))
    assert a @ b < tau and a @ good < tau


@pytest.mark.parametrize("value", [0, 255, 128, 37])
def test_flags_mark_black_white_and_grey_frames_low_texture(descriptor, room, value):
    """``flags(view)`` is a function of the pixels: the same answer before or after ``describe``,
    under any key; a textured frame is not flagged."""
    blank = np.full((240, 320, 3), value, np.uint8)
    textured = room.render(pose((0.1, 0, 0.2), (0, 3, 0)))[0]
    assert descriptor.flags(View(("flag-first", value), blank, K)) == frozenset({"low-texture"})
    descriptor.describe(View(("described", value), blank, K))
    assert descriptor.flags(View(("described", value), blank, K)) == frozenset({"low-texture"})
    assert descriptor.flags(View(("flag-first", value), textured, K)) == frozenset()
    descriptor.describe(View(("described", value), textured, K))
    assert descriptor.flags(View(("described", value), textured, K)) == frozenset()
    # grey noise below the texture threshold (sensor noise on a blank wall) is blank too
    noisy = np.clip(blank.astype(int) + np.random.default_rng(value).integers(-1, 2, blank.shape), 0, 255)
    assert descriptor.flags(View(("noisy", value), noisy.astype(np.uint8), K)) == frozenset({"low-texture"})


def test_flags_do_not_change_the_stage_timings(descriptor, room):
    descriptor.describe(View(("t", 0), room.render(pose((0.3, 0, 0), (0, 5, 0)))[0], K))
    before = dict(descriptor.last_timings_s)
    descriptor.flags(View(("t", 1), np.zeros((240, 320, 3), np.uint8), K))
    assert descriptor.last_timings_s == before


def test_descriptor_rejects_malformed_images(descriptor):
    from cerpe.backbones.xfeat import ImageInputError

    for img, msg in ((np.zeros((20, 20, 3), np.uint8), "smaller"), (np.zeros((64, 64, 4), np.uint8), "HxWx3"),
                     (np.zeros((64, 64), np.uint8), "HxWx3"), (np.zeros((64, 64, 3), np.float64), "uint8")):
        with pytest.raises(ImageInputError, match=msg):
            descriptor.describe(View(("bad", msg), img, K))


def test_centres_file_errors(tmp_path):
    from cerpe.backbones.descriptor import DescriptorError, load_centres

    with pytest.raises(DescriptorError, match="not found"):
        load_centres(tmp_path / "missing.npz")
    (tmp_path / "trunc.npz").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(DescriptorError, match="trunc.npz"):
        load_centres(tmp_path / "trunc.npz")
    np.savez(tmp_path / "nomean.npz", centres=np.ones((4, 64)))
    with pytest.raises(DescriptorError, match="'mean'"):
        load_centres(tmp_path / "nomean.npz")
    np.savez(tmp_path / "nan.npz", centres=np.full((4, 64), np.nan), mean=np.zeros(64))
    with pytest.raises(DescriptorError, match="finite"):
        load_centres(tmp_path / "nan.npz")


def test_descriptor_mean_file_errors_name_file_and_field(tmp_path, descriptor, encoder):
    """A mean of another size (other centres), a truncated or missing file, NaNs: errors naming the file
    and the field, raised when the descriptor is built, never at the first describe."""
    from cerpe.backbones.descriptor import DescriptorError, XFeatSaladDescriptor, load_descriptor_mean

    with pytest.raises(DescriptorError, match="not found.*mean: none"):
        load_descriptor_mean(tmp_path / "missing.npz", 8)
    (tmp_path / "trunc.npz").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(DescriptorError, match="trunc.npz"):
        load_descriptor_mean(tmp_path / "trunc.npz", 8)
    np.savez(tmp_path / "nomean.npz", centres=np.ones(8))
    with pytest.raises(DescriptorError, match="nomean.npz lacks field 'mean'"):
        load_descriptor_mean(tmp_path / "nomean.npz", 8)
    np.savez(tmp_path / "nan.npz", mean=np.full(8, np.nan))
    with pytest.raises(DescriptorError, match="nan.npz.*'mean'.*non-finite"):
        load_descriptor_mean(tmp_path / "nan.npz", 8)
    # the shipped mean (8192 values) with this fixture's 16 centres (5120): refused by name
    with pytest.raises(DescriptorError, match="xfeat_salad_mean.npz.*5120"):
        XFeatSaladDescriptor(dataclasses.replace(descriptor.conf, mean="shipped"), encoder=encoder)


def test_centring_subtracts_the_mean_and_renormalises(tmp_path, descriptor, encoder, room):
    """With a mean file, describe() is the unit vector of (uncentred descriptor - mean): the cosine of two
    views is that of their deviations from the mean; the shipped file fits the shipped centres."""
    from cerpe.backbones.descriptor import XFeatSaladDescriptor

    imgs = [room.render(pose((0.2 * i, 0, 0.1 * i), (0, 20 * i, 0)))[0] for i in range(3)]
    raw = [descriptor.describe(View(("m", i), im, K)) for i, im in enumerate(imgs)]
    mu = np.mean(raw, axis=0).astype(np.float32)
    np.savez(tmp_path / "mu.npz", mean=mu)
    cen = XFeatSaladDescriptor(dataclasses.replace(descriptor.conf, mean=str(tmp_path / "mu.npz")), encoder=encoder)
    got = [cen.describe(View(("m", i), im, K)) for i, im in enumerate(imgs)]
    for r, g in zip(raw, got):
        assert abs(np.linalg.norm(g) - 1) < 1e-5
        assert np.allclose(g, (r - mu) / np.linalg.norm(r - mu), atol=1e-5)
    # deviations from the mean of three views point apart: their cosines drop below the raw ones
    assert got[0] @ got[1] < raw[0] @ raw[1] and got[0] @ got[2] < raw[0] @ raw[2]
    shipped = XFeatSaladDescriptor()
    assert shipped.descriptor_mean is not None and shipped.descriptor_mean.shape == (shipped.dim,)


def test_fit_centres_recovers_clusters():
    from cerpe.backbones.descriptor import fit_centres

    rng = np.random.default_rng(0)
    true = rng.standard_normal((5, 64))
    true /= np.linalg.norm(true, axis=1, keepdims=True)
    pts = np.repeat(true, 200, axis=0) + 0.05 * rng.standard_normal((1000, 64))
    out = fit_centres([pts.T.reshape(64, 10, 100)], num_clusters=5, seed=1)
    best = np.max(out["centres"] @ true.T, axis=0)
    assert np.all(best > 0.99)


def test_too_few_keypoints_is_low_texture(descriptor, room):
    """An image with fewer keypoints than clusters gets the gate-safe placeholder and the flag."""
    img = np.full((240, 320, 3), 128, np.uint8)
    img[100:120, 150:170] = 255  # a textured patch: grey std passes, a handful of keypoints
    d = descriptor.describe(View(("few", 0), img, K))
    good = descriptor.describe(View(("g", 1), room.render(pose())[0], K))
    assert descriptor.flags(View(("few", 0), img, K)) == {"low-texture"}
    assert abs(np.linalg.norm(d) - 1) < 1e-5 and d @ good < descriptor.thresholds["tau"]


def test_residual_descriptor_is_sensitive_to_content(descriptor, room):
    """Changing the image content changes the descriptor (guards against a constant output)."""
    a = descriptor.describe(View(("c", 0), room.render(pose())[0], K))
    b = descriptor.describe(View(("c", 1), Room(5).render(pose((0.3, 0, 0), (0, 90, 0)))[0], K))
    assert a @ b < 0.99


def test_nms_gives_kornias_keypoints():
    """The OpenCV NMS returns exactly kornia XFeat's strict 5x5 peaks, in the same order
    (a plateau has none; nothing within 2 px of the border)."""
    import torch
    from kornia.feature.xfeat import XFeat

    from cerpe.backbones.xfeat import _nms

    g = torch.Generator().manual_seed(3)
    x = torch.rand(1, 1, 120, 160, generator=g) ** 6
    x[0, 0, 40:48, 40:48] = 0.5
    x[0, 0, 0, 80] = x[0, 0, 60, 1] = 0.99
    want = XFeat._nms(x, threshold=0.05, kernel_size=5)
    got = _nms(x, 0.05, 5)
    assert want.shape[1] > 100
    assert torch.equal(got, want)


@pytest.mark.parametrize("hw", [(480, 640), (64, 96), (33, 70), (250, 333)])
def test_resize_to_multiples_of_32_is_kornias(encoder, hw):
    """Sides already multiples of 32 skip XFeat's resize, which there is the identity; others
    are resized by it: the same tensor and ratios either way."""
    import torch

    from cerpe.backbones.xfeat import _resize_to_32

    x = torch.rand(1, 3, *hw, generator=torch.Generator().manual_seed(1))
    want, got = encoder.model._preprocess_tensor(x), _resize_to_32(encoder.model, x)
    assert torch.equal(got[0], want[0]) and got[1:] == want[1:]


def test_grey_network_input_is_the_channel_mean_torch_takes(encoder, room):
    """A 640x480 image reaches the network as the grey image computed in numpy: for every one of the
    2^24 colours the bits of torch's channel mean, so the network's outputs are those of the
    three-channel input, bit for bit; other sizes keep XFeat's resize (three channels)."""
    import torch

    from cerpe.backbones.xfeat import _network_input

    v = np.arange(256, dtype=np.uint8)
    every = np.stack(np.meshgrid(v, v, v, indexing="ij"), -1).reshape(4096, 4096, 3)
    grey, rh, rw = _network_input(encoder.model, every)
    rgb = torch.from_numpy(every).permute(2, 0, 1)[None].float() / 255.0
    assert grey.shape == (1, 1, 4096, 4096) and (rh, rw) == (1.0, 1.0)
    assert torch.equal(grey, rgb.contiguous(memory_format=torch.channels_last).mean(dim=1, keepdim=True))
    import cv2

    img = cv2.resize(room.render(pose((0.2, 0, 0.1), (0, 10, 0)))[0], (640, 480))  # the room renders 320x240
    x3 = (torch.from_numpy(img).permute(2, 0, 1)[None].float() / 255.0).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        for a, b in zip(encoder.net(_network_input(encoder.model, img)[0]), encoder.net(x3)):
            assert torch.equal(a, b)
    x, rh, rw = _network_input(encoder.model, np.zeros((250, 333, 3), np.uint8))
    assert x.shape == (1, 3, 224, 320) and rh != 1.0 and rw != 1.0


def test_fast_cpu_network_is_the_same_function(encoder, room):
    """Batch norms folded into the convolutions, channels-last layout: the same outputs up to
    float rounding, so the same keypoints, descriptors and dense map."""
    import torch

    from cerpe.backbones.xfeat import XFeatEncoder, fold_batchnorm

    net = encoder.model.net
    folded = fold_batchnorm(net)
    n_bn = sum(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    assert n_bn > 10 and not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    x = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        for a, b in zip(net(x), folded(x)):
            assert a.shape == b.shape and float((a - b).abs().max()) < 1e-4
    assert encoder.net is not net
    img = room.render(pose((0.2, 0, 0.1), (0, 10, 0)))[0]
    fast = encoder.encode_image(img)
    plain = XFeatEncoder()
    plain.net = plain.model.net  # the network as kornia builds it (batch norms, its own layout)
    slow = plain.encode_image(img)
    assert fast.n == slow.n and fast.dense.flags["C_CONTIGUOUS"]
    assert np.abs(fast.dense - slow.dense).max() < 1e-3
    # near-equal scores may swap places in the ranking: compare each keypoint with its nearest
    d = np.linalg.norm(fast.keypoints[:, None] - slow.keypoints[None], axis=2)
    nn = d.argmin(1)
    assert np.mean(d.min(1) < 0.05) > 0.99
    assert np.median(np.sum(fast.descriptors * slow.descriptors[nn], axis=1)) > 0.9999


def test_keep_freed_memory_on_glibc():
    """The encoder asks glibc to keep freed blocks (set once per process); elsewhere it says no.
    How many page faults that saves depends on the heap's history, so ``cerpe bench`` shows
    the effect, not a test."""
    import platform
    import sys

    from cerpe.backbones import xfeat

    glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    xfeat.XFeatEncoder()
    assert xfeat._HEAP_KEPT is glibc  # set by the encoder
    assert xfeat.keep_freed_memory() is glibc and xfeat.keep_freed_memory() is glibc
    assert xfeat._HEAP_KEPT is glibc


def test_shipped_data_is_found_beside_a_folder_named_cerpe(tmp_path):
    # a run folder called "cerpe" in the working directory (`cerpe run --out cerpe`) makes `cerpe` a namespace
    # package under the editable install; the shipped centres and projection must still be found
    (tmp_path / "cerpe").mkdir()
    code = ("from cerpe.backbones.descriptor import CENTRES_FILE, data_path, load_centres\n"
            "from cerpe.compress import default_projection_path\n"
            "assert data_path(CENTRES_FILE).is_file() and default_projection_path().is_file()\n"
            "load_centres()\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
