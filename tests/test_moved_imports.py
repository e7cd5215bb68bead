"""Old module paths keep working for one release with a DeprecationWarning naming the new import
(issue 71, item 6): `from e3cm_bench.matches import Matches`, the earlier plugin guide's path,
was an ImportError with no hint and broke two plugins."""

from __future__ import annotations

import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

import e3cm_bench
from e3cm_bench.ground.moved import MOVED


def test_the_plugin_guides_old_import_warns_and_works():
    sys.modules.pop("e3cm_bench.matches", None)
    with pytest.warns(DeprecationWarning, match="from e3cm_bench import Matches"):
        from e3cm_bench.matches import Matches
    assert Matches is e3cm_bench.Matches


def test_a_script_importing_the_old_path_is_told_the_new_one():
    done = subprocess.run([sys.executable, "-c", "from e3cm_bench.matches import Matches; print('imported')"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "imported" in done.stdout
    assert "DeprecationWarning: e3cm_bench.matches moved" in done.stderr and "from e3cm_bench import Matches" in done.stderr


def test_old_packages_reach_their_submodules():
    with pytest.warns(DeprecationWarning, match="e3cm_bench.apps.synth.textures"):
        textures = importlib.import_module("e3cm_bench.synth.textures")
    assert textures.procedural_scene is importlib.import_module("e3cm_bench.apps.synth.textures").procedural_scene


@pytest.mark.parametrize("old", sorted(MOVED))
def test_every_moved_name_leads_to_a_module_and_none_still_exists(old):
    assert importlib.util.find_spec(MOVED[old]) is not None, MOVED[old]
    where = Path(e3cm_bench.__file__).parent.joinpath(*old.split(".")[1:])
    assert not where.with_suffix(".py").exists() and not (where / "__init__.py").exists(), where


def test_a_module_that_exists_is_never_intercepted():
    import e3cm_bench.ground.matches as real

    assert real.__spec__.loader is not e3cm_bench.ground.moved.FINDER


def test_a_renamed_name_warns_and_leads_to_the_new_one():
    """A name renamed inside a module that stayed (RENAMED): the old name still imports, with a
    DeprecationWarning naming the new import; a name never there is Python's AttributeError."""
    from e3cm_bench.ground.moved import RENAMED

    for (module, old), new in RENAMED.items():
        with pytest.warns(DeprecationWarning, match=f"from {module} import {new}"):
            got = getattr(importlib.import_module(module), old)
        assert got is getattr(importlib.import_module(module), new)
    with pytest.raises(AttributeError, match="no attribute 'Protocl'"):
        importlib.import_module("e3cm_bench.method.protocols").Protocl


def test_a_name_moved_to_its_concepts_module_warns_and_leads_to_it():
    """A name moved out of a module that stayed (MOVED_NAMES: ground/files.py's lock and machine
    facts): `from e3cm_bench.ground.files import FolderLock` still works, with a DeprecationWarning
    naming the new import; a name never there is Python's AttributeError."""
    from e3cm_bench.ground.moved import MOVED_NAMES

    assert MOVED_NAMES
    for (module, name), home in MOVED_NAMES.items():
        with pytest.warns(DeprecationWarning, match=f"from {home} import {name}"):
            got = getattr(importlib.import_module(module), name)
        assert got is getattr(importlib.import_module(home), name)
    with pytest.raises(AttributeError, match="no attribute 'FolderLok'"):
        importlib.import_module("e3cm_bench.ground.files").FolderLok
