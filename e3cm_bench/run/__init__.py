"""A run: its folder (RunFolder, the one owner of the layout, the config record and the identity
check) and the one driver every kind of run goes through (run.driver)."""

from .folder import FAILED_ATTR, RunConfig, RunFolder

__all__ = ["FAILED_ATTR", "RunConfig", "RunFolder"]
