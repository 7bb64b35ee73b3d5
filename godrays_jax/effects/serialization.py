"""Effects to and from JSON: the file `godrays-jax apply --params` and `batch` read, and `fit` and the tuner write."""

import dataclasses
import json
import os
import typing
import warnings

import numpy as np

from godrays_jax.effects.base import Effect, effect_class
from godrays_jax.effects.fields import (
    by_part,
    field_metadata,
    field_value,
    plain_value,
    renamed_fields,
    replace_fields,
)
from godrays_jax.primitives.files import atomic_write


def effect_to_dict(effect: Effect) -> dict:
    """A JSON-ready description: `{"effect": class name, field: value, ...}`, a part's fields as `"part.field"`.

    Numbers are the shortest decimals that read back to the same float32
    (`plain_value`), so saved files carry `0.95`, not `0.949999988079071`.
    """
    fields = {"effect": type(effect).__name__}
    for name in field_metadata(effect):
        fields[name] = plain_value(field_value(effect, name))
    return fields


def effect_from_dict(fields: dict) -> Effect:
    """Rebuild an effect from `effect_to_dict`'s output, validated as the constructor validates its arguments.

    Raises `ValueError` naming the field for an unknown effect or key, a value
    of the wrong JSON type (`"0.5"` for a number, `"false"` for a boolean), a
    vector of the wrong length, or a value out of its range (`field_metadata`).
    A field's old name (`renamed_fields`; a field now in a part included) is
    read as its new one, with a `FutureWarning` naming the new name.
    """
    fields = dict(fields)
    kind = fields.pop("effect", None)
    if not isinstance(kind, str):
        raise ValueError(f'the "effect" key must name an effect class, got {json.dumps(kind)}')
    cls = effect_class(kind)
    for old, new in renamed_fields(cls).items():
        if old not in fields:
            continue
        if new in fields:
            raise ValueError(f"{kind} has both {old!r} and its new name {new!r}: keep {new!r}")
        warnings.warn(f"{kind}.{old} is now named {new}: read as {new}", FutureWarning, stacklevel=2)
        fields[new] = fields.pop(old)
    infos = field_metadata(cls)
    unknown = sorted(set(fields) - set(infos))
    if unknown:
        raise ValueError(f"unknown parameter(s) for {kind}: {', '.join(unknown)}")
    effect = _built(cls, fields)
    for name, value in fields.items():
        expected = _default_shape(cls, name) if infos[name].kind == "fittable" else None
        if expected is not None and np.shape(field_value(effect, name)) != expected:
            raise ValueError(f"{kind}.{name} must have shape {list(expected)}, got {np.shape(field_value(effect, name))}")
    return effect


def _built(cls, fields: dict):
    """`cls(**fields)`, the fields named `part.field` set on the part's declared default first."""
    own, parts = by_part(fields)
    declared = {field.name: field for field in dataclasses.fields(cls)}
    for head, inner in parts.items():
        default = declared[head].default_factory()
        try:
            own[head] = replace_fields(default, inner)
        except ValueError as error:  # named from the effect: `SunSpot.bloom.intensity`, not `Bloom.intensity`
            text, prefix = str(error), f"{type(default).__name__}."
            raise ValueError(f"{cls.__name__}.{head}.{text[len(prefix):]}" if text.startswith(prefix) else text) from None
    return cls(**own)


def _default_shape(cls, name: str) -> tuple[int, ...]:
    """The shape of a field's declared default (`"part.field"`: the part's own default)."""
    head, _, inner = name.partition(".")
    if inner:
        return _default_shape(typing.get_type_hints(cls)[head], inner)
    return np.shape(next(field.default for field in dataclasses.fields(cls) if field.name == name))


def save_effect(path: str | os.PathLike, effect: Effect) -> None:
    """Write the effect's parameters as JSON, atomically (a temporary file renamed into place)."""
    path = os.fspath(path)
    text = json.dumps(effect_to_dict(effect), indent=2) + "\n"
    with atomic_write(path) as temporary, open(temporary, "w") as stream:
        stream.write(text)


MAX_EFFECT_FILE_BYTES = 1 << 20
"""`load_effect` refuses larger files: an effect's parameters take a few hundred bytes."""


def load_effect(path: str | os.PathLike) -> Effect:
    """Read parameters written by `save_effect` (or by `godrays-jax fit`); `ValueError` for anything else.

    Every value is validated as `effect_from_dict` does; a file over
    `MAX_EFFECT_FILE_BYTES`, not UTF-8, not JSON (also numbers of thousands
    of digits, nesting too deep for the parser) or not a JSON object is refused.
    """
    path = os.fspath(path)
    with open(path, "rb") as stream:
        data = stream.read(MAX_EFFECT_FILE_BYTES + 1)
    if len(data) > MAX_EFFECT_FILE_BYTES:
        raise ValueError(f"{path} is not an effect's parameters: larger than {MAX_EFFECT_FILE_BYTES} bytes")
    try:
        fields = parse_json_object(data)
    except ValueError as error:
        raise ValueError(f"{path} {error}") from None
    return effect_from_dict(fields)


MAX_INTEGER_DIGITS = 100
"""`parse_json_object` refuses integers longer than this (no parameter needs more; Python's own limit is 4300)."""


def _integer(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INTEGER_DIGITS:
        raise ValueError(f"an integer of {len(text.lstrip('-'))} digits (at most {MAX_INTEGER_DIGITS})")
    return int(text)


def parse_json_object(data: bytes | str) -> dict:
    """A JSON object from UTF-8 bytes or text; for anything else `ValueError("is not ...: reason")`, one line.

    Malformed JSON, bytes that are not UTF-8, nesting too deep for the parser,
    integers of more than `MAX_INTEGER_DIGITS` digits and any value that is not
    an object are refused.
    """
    try:
        value = json.loads(data.decode("utf-8") if isinstance(data, bytes) else data, parse_int=_integer)
    except RecursionError:
        raise ValueError("is not valid JSON: nested too deeply") from None
    except ValueError as error:  # malformed JSON, not UTF-8, an integer of too many digits
        raise ValueError(f"is not valid JSON: {error}") from None
    if not isinstance(value, dict):
        kind = {list: "an array", str: "a string", bool: "a boolean", type(None): "null"}.get(type(value), "a number")
        raise ValueError(f"is not a JSON object {{...}}: it is {kind}")
    return value


