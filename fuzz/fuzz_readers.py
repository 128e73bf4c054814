"""Coverage-guided fuzzing of every reader (atheris / libFuzzer), seeded with the real files.

Run: ``.venv/bin/python fuzz/fuzz_readers.py FORMAT [-runs=N] [-max_total_time=S]`` with FORMAT one of
``3d ply pcd npz npy png``; e.g. ``.venv/bin/python fuzz/fuzz_readers.py ply -runs=100000``.
``fuzz/run_all.py`` runs every format for a fixed budget and records the counts in
``benchmarks/results/fuzz.md``.

Seeds: the real scans in ``../shared/data`` where the format has one (3DTK ``.3d``, the bunny's
``.ply``), plus a simulated frame written by rangesurf's writer in every format. The only outcomes
allowed for an input are valid frames or `rangesurf.io.FormatError`; anything else is a crash that
libFuzzer reports with the input saved as ``crash-*`` (turn each into a regression test).
Needs ``pip install atheris`` (not a dependency of rangesurf).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import atheris

# Coverage instrumentation for the pure-Python parsers only: rewriting Numba kernels' bytecode would
# break their compilation (the compiled number parsers are exercised all the same).
_PARSERS = ["rangesurf.io", "rangesurf.io.ply", "rangesurf.io.pcd", "rangesurf.io.uos", "rangesurf.io.npz",
            "rangesurf.io.depth_png", "rangesurf.io._common"]
with atheris.instrument_imports(include=_PARSERS):
    import numpy as np

    import rangesurf as rs
    from rangesurf.io import FormatError

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
FORMATS = ("3d", "ply", "pcd", "npz", "npy", "png")


def seed_corpus(form: str, folder: Path) -> None:
    """Seed files: real data where there is some, and a simulated frame through our own writer."""
    folder.mkdir(parents=True, exist_ok=True)
    # A small synthetic frame (a tilted plane with holes) of a 16 x 12 pinhole camera: small inputs
    # mutate and parse fast; the simulator's compiled kernels stay out of the instrumented process.
    sensor = rs.SensorModel(name="fuzz16x12", width=16, height=12, projection=rs.PinholeProjection(14.0, 14.0, 7.5, 5.5),
                            min_range=0.1, max_range=10.0, frame_rate=25.0)
    rays = sensor.rays()
    with np.errstate(divide="ignore"):
        range_image = (2.5 / np.maximum(rays @ np.array([0.1, -0.2, 0.97]), 0.2)).astype(np.float32)
    range_image[::7, ::5] = np.nan
    frame = rs.RangeFrame(rays=rays, range=range_image, sensor=sensor, intensity=np.full(sensor.shape, 0.5, np.float32))
    if form == "npy":
        np.save(folder / "seed.npy", frame.range)
    else:
        rs.save(folder / f"seed.{form}", frame)
    real = {"3d": [SHARED / "uos-3dtk" / "scan000.3d"], "ply": [SHARED / "bunny" / "bun045.ply"]}.get(form, [])
    for path in real:
        if path.is_file():
            # The first 64 kB: libFuzzer mutates better on small inputs, and headers matter most.
            (folder / f"real_{path.name}").write_bytes(path.read_bytes()[:65536])


def make_target(form: str):
    scratch = Path(tempfile.mkdtemp(prefix="rangesurf-fuzz-"))
    target = scratch / f"input.{form}"

    def test_one_input(data: bytes) -> None:
        target.write_bytes(data)
        try:
            for frame in rs.load(target):
                if np.isinf(frame.range).any():
                    raise AssertionError("a frame with Inf ranges")
        except FormatError:
            pass

    return test_one_input


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in FORMATS:
        sys.exit(f"usage: {sys.argv[0]} FORMAT [libFuzzer options]; FORMAT one of {', '.join(FORMATS)}")
    form = sys.argv[1]
    corpus = Path(os.environ.get("RANGESURF_FUZZ_CORPUS", tempfile.mkdtemp(prefix=f"corpus-{form}-")))
    seed_corpus(form, corpus)
    atheris.Setup([sys.argv[0], *sys.argv[2:], str(corpus)], make_target(form))
    atheris.Fuzz()


if __name__ == "__main__":
    main()
