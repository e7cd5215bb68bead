"""The matching algorithms as pure tensor functions (no I/O): levels, dense, refine, cascade,
pipeline (E3CM), dfm (two-stage DFM). This file imports nothing heavy, so that the names
below can be read without loading torch."""

# How F_l is estimated at each level of the cascade (cascade.py implements them).
ESTIMATORS = ("top8", "ransac", "prosac", "magsac")
# The estimators that read the confidence score (Eq. 3) of the matches.
SCORED_ESTIMATORS = ("top8", "prosac")
# The estimators that draw from OpenCV's RNG: a matcher using one depends on its seed.
RANDOM_ESTIMATORS = ("ransac", "prosac", "magsac")
