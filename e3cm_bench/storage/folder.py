"""A run folder and its one owner: the layout, the config record, and lock / resume / clear.

Every command that writes or reads a run folder (a benchmark run, a merge of shards, an
import, a calibration, table, check, compare, report) asks a `RunFolder` for its files, so
that how a run is stored is decided here and nowhere else. The two levels of a run's
identity are those of glue-factory's evaluation pipeline: what made the matches (the
config's ``identity``: a MethodSpec's, an import's sources) decides whether a folder may
be resumed; the evaluation settings (``evaluation``) change only the metrics, and
``--eval-only`` may change them.

    OUT/config.yaml      the RunConfig record (run_config.py: its one writer and reader)
    OUT/matches.h5       the match cache (cache.MatchCache; blocks matches.NNN.h5 beside it)
    OUT/per_pair.csv     one row per pair;  OUT/summary.csv: the run's numbers with intervals
    OUT/cost.csv         each pair's matching time and peak memory (measurements: they move with the machine)
    OUT/skipped.csv      pairs skipped for bad input;  OUT/failures.csv: pairs a matcher failed on
    OUT/viz/             match drawings (--viz)
    OUT/shards/K-of-N/   the shards of a sharded run, each a run folder of its own
    OUT/.lock            held while a process uses the folder, removed when it is done (locks.FolderLock)
    OUT/.feature-spill/  feature maps memory could not hold, while matching
"""

from __future__ import annotations

import fcntl
import os
import re
import stat
from pathlib import Path

from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.ground.files import refuse_link, save_yaml
from e3cm_bench.ground.locks import FolderLock
from e3cm_bench.ground.folders import remove_folder
from e3cm_bench.storage.run_config import CONFIG_FILE, RunConfig

# The cache attribute of a pair whose matcher failed (--on-matcher-error fail-pair): the message.
# The pair is stored with no matches, so that it scores as a failure and a resume keeps it;
# failures.csv lists such pairs.
FAILED_ATTR = "matcher_error"


