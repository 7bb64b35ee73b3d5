"""Files that appear whole or not at all, and claims on outputs that several processes may race for.

Every output is written to a hidden temporary file beside its path, flushed to
disk and renamed into place. A temporary's name says which process wrote it
(`.STEM.tmp-HOST-PID-XXXXXXXX.EXT`), so a run cleans up only what dead runs
left (`is_stale`), never a live run's file in progress.
"""

import contextlib
import errno
import glob
import os
import re
import secrets
import socket
import stat
import time
from collections.abc import Iterator

import filelock

STALE_AGE_S = 6 * 3600.0
"""A temporary this old is stale even if its process seems alive (the pid may have been reused) or runs on
another host (its pid cannot be checked from here): writing one frame takes seconds, not hours."""

_OWNER = re.compile(r"\.tmp-(?P<host>[A-Za-z0-9]+)-(?P<pid>\d+)-[0-9a-f]{8}")


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9]", "", socket.gethostname())[:32] or "host"


def _owner_tag() -> str:
    """`HOST-PID-XXXXXXXX`: this process, and a random part so that one process's names never collide."""
    return f"{_host()}-{os.getpid()}-{secrets.token_hex(4)}"


def temporary_path(path: str | os.PathLike) -> str:
    """A fresh hidden name beside `path` with the same extension: `.STEM.tmp-HOST-PID-XXXXXXXX.EXT`."""
    folder, base = os.path.split(os.path.abspath(os.fspath(path)))
    stem, ext = os.path.splitext(base)
    return os.path.join(folder, f".{stem}.tmp-{_owner_tag()}{ext}")


def temporaries_of(path: str | os.PathLike) -> list[str]:
    """The temporary files (`temporary_path`) that exist beside `path`, of any process, live or dead."""
    folder, base = os.path.split(os.path.abspath(os.fspath(path)))
    stem, ext = os.path.splitext(base)
    return glob.glob(os.path.join(glob.escape(folder), f".{glob.escape(stem)}.tmp-*{glob.escape(ext)}"))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def is_stale(path: str | os.PathLike, *, max_age_s: float = STALE_AGE_S) -> bool:
    """Whether a temporary file was left by a process that is gone.

    Stale: its process (named in the file name) no longer exists on this host,
    or the file is older than `max_age_s` (a reused pid, another host, or a
    name without an owner, as older versions wrote). A file that vanished is
    not stale (someone else cleaned it).
    """
    try:
        age = time.time() - os.stat(path).st_mtime
    except FileNotFoundError:
        return False
    if age > max_age_s:
        return True
    owner = _OWNER.search(os.path.basename(os.fspath(path)))
    if owner is None or owner["host"] != _host():
        return False
    return int(owner["pid"]) != os.getpid() and not _alive(int(owner["pid"]))


def remove_stale(paths) -> list[str]:
    """Delete those of `paths` that are stale (`is_stale`); returns the ones this call removed."""
    removed = []
    for path in paths:
        if is_stale(path):
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)
                removed.append(path)
    return removed


def private_folder_problem(folder: str | os.PathLike) -> str | None:
    """Why no user but this one can be trusted to have written what `folder` holds, or None if so.

    Trusted: a folder (a link to one is followed) that belongs to this user
    and that neither its group nor other users may write to.
    """
    try:
        info = os.stat(folder)
    except OSError as error:
        return error.strerror.lower() if error.strerror else str(error)
    if not stat.S_ISDIR(info.st_mode):
        return "not a folder"
    owner = getattr(os, "geteuid", None)
    if owner is not None and info.st_uid != owner():
        return f"it belongs to another user (uid {info.st_uid})"
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"other users can write to it (mode {stat.S_IMODE(info.st_mode):o})"
    return None


