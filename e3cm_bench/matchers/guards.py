"""What the toolkit does around a plugin's code so that the plugin cannot end or freeze it.

A matcher is someone else's code called in our process. Three helpers keep its failures its own:

- ``no_exit(what)``: ``sys.exit`` inside a matcher's factory, ``match`` or ``config`` raises
  SystemExit, which no ``except Exception`` stops, so the whole tool would end with the
  plugin's exit code and no word. Inside the block it becomes a PluginExit (a RuntimeError)
  that the caller reports as that matcher's failure.
- ``describe_matcher(matcher)``: the matcher's ``config()`` as a dict YAML can write, or a
  one-line ValueError (it raised, exited, or returned an object YAML cannot represent).
- ``pair_time_limit(seconds, what)``: a per-pair bound on a matcher's ``match``
  (``--pair-timeout``). It uses SIGALRM, so it works in the main thread on POSIX, where the
  runner matches; the matcher is interrupted when control next returns to Python (a call
  into C that never returns cannot be interrupted in-process).
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator

import yaml

from ..files import yaml_plain


class PluginExit(RuntimeError):
    """A matcher's code called sys.exit (or raised SystemExit)."""


class PairTimeout(TimeoutError):
    """A matcher took longer than --pair-timeout on one pair."""


def exit_text(exc: SystemExit) -> str:
    return f"sys.exit({exc.code!r})"


@contextmanager
def no_exit(what: str) -> Iterator[None]:
    """SystemExit raised inside the block -> PluginExit naming `what` (e.g. 'match()')."""
    try:
        yield
    except SystemExit as exc:
        raise PluginExit(f"{exit_text(exc)} called inside {what}") from None


def describe_matcher(matcher) -> dict:
    """What a matcher says of itself for config.yaml: its ``config()`` (a plugin's object may
    have none: then its name), checked to be a mapping that YAML can write; a one-line
    ValueError naming the matcher otherwise, raised before anything is written."""
    name = getattr(matcher, "name", type(matcher).__name__)
    describe = getattr(matcher, "config", None)
    if not callable(describe):
        return {"matcher": name}
    try:
        with no_exit("config()"):
            described = describe()
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:  # noqa: BLE001 - a plugin's config() may raise anything
        raise ValueError(f"matcher {name}: config() raised {type(exc).__name__}: {exc}") from None
    if not isinstance(described, dict):
        raise ValueError(f"matcher {name}: config() returned {type(described).__name__}, expected a dict")
    try:  # as files.save_yaml will write it
        yaml.safe_dump(yaml_plain(described))
    except (yaml.YAMLError, ValueError, TypeError) as exc:  # RepresenterError: an object, a set
        reason = " ".join(str(exc).split())
        raise ValueError(f"matcher {name}: config() returned a value YAML cannot write ({reason}); "
                         "return plain numbers, strings, lists and dicts") from None
    return described


@contextmanager
def pair_time_limit(seconds: float | None, what: str) -> Iterator[None]:
    """Raise PairTimeout inside the block once `seconds` have passed (None or 0: no limit).

    `what` names the matcher and the pair in the message. A ValueError where no alarm can be
    set (a thread other than the main one, a system without SIGALRM), so that a limit asked
    for is never silently ignored.
    """
    if not seconds:
        yield
        return
    if not hasattr(signal, "setitimer") or threading.current_thread() is not threading.main_thread():
        raise ValueError("--pair-timeout needs the main thread of a POSIX system (it uses SIGALRM)")

    def expired(signum, frame):
        raise PairTimeout(f"{what}: no result within --pair-timeout {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, float(seconds))
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        # None: a handler installed outside Python, which cannot be put back; the default then
        signal.signal(signal.SIGALRM, previous if previous is not None else signal.SIG_DFL)