class RunFolder:
    """One run folder. Its file names are its own; everyone else asks for paths."""

    CONFIG = CONFIG_FILE
    MATCHES = "matches.h5"
    PER_PAIR = "per_pair.csv"
    SUMMARY = "summary.csv"
    COST = "cost.csv"
    SKIPPED = "skipped.csv"
    FAILURES = "failures.csv"
    VIZ = "viz"
    SHARDS = "shards"
    SPILL = ".feature-spill"
    # A calibration's (apps/calibration/run.py): every window's errors, and in the folder of a
    # set of methods the set's record and its two plots.
    WINDOWS = "windows.csv"
    CALIBRATION_SET = "calibrate.yaml"
    CALIBRATION_PLOTS = ("calibration_boxplot.png", "calibration_vs_frames.png")
    # What a new run replaces (--overwrite), besides the match cache.
    RESULTS = (CONFIG, PER_PAIR, SUMMARY, COST, SKIPPED, FAILURES)
    # The run's own plot (each benchmark draws one of these).
    RUN_PLOTS = ("mma.png", "pose_error_cdf.png")

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    @classmethod
    def own_file(cls, path: str | Path) -> bool:
        """Whether `path` names a file a run folder holds of its own (its record, tables, match
        cache and blocks, plot, a calibration's files), in a folder that is a run (holds config.yaml)."""
        path = Path(path)
        name = path.name
        own = (name in (cls.CONFIG, cls.MATCHES, cls.PER_PAIR, cls.SUMMARY, cls.COST, cls.SKIPPED, cls.FAILURES,
                        cls.WINDOWS, cls.CALIBRATION_SET, *cls.CALIBRATION_PLOTS, *cls.RUN_PLOTS)
               or re.fullmatch(r"matches\.\d+\.h5", name) is not None)
        return own and (path.parent / cls.CONFIG).is_file()

    @classmethod
    def refuse_own_files(cls, paths, command: str, option: str = "--out") -> None:
        """One line naming the first of `paths` that is a run folder's own file: `command` would
        write over it (table --out RUN/summary would have replaced the run's summary.csv; check
        --update --baseline RUN/summary.csv too). option: the option that named it."""
        for path in paths:
            if cls.own_file(path):
                raise ValueError(f"{path}: a file of the run folder {Path(path).parent}; {command} never writes over "
                                 f"a run's own files: choose another {option}")

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    def __fspath__(self) -> str:
        return str(self.path)

    # ---- layout
    @property
    def config_path(self) -> Path:
        return self.path / self.CONFIG

    @property
    def matches_path(self) -> Path:
        return self.path / self.MATCHES

    @property
    def per_pair_path(self) -> Path:
        return self.path / self.PER_PAIR

    @property
    def cost_path(self) -> Path:
        return self.path / self.COST

    @property
    def summary_path(self) -> Path:
        return self.path / self.SUMMARY

    @property
    def skipped_path(self) -> Path:
        return self.path / self.SKIPPED

    @property
    def failures_path(self) -> Path:
        return self.path / self.FAILURES

    @property
    def viz_dir(self) -> Path:
        return self.path / self.VIZ

    @property
    def spill_dir(self) -> Path:
        return self.path / self.SPILL

    @property
    def shards_dir(self) -> Path:
        return self.path / self.SHARDS

    @property
    def windows_path(self) -> Path:
        return self.path / self.WINDOWS

    @property
    def calibration_set_path(self) -> Path:
        return self.path / self.CALIBRATION_SET

    def drawing_path(self, pair_name: str) -> Path:
        """Where a pair's drawing goes; a link at viz/ is refused (refuse_link): a drawing is
        never written through it, over a file of the same name in its target."""
        return refuse_link(self.viz_dir) / (pair_name.replace("/", "__") + ".png")

    def shard(self, shard: tuple[int, int]) -> RunFolder:
        """The folder of the K-th of N shards of this run."""
        return RunFolder(self.shards_dir / f"{shard[0]}-of-{shard[1]}")

    def shard_folders(self) -> list[RunFolder]:
        return [RunFolder(p) for p in sorted(self.shards_dir.glob("*-of-*"))]

    # ---- state
    def is_run(self) -> bool:
        """A finished (or evaluated) run: its config and summary are there."""
        return self.config_path.is_file() and self.summary_path.is_file()

    # The file every report site holds (reporting/site.py MARKER): the copies of runs inside a
    # report (REPORT/runs/NN/) are not runs, and `reproduce` writes its report among its runs.
    REPORT_MARKER = ".e3cm-bench-report"

    @classmethod
    def find(cls, path: str | Path) -> list[RunFolder]:
        """The run folder at `path`, or the finished ones below it (not those inside a report)."""
        here = cls(path)
        if here.config_path.is_file():
            return [here]
        top = Path(path)

        def in_report(folder: Path) -> bool:  # a report's marker in it or in a folder between it and `top`
            while not (folder / cls.REPORT_MARKER).exists():
                if folder == top:
                    return False
                folder = folder.parent
            return True

        return [
            cls(p.parent) for p in sorted(top.rglob(cls.CONFIG)) if cls(p.parent).is_run() and not in_report(p.parent)
        ]

    def lock(self) -> FolderLock:
        """The folder's exclusive lock (a context manager), taken before anything in it is read
        or written."""
        return FolderLock(self.path)

    def check_free(self) -> None:
        """The lock's refusal of a folder another process holds, now, taking nothing: a command
        asks before it loads torch and its method (seconds to minutes), then takes the lock as
        ever. A shared lock is tried and dropped at once; a lock file that is not a regular file
        is left for the lock itself to refuse with its reason."""
        lock = FolderLock(self.path)  # only its file and its message: nothing is taken
        try:
            fd = os.open(lock.path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
        except OSError:
            return  # no lock file: nobody holds the folder
        try:
            if stat.S_ISREG(os.fstat(fd).st_mode):
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)  # dropped when fd closes
        except BlockingIOError:
            raise lock.busy_error(os.read(fd, 4096).decode("utf-8", "replace")) from None
        finally:
            os.close(fd)

    def run_config(self, required: bool = True) -> RunConfig | None:
        """The run's record (RunConfig.read: a ValueError naming the file when it is missing or
        unusable); required=False: None for a folder without one (RunConfig.read_if_present)."""
        return RunConfig.read(self.config_path) if required else RunConfig.read_if_present(self.config_path)

    def write_config(self, config: RunConfig | dict) -> Path:
        return save_yaml(config.as_dict() if isinstance(config, RunConfig) else config, self.config_path)

    def cache(self) -> MatchCache:
        return MatchCache(self.matches_path)

    def clear(self) -> None:
        """Remove a run's matches and results (--overwrite); the folder and foreign files stay. A
        link at viz/ is refused first, so that nothing is removed when the drawings cannot be."""
        refuse_link(self.viz_dir)
        self.cache().clear()
        for name in self.RESULTS:
            (self.path / name).unlink(missing_ok=True)
        remove_folder(self.viz_dir, ignore_errors=True)

    def previous(self, identity: dict | None, benchmark: str, eval_only: bool = False,
                 changes=None, console=None) -> RunConfig | None:
        """The record of the matches already here, or None for a new folder; a ValueError when
        they were made otherwise (another benchmark, or an identity that `changes(before, now)`
        finds different: method.identity_changes) and this is not --eval-only.

        Settings are refused only where they would mix with matches: a folder whose run wrote
        none (it failed before its first pair: weights not found, a plugin that did not load)
        takes the new settings, its old record is removed, and `console` is told so."""
        previous = self.run_config(required=False)
        if previous is None:
            return None
        before = previous.identity
        if before is None and "match_options" in previous.record and not eval_only:
            # Made by e3cm-bench before MethodSpec: its record lacks what the identity now holds
            # (the weights' hash, the seed), so its matches cannot be trusted to resume.
            raise ValueError(f"{self.config_path}: made by an older e3cm-bench (no 'identity'); --eval-only "
                             "re-evaluates it, --overwrite replaces its matches")
        if eval_only or before is None or identity is None:
            return previous
        changed = (
            list(changes(before, identity)) if changes is not None else ([] if before == identity else ["identity"])
        )
        if previous.benchmark != benchmark:
            changed.insert(0, "benchmark")
        if changed and not self.holds_matches():
            if console is not None:
                console.print(f"{self.path}: holds no matches of its earlier settings ({', '.join(changed)}); "
                              "starting anew with these", markup=False, highlight=False, soft_wrap=True)
            self.clear()
            return None
        if changed:
            differences = changed_values({"benchmark": previous.benchmark, **before},
                                         {"benchmark": benchmark, **identity}, changed, previous.matcher)
            raise ValueError(f"{self.config_path}: the matches in this folder were made with other settings "
                             f"({differences}); pass --overwrite to replace them or choose another --out")
        return previous

    # Settings a matcher resolves when it is built, not in the identity: `auto` there may resolve
    # otherwise in another version (VGG19's fp32 layout became channels_last), and the maps with it.
    RESOLVED_AT_BUILD = ("memory_format",)

    def check_resolved(self, before: dict | None, now: dict) -> None:
        """Refuse to resume a folder whose matches were made with a setting that resolved otherwise
        (recorded in its config.yaml `matcher`; records without it are not checked)."""
        changed = [f"{key} {before[key]} -> {now[key]}" for key in self.RESOLVED_AT_BUILD
                   if before and key in before and key in now and before[key] != now[key]]
        if changed:
            raise ValueError(
                f"{self.config_path}: the matches in this folder were made with the backbone run otherwise "
                f"({', '.join(changed)}; the maps round differently); pass --overwrite to replace them or choose "
                "another --out"
            )

    def check_imported(self, before: RunConfig, benchmark: str, identity: dict, files: dict | None,
                       done: set[str]) -> None:
        """Refuse to add to matches imported from other sources. files: each pair's file's hash,
        for a source of one file per pair (npz), which may gain or fix the files of pairs not
        imported yet (a resume after a bad pair); those already imported must be the same files."""
        path = self.config_path
        if before.benchmark != benchmark:
            raise ValueError(f"{path}: this folder holds a {before.benchmark} run; choose another --out")
        old, new = (before.identity or {}).get("imported") or {}, identity["imported"]
        if files is not None and old.get("format") == new["format"]:
            recorded = before.imported_files or {}
            changed = sorted(n for n in done if recorded.get(f"{n}.npz") != files.get(f"{n}.npz"))
            if not changed:
                return
            why = f"{len(changed)} imported pair file(s) changed since (first: {changed[0]}.npz)"
        elif old == new:
            return
        else:
            why = "the matches in this folder came from elsewhere (imported)"
        raise ValueError(f"{path}: {why}; pass --overwrite to replace them or choose another --out")

    def check_frames(self, before: RunConfig | None, root: str) -> None:
        """A calibration's: refuse matches made from another sequence's frames."""
        if before is not None and (before.sequence or {}).get("root") != root:
            raise ValueError(f"{self.config_path}: the matches in this folder were made from other frames "
                             f"({(before.sequence or {}).get('root')}); pass --overwrite or choose another --out")

    def check_shards(self, configs: dict[tuple[int, int], RunConfig]) -> None:
        """A merge's: the shards' records (by (K, N)) must come from one command."""
        n = next(iter(configs))[1]
        first = configs[(1, n)]
        for (k, _), config in sorted(configs.items()):
            for key in ("benchmark", "identity", "dataset_load", "evaluation"):
                if getattr(config, key) != getattr(first, key):
                    raise ValueError(
                        f"{self.shard((k, n)).config_path}: its {key} differs from shard 1-of-{n}'s "
                        f"({changed_values(first.record, config.record, [key])}); shards of one run must be made "
                        "with one command"
                    )

    def holds_matches(self) -> bool:
        """Whether any pair's matches (or a matcher's failure on it) were written here; a block of
        the cache that cannot be read counts as holding some."""
        cache = self.cache()
        return bool(cache.names()) or bool(cache.damaged)

    def resume(self, pairs, console=None) -> tuple[MatchCache, list]:
        """The cache and the pairs it still lacks (an interrupted run resumes at them); a block of
        the cache that HDF5 cannot read is said, and its lost pairs are matched again."""
        from e3cm_bench.storage.cache import BLOCK_PAIRS

        cache = self.cache()
        done = set(cache.names())  # one pass over the files, not one open per pair
        if done and not self.config_path.exists():
            # matches whose record is gone: what made them (a matcher, an import) is unknown
            raise ValueError(f"{self.matches_path}: holds the matches of {len(done)} pairs but {self.CONFIG} is "
                             "missing, so what made them is unknown; pass --overwrite to replace them or choose "
                             "another --out")
        for block in cache.damaged:
            if console is not None:
                console.print(f"warning: {block} is damaged (unreadable); its pairs (at most {BLOCK_PAIRS}) will be "
                              "matched again into a new file; the damaged file is left as it is", markup=False)
        return cache, [p for p in pairs if p.name not in done]


