"""Binary glTF (``.glb``) export of a model's surfaces, coloured by their uncertainty (via trimesh)."""

from __future__ import annotations

import os

import numpy as np

from rangesurf.io._common import atomic_write

__all__ = ["write_glb"]


def write_glb(path: str | os.PathLike, surfaces: list, *, levels: tuple[str, ...] = ("UL1", "UL2", "UL3", "UL4"),
              vmax: float | None = None) -> None:
    """Write surfaces as one ``.glb`` scene (one mesh per surface), atomically.

    Vertex colours show the uncertainty of the chosen levels, combined
    (root of the sum of squares): warmer is less certain
    (`rangesurf.glyphs.hue_colours`); surfaces without any of the levels are grey.

    Parameters
    ----------
    path : path-like
    surfaces : list of rangesurf.mesh.Surface
    levels : tuple of str
        Uncertainty levels to combine for the colours.
    vmax : float, optional
        Metres mapped to the hottest colour (default: the 95th percentile).
    """
    import trimesh

    from rangesurf.glyphs import combined_uncertainty, hue_colours

    values = [combined_uncertainty(surface, levels) for surface in surfaces]
    finite = np.concatenate([value[np.isfinite(value)] for value in values]) if values else np.zeros(0)
    if vmax is None:
        vmax = float(np.percentile(finite, 95)) if finite.size else 1.0
    scene = trimesh.Scene()
    for index, (surface, value) in enumerate(zip(surfaces, values), start=1):
        if surface.n_faces == 0:
            continue
        colours = hue_colours(value, vmax=vmax)
        mesh = trimesh.Trimesh(vertices=surface.vertices, faces=surface.faces, vertex_normals=surface.normals,
                               vertex_colors=colours, process=False)
        scene.add_geometry(mesh, node_name=f"surface_{index}")
    with atomic_write(path, "wb") as stream:
        stream.write(scene.export(file_type="glb"))
