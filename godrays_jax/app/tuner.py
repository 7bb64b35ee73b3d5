"""The live tuner's state and actions, independent of HTTP: renders, presets, fits and saves for its page.

`server.py` answers the page's HTTP requests with these actions (its docstring has the API table);
docs/tuner.md says how renders are coalesced, previewed and displayed, and how "fit to target" runs.
"""

import base64
import dataclasses
import json
import math
import os
import reprlib
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from typing import Any, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, UInt8

from godrays_jax.effects.base import Effect
from godrays_jax.effects.fields import count_fields
from godrays_jax.effects.lights import Light, lit_by
from godrays_jax.effects.presets import PRESETS, preset
from godrays_jax.effects.serialization import (
    effect_from_dict,
    effect_to_dict,
    save_effect,
)
from godrays_jax.pipeline.fit import fit
from godrays_jax.pipeline.problem import fitted_bounds
from godrays_jax.pipeline.reduced import clip_to_bounds, downsample_buffers, pixel_fields, scale_pixel_fields
from godrays_jax.primitives.buffers import Buffers
from godrays_jax.primitives.checks import check_light, error_line, ranges_guaranteed
from godrays_jax.primitives.color import display_map, to_srgb8
from godrays_jax.primitives.images import encode_png
from godrays_jax.primitives.resample import downsample_box

VIEWS: tuple[str, ...] = ("after", "before", "layer", "difference", "target")


TONEMAPS: tuple[str, ...] = ("reinhard", "clip")


QUALITIES: tuple[str, ...] = ("preview", "full")


DIFFERENCE_GAIN = 4.0
"""The difference view shows `DIFFERENCE_GAIN * |after - reference|` in display space, so small errors show."""


class TuneRequestError(ValueError):
    """A bad request from the page: answered 400 with the message."""


class Superseded(Exception):
    """A render request replaced by a newer one before it started, or a fit while one runs: answered 409."""


class FitCancelled(Exception):
    """Raised inside a running fit (from its progress callback) when the page cancels it."""


def preview_factor(height: int, width: int, *, max_pixels: int = 40_000) -> int:
    """The smallest integer downsampling factor that brings `height x width` to at most `max_pixels` pixels."""
    if max_pixels < 1:
        raise ValueError(f"max_pixels must be >= 1, got {max_pixels}")
    factor = max(1, math.ceil(math.sqrt(height * width / max_pixels)))
    while math.ceil(height / factor) * math.ceil(width / factor) > max_pixels:
        factor += 1
    return factor


def display_encode(
    image: Float[Array, "H W C"], *, tonemap: Literal["reinhard", "clip"] = "reinhard"
) -> UInt8[Array, "H W 3"]:
    """Linear HDR to 8-bit sRGB RGB for the page: `x / (1 + x)` (`"reinhard"`) or a clip, then sRGB.

    One channel is shown grey; a fourth (alpha) channel is dropped. Negative
    values show black.
    """
    if tonemap not in TONEMAPS:
        raise ValueError(f"tonemap must be one of {', '.join(TONEMAPS)}; got {tonemap!r}")
    rgb = jnp.maximum(image[..., :3], 0.0)
    return to_srgb8(display_map(rgb) if tonemap == "reinhard" else rgb)


@eqx.filter_jit
def _render_view(
    effect: Effect,
    buffers: Buffers,
    light_xy: Float[Array, "2"],
    light_in_front: Bool[Array, ""],
    target: Float[Array, "H W C"] | None,
    view: str,
    tonemap: str,
    light_depth: float = math.inf,
    other_lights: tuple[Light, ...] = (),
    light_tint: Float[Array, "3"] | None = None,
) -> UInt8[Array, "H W 3"]:
    if view == "before":
        return display_encode(buffers.color, tonemap=tonemap)
    if view == "target":
        return display_encode(target, tonemap=tonemap)
    if view == "layer":
        return display_encode(
            effect.layer(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth), tonemap=tonemap
        )
    if other_lights or light_tint is not None:  # several or tinted lights: their light added (`lit_by`)
        first = Light(light_xy, in_front=light_in_front, depth=light_depth,
                      tint=(1.0, 1.0, 1.0) if light_tint is None else light_tint)  # fmt: skip
        after = lit_by(effect, buffers, [first, *other_lights])
    else:
        after = effect(buffers, light_xy, light_in_front=light_in_front, light_depth=light_depth)
    if view == "after":
        return display_encode(after, tonemap=tonemap)
    reference = buffers.color if target is None else target
    channels = min(after.shape[-1], reference.shape[-1], 3)
    difference = jnp.abs(
        display_map(jnp.maximum(after[..., :channels], 0.0)) - display_map(jnp.maximum(reference[..., :channels], 0.0))
    )
    return to_srgb8(DIFFERENCE_GAIN * difference)


