"""Where the image tracks' cache lives, and one build per cache entry among processes (``image_tracks``).

The default cache is ``s2camp_image_tracks`` in the scene folder; where that cannot be written (``write_error``) a
shipped cache is still read and builds go to ``user_cache_folder``. A build holds an exclusive ``flock`` on
``.<key>.lock`` beside its entry (``entry_lock``): one process builds, the others wait and read the entry (a dead
holder's lock is released, and a waiter then builds). No lock without ``fcntl`` (Windows): each builds, the first
entry to finish is kept. A damaged entry raises ``DamagedEntryError`` in its reader and is built again in its place
(``notice_damaged``, ``discard``).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

try:
    import fcntl
except ImportError:  # Windows: no inter-process lock (module docstring, Lock)
    fcntl = None

HOLDER_NAME_WAIT_S = 5.0
"""How long a waiter reads the lock file again for the holder's name before its notice names it "?"."""
USER_CACHE_NAME = "s2camp-ns"
"""This package's folder in the user's cache folder (``XDG_CACHE_HOME``, else ``~/.cache``)."""
LOG = Console(stderr=True, width=120)
"""The cache's notices (on stderr, as the data parser's)."""


class DamagedEntryError(ValueError):
    """A cache entry that cannot be used as it is (module docstring, Damage); the message says why."""


def notice_damaged(entry: Path, what: str, why: str) -> None:
    """The notice that the cache entry ``entry`` of ``what`` is damaged (``why``), not used and built again."""
    LOG.print(
        f"[bold yellow]{what}: the cache entry {escape(str(entry))} is damaged ({escape(why)}); it is not used, and "
        "is built again",
        soft_wrap=True,
    )


def hash_file(digest: Any, path: Path) -> None:
    """Feed the bytes of the file ``path`` to ``digest`` (a ``hashlib`` object), a block at a time."""
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)


def discard(entry: Path) -> None:
    """Remove the damaged entry ``entry`` (folder or file), renamed out of sight first so that a reader without the
    lock finds the whole entry or none; only the holder of its ``entry_lock`` may call it."""
    hidden = entry.parent / f".{entry.name}.{os.getpid()}.damaged.building"
    os.rename(entry, hidden)
    if hidden.is_dir():
        shutil.rmtree(hidden, ignore_errors=True)
    else:
        hidden.unlink(missing_ok=True)


def file_digest(path: Path) -> str:
    """The SHA-256 (hex) of the file ``path``."""
    digest = hashlib.sha256()
    hash_file(digest, path)
    return digest.hexdigest()


def user_cache_folder(kind: str = "image_tracks") -> Path:
    """``$XDG_CACHE_HOME/s2camp-ns/<kind>``, or ``~/.cache/s2camp-ns/<kind>`` when ``XDG_CACHE_HOME`` is unset, empty
    or relative; ``kind``: ``image_tracks`` or ``readjusted_points`` (``robust_adjustment``)."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if base and os.path.isabs(base) else Path.home() / ".cache"
    return root / USER_CACHE_NAME / kind


def write_error(folder: Path) -> OSError | None:
    """None when a file can be created in ``folder`` (made with its parents if missing), else the error. Creating a
    file is the test: ``os.access`` says yes to root and on some read-only mounts."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(prefix=".write-probe.", dir=folder)
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        return error
    return None


