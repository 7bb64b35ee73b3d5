"""The house rules: layers import one way, the package root is the library, and every public kernel has one shape.

Kernels follow dm-pix's API conventions: the image (or the plane, or the frame's
size for a generator) first, every option keyword-only, jaxtyping annotations on
every argument and the result, and a docstring that says the units.
"""

import ast
import inspect
import pathlib
import subprocess
import sys

import jaxtyping
import pytest

import godrays_jax as gr

ROOT = pathlib.Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "godrays_jax"
SOURCES = sorted(PACKAGE.rglob("*.py"))

KERNELS = sorted(
    name
    for name in dir(gr)
    if inspect.isfunction(getattr(gr, name)) and getattr(gr, name).__module__.startswith("godrays_jax.kernels.")
)
GENERATORS = {"dirt_texture", "flare_image", "interleaved_gradient_noise", "light_direction", "light_source_mask",
              "procedural_flare", "sun_spot", "view_directions"}  # fmt: skip
"""Kernels that make an image of a given size: `height, width` come first instead of an image."""


def _run_python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_layers_import_one_way():
    """The import-linter contract in pyproject.toml: app -> pipeline -> effects | raster -> kernels -> primitives."""
    done = _run_python("import sys; from importlinter.cli import lint_imports; sys.exit(lint_imports())")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "KEPT" in done.stdout and "BROKEN" not in done.stdout


def test_the_contract_catches_an_upward_import(tmp_path):
    """A kernel that imports the command line must break the contract (the check is real, not vacuous)."""
    copy = tmp_path / "godrays_jax"
    subprocess.run(["cp", "-r", str(PACKAGE), str(copy)], check=True)
    (copy / "kernels" / "composite.py").write_text(
        (copy / "kernels" / "composite.py").read_text() + "\nfrom godrays_jax.app import options  # noqa\n"
    )
    subprocess.run(["cp", str(ROOT / "pyproject.toml"), str(tmp_path)], check=True)
    done = subprocess.run(
        [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports; sys.exit(lint_imports())"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300, env={"PYTHONPATH": str(tmp_path), "PATH": ""},
    )  # fmt: skip
    assert done.returncode != 0 and "BROKEN" in done.stdout


def test_the_package_root_loads_no_command_line_or_server():
    done = _run_python(
        "import sys, godrays_jax\n"
        "loaded = sorted(m for m in sys.modules if m.startswith('godrays_jax.app'))\n"
        "print(loaded)"
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


HEAVY = ("OpenImageIO", "tqdm", "optimistix", "lineax")
"""What the kernels and effects must not load: image files, the progress bar, the solver."""


def test_the_kernels_and_effects_load_no_files_progress_bar_or_solver():
    done = _run_python(
        "import importlib, pkgutil, sys\n"
        "import godrays_jax.effects, godrays_jax.kernels\n"
        "for package in (godrays_jax.kernels, godrays_jax.effects):\n"
        "    for module in pkgutil.walk_packages(package.__path__, package.__name__ + '.'):\n"
        "        importlib.import_module(module.name)\n"
        "print(len([m for m in sys.modules if m.startswith('godrays_jax.kernels.copy_sums.')]))\n"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r})))"
    )
    assert done.returncode == 0, done.stderr
    copies_loaded, heavy = done.stdout.split("\n")[:2]
    assert int(copies_loaded) >= 6, "the walk must reach the subpackage of the copy sums"
    assert heavy == "[]"


def test_only_the_kernels_import_the_copy_sums():
    offenders = [
        f"{path.relative_to(ROOT)} line {node.lineno}"
        for path in SOURCES
        if PACKAGE / "kernels" not in path.parents
        for node in _imports(path)[1]
        for name in ([node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names])
        if name.startswith("godrays_jax.kernels.copy_sums")
    ]
    assert not offenders


MAX_MODULE_LINES = 600
"""A module longer than this holds more than one concern: split it (docs/ARCHITECTURE.md, one line per module)."""


