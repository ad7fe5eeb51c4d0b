"""Compressed descriptor messages (cerpe.compress) and image reply codecs: round trips, sizes, bad input,
and the gate on decoded descriptors against the same quantised vectors computed directly."""
from __future__ import annotations

import dataclasses
import struct
import zlib

import numpy as np
import pytest

from cerpe.algorithm import AlgorithmConfig, Team
from cerpe.reasons import known_degradation as known
from cerpe.compress import CompressError, DescriptorCodec, fit_projection, load_projection, save_projection
from cerpe.memory import cosine
from cerpe.messages import (HEADER_BYTES, DescriptorMessage, ImageReply, MessageError, PoseMessage, decode)
from cerpe.protocols import FrameContext
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world


def _projection(dim=96, n=300, k=16, random_dims=32, pq_m=8, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, 12)) @ rng.standard_normal((12, dim)) + 0.1 * rng.standard_normal((n, dim))
    X /= np.linalg.norm(X, axis=1, keepdims=True)
    return fit_projection(X.astype(np.float32), k=k, random_dims=random_dims, pq_m=pq_m, seed=seed), X


@pytest.fixture(scope="module")
def proj_file(tmp_path_factory):
    proj, _ = _projection()
    path = tmp_path_factory.mktemp("proj") / "p.npz"
    save_projection(proj, path, source="random test data")
    return path


@pytest.mark.parametrize("name", ["pca-int8", "pca-pq"])
def test_round_trip_and_sizes(proj_file, name):
    codec = DescriptorCodec(name, load_projection(proj_file))
    d = _projection()[1][5].astype(np.float32)  # a descriptor of the fitted distribution
    msg = codec.message(3, 17, d)
    frame = msg.encode()
    assert len(frame) == codec.wire_bytes() == HEADER_BYTES + 9 + codec.code_bytes
    assert codec.code_bytes == (4 + 16 + 32 if name == "pca-int8" else 8)
    back = decode(frame)
    assert (back.sender, back.step, back.dtype, back.codebook) == (3, 17, name, codec.codebook)
    np.testing.assert_array_equal(back.descriptor, msg.descriptor)
    v, fault = codec.decode(back)
    assert fault == "" and v.shape == (codec.dims,)
    np.testing.assert_array_equal(v, codec.wire(d))
    y = codec.projection.project(d)
    assert cosine(v, y) > (0.999 if name == "pca-int8" else 0.8)  # quantisation keeps the direction
    # the blank frame: the empty code, decoded to zeros
    z = codec.message(0, 1, np.zeros(96, np.float32))
    assert z.descriptor.size == 0 and not np.any(codec.decode(decode(z.encode()))[0])


def test_saved_file_keeps_its_codebook_id_and_rejects_corruption(proj_file, tmp_path):
    p = load_projection(proj_file)
    assert load_projection(proj_file).codebook == p.codebook
    other, _ = _projection(seed=5)
    assert other.codebook != p.codebook
    bad = tmp_path / "bad.npz"
    bad.write_bytes(proj_file.read_bytes()[:200])
    with pytest.raises(CompressError, match="bad.npz"):
        load_projection(bad)
    with pytest.raises(CompressError, match="not found"):
        load_projection(tmp_path / "none.npz")


def test_projection_keeps_cosines_in_and_out_of_the_fitted_subspace():
    proj, X = _projection(dim=256, n=400, k=12, random_dims=0, pq_m=4)
    Y = proj.project(X[:50].astype(np.float32))
    np.testing.assert_allclose(Y @ Y.T, X[:50] @ X[:50].T, atol=0.03)  # the data lie in 12 directions + noise
    assert np.allclose(proj.components @ proj.components.T, np.eye(12), atol=1e-5)
    # descriptors outside the fitted subspace: the random directions estimate what the principal ones miss
    Z = np.random.default_rng(9).standard_normal((40, 256)).astype(np.float32)
    Z[20:] = Z[:20] + 0.8 * np.random.default_rng(10).standard_normal((20, 256))  # pairs of similar vectors
    Z /= np.linalg.norm(Z, axis=1, keepdims=True)
    true = np.sum(Z[:20] * Z[20:], axis=1)
    only_pca = proj.project(Z)
    with_rand = _projection(dim=256, n=400, k=12, random_dims=512, pq_m=4)[0].project(Z)
    err_pca = np.abs(np.sum(only_pca[:20] * only_pca[20:], axis=1) - true).mean()
    err_rand = np.abs(np.sum(with_rand[:20] * with_rand[20:], axis=1) - true).mean()
    assert err_rand < 0.05 < err_pca