def build_folder(cache: Path, user_fallback: bool) -> Path:
    """The folder to build a cache entry in: ``cache`` when writable, else with ``user_fallback`` the user's cache
    folder (with a notice). OSError naming the ``image_tracks_cache`` option when neither can be written."""
    error = write_error(cache)
    if error is None:
        return cache
    option = "choose a writable folder with the data parser's --image-tracks-cache"
    example = "(ns-train s2camp --data D s2camp-data --image-tracks-cache DIR)"
    if not user_fallback:
        raise OSError(
            f"cannot write the image tracks' cache folder {cache} (image_tracks_cache; {error}): {option} {example}"
        ) from error
    user = user_cache_folder()
    user_error = write_error(user)
    if user_error is not None:
        raise OSError(
            f"cannot write the image tracks' cache folder {cache} in the scene ({error}) nor the user's cache folder "
            f"{user} ({user_error}): {option} {example}, or set XDG_CACHE_HOME to a writable folder"
        ) from user_error
    why = escape(error.strerror or str(error))
    LOG.print(
        f"[dim]Image tracks: the scene's cache folder {escape(str(cache))} cannot be written ({why}); building them "
        f"in the user's cache folder {escape(str(user))}",
        soft_wrap=True,
    )
    return user


@contextlib.contextmanager
def entry_lock(entry: Path, what: str = "Image tracks") -> Iterator[None]:
    """Hold the exclusive lock of the cache entry ``entry`` (``.<name>.lock`` beside it) for the body, waiting with
    one notice naming ``what`` while another process holds it. The body must check whether ``entry`` was finished
    meanwhile. No lock without ``fcntl``."""
    if fcntl is None:
        yield
        return
    path = entry.parent / f".{entry.name}.lock"
    noticed = False
    while True:
        handle = _open_lock_file(path)
        try:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if not noticed:
                    _notice_wait(handle, entry, what)
                    noticed = True
                fcntl.flock(handle, fcntl.LOCK_EX)
            if _is_file_at(handle, path):
                break
        except BaseException:
            os.close(handle)
            raise
        os.close(handle)  # the holder removed this lock file when it was done: lock the one now at `path`
    try:
        with contextlib.suppress(OSError):  # who holds it, for the waiters' notice (not where it is read-only)
            os.ftruncate(handle, 0)
            os.write(handle, f"{os.getpid()} {socket.gethostname()}\n".encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(handle)


def remove_stale_builds(entry: Path) -> None:
    """Remove the build folders (``.<name>.*.building``) of dead builders; only the holder of ``entry_lock`` may
    call it. Nothing without ``fcntl``."""
    if fcntl is None:
        return
    for stale in entry.parent.glob(f".{entry.name}.*.building"):
        shutil.rmtree(stale, ignore_errors=True)


def _open_lock_file(path: Path) -> int:
    """A descriptor of the lock file ``path``, created if missing; read-only for another user's (``flock`` locks
    either)."""
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except PermissionError:
        return os.open(path, os.O_RDONLY)


def _is_file_at(handle: int, path: Path) -> bool:
    """Whether the open file ``handle`` is still the file at ``path`` (not removed, nor replaced)."""
    try:
        here = os.stat(path)
    except FileNotFoundError:
        return False
    mine = os.fstat(handle)
    return (here.st_dev, here.st_ino) == (mine.st_dev, mine.st_ino)


def _notice_wait(handle: int, entry: Path, what: str) -> None:
    """The notice that this process waits for the build of ``entry`` by the process named in the lock file (read
    again for up to ``HOLDER_NAME_WAIT_S`` while empty, then "?")."""
    holder: list[str] = []
    deadline = time.monotonic() + HOLDER_NAME_WAIT_S
    while True:
        with contextlib.suppress(OSError):
            holder = os.pread(handle, 200, 0).decode(errors="replace").split()
        if len(holder) == 2 or time.monotonic() >= deadline:
            break
        time.sleep(0.02)
    holder = holder if len(holder) == 2 else ["?", "?"]
    LOG.print(
        f"[dim]{what}: waiting for process {escape(holder[0])} on {escape(holder[1])}, which builds them in "
        f"{escape(str(entry))} (another rank, or another run of the same data), to read them",
        soft_wrap=True,
    )


__all__ = [
    "USER_CACHE_NAME",
    "DamagedEntryError",
    "build_folder",
    "discard",
    "entry_lock",
    "file_digest",
    "hash_file",
    "notice_damaged",
    "remove_stale_builds",
    "user_cache_folder",
    "write_error",
]
