"""Effects' fields: how they are declared (`param`, `count_param`, `size_param`, `static`, `size_reach`,
`texture_field`, `part`), what the declarations say (`field_metadata`, `FieldInfo`), and `Part`, the base class that
checks every field against its declaration (effects and the parts they hold).

One source for each fact about a field: its range, whether it is a count and
which static field caps it, whether it is a size, its old names. The
constructors' checks, `fit`, the tuner and params files read it here.
"""

import dataclasses
import functools
import reprlib
import typing
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from godrays_jax.primitives.checks import is_static_int


MAX_SEED = 2**63 - 1
"""The largest static integer that is not a loop length (a seed): any non-negative 64-bit value."""

MAX_REACH: dict[str, float] = {"frame": 1.0, "px": 4096.0}
"""The largest static size (a blur's or a morphology's reach) per unit system: the whole frame, or 4096 pixels."""


def _is_numbers(value) -> bool:
    if isinstance(value, jax.core.Tracer):
        return True
    if isinstance(value, (jax.Array, np.ndarray, np.generic)):
        return value.dtype.kind in "fiu"
    if isinstance(value, bool) or not isinstance(value, (int, float, list, tuple)):
        return False
    try:
        return np.asarray(value).dtype.kind in "fiu"  # ragged or too deep lists raise; huge ints are objects
    except (ValueError, TypeError, OverflowError, RecursionError):
        return False


def _array(value) -> Array:
    # Anything but numbers is kept as given, so that `__check_init__` names the field:
    # a JSON "0.5" or true is not a number.
    return jnp.asarray(value, dtype=jnp.result_type(float)) if _is_numbers(value) else value


_SHOWN = reprlib.Repr()
_SHOWN.maxlevel, _SHOWN.maxstring, _SHOWN.maxother = 3, 40, 40


def _check_fittable(owner: str, name: str, value, bounds, size: bool) -> None:
    """A fittable field's value: numbers (any shape the converter made an array of) inside `bounds`, sizes >= 0."""
    if not isinstance(value, jax.Array):
        raise ValueError(f"{owner}.{name} must be a number (a list of numbers for a vector), got {_SHOWN.repr(value)}")
    values = np.asarray(value)
    if size and not float(np.min(values)) >= 0:
        raise ValueError(f"{owner}.{name} must be >= 0, got {value!r}")
    low, high = bounds
    if not (np.all(np.isfinite(values)) and np.all(values >= low) and np.all(values <= high)):
        raise ValueError(f"{owner}.{name} must lie in [{low:g}, {high:g}], got {values.tolist()}")


def _check_static(owner: str, name: str, annotation, value, bounds) -> None:
    """A static field's value against its annotation (`bool`, `int` within `bounds`, `Literal`, `float`, `str`)."""
    shown = _SHOWN.repr(value)
    if annotation is bool:
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{owner}.{name} must be true or false (a boolean), got {shown}")
    elif annotation is int:
        if not is_static_int(value):
            raise ValueError(f"{owner}.{name} must be an integer, got {shown}")
        low, high = bounds
        if not low <= value <= high:
            raise ValueError(f"{owner}.{name} must lie in [{low}, {high}], got {value}")
    elif typing.get_origin(annotation) is Literal:
        if not isinstance(value, str) or value not in typing.get_args(annotation):
            raise ValueError(f"{owner}.{name} must be one of {', '.join(typing.get_args(annotation))}; got {shown}")
    elif annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not np.isfinite(value):
            raise ValueError(f"{owner}.{name} must be a finite number, got {shown}")
    elif annotation is str and not isinstance(value, str):
        raise ValueError(f"{owner}.{name} must be a string, got {shown}")


def plain_value(value):
    """A field's value as plain Python (float, nested lists of floats, or the static value itself).

    Floating arrays become the shortest decimals that read back to the same
    numbers in their own precision: a float32 0.95 is `0.95`, not
    `0.949999988079071`.
    """
    if not isinstance(value, (jax.Array, np.ndarray, np.generic)) or isinstance(value, jax.core.Tracer):
        return value
    array = np.asarray(value)
    if not np.issubdtype(array.dtype, np.floating):
        return array.tolist()
    # NumPy's str of a float32 scalar is the shortest decimal that round-trips; float() of it keeps that text.
    shortest = [float(str(number)) for number in array.ravel()]
    return np.array(shortest, dtype=object).reshape(array.shape).tolist()


MAX_TEXTURE_SIDE = 2048
"""The most texels a flare texture may have on a side: a flare covers a part of the frame, and a larger texture only
costs memory and time (resample it before)."""

MAX_TEXTURE_VALUE = 1e6
"""The largest magnitude of a flare texture's values: brighter flares come from the effect's gains, and float32 keeps
sums and squares of the frame's values finite."""


