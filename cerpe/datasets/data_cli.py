"""Public datasets: list them, download one, print the manifest lines that read it.

  cerpe data list
  cerpe data download NAME --to DIR [--sha256 HEX] [--url URL]

NAME is a TUM RGB-D sequence (``fr1/desk``, ``freiburg1_desk`` or
``rgbd_dataset_freiburg1_desk``) or a 7-Scenes scene (``7-scenes/chess``). The
archive comes from the dataset's official address (``--url`` for a mirror),
with a progress bar. An interrupted download resumes when the same command is
run again. The size is checked against what the server announced, and with
``--sha256`` (the publishers give none) the checksum too. The archive is unpacked
next to it (7-Scenes: the per-sequence zips too) and deleted unless
``--keep-archive``. Finally the manifest lines to use are printed. Each
dataset's licence is printed before anything is fetched: read it.
"""
from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from .download import DownloadError, extract, fetch, finished

TUM_SEQUENCES: dict[int, tuple[str, ...]] = {
    1: ("360", "desk", "desk2", "floor", "plant", "room", "rpy", "teddy", "xyz"),
    2: ("360_hemisphere", "360_kidnap", "coke", "desk", "desk_with_person", "dishes", "flowerbouquet",
        "flowerbouquet_brownbackground", "large_no_loop", "large_with_loop", "metallic_sphere", "metallic_sphere2",
        "pioneer_360", "pioneer_slam", "pioneer_slam2", "pioneer_slam3", "rpy", "xyz"),
    3: ("cabinet", "large_cabinet", "long_office_household", "nostructure_notexture_far",
        "nostructure_notexture_near_withloop", "nostructure_texture_far", "nostructure_texture_near_withloop",
        "sitting_halfsphere", "sitting_rpy", "sitting_static", "sitting_xyz", "structure_notexture_far",
        "structure_notexture_near", "structure_texture_far", "structure_texture_near", "teddy", "walking_halfsphere",
        "walking_rpy", "walking_static", "walking_xyz"),
}
SEVEN_SCENES: tuple[str, ...] = ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs")
TUM_URL = "https://cvg.cit.tum.de/rgbd/dataset/freiburg{n}/rgbd_dataset_freiburg{n}_{seq}.tgz"
SEVEN_SCENES_URL = "https://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8/{scene}.zip"
LICENCES = {
    "tum-rgbd": "TUM RGB-D benchmark (Sturm et al., IROS 2012): Creative Commons Attribution 4.0 (CC BY 4.0); "
                "cite the paper. https://cvg.cit.tum.de/data/datasets/rgbd-dataset",
    "7-scenes": "Microsoft Research 7-Scenes (Shotton et al., CVPR 2013): Microsoft Research licence, "
                "non-commercial research use only. https://www.microsoft.com/en-us/research/project/rgb-d-dataset-7-scenes/",
}


@dataclass(frozen=True)
class Entry:
    """One downloadable dataset: where it lives, its licence, how to read it."""

    name: str          # canonical name (``tum-rgbd/freiburg1_desk``, ``7-scenes/chess``)
    family: str        # key of LICENCES
    url: str
    folder: str        # the folder the archive unpacks to
    nested_zips: bool = False
    extra: dict = field(default_factory=dict)


class CatalogueError(DownloadError):
    """An unknown dataset name (the message lists the known ones)."""


def lookup(name: str) -> Entry:
    """The catalogue entry of ``name`` (see module doc for the accepted spellings)."""
    text = name.strip().lower()
    hit = (re.fullmatch(r"(?:tum(?:-rgbd)?/)?(?:rgbd_dataset_)?(?:freiburg|fr)([123])[_/](\w+)", text))
    if hit:
        n, seq = int(hit.group(1)), hit.group(2)
        if seq not in TUM_SEQUENCES[n]:
            raise CatalogueError(f"unknown TUM RGB-D sequence freiburg{n}_{seq}; known: "
                                 f"{', '.join(TUM_SEQUENCES[n])} (a sequence not listed: pass --url)")
        folder = f"rgbd_dataset_freiburg{n}_{seq}"
        return Entry(f"tum-rgbd/freiburg{n}_{seq}", "tum-rgbd", TUM_URL.format(n=n, seq=seq), folder, extra={"camera": f"fr{n}"})
    hit = re.fullmatch(r"(?:7-?scenes|seven-?scenes)/(\w+)", text)
    if hit:
        scene = hit.group(1)
        if scene not in SEVEN_SCENES:
            raise CatalogueError(f"unknown 7-Scenes scene {scene!r}; known: {', '.join(SEVEN_SCENES)}")
        return Entry(f"7-scenes/{scene}", "7-scenes", SEVEN_SCENES_URL.format(scene=scene), scene, nested_zips=True)
    raise CatalogueError(f"unknown dataset {name!r}: use a TUM RGB-D sequence (fr1/desk, freiburg2_xyz, "
                         f"rgbd_dataset_freiburg3_long_office_household) or a 7-Scenes scene (7-scenes/chess); "
                         "`cerpe data list` shows them all")


