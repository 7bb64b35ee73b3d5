"""The docs site (mkdocs.yml, docs/): every public name documented and in the API reference, the pages' code runs,
and `mkdocs build --strict` succeeds.

What runs in a page (docs/*.md): its ```python blocks, in order in one namespace, and the lines of its ```bash
blocks, in order, each page in a scratch folder of its own that sees the checkout's examples/ and benchmarks/, with
`godrays-jax` on PATH running this checkout. A fenced block right after the line `<!-- not run -->` is skipped: it
needs files that are not shipped, runs for minutes, or serves a page until stopped. Plain ``` blocks (option
listings, printed output) never run. In bash blocks, install steps and the lines starting with LEFT_OUT are skipped
as tests/test_readme.py skips them.
"""

import ast
import importlib
import os
import re
import shlex
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest
from frames import slow_where

import godrays_jax as gr
from godrays_jax.primitives.camera_metadata import read_frame_camera

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
API_PAGES = sorted((DOCS / "api").glob("*.md"))
NOT_RUN = "<!-- not run -->"
INSTALL = ("python3 -m venv", ". .venv/bin/activate", "pip install")
LEFT_OUT = ("python -m pytest", "godrays-jax tune", "python examples/", "python benchmarks/", "mkdocs ")

# Public names whose definition has no docstring yet: each one's docstring belongs beside its definition in
# godrays_jax/ (a string literal right after a constant's assignment), which then drops it from this set.
WITHOUT_DOCSTRING: set[str] = set()

# What a page's shell commands leave in its scratch folder.
WRITES = {
    "index.md": ["out/sample_rays.exr", "out/left_of_frame.png"],
    "rasterizer.md": ["out/crepuscular.exr", "out/crepuscular.png", "out/two_lamps.exr", "out/two_lamps.png"],
    "pipelines.md": ["out/photo.png", "out/photo_rays.png"]
    + [f"out/{folder}/frame.{n}.exr" for folder in ("shot_rays", "shot_hosts", "shot_farm") for n in range(1001, 1005)],
}


def public_names() -> list[str]:
    """The names `godrays_jax/__init__.py` gives users: imported or loaded on first use, modules left out."""
    return sorted(
        name for name in dir(gr) if not name.startswith("_") and not isinstance(getattr(gr, name), types.ModuleType)
    )


def api_entries() -> dict[str, list[str]]:
    """Each `::: dotted.path` of the API reference pages, by the name it ends in."""
    entries: dict[str, list[str]] = {}
    for page in API_PAGES:
        for path in re.findall(r"^::: (\S+)$", page.read_text(), re.MULTILINE):
            entries.setdefault(path.rsplit(".", 1)[1], []).append(path)
    return entries


def has_docstring(module_name: str, name: str) -> bool:
    """Whether `name`'s definition in that module's source has a docstring (a constant's: the string literal right
    after its assignment), as mkdocstrings reads it."""
    body = ast.parse(Path(importlib.import_module(module_name).__file__).read_text()).body
    for statement, after in zip(body, [*body[1:], None]):
        if isinstance(statement, (ast.ClassDef, ast.FunctionDef)) and statement.name == name:
            return bool(ast.get_docstring(statement))
        targets = (
            statement.targets if isinstance(statement, ast.Assign)
            else [statement.target] if isinstance(statement, ast.AnnAssign) else []
        )  # fmt: skip
        if any(isinstance(target, ast.Name) and target.id == name for target in targets):
            return isinstance(after, ast.Expr) and isinstance(getattr(after.value, "value", None), str)
    raise AssertionError(f"{module_name} does not define {name}")


def test_every_public_name_is_in_the_api_reference_once():
    entries = api_entries()
    for name in public_names():
        assert len(entries.get(name, [])) == 1, f"{name}: {entries.get(name)} in docs/api/"
        module_name = entries[name][0].rsplit(".", 1)[0]
        assert getattr(importlib.import_module(module_name), name) is getattr(gr, name), entries[name][0]
    assert set(entries) == set(public_names()), "the API reference names what godrays_jax does not export"


def test_all_lists_the_public_names_and_no_helper_module_leaks():
    """`godrays_jax.__all__` is exactly what users get (`from godrays_jax import *` included, the names loaded on
    first use too), and the modules the package's `__init__` uses itself are not among its attributes."""
    assert gr.__all__ == public_names()
    modules = {name for name in dir(gr) if not name.startswith("_") and isinstance(getattr(gr, name), types.ModuleType)}
    assert modules <= {"app", "effects", "kernels", "pipeline", "primitives", "raster"}, modules
    namespace = {}
    exec("from godrays_jax import *", namespace)  # noqa: S102 - the star import users write
    assert set(gr.__all__) <= set(namespace)


