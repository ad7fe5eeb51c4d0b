"""Wire frames (round trips, exact sizes, corruption) and the lossy in-process channel."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cerpe.geometry import random_se3
from cerpe.messages import (
    HEADER_BYTES, DescriptorMessage, ImageReply, ImageRequest, MessageError, PoseMessage, decode,
)
from cerpe.transport import Channel, TransportError

SALAD_DIM = 8448  # 64 clusters x 128 + 256 global


def _descriptor(rng: np.random.Generator, dim: int = SALAD_DIM) -> np.ndarray:
    d = rng.normal(size=dim).astype(np.float32)
    return d / np.linalg.norm(d)


def test_descriptor_message_is_the_papers_16_9_kb():
    d = _descriptor(np.random.default_rng(0))
    frame = DescriptorMessage(3, 17, d, "fp16").encode()
    assert len(frame) == HEADER_BYTES + 5 + 2 * SALAD_DIM == 16915 == DescriptorMessage.wire_bytes(SALAD_DIM, "fp16")
    assert round(len(frame) / 1000, 1) == 16.9
    for dtype, per, extra in (("fp32", 4, 0), ("int8", 1, 4)):
        n = len(DescriptorMessage(3, 17, d, dtype).encode())
        assert n == HEADER_BYTES + 5 + per * SALAD_DIM + extra == DescriptorMessage.wire_bytes(SALAD_DIM, dtype)


@pytest.mark.parametrize("dtype, tol", [("fp32", 0.0), ("fp16", 1e-3), ("int8", 1e-2)])
def test_descriptor_round_trip(dtype, tol):
    d = _descriptor(np.random.default_rng(1), 256)
    msg = decode(DescriptorMessage(65535, 2**32 - 1, d, dtype).encode())
    assert isinstance(msg, DescriptorMessage)
    assert (msg.sender, msg.step, msg.dtype) == (65535, 2**32 - 1, dtype)
    np.testing.assert_allclose(msg.descriptor, d, atol=tol * np.abs(d).max() + 1e-12)
    # the gate works on quantised values; cosine must survive quantisation
    assert float(msg.descriptor @ d / np.linalg.norm(msg.descriptor)) > 0.999


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 2**16 - 1), st.integers(0, 2**32 - 1))
def test_pose_round_trip(seed, sender, step):
    T = random_se3(np.random.default_rng(seed), 1000.0)
    frame = PoseMessage(sender, step, T).encode()
    assert len(frame) == HEADER_BYTES + 56 == 70
    msg = decode(frame)
    assert isinstance(msg, PoseMessage) and (msg.sender, msg.step) == (sender, step)
    np.testing.assert_allclose(msg.T_odom_cam, T, atol=1e-9)


def test_request_and_reply_round_trip_and_sizes():
    frame = ImageRequest(1, 5, 2).encode()
    assert len(frame) == HEADER_BYTES + 2 == 16
    assert decode(frame) == ImageRequest(1, 5, 2)
    rng = np.random.default_rng(2)
    img = (np.add.outer(np.arange(48), np.arange(64))[:, :, None] * [1, 2, 3] % 256).astype(np.uint8)
    img = np.ascontiguousarray(np.clip(img + rng.integers(0, 8, img.shape), 0, 255).astype(np.uint8))
    rep = ImageReply.from_image(2, 5, img, (50.0, 51.0, 31.5, 23.5), quality=90)
    frame = rep.encode()
    assert len(frame) == HEADER_BYTES + 16 + 60 + 5 + len(rep.jpeg)  # intrinsics, pose, codec + length, image
    back = decode(frame)
    assert isinstance(back, ImageReply) and back.jpeg == rep.jpeg
    assert back.pose_step == -1 and back.T_odom_cam is None  # no pose given: none on the wire
    assert back.intrinsics == pytest.approx((50.0, 51.0, 31.5, 23.5))
    dec = back.image_rgb()
    assert dec.shape == img.shape and np.abs(dec.astype(int) - img).mean() < 6  # JPEG, colour order kept


def _frames() -> list[bytes]:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 255, (16, 16, 3), dtype=np.uint8)
    return [DescriptorMessage(0, 1, _descriptor(rng, 64)).encode(), PoseMessage(0, 1, random_se3(rng)).encode(),
            ImageRequest(0, 1, 1).encode(), ImageReply.from_image(0, 1, img, (10, 10, 8, 8)).encode()]


@pytest.mark.parametrize("k", range(4))
def test_every_flipped_byte_and_every_truncation_raises(k):
    frame = _frames()[k]
    for pos in range(0, len(frame), max(1, len(frame) // 60)):
        bad = bytearray(frame)
        bad[pos] ^= 0x5A
        with pytest.raises(MessageError):
            decode(bytes(bad))
    for n in range(0, len(frame), max(1, len(frame) // 60)):
        with pytest.raises(MessageError):
            decode(frame[:n])
    with pytest.raises(MessageError):
        decode(frame + b"\x00")


def test_bad_messages_refuse_to_encode():
    with pytest.raises(MessageError):
        DescriptorMessage(0, 0, np.array([np.nan, 1.0])).encode()
    with pytest.raises(MessageError):
        DescriptorMessage(0, 0, np.ones(4), "bf16").encode()
    T = np.eye(4)
    T[0, 0] = np.inf
    with pytest.raises(MessageError):
        PoseMessage(0, 0, T).encode()
    with pytest.raises(MessageError):
        ImageRequest(2**16, 0, 1).encode()


# ------------------------------------------------------------------ channel
def test_lossless_channel_counts_bytes_per_sender_and_kind():
    ch = Channel(["a", "b", "c"])
    f = _frames()
    assert ch.broadcast("a", "descriptor", f[0]) == len(f[0])
    ch.send("b", "request", f[2], "a")
    ch.send("a", "reply", f[3], "b")
    got_b = ch.receive("b")
    assert [type(m).__name__ for _, m in got_b.messages] == ["DescriptorMessage", "ImageReply"]
    assert [s for s, _ in got_b.messages] == ["a", "a"]
    assert [type(m).__name__ for _, m in ch.receive("a").messages] == ["ImageRequest"]
    assert len(ch.receive("c").messages) == 1
    assert ch.receive("c").messages == []  # drained
    assert ch.bytes_sent["a"] == {"descriptor": len(f[0]), "reply": len(f[3])}  # broadcast counted once
    assert ch.total_bytes() == len(f[0]) + len(f[2]) + len(f[3])


def test_lossy_channel_counts_lost_and_garbled_and_is_seeded():
    def run(seed):
        ch = Channel(["a", "b"], p_drop=0.2, p_garble=0.2, seed=seed)
        frame = _frames()[1]
        got, degr = 0, []
        for _ in range(500):
            ch.send("a", "pose", frame, "b")
            d = ch.receive("b")
            got += len(d.messages)
            degr += d.degradations
        return got, degr, ch.counts

    got, degr, counts = run(11)
    assert counts["msg:lost"] + counts["msg:garbled"] + got == 500
    assert 60 < counts["msg:lost"] < 140 and 40 < counts["msg:garbled"] < 130
    assert degr.count("msg:lost") == counts["msg:lost"] and degr.count("msg:garbled") == counts["msg:garbled"]
    assert run(11)[0] == got  # reproducible


def test_channel_misuse():
    with pytest.raises(TransportError, match="p_drop"):
        Channel(p_drop=1.5)
    ch = Channel(["a"])
    with pytest.raises(TransportError, match="kind"):
        ch.broadcast("a", "gossip", b"xx")
    with pytest.raises(TransportError, match="unknown sending robot"):
        ch.broadcast("zz", "pose", b"xx")
    with pytest.raises(TransportError, match="unknown receiving robot"):
        ch.send("a", "pose", b"xx", "zz")
    with pytest.raises(TransportError, match="empty"):
        ch.broadcast("a", "pose", b"")


def test_reply_carries_the_senders_pose_and_another_version_is_garbled():
    rng = np.random.default_rng(5)
    img = rng.integers(0, 255, (16, 16, 3), dtype=np.uint8)
    for _ in range(20):
        X = random_se3(rng)
        step = int(rng.integers(0, 1000))
        back = decode(ImageReply.from_image(1, step + 1, img, (10, 10, 8, 8), pose_step=step, T_odom_cam=X).encode())
        assert back.pose_step == step and np.allclose(back.T_odom_cam, X, atol=1e-12)
    frame = bytearray(ImageReply.from_image(1, 2, img, (10, 10, 8, 8), pose_step=1, T_odom_cam=np.eye(4)).encode())
    frame[2] = 1  # a version-1 frame (no pose): refused by name, counted as garbled by the links
    import struct
    import zlib
    frame[-4:] = struct.pack("<I", zlib.crc32(bytes(frame[:-4])) & 0xFFFFFFFF)
    with pytest.raises(MessageError, match="version"):
        decode(bytes(frame))
