"""A run: its folder (RunFolder, the one owner of the layout and the identity check), its record
(RunConfig, the one writer and reader of config.yaml; load_run_pairs, the one way to load a run's
pairs again) and the one driver every kind of run goes through (run.driver)."""

from .config import RunConfig, RunPairs, load_run_pairs
from .folder import FAILED_ATTR, RunFolder

__all__ = ["FAILED_ATTR", "RunConfig", "RunFolder", "RunPairs", "load_run_pairs"]