@pytest.mark.parametrize("tamper, fault", [
    (lambda m, c: dataclasses.replace(m, codebook=(m.codebook + 1) % 2**32), "codebook-mismatch"),
    (lambda m, c: dataclasses.replace(m, descriptor=m.descriptor[:-1]), "bad-code"),
    (lambda m, c: dataclasses.replace(m, descriptor=np.r_[np.frombuffer(struct.pack("<f", -1.0), np.uint8),
                                                          m.descriptor[4:]].astype(np.uint8)), "bad-code"),
    (lambda m, c: DescriptorMessage(m.sender, m.step, np.ones(c.projection.dim), "fp16"), "codec-mismatch"),
])
def test_bad_codes_decode_to_a_fault_never_an_exception(proj_file, tamper, fault):
    codec = DescriptorCodec("pca-int8", load_projection(proj_file))
    msg = codec.message(1, 2, np.random.default_rng(0).standard_normal(96))
    v, got = codec.decode(decode(tamper(msg, codec).encode()))
    assert v is None and got == fault and known(f"descriptor:{fault}")


def test_coded_frame_with_wrong_length_is_garbled():
    frame = DescriptorMessage(0, 1, np.arange(10, dtype=np.uint8), "pca-pq", 7).encode()
    body = frame[:-4][:-1]  # one code byte less, checksum recomputed: the declared size no longer matches
    with pytest.raises(MessageError, match="code size"):
        decode(body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF))


# ------------------------------------------------------------------ image replies
def _image():
    rng = np.random.default_rng(0)
    img = (np.add.outer(np.arange(96), np.arange(128))[:, :, None] * [1, 2, 3] % 256).astype(np.uint8)
    return np.ascontiguousarray(np.clip(img + rng.integers(0, 8, img.shape), 0, 255).astype(np.uint8))


@pytest.mark.parametrize("codec, quality, scale", [("jpeg", 90, 1.0), ("jpeg", 60, 0.5), ("webp", 70, 0.75),
                                                   ("jpeg-grey", 75, 1.0), ("webp-grey", 60, 0.5)])
def test_reply_codecs_round_trip_with_scaled_intrinsics(codec, quality, scale):
    from cerpe.algorithm.frames import received_view

    img = _image()
    K = (100.0, 101.0, 63.5, 47.5)
    rep = ImageReply.from_image(1, 4, img, K, quality=quality, codec=codec, scale=scale)
    frame = rep.encode()
    assert len(frame) == HEADER_BYTES + 16 + 60 + 5 + len(rep.jpeg)  # intrinsics, pose, codec + length
    back = decode(frame)
    assert back.codec == codec and back.jpeg == rep.jpeg
    out = back.image_rgb()
    assert out.shape == (round(96 * scale), round(128 * scale), 3)
    np.testing.assert_allclose(back.intrinsics, [100 * scale, 101 * scale, (64 * scale) - 0.5, (48 * scale) - 0.5],
                               rtol=1e-6)
    view, fault = received_view("r1", back)
    assert fault == "" and view.image.shape == out.shape and view.intrinsics.width == out.shape[1]
    import cv2

    ref = cv2.resize(img, out.shape[1::-1], interpolation=cv2.INTER_AREA) if scale != 1 else img
    if codec.endswith("-grey"):  # three equal channels: the mean of the sender's
        assert np.array_equal(out[:, :, 0], out[:, :, 1]) and np.array_equal(out[:, :, 1], out[:, :, 2])
        ref = np.repeat(ref.mean(axis=2, keepdims=True), 3, axis=2)
    assert np.abs(out.astype(float) - ref.astype(float)).mean() < 12  # lossy, but the same picture


