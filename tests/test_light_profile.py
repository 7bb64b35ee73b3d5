"""`profile_light`: the light placed by the losses of fits around it, on losses of known shape."""

import numpy as np
import pytest

from godrays_jax.pipeline.light_profile import profile_light

TRUE = np.asarray([100.3, 40.7])
START = np.asarray([108.0, 61.0])  # as far as `find_light` has left a light from the one drawn, mostly in y
STEP = 9.6  # `PROFILE_STEP` of a 320-pixel frame


def bowl(xy):
    return float(np.sum(np.asarray([1.0, 2.0]) * (xy - TRUE) ** 2))


def cusp(xy):
    """Sharp at the light, as a fit whose shafts meet there: steepest right at it."""
    distance = np.linalg.norm(xy - TRUE)
    return float(np.sqrt(distance) + 0.01 * distance**2)


@pytest.mark.parametrize("loss", [bowl, cusp], ids=["bowl", "cusp"])
def test_the_light_is_placed_where_the_loss_is_lowest(loss):
    tried = []

    def counted(xy):
        tried.append(xy)
        return loss(xy)

    profile = profile_light(counted, START, step=STEP)
    assert np.linalg.norm(profile.light_xy - TRUE) < (0.05 if loss is bowl else 1.0), profile.light_xy
    # Each light is fitted once, and the profile records every fit it ran, in order.
    assert len(tried) == len({tuple(xy) for xy in tried}) == len(profile.losses) <= 20
    np.testing.assert_array_equal(profile.tried, np.asarray(tried))
    np.testing.assert_array_equal(profile.losses, [loss(xy) for xy in tried])


def test_a_flat_loss_leaves_the_light_where_it_starts():
    profile = profile_light(lambda xy: 1.0, START, step=STEP, visible_rise=1e-6)
    np.testing.assert_array_equal(profile.light_xy, START)
    # And says that the fits do not place it: no move raises their loss.
    np.testing.assert_array_equal(profile.visible_shift, [np.inf, np.inf])


def test_how_far_the_light_moves_before_a_fit_loss_rises_visibly():
    """On a bowl `x^2 + 2 y^2` (loss per pixel squared) a rise of `r` is `sqrt(r)` in x and `sqrt(r / 2)` in y; with
    noise on each fit's loss, as a fit's own stopping gives it, the same within its scatter; along an axis whose
    losses fall away from the light (a ridge), no move raises them."""
    rise = 4.0
    profile = profile_light(bowl, START, step=STEP, visible_rise=rise)
    np.testing.assert_allclose(profile.visible_shift, [2.0, np.sqrt(2.0)], rtol=1e-9)
    noise = np.random.default_rng(0)
    noisy = profile_light(lambda xy: bowl(xy) * (1.0 + 0.01 * noise.standard_normal()), START, step=STEP, visible_rise=rise)
    np.testing.assert_allclose(noisy.visible_shift, [2.0, np.sqrt(2.0)], rtol=0.1)
    ridge = profile_light(lambda xy: bowl(xy) - 3.0 * (xy[1] - TRUE[1]) ** 2, START, step=STEP, visible_rise=rise)
    assert ridge.visible_shift[0] == pytest.approx(2.0, rel=1e-6) and ridge.visible_shift[1] == np.inf, ridge
    # Unmeasured without a rise, or with fewer than six fits within the first step of the light placed.
    assert np.all(np.isnan(profile_light(bowl, START, step=STEP).visible_shift))
    assert np.all(np.isnan(profile_light(bowl, START, step=STEP, rounds=0, visible_rise=rise).visible_shift))


def test_a_fit_that_fails_counts_as_the_highest_loss():
    """A side whose fit diverges (NaN) is never moved to; the other side's lower loss still is."""

    def loss(xy):
        return np.nan if xy[1] < START[1] - 1.0 else float(np.sum((xy - (START + [0.0, 30.0])) ** 2))

    profile = profile_light(loss, START, step=STEP)
    assert profile.light_xy[1] > START[1] + 20.0, profile.light_xy
    assert np.all(np.isinf(profile.losses[np.isnan([loss(xy) for xy in profile.tried])]))


@pytest.mark.parametrize(
    ("arguments", "named"),
    [({"step": 0.0}, "step"), ({"rounds": -1}, "rounds"), ({"max_moves": 1.5}, "max_moves"),
     ({"start_xy": (1.0, np.inf)}, "start_xy"), ({"start_xy": (1.0, 2.0, 3.0)}, "start_xy"),
     ({"visible_rise": 0.0}, "visible_rise")],
)  # fmt: skip
def test_errors_name_the_argument(arguments, named):
    given = {"start_xy": START, "step": STEP, **arguments}
    with pytest.raises(ValueError, match=named):
        profile_light(bowl, given.pop("start_xy"), **given)
