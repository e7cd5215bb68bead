"""A plugin's import, bounded (the matcher registry's loading of plugins and of
``--matcher package.module:factory``): first in a forked child process, killed with its process
group at the bound, then here in a daemon thread bounded the same way; what goes wrong in it
(a timeout, a crash, sys.exit, an exception) as one line (`why`)."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Callable

from e3cm_bench.matchers.guards import exit_text

# How long one plugin's import may take. Generous: a plugin importing torch and a model zoo
# takes seconds on a cold disk; one that never returns must not hang every command.
PLUGIN_IMPORT_SECONDS = 60.0


def plugin_import_seconds() -> float:
    """The bound on one plugin's import: E3CM_BENCH_PLUGIN_TIMEOUT seconds, else PLUGIN_IMPORT_SECONDS."""
    text = os.environ.get("E3CM_BENCH_PLUGIN_TIMEOUT")
    if not text:
        return PLUGIN_IMPORT_SECONDS
    try:
        seconds = float(text)
    except ValueError:
        seconds = -1.0
    if not seconds > 0:
        raise ValueError(f"E3CM_BENCH_PLUGIN_TIMEOUT={text!r}: expected a number of seconds > 0")
    return seconds


class TimedOut(Exception):
    pass


def probe(call: Callable[[], object], what: str, seconds: float) -> None:
    """call() in a forked child, in a process group of its own, killed with that group after
    `seconds`: TimedOut then, or where the child crashed. Whatever call() raises there is not
    looked at: the import here gives the same error, in one line."""
    if not (hasattr(os, "fork") and hasattr(os, "killpg")):
        return
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # the child: quiet, never returns
        code = 0
        try:
            os.setpgid(0, 0)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            call()
        except BaseException:  # noqa: BLE001 - an error is the import's own, reported by the import here
            pass
        finally:
            os._exit(code)
    try:
        os.setpgid(pid, pid)
    except OSError:
        pass
    deadline, pause = time.monotonic() + seconds, 0.001
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() >= deadline:
            for kill in (lambda: os.killpg(pid, signal.SIGKILL), lambda: os.kill(pid, signal.SIGKILL)):
                try:
                    kill()
                except OSError:
                    pass
            os.waitpid(pid, 0)
            raise TimedOut(f"did not finish importing within {seconds:g} s (E3CM_BENCH_PLUGIN_TIMEOUT sets the bound)")
        time.sleep(pause)
        pause = min(pause * 2, 0.05)
    if os.WIFSIGNALED(status):
        raise TimedOut(f"crashed while importing (signal {os.WTERMSIG(status)}); not imported here")


def bounded(call: Callable[[], object], what: str):
    """call() first in a forked child (probe: killed after plugin_import_seconds()), then here
    in a daemon thread, waited for as long; TimedOut where either does not finish. Whatever
    call() raises, SystemExit included, is raised here in the caller."""
    seconds = plugin_import_seconds()
    probe(call, what, seconds)
    done: dict = {}

    def target() -> None:
        try:
            done["value"] = call()
        except BaseException as exc:  # noqa: BLE001 - carried to the caller, SystemExit included
            done["error"] = exc

    thread = threading.Thread(target=target, name=f"e3cm-bench import {what}", daemon=True)
    thread.start()
    thread.join(seconds)
    if thread.is_alive():
        raise TimedOut(f"did not finish importing within {seconds:g} s (E3CM_BENCH_PLUGIN_TIMEOUT sets the bound)")
    if "error" in done:
        raise done["error"]
    return done["value"]


def why(exc: BaseException) -> str:
    if isinstance(exc, SystemExit):
        return f"called {exit_text(exc)}"
    if isinstance(exc, TimedOut):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"
