"""A run folder on disk: its layout, lock and identity check (RunFolder), its record (RunConfig,
the one writer and reader of config.yaml) and the match cache (MatchCache). Imports only the
ground floor: what a run folder holds is read here, what runs into it is the pipeline's."""

from e3cm_bench.storage.folder import FAILED_ATTR, RunFolder
from e3cm_bench.storage.run_config import RunConfig

__all__ = ["FAILED_ATTR", "RunConfig", "RunFolder"]