def changed_values(before: dict, now: dict, keys: list[str], built: dict | None = None) -> str:
    """Each setting of `keys` that differs, with the folder's value and this run's:
    'settings.ratio 0.8 -> 0.9, max_side 640 -> 320' (a mapping's changed entries one by one;
    a plugin's code hash as 'plugin code: sha256 8aa51a115606... -> b3d626dbaa42...'). built:
    the folder's record of the matcher as built (config.yaml `matcher`): a setting its identity
    lacks (not given: the default) is shown with the value it was built with, '1.0 (default)',
    never 'none', which config.yaml contradicts."""
    parts = []
    for key in keys:
        old, new = before.get(key), now.get(key)
        if isinstance(old, dict) and isinstance(new, dict):
            default = built if key == "settings" and isinstance(built, dict) else {}
            was = {k: f"{_shown(default[k])} (default)" if k not in old and k in default else _shown(old.get(k))
                   for k in set(old) | set(new)}
            parts += [f"{LABELS.get(f'{key}.{k}', f'{key}.{k}')} {was[k]} -> {_shown(new.get(k))}"
                      for k in sorted(set(old) | set(new), key=str) if old.get(k) != new.get(k)]
        else:
            parts.append(f"{LABELS.get(key, key)} {_shown(old)} -> {_shown(new)}")
    return ", ".join(parts)


# How a setting is named in a refusal where its key alone would not say what changed.
LABELS = {"plugin.sha256": "plugin code: sha256", "weights_sha256": "weights: sha256"}
SHA256 = re.compile(r"\b([0-9a-f]{12})[0-9a-f]{52}\b")


def _shown(value) -> str:
    """A recorded value in a message: 'none' when absent; a sha256 as its first 12 digits (as
    git shows a commit); another long value cut to its start."""
    if value is None:
        return "none"
    text = SHA256.sub(r"\1...", str(value))
    return text if len(text) <= 40 else text[:37] + "..."
