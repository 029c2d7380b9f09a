"""What keeps a run dir whole: one writer at a time, a clean stop on SIGTERM/SIGINT, and one line
for a write the disk refused.

- :class:`RunLock`: ``RUN/run.lock``, an advisory ``flock`` held for as long as a process writes the
  run, holding who took it (pid, host, start time). A second writer fails at once with
  :class:`RunLocked`; the kernel drops the ``flock`` of a process that dies, so a lock file left
  by a dead process is taken over (with a note). Re-entrant within a process (a sweep trial holds
  it around ``explore``, which takes it too).
- :func:`stop_on_signals`: SIGTERM and SIGINT raise :class:`Stopped` where the run is, except inside
  :func:`critical` (a checkpoint being written), where they wait for the write to finish. Either
  way the run dir holds the last complete episode, and the same command resumes it bit for bit.
- :func:`write_failure`: the one line for an ``OSError`` of a full disk or a file-size limit.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import signal
import socket
import threading
import time
from pathlib import Path

__all__ = ["LOCK_FILE", "RunLock", "RunLocked", "Stopped", "critical", "stop_on_signals", "write_failure",
           "DISK_ERRNOS"]

LOCK_FILE = "run.lock"
#: the errors of a write the disk refused: no space, a file-size limit (RLIMIT_FSIZE), a quota
DISK_ERRNOS = (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)


class RunLocked(RuntimeError):
    """Another live process writes this run dir."""


class RunLock:
    """The exclusive right to write the run dir ``path``, as a context manager.

    Args:
        path: the run dir (it must exist).
        note: where the line about taking over a dead process's lock goes (``None``: nowhere).
    """

    _held: dict[str, list] = {}  # resolved run dir -> [fd, depth]: re-entrant within the process
    _guard = threading.Lock()

    def __init__(self, path: str | os.PathLike, note=print):
        self.path = Path(path)
        self.note = note

    @property
    def file(self) -> Path:
        return self.path / LOCK_FILE

    def __enter__(self) -> RunLock:
        key = str(self.path.resolve())
        with self._guard:
            if key in self._held:
                self._held[key][1] += 1
                return self
            fd = os.open(self.file, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                holder = _read_holder(fd)
                os.close(fd)
                if e.errno not in (errno.EAGAIN, errno.EACCES):
                    raise
                who = (f"pid {holder.get('pid', '?')} on {holder.get('host', '?')} since {holder.get('started', '?')}"
                       if holder else "another process")
                raise RunLocked(f"{self.path} is being written by {who}; wait for it to finish, stop it, or use "
                                "another --run-dir") from None
            previous = _read_holder(fd)
            if previous and self.note is not None:
                self.note(f"{self.path}: took over the lock of pid {previous.get('pid', '?')} on "
                          f"{previous.get('host', '?')} (started {previous.get('started', '?')}), which has ended "
                          "without releasing it")
            me = {"pid": os.getpid(), "host": socket.gethostname(),
                  "started": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(me).encode(), 0)
            os.fsync(fd)
            self._held[key] = [fd, 1]
        return self

    def __exit__(self, *exc) -> None:
        key = str(self.path.resolve())
        with self._guard:
            held = self._held[key]
            held[1] -= 1
            if held[1]:
                return
            del self._held[key]
            # emptied, not removed: a process that opened the file meanwhile must lock the same inode
            with contextlib.suppress(OSError):
                os.ftruncate(held[0], 0)
            fcntl.flock(held[0], fcntl.LOCK_UN)
            os.close(held[0])


def _read_holder(fd: int) -> dict:
    try:
        text = os.pread(fd, 4096, 0).decode()
        return json.loads(text) if text.strip() else {}
    except (OSError, ValueError):
        return {"pid": "?", "host": "?", "started": "? (unreadable lock file)"}


class Stopped(BaseException):
    """The run was asked to stop by ``signum``; the process should exit with :attr:`exit_code`.
    ``done`` and ``total``: the complete episodes on disk and the run's episodes, where the run that
    stopped knows them. A ``BaseException``, as ``KeyboardInterrupt``: no ``except Exception``
    (an env's fault guard, a user's env) may take a stop for an error and carry on."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.done: int | None = None
        self.total: int | None = None

    @property
    def exit_code(self) -> int:
        return 128 + self.signum  # the shell's convention: 143 for SIGTERM, 130 for SIGINT


_state = {"critical": 0, "pending": None}


def _raise_stop(signum, frame) -> None:
    if _state["critical"]:
        _state["pending"] = signum
        return
    raise Stopped(signum)


@contextlib.contextmanager
def critical():
    """A write that must finish: SIGTERM/SIGINT arriving inside wait for its end (then stop)."""
    _state["critical"] += 1
    try:
        yield
    finally:
        _state["critical"] -= 1
    if not _state["critical"] and _state["pending"] is not None:
        signum, _state["pending"] = _state["pending"], None
        raise Stopped(signum)


@contextlib.contextmanager
def stop_on_signals(signals=(signal.SIGTERM, signal.SIGINT)):
    """SIGTERM and SIGINT raise :class:`Stopped` inside the block (deferred inside :func:`critical`);
    the previous handlers are back after it. Outside the main thread (a Ray trial's worker thread)
    signals cannot be handled, and the block changes nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise_stop) for s in signals}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        _state["pending"] = None


def write_failure(e: OSError) -> str | None:
    """The one line for a write the disk refused (:data:`DISK_ERRNOS`), else ``None``."""
    if e.errno not in DISK_ERRNOS:
        return None
    where = f" {e.filename}" if e.filename else ""
    return (f"cannot write{where}: {e.strerror or os.strerror(e.errno)}; nothing written before it is lost (the "
            "previous checkpoint, replay dump and metrics are intact): free space and rerun the same command to resume")
