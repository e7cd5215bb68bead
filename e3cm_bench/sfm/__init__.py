"""Multi-view evaluation: image sets with ground truth (views.py, dataset.py), their reconstruction
by pycolmap (mapper.py) and the metrics read from it (metrics.py). benchmark.py is the
benchmark that puts them together."""