class RenderQueue:
    """One worker thread; at most one request waits, and a newer one supersedes it (coalescing, not queueing).

    `submit(job)` blocks until the worker has run `job` and returns its result,
    or raises `Superseded` if a newer job arrived before this one started.
    """

    def __init__(self):
        self._condition = threading.Condition()
        self._pending: tuple[Callable[[], Any], Future] | None = None
        self._closed = False
        self._worker = threading.Thread(target=self._work, name="godrays-tune-render", daemon=True)
        self._worker.start()

    def submit(self, job: Callable[[], Any]) -> Any:
        future: Future = Future()
        with self._condition:
            if self._closed:
                raise RuntimeError("the render queue is closed")
            if self._pending is not None:
                self._pending[1].set_exception(Superseded("superseded by a newer render request"))
            self._pending = (job, future)
            self._condition.notify_all()  # the worker, and whoever waits in `wait_for_request`
        return future.result()

    def wait_for_request(self, previous: Future | None = None, timeout: float | None = None) -> Future | None:
        """Block until a request other than `previous` waits for the worker: its future (None once closed or after
        `timeout` seconds).

        A caller that knows one request waits before it sends the next knows which of them will be superseded,
        whatever the threads' timing: concurrent requests are ordered without sleeping.
        """
        def arrived() -> bool:
            return self._pending is not None and self._pending[1] is not previous

        with self._condition:
            self._condition.wait_for(lambda: self._closed or arrived(), timeout)
            return self._pending[1] if arrived() else None

    def close(self) -> None:
        """Stop the worker after the job in progress; a waiting job is answered `Superseded`."""
        with self._condition:
            self._closed = True
            if self._pending is not None:
                self._pending[1].set_exception(Superseded("the tuner is shutting down"))
                self._pending = None
            self._condition.notify_all()
        self._worker.join()

    def _work(self) -> None:
        while True:
            with self._condition:
                while self._pending is None and not self._closed:
                    self._condition.wait()
                if self._closed:
                    return
                job, future = self._pending
                self._pending = None
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(job())
            except BaseException as error:  # handed to the request's thread, which answers it
                future.set_exception(error)


def _shown(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, (list, dict)) else _SHOWN.repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


_SHOWN = reprlib.Repr()
_SHOWN.maxlevel, _SHOWN.maxlist = 3, 8


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise TuneRequestError(f"{name} must be a finite number, got {_shown(value)}")
    return float(value)


def _fit_state(*, running: bool) -> dict[str, Any]:
    return {"running": running, "step": 0, "loss": None, "result": None, "error": None, "cancelled": False}


def _choice(payload: Mapping, key: str, choices: tuple[str, ...], default: str) -> str:
    value = payload.get(key, default)
    if value not in choices:
        raise TuneRequestError(f"{key} must be one of {', '.join(choices)}; got {_shown(value)}")
    return value


