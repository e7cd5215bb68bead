"""The matcher registry: name -> MatcherEntry, the twin of the benchmark registry.

Three ways in, one `register`:
- built-ins (matchers/builtin.py) on the first lookup;
- plugins: packages that declare entries in the entry-point group ``e3cm_bench.matchers``
  (pyproject: ``[project.entry-points."e3cm_bench.matchers"] orb = "my_pkg:ENTRY"``); the
  object is a MatcherEntry, or a callable returning one or several;
- ``--matcher package.module:factory``: a module on the Python path, no packaging; the
  factory is a MatcherEntry, or a callable returning one or a Matcher.

A plugin that fails to load costs only itself: it is listed with its error, and asking for
it gives that error in one line. Models load when a matcher is built, never at lookup.

Entry points are imported only when they are needed: when a name that is not a built-in is
asked for, or when every matcher is listed (`e3cm-bench matchers`, `entries()`). A run of
`--matcher sift` imports no plugin, so a broken one cannot touch it. Each import (with the
call of its object) is bounded by PLUGIN_IMPORT_SECONDS (plugin_import.py; environment:
E3CM_BENCH_PLUGIN_TIMEOUT): it is first tried in a forked child process, which is killed at
the bound (a C call that holds the interpreter lock, such as a regular expression that never
ends, cannot be interrupted inside this process: no thread of it runs meanwhile); a plugin
whose child does not finish in time, or crashes, is listed as not loaded and never imported
here. Then it is imported here, in a daemon thread bounded the same way (the import must
happen in this process for its classes to be used; a consequence is that a plugin cannot
install signal handlers at import). ``sys.exit`` at import, or in a factory, is that
plugin's failure in one line, never the tool's exit; so is a factory that raises.

``--matcher package.module:factory`` comes from the Python path, else from the current folder,
where only that one module (or package) is taken from: the folder never joins ``sys.path``
(user_module.py). The names the user gave this way are passed to the processes this one starts
(--workers, SLURM shards: USER_MATCHERS_ENV), with the file each came from, which they import.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import os
from typing import Callable

from e3cm_bench.backbones.names import DEFAULT_BACKBONE
from e3cm_bench.ground.devices import check_device
from e3cm_bench.matchers.base import BACKBONE_SETTINGS, BackboneSettings, Matcher, MatcherEntry
from e3cm_bench.ground.suggest import did_you_mean
from e3cm_bench.matchers.guards import exit_text
from e3cm_bench.matchers.names import BUILTIN_MATCHERS
from e3cm_bench.matchers.plugin_code import built_with, code_sha256
from e3cm_bench.matchers.plugin_import import bounded, why
from e3cm_bench.matchers.user_module import importing

ENTRY_POINT_GROUP = "e3cm_bench.matchers"

_REGISTRY: dict[str, MatcherEntry] = {}
_BROKEN: dict[str, str] = {}  # plugin entry point -> why it did not load
_loaded = False
_plugins_loaded = False


# The package.module:factory names given by the user (--matcher, an experiment config), for the
# worker processes this one starts: set in the environment they inherit.
USER_MATCHERS_ENV = "E3CM_BENCH_USER_MATCHERS"


def register(entry: MatcherEntry, replace: bool = False) -> MatcherEntry:
    """Add a matcher; a name taken by another matcher is an error unless replace."""
    if not isinstance(entry, MatcherEntry):
        raise ValueError(f"register: expected a MatcherEntry, got {type(entry).__name__}")
    _load()
    if entry.name in _REGISTRY and not replace and _REGISTRY[entry.name] is not entry:
        raise ValueError(f"matcher {entry.name!r} is already registered ({_REGISTRY[entry.name].origin})")
    _REGISTRY[entry.name] = entry
    return entry


def unregister(name: str) -> None:
    _REGISTRY.pop(name, None)


def matcher_names() -> list[str]:
    """Every registered matcher's name (built-ins first, then plugins, in load order)."""
    _load(plugins=True)
    return list(_REGISTRY)


def entries() -> list[MatcherEntry]:
    _load(plugins=True)
    return list(_REGISTRY.values())


def broken_plugins() -> dict[str, str]:
    """Plugin entry points that failed to load: name -> one line."""
    _load(plugins=True)
    return dict(_BROKEN)


def get_matcher(name: str, allow_import: bool = False) -> MatcherEntry:
    """The entry of `name`: a registered matcher, or ``module:factory`` (imported on first use).

    allow_import=True only for a name the user gave (--matcher, an experiment config, the API's
    MethodSpec.create): importing ``module:factory`` runs its code. A name read from a run
    folder's config.yaml is data and resolves among registered matchers only (those already
    imported in this process included); ``this:x`` there is an unknown matcher, imported never.
    """
    _load()
    if name not in _REGISTRY and name not in _BROKEN and not (isinstance(name, str) and ":" in name):
        _load(plugins=True)  # not a built-in: perhaps an installed plugin's
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name in _BROKEN:
        raise ValueError(f"matcher {name!r}: {_BROKEN[name]}")
    if isinstance(name, str) and ":" in name and (allow_import or name in user_named()):
        entry = _from_module(name)
        _REGISTRY[name] = entry
        _remember_user_named(name)
        return entry
    if isinstance(name, str) and ":" in name:
        raise ValueError(f"matcher {name!r} is not registered here; a package.module:factory is imported only when "
                         "named by --matcher (or an experiment config), never from a run folder's files")
    raise _unknown(name, list(_REGISTRY))


