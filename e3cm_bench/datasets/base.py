"""What every benchmark dataset yields: pairs of image paths with their ground truth."""

from __future__ import annotations

import copy
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import InitVar, dataclass
from pathlib import Path

import numpy as np

from e3cm_bench.ground.images import image_file_problem


class DatasetError(ValueError):
    """Bad or missing benchmark input; the message is one line naming the file and the problem."""


@dataclass
class Pair:
    """One image pair and its ground truth.

    ``name`` is unique within a dataset; it is the key of the pair in ``matches.h5`` and
    the ``pair`` column of ``per_pair.csv``. Homography pairs carry ``H`` (maps pixels of
    image 0 to image 1); pose pairs carry ``K0``, ``K1`` (original images) and ``T_0to1``
    (4x4, camera 0 to camera 1).

    The labels a sample is stratified by and a table grouped by are typed fields, so that a
    misspelt label is an error where the pair is built, not an empty group where it is read:
    ``sequence`` (HPatches), ``scene`` (MegaDepth, YFCC, a multi-view set), ``category``
    (WxBS). ``rotations``: the quarter turns (image 0, image 1) that make the pair upright
    (YFCC's list), which a method with ``upright`` applies before matching.

    ``meta`` is taken at construction only, for code written against the dict these labels
    once were: each of its keys must name a label (``rot0``/``rot1`` the rotations).
    """

    name: str
    image0: Path
    image1: Path
    H: np.ndarray | None = None
    K0: np.ndarray | None = None
    K1: np.ndarray | None = None
    T_0to1: np.ndarray | None = None
    sequence: str = ""
    scene: str = ""
    category: str = ""
    rotations: tuple[int, int] = (0, 0)
    meta: InitVar[dict | None] = None

    def __post_init__(self, meta: dict | None) -> None:
        if not meta:
            return
        unknown = sorted(set(meta) - {*LABELS, "rot0", "rot1"})
        if unknown:
            raise ValueError(f"pair {self.name}: unknown label(s) {', '.join(unknown)}; a pair's labels are "
                             f"{', '.join(LABELS)}, rot0, rot1")
        for key in LABELS:
            if key in meta:
                setattr(self, key, str(meta[key]))
        if "rot0" in meta or "rot1" in meta:
            self.rotations = (int(meta.get("rot0", 0)), int(meta.get("rot1", 0)))

    @property
    def labels(self) -> dict:
        """The labels this pair has (the non-empty ones), by name."""
        return {key: getattr(self, key) for key in LABELS if getattr(self, key)}


# The labels a sample is stratified by, coarse to fine (stratum).
LABELS = ("category", "scene", "sequence")
# `meta` is a constructor argument only: without this, the InitVar's default would stay behind as a
# class attribute and code still reading the old dict would fail on None instead of naming `meta`.
del Pair.meta


