"""Programs traced once and stored (`pipeline.exported`): read back without tracing, keyed by all a trace sees."""

import dataclasses
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import godrays_jax as gr
from godrays_jax.pipeline import exported
from godrays_jax.pipeline.compiled import render_compiled
from godrays_jax.pipeline.determination import determination
from godrays_jax.pipeline.fit import fit
from godrays_jax.primitives.checks import ranges_guaranteed


@pytest.fixture
def folder(tmp_path):
    exported.use_directory(tmp_path)
    yield tmp_path
    exported.use_directory(None)


def _stored(folder, name):
    return sorted(p.name for p in folder.glob(f"{name}-*.jaxexport"))


@eqx.filter_jit
def _scaled(x, factor):
    return x * factor


def _never_traced(*args):
    raise AssertionError("traced, though a stored program exists")


def test_a_stored_program_is_read_back_without_tracing(folder):
    x = jnp.arange(3.0)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, x, 2.0), [0.0, 2.0, 4.0])
    assert len(_stored(folder, "scaled")) == 1
    exported.use_directory(folder)  # as a later process finds the folder: nothing loaded yet
    np.testing.assert_array_equal(exported.call("scaled", _scaled, x + 1, 2.0), [2.0, 4.0, 6.0])
    np.testing.assert_array_equal(exported.call("scaled", jax.jit(_never_traced), x, 2.0), [0.0, 2.0, 4.0])
    assert len(_stored(folder, "scaled")) == 1


def test_a_program_stays_compiled_through_the_next_programs_export(folder, monkeypatch):
    """With the persistent compilation cache on, an export clears JAX's caches: a program `call` ran before is held
    compiled (with `COMPILER_OPTIONS`), not compiled or read back again. Each program is compiled once."""
    assert jax.config.jax_compilation_cache_dir  # the suite's (conftest.py)
    compiles = []
    compile_as_jax = jax.stages.Lowered.compile

    def counted(self, **options):
        compiles.append(options)
        return compile_as_jax(self, **options)

    monkeypatch.setattr(jax.stages.Lowered, "compile", counted)
    x = jnp.arange(3.0)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, x, 2.0), [0.0, 2.0, 4.0])
    np.testing.assert_array_equal(exported.call("scaled", _scaled, x, 3.0), [0.0, 3.0, 6.0])  # exported, caches cleared
    np.testing.assert_array_equal(exported.call("scaled", _scaled, x + 1, 2.0), [2.0, 4.0, 6.0])
    assert compiles == [{"compiler_options": exported.COMPILER_OPTIONS}] * 2


def test_a_jaxlib_without_the_compiler_options_compiles_without_them(folder, monkeypatch):
    monkeypatch.setattr(exported, "COMPILER_OPTIONS", {"xla_no_such_option_anywhere": ""})
    monkeypatch.setattr(exported, "_options_known", True)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, jnp.arange(3.0), 5.0), [0.0, 5.0, 10.0])
    assert exported._options_known is False  # asked once: the next programs compile with XLA's defaults straight away


def test_static_values_shapes_dtypes_and_settings_each_get_their_own_program(folder):
    x = jnp.arange(3.0)
    cases = [
        (lambda: exported.call("scaled", _scaled, x, 2.0), [0.0, 2.0, 4.0]),
        (lambda: exported.call("scaled", _scaled, x, 3.0), [0.0, 3.0, 6.0]),
        (lambda: exported.call("scaled", _scaled, jnp.arange(4.0), 2.0), [0.0, 2.0, 4.0, 6.0]),
        (lambda: exported.call("scaled", _scaled, jnp.arange(3), 2), [0, 2, 4]),
        (lambda: exported.call("scaled", _scaled, jnp.asarray(1.0), 2.0), 2.0),  # weakly typed
    ]
    for count, (run, expected) in enumerate(cases, start=1):
        np.testing.assert_array_equal(run(), expected)
        assert len(_stored(folder, "scaled")) == count
    with ranges_guaranteed():
        exported.call("scaled", _scaled, x, 2.0)
    with jax.default_matmul_precision("highest"):
        exported.call("scaled", _scaled, x, 2.0)
    assert len(_stored(folder, "scaled")) == len(cases) + 2