def _texture(value) -> Array | None:
    if value is None:
        return None
    shape = np.shape(value)  # before any copy: a texture too large is refused unread
    if len(shape) not in (2, 3) or min(shape) < 1:
        raise ValueError(f"flare_texture must have shape (h, w) or (h, w, C), got shape {shape}")
    channels = 1 if len(shape) == 2 else shape[2]
    if channels not in (1, 2, 3, 4):
        raise ValueError(
            f"flare_texture must have 1 (grey), 2 (grey and alpha), 3 (RGB) or 4 (RGBA) channels, got {channels}"
        )
    if max(shape[:2]) > MAX_TEXTURE_SIDE:
        raise ValueError(
            f"flare_texture is {shape[1]}x{shape[0]} texels, more than {MAX_TEXTURE_SIDE} on a side: resample it"
        )
    if not isinstance(value, jax.core.Tracer):
        try:
            values = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError("flare_texture must hold numbers") from None
        if (count := int(np.sum(~np.isfinite(values)))) > 0:
            raise ValueError(f"flare_texture has {count} value(s) that are NaN or infinite")
        if (count := int(np.sum(np.abs(values) > MAX_TEXTURE_VALUE))) > 0:
            raise ValueError(f"flare_texture has {count} value(s) beyond +-{MAX_TEXTURE_VALUE:g}: scale it down")
    texture = jnp.asarray(value, dtype=jnp.result_type(float))
    if texture.ndim == 2:
        texture = texture[..., None]
    # Alpha is premultiplied into the colour (as EXR and `read_image` hold it): what the flare adds is the colour.
    return texture[..., :1] if channels == 2 else texture[..., :3]


@dataclasses.dataclass(frozen=True)
class FieldInfo:
    """What one field of an effect is, as its declaration says (`param`, `count_param`, `size_param`, `static`,
    `size_reach`, `texture_field`): the one source that the constructor's checks, `fit`, the tuner and params files
    read.

    Attributes:
        name: the field's name.
        kind: `"fittable"` (a floating JAX scalar or vector that `fit` may change), `"static"` (a Python value that
            selects the algorithm and is part of the compiled program) or `"data"` (an array the effect samples and
            never fits: a texture).
        bounds: the inclusive valid range: a fittable field's (every element; a size's in frame units) or a static
            integer's; `None` for other static fields.
        px_bounds: a size's range under `units="px"` (pixels).
        size: whether it is a size, in frame units or in pixels as the effect's `units` says.
        count: whether it is an integer count, fitted through the kernels' continuous relaxation and rounded after.
        cap: the static field that caps its value (a count's loop length, a morphology's reach), or `None`.
        choices: the values a static name may take (its `Literal` annotation), or `None`.
        formerly: its old names, which params files may still use.
        decades: how many decades of its range a fittable field's values of interest span: `fit` then also races
            its starts with that field moved by ratios (0: by differences alone).
    """

    name: str
    kind: Literal["fittable", "static", "data"]
    bounds: tuple[float, float] | None = None
    px_bounds: tuple[float, float] | None = None
    size: bool = False
    count: bool = False
    cap: str | None = None
    choices: tuple[str, ...] | None = None
    formerly: tuple[str, ...] = ()
    decades: float = 0.0


def param(
    default, *, low: float, high: float, cap: str | None = None, formerly: tuple[str, ...] = (), decades: float = 0.0
):
    """A fittable field, stored as a floating JAX array whatever number or list is given.

    `[low, high]` is its valid range (every element, for a vector): fitting keeps
    the value inside it and the tuner's sliders span it; `cap` names a static
    field whose value lowers `high` for fitting. `formerly`: the field's old
    names, which params files may still use. `decades`: for a range whose
    values of interest span orders of magnitude, how many (the top `decades`
    decades of the range): `fit` races its starts a second time with the field
    moved by ratios there (`pipeline.problem.folded_positions`), where a step
    from 300 to 16 is as long as one from 3000 to 160; 0: by differences alone.
    """
    metadata = {"kind": "fittable", "bounds": (low, high), "cap": cap, "formerly": formerly, "decades": decades}
    return eqx.field(converter=_array, default=default, metadata=metadata)


def count_param(default: float, *, low: float, high: float, cap: str, formerly: tuple[str, ...] = ()):
    """A fittable integer count (`num_samples`, ...): fitted through its kernel's relaxation, at most the static `cap`.

    `cap` is the static field holding the loop length (`max_samples`, ...):
    fitting keeps the count at or below it and rounds it after.
    """
    metadata = {"kind": "fittable", "bounds": (low, high), "count": True, "cap": cap, "formerly": formerly}
    return eqx.field(converter=_array, default=default, metadata=metadata)