class Tuner:
    """The tuner's state and actions, independent of HTTP (the server calls these; so can tests).

    Args:
        buffers: the frame.
        light_xy: the light's starting position in pixels (x right, y down).
        effect: the starting effect (its static fields are kept until a preset replaces it).
        target: an optional reference image `(H, W, C)` of the frame's size for
            the difference view and "fit to target".
        light_in_front: whether the light starts in front of the camera.
        light_depth: the light's distance from the camera (scene units, `inf` at infinity), as the frame stores it.
        other_lights: the frame's lights beside that one (`effects.lights.Light`s: a render of several), drawn with
            it where their light adds (`lit_by`), "fit to target" too; the page drags each. The layer view draws
            one untinted light and refuses them.
        light_tint: the linear RGB that light's light is multiplied by (`Light.tint`; None or 1: the effect's own);
            "fit to target" fits that light's colour and refuses a tint.
        save_path: where "save" writes the parameters JSON.
        max_preview_pixels: previews have at most this many pixels (see `preview_factor`).
        fit_steps: solver steps at most for "fit to target".
    """

    def __init__(
        self,
        buffers: Buffers,
        light_xy: tuple[float, float],
        *,
        effect: Effect,
        target: Float[ArrayLike, "H W C"] | None = None,
        light_in_front: bool = True,
        light_depth: float = math.inf,
        other_lights: Sequence[Light] = (),
        light_tint: Float[ArrayLike, "3"] | None = None,
        save_path: str | os.PathLike = "params.json",
        max_preview_pixels: int = 40_000,
        fit_steps: int = 20,
    ):
        if target is not None:
            target = jnp.asarray(target, buffers.color.dtype)
            if target.ndim != 3 or target.shape[:2] != (buffers.height, buffers.width):
                raise ValueError(
                    f"target must have the frame's size {buffers.width}x{buffers.height}, got shape {target.shape}"
                )
        self.buffers = buffers
        self.target = target
        self.factor = preview_factor(buffers.height, buffers.width, max_pixels=max_preview_pixels)
        self.preview_buffers = downsample_buffers(buffers, self.factor)
        self.preview_target = None if target is None else downsample_box(target, self.factor)
        self.light_xy = (float(light_xy[0]), float(light_xy[1]))
        self.light_in_front = bool(light_in_front)
        self.light_depth = float(light_depth)
        self.other_lights = list(other_lights)
        if not all(isinstance(light, Light) for light in self.other_lights):
            raise ValueError(f"other_lights must be a sequence of Light, got {other_lights!r}")
        self.light_tint = None if light_tint is None else np.broadcast_to(np.asarray(light_tint, np.float32), (3,))
        if self.light_tint is not None and np.all(self.light_tint == 1.0):
            self.light_tint = None  # the effect's own light
        if self.light_tint is not None and not (np.isfinite(self.light_tint).all() and (self.light_tint >= 0).all()):
            raise ValueError(f"light_tint must be finite and >= 0 (linear RGB), got {light_tint!r}")
        self._check_renders(effect)
        self.effect = effect
        self.save_path = os.path.abspath(os.fspath(save_path))
        self.fit_steps = fit_steps
        self.queue = RenderQueue()
        self._lock = threading.Lock()
        self._fit_lock = threading.Lock()
        self._fit_thread: threading.Thread | None = None
        self._fit_cancel = threading.Event()
        self._fit_progress: dict[str, Any] = _fit_state(running=False)

    def close(self) -> None:
        """Cancel a running fit and wait for it, then stop the render worker."""
        self._fit_cancel.set()
        self.wait_fit()
        self.queue.close()

    def _check_renders(self, effect: Effect) -> None:
        """Trace (without running) the effect on this frame: a missing pass or a bad static field raises `ValueError` now."""
        light = jnp.asarray(self.light_xy, self.buffers.color.dtype)
        eqx.filter_eval_shape(lambda e, b, l: e(b, l), effect, self.preview_buffers, light)

    # --------------------------------------------------------------- state

    def bounds(self, effect: Effect | None = None) -> dict[str, tuple[float, float]]:
        """Slider ranges: the effect's bounds, counts capped by their static loop lengths."""
        return fitted_bounds(self.effect if effect is None else effect)

    def state(self) -> dict:
        with self._lock:
            effect = self.effect
        return {
            "width": self.buffers.width,
            "height": self.buffers.height,
            "preview_factor": self.factor,
            "light": list(self.light_xy),
            "light_in_front": self.light_in_front,
            "other_lights": [[float(v) for v in np.asarray(light.xy)] for light in self.other_lights],
            "effect": effect_to_dict(effect),
            "bounds": {name: list(bounds) for name, bounds in self.bounds(effect).items()},
            "pixel_fields": sorted(pixel_fields(effect)),
            "count_fields": list(count_fields(effect)),
            "presets": sorted(PRESETS),
            "views": list(VIEWS) if self.target is not None else [v for v in VIEWS if v != "target"],
            "tonemaps": list(TONEMAPS),
            "has_target": self.target is not None,
            "save_path": self.save_path,
        }

    def parse_effect(self, params: Any) -> Effect:
        """The current effect with the page's values; `TuneRequestError` names any bad field."""
        with self._lock:
            effect = self.effect
        if params is None:
            return effect
        if not isinstance(params, dict):
            raise TuneRequestError("params must be a JSON object {field: value}")
        bounds = self.bounds(effect)
        fields = effect_to_dict(effect)
        for name, value in params.items():
            if name not in bounds:
                raise TuneRequestError(
                    f"unknown parameter {name!r} for {fields['effect']}; sliders: {', '.join(bounds)}"
                )
            low, high = bounds[name]
            expected = np.shape(fields[name])
            values = value if isinstance(value, list) else [value]
            if len(expected) > 1 or any(isinstance(v, list) for v in values) or np.ndim(value) != len(expected) or (
                expected and len(values) != expected[0]
            ):  # checked without NumPy, which refuses ragged lists with an error of its own
                raise TuneRequestError(f"{name} must have shape {list(expected)}, got {_shown(value)}")
            for element in values:
                number = _number(element, name)
                if not low <= number <= high:
                    raise TuneRequestError(f"{name} = {number} lies outside its range [{low}, {high}]")
            fields[name] = value
        try:
            return effect_from_dict(fields)
        except ValueError as error:
            raise TuneRequestError(str(error)) from None

    def _light(self, payload: Mapping) -> tuple[Float[Array, "2"], bool]:
        light = payload.get("light", list(self.light_xy))
        if not (isinstance(light, list) and len(light) == 2):
            raise TuneRequestError(f"light must be [x, y] in pixels, got {_shown(light)}")
        x, y = check_light([_number(v, "light") for v in light])  # a far light bounded before a float32 cast
        in_front = payload.get("light_in_front", self.light_in_front)
        if not isinstance(in_front, bool):
            raise TuneRequestError(f"light_in_front must be true or false, got {_shown(in_front)}")
        return jnp.asarray([x, y], self.buffers.color.dtype), in_front

    def _other_lights(self, payload: Mapping) -> list[Light]:
        """The lights beside the dragged one, at the page's positions (`other_lights`: one `[x, y]` each)."""
        positions = payload.get("other_lights", [[float(v) for v in np.asarray(o.xy)] for o in self.other_lights])
        count = len(self.other_lights)
        if not (isinstance(positions, list) and len(positions) == count and all(
            isinstance(xy, list) and len(xy) == 2 for xy in positions
        )):
            raise TuneRequestError(f"other_lights must be {count} [x, y] in pixels, got {_shown(positions)}")
        return [
            dataclasses.replace(light, xy=jnp.asarray(check_light([_number(v, "other_lights") for v in xy]),
                                                      self.buffers.color.dtype))
            for light, xy in zip(self.other_lights, positions)
        ]  # fmt: skip

    # --------------------------------------------------------------- actions

    def render(self, payload: Mapping) -> dict:
        """Render one view (validated here, rendered on the worker; may raise `Superseded`)."""
        effect = self.parse_effect(payload.get("params"))
        light, in_front = self._light(payload)
        others = self._other_lights(payload)
        quality = _choice(payload, "quality", QUALITIES, "full")
        view = _choice(payload, "view", VIEWS, "after")
        tonemap = _choice(payload, "tonemap", TONEMAPS, "reinhard")
        if view == "target" and self.target is None:
            raise TuneRequestError("view 'target' needs a target (start the tuner with --target)")
        if view == "layer" and (others or self.light_tint is not None):
            raise TuneRequestError(f"the layer view draws one untinted light and this frame has {len(others) + 1} "
                                   "lights or a tint: the after and difference views draw them")  # fmt: skip
        preview = quality == "preview"
        buffers = self.preview_buffers if preview else self.buffers
        target = self.preview_target if preview else self.target
        if preview:
            effect = scale_pixel_fields(effect, 1.0 / self.factor)
            light = light / self.factor
            others = [dataclasses.replace(other, xy=other.xy / self.factor) for other in others]

        def job():
            start = time.perf_counter()
            # Values were checked against their bounds above (parse_effect): no run-time check, whose host
            # callback would keep the compiled view out of the persistent cache (a second launch compiles again).
            with ranges_guaranteed():
                pixels = np.asarray(
                    _render_view(effect, buffers, light, jnp.asarray(in_front), target, view, tonemap, self.light_depth,
                                 tuple(others), None if self.light_tint is None else jnp.asarray(self.light_tint))
                )
            rendered = time.perf_counter()
            png = encode_png(pixels)
            return {
                "image": "data:image/png;base64," + base64.b64encode(png).decode("ascii"),
                "width": int(pixels.shape[1]),
                "height": int(pixels.shape[0]),
                "quality": quality,
                "view": view,
                "render_ms": round((rendered - start) * 1000.0, 2),
                "encode_ms": round((time.perf_counter() - rendered) * 1000.0, 2),
            }

        return self.queue.submit(job)

    def set_preset(self, payload: Mapping) -> dict:
        name = payload.get("name")
        if not isinstance(name, str) or name not in PRESETS:
            raise TuneRequestError(f"unknown preset {_shown(name)}; choose one of: {', '.join(sorted(PRESETS))}")
        effect = preset(name)
        try:
            self._check_renders(effect)
        except ValueError as error:
            raise TuneRequestError(f"preset {name} cannot render this frame: {error}") from None
        with self._lock:
            self.effect = effect
        return self.state()

    def save(self, payload: Mapping) -> dict:
        effect = self.parse_effect(payload.get("params"))
        save_effect(self.save_path, effect)
        with self._lock:
            self.effect = effect
        return {"path": self.save_path, "effect": effect_to_dict(effect)}

    def fit_progress(self) -> dict:
        """The current or last fit: `{"running", "step", "loss", "result", "error", "cancelled"}`."""
        with self._fit_lock:
            return dict(self._fit_progress)

    def cancel_fit(self, payload: Mapping | None = None) -> dict:
        """Ask the running fit to stop after its current step (nothing happens if none runs); its progress."""
        self._fit_cancel.set()
        return self.fit_progress()

    def wait_fit_cancelled(self, timeout: float | None = None) -> bool:
        """Block until the running fit is asked to stop (`cancel_fit`, `close`); whether it was, within `timeout`
        seconds.

        The fit itself notices at its next step; code that runs beside it (a stand-in for the solver) waits here
        instead of polling.
        """
        return self._fit_cancel.wait(timeout)

    def wait_fit(self, timeout: float | None = None) -> dict:
        """Wait until the running fit (if any) ends; its progress."""
        thread = self._fit_thread
        if thread is not None:
            thread.join(timeout)
        return self.fit_progress()

    def fit(self, payload: Mapping) -> dict:
        """Start fitting the page's effect to the target at preview resolution, on a thread of its own.

        Validates the request here (`TuneRequestError`), raises `Superseded`
        if a fit is running, and returns the progress at once; `fit_progress`
        then reports the steps and, when done, the full-resolution result.
        """
        if self.target is None:
            raise TuneRequestError("no target to fit to: start the tuner with --target TARGET")
        if self.light_tint is not None:
            raise TuneRequestError("fit to target fits the first light's colour, untinted, and this light has a tint: "
                                   "godrays-jax fit --light-tint takes the tints over the first's")  # fmt: skip
        effect = self.parse_effect(payload.get("params"))
        light, in_front = self._light(payload)
        others = self._other_lights(payload)
        fixed = payload.get("fixed", [])
        bounds = self.bounds(effect)
        if not (isinstance(fixed, list) and all(isinstance(name, str) and name in bounds for name in fixed)):
            raise TuneRequestError(f"fixed must be a list of slider names ({', '.join(bounds)}), got {_shown(fixed)}")
        fractional = payload.get("fractional_counts", False)
        if not isinstance(fractional, bool):
            raise TuneRequestError(f"fractional_counts must be true or false, got {_shown(fractional)}")
        if len(fixed) == len(bounds):
            raise TuneRequestError("every parameter is locked: unlock at least one to fit")
        with self._fit_lock:
            if self._fit_progress["running"]:
                raise Superseded("a fit is already running: wait for it or cancel it")
            self._fit_cancel.clear()
            self._fit_progress = _fit_state(running=True)
            self._fit_thread = threading.Thread(
                target=self._run_fit, args=(effect, light, in_front, others, fixed, bounds, fractional),
                name="godrays-tune-fit", daemon=True,
            )  # fmt: skip
            self._fit_thread.start()
            return dict(self._fit_progress)

    def _run_fit(
        self, effect: Effect, light, in_front: bool, others: list[Light], fixed: list[str], bounds: Mapping,
        fractional: bool,
    ) -> None:
        def progress(step, loss):
            if self._fit_cancel.is_set():
                raise FitCancelled
            with self._fit_lock:
                self._fit_progress.update(step=int(step), loss=float(loss))

        try:
            start = scale_pixel_fields(effect, 1.0 / self.factor)
            result = fit(
                start,
                self.preview_buffers,
                light / self.factor,
                self.preview_target,
                fixed=fixed,
                max_steps=self.fit_steps,
                light_in_front=in_front,
                light_depth=self.light_depth,
                other_lights=[dataclasses.replace(other, xy=other.xy / self.factor) for other in others],
                fit_light_tints=False,  # the page's tints, which its views draw the fitted effect with
                progress=progress,
            )
            # Counts rounded, as `godrays-jax fit` saves them, unless the page asks for the relaxation's values.
            chosen = result.effect if fractional else result.rounded
            fitted = clip_to_bounds(scale_pixel_fields(chosen, float(self.factor)), bounds)
            with self._lock:
                self.effect = fitted
            outcome = {"result": {
                "effect": effect_to_dict(fitted),
                "loss_before": result.loss_before,
                "loss_after": result.loss_after if fractional else result.loss_rounded,
                "steps": result.steps,
                "fitted": list(result.fitted),
                "kept_start": result.kept_start,
            }}  # fmt: skip
        except FitCancelled:
            outcome = {"cancelled": True}
        except Exception as error:  # reported to the page, which shows it; the tuner goes on
            outcome = {"error": error_line(error)}
        with self._fit_lock:
            self._fit_progress.update(running=False, **outcome)


