"""A run: its folder (RunFolder, the one owner of the layout and the config record)."""

from .folder import RunConfig, RunFolder

__all__ = ["RunConfig", "RunFolder"]