def test_what_a_program_closes_over_keys_it_by_value(folder):
    x = jnp.arange(3.0)

    def closing_over(weights):
        return jax.jit(lambda x: x * weights)

    for weights in (jnp.asarray([1.0, 2.0, 3.0]), jnp.asarray([1.0, 2.0, 4.0])):
        result = exported.call("closing", closing_over(weights), x, closed_over=weights)
        np.testing.assert_array_equal(result, x * weights)
    assert len(_stored(folder, "closing")) == 2
    exported.use_directory(folder)
    np.testing.assert_array_equal(
        exported.call("closing", jax.jit(_never_traced), x, closed_over=jnp.asarray([1.0, 2.0, 4.0])), [0.0, 2.0, 8.0]
    )


@dataclasses.dataclass(frozen=True)
class _Elsewhere:
    """A class outside the packages a key versions: its code can change under the same name."""

    factor: float


def test_arguments_no_key_can_describe_are_run_as_they_are(folder):
    x = jnp.arange(3.0)
    applied = eqx.filter_jit(lambda x, function: function(x))
    np.testing.assert_array_equal(exported.call("closure", applied, x, lambda v: v * 5.0), [0.0, 5.0, 10.0])
    scaled_by = eqx.filter_jit(lambda x, owner: x * owner.factor)
    np.testing.assert_array_equal(exported.call("elsewhere", scaled_by, x, _Elsewhere(4.0)), [0.0, 4.0, 8.0])
    assert not list(folder.iterdir())


def test_a_program_jax_cannot_export_is_run_as_it_is(folder):
    """A host callback (`equinox.error_if` with a traced value) cannot be exported: the plain call still checks."""
    checked = eqx.filter_jit(lambda x: eqx.error_if(x, x < 0, "negative"))
    np.testing.assert_array_equal(exported.call("checked", checked, jnp.arange(2.0)), [0.0, 1.0])
    with pytest.raises(Exception, match="negative"):
        jax.block_until_ready(exported.call("checked", checked, -jnp.ones(2)))
    assert not _stored(folder, "checked")


def test_a_damaged_file_is_exported_again(folder):
    x = jnp.arange(3.0)
    exported.call("scaled", _scaled, x, 2.0)
    (stored,) = folder.glob("scaled-*.jaxexport")
    stored.write_bytes(b"not a program")
    exported.use_directory(folder)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, x, 2.0), [0.0, 2.0, 4.0])
    exported.use_directory(folder)
    np.testing.assert_array_equal(exported.call("scaled", jax.jit(_never_traced), x, 2.0), [0.0, 2.0, 4.0])


def test_without_a_folder_nothing_is_stored(tmp_path):
    exported.use_directory(None)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, jnp.arange(3.0), 2.0), [0.0, 2.0, 4.0])
    with pytest.raises(AssertionError, match="traced"):
        exported.call("scaled", jax.jit(_never_traced), jnp.arange(3.0), 2.0)


def test_the_folder_keeps_the_most_recently_used_programs_under_its_cap(folder, monkeypatch):
    x = jnp.arange(3.0)
    exported.call("scaled", _scaled, x, 1.0)
    size = next(folder.glob("*.jaxexport")).stat().st_size
    monkeypatch.setattr(exported, "MAX_BYTES", int(2.5 * size))
    for factor in (2.0, 3.0, 4.0):
        exported.call("scaled", _scaled, x, factor)
    assert len(_stored(folder, "scaled")) == 2
    exported.use_directory(folder)
    for factor in (3.0, 4.0):  # the two stored last are kept
        np.testing.assert_array_equal(exported.call("scaled", jax.jit(_never_traced), x, factor), x * factor)


