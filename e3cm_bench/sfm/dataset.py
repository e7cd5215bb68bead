"""The sfm benchmark's dataset: a multi-view set (sfm/views.py) as the pairs its graph matches.

Each pair is an ordinary pose pair (K0, K1, T_0to1), so the match stage, its cache, shards and
feature reuse treat it as any other; as a views.ViewPair it also carries the two views' names,
which the reconstruction keys its images by, and its bag; how the set is reconstructed is the
evaluation's (sfm/protocol.py), not the pairs'. Pairs are named ``SET/<stem0>--<stem1>``, SET being
the scene_info file's or the model folder's name (the pair list's own names otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from e3cm_bench.datasets.base import DatasetError, PairList, require_directory
from e3cm_bench.sfm import views as V
from e3cm_bench.sfm.protocol import _whole
from e3cm_bench.sfm.mapper import mapper_settings


@dataclass(frozen=True)
class SetOptions:
    """The sfm benchmark's dataset options as given (text from the command line or a config,
    checked by MultiViewSet): where the views come from (scene_info, colmap_model or pairs),
    and the pair graph (window, graph, max_pairs, allow_disconnected, absolute_paths). The
    reconstruction's protocol is the evaluation's (sfm/protocol.py protocol_of)."""

    scene_info: str | Path | None = None
    colmap_model: str | Path | None = None
    pairs: str | Path | None = None
    window: str | int | None = None
    graph: str | Path | None = None
    allow_disconnected: bool = False
    absolute_paths: bool = False
    max_pairs: str | int | None = None


class MultiViewSet(PairList):
    """The pairs of a multi-view set, by its options (SetOptions): ``scene_info`` (MegaDepth, absolute poses),
    ``colmap_model`` (a sparse model's folder, absolute poses) or ``pairs`` (a SuperGlue list: those pairs, their
    relative poses). Exactly one is given. With absolute poses the graph is every pair, or
    ``window`` (each image with the next K), or ``graph`` (a file of image-name pairs).

    Everything that would stop the reconstruction is refused here, before any matching: no
    pycolmap, an image listed twice, two pairs of the same two images (either way round), an
    image outside the root (unless ``absolute_paths``), and a pair graph in several connected
    components (unless ``allow_disconnected``: then each component is a bag of its own,
    ``pair.bag``, 0 the largest)."""

    name = "sfm"

    def __init__(self, root: str | Path, options: SetOptions = SetOptions(), skip_bad: bool = False,
                 first: int | None = None) -> None:
        # on first use: the command line's help reads this module
        from e3cm_bench.ground.pycolmap import pycolmap_module

        o = options  # as given: each is checked here
        self.root = require_directory(root, "image set")
        pycolmap_module()  # the reconstruction's: missing, it is said now rather than after every pair is matched
        given = [flag for flag, value in (("--scene-info", o.scene_info), ("--colmap-model", o.colmap_model),
                                           ("--pairs", o.pairs)) if value is not None]
        if len(given) != 1:
            raise DatasetError(f"{self.root}: give exactly one of --scene-info, --colmap-model and --pairs "
                               f"(given: {', '.join(given) or 'none'})")
        self.window = _window(o.window)
        self.graph = Path(o.graph) if o.graph is not None else None
        self.allow_disconnected, self.absolute_paths = bool(o.allow_disconnected), bool(o.absolute_paths)
        if self.window is not None and self.graph is not None:
            raise DatasetError(f"{self.graph}: --window and --graph are two pair graphs; give one")
        listed, bad = self._read(o.scene_info, o.colmap_model, o.pairs)
        self.max_pairs = _count(o.max_pairs, "--max-pairs") or DEFAULT_MAX_PAIRS
        self.n_graph_pairs = self._check_size(listed, first)
        built, unusable = self._pairs(listed, first)
        super().__init__(built, self.source, skip_bad, bad + unusable)
        self.components = self._bags()

    def _read(self, scene_info, colmap_model, pairs) -> tuple[list[V.ListedPair], list[tuple[str, str]]]:
        """The views (self.views) and the pairs of the graph; (pair, problem) of a pair list's
        pairs whose ground truth is unusable."""
        anywhere = self.absolute_paths
        if scene_info is not None:
            self.source, self.kind = Path(scene_info), "scene_info"
            self.views = V.views_from_scene_info(self.source, self.root, anywhere)
        elif colmap_model is not None:
            self.source, self.kind = Path(colmap_model), "colmap_model"
            self.views = V.views_from_colmap(self.source, self.root, anywhere)
        else:
            self.source, self.kind = Path(pairs), "pairs"
            if self.window is not None or self.graph is not None:
                raise DatasetError(f"{self.source}: a pair list is its own graph (its relative poses are the only "
                                   "ground truth); --window and --graph apply to --scene-info and --colmap-model")
            self.views, listed, bad = V.views_from_pair_list(self.source, self.root, anywhere)
            return listed, bad
        if self.graph is not None:
            return V.read_graph(self.graph, self.views), []
        return (V.window(self.views, self.window) if self.window is not None else V.exhaustive(self.views)), []

    def _pairs(self, listed, first: int | None = None) -> tuple[list[V.ViewPair], list[tuple[str, str]]]:
        """A Pair per listed pair, named SET/<label0>--<label1> (views.pair_labels); (name, problem)
        of those whose relative pose is unusable. Two pairs of the same two images are refused:
        the database holds one match list per image pair."""
        by_name = {v.name: v for v in self.views}
        labels = V.pair_labels(self.views)
        set_name = self.source.stem if self.kind == "scene_info" else self.source.name
        built, bad, seen = [], [], {}
        for item in listed:
            if first and len(built) >= first:  # --limit: the graph is built no further than the run reaches
                break
            view0, view1 = by_name[item.view0], by_name[item.view1]
            name = f"{set_name}/{labels[item.view0]}--{labels[item.view1]}"
            key = frozenset((item.view0, item.view1))
            if key in seen:
                raise DatasetError(
                    f"{self.graph or self.source}: pairs {seen[key]} and {name} join the same two images "
                    f"({item.view0} and {item.view1}); a reconstruction holds one match list per image pair"
                )
            seen[key] = name
            try:
                T = item.T_0to1 if item.T_0to1 is not None else V.relative_pose(
                    view0, view1, f"{self.source}: images {item.view0} and {item.view1}")
            except DatasetError as error:
                bad.append((name, str(error)))
                continue
            built.append(V.ViewPair(name=name, image0=view0.path, image1=view1.path, K0=view0.K, K1=view1.K, T_0to1=T,
                                    scene=set_name, view0=item.view0, view1=item.view1))
        return built, bad

    def _bags(self) -> list[list[str]]:
        """The pair graph's connected components (image names, largest first), checked before any
        matching: a graph of several is refused, unless allow_disconnected, where each pair's
        bag says its component (pairs never join two: a component is closed)."""
        found = graph_components(self.pairs, self.views, self.allow_disconnected, self.graph or self.source)
        bag = {name: k for k, names in enumerate(found) for name in names}
        for pair in self.pairs:
            pair.bag = bag[pair.view0]
        return found

    def preamble(self) -> str:
        sizes = [len(names) for names in self.components]
        if len(sizes) == 1:
            return f"pair graph: one component of {sizes[0]} images"
        return f"pair graph: {len(sizes)} components (bags) of {', '.join(map(str, sizes))} images"

    def _check_size(self, listed, first: int | None) -> int:
        """The number of pairs of the graph, counted before one is built; a DatasetError where the
        run would build more than max_pairs of them."""
        n = len(self.views)
        count = len(listed) if isinstance(listed, list) else V.graph_size(n, self.window)
        every = self.window is None and self.graph is None and self.kind != "pairs"
        check_graph_size(self.graph or self.source, n, count, min(count, first) if first else count, self.max_pairs,
                         every, "--window K, --graph FILE, --limit N")
        return count

    def settings(self) -> dict:
        graph = ("listed" if self.kind == "pairs" else f"file {self.graph}" if self.graph is not None
                 else f"window {self.window}" if self.window is not None else "exhaustive")
        # The reconstruction's settings are recorded with the set (config.yaml's dataset block):
        # they decide every number the evaluation gives, as the set does.
        return {"dataset": self.name, "root": str(self.root), self.kind: str(self.source), "window": self.window,
                "graph": str(self.graph) if self.graph is not None else None, "pair_graph": graph,
                "components": {"count": len(self.components), "sizes": [len(c) for c in self.components]},
                "allow_disconnected": self.allow_disconnected, "absolute_paths": self.absolute_paths,
                "max_pairs": self.max_pairs, "n_views": len(self.views), "reconstruction": mapper_settings()}


# The pairs a set's graph may hold unless --max-pairs says more: an exhaustive graph grows with
# the square of the images (20,000 pairs: 200 images; 3000 images give 4.5 million).
DEFAULT_MAX_PAIRS = 20_000
MAX_WINDOW = 10_000  # each image with the next K: beyond a set's size it is every pair anyway


def check_graph_size(source, n: int, count: int, building: int, max_pairs: int, every: bool, fewer: str) -> None:
    """A DatasetError, before a pair is built, where a run would build more than max_pairs (sfm and
    reconstruct: 3000 images give 4.5 million pairs, gigabytes before the first match)."""
    if building > max_pairs:
        raise DatasetError(f"{source}: {n} images give {count:,} pairs ({'every pair' if every else 'its graph'}), "
                           f"over the {max_pairs:,} a run builds; --max-pairs {count} lifts the bound, or choose "
                           f"fewer pairs ({fewer})")


def graph_components(pairs, views, allow_disconnected: bool, source) -> list[list[str]]:
    """The pair graph's connected components (image names, largest first); a DatasetError where
    there are several and allow_disconnected is not given (sfm and reconstruct alike)."""
    found = V.components((p.view0, p.view1) for p in pairs)
    if len(found) > 1 and not allow_disconnected:
        labels = V.pair_labels(views)
        shown = ", ".join(
            "{"
            + ", ".join(labels[n] for n in names[:3])
            + (f", ... {len(names)} images" if len(names) > 3 else "")
            + "}"
            for names in found[:4]
        )
        more = f" and {len(found) - 4} more" if len(found) > 4 else ""
        raise DatasetError(f"{source}: the pair graph has {len(found)} components that share no "
                           f"image: {shown}{more}; pass --allow-disconnected to reconstruct each as its own bag")
    return found


def _count(value, option: str) -> int | None:
    return None if value is None else _whole(value, option)


def _window(value) -> int | None:
    if value is None:
        return None
    try:
        k = int(str(value))
    except ValueError:
        raise DatasetError(f"--window must be a whole number of images, got {value!r}") from None
    if not 1 <= k <= MAX_WINDOW:
        raise DatasetError(f"--window must be from 1 to {MAX_WINDOW}, got {k}")
    return k
