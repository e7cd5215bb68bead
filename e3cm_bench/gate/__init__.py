"""The regression gate: check against a baseline, tolerances, the noise gate and its ensemble."""
