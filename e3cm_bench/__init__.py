"""e3cm-bench: training-free deep feature matching (E3CM, DFM, SIFT+NN) and its benchmarks."""

__version__ = "0.1.0"