@pytest.mark.parametrize("codec", ["jpeg", "webp"])
def test_grey_reply_is_smaller_and_keeps_the_grey_levels(codec):
    """The grey codec carries the channel mean (what XFeat sees of a colour image) in fewer bytes."""
    rng = np.random.default_rng(3)
    img = np.clip(_image().astype(int) + rng.integers(-40, 40, (96, 128, 3)), 0, 255).astype(np.uint8)
    K = (100.0, 101.0, 63.5, 47.5)
    colour = ImageReply.from_image(1, 4, img, K, quality=75, codec=codec)
    grey = ImageReply.from_image(1, 4, img, K, quality=75, codec=f"{codec}-grey")
    assert len(grey.jpeg) < len(colour.jpeg)
    mean = img.mean(axis=2)
    err = lambda rep: np.abs(decode(rep.encode()).image_rgb().mean(axis=2) - mean).mean()
    assert err(grey) <= err(colour) + 1.0


def test_truncated_grey_jpeg_is_refused():
    from cerpe.algorithm.frames import received_view

    rep = ImageReply.from_image(1, 4, _image(), (100.0, 101.0, 63.5, 47.5), codec="jpeg-grey")
    cut = dataclasses.replace(rep, jpeg=rep.jpeg[: len(rep.jpeg) // 2])
    assert received_view("r1", decode(cut.encode())) == (None, "truncated-jpeg")
    bad = dataclasses.replace(rep, jpeg=b"\x00" + rep.jpeg[1:])
    assert received_view("r1", decode(bad.encode())) == (None, "undecodable-jpeg")


def test_unknown_reply_codec_decodes_and_is_refused():
    from cerpe.algorithm.frames import received_view

    rep = ImageReply.from_image(1, 4, _image(), (100.0, 101.0, 63.5, 47.5))
    frame = bytearray(rep.encode()[:-4])
    frame[HEADER_BYTES - 4 + 16 + 60] = 9  # the codec byte after the four intrinsics and the pose
    frame = bytes(frame) + struct.pack("<I", zlib.crc32(bytes(frame)) & 0xFFFFFFFF)
    back = decode(frame)
    assert back.codec == "unknown-9"
    assert received_view("r1", back) == (None, "unknown-reply-codec")
    with pytest.raises(MessageError, match="codec"):
        back.image_rgb()
    with pytest.raises(MessageError, match="codec"):
        back.encode()


# ------------------------------------------------------------------ the agent's gate
@pytest.fixture(scope="module")
def world():
    return make_world(2, 8, seed=1)


def _fit_on(world, tmp_path):
    desc = OverlapDescriptor(world)
    X = desc.table.reshape(-1, desc.dim)
    X = np.concatenate([X + 0.01 * np.random.default_rng(k).standard_normal(X.shape) for k in range(20)])
    proj = fit_projection(X, k=desc.dim // 2, random_dims=desc.dim - desc.dim // 2, pq_m=desc.dim // 2)
    proj = dataclasses.replace(proj, thresholds={"pca-int8": {"tau": 0.3}, "pca-pq": {"tau": 0.3}})
    return desc, save_projection(proj, tmp_path / "proj.npz")


def _inputs(world, t):
    imgs = [world.images[a][t] for a in range(2)]
    ctx = [FrameContext(r, t, world.intrinsics, world.depth_m[a][t]) for a, r in enumerate(world.robot_ids)]
    return imgs, ctx


@pytest.mark.parametrize("name", ["pca-int8", "pca-pq"])
def test_gate_on_decoded_messages_equals_direct_quantised_cosine(world, tmp_path, name):
    desc, path = _fit_on(world, tmp_path)
    cfg = AlgorithmConfig().override({"scale.min_pixels": 20, "messages.descriptor_codec": name, "messages.projection": str(path)})
    team = Team(world.robot_ids, desc, GTBackbone(world), SensorDepthDouble(), cfg)
    codec = team.agents[0].gate.codec
    assert team.agents[0].gate.tau == 0.3
    for t in range(8):
        res = team.step(*_inputs(world, t))
        for p in res.pairs:
            a, b = world.robot_ids.index(p.ego), world.robot_ids.index(p.other)
            va, vb = codec.wire(desc.table[a, t]), codec.wire(desc.table[b, t])
            assert p.gate_score == pytest.approx(cosine(va, vb), abs=1e-6)
            best = max([cosine(va, vb)] + [cosine(codec.wire(kf.descriptor), vb)
                                           for kf in team.agents[a].memory.newest_first() if kf.step < t])
            assert p.gate_open == (best >= 0.3 - 1e-9) or p.gate_open == (p.gate_score_memory >= 0.3)
        for r in res.robots:
            assert r.bytes_sent["descriptor"] == codec.wire_bytes() and r.degradations == []


def _tampered_team(world, tmp_path, tamper):
    """A team whose robot r1 broadcasts a tampered descriptor frame at step 6."""
    desc, path = _fit_on(world, tmp_path)
    cfg = AlgorithmConfig().override({"scale.min_pixels": 20, "messages.descriptor_codec": "pca-int8", "messages.projection": str(path), "messages.codec_tau": -1.0})  # the gate opens whenever a descriptor decodes
    team = Team(world.robot_ids, desc, GTBackbone(world), SensorDepthDouble(), cfg)
    agent = team.agents[1]
    honest = agent.descriptor_frame

    def frame(dtype):
        f = honest(dtype)
        if agent.cur.step != 6:
            return f
        m = tamper(decode(f), agent.gate.codec)
        return m.encode()

    agent.descriptor_frame = frame
    return team


@pytest.mark.parametrize("tamper, fault", [
    (lambda m, c: dataclasses.replace(m, codebook=(m.codebook + 1) % 2**32), "codebook-mismatch"),
    (lambda m, c: dataclasses.replace(m, descriptor=m.descriptor[:-2]), "bad-code"),
    (lambda m, c: dataclasses.replace(m, descriptor=np.r_[np.frombuffer(struct.pack("<f", np.nan), np.uint8),
                                                          m.descriptor[4:]].astype(np.uint8)), "bad-code"),
    (lambda m, c: DescriptorMessage(m.sender, m.step, np.ones(c.projection.dim), "fp16"), "codec-mismatch"),
])
def test_bad_compressed_descriptor_counts_once_and_closes_that_pair_for_that_step(world, tmp_path, tamper, fault):
    team = _tampered_team(world, tmp_path, tamper)
    results = [team.step(*_inputs(world, t)) for t in range(8)]  # overlap window from step 5
    r0 = results[6].robots[0]
    assert r0.degradations == [f"descriptor:{fault}"]
    p = next(p for p in results[6].pairs if p.ego == "r0")
    assert not p.gate_open and np.isnan(p.gate_score) and p.reason.startswith(f"descriptor-{fault}")
    clean = _tampered_team(world, tmp_path, lambda m, c: m)
    want = [clean.step(*_inputs(world, t)) for t in range(8)]
    for t in (5, 7):  # the steps before and after are untouched
        assert [(p.gate_score, p.gate_open) for p in results[t].pairs] == [(p.gate_score, p.gate_open)
                                                                            for p in want[t].pairs]
    assert want[6].pairs[0].gate_open  # the tampered step would have opened
    assert all(r.degradations == [] for res in results if res.step != 6 for r in res.robots)


def test_unknown_reply_codec_in_a_team_counts_once(world):
    team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world), SensorDepthDouble(),
                AlgorithmConfig().override({"scale.min_pixels": 20}))
    honest = team.agents[1].image_reply
    team.agents[1].image_reply = lambda req: (dataclasses.replace(honest(req), codec="jpeg")
                                              if req.step != 6 else _unknown(honest(req)))
    results = [team.step(*_inputs(world, t)) for t in range(8)]
    assert results[6].robots[0].degradations == ["msg:unknown-reply-codec"]
    p = next(p for p in results[6].pairs if p.ego == "r0")
    assert p.gate_open and p.source == "propagated" and p.reason.startswith("reply-unknown-reply-codec")


def _unknown(rep):
    """A reply that encodes with a codec id this version does not know (as a newer robot would send)."""

    class Future(ImageReply):
        def encode(self):
            f = bytearray(super().encode()[:-4])
            f[HEADER_BYTES - 4 + 16 + 60] = 42  # the codec byte after the intrinsics and the pose
            return bytes(f) + struct.pack("<I", zlib.crc32(bytes(f)) & 0xFFFFFFFF)

    return Future(rep.sender, rep.step, rep.jpeg, rep.intrinsics, rep.codec, rep.pose_step, rep.T_odom_cam)


def test_codec_config_is_checked(world, tmp_path):
    from cerpe.algorithm import AlgorithmError
    from cerpe.knobs import KnobError

    with pytest.raises(KnobError, match="messages.descriptor_codec"):
        AlgorithmConfig().override({"messages.descriptor_codec": "zip"})
    with pytest.raises(KnobError, match="messages.reply_codec"):
        AlgorithmConfig().override({"messages.reply_codec": "png"})
    with pytest.raises(KnobError, match="messages.reply_scale"):
        AlgorithmConfig().override({"messages.reply_scale": 0.0})
    _, path = _fit_on(world, tmp_path)
    proj96, _ = _projection()
    p96 = save_projection(proj96, tmp_path / "p96.npz")
    with pytest.raises(AlgorithmError, match="projection takes 96"):
        Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world), SensorDepthDouble(),
             AlgorithmConfig().override({"messages.descriptor_codec": "pca-pq", "messages.projection": str(p96)}))
    assert PoseMessage(0, 0, np.eye(4)).encode()  # the pose frame is unchanged: 70 B
    assert len(PoseMessage(0, 0, np.eye(4)).encode()) == 70