def manifest_lines(entry: Entry, folder: Path) -> str:
    """A manifest for the downloaded folder: two robots (first and second half, or two sequences)."""
    root = folder.resolve()
    slug = entry.name.replace("/", "-").replace("_", "-")
    if entry.family == "tum-rgbd":
        n = sum(1 for ln in (folder / "rgb.txt").read_text().splitlines() if ln.strip() and not ln.startswith("#")) \
            if (folder / "rgb.txt").is_file() else 0
        half = max(n // 2, 1)
        return (f"name: {slug}\nadapter: tum-rgbd\ndata_root: {root}\nmetric_depth: dataset\n"
                f"encounters:\n  - name: halves\n    sync: index\n    robots:\n"
                f"      - {{id: first, sequence: ., camera: {entry.extra['camera']}, frames: [0, {half}]}}\n"
                f"      - {{id: second, sequence: ., camera: {entry.extra['camera']}, frames: [{half}, null]}}\n")
    seqs = sorted(p.name for p in folder.glob("seq-*") if p.is_dir()) or ["seq-01", "seq-02"]
    robots = "".join(f"      - {{id: {s}, folder: {s}}}\n" for s in (seqs[:2] if len(seqs) > 1 else seqs * 2))
    return (f"name: {slug}\nadapter: frames\ndata_root: {root}\n"
            "intrinsics: {fx: 585, fy: 585, cx: 320, cy: 240}   # the usual 7-Scenes values (depth camera)\n"
            "rate_hz: 30\ndepth_units_per_m: 1000\nmetric_depth: dataset\n"
            f"encounters:\n  - name: sequences\n    sync: index\n    robots:\n{robots}")


def download(entry: Entry, to: Path, url: str | None = None, sha256: str | None = None, keep_archive: bool = False,
             retries: int = 2, progress: bool = True, out=None) -> Path:
    """Fetch, check and unpack ``entry`` under ``to``; returns the dataset folder (reused when finished)."""
    out = out if out is not None else sys.stdout
    to = Path(to)
    folder = to / entry.folder
    if finished(folder) is not None:
        print(f"{folder}: already downloaded", file=out)
        return folder
    url = url or entry.url
    archive = to / ".downloads" / url.rstrip("/").rsplit("/", 1)[-1]
    print(f"downloading {entry.name} from {url}", file=out)
    fetch(url, archive, sha256=sha256, retries=retries, progress=progress)
    try:
        folder = extract(archive, to, entry.folder, entry.nested_zips, meta={"name": entry.name, "url": url})
    except DownloadError:
        archive.unlink(missing_ok=True)  # a corrupt archive is not kept: the next run fetches it again
        raise
    if not keep_archive:
        archive.unlink(missing_ok=True)
    return folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="data_command", metavar="ACTION", required=True)
    sub.add_parser("list", help="the datasets `download` knows, with their licences")
    d = sub.add_parser("download", help="download, check and unpack a dataset; print its manifest lines")
    d.add_argument("name", metavar="NAME", help="fr1/desk, freiburg3_long_office_household, 7-scenes/chess, ...")
    d.add_argument("--to", type=Path, required=True, metavar="DIR", help="folder to put the dataset in")
    d.add_argument("--sha256", default=None, metavar="HEX", help="refuse the archive unless its SHA-256 is this")
    d.add_argument("--url", default=None, help="download from this address instead (a mirror)")
    d.add_argument("--retries", type=int, default=2, help="resume attempts after a dropped connection (default 2)")
    d.add_argument("--keep-archive", action="store_true", help="keep the archive after unpacking it")
    d.add_argument("--quiet", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    if args.data_command == "list":
        print(f"tum-rgbd ({LICENCES['tum-rgbd']}):")
        for n, seqs in TUM_SEQUENCES.items():
            print(f"  fr{n}/: " + " ".join(seqs))
        print(f"7-scenes ({LICENCES['7-scenes']}):\n  7-scenes/: " + " ".join(SEVEN_SCENES))
        return 0
    entry = lookup(args.name)
    print(f"licence: {LICENCES[entry.family]}")
    folder = download(entry, args.to, args.url, args.sha256, args.keep_archive, max(args.retries, 0), not args.quiet)
    print(f"unpacked into {folder}\n\n# manifest lines (save as datasets_manifest/{entry.name.replace('/', '-')}.yaml, "
          "then `cerpe check` it):")
    print(manifest_lines(entry, folder))
    return 0