class PairList:
    """A dataset's pairs, checked before any matching; iterable, sized, indexable.

    Subclasses build their pairs and pass them here with ``source``, the file or folder
    that the pairs came from (named in error messages), and ``bad``: (pair name, problem)
    for the pairs whose ground truth could not be used. Every image is checked cheaply
    (exists, not empty, not cut short). With ``skip_bad`` the bad pairs are dropped and
    listed in ``skipped``; without it, any bad pair is an error, so that a partial dataset
    never passes for the whole benchmark.
    """

    def __init__(self, pairs: Sequence[Pair], source: Path, skip_bad: bool,
                 bad: Sequence[tuple[str, str]] = ()) -> None:
        if not pairs and not bad:
            raise DatasetError(f"{source}: the pair list is empty")
        _reject_duplicate_names(pairs, source)
        n_total = len(pairs) + len(bad)  # pairs with bad ground truth were never built
        image_problems = _image_problems(pairs)
        image_bad = []
        for pair in pairs:
            path = next((p for p in (pair.image0, pair.image1) if p in image_problems), None)
            if path is not None:
                image_bad.append((pair.name, f"{path}: {image_problems[path]}"))
        all_bad = list(bad) + image_bad
        if all_bad and not skip_bad:
            missing = [path for path, problem in image_problems.items() if problem == MISSING]
            if not bad and len(missing) == len(image_problems):
                examples = ", ".join(str(path) for path in missing[:3])
                raise DatasetError(
                    f"{source}: {len(missing)} image(s) missing ({len(image_bad)} of {n_total} pairs affected), "
                    f"e.g. {examples}; pass --skip-bad to evaluate only the pairs whose input is sound"
                )
            raise DatasetError(
                f"{all_bad[0][1]} ({len(all_bad)} of {n_total} pairs have bad input); "
                "pass --skip-bad to skip them (they are listed in skipped.csv)"
            )
        bad_names = {name for name, _ in image_bad}
        self.pairs = [p for p in pairs if p.name not in bad_names]
        self.skipped = all_bad
        self.skip_bad = skip_bad
        if not self.pairs:
            raise DatasetError(f"{source}: none of the {n_total} pairs is usable (first: {all_bad[0][1]})")

    @property
    def n_skipped(self) -> int:
        return len(self.skipped)

    def skip_reason(self) -> str:
        """Why pairs were skipped, in a few words for the console."""
        if all(reason.endswith(MISSING) for _, reason in self.skipped):
            return "images missing"
        return "bad input, listed in skipped.csv"

    def preamble(self) -> str:
        """What a run prints of the pairs besides their number (the sfm set: its pair graph's
        components); empty for most datasets."""
        return ""

    def __iter__(self) -> Iterator[Pair]:
        return iter(self.pairs)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> Pair:
        return self.pairs[index]

    def settings(self) -> dict:
        """What defines the pair list, besides its length (overridden by each dataset)."""
        return {}

    def describe(self) -> dict:
        described = {
            **self.settings(),
            "skip_bad": self.skip_bad,
            "n_pairs": len(self.pairs),
            "n_skipped": self.n_skipped,
        }
        sample = getattr(self, "sample", None)
        if sample is not None:  # only a sampled list says so: unsampled runs keep their old record
            described["sample"] = dict(sample)
        return described

    def sampled(self, n: int, seed: int = 0) -> PairList:
        """A stratified sample of `n` pairs (`stratified_sample`), in this list's order; the
        sample (its size, seed, and the number of pairs drawn from) is in `describe()`."""
        if n < 1:
            raise ValueError(f"--sample must be at least 1, got {n}")
        chosen = stratified_sample(self.pairs, n, seed)
        subset = copy.copy(self)
        subset.pairs = chosen
        subset.sample = {"n": n, "seed": seed, "from": len(self.pairs), "strata": len({stratum(p) for p in self.pairs})}
        return subset


# --------------------------------------------------------------------------- sampling

def stratum(pair: Pair) -> tuple[str, ...]:
    """The group a pair is drawn from, coarse to fine: its category (WxBS), scene (MegaDepth,
    YFCC) and sequence (HPatches, with the sequence's kind, the `i`/`v` of `i_leuven`, above
    it so that a sample holds both kinds). A pair with none of these is in the one group ()."""
    levels = [label for label in (pair.category, pair.scene) if label]
    sequence = pair.sequence
    if sequence:
        if "_" in sequence:
            levels.append(sequence.split("_", 1)[0])
        levels.append(sequence)
    return tuple(levels)


def stratified_sample(pairs: Sequence[Pair], n: int, seed: int = 0) -> list[Pair]:
    """`n` of `pairs` spread over their strata (`stratum`), deterministic given `seed`.

    Round robin over a tree of groups: at each level the groups are visited in a seeded random
    order, one pair from each in turn, so that `n` pairs cover min(n, groups) groups at every
    level before any group gives a second pair; within a group the pairs come in a seeded
    random order. The chosen pairs are returned in the order of `pairs` (a run's pair order
    stays the dataset's). n >= len(pairs) returns every pair.
    """
    pairs = list(pairs)
    if n >= len(pairs):
        return pairs
    rng = np.random.default_rng(seed)
    keys = [stratum(p) for p in pairs]
    depth = max((len(k) for k in keys), default=0)

    def order(indices: list[int], level: int) -> list[int]:
        if level >= depth or len(indices) <= 1:
            return [indices[i] for i in rng.permutation(len(indices))]
        groups: dict[str, list[int]] = {}
        for i in indices:
            groups.setdefault(keys[i][level] if level < len(keys[i]) else "", []).append(i)
        names = sorted(groups)
        streams = [order(groups[names[g]], level + 1) for g in rng.permutation(len(names))]
        merged = []
        for rank in range(max(len(s) for s in streams)):
            merged.extend(s[rank] for s in streams if rank < len(s))
        return merged

    chosen = set(order(list(range(len(pairs))), 0)[:n])
    return [pair for i, pair in enumerate(pairs) if i in chosen]


MISSING = "image file not found"  # what images.image_file_problem says of a missing file


def _reject_duplicate_names(pairs: Iterable[Pair], source: Path) -> None:
    # Names key the match cache and the per-pair CSV; a duplicate would silently overwrite.
    seen: set[str] = set()
    for pair in pairs:
        if pair.name in seen:
            raise DatasetError(f"{source}: pair name {pair.name!r} occurs twice")
        seen.add(pair.name)


