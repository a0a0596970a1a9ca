"""Ctrl-C and ``kill``: a job stops within about a second, wherever it is (README, Trust and
failure model).

:func:`install` (called by ``python -m pipeline``) handles SIGINT and SIGTERM in the main thread by
raising :class:`Interrupted` (a ``KeyboardInterrupt``): the runner removes the stage's temporary
directory, ends the MLflow run KILLED and the entry point exits 128 + the signal number (130 for
Ctrl-C) with one line.  SIGINT is handled even when the process inherited it ignored (``cmd &`` in
a non-interactive shell starts ``cmd`` with SIGINT ignored: Python then never raises
``KeyboardInterrupt`` and ``kill -INT`` did nothing).

A watchdog thread is woken by the signal itself (``signal.set_wakeup_fd``), not by the Python
handler, which only runs when the main thread returns to the interpreter.  If that has not happened
after :data:`GRACE` seconds (a long call into native code that released the GIL: BLAS, torch), or
the orderly unwinding has not ended the process after :data:`DEADLINE` seconds, it runs the
registered cleanups (:func:`on_abort`: remove temporary directories, mark runs KILLED; each bounded
in time) and ends the process with ``os._exit``.  A second signal does so at once.  Native code that
holds the GIL (a numba kernel) runs until it returns: no Python thread can run meanwhile.
"""
from __future__ import annotations

import atexit
import os
import select
import signal
import sys
import threading
import time
from typing import Callable

#: seconds the main thread has to react to the signal before the watchdog ends the process
GRACE = 1.0
#: seconds from the signal to the end of the orderly cleanup before the watchdog ends the process
DEADLINE = 5.0
#: seconds the watchdog gives the registered cleanups (an MLflow server may not answer)
CLEANUP_TIMEOUT = 3.0

HANDLED = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """The job was stopped by a signal (Ctrl-C: SIGINT, ``kill``: SIGTERM)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


_lock = threading.Lock()
_cleanups: dict[object, Callable[[], None]] = {}
_state: dict = {"signum": None, "t0": None, "installed": False, "previous": {}, "wakeup": None, "generation": 0}
_reacted = threading.Event()
_aborting = threading.Lock()


def on_abort(key: object, fn: Callable[[], None]) -> None:
    """Run ``fn()`` if the watchdog has to end the process (the orderly path is the caller's own
    ``except``/``finally``); :func:`discard` ``key`` when it no longer applies."""
    with _lock:
        _cleanups[key] = fn


def discard(key: object) -> None:
    with _lock:
        _cleanups.pop(key, None)


def received() -> int | None:
    """The signal that is stopping this process (None: none)."""
    return _state["signum"]


def seconds_since_signal() -> float | None:
    t0 = _state["t0"]
    return None if t0 is None else time.monotonic() - t0


def _note(signum: int) -> bool:
    """Record ``signum``; True if it is the first."""
    with _lock:
        first = _state["signum"] is None
        if first:
            _state["signum"], _state["t0"] = int(signum), time.monotonic()
    return first


def _handler(signum, frame) -> None:
    first = _note(signum)
    if not first and _reacted.is_set():   # a second Ctrl-C during the cleanup: stop now
        _abort(signum, "second signal")
    _reacted.set()
    raise Interrupted(signum)


def _say(line: str) -> None:
    try:   # os.write: the main thread may hold sys.stderr's lock
        os.write(2, (line + "\n").encode())
    except OSError:
        pass


def _abort(signum: int, why: str) -> None:
    """Run the registered cleanups (bounded in time) and end the process with 128 + signum."""
    if not _aborting.acquire(blocking=False):   # the watchdog and a second signal: one of them
        while True:
            time.sleep(1)
    with _lock:
        fns = list(_cleanups.values())
    done = threading.Event()

    def run_all():
        for fn in fns:
            try:
                fn()
            except BaseException:  # noqa: BLE001 — best effort; the next job cleans up the rest
                pass
        done.set()

    threading.Thread(target=run_all, name="pipeline-abort", daemon=True).start()
    finished = done.wait(CLEANUP_TIMEOUT)
    name = signal.Signals(signum).name
    _say(f"interrupted ({name}; {why}): stopped"
         + (", temporary files removed, run marked KILLED" if finished else
            "; cleanup did not finish (the next job marks the run KILLED and removes its temporaries)")
         + "; rerun the same command to resume from the cache")
    os._exit(128 + signum)


def _signals_in(read_fd: int, timeout: float | None) -> list[int] | None:
    """Handled signals read from the wakeup pipe within ``timeout`` ([]: none; None: pipe closed)."""
    ready, _, _ = select.select([read_fd], [], [], timeout)
    if not ready:
        return []
    try:
        data = os.read(read_fd, 64)
    except InterruptedError:
        return []
    except OSError:
        return None
    if not data:
        return None
    return [s for s in data if s in HANDLED]


def _watchdog(read_fd: int, generation: int) -> None:
    try:
        while True:                     # wait for the first SIGINT / SIGTERM
            sigs = _signals_in(read_fd, None)
            if sigs is None:
                return
            if sigs:
                _note(sigs[0])
                break
        signum, t0 = _state["signum"], _state["t0"]
        if not _reacted.wait(max(0.0, GRACE - (time.monotonic() - t0))):
            if _state["generation"] == generation:
                _abort(signum, f"no reaction within {GRACE:g} s")
            return
        while (left := t0 + DEADLINE - time.monotonic()) > 0:   # the orderly cleanup runs
            sigs = _signals_in(read_fd, left)
            if sigs is None or _state["generation"] != generation:
                return
            if sigs:
                _abort(signum, "second signal")
        if _state["generation"] == generation:
            _abort(signum, f"cleanup took over {DEADLINE:g} s")
    finally:
        os.close(read_fd)


def exit_now(code: int) -> None:
    """End the process with ``code`` after the ``atexit`` hooks (the sweep's parent run), skipping
    the interpreter's teardown of every loaded module (1.5-2 s with torch, numba and MLflow loaded)."""
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 — a closed stream: nothing to flush
                pass
        os._exit(code)


def install() -> None:
    """Handle SIGINT and SIGTERM as :class:`Interrupted` and start the watchdog (main thread only;
    a no-op elsewhere and when already installed)."""
    if _state["installed"] or threading.current_thread() is not threading.main_thread():
        return
    r, w = os.pipe()
    os.set_blocking(w, False)
    try:
        previous_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    except ValueError:
        os.close(r)
        os.close(w)
        return
    _state["previous"] = {s: signal.signal(s, _handler) for s in HANDLED}
    _state["generation"] += 1
    _state.update(wakeup=(w, previous_fd), installed=True)
    threading.Thread(target=_watchdog, args=(r, _state["generation"]), name="pipeline-interrupt-watchdog",
                     daemon=True).start()


def uninstall() -> None:
    """Restore the previous handlers and forget any signal (tests calling the entry point in-process)."""
    if not _state["installed"]:
        return
    for s, h in _state["previous"].items():
        signal.signal(s, h if h is not None else signal.SIG_DFL)
    w, previous_fd = _state["wakeup"]
    signal.set_wakeup_fd(previous_fd)
    _state["generation"] += 1
    os.close(w)    # the watchdog reads end-of-file and ends
    _state.update(installed=False, previous={}, wakeup=None, signum=None, t0=None)
    _reacted.clear()
    with _lock:
        _cleanups.clear()
