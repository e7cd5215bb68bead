"""What the toolkit does around a plugin's code so that the plugin cannot end or freeze it.

A matcher is someone else's code called in our process. Three helpers keep its failures its own:

- ``no_exit(what)``: ``sys.exit`` inside a matcher's factory, ``match`` or ``config`` raises
  SystemExit, which no ``except Exception`` stops, so the whole tool would end with the
  plugin's exit code and no word. Inside the block it becomes a PluginExit (a RuntimeError)
  that the caller reports as that matcher's failure.
- ``describe_matcher(matcher)``: the matcher's ``settings()`` or ``config()`` as a dict YAML can
  write, or a one-line ValueError (it raised, exited, or returned an object YAML cannot represent).
- ``StoppableWorker(target, what)``: the per-pair bound of ``--pair-timeout`` where it must
  hold against code that does not cooperate. ``target`` runs in a forked child process, in a
  process group of its own; a call with no answer by its deadline kills that whole group
  (the child and whatever it forked), and the next call forks a fresh child. A matcher that
  catches the timeout, ignores or blocks SIGALRM, forks, or sits in C code is stopped all
  the same, and a result that comes after the deadline is never read.
- ``pair_time_limit(seconds, what)``: the in-process bound, for where a forked child cannot
  run the matcher (CUDA cannot be used in a forked child). It uses SIGALRM in the main
  thread; the matcher is interrupted when control next returns to Python, and a result
  returned after the deadline (a matcher that caught the timeout) is a timeout all the same.
  Code that blocks the signal or sits in C is not stopped by it: StoppableWorker is.
"""

from __future__ import annotations

import os
import pickle
import signal
import socket
import struct
import sys
import threading
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import yaml

from e3cm_bench.ground.files import yaml_plain
from e3cm_bench.matchers import child_answer


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


def describe_matcher(matcher, built_with: dict | None = None) -> dict:
    """What a matcher says of itself for config.yaml, checked to be a mapping that YAML can
    write (a one-line ValueError naming the matcher otherwise, raised before anything is
    written): its ``settings()`` (the documented hook for a plugin: {"matcher": name, **settings}),
    else its ``config()`` where its class defines one (the built-ins), else its name and
    `built_with`, the settings the registry built it from (plugin_code.built_with)."""
    name = getattr(matcher, "name", type(matcher).__name__)
    hook = getattr(matcher, "settings", None)
    if callable(hook):
        return {"matcher": name, **_described(name, "settings()", hook)}
    describe = getattr(matcher, "config", None)
    if callable(describe) and (built_with is None or _defines_config(matcher)):
        return _described(name, "config()", describe)
    return {"matcher": name, **(built_with or {})}


def _defines_config(matcher) -> bool:
    """Whether the matcher's class has a config() of its own (not only Matcher's, its name)."""
    from e3cm_bench.matchers.base import Matcher

    return getattr(type(matcher), "config", None) is not Matcher.config