def size_param(
    default, *, low: float, high: float, px_high: float, cap: str | None = None, formerly: tuple[str, ...] = ()
):
    """A fittable size: in frame units within `[low, high]`, or in pixels within `[0, px_high]` under `units="px"`.

    `cap` names a static size that bounds it (a morphology's reach).
    """
    metadata = {
        "kind": "fittable", "bounds": (low, high), "px_bounds": (0.0, px_high), "size": True, "cap": cap,
        "formerly": formerly,
    }  # fmt: skip
    return eqx.field(converter=_array, default=default, metadata=metadata)


def static(default, *, low: int | None = None, high: int | None = None, formerly: tuple[str, ...] = ()):
    """A static field (a Python value that selects the algorithm), checked against its annotation.

    An `int` field takes its inclusive range `[low, high]` here (loop lengths
    stop at the top of the count they bound: a longer loop renders the same
    image more slowly, and a huge one hangs a render); a `Literal` field's
    choices are its annotation's.
    """
    bounds = None if low is None else (low, high)
    return eqx.field(static=True, default=default, metadata={"kind": "static", "bounds": bounds, "formerly": formerly})


def size_reach(default: float, *, formerly: tuple[str, ...] = ()):
    """A static size (a blur's or a morphology's reach, in frame units or pixels as the effect's `units`).

    At most `MAX_REACH` of its units.
    """
    return eqx.field(static=True, default=default, metadata={"kind": "static", "size": True, "formerly": formerly})


def texture_field():
    """An optional texture, linear values: data the effect samples, not fitted.

    `(h, w)` or `(h, w, C)` with C = 1 (grey), 2 (grey and alpha), 3 (RGB) or
    4 (RGBA); alpha is taken as premultiplied into the colour and dropped. At
    most `MAX_TEXTURE_SIDE` texels on a side; values finite, of magnitude at
    most `MAX_TEXTURE_VALUE`. `ValueError` naming the field otherwise.
    """
    return eqx.field(default=None, converter=_texture, metadata={"kind": "data"})


def part(default_factory, *, formerly: dict[str, str] | None = None):
    """A part the effect is made of (a `Part` or an `Effect`, its fields declared with the functions above).

    Its fields are the effect's, named `part.field` wherever fields are named
    (`field_metadata`, params files, `fit(fixed=...)`, the tuner).
    `formerly`: `{old name on the effect: the part's field}`, for params files
    written before the part existed.
    """
    return eqx.field(default_factory=default_factory, metadata={"kind": "part", "formerly": formerly or {}})


_type_hints = functools.cache(typing.get_type_hints)


@functools.cache
def _own_field_infos(cls) -> dict[str, FieldInfo]:
    """The class's own fields, parts as one entry each (kind `"part"`)."""
    hints = _type_hints(cls)
    infos = {}
    for field in dataclasses.fields(cls):
        metadata = field.metadata
        kind = metadata.get("kind", "static" if metadata.get("static") else "data")
        annotation = hints[field.name]
        choices = typing.get_args(annotation) if typing.get_origin(annotation) is Literal else None
        bounds = metadata.get("bounds")
        if kind == "static" and annotation is int and bounds is None:
            bounds = (0, MAX_SEED)
        formerly = () if kind == "part" else tuple(metadata.get("formerly", ()))
        infos[field.name] = FieldInfo(
            name=field.name, kind=kind, bounds=bounds, px_bounds=metadata.get("px_bounds"),
            size=metadata.get("size", False), count=metadata.get("count", False), cap=metadata.get("cap"),
            choices=choices, formerly=formerly, decades=metadata.get("decades", 0.0),
        )  # fmt: skip
    return infos


@functools.cache
def _field_infos(cls) -> dict[str, FieldInfo]:
    infos = {}
    for name, info in _own_field_infos(cls).items():
        if info.kind != "part":
            infos[name] = info
            continue
        renamed = next(f for f in dataclasses.fields(cls) if f.name == name).metadata["formerly"]
        for inner, inner_info in _field_infos(_type_hints(cls)[name]).items():
            olds = tuple(old for old, new in renamed.items() if new == inner)
            infos[f"{name}.{inner}"] = dataclasses.replace(
                inner_info,
                name=f"{name}.{inner}",
                cap=None if inner_info.cap is None else f"{name}.{inner_info.cap}",
                formerly=olds + tuple(f"{name}.{old}" for old in inner_info.formerly),
            )
    return infos


def field_metadata(effect: "Effect | type[Effect]") -> dict[str, FieldInfo]:
    """`{field name: FieldInfo}` for every field of an effect (instance or class), in declaration order.

    A part's fields are listed as `part.field` (`part`), in place of the part.
    """
    return _field_infos(effect if isinstance(effect, type) else type(effect))


