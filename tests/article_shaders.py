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
#
# The shaders take the light as `lightPosition` and the camera as `matVP`, XNA's row-vector matrices
# (`mul(v, M)`), its view space looking down -z; here the light is given in view space (`matVP` is then the
# projection alone) as the point `float4(lightPosition, 1)`: its clip-space z is `(d - near) * far / (far -
# near)` and `w` its distance `d` along the axis. (Compiled as printed, `mul(float3, float4x4)` would drop
# the matrix's last row, the view's translation and the projection's z offset with it; the article's
# comments meet that and subtract the camera's position.) Full-screen passes shade each pixel at its
# texel centre: the shared vertex shader (not printed) adds the half pixel that `texCoord -= halfPixel`
# takes away (Direct3D 9's rule).


def xna_projection(fov_y, aspect, near, far):
    """`Matrix.CreatePerspectiveFieldOfView(fov_y, aspect, near, far)`, row-vector convention."""
    y_scale = 1.0 / np.tan(fov_y / 2)
    matrix = np.zeros((4, 4))
    matrix[0, 0] = y_scale / aspect
    matrix[1, 1] = y_scale
    matrix[2, 2] = far / (near - far)
    matrix[2, 3] = -1.0
    matrix[3, 2] = near * far / (near - far)
    return matrix


def screen_position(light_view, mat_vp):
    """`ScreenPosition = mul(lightPosition, matVP)`, then as every XNA pass continues:
    `(xy / w) * (.5, -.5) + .5`, z divided by w, w kept. Returns `(u, v, z / w, w)`."""
    clip = np.append(np.asarray(light_view, np.float64), 1.0) @ mat_vp
    x, y, z, w = clip / np.array([clip[3], clip[3], clip[3], 1.0])
    return x / 2 + 0.5, -y / 2 + 0.5, z, w


def article_depth_map(planar_depth, mat_vp):
    """The depth map the scene mask reads: `1 - z/w` in `.r` (`depthVal = 1 - tex.r` is then z/w), cleared to 0
    where nothing was drawn (the sky: depthVal 1, the far plane). `planar_depth` is distance along the axis."""
    drawn = np.isfinite(planar_depth)
    d = np.where(drawn, planar_depth, 1.0)
    z_over_w = (-d * mat_vp[2, 2] + mat_vp[3, 2]) / d  # a point (0, 0, -d, 1): w = d
    return np.where(drawn, 1.0 - z_over_w, 0.0)[..., None]


def light_source_mask(height, width, light_view, mat_vp, sun_size, flare):
    """LightSourceMask.fx: `size = SunSize / ScreenPosition.z` (before the divide); `coord = .5 - (texCoord -
    center) / size * .5; col = pow(tex2D(Flare, coord), 2) * 2` while `w > 0` (clamp addressing)."""
    u, v = uv_grid(height, width)
    scale = (np.append(np.asarray(light_view, np.float64), 1.0) @ mat_vp)[2]
    center_u, center_v, _, w = screen_position(light_view, mat_vp)
    if not w > 0:
        return np.zeros((height, width, flare.shape[-1]))
    size = sun_size / scale
    return tex2d(flare, 0.5 - (u - center_u) / size * 0.5, 0.5 - (v - center_v) / size * 0.5) ** 2 * 2


def scene_mask(scene, depth_map, light_view, mat_vp):
    """LightSceneMask.fx: `depthVal = 1 - tex2D(DepthMap, texCoord).r` (point filtering: the pixel's own texel);
    `if (depthVal < ScreenPosition.z - .00025) scene = 0`."""
    depth_val = 1.0 - depth_map[..., 0]
    _, _, light_z, _ = screen_position(light_view, mat_vp)
    return np.where((depth_val < light_z - 0.00025)[..., None], 0.0, scene)


def light_rays(scene, light_view, mat_vp, *, num_samples=128, density=0.5, decay=0.95, weight=1.0, exposure=0.15):
    """LightRays.fx: `DeltaTexCoord = (TexCoord - ScreenPosition.xy) * (1 / NUM_SAMPLES * Density) *
    clamp(ScreenPosition.w * ScreenPosition.z, 0, .5)` (z already divided by w), then the GPU Gems loop; it
    returns `col * Exposure` before its `w > 0` test (dead code)."""
    height, width = scene.shape[:2]
    light_u, light_v, z_over_w, w = screen_position(light_view, mat_vp)
    u, v = uv_grid(height, width)
    step = 1.0 / num_samples * density * np.clip(w * z_over_w, 0.0, 0.5)
    du, dv = (u - light_u) * step, (v - light_v) * step
    col = tex2d(scene, u, v)
    illumination = 1.0
    for _ in range(num_samples):
        u, v = u - du, v - dv
        col = col + tex2d(scene, u, v) * illumination * weight
        illumination *= decay
    return col * exposure


