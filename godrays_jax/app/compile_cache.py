"""The command line's persistent compilation cache: an effect compiled once is reused by later processes.

JAX's persistent cache stores each compiled program under a key of its
program text, so a later `apply`, `batch`, `fit` or `tune` of the same effect
on frames of the same size loads it instead of compiling. The programs of
`apply` and `fit` are also stored traced (`pipeline.exported`, in the
subfolder `EXPORTED_FOLDER`), so a later run does not trace them again
either. Where: the environment variable `GODRAYS_JAX_CACHE_DIR`, else the
user's cache folder (`cache_dir`). Its size is capped (`MAX_BYTES`; least
recently used entries go first); `godrays-jax cache` shows it and `godrays-jax cache --clear`
removes the entries the library wrote; `--no-cache` on any command leaves it alone. The
fits that finished with the cache on are remembered by what decides their
programs (`remember_fit`, in the subfolder `FITS_FOLDER`), so that a later
process knows before JAX starts whether it will compile them
(`app.allocator`).

The entries are programs (JAX's hold machine code) that later runs execute,
so the cache is used only from a folder that this user alone can write to
(`primitives.files.private_folder`): it is created 0700, and one that belongs
to another user or that its group or others may write to is refused, as is a
path that cannot be a folder; the command then runs without a cache
(`enable` raises `CacheUnavailable`, the command line warns in one line).
"""

import hashlib
import os
import re
import warnings

import jax
import platformdirs

from godrays_jax.pipeline import exported
from godrays_jax.primitives.files import private_folder

ENVIRONMENT_VARIABLE = "GODRAYS_JAX_CACHE_DIR"

MAX_BYTES = 1 << 30
"""The cache's cap: JAX evicts the least recently used entries beyond it."""

EXPORTED_FOLDER = "exported"
"""The subfolder of traced programs (`pipeline.exported`, capped at its own `MAX_BYTES`)."""

FITS_FOLDER = "fits"
"""The subfolder of the fits that finished with the cache on: an empty file named by each one's digest
(`remember_fit`)."""


def cache_dir() -> str:
    """`$GODRAYS_JAX_CACHE_DIR`, else the user's cache folder for `godrays_jax` (`platformdirs`: on Linux
    `$XDG_CACHE_HOME/godrays_jax`, else `~/.cache/godrays_jax`; `~/Library/Caches/godrays_jax` on macOS)."""
    chosen = os.environ.get(ENVIRONMENT_VARIABLE)
    if chosen:
        return os.path.abspath(os.path.expanduser(chosen))
    return platformdirs.user_cache_dir("godrays_jax", appauthor=False)


class CacheUnavailable(Exception):
    """The cache folder cannot be used (the message says why); the command runs without it."""


def enable(directory: str | None = None) -> str:
    """Store and reuse every compiled program in `directory` (default `cache_dir()`); returns the folder.

    Every program is stored, however quick its compilation: the command line
    compiles a handful of programs per run and each saved one is saved start-up.

    Raises:
        CacheUnavailable: the folder cannot be created or written to, or
            other users can write to it (nothing is changed then).
    """
    directory = directory or cache_dir()
    stored = os.path.join(directory, EXPORTED_FOLDER)
    try:
        private_folder(directory)
        private_folder(stored)
        private_folder(os.path.join(directory, FITS_FOLDER))
    except OSError as error:
        reason = error.strerror or str(error)
        raise CacheUnavailable(f"cache folder {error.filename or directory} not used: {reason}") from None
    # The cache is best effort: processes sharing it (a farm, parallel shells) race on its bookkeeping files,
    # and a failed read or write only means a compilation. Its warnings would break the one-line contract.
    warnings.filterwarnings("ignore", message=r"Error (reading|writing) persistent compilation cache", category=UserWarning)
    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    # Programs whose tracing costs as much as running them (a fit's solver step, apply's frame) are stored traced.
    exported.use_directory(stored)
    return directory


_COMPILED = re.compile(r"[^/]+-[0-9a-f]{64}-(?:cache|atime)|\.lockfile")
"""The names of JAX's cache entries (`NAME-KEY-cache`, its access time `NAME-KEY-atime`) and of its lock file."""

_STORED = re.compile(r"[^/]+\.jaxexport")
"""The names of stored traced programs, and of their temporaries (`pipeline.exported`)."""

_FIT = re.compile(r"[0-9a-f]{64}")
"""The names of the fits remembered (`remember_fit`)."""


def _fit_path(signature: str, directory: str | None) -> str:
    return os.path.join(directory or cache_dir(), FITS_FOLDER, hashlib.sha256(signature.encode()).hexdigest())


def holds_fit(signature: str, directory: str | None = None) -> bool:
    """Whether a fit of this `signature` (`remember_fit`) finished with the cache in `directory` (default
    `cache_dir()`): its programs are then most likely in the cache, unless evicted since or cleared by hand."""
    return os.path.isfile(_fit_path(signature, directory))


def remember_fit(signature: str, directory: str | None = None) -> None:
    """Record that a fit of this `signature` (text of whatever decides the programs it compiles: its frames'
    sizes, its options, the package's source) finished with the cache in `directory` (default `cache_dir()`),
    once `enable` made the folder. A folder that cannot be written to only means it is not recorded."""
    try:
        with open(_fit_path(signature, directory), "x"):
            pass
    except OSError:  # recorded already (FileExistsError), or the folder cannot be written to
        pass


def _entries(directory: str) -> list[os.DirEntry]:
    """The library's entries in the cache folder and in its `EXPORTED_FOLDER`, without following links inside."""
    found = []
    for folder, pattern in (
        (directory, _COMPILED),
        (os.path.join(directory, EXPORTED_FOLDER), _STORED),
        (os.path.join(directory, FITS_FOLDER), _FIT),
    ):
        if folder != directory and os.path.islink(folder):
            continue  # the stored programs' folder is the library's own: a link there leads elsewhere
        try:
            with os.scandir(folder) as listing:
                found += [e for e in listing if pattern.fullmatch(e.name) and not e.is_dir(follow_symlinks=False)]
        except (FileNotFoundError, NotADirectoryError):
            continue
    return found


def cache_size(directory: str | None = None) -> tuple[int, int]:
    """`(files, bytes)` of the library's entries in the cache now (links counted, not what they lead to)."""
    entries = _entries(directory or cache_dir())
    return len(entries), sum(entry.stat(follow_symlinks=False).st_size for entry in entries)


def clear(directory: str | None = None) -> tuple[int, bool]:
    """Remove the entries the library wrote: JAX's compiled programs, the stored traced ones and the fits
    remembered.

    Nothing else in the folder is touched, and a link among the entries is
    removed itself, never what it leads to. The folders go too once empty,
    unless the cache folder is a link. Returns `(entries removed, whether the
    folder is gone)`.
    """
    directory = directory or cache_dir()
    removed = 0
    for entry in _entries(directory):
        try:
            os.unlink(entry.path)
            removed += 1
        except FileNotFoundError:  # removed meanwhile by JAX's eviction in another process
            pass
    if not os.path.islink(directory):
        for folder in (os.path.join(directory, EXPORTED_FOLDER), os.path.join(directory, FITS_FOLDER), directory):
            try:
                os.rmdir(folder)
            except OSError:  # not empty (it holds what the library did not write), a link, or gone
                pass
    return removed, not os.path.lexists(directory)
