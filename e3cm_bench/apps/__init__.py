"""The applications built on the rest: the demo, stereo calibration, the synthetic scenes."""
