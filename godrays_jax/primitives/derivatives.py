"""Values computed one way, derivatives taken through another that computes the same values."""

from collections.abc import Callable

import jax


def with_derivatives_of(full: Callable, cheap: Callable, args):
    """`cheap(args)`, with the derivatives (forward and reverse mode) of `full(args)`, which must give the same
    values: `cheap` may skip work that a derivative's lanes cannot (a mask's compaction, a loop whose trip count
    the values set) or that reverse mode cannot transpose (a `while_loop`). Both may close over traced values
    (`jax.closure_convert`); the derivatives flow through `full`'s closure alone."""
    full_converted, full_consts = jax.closure_convert(full, args)
    cheap_converted, cheap_consts = jax.closure_convert(cheap, args)

    @jax.custom_jvp
    def values(args, full_consts, cheap_consts):
        return cheap_converted(args, *cheap_consts)

    @values.defjvp
    def derivatives(primals, tangents):
        (args, full_consts, _), (args_tangent, full_consts_tangent, _) = primals, tangents
        return jax.jvp(lambda a, c: full_converted(a, *c), (args, full_consts), (args_tangent, full_consts_tangent))

    return values(args, full_consts, cheap_consts)
