"""Files that appear whole or not at all: every output is written beside its path and renamed into place."""

import contextlib
import glob
import os
import secrets
from collections.abc import Iterator


def temporary_path(path: str | os.PathLike) -> str:
    """A fresh hidden name beside `path` with the same extension: `.STEM.tmp-XXXXXXXX.EXT`."""
    folder, base = os.path.split(os.path.abspath(os.fspath(path)))
    stem, ext = os.path.splitext(base)
    return os.path.join(folder, f".{stem}.tmp-{secrets.token_hex(4)}{ext}")


def temporaries_of(path: str | os.PathLike) -> list[str]:
    """The temporary files (`temporary_path`) that exist beside `path`, e.g. left by a killed run."""
    folder, base = os.path.split(os.path.abspath(os.fspath(path)))
    stem, ext = os.path.splitext(base)
    return glob.glob(os.path.join(glob.escape(folder), f".{glob.escape(stem)}.tmp-*{glob.escape(ext)}"))


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[str]:
    """A temporary path to write to; renamed onto `path` when the block ends, removed if it raises.

    A reader of `path` sees the old file or the whole new one, never a part.
    Raises `FileNotFoundError` naming the folder when it does not exist.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"cannot write '{path}': folder '{folder}' does not exist")
    temporary = temporary_path(path)
    try:
        yield temporary
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise
