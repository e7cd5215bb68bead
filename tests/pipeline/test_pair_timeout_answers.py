"""The answer of a --pair-timeout matcher's process (matchers/child_answer.py), against a matcher
that writes on its socket itself: a spare answer is never the next pair's, bytes that would run
code or take seconds to load in the parent are refused unread, and the run folder's lock cannot
be released from the matcher's process (issue 61, item 4). Each case runs the command in a fresh
process, as test_pair_timeout_hostile.py does."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from e3cm_bench.ground.matches import Matches
from e3cm_bench.storage import RunFolder

ROOT = Path(__file__).resolve().parents[2]

# The socket the matcher's process answers on, found as a hostile matcher would find it.
HOSTILE = '''
import gc, os, pickle, socket, struct, sys
import numpy as np
from e3cm_bench.ground.matches import Matches

CALLS = os.environ["HOSTILE_CALLS"]

def points(n):
    k = np.stack([10.0 + 3 * np.arange(n), 10.0 + 2 * np.arange(n)], 1).astype(np.float32)
    return Matches(k, k.copy(), np.ones(n, np.float32))

def the_socket():
    return next(o for o in gc.get_objects() if isinstance(o, socket.socket) and o.fileno() >= 0)

def this_call():
    frame = sys._getframe()
    while frame is not None and "nonce" not in frame.f_locals:
        frame = frame.f_back
    return None if frame is None else frame.f_locals["nonce"]

class Evil:
    def __reduce__(self):
        return (os.system, (f"touch {os.environ['HOSTILE_MARKER']}; sleep 6",))

class Hostile:
    name = "hostile"

    def match(self, image0, image1):
        with open(CALLS, "a") as f:
            f.write("call\\n")
        call = len(open(CALLS).read().splitlines())
        kind = os.environ["HOSTILE_KIND"]
        if call == 1 and kind == "spare":  # an answer of 50 matches first, then the real one
            try:
                from e3cm_bench.matchers import child_answer
                frame = child_answer.encode(this_call(), ("ok", points(50)))
            except ImportError:  # the pickled answers before child_answer
                data = pickle.dumps(("ok", points(50)))
                frame = struct.pack("!Q", len(data)) + data
            the_socket().sendall(frame)
        if call == 1 and kind == "code":  # bytes that, unpickled, run a command in the parent
            data = pickle.dumps(("ok", Evil()))
            the_socket().sendall(struct.pack("!Q", len(data)) + data)
        if kind == "lock":  # release the run folder's lock, then see whether another run could take it
            import fcntl
            lock = os.path.join(os.environ["HOSTILE_OUT"], ".lock")
            for fd in os.listdir("/proc/self/fd"):
                try:
                    if os.readlink(f"/proc/self/fd/{fd}") == lock:
                        fcntl.flock(int(fd), fcntl.LOCK_UN)
                except OSError:
                    pass
            try:
                other = os.open(lock, os.O_RDWR)
                fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
                open(os.environ["HOSTILE_MARKER"], "w").write("took the lock")
                fcntl.flock(other, fcntl.LOCK_UN)
            except OSError:
                pass
        return points(call + 3)

def factory():
    return Hostile()
'''


@pytest.fixture(scope="module")
def boat(shared_data, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data") / "hpatches"
    shutil.copytree(shared_data / "hpatches-sequences-release" / "v_boat", root / "v_boat")
    return root


def hostile_run(kind: str, boat: Path, tmp_path: Path, *extra) -> tuple[subprocess.CompletedProcess, Path, Path]:
    (tmp_path / "hostile_answers.py").write_text(HOSTILE)
    out, marker = tmp_path / "run", tmp_path / "marker"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "HOSTILE_KIND": kind, "HOSTILE_CALLS": str(tmp_path / "calls"),
           "HOSTILE_MARKER": str(marker), "HOSTILE_OUT": str(out)}
    process = subprocess.Popen([sys.executable, "-m", "e3cm_bench", "hpatches", "--root", str(boat), "--out", str(out),
                                "--matcher", "hostile_answers:factory", "--limit", "4", "--pair-timeout", "3", *extra],
                               cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    try:
        stdout, stderr = process.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate()
        pytest.fail(f"the {kind} run did not end")
    return subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr), out, marker


def test_a_spare_answer_on_the_socket_is_never_the_next_pairs(boat, tmp_path):
    done, out, _ = hostile_run("spare", boat, tmp_path)
    assert done.returncode == 0, done.stderr
    counts = pd.read_csv(RunFolder(out).per_pair_path).set_index("pair")["n_matches"].to_dict()
    # pair 1-2 takes the first answer naming its call (the matcher's spare); every later pair its own
    assert counts == {"v_boat/1-2": 50, "v_boat/1-3": 5, "v_boat/1-4": 6, "v_boat/1-5": 7}


def test_an_answer_that_would_run_code_in_the_parent_is_refused_unread(boat, tmp_path):
    done, out, marker = hostile_run("code", boat, tmp_path, "--on-matcher-error", "fail-pair")
    assert done.returncode == 0, done.stderr
    assert not marker.exists(), "the matcher's bytes ran a command in the parent"
    failures = pd.read_csv(RunFolder(out).failures_path)
    assert failures["pair"].tolist() == ["v_boat/1-2"]
    assert "its answer was refused (it announced" in failures["error"].iloc[0]
    per_pair = pd.read_csv(RunFolder(out).per_pair_path).set_index("pair")
    assert per_pair.loc["v_boat/1-3", "n_matches"] == 5  # the next pair answered by a fresh process (its call 2)


def test_the_matchers_process_cannot_release_the_run_folders_lock(boat, tmp_path):
    done, out, marker = hostile_run("lock", boat, tmp_path)
    assert done.returncode == 0, done.stderr
    assert not marker.exists(), "the matcher's process released the folder lock: another run could take it"
    assert len(pd.read_csv(RunFolder(out).per_pair_path)) == 4


# --------------------------------------------------------------------------- the format itself


def test_an_answer_is_checked_against_its_bounds_before_anything_is_built():
    from e3cm_bench.matchers import child_answer

    k = np.arange(8, dtype=np.float32).reshape(4, 2)
    frame = child_answer.encode(b"n" * 16, ("ok", Matches(k, k + 1, None, {"level": (1, np.eye(2))})))
    header = child_answer.ANSWER_HEADER
    nonce, text_bytes, array_bytes = header.unpack(frame[:header.size])
    text = frame[header.size:header.size + text_bytes]
    document, declared = child_answer.declared_arrays(text, array_bytes)
    back = child_answer.decode(document, declared, frame[header.size + text_bytes:], {})
    assert np.array_equal(back.keypoints1, k + 1) and back.info["level"][0] == 1
    assert np.array_equal(back.info["level"][1], np.eye(2))
    with pytest.raises(child_answer.BadAnswer, match="bytes of arrays"):
        child_answer.check_lengths(10, 1 << 40, child_answer.MAX_ARRAY_BYTES)
    with pytest.raises(child_answer.BadAnswer, match="declare"):  # an array larger than the bytes announced
        child_answer.declared_arrays(text.replace(b"[4, 2]", b"[400000, 2]"), array_bytes)
    with pytest.raises(child_answer.BadAnswer, match="dtype"):
        child_answer.declared_arrays(text.replace(b"<f4", b"|O"), array_bytes)
    with pytest.raises(child_answer.BadAnswer, match="nested too deeply|not readable"):
        child_answer.declared_arrays(b'{"ok": ' + b"[" * 100000 + b"]" * 100000 + b"}", 0)