def _unknown(name: str, names: list[str]) -> ValueError:
    return ValueError(f"unknown matcher {name!r}{did_you_mean(name, names)}; choose one of: {', '.join(names)} "
                      "(or a plugin's, or package.module:factory)")


def check_name(name: str) -> None:
    """get_matcher's refusal of an unknown name, without importing anything: the built-ins by
    name (names.py), the installed plugins by their entry points' names, the entries this process
    registered, and any ``module:factory`` pass (each is checked when it is loaded). A command
    asks this before it loads torch, so that a mistyped --matcher is refused at once."""
    if not isinstance(name, str) or ":" in name or name in BUILTIN_MATCHERS or name in _REGISTRY or name in _BROKEN:
        return
    plugins = [point.name for point in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)]
    if name not in plugins:
        raise _unknown(name, list(dict.fromkeys([*BUILTIN_MATCHERS, *_REGISTRY, *plugins])))


def resolve(name: str, settings: dict, allow_import: bool = False) -> tuple[MatcherEntry, dict]:
    """A preset's base entry and its settings with the preset's; other entries as they are.
    A setting given against the preset's is an error (e3cm-ransac with estimator top8).
    allow_import: as get_matcher's."""
    entry = get_matcher(name, allow_import)
    if entry.preset_of is None:
        return entry, dict(settings)
    clash = sorted(k for k, v in entry.preset.items() if k in settings and settings[k] != v)
    if clash:
        fixed = ", ".join(f"{k}={entry.preset[k]}" for k in clash)
        raise ValueError(f"{name} is {entry.preset_of} with {fixed}; use --matcher {entry.preset_of} to change it")
    return get_matcher(entry.preset_of), {**settings, **entry.preset}


def split_settings(entry: MatcherEntry, settings: dict) -> tuple[dict, dict]:
    """(the matcher's own settings, its backbone settings)."""
    own = {k: v for k, v in settings.items() if not (entry.needs_backbone and k in BACKBONE_SETTINGS)}
    return own, {k: v for k, v in settings.items() if k not in own}


def check_settings(name: str, settings: dict):
    """The validated settings instance of matcher `name` (builds no model); a one-line
    ValueError where `settings` do not fit it."""
    entry = get_matcher(name)
    own, net = split_settings(entry, settings)
    if net:
        BackboneSettings(**net)
    return entry.make_settings(own)


def built_settings(name: str, settings: dict) -> dict | None:
    """What a plugin's matcher is built from (plugin_code.built_with), for config.yaml where the
    matcher says nothing of its settings itself; None for a built-in (its config() says it all)."""
    entry, settings = resolve(name, settings or {})
    if entry.origin == "built-in":
        return None
    own, _ = split_settings(entry, settings)
    return built_with(entry, entry.make_settings(own))


def build_matcher(
    name: str = "e3cm",
    backbone: str = DEFAULT_BACKBONE,
    weights: str | None = None,
    device: str = "cpu",
    pretrained: bool = True,
    settings: dict | None = None,
    loaded: dict | None = None,
) -> Matcher:
    """A matcher by name (a preset's settings added). `settings` holds the matcher's own fields
    and, for a matcher on a backbone, BackboneSettings' fields. loaded: backbones built
    before, by what they were built from; a matcher asking for the same one reuses it
    instead of loading the weights again."""
    entry, settings = resolve(name, settings or {})
    own, net_settings = split_settings(entry, settings)
    instance = entry.make_settings(own)
    if entry.model:
        entry.check_requirements()
        check_device(device)
        return _built(entry, lambda: entry.build(instance, device=device, weights=weights, pretrained=pretrained))
    if not entry.needs_backbone:
        return _built(entry, lambda: entry.build(instance))
    from e3cm_bench.backbones.loading import load_backbone

    net_settings = BackboneSettings(**net_settings)
    check_device(device)
    key = (backbone, str(weights), pretrained, device, net_settings.num_levels, net_settings.precision,
           net_settings.memory_format)
    net = None if loaded is None else loaded.get(key)
    if net is None:
        net = load_backbone(backbone, weights=weights, pretrained=pretrained, device=device,
                            num_levels=net_settings.num_levels, precision=net_settings.precision,
                            memory_format=net_settings.memory_format)
        if loaded is not None:
            loaded[key] = net
    return _built(entry, lambda: entry.build(instance, net=net, channel_order=net_settings.channel_order))


