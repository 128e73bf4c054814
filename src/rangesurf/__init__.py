"""rangesurf: online multi-resolution surface models from range-sensor streams.

>>> import rangesurf as rs
>>> frames = rs.load("scans/")                      # doctest: +SKIP
>>> frames, truth = rs.simulate.simulate_sequence("arena", "sr3000", n_frames=3)  # doctest: +SKIP
"""

from rangesurf import simulate
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
    "get_sensor",
    "load",
    "save",
    "simulate",
    "unknown_sensor",
]