def test_shipped_projection_fits_the_offline_descriptor_in_one_kilobyte():
    from cerpe.backbones.descriptor import COLOUR_BINS, load_centres
    from cerpe.compress import make_codec

    dim = load_centres()["centres"].size + int(np.prod(COLOUR_BINS))  # the offline descriptor's size
    assert dim == 64 * 64 + 32 * 16 * 8
    for name in ("pca-int8", "pca-pq"):
        codec = make_codec(name)
        assert codec.projection.dim == dim and codec.tau is not None
        assert codec.projection.meta["n_images"] >= 256 and "s0" not in codec.projection.meta["source"]
        d = np.random.default_rng(0).standard_normal(dim).astype(np.float32)
        frame = codec.message(0, 1, d).encode()
        assert len(frame) == codec.wire_bytes() and len(frame) + len(PoseMessage(0, 1, np.eye(4)).encode()) <= 1024


def test_compressed_messages_preset_runs_a_team_with_webp_replies(world, tmp_path):
    from cerpe.method_config import PRESETS

    desc, path = _fit_on(world, tmp_path)
    cfg = AlgorithmConfig().override({**PRESETS["pays-compressed"], "policy.mode": "gate", "messages.projection": str(path),
                                      "messages.codec_tau": -1.0, "scale.min_pixels": 20})
    team = Team(world.robot_ids, desc, GTBackbone(world), SensorDepthDouble(), cfg)
    res = [team.step(*_inputs(world, t)) for t in range(6)]
    assert all(r.degradations == [] for x in res for r in x.robots)
    assert any(r.bytes_sent["reply"] > 0 for x in res for r in x.robots)
    assert team.agents[1].cur.reply_cache is None or team.agents[1].cur.reply_cache.codec == "webp"
    assert any(p.source == "direct" for x in res for p in x.pairs)
