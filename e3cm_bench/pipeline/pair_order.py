"""The order a match stage visits its pairs in, so that each image goes through the network once.

A benchmark's pairs share images (YFCC100M: 4000 pairs over 1455 images). An image's feature
maps are needed from its first pair to its last; in between they are held in memory or on
disk (matchers/feature_cache.py), and what neither can hold is computed again. So the order
that needs the fewest backbone passes is the one with the fewest images "alive" at once (had
a pair, have one left): the vertex separation of the image graph, whose minimum is NP-hard to
find. `reuse_order` takes the usual greedy for it: images are introduced one at a time, each
with all its pairs to images introduced before, and the next image is the one that leaves the
fewest images alive (it closes the images it is the last partner of; it stays alive itself
while it has partners left), ties to the image with the most partners already introduced.

On the real YFCC100M pair graph the most images alive at once are 101, against 441 for the
walk this replaced (which followed the most recently used image). With this machine's default
budgets (VGG19 at 1200x900: 20 pyramids in memory and 62 on disk) the cache then needs 1.09
passes per image instead of 1.83 (`scripts/measure/pair_order_passes.py`). Pure: no I/O, no torch.
"""

from __future__ import annotations

import heapq

from e3cm_bench.datasets.base import Pair


def _files(pair: Pair) -> tuple[str, str]:
    return str(pair.image0), str(pair.image1)


def reuse_order(pairs: list[Pair]) -> list[Pair]:
    """The pairs in an order with few images alive at once (see the module). Every pair once;
    deterministic (ties go by image path); the order changes no result: matches are stored by
    pair name, and per_pair.csv keeps the pair list's order. O(E log E) for E pairs."""
    adj: dict[str, dict[str, list[int]]] = {}
    own: dict[str, list[int]] = {}  # pairs of an image with itself
    for i, pair in enumerate(pairs):
        a, b = _files(pair)
        adj.setdefault(a, {})
        adj.setdefault(b, {})
        if a == b:
            own.setdefault(a, []).append(i)
        else:
            adj[a].setdefault(b, []).append(i)
            adj[b].setdefault(a, []).append(i)
    unseen = {v: len(partners) for v, partners in adj.items()}  # partners not yet introduced
    closes = dict.fromkeys(adj, 0)  # alive partners whose last partner left is this image
    joined = dict.fromkeys(adj, 0)  # partners already introduced
    introduced: set[str] = set()
    starts = sorted(adj, key=lambda v: (len(adj[v]), v))  # a new component starts at its least connected image
    next_start = 0
    heap: list[tuple[int, int, str]] = []

    def score(v: str) -> tuple[int, int, str]:
        return (1 if unseen[v] else 0) - closes[v], -joined[v], v

    def last_partner(w: str) -> str:
        return next(u for u in adj[w] if u not in introduced)

    order: list[int] = []
    while len(introduced) < len(adj):
        v = None
        while heap:
            entry = heapq.heappop(heap)
            if entry[2] not in introduced and entry == score(entry[2]):
                v = entry[2]
                break
        if v is None:
            while starts[next_start] in introduced:
                next_start += 1
            v = starts[next_start]
        introduced.add(v)
        order.extend(sorted(own.get(v, []) + [i for w, items in adj[v].items() if w in introduced for i in items]))
        for w in adj[v]:
            unseen[w] -= 1
            if w in introduced:
                if unseen[w] == 1:
                    u = last_partner(w)
                    closes[u] += 1
                    heapq.heappush(heap, score(u))
            else:
                joined[w] += 1
                heapq.heappush(heap, score(w))
        if unseen[v] == 1:
            u = last_partner(v)
            closes[u] += 1
            heapq.heappush(heap, score(u))
    return [pairs[i] for i in order]


def most_alive(order: list[Pair]) -> int:
    """The most images that have had a pair and still have one left, at any point of the order:
    with that many pyramids held (memory and disk together), every image passes once."""
    first, last = {}, {}
    for k, pair in enumerate(order):
        for image in _files(pair):
            first.setdefault(image, k)
            last[image] = k
    alive = top = 0
    for _, step in sorted(
        [(k, 1) for k in first.values()] + [(k, -1) for k in last.values()], key=lambda e: (e[0], -e[1])
    ):
        alive += step
        top = max(top, alive)
    return top