def _built(entry: MatcherEntry, build: Callable[[], Matcher]) -> Matcher:
    """entry.build(...), where a factory that calls sys.exit is that matcher's failure in one
    line, and so is a plugin's factory that raises (the built-ins' exceptions pass as they
    are: the callers already say what they mean). E3CM_BENCH_DEBUG=1 shows its traceback."""
    try:
        return build()
    except SystemExit as exc:
        raise ValueError(f"matcher {entry.name} ({entry.origin}): building it called {exit_text(exc)}") from None
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:  # noqa: BLE001 - a plugin's factory may raise anything
        if entry.origin == "built-in":
            raise
        reason = " ".join(str(exc).split()) or "(no message)"
        raise ValueError(f"matcher {entry.name} ({entry.origin}): its factory raised {type(exc).__name__}: "
                         f"{reason}") from exc


def user_named() -> set[str]:
    """The package.module:factory names the user gave, here or in the process that started this one."""
    return {n for n in os.environ.get(USER_MATCHERS_ENV, "").split(",") if n}


def _remember_user_named(name: str) -> None:
    # a module name holds no comma; a factory's neither
    os.environ[USER_MATCHERS_ENV] = ",".join(sorted(user_named() | {name}))


# --------------------------------------------------------------------------- loading


def _load(plugins: bool = False) -> None:
    """The built-ins on the first call; the installed plugins too when `plugins` (once)."""
    global _loaded, _plugins_loaded
    if not _loaded:
        _loaded = True
        from e3cm_bench.matchers.builtin import BUILTIN
        from e3cm_bench.matchers.peers import PEERS

        for entry in (*BUILTIN, *PEERS):  # the peers' entries import neither kornia nor transformers
            _REGISTRY[entry.name] = entry
    if plugins and not _plugins_loaded:
        _plugins_loaded = True
        load_plugins()


def load_plugins() -> None:
    """Register every entry point of the group (again: a test may add a distribution)."""
    for point in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        dist = getattr(point, "dist", None)
        origin = f"plugin {dist.name} {dist.version}" if dist is not None else f"plugin {point.value}"
        source = {"package": dist.name, "version": dist.version} if dist is not None else {"entry_point": point.value}
        try:
            found = bounded(lambda point=point: _entries_of(point.load(), point.value), point.value)
            # the code it runs (an editable install keeps its version through every edit)
            source["sha256"] = code_sha256(point.module)
        except KeyboardInterrupt:
            raise
        except (Exception, SystemExit) as exc:  # noqa: BLE001 - a broken plugin must not break the toolkit
            _BROKEN[point.name] = f"plugin {point.value} ({origin.split(' ', 1)[1]}) failed to load: {why(exc)}"
            continue
        _BROKEN.pop(point.name, None)
        for entry in found:
            if entry.name in _REGISTRY and _REGISTRY[entry.name].origin == "built-in":
                _BROKEN[point.name] = (
                    f"plugin {point.value} ({origin.split(' ', 1)[1]}) tries to replace the built-in {entry.name!r}"
                )
                continue
            _REGISTRY[entry.name] = dataclasses.replace(entry, origin=origin, source=source)


def _entries_of(obj, where: str) -> list[MatcherEntry]:
    if callable(obj) and not isinstance(obj, MatcherEntry):
        obj = obj()
    found = [obj] if isinstance(obj, MatcherEntry) else list(obj) if isinstance(obj, (list, tuple)) else []
    if not found or not all(isinstance(e, MatcherEntry) for e in found):
        raise ValueError(f"{where}: expected a MatcherEntry (or a callable returning one or a list of them)")
    return found


def _from_module(name: str) -> MatcherEntry:
    module_name, _, attr = name.partition(":")
    try:
        with importing(module_name):  # from the Python path, else this one name from the current folder
            module = bounded(lambda: importlib.import_module(module_name), module_name)
    except KeyboardInterrupt:
        raise
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - one line, whatever the module does wrong
        raise ValueError(f"--matcher {name}: cannot import {module_name} ({why(exc)})") from None
    if not hasattr(module, attr):
        raise ValueError(f"--matcher {name}: module {module_name} has no {attr!r}")
    factory = getattr(module, attr)
    file = getattr(module, "__file__", None)
    source = {"module": module_name, "sha256": code_sha256(module_name)}
    origin = f"module {module_name}" + (f" ({file})" if file else "")
    if isinstance(factory, MatcherEntry):
        entry = factory
    elif callable(factory):
        try:
            made = factory()
        except SystemExit as exc:
            raise ValueError(f"--matcher {name}: {attr}() called {exit_text(exc)}") from None
        except Exception as exc:  # noqa: BLE001
            raise ValueError(f"--matcher {name}: {attr}() raised {type(exc).__name__}: {exc}") from None
        if isinstance(made, MatcherEntry):
            entry = made
        elif callable(getattr(made, "match", None)):
            def build(settings):
                return factory()

            build.factory = factory  # whose arguments config.yaml records (plugin_code.built_with)
            entry = MatcherEntry(name=attr, description=f"{attr}() of {module_name}", build=build)
        else:
            raise ValueError(f"--matcher {name}: {attr}() returned {type(made).__name__}, "
                             "expected a MatcherEntry or a matcher (an object with match(image0, image1))")
    else:
        raise ValueError(
            f"--matcher {name}: {attr} is a {type(factory).__name__}, expected a MatcherEntry or a factory"
        )
    return dataclasses.replace(entry, origin=origin, source=source)
