"""A method's code fingerprint follows a rule: the cerpe modules its entry points import, transitively,
and the data files they name. Edits outside keep cached runs; edits inside invalidate them."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from cerpe.runfolder.provenance import PACKAGE_ROOT, code_hash, code_modules


@pytest.fixture()
def pkg(tmp_path: Path) -> Path:
    """A copy of the cerpe package to edit."""
    return Path(shutil.copytree(PACKAGE_ROOT, tmp_path / "cerpe", ignore=shutil.ignore_patterns("__pycache__")))


def _touch(path: Path, text: str = "\n# edited\n") -> None:
    path.write_text(path.read_text() + text)


def test_a_copy_hashes_the_same_and_the_cerpe_rows_share_one_hash(pkg):
    assert code_hash("cerpe", pkg) == code_hash("cerpe") == code_hash("cerpe-wo-em") == code_hash("cerpe-graph")
    assert code_hash("sift-ransac", pkg) == code_hash("sift-ransac") != code_hash("cerpe")


@pytest.mark.parametrize("outside", ["pipeline/export.py", "plotting.py", "pipeline/evaluate.py", "pipeline/paper.py",
                                     "online/zenoh_link.py", "fit/thresholds.py", "cli.py"])
def test_editing_a_module_no_method_imports_keeps_every_hash(pkg, outside):
    before = {m: code_hash(m, pkg) for m in ("cerpe", "sift-ransac")}
    _touch(pkg / outside)
    assert {m: code_hash(m, pkg) for m in before} == before


def test_editing_a_module_of_one_method_changes_its_hash_only(pkg):
    cerpe, sift = code_hash("cerpe", pkg), code_hash("sift-ransac", pkg)
    _touch(pkg / "algorithm" / "anchors.py")
    assert code_hash("cerpe", pkg) != cerpe and code_hash("sift-ransac", pkg) == sift
    cerpe = code_hash("cerpe", pkg)
    _touch(pkg / "baselines" / "sift.py")
    assert code_hash("sift-ransac", pkg) != sift and code_hash("cerpe", pkg) == cerpe
    _touch(pkg / "runfolder" / "write.py")  # the run writer: every method
    assert code_hash("cerpe", pkg) != cerpe and code_hash("sift-ransac", pkg) != sift


def test_a_data_file_counts_for_the_methods_whose_modules_name_it(pkg):
    cerpe, sift = code_hash("cerpe", pkg), code_hash("sift-ransac", pkg)
    _touch(pkg / "data" / "xfeat_salad_thresholds.json", " ")
    assert code_hash("cerpe", pkg) != cerpe and code_hash("sift-ransac", pkg) == sift


def test_the_closure_follows_deferred_imports_and_module_names(pkg):
    mods = code_modules("cerpe", pkg)
    assert "cerpe.datasets.synthetic" in mods  # the adapters' registry names it as a string
    assert "cerpe.backbones.offline.backbone" in mods  # built inside build_plugins
    assert "cerpe.algorithm" in mods and "cerpe" in mods  # packages run before their modules
    (pkg / "algorithm" / "newmod.py").write_text('"""new"""\n')
    before = code_hash("cerpe", pkg)
    assert "cerpe.algorithm.newmod" not in code_modules("cerpe", pkg)
    _touch(pkg / "algorithm" / "newmod.py")
    assert code_hash("cerpe", pkg) == before  # nobody imports it yet
    _touch(pkg / "algorithm" / "gating.py", "\n\ndef _later():\n    from . import newmod  # noqa: F401\n")
    assert "cerpe.algorithm.newmod" in code_modules("cerpe", pkg)
