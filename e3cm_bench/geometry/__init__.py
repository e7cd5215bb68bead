"""Geometry: two-view geometry, the evaluation's robust estimators as backends, and the metrics
(arrays in, numbers out)."""
