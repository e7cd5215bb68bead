"""A run: its folder (RunFolder, the one owner of the layout and the config record)."""

from .folder import FAILED_ATTR, RunConfig, RunFolder

__all__ = ["FAILED_ATTR", "RunConfig", "RunFolder"]