def _described(name: str, what: str, call) -> dict:
    try:
        with no_exit(what):
            described = call()
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:  # noqa: BLE001 - a plugin's config() may raise anything
        raise ValueError(f"matcher {name}: {what} raised {type(exc).__name__}: {exc}") from None
    if not isinstance(described, dict):
        raise ValueError(f"matcher {name}: {what} returned {type(described).__name__}, expected a dict")
    try:  # as files.save_yaml will write it
        yaml.safe_dump(yaml_plain(described))
    except (yaml.YAMLError, ValueError, TypeError) as exc:  # RepresenterError: an object, a set
        reason = " ".join(str(exc).split())
        raise ValueError(f"matcher {name}: {what} returned a value YAML cannot write ({reason}); "
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
    started = time.monotonic()
    signal.setitimer(signal.ITIMER_REAL, float(seconds))
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        # None: a handler installed outside Python, which cannot be put back; the default then
        signal.signal(signal.SIGALRM, previous if previous is not None else signal.SIG_DFL)
    if time.monotonic() - started > seconds:  # it caught the timeout and returned late: not a result
        raise PairTimeout(f"{what}: no result within --pair-timeout {seconds:g} s (it returned after "
                          f"{time.monotonic() - started:.3g} s)")


# --------------------------------------------------------------------------- a stoppable child

_LENGTH = struct.Struct("!Q")


class WorkerDied(RuntimeError):
    """The child running a matcher ended without an answer (killed by a signal, os._exit, a crash)."""


def can_fork() -> bool:
    return hasattr(os, "fork") and hasattr(os, "killpg") and hasattr(socket, "socketpair")


class StoppableWorker:
    """``target(*args)`` run in a forked child that can be stopped, one call at a time.

    The child is forked on the first call (it inherits everything built so far: the matcher,
    its model) and answers calls until it is closed or stopped. Each call has a deadline; a
    child without an answer by then is killed with its whole process group (SIGKILL: no
    handler can delay it), reaped, and the call raises PairTimeout; the next call forks a
    fresh child. Only a process that leaves the group on purpose (setsid) escapes the kill.
    The child dies with its parent (PR_SET_PDEATHSIG on Linux). Its answer is plain data and
    arrays (child_answer.py: no pickle, lengths bounded before they are read, the call it
    answers named by a nonce); the deadline covers reading it. What the target raises is
    raised in the caller as the same class where that is a built-in one or one of `errors`,
    else as a RuntimeError with its type and message.
    """

    def __init__(self, target: Callable[..., Any], what: str, errors: tuple[type, ...] = (),
                 max_bytes: int = child_answer.MAX_ARRAY_BYTES) -> None:
        self.target, self.what = target, what
        self.errors = {cls.__name__: cls for cls in errors}  # what the target raises, raised as itself here
        self.max_bytes = max_bytes  # the array bytes one answer may announce
        self.pid: int | None = None
        self.sock: socket.socket | None = None
        self.forks = 0  # children started (the first, and one after each stop)

    # ---- the parent's side

    def call(self, args: tuple, seconds: float | None, what: str | None = None) -> Any:
        what = what or self.what
        self.start()
        deadline = None if seconds is None else time.monotonic() + float(seconds)
        nonce = os.urandom(child_answer.NONCE_BYTES)  # the answer names its call: a spare one is never this call's
        try:
            _send(self.sock, pickle.dumps((nonce, args), protocol=pickle.HIGHEST_PROTOCOL), deadline)
            document, declared, data = self._answer(nonce, deadline)
        except (TimeoutError, socket.timeout):
            self.stop()
            raise PairTimeout(f"{what}: no result within --pair-timeout {seconds:g} s "
                              "(its process was stopped, with every process it started)") from None
        except child_answer.BadAnswer as exc:
            self.stop()
            raise WorkerDied(f"{what}: its answer was refused ({exc}); its process was stopped") from None
        except (OSError, EOFError, struct.error) as exc:
            status = self.stop()
            raise WorkerDied(f"{what}: its process ended without a result ({status or type(exc).__name__})") from None
        try:
            value = child_answer.decode(document, declared, data, self.errors)
        except child_answer.BadAnswer as exc:
            self.stop()
            raise WorkerDied(f"{what}: its answer was refused ({exc}); its process was stopped") from None
        if deadline is not None and time.monotonic() > deadline:  # reading it back counts toward the limit
            raise PairTimeout(f"{what}: no result within --pair-timeout {seconds:g} s (its answer was read back late)")
        return value

    def _answer(self, nonce: bytes, deadline: float | None, spares: int = 16):
        """The answer to the call `nonce` (its JSON document, declared arrays and bytes), each
        length checked before it is read; answers to other calls (at most `spares`) read past."""
        for _ in range(spares + 1):
            got, text_bytes, array_bytes = child_answer.ANSWER_HEADER.unpack(
                _exactly(self.sock, child_answer.ANSWER_HEADER.size, deadline))
            child_answer.check_lengths(text_bytes, array_bytes, self.max_bytes)
            if got != nonce:
                _discard(self.sock, text_bytes + array_bytes, deadline)
                continue
            document, declared = child_answer.declared_arrays(_exactly(self.sock, text_bytes, deadline), array_bytes)
            return document, declared, _exactly(self.sock, array_bytes, deadline)
        raise child_answer.BadAnswer(f"more than {spares} answers to other calls")

    def start(self) -> None:
        """Fork the child, unless it is running."""
        if self.pid is not None:
            return
        parent_sock, child_sock = socket.socketpair()
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # the child: never returns
            parent_sock.close()
            _child_main(self.target, child_sock, os.getppid())
        child_sock.close()
        self.pid, self.sock = pid, parent_sock
        self.forks += 1
        try:  # set here too: the parent's kill must find the group even if the child has not yet run
            os.setpgid(pid, pid)
        except OSError:
            pass

    def stop(self) -> str | None:
        """Kill the child's process group and reap the child; how it ended, in words."""
        if self.pid is None:
            return None
        pid, self.pid = self.pid, None
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        for kill in (lambda: os.killpg(pid, signal.SIGKILL), lambda: os.kill(pid, signal.SIGKILL)):
            try:
                kill()
            except OSError:  # already gone (a group with no member left)
                pass
        try:
            _, status = os.waitpid(pid, 0)
        except ChildProcessError:
            return None
        if os.WIFSIGNALED(status):
            return f"signal {os.WTERMSIG(status)}"
        return f"exit code {os.WEXITSTATUS(status)}" if os.WIFEXITED(status) else None

    def close(self) -> None:
        """End the child (and anything it left in its group)."""
        self.stop()

    def __enter__(self) -> "StoppableWorker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _send(sock: socket.socket, data: bytes, deadline: float | None) -> None:
    _timeout(sock, deadline)
    sock.sendall(_LENGTH.pack(len(data)))
    _timeout(sock, deadline)
    view = memoryview(data)
    while view:  # sendall's timeout is per call: the deadline is checked between chunks
        _timeout(sock, deadline)
        sent = sock.send(view[:1 << 24])
        view = view[sent:]


def _receive(sock: socket.socket, deadline: float | None) -> bytearray:
    header = _exactly(sock, _LENGTH.size, deadline)
    return _exactly(sock, _LENGTH.unpack(header)[0], deadline)


def _exactly(sock: socket.socket, n: int, deadline: float | None) -> bytearray:
    buffer = bytearray(n)
    view, got = memoryview(buffer), 0
    while got < n:
        _timeout(sock, deadline)
        k = sock.recv_into(view[got:], min(n - got, 1 << 24))
        if k == 0:
            raise EOFError("the other end closed")
        got += k
    return buffer  # pickle reads a bytearray as it is: no copy


def _discard(sock: socket.socket, n: int, deadline: float | None) -> None:
    while n > 0:
        n -= len(_exactly(sock, min(n, 1 << 20), deadline))


def _timeout(sock: socket.socket, deadline: float | None) -> None:
    if deadline is None:
        sock.settimeout(None)
        return
    left = deadline - time.monotonic()
    if left <= 0:
        raise TimeoutError
    sock.settimeout(left)


def _child_main(target: Callable[..., Any], sock: socket.socket, parent: int) -> None:
    """The child's loop: a call's arguments in, ("ok", value) or ("error", exception) out."""
    code = 0
    try:
        os.setpgid(0, 0)  # its own group: the parent's kill reaches whatever it forks
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG: die with the parent
        except (OSError, AttributeError):
            pass
        if os.getppid() != parent:
            os._exit(1)
        # The parent's console (a progress bar may have replaced sys.stdout) and its handlers
        # are not the child's: it prints to the real streams, and Ctrl-C is the parent's to handle.
        sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if "torch" in sys.modules:
            # GNU OpenMP (torch's CPU thread pool) hangs in a forked child once the parent has
            # used it (measured: the child's first parallel op never returns); one thread runs
            # no parallel region.
            sys.modules["torch"].set_num_threads(1)
        while True:
            try:
                nonce, args = pickle.loads(_receive(sock, None))  # the parent's own call
            except (EOFError, OSError):
                break
            try:
                answer = ("ok", target(*args))
            except BaseException as exc:  # noqa: BLE001 - carried to the parent, SystemExit included
                answer = ("error", exc)
            sock.sendall(child_answer.encode(nonce, answer))  # its own framing: a header, no length prefix
    except BaseException:  # noqa: BLE001 - nothing of the child may run on in the parent's code
        code = 1
    finally:
        os._exit(code)
