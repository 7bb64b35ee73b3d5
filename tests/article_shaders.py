"""The source articles' shaders, emulated in NumPy in UV space with GPU sampler semantics.

Independent of the library: every pass is written as the article's HLSL reads,
on whole-frame NumPy arrays (one "pixel shader invocation" per pixel, the
sample loops in Python). Texture coordinates are UV: pixel `(row, col)` of a
`W x H` target is shaded at `uv = ((col + 0.5) / W, (row + 0.5) / H)`, and a
`w x h` texture's texel `i` has its centre at `(i + 0.5) / w` (`tex2D` with
linear filtering). Addressing is clamp unless a shader says otherwise.
"""

import numpy as np


def uv_grid(height, width):
    """Per-pixel texture coordinates `(u, v)`, each `(H, W)`: texel centres `(i + 0.5) / size`."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    return np.meshgrid(u, v)


def tex2d(texture, u, v, address="clamp"):
    """`tex2D` with linear filtering: `texture` `(h, w, C)` at UV `(u, v)` (any shape), `address` clamp or border 0."""
    h, w = texture.shape[:2]
    x = np.asarray(u, np.float64) * w - 0.5
    y = np.asarray(v, np.float64) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)

    def texel(col, row):
        values = texture[np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)]
        if address == "border":
            inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
            values = np.where(inside[..., None], values, 0.0)
        return values

    top = texel(x0, y0) * (1 - fx) + texel(x0 + 1, y0) * fx
    bottom = texel(x0, y0 + 1) * (1 - fx) + texel(x0 + 1, y0 + 1) * fx
    return top * (1 - fy) + bottom * fy


def saturate(x):
    return np.clip(x, 0.0, 1.0)


# --- seed 003: XNA crepuscular rays (LightSourceMask, LightSceneMask, LightRays, BrightPass, SceneBlend) ---


def light_source_mask(height, width, light_uv, size, flare):
    """LightSourceMask.fx: `coord = .5 - (texCoord - center) / size * .5; col = pow(tex2D(Flare, coord), 2) * 2`.

    `size` is `SunSize / scale` in UV units (half the flare's extent in u and in v).
    """
    u, v = uv_grid(height, width)
    coord_u = 0.5 - (u - light_uv[0]) / size * 0.5
    coord_v = 0.5 - (v - light_uv[1]) / size * 0.5
    return tex2d(flare, coord_u, coord_v) ** 2 * 2


def scene_mask(source, depth, light_depth, bias):
    """LightSceneMask.fx: black out the pixels in front of the light (`depth < light depth - bias`).

    Linear depths in scene units; the bias is a fraction of the light's depth.
    """
    in_front = depth < light_depth * (1.0 - bias)
    return np.where(in_front[..., None], 0.0, source)


def light_rays(scene, light_uv, light_depth, *, num_samples=128, density=0.5, decay=0.95, weight=1.0, exposure=0.15,
               step_clamp=True):
    """LightRays.fx, with `DeltaTexCoord *= clamp(ScreenPosition.w * ScreenPosition.z, 0, .5)` (clip-space z, the
    light's depth for a near plane much closer than the light) when `step_clamp`."""
    height, width = scene.shape[:2]
    u, v = uv_grid(height, width)
    du = (u - light_uv[0]) * (1.0 / num_samples * density)
    dv = (v - light_uv[1]) * (1.0 / num_samples * density)
    if step_clamp:
        clamp = np.clip(light_depth, 0.0, 0.5)
        du, dv = du * clamp, dv * clamp
    col = tex2d(scene, u, v)
    illumination = 1.0
    for _ in range(num_samples):
        u, v = u - du, v - dv
        col = col + tex2d(scene, u, v) * illumination * weight
        illumination *= decay
    return col * exposure


def bright_pass(image, threshold):
    """BrightPass.fx: `saturate((c - BloomThreshold) / (1 - BloomThreshold))`."""
    return saturate((image - threshold) / (1.0 - threshold))


def xna_crepuscular(color, depth, light_uv, light_depth, *, size, flare, bias, threshold, tint, **rays):
    """The five passes of seed 003 (tint, ours, scales the bright pass): `(frame, layer)`."""
    height, width = depth.shape
    mask = light_source_mask(height, width, light_uv, size, flare)
    masked = scene_mask(mask, depth, light_depth, bias)
    layer = bright_pass(light_rays(masked, light_uv, light_depth, **rays), threshold) * np.asarray(tint)
    return color + layer, layer


# --- seed 004: galaxy engine VLS (PS_VLS) ---


def galaxy_vls(black_scene, light_uv, *, num_samples=200, density=1.0, weight=1.0, decay=0.98, exposure=0.05):
    """PS_VLS on the white-light/black-occluder target (its `1 - y` flip undone: both targets share it)."""
    return light_rays(black_scene, light_uv, 0.0, num_samples=num_samples, density=density, decay=decay, weight=weight,
                      exposure=exposure, step_clamp=False)


# --- seed 002: kbEngine flare-outs ---


def kbengine_masked_flare(height, width, light_uv, size, flare, depth):
    """The base flare texture times `1 - sign(depth)` (the article's depth buffer holds 0 on the sky: here `+inf`).

    The article does not print where the base texture is drawn: placed as the XNA article places its flare
    (`coord = .5 - (uv - light) / size * .5`), without the `2 * pow(tex, 2)`.
    """
    u, v = uv_grid(height, width)
    texture = tex2d(flare, 0.5 - (u - light_uv[0]) / size * 0.5, 0.5 - (v - light_uv[1]) / size * 0.5)
    sky = ~np.isfinite(depth)
    return texture * sky[..., None]


def kbengine_flares(color, depth, light_uv, *, size, flare, num_iters, scale_step, intensity, sigma, radius, factor,
                    tint=(1.0, 1.0, 1.0)):
    """The whole kbEngine pass: masked flare, flare-outs into a `1/factor` target, `intensity`, a Gaussian against
    banding on that target (`sigma` texels, `radius` taps), drawn back over the frame and added: `(frame, layer)`."""
    height, width = depth.shape
    masked = kbengine_masked_flare(height, width, light_uv, size, flare, depth)
    low = box_downsample(masked, factor)
    low = flare_outs(low, light_uv, low.shape[:2], num_iters=num_iters, scale_step=scale_step) * intensity
    layer = upsample(gaussian_blur(low, sigma, radius), height, width) * np.asarray(tint)
    return color + layer, layer


def flare_outs(masked, light_uv, target_hw, *, num_iters, scale_step, decay=1.0):
    """Each step draws the masked texture scaled by `scale_step ** k` about the light into the low-res target
    (border 0 outside the scaled quad), additive blends."""
    u, v = uv_grid(*target_hw)
    out = 0.0
    for k in range(num_iters):
        scale = scale_step**k
        out = out + decay**k * tex2d(masked, light_uv[0] + (u - light_uv[0]) / scale,
                                     light_uv[1] + (v - light_uv[1]) / scale, address="border")
    return out


def gaussian_blur(image, sigma, radius):
    """A separable Gaussian of `sigma` texels, `radius` taps each side, weights normalised, clamp."""
    taps = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (taps / max(sigma, 1e-6)) ** 2)
    kernel /= kernel.sum()
    h, w = image.shape[:2]
    rows = sum(kernel[i] * image[np.clip(np.arange(h) + t, 0, h - 1)] for i, t in enumerate(taps))
    return sum(kernel[i] * rows[:, np.clip(np.arange(w) + t, 0, w - 1)] for i, t in enumerate(taps))


def box_downsample(image, factor):
    h, w = image.shape[:2]
    lh, lw = -(-h // factor), -(-w // factor)
    padded = np.pad(image, ((0, lh * factor - h), (0, lw * factor - w), (0, 0)), mode="edge")
    return padded.reshape(lh, factor, lw, factor, -1).mean(axis=(1, 3))


def upsample(low, height, width):
    """Draw a low-res target over the full frame: linear filtering at each full pixel's UV."""
    u, v = uv_grid(height, width)
    return tex2d(low, u, v)


# --- seed 000: sun overcasting (Overimpose blur, additive sprite blend) ---

POISSON = np.array([
    -0.326212, -0.405805, -0.840144, -0.073580, -0.695914, 0.457137, -0.203345, 0.620716, 0.962340, -0.194983,
    0.473434, -0.480026, 0.519456, 0.767022, 0.185461, -0.893124, 0.507431, 0.064425, 0.896420, 0.412458,
    -0.321940, -0.932615, -0.791559, -0.597705,
]).reshape(12, 2)  # fmt: skip


def overimpose(image, blur_power):
    """Overimpose: `sum = tex2D(uv); sum += tex2D(uv + BlurPower * offsets[i]) (12 taps); sum / 13`."""
    u, v = uv_grid(*image.shape[:2])
    total = tex2d(image, u, v)
    for du, dv in POISSON:
        total = total + tex2d(image, u + blur_power * du, v + blur_power * dv)
    return total / 13


def sun_overcast(color, glow_pass, blur_power, passes=2):
    """Two blur passes of the overcast target, then `SpriteBlendMode.Additive`: `rgb * alpha` added."""
    blurred = glow_pass
    for _ in range(passes):
        blurred = overimpose(blurred, blur_power)
    layer = blurred[..., :3] * blurred[..., 3:]
    return color + layer, layer


# --- seed 001: VBex lens dirt, sky sun spot, glow/bloom ---


def view_rays(height, width, fov_x_deg):
    """Unit view-space rays (x right, y up, z forward) through the pixel centres."""
    u, v = uv_grid(height, width)
    tan = np.tan(np.radians(fov_x_deg) / 2)
    rays = np.stack([(2 * u - 1) * tan, (1 - 2 * v) * tan * height / width, np.ones_like(u)], axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def lens_dirt(dirt, depth, to_light, fov_x_deg, far, sun_color, *, power=20.0, scale=2.0, offset=0.002,
              depth_in_power=False, floor=0.8):
    """VBex LensDirt: per-channel dirt samples (green at `tex + (0, .002)`, blue at `tex + (.002, 0)`) times the sun
    colour, times `pow(saturate(dot(view, -lightdir) * max(LDepth, .8)), 20) * 2` as written (`depth_in_power`), or
    with `max(LDepth, .8)` applied to the intensity after the power (the depth response we ship)."""
    height, width = depth.shape
    u, v = uv_grid(height, width)
    colour = np.concatenate([tex2d(dirt, u, v), tex2d(dirt, u, v + offset), tex2d(dirt, u + offset, v)], axis=-1)
    colour = colour * np.asarray(sun_color)
    ldepth = np.where(np.isfinite(depth), np.clip(np.where(np.isfinite(depth), depth, 0) / far, 0, 1), 1.0)
    cosine = view_rays(height, width, fov_x_deg) @ to_light
    occluder = np.maximum(ldepth, floor)
    if depth_in_power:
        intensity = saturate(cosine * occluder) ** power * scale
    else:
        intensity = saturate(cosine) ** power * scale * occluder
    return colour * intensity[..., None]


def sun_spot(height, width, to_light, fov_x_deg, sun_distance, sun_sharpness):
    """The sky shader's `saturate(pow(sunDot, SunDistance * 2000)) * SunSharpness * 30`."""
    cosine = np.clip(view_rays(height, width, fov_x_deg) @ to_light, 0.0, 1.0)
    return saturate(cosine ** (sun_distance * 2000)) * sun_sharpness * 30


def bright_glow(glow, sigma, radius, weights=(1, 1, 1, 1)):
    """Glow/Bloom: the glow target box-reduced to Fullsize/2, /4, /8, /16, each blurred by the same Gaussian
    (`sigma` texels of that target, `radius` taps), read back with linear filtering and added."""
    height, width = glow.shape[:2]
    total = 0.0
    for weight, factor in zip(weights, (2, 4, 8, 16)):
        low = gaussian_blur(box_downsample(glow, factor), sigma, radius)
        total = total + weight * upsample(low, height, width)
    return total
