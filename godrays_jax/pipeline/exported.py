"""Programs traced once and kept across processes (`jax.export`): a later fit runs without tracing its solver again.

JAX's persistent compilation cache (the command line turns it on, `app.compile_cache`)
spares compiling a program twice, but every process still traces each program
in Python before it can look it up. For a fit that tracing (the loss, the
solver's first state and step, the Jacobian of `determination`, the render)
costs more than the solver's steps on a small frame, and it is a good part of
an `apply`; `benchmarks/README.md` ("Command start-up and the compilation cache")
has the figures.

`call(name, function, *args)` runs `function(*args)` (an `equinox.filter_jit`
function: arrays are traced, everything else is static) from an exported
program stored in `use_directory`'s folder, exported the first time and read
back by later processes instead of tracing. A program is stored under a key of
everything its trace depends on:

- every static argument, described value by value (numbers, strings, the
  fields of Modules, the names of functions and classes);
- the arrays' shapes, dtypes and weak types;
- the JAX settings that change a trace (`jax_enable_x64`, the default matmul
  precision, ...) and whether range checks are left out (`ranges_guaranteed`);
- the installed versions of JAX, jaxlib, Equinox, Optimistix, Lineax and
  NumPy, the backend and its device kind, and a digest of this package's
  source files.

An argument that cannot be described exactly (a closure or lambda, a class
or function from a package outside that list) is never stored: `call` then
runs `function(*args)` as it is. So is a program whose output JAX cannot
serialise, and everything when no folder is set (the library's default).
A file that cannot be read back is exported again; a folder that cannot be
written to only means the program is not stored. The folder is kept under
`MAX_BYTES`, least recently used programs first.

With JAX's persistent compilation cache on (the command line's), exporting a
program clears JAX's in-memory caches (`jax.clear_caches`): the trace it no
longer needs would otherwise stay beside the compile that follows. The
programs `call` runs are compiled ahead of their first call and held by this
module, out of those caches' reach; what else they held compiled (the small
programs around) is read back from the persistent cache when next called.

A stored program is code the process runs, so the folder must be this
user's alone (`primitives.files.private_folder`: created 0700, refused when
another user owns it or may write to it), and a file in it is read only if
this user owns it and nobody else may write to it (a link is never followed).
"""

import contextlib
import contextvars
import dataclasses
import functools
import hashlib
import importlib.metadata
import os
import threading
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from godrays_jax.primitives.checks import ranges_are_guaranteed
from godrays_jax.primitives.files import atomic_write, owned_privately, private_folder, private_folder_problem

MAX_BYTES = 64 << 20
"""The folder's cap: storing a program beyond it removes the least recently used ones."""

_VERSIONED = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy")
"""The distributions whose installed versions are part of every key."""

_DESCRIBED_PACKAGES = frozenset({"godrays_jax", "builtins", *_VERSIONED})
"""Packages whose classes and functions a key may name: this package by its source digest, the others by version."""

_SETTINGS = (
    "jax_enable_x64",
    "jax_default_matmul_precision",
    "jax_numpy_dtype_promotion",
    "jax_numpy_rank_promotion",
)
"""JAX settings read while tracing: part of every key."""

_SUFFIX = ".jaxexport"

_directory: Path | None = None
_programs: dict[str, Callable[..., Any] | None] = {}
"""This process's compiled programs by key, called with the arguments' arrays; None marks a program that cannot be
stored (its plain call is used)."""
_making = threading.RLock()
"""Held while a program is read back or exported and compiled: threads that call the same new program make it once."""


def use_directory(directory: str | os.PathLike | None) -> None:
    """Store exported programs in `directory` and read them from there; None (the default) stores nothing.

    The folder is created for this user alone (0700) if missing.

    Raises:
        PermissionError: another user owns the folder or may write to it
            (nothing is stored or read then).
        OSError: the folder cannot be created.
    """
    global _directory
    _directory = None
    _programs.clear()
    if directory is not None:
        _directory = Path(private_folder(directory))


