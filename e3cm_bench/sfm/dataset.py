"""The sfm benchmark's dataset: a multi-view set (sfm/views.py) as the pairs its graph matches.

Each pair is an ordinary pose pair (K0, K1, T_0to1), so the match stage, its cache, shards and
feature reuse treat it as any other; ``meta`` carries the two views' names, which the
reconstruction keys its images by. Pairs are named ``SET/<stem0>--<stem1>``, SET being the
scene_info file's or the model folder's name (the pair list's own names otherwise).
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

from ..datasets.base import DatasetError, Pair, PairList, require_directory
from . import views as V
from .protocol import parse_protocol
from .reconstruct import mapper_settings


class MultiViewSet(PairList):
    """The pairs of a multi-view set: ``scene_info`` (MegaDepth, absolute poses), ``colmap_model``
    (a sparse model's folder, absolute poses) or ``pairs`` (a SuperGlue list: those pairs, their
    relative poses). Exactly one is given. With absolute poses the graph is every pair, or
    ``window`` (each image with the next K), or ``graph`` (a file of image-name pairs)."""

    name = "sfm"

    def __init__(self, root: str | Path, scene_info: str | Path | None = None, colmap_model: str | Path | None = None,
                 pairs: str | Path | None = None, window: str | int | None = None, graph: str | Path | None = None,
                 merge_px: str | float | None = None, mapper: str | None = None, mapper_seeds: str | int | None = None,
                 merge: str | None = None, verification: str | None = None, score_model: str | None = None,
                 skip_bad: bool = False) -> None:
        self.root = require_directory(root, "image set")
        given = [flag for flag, value in (("--scene-info", scene_info), ("--colmap-model", colmap_model),
                                           ("--pairs", pairs)) if value is not None]
        if len(given) != 1:
            raise DatasetError(f"{self.root}: give exactly one of --scene-info, --colmap-model and --pairs "
                               f"(given: {', '.join(given) or 'none'})")
        self.window = _window(window)
        self.protocol = parse_protocol(mapper, mapper_seeds, merge, merge_px, verification, score_model)
        self.merge_px = self.protocol.merge_px
        self.graph = Path(graph) if graph is not None else None
        if self.window is not None and self.graph is not None:
            raise DatasetError(f"{self.graph}: --window and --graph are two pair graphs; give one")
        if scene_info is not None:
            self.source, self.kind = Path(scene_info), "scene_info"
            self.views = V.views_from_scene_info(self.source, self.root)
        elif colmap_model is not None:
            self.source, self.kind = Path(colmap_model), "colmap_model"
            self.views = V.views_from_colmap(self.source, self.root)
        else:
            self.source, self.kind = Path(pairs), "pairs"
            if self.window is not None or self.graph is not None:
                raise DatasetError(f"{self.source}: a pair list is its own graph (its relative poses are the only "
                                   "ground truth); --window and --graph apply to --scene-info and --colmap-model")
            self.views, listed = V.views_from_pair_list(self.source, self.root)
        by_name = {v.name: v for v in self.views}
        if self.kind != "pairs":
            if self.graph is not None:
                listed = V.read_graph(self.graph, self.views)
            elif self.window is not None:
                listed = V.window(self.views, self.window)
            else:
                listed = V.exhaustive(self.views)
        set_name = self.source.stem if self.kind == "scene_info" else self.source.name
        built, bad = [], []
        for number, item in enumerate(listed):
            view0, view1 = by_name[item.view0], by_name[item.view1]
            stems = f"{PurePosixPath(item.view0).stem}--{PurePosixPath(item.view1).stem}"
            name = f"{set_name}/{stems}"
            try:
                T = item.T_0to1 if item.T_0to1 is not None else V.relative_pose(
                    view0, view1, f"{self.source}: images {item.view0} and {item.view1}")
            except DatasetError as error:
                bad.append((name, str(error)))
                continue
            built.append(Pair(name=name, image0=view0.path, image1=view1.path, K0=view0.K, K1=view1.K, T_0to1=T,
                              meta={"scene": set_name, "view0": item.view0, "view1": item.view1,
                                    "merge_px": self.merge_px, "protocol": self.protocol}))
        super().__init__(built, self.source, skip_bad, bad)

    def settings(self) -> dict:
        graph = ("listed" if self.kind == "pairs" else f"file {self.graph}" if self.graph is not None
                 else f"window {self.window}" if self.window is not None else "exhaustive")
        # The reconstruction's settings are recorded with the set (config.yaml's dataset block):
        # they decide every number the evaluation gives, as the set does.
        return {"dataset": self.name, "root": str(self.root), self.kind: str(self.source), "window": self.window,
                "graph": str(self.graph) if self.graph is not None else None, "pair_graph": graph,
                "merge_px": self.merge_px, "n_views": len(self.views), "protocol": self.protocol.record(),
                "reconstruction": mapper_settings()}


def _window(value) -> int | None:
    if value is None:
        return None
    try:
        k = int(str(value))
    except ValueError:
        raise DatasetError(f"--window must be a whole number of images, got {value!r}") from None
    if k < 1:
        raise DatasetError(f"--window must be at least 1, got {k}")
    return k
