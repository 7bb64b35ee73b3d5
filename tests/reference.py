"""Slow, obviously-correct NumPy loops that the kernels are checked against.

Every function here loops over pixels (and samples) in plain Python, as a GPU
pixel shader would run, with the same pixel convention: centres at i + 0.5.
"""

import math

import numpy as np


def texel(image, col, row, addressing):
    height, width = image.shape[:2]
    if addressing == "zero" and not (0 <= col < width and 0 <= row < height):
        return np.zeros(image.shape[2])
    return image[min(max(row, 0), height - 1), min(max(col, 0), width - 1)]


def bilinear(image, x, y, addressing="clamp"):
    u, v = x - 0.5, y - 0.5
    col, row = math.floor(u), math.floor(v)
    fu, fv = u - col, v - row
    return (
        texel(image, col, row, addressing) * (1 - fu) * (1 - fv)
        + texel(image, col + 1, row, addressing) * fu * (1 - fv)
        + texel(image, col, row + 1, addressing) * (1 - fu) * fv
        + texel(image, col + 1, row + 1, addressing) * fu * fv
    )


def radial_rays(image, light, num_samples, density, decay, weight, exposure):
    height, width = image.shape[:2]
    out = np.zeros_like(image)
    for row in range(height):
        for col in range(width):
            px, py = col + 0.5, row + 0.5
            dx = (px - light[0]) * density / num_samples
            dy = (py - light[1]) * density / num_samples
            colour = image[row, col].copy()
            illumination = 1.0
            for _ in range(num_samples):
                px -= dx
                py -= dy
                colour += bilinear(image, px, py) * illumination * weight
                illumination *= decay
            out[row, col] = colour * exposure
    return out


def scale_iterated_flares(masked, light, num_iters, scale_step, decay=1.0):
    height, width = masked.shape[:2]
    out = np.zeros_like(masked)
    for row in range(height):
        for col in range(width):
            for k in range(num_iters):
                scale = scale_step**k
                x = light[0] + (col + 0.5 - light[0]) / scale
                y = light[1] + (row + 0.5 - light[1]) / scale
                out[row, col] += decay**k * bilinear(masked, x, y, addressing="zero")
    return out


POISSON = [
    (-0.326212, -0.405805), (-0.840144, -0.073580), (-0.695914, 0.457137), (-0.203345, 0.620716),
    (0.962340, -0.194983), (0.473434, -0.480026), (0.519456, 0.767022), (0.185461, -0.893124),
    (0.507431, 0.064425), (0.896420, 0.412458), (-0.321940, -0.932615), (-0.791559, -0.597705),
]  # fmt: skip


def poisson_blur(image, blur_power, passes):
    height, width = image.shape[:2]
    for _ in range(passes):
        out = np.zeros_like(image)
        for row in range(height):
            for col in range(width):
                total = image[row, col].copy()
                for du, dv in POISSON:
                    total += bilinear(image, col + 0.5 + du * blur_power * width, row + 0.5 + dv * blur_power * height)
                out[row, col] = total / 13
        image = out
    return image


def gaussian_blur(image, sigma, radius):
    height, width = image.shape[:2]
    weights = np.array([math.exp(-0.5 * (t / sigma) ** 2) for t in range(-radius, radius + 1)])
    weights /= weights.sum()
    out = np.zeros_like(image)
    for row in range(height):
        for col in range(width):
            for i, dy in enumerate(range(-radius, radius + 1)):
                for j, dx in enumerate(range(-radius, radius + 1)):
                    r = min(max(row + dy, 0), height - 1)
                    c = min(max(col + dx, 0), width - 1)
                    out[row, col] += weights[i] * weights[j] * image[r, c]
    return out
