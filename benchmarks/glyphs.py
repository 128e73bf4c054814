"""Speed of the uncertainty geometry: every method for a 100,000-vertex surface with all four levels.

Run: ``.venv/bin/python benchmarks/glyphs.py``; writes ``benchmarks/results/glyphs.md``.
The issue's target: well under 100 ms per method on one core.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from rangesurf import glyphs  # noqa: E402
from rangesurf.bench import machine_description, time_call, write_results  # noqa: E402
from rangesurf.mesh import Surface, triangulate_in_plane  # noqa: E402

LEVELS = ("UL1", "UL2", "UL3", "UL4")


def surface(side: int = 317) -> Surface:
    rows, cols = np.mgrid[0:side, 0:side] * 0.01
    count = side * side
    vertices = np.column_stack([cols.ravel(), rows.ravel(), 2.0 + 0.01 * np.sin(5 * cols.ravel())])
    rng = np.random.default_rng(0)
    uncertainty = {level: rng.uniform(0.001, 0.02, count) for level in LEVELS}
    return Surface(vertices, triangulate_in_plane(vertices, [0, 0, -1, 2.0]), np.tile([0, 0, -1.0], (count, 1)),
                   np.full((count, 2), -1), plane=[0, 0, -1, 2.0], uncertainty=uncertainty)


def main() -> None:
    mesh = surface()
    values = glyphs.combined_uncertainty(mesh, LEVELS)
    methods = {
        "hue colours": lambda: glyphs.hue_colours(values, vmax=0.03),
        "opacity": lambda: glyphs.opacity(values, vmax=0.03),
        "displaced points, cumulative": lambda: glyphs.displaced_points(mesh, LEVELS),
        "displaced points, separate": lambda: glyphs.displaced_points(mesh, LEVELS, mode="separate"),
        "bars, stacked": lambda: glyphs.bars(mesh, LEVELS),
        "shells": lambda: glyphs.shells(mesh, LEVELS),
        "uncertainty volume": lambda: glyphs.uncertainty_volume(mesh, LEVELS),
        "cones (2,000 glyphs)": lambda: glyphs.cones(mesh, "UL1", "UL4"),
        "perturbation": lambda: glyphs.perturbed(mesh, LEVELS),
        "oscillation (one frame)": lambda: glyphs.oscillating(mesh, LEVELS, 0.3),
    }
    lines = [f"Machine: {machine_description()}; one core. Command: `.venv/bin/python benchmarks/glyphs.py`.", "",
             f"A {mesh.n_vertices}-vertex, {mesh.n_faces}-triangle surface with all four levels; median of 7 calls.", "",
             "| method | ms | output |", "|---|---:|---|"]
    for name, method in methods.items():
        seconds = time_call(method, repeats=7)
        result = method()
        result = result[0] if isinstance(result, tuple) else result
        if isinstance(result, np.ndarray):
            size = f"{len(result)} values"
        else:
            size = ", ".join(f"{len(getattr(result, field))} {field}" for field in ("points", "segments", "vertices", "faces")
                             if getattr(result, field) is not None)
        lines.append(f"| {name} | {1e3 * seconds:.1f} | {size} |")
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    write_results(Path(__file__).parent / "results", "glyphs.md", lines)


if __name__ == "__main__":
    main()
