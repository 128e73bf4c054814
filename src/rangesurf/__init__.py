"""rangesurf: online multi-resolution surface models from range-sensor streams.

>>> import rangesurf as rs
>>> frames = rs.load("scans/")                      # doctest: +SKIP
>>> frames, truths = rs.simulate.simulate_sequence("arena", "sr3000", n_frames=1)
>>> smooth = rs.denoise.anisotropic_diffusion(frames[0].range)
>>> smooth.shape
(144, 176)
"""

from rangesurf import denoise, edges, simulate
from rangesurf.frame import (
    SENSORS,
    PinholeProjection,
    RangeFrame,
    RangeNoiseModel,
    SensorModel,
    SweptFanProjection,
    get_sensor,
    unknown_sensor,
)
from rangesurf.io import FormatError, load, save

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "SENSORS",
    "FormatError",
    "PinholeProjection",
    "RangeFrame",
    "RangeNoiseModel",
    "SensorModel",
    "SweptFanProjection",
    "denoise",
    "edges",
    "get_sensor",
    "load",
    "save",
    "simulate",
    "unknown_sensor",
]
