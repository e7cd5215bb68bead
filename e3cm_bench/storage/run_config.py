"""A run's config.yaml: its one writer and its one reader (`RunConfig`), a plain record that
imports only the ground floor (what it rebuilds, a benchmark, its settings, a method, the
run's pairs, is benchmarks/from_record.py's).

Every module that needs what a run recorded (its benchmark, its identity, its evaluation
settings, where its pairs came from, the environment its numbers were made in, a shard's
command) asks a `RunConfig` read with `RunConfig.read`; none reads the YAML itself, so that
what a missing, broken or incomplete record means is decided here, in one line naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

from e3cm_bench.ground.files import load_yaml
from e3cm_bench.ground.machine import package_versions, run_environment

# The record's file in a run folder (RunFolder.config_path names it from here).
CONFIG_FILE = "config.yaml"
# What a dataset_load's options may hold besides a benchmark's own options: --sample's draw
# (Benchmark.load_dataset takes them among the options).
SAMPLE_OPTIONS = ("sample", "sample_seed")


@dataclass
class RunConfig:
    """What config.yaml records, in the order it is written. The optional blocks are written
    only where they apply (a shard, a merge, an import, a calibration)."""

    benchmark: str | None
    method: str
    identity: dict | None
    matcher: dict | None = None
    device: str | None = None
    dataset: dict = field(default_factory=dict)
    evaluation: dict | None = None
    # Where the numbers were made (this stage's); not part of the identity that decides whether
    # a folder may be resumed.
    versions: dict = field(default_factory=package_versions)
    environment: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)
    feature_reuse: dict | None = None
    # what the user gave, by section, in the flags' and the YAML's names (pipeline/resolve.py), and its
    # digest as written: rerun resolves `given`, and tells an edited one by the digest
    given: dict | None = None
    given_digest: str | None = None
    dataset_load: dict | None = None
    shard: dict | None = None
    shards: dict | None = None
    imported_files: dict | None = None
    pixel_origin_check: dict | None = None  # an import's half-pixel check (interchange.pixels)
    # a calibration's (apps/calibration/run.py): the sequence and its settings
    command: str | None = None
    sequence: dict | None = None
    calibration: dict | None = None
    # Not written: the file a record was read from (named in errors), and the record as read,
    # keys of older e3cm-bench versions included (RunFolder.previous reads `match_options`).
    path: Path | None = field(default=None, repr=False, compare=False)
    record: dict | None = field(default=None, repr=False, compare=False)

    OPTIONAL = ("feature_reuse", "given", "given_digest", "dataset_load", "shard", "shards", "imported_files",
                "pixel_origin_check", "command", "sequence", "calibration")
    UNWRITTEN = ("path", "record")

    def __post_init__(self) -> None:
        if self.given is not None and self.given_digest is None:  # a new record's; a read one keeps its own
            self.given_digest = given_digest(self.given)

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in self.UNWRITTEN
                and not (f.name in self.OPTIONAL and getattr(self, f.name) is None)}

    @classmethod
    def record_keys(cls) -> set[str]:
        """The top-level keys of config.yaml this version reads."""
        return {f.name for f in fields(cls)} - set(cls.UNWRITTEN)

    @classmethod
    def from_dict(cls, record: dict, path: str | Path | None = None) -> RunConfig:
        """The record as a RunConfig (keys it does not know kept in `record` only)."""
        names = cls.record_keys()
        values = {k: v for k, v in record.items() if k in names}
        for name, default in (("benchmark", None), ("method", ""), ("identity", None)):
            values.setdefault(name, default)
        for name in ("dataset", "environment", "timing", "versions"):
            if not isinstance(values.get(name), dict):
                values[name] = {}  # absent (an older record; not this package's versions), or no mapping
        return cls(**values, path=None if path is None else Path(path), record=dict(record))

    # ---- reading
    @classmethod
    def read(cls, path: str | Path) -> RunConfig:
        """A run's config.yaml (or that of the run folder `path`); ValueError in one line naming
        the file when it is missing, unreadable, not a mapping, or records no ``benchmark``."""
        path = _config_file(path)
        record = load_yaml(path, what="config.yaml (every run folder needs one)")
        if "benchmark" not in record:
            raise ValueError(f"{path}: records no benchmark (not a run's config.yaml, or cut short)")
        return cls.from_dict(record, path)

    @classmethod
    def read_if_present(cls, path: str | Path) -> RunConfig | None:
        """`read`, or None where the file does not exist (a new folder); its other problems are errors."""
        path = _config_file(path)
        if not path.exists():
            return None
        record = load_yaml(path, what="run record (config.yaml)")
        return cls.from_dict(record, path)

    @property
    def where(self) -> str:
        """The file named in errors."""
        return str(self.path) if self.path is not None else "the run's config.yaml"

    # ---- what readers need
    @property
    def protocol(self) -> str:
        """The evaluation protocol's name (method/protocols.py)."""
        return (self.evaluation or {}).get("protocol", "default")

    @property
    def matcher_name(self) -> str | None:
        """The registered matcher that made the run (identity.matcher; an import's method name), or None."""
        return (self.identity or {}).get("matcher") or self.method or None

    @property
    def limit(self) -> int | None:
        """The run's --limit (the first N pairs of its dataset), or None."""
        limit = self.dataset.get("limit")
        return limit if isinstance(limit, int) and not isinstance(limit, bool) and limit > 0 else None

    @property
    def shard_key(self) -> tuple[int, int] | None:
        """(K, N) of a shard's record, else None."""
        shard = self.shard
        return (int(shard["index"]), int(shard["count"])) if isinstance(shard, dict) else None

    @property
    def shard_complete(self) -> bool:
        return bool((self.shard or {}).get("complete"))

    @property
    def rerun_command(self) -> str | None:
        """The command line that runs (or resumes) this shard, as it recorded it (shards.shard_command)."""
        return (self.shard or {}).get("command") or None

    # ---- writing
    @staticmethod
    def dataset_load_of(root: str | Path, skip_bad: bool, options: dict | None) -> dict:
        """How to load the same pairs again (merging shards and exporting need the ground truth),
        with absolute paths: a merge may run in another working directory (a SLURM task's)."""
        from e3cm_bench.ground.files import absolute_paths

        return {"root": str(Path(root).resolve()), "skip_bad": skip_bad,
                "options": {k: absolute_paths(v) for k, v in (options or {}).items() if v is not None}}

    @staticmethod
    def environment_now() -> dict:
        """The environment block: CPU dispatch, threads, allocator (machine.run_environment)."""
        from e3cm_bench.ground.devices import allocator

        return {**run_environment(), "allocator": allocator()}


def given_digest(given: dict) -> str:
    """A record's `given` as a short sha256 of its YAML (keys sorted): an edit changes it."""
    import hashlib

    import yaml

    return hashlib.sha256(yaml.safe_dump(given, sort_keys=True).encode()).hexdigest()[:16]


def _config_file(path: str | Path) -> Path:
    """The config.yaml at `path`, or that of the run folder `path`."""
    path = Path(path)
    return path / CONFIG_FILE if path.is_dir() else path
