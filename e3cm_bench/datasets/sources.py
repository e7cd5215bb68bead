"""Where each benchmark's data comes from: one table, data not code (what `download` fetches).

sha256: pinned where a trustworthy hash is known; None where none is published (HPatches,
glue-factory and hloc publish none): then the hash of the first download is recorded in
the lock file beside the data (download.LOCK_FILE) and checked from then on.
A source without a URL cannot be fetched by a script (a Google Drive folder): `download`
prints its steps instead, and `download NAME --check` verifies what was placed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class Part:
    """One file of a source: where it comes from, what it is called, what it unpacks to."""

    file: str
    url: str | None = None
    sha256: str | None = None
    # bytes (rounded up): the free-disk check before downloading, the most bytes a body may
    # have (with download.SIZE_MARGIN) and its deadline; None: download.UNKNOWN_SIZE_CAP bounds it
    size: int | None = None
    extract: bool = True     # an archive to unpack (else the file is placed as it is)
    md5: str | None = None   # for sources that publish only an md5 (WxBS, EVD); the sha256 is still recorded


@dataclass(frozen=True)
class Source:
    name: str
    benchmark: str
    folder: str              # the folder under --to that holds the data (the benchmark's --root)
    parts: tuple[Part, ...]
    manual: str = ""         # the steps a script cannot do
    expected: dict = field(default_factory=dict)  # what a complete copy holds (counts)
    same_data_as: str = ""   # another source's data in another layout (either one serves)


# LoFTR's MegaDepth-1500 pair lists, in its repository.
LOFTR_SCENE_INFO = "https://raw.githubusercontent.com/zju3dv/LoFTR/master/assets/megadepth_test_1500_scene_info"
LOFTR_SCENES = ("0015_0.1_0.3", "0015_0.3_0.5", "0022_0.1_0.3", "0022_0.3_0.5", "0022_0.5_0.7")

SOURCES: dict[str, Source] = {
    s.name: s
    for s in [
        Source(
            "hpatches",
            "hpatches",
            "hpatches-sequences-release",
            (
                Part(
                    "hpatches-sequences-release.zip",
                    "https://huggingface.co/datasets/vbalnt/hpatches/resolve/main/hpatches-sequences-release.zip",
                    size=1_300_000_000,
                ),
            ),
            expected={"sequences": 116, "images": 696},
        ),
        Source(
            "megadepth-1500",
            "megadepth",
            "megadepth_test_1500",
            # each list 231-273 kB (the copies under ../shared/data)
            tuple(
                Part(f"scene_info/{scene}.npz", f"{LOFTR_SCENE_INFO}/{scene}.npz", size=300_000, extract=False)
                for scene in LOFTR_SCENES
            ),
            manual=(
                "the images are in LoFTR's test data on Google Drive (folder 1DOcOPZb3-5cWxLqn256AhwUVjBPifhuf, "
                "file megadepth_test_1500.tar): download it by hand and unpack it so that "
                "{folder}/Undistorted_SfM/0015/images/ and .../0022/images/ hold the images"
            ),
            expected={"pairs": 1500},
        ),
        Source(
            "megadepth-1500-gluefactory",
            "megadepth",
            "megadepth1500",
            # no size published or measured here: UNKNOWN_SIZE_CAP bounds it
            (Part("megadepth1500.zip", "https://cvg-data.inf.ethz.ch/megadepth/megadepth1500.zip"),),
            expected={"pairs": 1500},
            same_data_as="megadepth-1500",
        ),
        Source(
            "yfcc",
            "yfcc",
            "yfcc100m",
            (
                Part(
                    "yfcc_test_pairs_with_gt.txt",
                    "https://raw.githubusercontent.com/magicleap/SuperGluePretrainedNetwork/master/assets/yfcc_test_pairs_with_gt.txt",
                    size=1_900_000,
                    extract=False,
                ),
            ),  # 1,829,347 bytes
            manual=(
                "the test images come from OANet's raw data, whose host is down; OANet's issue #32 points to Google "
                "Drive "
                "folder 1qbnrDSXJhnXC0MiZNNqW7vezAHlkBNgo: download the four scenes' test images by hand into "
                "{folder}/<scene>/test/images/ (buckingham_palace, notre_dame_front_facade, reichstag, sacre_coeur)"
            ),
            expected={"pairs": 4000},
        ),
        Source(
            "scannet-1500",
            "yfcc",
            "scannet_test_1500",
            (),
            manual=(
                "LoFTR's test data on Google Drive (folder 1DOcOPZb3-5cWxLqn256AhwUVjBPifhuf, file "
                "scannet_test_1500.tar) holds the images and the pair list: download it by hand and unpack it into "
                "{folder}/"
            ),
            expected={"pairs": 1500},
        ),
        # WxBS and EVD: the zips and md5s that wxbs-benchmark's dataset.py names (no sha256 is
        # published). WxBS_v1.1.zip holds the category folders and a README at its top, which the
        # reference unpacks into v1.1/; EVD.zip holds one EVD/ folder (1/, 2/, h/). Neither size is
        # published: those given are the unpacked copies' under ../shared/data (WxBS 40.9 MB for 33
        # of its 34 pairs, EVD 28.6 MB), rounded up; PNG and JPEG hardly compress, so the zips are
        # about as large, and the download's margin (x1.25 + 8 MB) covers the rest.
        Source(
            "wxbs",
            "wxbs",
            "WxBS/v1.1",
            (
                Part(
                    "WxBS_v1.1.zip",
                    "http://cmp.felk.cvut.cz/wbs/datasets/WxBS_v1.1.zip",
                    size=44_000_000,
                    md5="66da037e7d20487e86db147307615870",
                ),
            ),
            expected={"pairs": 32},  # the test split, the benchmark's default; 2 validation pairs besides
        ),
        Source(
            "evd",
            "evd",
            "EVD",
            (
                Part(
                    "EVD.zip",
                    "http://cmp.felk.cvut.cz/wbs/datasets/EVD.zip",
                    size=30_000_000,
                    md5="7ce52151abdafa71a609424d09e43075",
                ),
            ),
            expected={"pairs": 15},
        ),
    ]
}


def get_source(name: str) -> Source:
    if name not in SOURCES:
        raise ValueError(f"unknown data {name!r}; choose one of {', '.join(SOURCES)}")
    return SOURCES[name]


def data_dir() -> Path:
    """Where data lives unless --root says otherwise: $E3CM_BENCH_DATA, else ./data."""
    import os

    return Path(os.environ.get("E3CM_BENCH_DATA") or "data")


def default_sources(benchmark: str) -> list[Source]:
    """Where a benchmark's default data may be, in the order the folders are looked for: its
    first source, then the same data in other layouts (never another dataset it also reads)."""
    first = next((s for s in SOURCES.values() if s.benchmark == benchmark), None)
    if first is None:
        raise ValueError(f"no data source is known for {benchmark}: pass --root (the folder holding its data)")
    return [first] + [s for s in SOURCES.values() if s.same_data_as == first.name]