HEIGHT, WIDTH = 12, 16


def _problem():
    coverage = np.zeros((HEIGHT, WIDTH), np.float32)
    coverage[7:] = 1.0
    coverage[3:, 5:7] = 1.0
    color = np.where(coverage[..., None] > 0, 0.05, 0.4).astype(np.float32) + np.linspace(0, 0.02, 3, dtype=np.float32)
    depth = np.where(coverage > 0, 10.0, np.inf).astype(np.float32)
    frame = gr.Buffers(color=jnp.asarray(color), depth=jnp.asarray(depth), coverage=jnp.asarray(coverage))
    effect = gr.GodRays(source="disc", flare_size=4.0, units="px", flare_shape="cone", max_samples=7, num_samples=7.0)
    light = jnp.array([8.5, 2.0])
    target = eqx.tree_at(lambda e: e.density, effect, jnp.asarray(0.8, jnp.float32))(frame, light)
    return effect, frame, light, target


FIXED = ("weight", "flare_size", "threshold", "tint", "offscreen_fade", "num_samples", "exposure")


def _fit_and_look(effect, frame, light, target):
    result = fit(effect, frame, light, target, fixed=FIXED, max_steps=4)
    found = determination(result.effect, frame, light, target, fitted=result.fitted)
    return result, found, render_compiled(result.rounded, frame, light, True)


def test_a_fit_from_stored_programs_equals_the_fit_traced(tmp_path, monkeypatch):
    """The solver's state crosses the stored steps as its leaves alone: every number is the traced fit's."""
    problem = _problem()
    traced = _fit_and_look(*problem)
    exported.use_directory(tmp_path)
    try:
        stored = _fit_and_look(*problem)
        names = {p.name.rsplit("-", 1)[0] for p in tmp_path.glob("*.jaxexport")}
        assert names == {"fit_jacobian", "fit_image_loss", "render"}
        exported.use_directory(tmp_path)
        rendered = []
        call = gr.GodRays.__call__
        monkeypatch.setattr(gr.GodRays, "__call__", lambda *args, **kwargs: rendered.append(1) or call(*args, **kwargs))
        read_back = _fit_and_look(*problem)
        assert not rendered, "a stored program was traced again"
    finally:
        exported.use_directory(None)
    for result, found, image in (stored, read_back):
        assert result.steps == traced[0].steps and result.converged == traced[0].converged
        # Near the minimum the loss is a sum of squares of small differences, each with the float32 rounding of the
        # values it is taken between; the stored program (`jax.export`'s module, the copies' loop a called function
        # since 1dd54d1) and the traced one round differently: 2.4e-6 of the last loss, 1.8e-10 of the start's.
        start = traced[0].loss_history[0]
        np.testing.assert_allclose(result.loss_history, traced[0].loss_history, rtol=1e-6, atol=1e-6 * start)
        np.testing.assert_allclose(result.effect.density, traced[0].effect.density, rtol=1e-6)
        assert found.poorly_determined == traced[1].poorly_determined
        np.testing.assert_allclose(found.condition, traced[1].condition, rtol=1e-4)
        np.testing.assert_allclose(image, traced[2], rtol=1e-6, atol=1e-7)


def test_render_compiled_names_a_field_outside_its_range():
    effect, frame, light, _ = _problem()
    wild = eqx.tree_at(lambda e: e.density, effect, jnp.asarray(7.0, jnp.float32))  # tree_at skips the Module's checks
    with pytest.raises(ValueError, match=r"effect.density = 7.0 lies outside its fitting range"):
        render_compiled(wild, frame, light, True)


