"""Stereo rig self-calibration (paper Sec. 4.4): the extrinsics from matches and their errors
(extrinsics.py, pure functions), and `e3cm-bench calibrate`'s run over a sequence (run.py)."""

from e3cm_bench.apps.calibration.extrinsics import (
    ERROR_COLUMNS,
    estimate_extrinsics,
    extrinsic_errors,
    vertical_disparity,
)

__all__ = ["ERROR_COLUMNS", "estimate_extrinsics", "extrinsic_errors", "vertical_disparity"]
