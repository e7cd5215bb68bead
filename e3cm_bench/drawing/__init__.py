"""Plots, match drawings and the number formats they print; low enough that benchmarks draw with it."""