def gpu_gems_loop(scene, light_uv, *, num_samples, density, decay, weight, exposure):
    """The GPU Gems 3 loop alone (no step clamp), light given in UV."""
    height, width = scene.shape[:2]
    u, v = uv_grid(height, width)
    du = (u - light_uv[0]) * (1.0 / num_samples * density)
    dv = (v - light_uv[1]) * (1.0 / num_samples * density)
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


def xna_crepuscular(color, depth_map, light_view, mat_vp, *, sun_size, flare, threshold, tint, **rays):
    """The five passes of seed 003, SceneBlend's `Aditive` last (tint, ours, scales the bright pass): `(frame, layer)`."""
    height, width = color.shape[:2]
    mask = light_source_mask(height, width, light_view, mat_vp, sun_size, flare)
    masked = scene_mask(mask, depth_map, light_view, mat_vp)
    layer = bright_pass(light_rays(masked, light_view, mat_vp, **rays), threshold) * np.asarray(tint)
    return color + layer, layer


# --- seed 004: galaxy engine VLS (PS_VLS) ---


def galaxy_vls(black_scene, light_uv, *, num_samples=200, density=1.0, weight=1.0, decay=0.98, exposure=0.05):
    """PS_VLS on the white-light/black-occluder target (its `1 - y` flip undone: both targets share it)."""
    return gpu_gems_loop(black_scene, light_uv, num_samples=num_samples, density=density, decay=decay, weight=weight,
                         exposure=exposure)


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
    """The whole kbEngine pass: "repeatedly scaling and rendering the masked texture into a low-res scene texture"
    (`Fullsize / factor` whole pixels, each copy sampled from the full-resolution masked texture), `intensity`, a
    Gaussian against banding on that target (`sigma` texels, `radius` taps), "added on top the scene color buffer"
    (drawn by UV): `(frame, layer)`."""
    height, width = depth.shape
    masked = kbengine_masked_flare(height, width, light_uv, size, flare, depth)
    target = (max(1, height // factor), max(1, width // factor))
    low = flare_outs(masked, light_uv, target, num_iters=num_iters, scale_step=scale_step) * intensity
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


def lens_dirt(dirt, depth, to_light, fov_x_deg, far_plane, sun_color):
    """VBex LensDirt as printed: `LensDirtColor.r/g/b = TextureDirt.Sample(tex [+ ofsG | + ofsB]) * SunColor`, with
    `ofsG = (0, .002)`, `ofsB = (.002, 0)`; `LensDirtIntensity = saturate(dot(WViewDirection, -DirLight.direction) *
    max(GBuffer.LDepth, 0.8))`, then `pow(LensDirtIntensity, 20) * 2`. `LDepth` is linear depth over `far_plane`, 1 on the
    sky; the view direction is each pixel's ray."""
    height, width = depth.shape
    u, v = uv_grid(height, width)
    colour = np.concatenate([tex2d(dirt, u, v), tex2d(dirt, u, v + 0.002), tex2d(dirt, u + 0.002, v)], axis=-1)
    colour = colour * np.asarray(sun_color)
    ldepth = np.where(np.isfinite(depth), np.clip(np.where(np.isfinite(depth), depth, 0) / far_plane, 0, 1), 1.0)
    intensity = saturate((view_rays(height, width, fov_x_deg) @ to_light) * np.maximum(ldepth, 0.8))
    return colour * (intensity**20 * 2)[..., None]


def sun_spot(height, width, to_light, fov_x_deg, sun_distance, sun_sharpness):
    """The sky shader's `saturate(pow(sunDot, SunDistance * 2000)) * SunSharpness * 30`."""
    cosine = np.clip(view_rays(height, width, fov_x_deg) @ to_light, 0.0, 1.0)
    return saturate(cosine ** (sun_distance * 2000)) * sun_sharpness * 30


def bright_glow(glow, sigma, radius, weights=(1, 1, 1, 1)):
    """Glow/Bloom: "four BlurTargets with different sizes, Fullsize/2, Fullsize/4, Fullsize/8, Fullsize/16. Add all
    results". Render targets have whole-pixel sizes (`H // f` x `W // f`); each is drawn from the one before it (the
    first from the glow target) as a full-screen quad, linear filtering at its texel centres' UV; blurred by the same
    Gaussian (`sigma` texels of that target, `radius` taps); drawn back over the frame by UV and added."""
    height, width = glow.shape[:2]
    full_u, full_v = uv_grid(height, width)
    total, level = 0.0, glow
    for weight, factor in zip(weights, (2, 4, 8, 16)):
        level = tex2d(level, *uv_grid(max(1, height // factor), max(1, width // factor)))
        total = total + weight * tex2d(gaussian_blur(level, sigma, radius), full_u, full_v)
    return total
