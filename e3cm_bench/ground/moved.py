"""Module paths that moved, kept importable for one release (issue 71): an import of an old path
(`from e3cm_bench.matches import Matches`, the path the earlier plugin guide used) gets the new
module's names with a DeprecationWarning naming the new import, instead of an ImportError with
no hint. `MOVED` is the old name -> the new, read from the repository's renames (git log
--diff-filter=R); names a package of today still holds are not in it. The stable names a plugin
needs are importable from `e3cm_bench` itself (docs/own-matcher.md, "Stable imports").

The finder sits last on sys.meta_path (e3cm_bench/__init__.py installs it): a module that
exists is always found first; only a name that no longer exists reaches it.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import types
import warnings

MOVED = {
    "e3cm_bench.archives": "e3cm_bench.data.archives",
    "e3cm_bench.backbone_names": "e3cm_bench.backbones.names",
    "e3cm_bench.backbone_specs": "e3cm_bench.backbones.specs",
    "e3cm_bench.benchmarks.protocols": "e3cm_bench.method.protocols",
    "e3cm_bench.benchmarks.records": "e3cm_bench.benchmarks.from_record",
    "e3cm_bench.benchmarks.sfm": "e3cm_bench.sfm.benchmark",
    "e3cm_bench.cache": "e3cm_bench.storage.cache",
    "e3cm_bench.calibrate": "e3cm_bench.apps.calibration.run",
    "e3cm_bench.calibration": "e3cm_bench.apps.calibration.extrinsics",
    "e3cm_bench.calibration.extrinsics": "e3cm_bench.apps.calibration.extrinsics",
    "e3cm_bench.calibration.run": "e3cm_bench.apps.calibration.run",
    "e3cm_bench.check": "e3cm_bench.gate.check",
    "e3cm_bench.compare_runs": "e3cm_bench.reporting.compare",
    "e3cm_bench.data_folder": "e3cm_bench.data.folder",
    "e3cm_bench.datasets.synthetic": "e3cm_bench.apps.synth.textures",
    "e3cm_bench.demo": "e3cm_bench.apps.demo",
    "e3cm_bench.devices": "e3cm_bench.ground.devices",
    "e3cm_bench.download": "e3cm_bench.data.download",
    "e3cm_bench.download_http": "e3cm_bench.data.http",
    "e3cm_bench.ensemble": "e3cm_bench.gate.ensemble",
    "e3cm_bench.estimators": "e3cm_bench.geometry.estimators",
    "e3cm_bench.evaluate": "e3cm_bench.pipeline.evaluate",
    "e3cm_bench.experiments": "e3cm_bench.pipeline.experiments",
    "e3cm_bench.files": "e3cm_bench.ground.files",
    "e3cm_bench.formats": "e3cm_bench.drawing.formats",
    "e3cm_bench.images": "e3cm_bench.ground.images",
    "e3cm_bench.imported": "e3cm_bench.pipeline.imported",
    "e3cm_bench.interchange.export": "e3cm_bench.pipeline.export",
    "e3cm_bench.intervals": "e3cm_bench.benchmarks.intervals",
    "e3cm_bench.launch": "e3cm_bench.pipeline.launch",
    "e3cm_bench.library_errors": "e3cm_bench.ground.library_errors",
    "e3cm_bench.matchers.peers.wheels": "e3cm_bench.ground.wheels",
    "e3cm_bench.matches": "e3cm_bench.ground.matches",
    "e3cm_bench.metrics": "e3cm_bench.geometry.metrics",
    "e3cm_bench.noise_gate": "e3cm_bench.gate.noise_gate",
    "e3cm_bench.options": "e3cm_bench.method.options",
    "e3cm_bench.pair_order": "e3cm_bench.pipeline.pair_order",
    "e3cm_bench.perturb": "e3cm_bench.stats.perturb",
    "e3cm_bench.plots": "e3cm_bench.drawing.plots",
    "e3cm_bench.report": "e3cm_bench.reporting.tables",
    "e3cm_bench.reporting.check": "e3cm_bench.gate.check",
    "e3cm_bench.reporting.ensemble": "e3cm_bench.gate.ensemble",
    "e3cm_bench.reporting.environment": "e3cm_bench.storage.environment",
    "e3cm_bench.reporting.formats": "e3cm_bench.drawing.formats",
    "e3cm_bench.reporting.noise_gate": "e3cm_bench.gate.noise_gate",
    "e3cm_bench.reporting.plots": "e3cm_bench.drawing.plots",
    "e3cm_bench.reporting.tolerances": "e3cm_bench.gate.tolerances",
    "e3cm_bench.reportsite": "e3cm_bench.reporting.site",
    "e3cm_bench.run.address_space": "e3cm_bench.pipeline.address_space",
    "e3cm_bench.run.config": "e3cm_bench.storage.run_config",
    "e3cm_bench.run.driver": "e3cm_bench.pipeline.driver",
    "e3cm_bench.run.folder": "e3cm_bench.storage.folder",
    "e3cm_bench.run.launch": "e3cm_bench.pipeline.launch",
    "e3cm_bench.run.pair": "e3cm_bench.pipeline.pair",
    "e3cm_bench.run.progress": "e3cm_bench.pipeline.progress",
    "e3cm_bench.run.shards": "e3cm_bench.pipeline.shards",
    "e3cm_bench.run.stage": "e3cm_bench.pipeline.stage",
    "e3cm_bench.runner": "e3cm_bench.pipeline.runner",
    "e3cm_bench.sfm.reconstruct": "e3cm_bench.sfm.mapper",
    "e3cm_bench.shards": "e3cm_bench.pipeline.shards",
    "e3cm_bench.storage.record": "e3cm_bench.storage.run_config",
    "e3cm_bench.suggest": "e3cm_bench.ground.suggest",
    "e3cm_bench.synth": "e3cm_bench.apps.synth",
    "e3cm_bench.synth.layouts": "e3cm_bench.apps.synth.layouts",
    "e3cm_bench.synth.multiview": "e3cm_bench.apps.synth.multiview",
    "e3cm_bench.synth.scene": "e3cm_bench.apps.synth.scene",
    "e3cm_bench.synth.stereo": "e3cm_bench.apps.synth.stereo",
    "e3cm_bench.synth.textures": "e3cm_bench.apps.synth.textures",
    "e3cm_bench.viz": "e3cm_bench.drawing.matches",
}
# What to write instead, where the old path's names are the package's own public API.
PUBLIC = {"e3cm_bench.matches": "from e3cm_bench import Matches"}
# Names that were renamed inside a module that stayed: (module, old name) -> the new name. The
# module's own `__getattr__` calls `renamed` for a name it lacks.
RENAMED = {
    ("e3cm_bench.method.protocols", "Protocol"): "ReferenceProtocol",
    ("e3cm_bench.sfm.protocol", "Protocol"): "ReconstructionProtocol",
}


# Names that moved from a module that stayed to another, the concept's own (issue 78: modules split
# where their concepts part): (module, name) -> the module that holds it now. The old module's
# `__getattr__` calls `moved_name` for a name it lacks.
_MACHINE = ("PACKAGES", "ISA_VARIABLES", "CPU_FLAGS", "BF16_FLAGS", "package_versions", "cpu_info", "cpu_isa",
            "run_environment")
MOVED_NAMES = {
    **{("e3cm_bench.ground.files", name): "e3cm_bench.ground.machine" for name in _MACHINE},
    **{("e3cm_bench.ground.files", name): "e3cm_bench.ground.locks" for name in ("FolderLock", "writable_folder")},
    **{("e3cm_bench.benchmarks.base", name): "e3cm_bench.benchmarks.eval_settings"
       for name in ("MAX_INTERVAL_SEEDS", "MAX_REPEATS")},
    **{("e3cm_bench.pipeline.stage", name): "e3cm_bench.pipeline.match_options"
       for name in ("ON_MATCHER_ERROR", "resolve_pair_timeout")},
    **{("e3cm_bench.matchers.feature_cache", name): "e3cm_bench.matchers.spill"
       for name in ("auto_spill_mb", "SPILL_SHARE", "SPILL_CAP_MB")},
    **{("e3cm_bench.backbones.loading", name): "e3cm_bench.backbones.pyramid"
       for name in ("REDUCED_DTYPES", "COPY_BAND", "channels_last", "cast_weights", "pixel_rows",
                    "channel_first_float")},
}


def moved_name(module: str, name: str):
    """The object another module now holds under `name` (MOVED_NAMES), with a DeprecationWarning
    naming the new import; else what `renamed` gives."""
    home = MOVED_NAMES.get((module, name))
    if home is None:
        return renamed(module, name)
    warnings.warn(f"{module}.{name} moved: from {home} import {name} (the old import works until the next "
                  "release)", DeprecationWarning, stacklevel=3)
    return getattr(importlib.import_module(home), name)


def renamed(module: str, name: str):
    """The object `module` now holds under the new name of `name`, with a DeprecationWarning naming
    it; an AttributeError as Python gives it for a name that was never there."""
    new = RENAMED.get((module, name))
    if new is None:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    warnings.warn(f"{module}.{name} was renamed {new}: from {module} import {new} "
                  "(the old name works until the next release)", DeprecationWarning, stacklevel=3)
    return getattr(importlib.import_module(module), new)


def new_import(old: str) -> str:
    return PUBLIC.get(old, f"import {MOVED[old]}")


class _Moved(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds a moved module's old name; its module forwards every name to the new module."""

    def find_spec(self, name, path=None, target=None):
        return importlib.util.spec_from_loader(name, self, is_package=True) if name in MOVED else None

    def create_module(self, spec):
        warnings.warn(f"{spec.name} moved to {MOVED[spec.name]}: {new_import(spec.name)} "
                      "(the old path works until the next release)", DeprecationWarning, stacklevel=2)
        target = importlib.import_module(MOVED[spec.name])
        module = types.ModuleType(spec.name, target.__doc__)
        module.__getattr__ = lambda attribute: getattr(target, attribute)
        module.__all__ = getattr(target, "__all__", [n for n in vars(target) if not n.startswith("_")])
        return module

    def exec_module(self, module) -> None:
        module.__path__ = []  # a package: `e3cm_bench.synth.textures` is found through `e3cm_bench.synth`


FINDER = _Moved()