def private_folder(folder: str | os.PathLike) -> str:
    """`folder`, created if missing with permissions for this user alone (0700); returns its path.

    Raises:
        PermissionError: it exists but other users can write to it or it
            belongs to another user (`private_folder_problem` says which).
        OSError: it cannot be created (a file stands in its path, a parent is
            read-only), or cannot be written to.
    """
    folder = os.fspath(folder)
    os.makedirs(folder, mode=0o700, exist_ok=True)
    problem = private_folder_problem(folder)
    if problem is not None:
        raise PermissionError(errno.EACCES, problem, folder)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(errno.EACCES, "cannot write to it", folder)
    return folder


def owned_privately(info: os.stat_result) -> bool:
    """Whether a file's `os.stat` result says this user owns it and nobody else may write to it."""
    owner = getattr(os, "geteuid", None)
    mine = owner is None or info.st_uid == owner()
    return mine and stat.S_ISREG(info.st_mode) and not info.st_mode & (stat.S_IWGRP | stat.S_IWOTH)


def _fsync_folder(folder: str) -> None:
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    except OSError as error:  # some file systems cannot sync a folder; the rename itself is still atomic
        if error.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


def _place_without_replacing(temporary: str, path: str) -> None:
    """Move `temporary` to `path` unless `path` exists, atomically even against another process doing the same."""
    try:
        os.link(temporary, path)  # fails if `path` exists, whoever created it and whenever
    except FileExistsError:
        raise FileExistsError(errno.EEXIST, f"'{path}' exists already (written meanwhile by another run?)") from None
    except OSError as error:
        if error.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK):
            raise
        # No hard links on this file system: claim the name exclusively, then rename over the claim.
        try:
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            raise FileExistsError(errno.EEXIST, f"'{path}' exists already (written meanwhile by another run?)") from None
        os.replace(temporary, path)
        return
    os.remove(temporary)


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike, *, replace: bool = True, sync: bool = True, mode: int = 0o666
) -> Iterator[str]:
    """A temporary path to write to; flushed to disk and renamed onto `path` when the block ends, removed if it raises.

    A reader of `path` sees the old file or the whole new one, never a part,
    also after a crash of the machine (the file is synced before the rename,
    the folder after it). The temporary is created here, empty, with the
    user's normal permissions (`0o666` less the umask); the block writes it.
    With `replace=False` an existing `path` is never replaced, even one that
    another process creates while the block runs: `FileExistsError` instead.
    `sync=False` skips the syncs (for throwaway files).
    Raises `FileNotFoundError` naming the folder when it does not exist.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"cannot write '{path}': folder '{folder}' does not exist")
    temporary = temporary_path(path)
    os.close(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode))
    try:
        yield temporary
        if sync:
            fd = os.open(temporary, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        if replace:
            os.replace(temporary, path)
        else:
            _place_without_replacing(temporary, path)
        if sync:
            _fsync_folder(folder)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(temporary)
        raise


Claim = filelock.BaseFileLock
"""A path this process holds (`claim`): an acquired lock on its lock file."""


def claim(path: str | os.PathLike) -> Claim | None:
    """Take `path` for this process, or None if another process holds it; hand the claim to `release`.

    The claim is an exclusive `filelock.FileLock` (on Unix an `flock`) on a
    hidden lock file `.BASE.lock` beside `path`; the OS drops it when the
    process ends however it ends, so a killed run never keeps a frame from
    the next one.
    """
    folder, base = os.path.split(os.path.abspath(os.fspath(path)))
    lock = filelock.FileLock(os.path.join(folder, f".{base}.lock"))
    try:
        lock.acquire(timeout=0)
    except filelock.Timeout:
        return None
    return lock


def release(held: Claim | None) -> None:
    """Give up a claim from `claim` (None: nothing to do); its lock file is removed.

    Removed while still locked: a process that opened the file before sees
    the lock it then takes is on a removed file and starts again (filelock
    3.29.5 on: from 3.20.4 to 3.29.4 filelock itself removed the file on
    release, after this removal possibly another process's new one).
    """
    if held is None:
        return
    with contextlib.suppress(FileNotFoundError):
        os.remove(held.lock_file)
    held.release()
