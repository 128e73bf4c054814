"""Synthetic inputs shared by the denoising tests (imported by name: pytest puts this folder on sys.path)."""

from __future__ import annotations

import numpy as np

from rangesurf.simulate import SimulationNoise

# Range noise only: mixed pixels and outliers are other stages' business.
RANGE_NOISE_ONLY = SimulationNoise(mixed_pixels=False, salt_and_pepper=0.0)


def range_image(shape, *, seed=0, holes=True):
    """Ranges of 1-4 m: two planes, a box in front, 1 cm noise and (optionally) NaN holes."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    image = 2.0 + 0.01 * rows + 0.005 * cols
    image[:, cols[0] >= shape[1] // 2] += 1.0
    image[shape[0] // 4 : shape[0] // 2, shape[1] // 4 : shape[1] // 3 + 1] = 1.2
    image = image + rng.normal(0.0, 0.01, shape)
    if holes and image.size > 4:
        image[rng.random(shape) < 0.05] = np.nan
        image[shape[0] // 2 : shape[0] // 2 + 3, : shape[1] // 3] = np.nan
    return image.astype(np.float32)
