"""Range-image denoising that keeps surface edges (thesis Section 3.1).

Outlier removal (`outliers`), anisotropic diffusion (`diffusion`),
distance-layered diffusion (`layered`), phase-preserving log-Gabor denoising (`phase`), and their scores against
ground truth (`metrics`); `denoise_range` joins them for one frame.

>>> from rangesurf.denoise import anisotropic_diffusion
"""

import numpy as np

from rangesurf._checks import check_range_image, check_range_sigma
from rangesurf.denoise import metrics
from rangesurf.denoise.diffusion import (
    CONDUCTIONS,
    MAX_STABLE_STEP,
    METRIC_KAPPA_MULTIPLES,
    THESIS_PRESETS,
    DiffusionPreset,
    anisotropic_diffusion,
)
from rangesurf.denoise.layered import layer_weights, layered_denoise
from rangesurf.denoise.outliers import _remove_outliers, remove_cutoff, remove_flying_pixels, remove_isolated
from rangesurf.denoise.phase import PHASE_PRESETS, phase_preserving_denoise
from rangesurf.frame import SensorModel

__all__ = [
    "CONDUCTIONS",
    "MAX_STABLE_STEP",
    "METHODS",
    "METRIC_KAPPA_MULTIPLES",
    "PHASE_PRESETS",
    "THESIS_PRESETS",
    "DiffusionPreset",
    "anisotropic_diffusion",
    "denoise_range",
    "layer_weights",
    "layered_denoise",
    "metrics",
    "phase_preserving_denoise",
    "remove_cutoff",
    "remove_flying_pixels",
    "remove_isolated",
]


METHODS = ("diffusion", "layered", "phase", "none")


def denoise_range(
    range_image: np.ndarray,
    *,
    method: str = "diffusion",
    sensor: SensorModel | None = None,
    intensity: np.ndarray | None = None,
    rays: np.ndarray | None = None,
    remove_outliers: bool = True,
) -> np.ndarray:
    """Outlier removal, then edge-preserving smoothing: the denoise stage of one frame.

    Parameters
    ----------
    range_image : (H, W) float array
        Metres, NaN where there is no return.
    method : {"diffusion", "layered", "phase", "none"}
        ``"diffusion"``: `anisotropic_diffusion` in metric mode, its edge
        threshold from the sensor's noise model when ``sensor`` is given;
        ``"layered"``: `layered_denoise`, the thesis's distance layers, each
        diffused with the noise level of its range;
        ``"phase"``: `phase_preserving_denoise` (thesis preset "thesis-a");
        ``"none"``: outlier removal only.
    sensor : SensorModel, optional
        Supplies the cut-off (readings clamped to it are removed) and the
        per-pixel noise sigma that scales every threshold.
    intensity : (H, W) array, optional
        Return intensity, refining the noise sigma of dark surfaces.
    rays : (H, W, 3) array, optional
        Unit viewing rays (``frame.rays``): flying pixels are then removed
        only where the surface is seen almost edge-on, which keeps smooth
        grazing surfaces of coarse scanners (see `remove_flying_pixels`).
    remove_outliers : bool
        Remove cut-off readings, isolated spikes and flying pixels first.

    Returns
    -------
    (H, W) float32
        Denoised range, NaN where there is no return or an outlier was removed.

    Examples
    --------
    >>> from rangesurf import simulate
    >>> frames, truths = simulate.simulate_sequence("arena", "sr3000", 1, seed=0)
    >>> frame, truth = frames[0], truths[0]
    >>> smooth = denoise_range(frame.range, sensor=frame.sensor, intensity=frame.intensity, rays=frame.rays)
    >>> bool(np.nanmedian(np.abs(smooth - truth.range)) < np.nanmedian(np.abs(frame.range - truth.range)))
    True
    """
    if method not in METHODS:
        raise ValueError(f"unknown denoising method {method!r}; expected one of {', '.join(METHODS)}")
    range_image = check_range_image(range_image)
    sigma = None if sensor is None else check_range_sigma(range_image, sensor.range_sigma(range_image, intensity))
    if remove_outliers:
        # Flying pixels first: the cut-off readings beside them are the
        # "far side" of their jump (outliers module notes).
        clamped = sensor is not None and sensor.beyond_max_range == "clamp"
        range_image = _remove_outliers(range_image, sigma, rays, sensor.max_range if clamped else None)
    if method == "diffusion":
        return anisotropic_diffusion(range_image, range_sigma=sigma)
    if method == "phase":
        return phase_preserving_denoise(range_image)
    if method == "layered":
        return layered_denoise(range_image, range_sigma=sigma)
    return range_image
