"""How the match stage runs: `MatchOptions`, the `match` section of a run's options.

Its fields are that section's names by themselves, from the flags (`--feature-cache-mb`,
`--pair-timeout`, ...) through an experiment's `match:` and the resolver (pipeline/resolve.py)
to the stage that reads them (pipeline/stage.py). None of them changes a result.
"""

from __future__ import annotations

from dataclasses import dataclass


ON_MATCHER_ERROR = ("stop", "fail-pair")


def resolve_pair_timeout(pair_timeout: float | None) -> float | None:
    """Seconds a matcher may take on one pair: --pair-timeout as given, else (None) no limit, the
    default: a limit runs each matcher in a child process of its own and turns the feature cache
    off, so it is asked for. The one place that default is read: every command, `reproduce` and
    the Python API come through MatchOptions, which resolves its pair_timeout here."""
    if pair_timeout is not None and not pair_timeout > 0:
        raise ValueError(f"--pair-timeout must be a positive number of seconds, got {pair_timeout}")
    return pair_timeout


@dataclass(frozen=True)
class MatchOptions:
    """How the match stage runs.

    feature_cache_mb: memory (MiB) for the feature pyramids of images that have pairs left
    (matchers/feature_cache.py; 0: no reuse; None: half the memory available when the stage
    starts, at most 16 GiB). spill_mb: disk for the pyramids memory cannot hold, in the first
    job's run folder (0: none; None: half the free disk there, at most 64 GiB). backbone_batch:
    images passed through a shared backbone together when the current pair needs a pass, with
    the coming pairs' images the cache lacks (batch_ahead; None: 8 on a GPU, 1 on a CPU).
    None of these changes a result. on_matcher_error: `stop` ends the stage at a pair whose
    matcher raises (the pairs before it are kept); `fail-pair` stores that pair with no matches
    and its message (FAILED_ATTR), so that it counts as a failure, and goes on. pair_timeout:
    seconds a matcher may take on one pair before it fails on it (None: no limit). With a
    limit, each matcher runs in a child process of its own that is killed, with every process
    it started, when a pair takes longer (`isolates`); the feature cache is then off (each
    child computes its own maps), which changes no result. feature_reuse (default True): a
    two-stage matcher's features (matchers/base.py `splits`) extracted once per image, in the same
    cache; False: pair by pair, as before (deep matchers keep their cache). The same matches.
    """

    feature_cache_mb: float | None = None
    spill_mb: float | None = None
    backbone_batch: int | None = None
    on_matcher_error: str = "stop"
    pair_timeout: float | None = None
    feature_reuse: bool = True

    def __post_init__(self) -> None:
        if self.on_matcher_error not in ON_MATCHER_ERROR:
            raise ValueError(f"--on-matcher-error must be one of {', '.join(ON_MATCHER_ERROR)}, "
                             f"got {self.on_matcher_error!r}")
        object.__setattr__(self, "pair_timeout", resolve_pair_timeout(self.pair_timeout))  # frozen
        if self.backbone_batch is not None and int(self.backbone_batch) < 1:
            raise ValueError(f"--backbone-batch must be at least 1, got {self.backbone_batch}")
