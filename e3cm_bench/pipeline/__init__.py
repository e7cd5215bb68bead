"""Orchestration: the one run pipeline and its hooks, the match and evaluate stages, shards and
launch, import, export, reproduce."""
