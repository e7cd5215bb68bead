"""Where a peer's weights come from, the libraries' way: kornia's checkpoints in torch.hub's
cache (``$TORCH_HOME/hub/checkpoints``), transformers' models in the Hugging Face cache.
`fetch` finds a file in its cache, else downloads it there once (the library's own
download), else fails in one line naming the file and where to put it."""

from __future__ import annotations

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
        return f"kornia:{self.file_name}"

    def path(self) -> Path:
        import torch

        return Path(torch.hub.get_dir()) / "checkpoints" / self.file_name

    def fetch(self) -> Path:
        path = self.path()
        if path.is_file():
            return path
        from kornia.core.download import load_state_dict_from_url

        try:
            load_state_dict_from_url(list(self.urls), file_name=self.file_name, map_location="cpu")
        except Exception as error:  # noqa: BLE001 - offline, refused, cut short: one line
            raise ValueError(f"weights {self.file_name} are not in {path.parent} and could not be downloaded from "
                             f"{self.urls[0]} ({type(error).__name__}); download it into that folder, or pass --weights FILE") from None
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