def test_every_public_name_has_a_docstring():
    entries = api_entries()
    missing = {name for name in public_names() if not has_docstring(entries[name][0].rsplit(".", 1)[0], name)}
    assert missing == WITHOUT_DOCSTRING


def fenced(page: Path, language: str) -> list[str]:
    """A page's fenced blocks in that language that run, in order, dedented."""
    fence = re.compile(r"(?:^([^\n]*)\n)?^( *)```" + language + r"\n(.*?)^\2```", re.MULTILINE | re.DOTALL)
    return [textwrap.dedent(found.group(3)) for found in fence.finditer(page.read_text()) if found.group(1) != NOT_RUN]


def nav_pages() -> list[str]:
    """The pages mkdocs.yml's nav lists, in order, relative to docs/."""
    return re.findall(r"^\s+- (?:[^:\n]+: )?(\S+\.md)$", (ROOT / "mkdocs.yml").read_text(), re.MULTILINE)


def test_the_nav_lists_every_page():
    pages = nav_pages()
    assert len(pages) == len(set(pages))
    assert set(pages) == {str(page.relative_to(DOCS)) for page in DOCS.rglob("*.md")}


def test_the_presets_page_names_every_preset():
    text = (DOCS / "presets.md").read_text()
    table = text[: text.index("## ")]
    assert set(re.findall(r"^\| `(\w+)` \|", table, re.MULTILINE)) == set(gr.PRESETS)
    assert {name for name in gr.PRESETS if f"### `{name}`" in text} == set(gr.PRESETS)


def scratch_folder(tmp_path: Path) -> Path:
    """A folder that sees the checkout's examples/ and benchmarks/ and has an `out/` of its own."""
    for name in ("examples", "benchmarks"):
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / "out").mkdir()
    return tmp_path


PYTHON_PAGES = [page for page in nav_pages() if (DOCS / page).is_file() and fenced(DOCS / page, "python")]


@pytest.mark.parametrize("page", slow_where(PYTHON_PAGES, {"research.md", "fitting.md", "index.md"}))
def test_the_python_blocks_of_a_page_run_in_order(page, tmp_path, monkeypatch):
    monkeypatch.chdir(scratch_folder(tmp_path))
    namespace = {}
    for block in fenced(DOCS / page, "python"):
        exec(compile(block, f"docs/{page}", "exec"), namespace)  # noqa: S102 - the page is the code under test
    if page == "fitting.md":
        result = namespace["result"]
        assert result.loss_after < 1e-3 * result.loss_before
        assert set(namespace["found"].sensitivity) == set(result.fitted)


def commands(page: Path) -> list[str]:
    """Every shell command of the page that a test can run, install steps removed."""
    found = []
    for block in fenced(page, "bash"):
        for line in block.splitlines():
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = [part.strip() for part in line.split("&&") if not part.strip().startswith(INSTALL)]
            if parts and not any(part.startswith(LEFT_OUT) for part in parts):
                found.append(" && ".join(parts))
    return found


SHELL_PAGES = [page for page in nav_pages() if (DOCS / page).is_file() and commands(DOCS / page)]


def test_the_pages_that_write_files_run_commands():
    assert set(WRITES) <= set(SHELL_PAGES)


@pytest.mark.parametrize("page", slow_where(SHELL_PAGES, {"pipelines.md", "rasterizer.md", "index.md"}))
def test_the_shell_commands_of_a_page_run_in_order(page, tmp_path):
    scratch = scratch_folder(tmp_path)
    bin_dir = scratch / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "godrays-jax"
    shim.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m godrays_jax "$@"\n')
    shim.chmod(0o755)
    env = {
        **os.environ,
        # This interpreter's scripts (oiiotool) too, when its environment is not activated.
        "PATH": os.pathsep.join([str(bin_dir), str(Path(sys.executable).parent), os.environ["PATH"]]),
        "PYTHONPATH": str(ROOT),
        "JAX_PLATFORMS": "cpu",  # the compilation cache: GODRAYS_JAX_CACHE_DIR, set by conftest.py
    }
    for command in commands(DOCS / page):
        done = subprocess.run(
            ["bash", "-c", command], cwd=scratch, env=env, capture_output=True, text=True, timeout=600
        )
        assert done.returncode == 0, f"{command}\n{done.stderr[-3000:]}"
    for name in WRITES.get(page, []):
        assert (scratch / name).is_file(), name
    if page == "rasterizer.md":  # `render` writes the camera's field of view beside the light's distance
        assert read_frame_camera(scratch / "out" / "crepuscular.exr").fov_x_deg == pytest.approx(60.0)
        assert np.isfinite(np.asarray(gr.read_image(scratch / "out" / "crepuscular.png"))).all()


def test_the_strict_build_succeeds(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("material")
    pytest.importorskip("mkdocstrings_handlers.python")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")]
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-5000:]
    assert (tmp_path / "site" / "api" / "kernels" / "index.html").is_file()