def test_render_compiled_inside_jit_checks_traced_fields_when_run():
    effect, frame, light, _ = _problem()

    @jax.jit
    def rendered(count):
        return render_compiled(eqx.tree_at(lambda e: e.num_samples, effect, count), frame, light, True)

    expected = render_compiled(eqx.tree_at(lambda e: e.num_samples, effect, jnp.float32(5.0)), frame, light, True)
    np.testing.assert_allclose(rendered(jnp.float32(5.0)), expected, rtol=1e-6)
    with pytest.raises(Exception, match=r"num_samples must lie in \[0, max_samples=7\]"):
        jax.block_until_ready(rendered(jnp.float32(20.0)))


def test_a_folder_that_cannot_be_written_only_means_nothing_is_stored(folder, monkeypatch):
    def refused(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(exported, "atomic_write", refused)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, jnp.arange(3.0), 2.0), [0.0, 2.0, 4.0])
    assert not _stored(folder, "scaled")


@eqx.filter_jit
def _sevens(x, factor):
    return jnp.full_like(x, 7.0)


def _planted(folder) -> Path:
    """The program stored for `_scaled(arange(3.0), 2.0)`, replaced by one of the same signature that returns 7s."""
    x = jnp.arange(3.0)
    exported.call("scaled", _scaled, x, 2.0)
    (stored,) = folder.glob("scaled-*.jaxexport")
    exported.use_directory(folder)
    exported.call("sevens", _sevens, x, 2.0)
    (planted,) = folder.glob("sevens-*.jaxexport")
    os.replace(planted, stored)
    return stored


def test_programs_are_never_read_from_a_folder_other_users_can_write(folder):
    _planted(folder)
    os.chmod(folder, 0o777)
    with pytest.raises(PermissionError, match="other users can write to it"):
        exported.use_directory(folder)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, jnp.arange(3.0), 2.0), [0.0, 2.0, 4.0])


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="giving a file away takes root")
def test_a_program_another_user_owns_is_never_read(folder):
    stored = _planted(folder)
    os.chown(stored, 65534, 65534)
    exported.use_directory(folder)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, jnp.arange(3.0), 2.0), [0.0, 2.0, 4.0])


def test_a_link_in_the_folder_is_never_followed(folder, tmp_path_factory):
    stored = _planted(folder)
    elsewhere = tmp_path_factory.mktemp("elsewhere") / "program.jaxexport"
    os.replace(stored, elsewhere)
    stored.symlink_to(elsewhere)
    exported.use_directory(folder)
    np.testing.assert_array_equal(exported.call("scaled", _scaled, jnp.arange(3.0), 2.0), [0.0, 2.0, 4.0])
    assert elsewhere.exists()


def test_the_folder_is_created_for_its_user_alone(tmp_path):
    exported.use_directory(tmp_path / "new" / "programs")
    assert (tmp_path / "new" / "programs").stat().st_mode & 0o777 == 0o700
    exported.call("scaled", _scaled, jnp.arange(3.0), 2.0)
    assert all(p.stat().st_mode & 0o077 == 0 for p in (tmp_path / "new" / "programs").iterdir())


@pytest.mark.parametrize("cache_on", [False, True])
def test_exporting_drops_jaxs_traces_only_where_the_compilation_cache_keeps_what_was_compiled(
    folder, tmp_path, cache_on
):
    """A program's trace is not needed once it is exported, and JAX's caches would hold it under the compile that
    follows; they are cleared only where the persistent cache gives back what they held compiled (the command's)."""
    earlier = jax.jit(lambda x: x + 1.0)
    earlier(jnp.arange(3.0))
    previous = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "compiled") if cache_on else None)
    try:
        np.testing.assert_array_equal(exported.call("scaled", _scaled, jnp.arange(5.0), 4.0), 4.0 * np.arange(5))
        assert earlier._cache_size() == (0 if cache_on else 1)
        np.testing.assert_array_equal(earlier(jnp.arange(3.0)), [1.0, 2.0, 3.0])
    finally:
        jax.config.update("jax_compilation_cache_dir", previous)
