"""Effects to and from JSON: the file `godrays-jax apply --params` and `batch` read, and `fit` and the tuner write."""

import dataclasses
import json
import os

from godrays_jax.effects.base import Effect, effect_class, plain_value
from godrays_jax.primitives.files import atomic_write


def _field_names(cls) -> list[str]:
    return [field.name for field in dataclasses.fields(cls)]


def effect_to_dict(effect: Effect) -> dict:
    """A JSON-ready description: `{"effect": class name, field: value, ...}`.

    Numbers are the shortest decimals that read back to the same float32
    (`plain_value`), so saved files carry `0.95`, not `0.949999988079071`.
    """
    fields = {"effect": type(effect).__name__}
    for name in _field_names(type(effect)):
        fields[name] = plain_value(getattr(effect, name))
    return fields


def effect_from_dict(fields: dict) -> Effect:
    """Rebuild an effect from `effect_to_dict`'s output; unknown keys or effects raise `ValueError`."""
    fields = dict(fields)
    kind = fields.pop("effect", None)
    cls = effect_class(kind)
    unknown = sorted(set(fields) - set(_field_names(cls)))
    if unknown:
        raise ValueError(f"unknown parameter(s) for {kind}: {', '.join(unknown)}")
    return cls(**fields)


def save_effect(path: str | os.PathLike, effect: Effect) -> None:
    """Write the effect's parameters as JSON, atomically (a temporary file renamed into place)."""
    path = os.fspath(path)
    text = json.dumps(effect_to_dict(effect), indent=2) + "\n"
    with atomic_write(path) as temporary, open(temporary, "w") as stream:
        stream.write(text)


def load_effect(path: str | os.PathLike) -> Effect:
    """Read parameters written by `save_effect` (or by `godrays-jax fit`)."""
    with open(path) as stream:
        try:
            fields = json.load(stream)
        except json.JSONDecodeError as error:
            raise ValueError(f"{os.fspath(path)} is not valid JSON: {error}") from None
    if not isinstance(fields, dict):
        raise ValueError(f"{os.fspath(path)} must hold a JSON object")
    return effect_from_dict(fields)


