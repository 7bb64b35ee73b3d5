"""The command line's persistent compilation cache: an effect compiled once is reused by later processes.

JAX's persistent cache stores each compiled program under a key of its
program text, so a later `apply`, `batch`, `fit` or `tune` of the same effect
on frames of the same size loads it instead of compiling. The programs of
`apply` and `fit` are also stored traced (`pipeline.exported`, in the
subfolder `EXPORTED_FOLDER`), so a later run does not trace them again
either. Where: the environment variable `GODRAYS_JAX_CACHE_DIR`, else
`$XDG_CACHE_HOME/godrays_jax` (`~/.cache/godrays_jax`). Its size is capped (`MAX_BYTES`; least recently used
entries go first); `godrays-jax cache` shows it and `godrays-jax cache --clear`
empties it; `--no-cache` on any command leaves it alone.
"""

import os
import shutil
import warnings

import jax

from godrays_jax.pipeline import exported

ENVIRONMENT_VARIABLE = "GODRAYS_JAX_CACHE_DIR"

MAX_BYTES = 1 << 30
"""The cache's cap: JAX evicts the least recently used entries beyond it."""

EXPORTED_FOLDER = "exported"
"""The subfolder of traced programs (`pipeline.exported`, capped at its own `MAX_BYTES`)."""


def cache_dir() -> str:
    """`$GODRAYS_JAX_CACHE_DIR`, else `$XDG_CACHE_HOME/godrays_jax`, else `~/.cache/godrays_jax`."""
    chosen = os.environ.get(ENVIRONMENT_VARIABLE)
    if chosen:
        return os.path.abspath(os.path.expanduser(chosen))
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "godrays_jax")


def enable(directory: str | None = None) -> str:
    """Store and reuse every compiled program in `directory` (default `cache_dir()`); returns the folder.

    Every program is stored, however quick its compilation: the command line
    compiles a handful of programs per run and each saved one is saved start-up.
    """
    directory = directory or cache_dir()
    os.makedirs(directory, exist_ok=True)
    # The cache is best effort: processes sharing it (a farm, parallel shells) race on its bookkeeping files,
    # and a failed read or write only means a compilation. Its warnings would break the one-line contract.
    warnings.filterwarnings("ignore", message=r"Error (reading|writing) persistent compilation cache", category=UserWarning)
    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    # Programs whose tracing costs as much as running them (a fit's solver step, apply's frame) are stored traced.
    exported.use_directory(os.path.join(directory, EXPORTED_FOLDER))
    return directory


def cache_size(directory: str | None = None) -> tuple[int, int]:
    """`(files, bytes)` the cache holds now."""
    files = total = 0
    for folder, _, names in os.walk(directory or cache_dir()):
        for name in names:
            files += 1
            total += os.path.getsize(os.path.join(folder, name))
    return files, total


def clear(directory: str | None = None) -> None:
    """Remove the cache folder and everything in it."""
    shutil.rmtree(directory or cache_dir(), ignore_errors=True)