def _image_problems(pairs: Iterable[Pair]) -> dict[Path, str]:
    """Image path -> what is wrong with it (missing, empty, cut short), each path checked once."""
    checked: dict[Path, str | None] = {}
    for pair in pairs:
        for path in (pair.image0, pair.image1):
            if path not in checked:
                checked[path] = image_file_problem(path)
    return {path: problem for path, problem in checked.items() if problem}


# A text list's bounds (pairs.txt, views.txt, a pair graph, a YFCC pair list): a line holds two
# names or one view's numbers (at most a few KiB); a list of 20000 pairs is about 1 MiB.
MAX_LINE_CHARS = 1 << 16
MAX_LIST_BYTES = 1 << 28


def text_lines(path: Path, comments: bool = True) -> Iterator[tuple[int, str]]:
    """(number in the file, text) of each line of a text list but blank lines and # comments
    (comments=False: those are lines too): a message quotes the line number an editor shows.
    DatasetError naming the file where it cannot be read, is over MAX_LIST_BYTES (said before it
    is read) or holds a line over MAX_LINE_CHARS."""
    try:
        size = Path(path).stat().st_size
        if size > MAX_LIST_BYTES:
            raise DatasetError(f"{path}: {size} bytes, over the {MAX_LIST_BYTES} a list may hold")
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: not readable ({' '.join(str(error).split())})") from None
    for number, line in enumerate(text.splitlines(), 1):
        if len(line) > MAX_LINE_CHARS:
            raise DatasetError(f"{path}: line {number} holds {len(line)} characters, over the {MAX_LINE_CHARS} a "
                               "line of a list may hold")
        if line.strip() and (not comments or not line.lstrip().startswith("#")):
            yield number, line


# One name of a line as a POSIX shell reads it (shlex.split's rules): runs of plain characters,
# '...' (literal), "..." (a backslash escapes " and \ only) and \x, side by side. Each
# alternative is one pass over its characters (the double-quoted one unrolled), so a line is
# split in time linear in its length: shlex builds each name a character at a time, which is
# quadratic (a 4 MB line took minutes).
_NAME_PART = re.compile(r"""[^ \t\r\n'"\\]+|'[^']*'|"[^"\\]*(?:\\.[^"\\]*)*"|\\.|([ \t\r\n]+)""", re.S)
_ESCAPED_IN_QUOTES = re.compile(r'\\(["\\])')


def split_names(line: str) -> list[str]:
    """The names of a line as shlex.split (POSIX, no comments) reads them, in linear time; a
    ValueError with shlex's words for an unclosed quote or a trailing backslash."""
    names, current, position = [], None, 0  # current: the parts of the name being read (joined once)
    while position < len(line):
        part = _NAME_PART.match(line, position)
        if part is None:
            raise ValueError("No escaped character" if line[position] == "\\" else "No closing quotation")
        position, text = part.end(), part.group()
        if part.group(1) is not None:  # whitespace (shlex's: space, tab, CR, LF) ends a name
            if current is not None:
                names.append("".join(current))
            current = None
            continue
        if text[0] == "'":
            text = text[1:-1]
        elif text[0] == '"':
            text = _ESCAPED_IN_QUOTES.sub(r"\1", text[1:-1])
        elif text[0] == "\\":
            text = text[1]
        current = [] if current is None else current
        current.append(text)
    if current is not None:
        names.append("".join(current))
    return names


def name_pairs(path: Path, known, unknown: str) -> Iterator[tuple[int, str, str]]:
    """(line number, name0, name1) of each line of a list of image-name pairs (``name0 name1``
    per line; MegaDepth's pairs.txt, the sfm benchmark's pair graph). A line that does not hold
    two names, or names one not in `known`, is an error naming the file and line; `unknown`
    says what such a name is not (``which views.txt does not list``). A name holding a space
    is quoted as a POSIX shell quotes it ('a b.png'), as pair_line writes it."""
    for number, line in text_lines(path):
        try:
            names = split_names(line)
        except ValueError as error:  # an unclosed quote
            raise DatasetError(f"{path}: line {number}: {error}") from None
        if len(names) != 2:
            raise DatasetError(f"{path}: line {number} holds {len(names)} names, not two")
        for name in names:
            if name not in known:
                raise DatasetError(f"{path}: line {number} names {name}, {unknown}")
        yield number, names[0], names[1]


def pair_line(name0: str, name1: str) -> str:
    """One line of a list of image-name pairs, each name quoted where it must be (spaces and other
    characters a shell would split at), so that name_pairs reads the same two names back."""
    import shlex

    return f"{shlex.quote(name0)} {shlex.quote(name1)}\n"


def require_directory(root: Path, what: str) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: {what} root folder not found")
    return root