def test_no_module_is_over_600_lines():
    long = {str(path.relative_to(ROOT)): count for path in SOURCES if (count := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_version_comes_from_the_installed_metadata():
    import importlib.metadata

    assert gr.__version__ == importlib.metadata.version("godrays_jax")


def _imports(path: pathlib.Path):
    tree = ast.parse(path.read_text(), str(path))
    return tree, [node for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))]


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_import_inside_a_function(path):
    tree, _ = _imports(path)
    nested = [
        f"line {inner.lineno}: {ast.unparse(inner)}"
        for node in ast.walk(tree)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        for inner in ast.walk(node)
        if isinstance(inner, (ast.Import, ast.ImportFrom))
    ]
    assert not nested, f"{path.name} imports inside functions: {nested}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_private_name_is_imported_from_another_module(path):
    _, imports = _imports(path)
    private = [
        f"line {node.lineno}: {ast.unparse(node)}"
        for node in imports
        if isinstance(node, ast.ImportFrom)
        and (node.module or "").startswith("godrays_jax")
        and any(alias.name.startswith("_") for alias in node.names)
    ]
    assert not private, f"{path.name} imports private names: {private}"


def test_no_test_file_imports_another():
    offenders = []
    for path in sorted((ROOT / "tests").glob("test_*.py")):
        _, imports = _imports(path)
        for node in imports:
            names = [node.module or ""] if isinstance(node, ast.ImportFrom) else [alias.name for alias in node.names]
            offenders += [f"{path.name} imports {name}" for name in names if name.split(".")[0].startswith("test_")]
    assert not offenders


def _is_array_annotation(annotation) -> bool:
    """A jaxtyping array annotation (`Float[Array, "H W C"]`), alone or in a union (`int | Float[ArrayLike, ""]`)."""
    options = getattr(annotation, "__args__", None) if not hasattr(annotation, "dim_str") else None
    if options:
        return any(_is_array_annotation(option) for option in options)
    return isinstance(annotation, type) and issubclass(annotation, jaxtyping.AbstractArray)


def _dims(annotation) -> str | None:
    """The shape string of a jaxtyping annotation, or None for anything else."""
    if hasattr(annotation, "dim_str"):
        return annotation.dim_str
    for option in getattr(annotation, "__args__", None) or ():
        if (dims := _dims(option)) is not None:
            return dims
    return None


def test_every_kernel_is_checked():
    assert len(KERNELS) >= 35 and {"radial_rays", "scale_iterated_flares", "poisson_blur", "gaussian_blur"} <= set(KERNELS)


@pytest.mark.parametrize("name", KERNELS)
def test_kernel_api_conventions(name):
    kernel = getattr(gr, name)
    signature = inspect.signature(kernel)
    parameters = list(signature.parameters.values())
    positional = [p for p in parameters if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    assert positional, f"{name} takes no positional input"
    if name in GENERATORS:
        sizes = [p.name for p in positional if p.annotation is int]
        assert sizes[:2] == ["height", "width"] or name == "light_direction", f"{name}: height, width first"
    else:
        assert _is_array_annotation(positional[0].annotation), f"{name}: the first argument must be the image"
    for parameter in positional[1:]:
        # Inputs that are arrays (a second image, the light's position) may be positional; scalars are options.
        dims = _dims(parameter.annotation)
        is_size = name in GENERATORS and parameter.annotation is int
        assert is_size or (dims not in (None, "")), f"{name}: option {parameter.name!r} must be keyword-only"
    for parameter in parameters:
        if parameter.kind is parameter.VAR_KEYWORD:
            continue
        assert parameter.annotation is not inspect.Parameter.empty, f"{name}: {parameter.name} has no annotation"
    assert _is_array_annotation(signature.return_annotation) or _dims(signature.return_annotation) is not None, (
        f"{name}: the result needs a jaxtyping annotation"
    )
    doc = inspect.getdoc(kernel)
    assert doc and len(doc) > 40, f"{name} has no docstring"
    if "light_xy" in signature.parameters:
        assert "pixel" in doc, f"{name}: the docstring must say the light's units (pixels)"
