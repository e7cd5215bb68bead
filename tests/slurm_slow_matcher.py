"""A matcher for the SLURM tests (tests/pipeline/test_slurm_cluster.py): SIFT that first waits
E3CM_SLOW_SECONDS per pair, so that an array task is still matching when the test cancels it
or its time limit passes. The wait is no setting (not in the identity): a run without it, the
reference, makes the same matches and may be merged with the same shards."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from e3cm_bench import Matcher, MatcherEntry
from e3cm_bench.matchers import build_matcher


@dataclass(frozen=True)
class SlowSettings:
    pass


class SlowSift(Matcher):
    name = "slow-sift"

    def __init__(self, settings: SlowSettings) -> None:
        self.sift = build_matcher("sift")

    def config(self) -> dict:
        return {**self.sift.config(), "matcher": self.name}

    def match(self, image0, image1):
        time.sleep(float(os.environ.get("E3CM_SLOW_SECONDS", "0")))
        return self.sift.match(image0, image1)


ENTRY = MatcherEntry(name="slow-sift", description="SIFT after a wait of E3CM_SLOW_SECONDS (SLURM tests)",
                     build=SlowSift, settings=SlowSettings)
