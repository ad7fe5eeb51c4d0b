"""`cerpe fit descriptor` and `cerpe fit projection` on small image folders: the files they write load
as the descriptor and the codecs read them; bad arguments are one line and exit code 2.
(`cerpe fit thresholds`: tests/test_fit_calibrate.py.)"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cerpe.cli import main


def _textured_images(folder: Path, n: int, seed: int = 0) -> str:
    """``n`` 160x120 PNGs of random 4-pixel blocks (textured enough for XFeat); returns their glob."""
    import cv2

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        blocks = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / f"{k:04d}.png"), cv2.resize(blocks, (160, 120), interpolation=cv2.INTER_NEAREST))
    return str(folder / "*.png")


def _fit(capsys, *argv) -> tuple[int, str, str]:
    rc = main(["fit", *map(str, argv)])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err


def test_fit_descriptor_centres_and_mean(tmp_path, capsys):
    images = _textured_images(tmp_path / "img", 6)
    rc, out, _ = _fit(capsys, "descriptor", "--images", images, "--clusters", 8, "--max-keypoints", 64,
                      "--out", tmp_path / "centres.npz", "--source-note", "test")
    assert rc == 0 and "6 images -> 8 centres" in out
    with np.load(tmp_path / "centres.npz") as z:
        C = z["centres"]
        assert C.shape == (8, 64) and z["mean"].shape == (64,)
        np.testing.assert_allclose(np.linalg.norm(C, axis=1), 1.0, rtol=1e-5)
        assert str(z["source"]) == f"{images} test" and int(z["n_images"]) == 6 and int(z["num_clusters"]) == 8
    rc, out, _ = _fit(capsys, "descriptor", "--descriptor-mean", "--images", images, "--out", tmp_path / "mean.npz")
    assert rc == 0 and "6 images -> mean descriptor" in out
    from cerpe.backbones.config import DescriptorConfig
    from cerpe.backbones.descriptor import XFeatSaladDescriptor

    desc = XFeatSaladDescriptor(DescriptorConfig(mean=str(tmp_path / "mean.npz")))  # the descriptor reads it back
    with np.load(tmp_path / "mean.npz") as z:
        assert z["mean"].shape == (desc.dim,) and np.isfinite(z["mean"]).all()


@pytest.mark.parametrize("args, match", [
    (["descriptor", "--synth", "indoor-team:0"], "seed 0 is used by an evaluation suite"),
    (["descriptor", "--synth", "indoor-team"], "expected WORLD:SEED"),
    (["descriptor", "--images", "x", "--every", "0"], "--every: 0: must be >= 1"),
    (["descriptor"], "one of the arguments --manifest --images --synth is required"),
    (["descriptor", "--images", "x", "--bogus"], "unrecognized arguments: --bogus"),
    (["projection", "--images", "x", "--descriptor", "salad-dinov2"], "needs --checkpoint"),
    (["thresholds", "--memory-from", "some"], "invalid choice"),
    (["nothing"], "invalid choice: 'nothing'"),
    ([], "choose what to fit"),
])
def test_fit_bad_arguments_are_one_line(capsys, args, match):
    with pytest.raises(SystemExit) as exc:  # argparse's errors leave through exit(2)
        rc = main(["fit", *args])
        raise SystemExit(rc)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and match in err and len(err.strip().splitlines()) == 1, err


def test_fit_descriptor_without_images_is_one_error(tmp_path, capsys):
    rc, _, err = _fit(capsys, "descriptor", "--images", tmp_path / "none" / "*.png", "--out", tmp_path / "c.npz")
    assert rc == 2 and "no images found" in err and not (tmp_path / "c.npz").exists()


def test_fit_projection_writes_a_file_the_codecs_load(tmp_path, capsys):
    from cerpe.compress import DescriptorCodec, load_projection

    rc, _, err = _fit(capsys, "projection", "--images", _textured_images(tmp_path / "few", 3), "--out",
                      tmp_path / "p.npz")
    assert rc == 2 and "3 images; the product quantiser needs at least 256" in err
    images = _textured_images(tmp_path / "img", 260, seed=1)
    rc, out, _ = _fit(capsys, "projection", "--images", images, "--k", 8, "--random-dims", 8, "--pq-m", 4,
                      "--out", tmp_path / "p.npz")
    assert rc == 0 and "260 descriptors of 8192 -> 8 principal" in out
    proj = load_projection(tmp_path / "p.npz")
    assert proj.components.shape == (8, 8192) and proj.random_dims == 8
    assert proj.meta["n_images"] == 260 and proj.meta["source"] == images
    codec = DescriptorCodec("pca-pq", proj)
    assert codec.code_bytes == 4 and codec.dims == 16