def call(name: str, function: Callable[..., Any], *args: Any, closed_over: Any = None) -> Any:
    """`function(*args)`, from the program stored for these arguments when there is one, storing it when not.

    `name` names the program's file (with its key); the result is the same
    pytree of arrays `function` returns. `closed_over` holds what `function`
    closes over (compiled into it as constants, such as an effect whose known
    fields let kernels specialise): it is described in the key by value,
    arrays by a digest of their bytes.
    """
    if _directory is None:
        return function(*args)
    try:
        key = _key(name, args, closed_over)
    except _NotDescribable:
        return function(*args)
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, tree = jax.tree.flatten(dynamic)
    if key not in _programs:
        with _making:
            if key not in _programs:
                program = _read(name, key) or _exported(name, key, function, static, tree, leaves)
                # Compiled ahead of its call and held here, where the next export's `jax.clear_caches` cannot drop
                # it: a program jitted lazily is compiled, or read back from the compilation cache, again after
                # every export. It dispatches like any compiled function; a bare `Exported.call` goes through Python.
                _programs[key] = None if program is None else _compiled(jax.jit(program.call).lower(*leaves))
    program = _programs[key]
    return function(*args) if program is None else program(*leaves)


COMPILER_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}
"""XLA's options for every program `call` compiles: on the CPU, elementwise work left to XLA's own code rather than
YNNPACK's fusions, which ran the fit's Jacobian more slowly (benchmarks/README.md, "The fit's programs without
YNNPACK's fusions"). A jaxlib that lacks an option compiles without it."""

_options_known = True


def _compiled(lowered):
    """`lowered` compiled with `COMPILER_OPTIONS`, or with XLA's defaults where this jaxlib does not know them."""
    global _options_known
    if _options_known:
        try:
            return lowered.compile(compiler_options=COMPILER_OPTIONS)
        except jax.errors.JaxRuntimeError as error:
            if "No such compile option" not in str(error):
                raise
            _options_known = False
    return lowered.compile()


class _NotDescribable(Exception):
    """A static argument that no key can describe exactly."""


def _key(name: str, args, closed_over) -> str:
    text = "\n".join([
        name, _describe(args), _describe(closed_over, by_value=True), _environment(), _settings(),
        f"ranges_guaranteed={ranges_are_guaranteed()}",
    ])  # fmt: skip
    return hashlib.sha256(text.encode()).hexdigest()


def _describe(value, by_value: bool = False) -> str:
    """A text that two values share only if a trace cannot tell them apart (arrays by shape and dtype, or also by
    their bytes `by_value`)."""
    describe = functools.partial(_describe, by_value=by_value)
    if eqx.is_array(value):
        weak = " weak" if getattr(value, "weak_type", False) else ""
        digest = f" {hashlib.sha256(np.asarray(value).tobytes()).hexdigest()}" if by_value else ""
        return f"array({value.dtype}{list(np.shape(value))}{weak}{digest})"
    if value is None or isinstance(value, (bool, int, float, complex, str, bytes, np.generic, np.dtype)):
        return f"{type(value).__name__}({value!r})"
    if isinstance(value, (tuple, list)):
        kind = type(value).__name__ if type(value) in (tuple, list) else _named(type(value))
        return f"{kind}[{', '.join(map(describe, value))}]"
    if isinstance(value, dict):
        return f"dict{{{', '.join(sorted(f'{describe(k)}: {describe(v)}' for k, v in value.items()))}}}"
    if isinstance(value, (set, frozenset)):
        return f"{type(value).__name__}{{{', '.join(sorted(map(describe, value)))}}}"
    if isinstance(value, functools.partial):
        return f"partial({describe(value.func)}, {describe(value.args)}, {describe(value.keywords)})"
    if isinstance(value, (type, types.FunctionType, types.BuiltinFunctionType)):
        return _named(value)
    if dataclasses.is_dataclass(value):
        fields = ", ".join(f"{f.name}={describe(getattr(value, f.name))}" for f in dataclasses.fields(value))
        return f"{_named(type(value))}({fields})"
    raise _NotDescribable(type(value))


def _named(thing) -> str:
    """`module.qualname` of a class or function defined at the top of a module of a described package."""
    module, name = getattr(thing, "__module__", None), getattr(thing, "__qualname__", None)
    if not (module and name) or "<" in name or module.partition(".")[0] not in _DESCRIBED_PACKAGES:
        raise _NotDescribable(thing)
    return f"{module}.{name}"


