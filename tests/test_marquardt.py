"""`pipeline.marquardt`: Levenberg-Marquardt on the host, against optimistix's and NumPy's damped normal equations."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from godrays_jax.pipeline.marquardt import LevenbergMarquardt, normal_equations


def _curve(y, data):
    """Residuals of a small nonlinear least-squares problem: `a * exp(-b * t) + c` against samples."""
    t, samples, scale = data
    a, b, c = y[0] * scale[0], y[1] * scale[1], y[2] * scale[2]
    return a * jnp.exp(-b * t) + c - samples


def _data(scale):
    t = jnp.linspace(0.0, 4.0, 40)
    samples = 2.0 * jnp.exp(-0.7 * t) + 0.3 + 0.01 * jnp.sin(7.0 * t)
    return t, samples, jnp.asarray(scale, t.dtype)


def _evaluator(data, residuals=_curve):
    def evaluate(y):
        y = jnp.asarray(y)
        r, jacobian = np.asarray(residuals(y, data)), np.asarray(jax.jacfwd(residuals)(y, data))
        return r, lambda: normal_equations(jacobian, r)

    return evaluate


def _iterates(solver, y0, data, steps, residuals=_curve):
    """The last accepted unknowns after each of `steps` solver steps."""
    evaluate, state, found = _evaluator(data, residuals), solver.init(np.asarray(y0)), []
    for _ in range(steps):
        state = solver.step(state, evaluate)
        found.append(state.y)
    return found


@pytest.mark.usefixtures("x64")
def test_it_takes_optimistix_levenberg_marquardts_steps():
    """Unscaled, every step is optimistix's (its trust region, damping and first step alike), to rounding."""
    y0 = jnp.asarray([1.0, 0.2, 0.0])
    data = _data([1.0, 1.0, 1.0])
    function = lambda y, args: (_curve(y, args), None)  # noqa: E731 - optimistix's (residuals, aux) form
    solver = optx.LevenbergMarquardt(1e-10, 1e-12)
    state = solver.init(function, y0, data, {}, jax.eval_shape(lambda: _curve(y0, data)), None, frozenset())
    y, expected = y0, []
    for _ in range(8):
        y, state, _ = solver.step(function, y, data, {}, state, frozenset())
        expected.append(np.asarray(y))
    for ours, theirs in zip(_iterates(LevenbergMarquardt(1e-10, 1e-12), y0, data, 8), expected):
        np.testing.assert_allclose(ours, theirs, rtol=1e-8, atol=1e-12)


@pytest.mark.usefixtures("x64")
def test_the_scaled_step_solves_the_damped_normal_equations():
    data = _data([1.0, 1.0, 1.0])
    y = np.asarray([1.5, 0.4, 0.1])
    _, linearise = _evaluator(data)(y)
    normal, gradient = linearise()
    step_size = 0.25
    step = LevenbergMarquardt(1e-10, 1e-12, scaled=True)._damped_step(normal, gradient, step_size)
    expected = np.linalg.solve(normal + np.diag(np.diag(normal)) / step_size, -gradient)
    np.testing.assert_allclose(step, expected, rtol=1e-10)
    # The plain damping (lambda I) is another step: the test tells the two apart.
    plain = LevenbergMarquardt(1e-10, 1e-12)._damped_step(normal, gradient, step_size)
    assert not np.allclose(plain, expected, rtol=1e-3)


@pytest.mark.usefixtures("x64")
def test_scaled_steps_do_not_depend_on_how_each_unknown_is_scaled():
    """The same problem with `b` measured in units 30 times larger: the iterates are the same point; the plain
    damping's are not."""
    y0 = np.asarray([1.0, 0.2, 0.0])
    scale = np.asarray([1.0, 1.0 / 30.0, 1.0])
    scaled = LevenbergMarquardt(1e-10, 1e-12, scaled=True)
    plain, rescaled = _iterates(scaled, y0, _data([1.0, 1.0, 1.0]), 6), _iterates(scaled, y0 / scale, _data(scale), 6)
    for one, other in zip(plain, rescaled):
        np.testing.assert_allclose(one, other * scale, rtol=1e-7, atol=1e-12)
    unscaled = LevenbergMarquardt(1e-10, 1e-12)
    plain, rescaled = _iterates(unscaled, y0, _data([1.0, 1.0, 1.0]), 6), _iterates(unscaled, y0 / scale, _data(scale), 6)
    assert not np.allclose(plain[-1], rescaled[-1] * scale, rtol=1e-3)


