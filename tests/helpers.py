"""Small helpers shared by several test files (imported as `helpers`; pytest puts tests/ on the path)."""

from __future__ import annotations

import math

import numpy as np


def rotation(axis: str, degrees: float) -> np.ndarray:
    """3x3 rotation about one coordinate axis."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def one_line_error(result) -> str:
    """A clean CLI failure: exit code 2, exactly one line on stderr, no traceback."""
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: "), lines[0]
    assert "Traceback" not in result.output
    return lines[0]


def flat(text: str) -> str:
    """Output with rich's line wrapping undone (whitespace runs -> one space)."""
    return " ".join(text.split())
