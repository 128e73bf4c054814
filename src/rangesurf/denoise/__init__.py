"""Range-image denoising that keeps surface edges (thesis Section 3.1).

>>> from rangesurf.denoise import anisotropic_diffusion
"""

from rangesurf.denoise.diffusion import (
    CONDUCTIONS,
    MAX_STABLE_STEP,
    METRIC_KAPPA_MULTIPLES,
    THESIS_PRESETS,
    DiffusionPreset,
    anisotropic_diffusion,
)

__all__ = [
    "CONDUCTIONS",
    "MAX_STABLE_STEP",
    "METRIC_KAPPA_MULTIPLES",
    "THESIS_PRESETS",
    "DiffusionPreset",
    "anisotropic_diffusion",
]