@pytest.mark.usefixtures("x64")
def test_it_solves_a_badly_scaled_problem_and_leaves_an_unknown_that_changes_nothing():
    """Unknowns 10^4 apart in scale, and a fourth the residuals do not depend on: the minimum, the fourth kept."""
    data = _data([1.0, 1e-4, 1.0])

    def residuals(y, args):
        return _curve(y[:3], args) + 0.0 * y[3]

    solver = LevenbergMarquardt(1e-10, 1e-12, scaled=True)
    evaluate, state = _evaluator(data, residuals), solver.init(np.asarray([1.0, 2000.0, 0.0, 0.5]))
    for _ in range(200):
        state = solver.step(state, evaluate)
        if state.done:
            break
    t, samples, _ = data
    expected = optx.least_squares(
        lambda y, args: _curve(y, (t, samples, jnp.ones(3))), optx.LevenbergMarquardt(1e-12, 1e-14),
        jnp.asarray([1.0, 0.2, 0.0]), max_steps=400,
    ).value  # fmt: skip
    assert state.done
    np.testing.assert_allclose(state.y[:3] * [1.0, 1e-4, 1.0], expected, rtol=1e-6)
    assert state.y[3] == 0.5


def test_the_normal_equations_by_blocks_are_the_whole_ones():
    rng = np.random.default_rng(0)
    jacobian, residuals = rng.normal(size=(1000, 4)).astype(np.float32), rng.normal(size=1000).astype(np.float32)
    normal, gradient = normal_equations(jacobian, residuals, rows=128)
    whole = jacobian.astype(np.float64)
    np.testing.assert_allclose(normal, whole.T @ whole, rtol=1e-12)
    np.testing.assert_allclose(gradient, whole.T @ residuals.astype(np.float64), rtol=1e-12)


@pytest.mark.usefixtures("x64")
def test_a_step_linearises_only_the_points_it_accepts():
    """A rejected step costs its residuals only: the normal equations are asked for at accepted points alone."""
    data, accepted_losses, linearised = _data([1.0, 1.0, 1.0]), [], []
    full = _evaluator(data)

    def evaluate(y):
        residuals, linearise = full(y)

        def counted():
            linearised.append(float(np.sum(np.square(residuals))))
            return linearise()

        return residuals, counted

    solver = LevenbergMarquardt(1e-10, 1e-12)
    state = solver.init(np.asarray([10.0, 0.0, 3.0]))  # far off: some steps overshoot and are rejected
    losses = []
    for _ in range(12):
        before = None if state.residuals is None else state.loss
        state = solver.step(state, evaluate)
        losses.append((before, state.loss))
        if before is None or state.loss != before:
            accepted_losses.append(state.loss)
        assert state.rejected == (before is not None and state.loss == before)
    rejected = sum(1 for before, after in losses if before is not None and after == before)
    assert rejected > 0
    np.testing.assert_allclose(linearised, accepted_losses, rtol=1e-12)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("scaled", [False, True])
def test_held_unknowns_stay_and_the_others_descend_as_without_them(scaled):
    """`held` unknowns stay where they start, and the others take the steps of the same problem with the held
    ones' values fixed (their columns left out of the normal equations)."""
    y0 = np.asarray([1.0, 0.2, 0.5])
    data = _data([1.0, 1.0, 1.0])
    held = _iterates(LevenbergMarquardt(1e-10, 1e-12, scaled=scaled, held=(2,)), y0, data, 6)
    assert all(y[2] == 0.5 for y in held)

    def two(y, data):
        return _curve(jnp.concatenate([y, jnp.asarray([0.5])]), data)

    alone = _iterates(LevenbergMarquardt(1e-10, 1e-12, scaled=scaled), y0[:2], data, 6, residuals=two)
    for ours, theirs in zip(held, alone):
        np.testing.assert_allclose(ours[:2], theirs, rtol=1e-10, atol=1e-12)
    assert np.linalg.norm(held[-1][:2] - y0[:2]) > 0.1  # they did descend


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("scaled", [False, True])
def test_the_fall_predicted_for_a_linear_problem_is_the_proposals_own(scaled):
    """Residuals linear in the unknowns: the linear model is the loss itself, so the fall it predicts for the next
    proposal is the one the proposal's loss shows, as a fraction of the loss at the last accepted point."""
    rng = np.random.default_rng(0)
    matrix, target = rng.normal(size=(12, 3)), rng.normal(size=12)
    evaluate = _evaluator(None, lambda y, data: jnp.asarray(matrix) @ y - jnp.asarray(target))
    solver = LevenbergMarquardt(1e-10, 1e-12, scaled=scaled)
    state = solver.init(np.asarray([5.0, -3.0, 2.0]))
    assert state.predicted_fall == 0.0  # nothing linearised yet
    for _ in range(3):
        state = solver.step(state, evaluate)
        at_proposal = float(np.sum(np.square(matrix @ state.proposal - target)))
        assert 0.0 < state.predicted_fall < 1.0
        np.testing.assert_allclose(state.predicted_fall, 1.0 - at_proposal / state.loss, rtol=1e-9)