def field_value(effect: "Part", name: str):
    """The value of a field named as `field_metadata` names it (`"bloom.intensity"`: the part's field)."""
    return functools.reduce(getattr, name.split("."), effect)


def by_part(values: dict) -> tuple[dict, dict[str, dict]]:
    """`{name: value}` with names as `field_metadata` names them, split into the own fields' and each part's."""
    own, parts = {}, {}
    for name, value in values.items():
        head, _, inner = name.partition(".")
        if inner:
            parts.setdefault(head, {})[inner] = value
        else:
            own[name] = value
    return own, parts


def replace_fields(effect: "Part", values: dict):
    """The effect with fields (named as `field_metadata` names them) set to `values`, checked as when built."""
    own, parts = by_part(values)
    own |= {head: replace_fields(getattr(effect, head), inner) for head, inner in parts.items()}
    return dataclasses.replace(effect, **own)


def units_of(effect: "Part", name: str) -> str:
    """The units (`"frame"` or `"px"`) a size field is in: those of its owner, the effect or the part holding it."""
    owner = field_value(effect, name.rpartition(".")[0]) if "." in name else effect
    return getattr(owner, "units", "frame")


def renamed_fields(effect: "Effect | type[Effect]") -> dict[str, str]:
    """`{old name: field name}` for every field of an effect that had another name (`FieldInfo.formerly`)."""
    return {old: info.name for info in field_metadata(effect).values() for old in info.formerly}


def count_fields(effect: "Effect | type[Effect]") -> tuple[str, ...]:
    """The fittable integer counts (`FieldInfo.count`): fitted relaxed, reported rounded."""
    return tuple(name for name, info in field_metadata(effect).items() if info.count)


def round_counts(effect: "Effect") -> "Effect":
    """The effect with every count field (`FieldInfo.count`) rounded to the nearest integer."""
    names = count_fields(effect)
    if not names:
        return effect
    return eqx.tree_at(
        lambda e: [field_value(e, n) for n in names], effect, [jnp.round(field_value(effect, n)) for n in names]
    )


def parameter_bounds(effect: "Effect | type[Effect]") -> dict[str, tuple[float, float]]:
    """`{field name: (low, high)}` for every fittable field of an effect (instance or class).

    Sizes have their frame-unit bounds, or their pixel bounds for an instance
    built with `units="px"`.
    """
    return {name: _bounds(effect, name, info) for name, info in field_metadata(effect).items() if info.kind == "fittable"}


def _bounds(effect, name: str, info: FieldInfo) -> tuple[float, float]:
    """A fittable field's bounds: a size's pixel bounds when its owner (the effect or the part) has `units="px"`."""
    pixels = not isinstance(effect, type) and units_of(effect, name) == "px"
    return info.px_bounds if pixels and info.px_bounds is not None else info.bounds


def size_fields(effect: "Effect | type[Effect]") -> tuple[str, ...]:
    """The fields holding sizes (fittable or static), in frame units or in pixels as the effect's `units` says."""
    return tuple(name for name, info in field_metadata(effect).items() if info.size)


class Part(eqx.Module):
    """Fields declared with `param`, `count_param`, `size_param`, `static`, `size_reach`, `texture_field` and `part`,
    checked against their declarations when built: the base of effects and of the parts effects are made of."""

    def __check_init__(self):
        owner = type(self).__name__
        hints = _type_hints(type(self))
        infos = _own_field_infos(type(self))
        units = getattr(self, "units", "frame")
        for name, info in infos.items():
            value = getattr(self, name)
            if info.kind == "static":
                _check_static(owner, name, hints[name], value, info.bounds)
                if info.size and not 0 <= value <= MAX_REACH[units]:
                    raise ValueError(f"{owner}.{name} must lie in [0, {MAX_REACH[units]:g}] ({units} units), got {value!r}")
            elif info.kind == "part" and not isinstance(value, hints[name]):
                raise ValueError(f"{owner}.{name} must be a {hints[name].__name__}, got {_SHOWN.repr(value)}")
            elif info.kind == "fittable" and not isinstance(value, jax.core.Tracer):
                # A traced value (built inside a traced function): the kernels check what they must at run time.
                _check_fittable(owner, name, value, _bounds(self, name, info), info.size)

    def __repr__(self) -> str:
        """`GodRays(density=0.5, ...)`: every field with its value (equinox shows `f32[]` placeholders)."""
        fields = ", ".join(f"{field.name}={plain_value(getattr(self, field.name))!r}" for field in dataclasses.fields(self))
        return f"{type(self).__name__}({fields})"
