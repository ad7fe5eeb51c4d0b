"""The `paper` profile: one clear error listing every missing piece before any work starts."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cerpe.backbones import paper_profile as pp
from cerpe.backbones.config import BackboneConfig, PaperModelsConfig
from cerpe.backbones.paper_profile import build_paper, check_paper_requirements, require_paper
from cerpe.backbones.weights import PaperModelError, load_checkpoint, select_device, weight_file_problem


@pytest.fixture
def no_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(pp.WEIGHTS_ENV, raising=False)
    monkeypatch.delenv(pp.METRIC3D_REPO_ENV, raising=False)


def _save(path: Path, n: int = 10) -> Path:
    torch.save({"w": torch.zeros(n)}, path)
    return path


def test_everything_missing_is_listed_at_once(tmp_path: Path, no_env: None) -> None:
    conf = PaperModelsConfig(weights_dir=str(tmp_path), check_memory=False)
    problems = check_paper_requirements(conf)
    text = "\n".join(problems)
    assert f"{tmp_path / 'dino_salad.ckpt'} not found" in text and "backbone.paper.weights_dir" in text
    assert f"{tmp_path / 'model.pt'} not found" in text and pp.WEIGHTS_ENV in text
    assert "metric_depth_vit_small_800k.pth not found" in text
    assert "git clone https://github.com/YvanYin/Metric3D" in text
    with pytest.raises(PaperModelError) as exc:
        build_paper(conf)
    msg = str(exc.value)
    assert f"{len(problems)} problem(s)" in msg and all(p in msg for p in problems)


def test_env_dir_found_but_implausible_and_truncated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     no_env: None) -> None:
    monkeypatch.setenv(pp.WEIGHTS_ENV, str(tmp_path))
    _save(tmp_path / "dino_salad.ckpt")
    vggt = _save(tmp_path / "model.pt", 1000)
    vggt.write_bytes(vggt.read_bytes()[:-200])  # interrupted download: zip directory gone
    text = "\n".join(check_paper_requirements(PaperModelsConfig(check_memory=False), depth="sensor"))
    assert "dino_salad.ckpt: SALAD (DINOv2) checkpoint weight file has 0.0 MB" in text
    assert "model.pt: VGGT-1B weight file is truncated or corrupt" in text
    assert "Metric3D" not in text  # depth from the sensor: Metric3D not needed


def test_metric3d_clone_checked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_env: None) -> None:
    repo = tmp_path / "Metric3D"
    repo.mkdir()
    monkeypatch.setenv(pp.METRIC3D_REPO_ENV, str(repo))
    conf = PaperModelsConfig(check_memory=False)
    text = "\n".join(check_paper_requirements(conf))
    assert "has no hubconf.py" in text
    (repo / "hubconf.py").write_text("dependencies = []\n")
    text = "\n".join(check_paper_requirements(conf))
    assert "hubconf.py" not in text


def test_memory_check(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, no_env: None) -> None:
    monkeypatch.setattr(pp, "available_memory_bytes", lambda device: 2 * 2**30)
    text = "\n".join(check_paper_requirements(PaperModelsConfig(weights_dir=str(tmp_path), device="cpu")))
    assert "device cpu: CPU RAM has 2.0 GiB available" in text and "VGGT-1B" in text


def test_weight_file_checks_and_loading(tmp_path: Path) -> None:
    good = _save(tmp_path / "a.pt")
    assert weight_file_problem(good, "X", "x.checkpoint") is None
    assert torch.equal(load_checkpoint(good, "X")["w"], torch.zeros(10))
    (tmp_path / "empty.pt").write_bytes(b"")
    assert "is empty" in weight_file_problem(tmp_path / "empty.pt", "X", "x.checkpoint")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint at all")
    with pytest.raises(PaperModelError, match="junk.pth: X weight file is truncated or corrupt"):
        load_checkpoint(tmp_path / "junk.pth", "X")
    with pytest.raises(PaperModelError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt", "X")


def test_require_passes_when_complete(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_env: None) -> None:
    monkeypatch.setattr(pp, "module_available", lambda name: True)
    for name in ("dino_salad.ckpt", "model.pt", "metric_depth_vit_small_800k.pth"):
        _save(tmp_path / name)
    monkeypatch.setattr(pp, "APPROX_BYTES", {k: 1.0 for k in pp.APPROX_BYTES})
    repo = tmp_path / "Metric3D"
    repo.mkdir()
    (repo / "hubconf.py").write_text("")
    monkeypatch.setenv(pp.METRIC3D_REPO_ENV, str(repo))
    conf = PaperModelsConfig(weights_dir=str(tmp_path), check_memory=False)
    assert check_paper_requirements(conf) == []
    require_paper(conf)


def test_device_selection() -> None:
    assert select_device("cpu").type == "cpu"
    assert select_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(PaperModelError, match="CUDA is not available"):
            select_device("cuda")


def test_builder_reports_paper_problems(tmp_path: Path, no_env: None) -> None:
    from cerpe.backbones.build import build_plugins

    with pytest.raises(PaperModelError, match="the 'paper' profile cannot start"):
        build_plugins(BackboneConfig(models="paper", paper={"weights_dir": str(tmp_path), "check_memory": False}))