@functools.cache
def _environment() -> str:
    """The versions, backend and source digest that every key holds, found once per process (`_settings` are read
    at every call: a `with jax.default_matmul_precision(...)` changes them)."""
    versions = " ".join(f"{dist}={importlib.metadata.version(dist)}" for dist in _VERSIONED)
    device = jax.devices()[0]
    return f"{versions} {device.platform} {device.device_kind} source={source_digest()}"


@functools.cache
def source_digest() -> str:
    """A digest of this package's source files (their paths and bytes): part of every key, and of what a compiled
    fit is remembered by (`app.compile_cache.remember_fit`). Read once per process."""
    package = Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        digest.update(str(path.relative_to(package)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def carried(function: Callable[..., Any]) -> Callable[..., Any]:
    """`function`, to run on another thread as it would on this one: in this thread's values of the JAX settings
    that change a trace (`_SETTINGS`, which JAX keeps per thread) and in a copy of its context (`ranges_guaranteed`,
    `values_only`). On a thread of its own a call would otherwise trace, store and compile programs of other
    settings, and run them."""
    values = {setting: getattr(jax.config, setting) for setting in _SETTINGS}
    context = contextvars.copy_context()

    def run(*args):
        with contextlib.ExitStack() as stack:
            for setting, value in values.items():
                stack.enter_context(getattr(jax, setting.removeprefix("jax_"))(value))
            return context.copy().run(function, *args)

    return run


def _settings() -> str:
    return " ".join(f"{setting}={getattr(jax.config, setting)}" for setting in _SETTINGS)


def _path(name: str, key: str) -> Path:
    return _directory / f"{name}-{key[:40]}{_SUFFIX}"


def _read(name: str, key: str) -> jax.export.Exported | None:
    path = _path(name, key)
    if private_folder_problem(_directory) is not None:  # the folder was replaced since `use_directory`
        return None
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except OSError:  # missing, or a link
        return None
    with open(fd, "rb") as stream:
        if not owned_privately(os.fstat(fd)):
            return None  # a file another user could have written: never run, and not ours to remove
        data = stream.read()
    try:
        program = jax.export.deserialize(bytearray(data))
    except Exception:  # noqa: BLE001 - a truncated or foreign file: export the program again
        path.unlink(missing_ok=True)
        return None
    with contextlib.suppress(OSError):  # its use only orders eviction
        os.utime(path)
    return program


def _exported(name, key, function, static, tree, leaves) -> jax.export.Exported | None:
    """Trace `function` for these arguments, export it and store it; None if JAX cannot export or serialise it."""

    def of_leaves(*leaves):
        return function(*eqx.combine(jax.tree.unflatten(tree, leaves), static))

    shapes = [jax.ShapeDtypeStruct(np.shape(x), x.dtype, weak_type=getattr(x, "weak_type", False)) for x in leaves]
    try:
        data = jax.export.export(jax.jit(of_leaves))(*shapes).serialize()
    except Exception:  # noqa: BLE001 - e.g. a host callback, or an output pytree JAX cannot serialise
        return None
    if jax.config.jax_enable_compilation_cache and jax.config.jax_compilation_cache_dir:
        # The program runs from its export from now on, but JAX's caches would keep its trace (the jaxpr and its
        # lowering) for the rest of the process, under the compile that comes next: a cold fit's peak
        # (benchmarks/README.md, "The fit as users run it"). The programs `call` holds stay compiled.
        jax.clear_caches()
    try:
        with atomic_write(_path(name, key), sync=False, mode=0o600) as temporary:
            Path(temporary).write_bytes(data)
        _evict()
    except OSError:  # a full or read-only folder: the program runs, unstored, as the cache is best effort
        pass
    # Run what later processes will read: its compiled program is then in JAX's cache for them.
    return jax.export.deserialize(bytearray(data))


def _evict() -> None:
    """Remove the least recently used programs until the folder holds at most `MAX_BYTES`."""
    stored = []
    for path in _directory.glob(f"*{_SUFFIX}"):
        if path.name.startswith("."):  # another process's file in progress
            continue
        try:
            stat = path.stat()
        except FileNotFoundError:  # removed by another process meanwhile
            continue
        stored.append((stat.st_mtime, stat.st_size, path))
    total = sum(size for _, size, _ in stored)
    for _, size, path in sorted(stored):
        if total <= MAX_BYTES:
            break
        path.unlink(missing_ok=True)
        total -= size
