"""`pipeline.marquardt`: Levenberg-Marquardt damped by `diag(J^T J)`, against NumPy's damped normal equations."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest

from godrays_jax.pipeline.marquardt import ScaledDampedNewtonDescent, ScaledLevenbergMarquardt


def _curve(y, data):
    """Residuals of a small nonlinear least-squares problem: `a * exp(-b * t) + c` against samples."""
    t, samples, scale = data
    a, b, c = y[0] * scale[0], y[1] * scale[1], y[2] * scale[2]
    return a * jnp.exp(-b * t) + c - samples


def _data(scale):
    t = jnp.linspace(0.0, 4.0, 40)
    samples = 2.0 * jnp.exp(-0.7 * t) + 0.3 + 0.01 * jnp.sin(7.0 * t)
    return t, samples, jnp.asarray(scale, t.dtype)


def _iterates(solver, y0, data, steps):
    """The unknowns after each of `steps` solver steps."""
    function = lambda y, args: (_curve(y, args), None)  # noqa: E731 - optimistix's (residuals, aux) form
    f_struct = jax.eval_shape(lambda: function(y0, data)[0])
    state = solver.init(function, y0, data, {}, f_struct, None, frozenset())
    y, found = y0, []
    for _ in range(steps):
        y, state, _ = solver.step(function, y, data, {}, state, frozenset())
        found.append(np.asarray(y))
    return found


@pytest.mark.usefixtures("x64")
def test_the_step_solves_the_damped_normal_equations():
    data = _data([1.0, 1.0, 1.0])
    y = jnp.asarray([1.5, 0.4, 0.1])
    residual = _curve(y, data)
    jacobian = jax.jacfwd(_curve)(y, data)
    descent = ScaledDampedNewtonDescent(linear_solver=lx.Normal(lx.Cholesky()))
    f_info = optx.FunctionInfo.ResidualJac(residual, lx.MatrixLinearOperator(jacobian))
    state = descent.query(y, f_info, descent.init(y, f_info))
    step_size = 0.25
    step, result = descent.step(jnp.asarray(step_size), state)
    j, r = np.asarray(jacobian), np.asarray(residual)
    normal = j.T @ j
    expected = np.linalg.solve(normal + np.diag(np.diag(normal)) / step_size, -j.T @ r)
    assert result == optx.RESULTS.successful
    np.testing.assert_allclose(step, expected, rtol=1e-10)
    # optimistix's own damping (lambda I) is another step: the test tells the two apart.
    assert not np.allclose(np.linalg.solve(normal + np.eye(3) / step_size, -j.T @ r), expected, rtol=1e-3)


@pytest.mark.usefixtures("x64")
def test_its_steps_do_not_depend_on_how_each_unknown_is_scaled():
    """The same problem with `b` measured in units 30 times larger: the iterates are the same point.

    (Within the floor of the damping: a column more than 1000 times smaller than the largest is damped as one 1000
    times smaller.)"""
    y0 = jnp.asarray([1.0, 0.2, 0.0])
    scale = np.asarray([1.0, 1.0 / 30.0, 1.0])
    plain = _iterates(ScaledLevenbergMarquardt(1e-10, 1e-12), y0, _data([1.0, 1.0, 1.0]), 6)
    rescaled = _iterates(ScaledLevenbergMarquardt(1e-10, 1e-12), y0 / scale, _data(scale), 6)
    for one, other in zip(plain, rescaled):
        np.testing.assert_allclose(one, other * scale, rtol=1e-7, atol=1e-12)
    # optimistix's LevenbergMarquardt takes other steps once an unknown is rescaled.
    unscaled = optx.LevenbergMarquardt(1e-10, 1e-12)
    plain, rescaled = _iterates(unscaled, y0, _data([1.0, 1.0, 1.0]), 6), _iterates(unscaled, y0 / scale, _data(scale), 6)
    assert not np.allclose(plain[-1], rescaled[-1] * scale, rtol=1e-3)


@pytest.mark.usefixtures("x64")
def test_it_solves_a_badly_scaled_problem_and_leaves_an_unknown_that_changes_nothing():
    """Unknowns 10^4 apart in scale, and a fourth the residuals do not depend on: the minimum, the fourth kept."""
    data = _data([1.0, 1e-4, 1.0])

    def residuals(y, args):
        return _curve(y[:3], args) + 0.0 * y[3], None

    solution = optx.least_squares(residuals, ScaledLevenbergMarquardt(1e-10, 1e-12), jnp.asarray([1.0, 2000.0, 0.0, 0.5]),
                                  args=data, max_steps=200, has_aux=True)  # fmt: skip
    t, samples, _ = data
    expected = optx.least_squares(
        lambda y, args: _curve(y, (t, samples, jnp.ones(3))), optx.LevenbergMarquardt(1e-12, 1e-14),
        jnp.asarray([1.0, 0.2, 0.0]), max_steps=400,
    ).value  # fmt: skip
    found = np.asarray(solution.value)
    np.testing.assert_allclose(found[:3] * [1.0, 1e-4, 1.0], expected, rtol=1e-6)
    assert found[3] == 0.5
    assert np.all(np.isfinite(found))
