"""Volumetric (TSDF) fusion of registered range frames, with marching-cubes meshes.

Planar segments merge as patches (thesis Section 3.3); curved objects such as
the bunny fuse better as a field. `TSDFVolume` keeps a truncated signed
distance function (Curless & Levoy 1996) on a sparse grid: blocks of 8^3
voxels are allocated only where some frame has seen a surface, found
through a hash table of block coordinates (voxel hashing, Niessner et al.
2013), so a 5 m room at 1-2 cm and a 15 cm object at 0.5-1 mm both fit in
memory (12 bytes per allocated voxel, 6 KiB per block).

Integration walks along each valid pixel's viewing ray through the
truncation band around the measured range (half-voxel steps) and updates the
voxels it passes, so it works for every sensor projection (pinhole cameras,
swept laser fans, per-pixel ray tables) -- nothing is projected through a
camera model. A voxel's signed distance is measured along the surface
normal of the pixel (point-to-plane, Bylow et al. 2013), positive in front
of the surface (toward the sensor), negative behind it, clipped to
``+truncation`` in front. Behind the reading the weight falls off linearly
from one voxel deep to zero at ``max(2 voxels, 3 sigma)`` (at most
``truncation``), as Curless & Levoy ramp it down: deeper updates let one
view's "inside" spill past convex edges into space that other views see as
free.

Observations are weighted by ``cos(incidence) / sigma**2`` with ``sigma``
the range noise (Curless & Levoy weight by the angle between ray and normal;
the inverse variance makes the fused distance the maximum-likelihood one).
Each voxel keeps the weighted mean distance, the total weight, and a
weighted sum of squared deviations (West 1979), so the disagreement of the
fused observations is known per voxel; with a registration covariance the
pose's uncertainty along the normal is added to it. `TSDFVolume.extract_mesh`
runs marching cubes (Lorensen & Cline 1987) over the allocated blocks and
across their borders, and carries that disagreement to every vertex as
uncertainty level UL3.

References
----------
.. [1] B. Curless and M. Levoy, "A volumetric method for building complex
   models from range images", SIGGRAPH 1996.
.. [2] W. E. Lorensen and H. E. Cline, "Marching cubes: a high resolution 3D
   surface construction algorithm", SIGGRAPH 1987 (the triangle table is
   P. Bourke's and C. Bloyd's public-domain one, as shipped by PyMCubes).
.. [3] M. Niessner, M. Zollhoefer, S. Izadi and M. Stamminger, "Real-time 3D
   reconstruction at scale using voxel hashing", ACM TOG 32(6), 2013.
.. [4] E. Bylow, J. Sturm, C. Kerl, F. Kahl and D. Cremers, "Real-time camera
   tracking and 3D reconstruction using signed distance functions", RSS 2013
   (point-to-plane signed distances).
.. [5] D. H. D. West, "Updating mean and variance estimates: an improved
   method", Communications of the ACM 22(9), 1979.
.. [6] The reference thesis, Section 3.3 (``shared/reference/thesis.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike

from rangesurf._checks import check_point_grid, check_range_sigma
from rangesurf._hashgrid import insert as _insert
from rangesurf._hashgrid import lookup as _lookup
from rangesurf._hashgrid import rehash as _rehash
from rangesurf.frame import RangeFrame, check_rigid_transform
from rangesurf.mesh import Surface

__all__ = ["TSDFVolume", "VoxelSample"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")
# Voxels per block side: 8^3 voxels x 3 float32 arrays = 6 KiB a block.
_BLOCK = 8
# Neighbouring readings whose ranges differ by more than this fraction lie across a depth step.
_NORMAL_JUMP = 0.05
# Readings seen more obliquely than this incidence cosine (about 78 deg) are not fused: their normals
# are unreliable, and a small normal error times the long band they cross is a large distance error.
_MIN_COSINE = 0.2
# The sampled ray band is at most this many times longer than the band along the normal.
_MAX_BAND_STRETCH = 2.0
# Depth updated behind a reading, at least: a cube crossing the surface has corners up to sqrt(3) voxels
# away. Deeper, one view's "inside" spills past convex edges into space that other views see as free.
_BEHIND_VOXELS = 2.0
# Block and voxel coordinates are int32; keep world coordinates well inside that.
_MAX_VOXEL_INDEX = 2**30

# Marching-cubes triangle table (Lorensen & Cline; Bourke/Bloyd's table as in PyMCubes):
# row = cube index (bit m set when corner m lies behind the surface), each character an edge 0-b,
# three per triangle. Corners: 0 (0,0,0) 1 (1,0,0) 2 (1,1,0) 3 (0,1,0) 4 (0,0,1) 5 (1,0,1) 6 (1,1,1) 7 (0,1,1).
_TRIANGLE_CODES = (
    "", "083", "019", "183981", "12a", "08312a", "92a029", "2832a8a98", "3b2", "0b28b0", "19023b", "1b219b98b",
    "3a1ba3", "0a108a8ba", "3903b9ba9", "98aa8b", "478", "430734", "019847", "419471731", "12a847", "34730412a",
    "92a902847", "2a9297273794", "8473b2", "b47b24204", "90184723b", "47b94b9b2921", "3a13ba784", "1ba14b1047b4",
    "47890b9bab03", "47b4b99ba", "954", "954083", "054150", "854835315", "12a954", "30812a495", "52a542402",
    "2a5325354348", "95423b", "0b208b495", "05401523b", "21525828b485", "a3ba13954", "4950818a18ba", "54050b5bab03",
    "54858aa8b", "978579", "930953573", "078017157", "153357", "978957a12", "a12950530573", "802825857a52",
    "2a5253357", "7957893b2", "95797292027b", "23b018178157", "b21b17715", "958857a13a3b", "5705097b010aba0",
    "ba0b03a50807570", "ba57b5", "a65", "0835a6", "9015a6", "1831985a6", "165261", "165126308", "965906026",
    "598582526328", "23ba65", "b08b20a65", "01923b5a6", "5a61929b298b", "63b653513", "08b0b50515b6", "3b6036065059",
    "65969bb98", "5a6478", "43047365a", "1905a6847", "a65197173794", "612651478", "125526304347", "847905065026",
    "739794329596269", "3b2784a65", "5a647242027b", "01947823b5a6", "9219b294b7b45a6", "8473b53515b6",
    "51b5b610b7b404b", "059065036b63847", "65969b4797b9", "a4964a", "4a649a083", "a01a60640", "83181686461a",
    "149124264", "308129249264", "024426", "832824426", "a49a64b23", "08228b49a4a6", "3b201606461a",
    "64161a48121b8b1", "964936913b63", "8b1810b61914641", "3b6360064", "648b68", "7a678a89a", "0730a709a67a",
    "a671a7178180", "a67a71173", "126168189867", "269291679093739", "780706602", "732672", "23ba68a89867",
    "20727b09767a9a7", "1801781a767a23b", "b21b17a61671", "896867916b63136", "091b67", "7807063b0b60", "7b6", "76b",
    "308b76", "019b76", "819831b76", "a126b7", "12a3086b7", "2902a96b7", "6b72a3a83a98", "723627", "708760620",
    "276237019", "162186198876", "a76a17137", "a7617a187108", "03707a0a96a7", "76a7a88a9", "684b86", "36b306046",
    "86b846901", "946963931b36", "6846b82a1", "12a30b06b046", "4b846b0292a9", "a93a32943b36463", "823842462",
    "042462", "190234246438", "194142246", "8138618466a1", "a10a06604", "4634386a3039a93", "a946a4", "49576b",
    "083495b76", "50154076b", "b76834354315", "954a1276b", "6b712a083495", "76b54a42a402", "348354325a52b76",
    "723762549", "954086062687", "362376150540", "628687218485158", "954a16176137", "16a176107870954",
    "40a4a503a6a737a", "76a7a854a48a", "6956b9b89", "36b063056095", "0b805b01556b", "6b3635531", "12a95b9b8b56",
    "0b306b09656912a", "b85b56805a52025", "6b36352a3a53", "589528562382", "956960062", "158180568382628", "156216",
    "13616a386569896", "a10a06950560", "03856a", "a56", "b5a75b", "b5ab75830", "5b75ab190", "a75ab7981831",
    "b12b71751", "08312717572b", "9759279022b7", "75272b592328982", "25a235375", "820852875a25", "9015a35373a2",
    "982921872a25752", "135375", "087071175", "903935537", "987597", "5845a8ab8", "5045b05abb30", "01984a8aba45",
    "ab4a45b34941314", "2512852b8458", "04b0b345b2b151b", "0250592b5458b85", "9452b3", "25a352345384", "5a2524420",
    "3a235a385458019", "5a2524192942", "845853351", "045105", "845853905035", "945", "4b749b9ab", "0834979b79ab",
    "1ab1b414074b", "3143481a474bab4", "4b79b492b912", "9749b791b2b1083", "b74b42240", "b74b42834324",
    "29a279237749", "9a7974a27870207", "37a3a274a1a040a", "1a2874", "491417713", "491417081871", "403743", "487",
    "9a8ab8", "30939bb9a", "01a0a88ab", "31ab3a", "12b1b99b8", "30939b1292b9", "02b80b", "32b", "23828aa89",
    "9a2092", "23828a0181a8", "1a2", "138918", "091", "038", "",
)


def _triangle_table() -> np.ndarray:
    table = np.full((256, 16), -1, np.int8)
    for index, code in enumerate(_TRIANGLE_CODES):
        table[index, : len(code)] = [int(edge, 16) for edge in code]
    return table


_TRIANGLES = _triangle_table()
_CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], np.int64
)
# Each edge as (corner at its lower end, corner at its upper end, axis).
_EDGES = np.array(
    [[0, 1, 0], [1, 2, 1], [3, 2, 0], [0, 3, 1], [4, 5, 0], [5, 6, 1],
     [7, 6, 0], [4, 7, 1], [0, 4, 2], [1, 5, 2], [2, 6, 2], [3, 7, 2]], np.int64
)


@dataclass(frozen=True)
class VoxelSample:
    """Fused values of the voxels nearest to some query points (`TSDFVolume.query`).

    Parameters
    ----------
    distance : (N,) float32
        Weighted mean signed distance (metres, positive in front of the
        surface); NaN where the voxel was never observed.
    weight : (N,) float32
        Sum of the observation weights ``cos(incidence) / sigma**2``
        (1/m^2); 0 where never observed.
    spread : (N,) float32
        UL3 of the voxel: ``sqrt(M2 / weight)`` (metres), the weighted
        standard deviation of the fused signed distances plus the
        registration variance (see `TSDFVolume`); NaN where never observed.
    """

    distance: np.ndarray
    weight: np.ndarray
    spread: np.ndarray


class TSDFVolume:
    """A sparse, block-allocated truncated signed distance volume.

    Parameters
    ----------
    voxel_size : float
        Edge of a voxel in metres (> 0). Voxel ``(i, j, k)`` is centred at
        ``(i, j, k) * voxel_size`` in the world frame.
    truncation : float, optional
        Depth of the band updated in front of each reading (metres), and the
        largest signed distance stored; default ``4 * voxel_size``; at least
        ``voxel_size``. Make it a few times the range noise. Behind a reading
        the band reaches ``max(2 * voxel_size, 3 * sigma)``, at most
        ``truncation``, with the weight ramping down to 0 from one voxel
        deep.
    max_weight : float, optional
        Cap on a voxel's total weight (1/m^2): past it, old observations are
        down-weighted so that the volume can follow change (KinectFusion's
        running average). Default: no cap.
    angle_weighting : bool
        Multiply each observation's weight by the cosine of its incidence
        angle (Curless & Levoy). Readings seen at more than about 78 deg
        (cosine < 0.2) are never fused.

    Notes
    -----
    Per voxel the volume stores, in float32: the weighted mean signed
    distance ``D``, the total weight ``W = sum w_i`` and the weighted sum of
    squared deviations ``M2 = sum w_i (d_i - D)**2 + sum w_i v_i``, where
    ``v_i`` is the variance, along the pixel's normal, of the pose given with
    that frame (``pose_covariance``; 0 without), and ``w_i`` the observation
    weight (times the ramp behind the surface). So ``sqrt(M2 / W)`` is the
    weighted standard deviation of the fused observations (their
    disagreement: noise, misregistration, change) combined with the
    registration's own uncertainty; that is uncertainty level UL3. One
    observation alone has no disagreement: its UL3 is its pose term only
    (the sensor's noise is UL1).

    Examples
    --------
    >>> import numpy as np, rangesurf as rs
    >>> from rangesurf.simulate import look_at
    >>> sensor = rs.get_sensor("sr3000")
    >>> T_world_sensor = look_at((0, 0, 0), (0, 0, 2), up=(0, -1, 0))
    >>> frame = rs.RangeFrame(rays=sensor.rays(), range=np.float32(2) / sensor.rays()[..., 2], sensor=sensor)
    >>> volume = TSDFVolume(0.02)
    >>> volume.integrate(frame, T_world_sensor, range_sigma=0.005)
    >>> surface = volume.extract_mesh()
    >>> bool(np.allclose(surface.vertices[:, 2], 2.0, atol=1e-3)), sorted(surface.uncertainty)
    (True, ['UL3'])
    """

    def __init__(
        self,
        voxel_size: float,
        *,
        truncation: float | None = None,
        max_weight: float | None = None,
        angle_weighting: bool = True,
    ) -> None:
        voxel_size = float(voxel_size)
        if not (math.isfinite(voxel_size) and voxel_size > 0):
            raise ValueError(f"voxel_size must be finite and > 0 metres, got {voxel_size}")
        truncation = 4.0 * voxel_size if truncation is None else float(truncation)
        if not (math.isfinite(truncation) and truncation >= voxel_size):
            raise ValueError(f"truncation must be finite and >= voxel_size ({voxel_size}), got {truncation}")
        if max_weight is not None:
            max_weight = float(max_weight)
            if not (max_weight > 0):  # also refuses NaN
                raise ValueError(f"max_weight must be > 0 (or None for no cap), got {max_weight}")
        self.voxel_size = voxel_size
        self.truncation = truncation
        self.max_weight = max_weight
        self.angle_weighting = bool(angle_weighting)
        self.n_frames = 0
        self._n_blocks = 0
        # Block capacity C (a power of two) and a hash table of 2 C entries: at most half full.
        self._table_keys = np.zeros((128, 3), np.int32)
        self._table_slots = np.full(128, -1, np.int32)
        self._coords = np.zeros((64, 3), np.int32)
        self._distance = np.zeros((64, _BLOCK, _BLOCK, _BLOCK), np.float32)
        self._weight = np.zeros_like(self._distance)
        self._m2 = np.zeros_like(self._distance)

    def __repr__(self) -> str:
        return (f"TSDFVolume(voxel_size={self.voxel_size}, truncation={self.truncation}, "
                f"blocks={self._n_blocks}, frames={self.n_frames})")

    @property
    def n_blocks(self) -> int:
        """Number of allocated blocks of 8^3 voxels."""
        return self._n_blocks

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """The volume as named arrays (for checkpoints; `from_arrays` rebuilds it exactly)."""
        n = self._n_blocks
        settings = np.array([self.voxel_size, self.truncation, np.nan if self.max_weight is None else self.max_weight,
                             float(self.angle_weighting), float(self.n_frames)])
        arrays = {"settings": settings, "coords": self._coords[:n], "distance": self._distance[:n],
                  "weight": self._weight[:n], "m2": self._m2[:n]}
        return {prefix + name: value for name, value in arrays.items()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], prefix: str = "") -> TSDFVolume:
        """Rebuild a volume written by `to_arrays`."""
        voxel_size, truncation, max_weight, angle_weighting, n_frames = (float(v) for v in arrays[prefix + "settings"])
        volume = cls(voxel_size, truncation=truncation, max_weight=None if math.isnan(max_weight) else max_weight,
                     angle_weighting=bool(angle_weighting))
        volume.n_frames = int(n_frames)
        coords = np.asarray(arrays[prefix + "coords"], np.int32)
        n = len(coords)
        capacity = 64
        while capacity < n:
            capacity *= 2
        volume._coords = np.zeros((capacity, 3), np.int32)
        volume._coords[:n] = coords
        for name in ("distance", "weight", "m2"):
            grown = np.zeros((capacity, _BLOCK, _BLOCK, _BLOCK), np.float32)
            grown[:n] = arrays[prefix + name]
            setattr(volume, f"_{name}", grown)
        volume._table_keys = np.zeros((2 * capacity, 3), np.int32)
        volume._table_slots = np.full(2 * capacity, -1, np.int32)
        _rehash(volume._table_keys, volume._table_slots, volume._coords, n)
        volume._n_blocks = n
        return volume

    @property
    def block_coordinates(self) -> np.ndarray:
        """``(n_blocks, 3)`` int32 block indices; block ``b`` holds voxels ``8 b .. 8 b + 7``."""
        return self._coords[: self._n_blocks].copy()

    @property
    def nbytes(self) -> int:
        """Bytes held by the voxel arrays and the block table (allocated capacity)."""
        arrays = (self._distance, self._weight, self._m2, self._coords, self._table_keys, self._table_slots)
        return int(sum(array.nbytes for array in arrays))

    # ------------------------------------------------------------------
    # Integration.
    # ------------------------------------------------------------------

    def integrate(
        self,
        frame_or_points: RangeFrame | ArrayLike,
        T_world_sensor: ArrayLike,
        *,
        range_sigma: float | ArrayLike | None = None,
        pose_covariance: ArrayLike | None = None,
        mask: ArrayLike | None = None,
    ) -> None:
        """Fuse one organized range frame seen from ``T_world_sensor``.

        Parameters
        ----------
        frame_or_points : RangeFrame or (H, W, 3) float array
            A frame (any projection: its ``rays`` and ``range`` are used;
            readings at the cut-off of a sensor that clamps there are no
            returns), or an organized point grid in the sensor frame (metres,
            NaN where there is no return), seen from the sensor origin.
            Readings without a normal (no neighbour along a grid row or
            column) or seen at more than about 78 deg incidence are not
            fused.
        T_world_sensor : (4, 4) array
            Rigid pose of the sensor in the world (e.g. a registered
            ``frame.pose``).
        range_sigma : float or (H, W) array, optional
            Range noise standard deviation (metres), > 0 wherever there is a
            return. Default: ``frame.sensor.range_sigma(range, intensity)``
            for a frame, and ``voxel_size`` where that model gives no value
            (sensors without a noise model) and for point grids.
        pose_covariance : (6, 6) array, optional
            Covariance of the pose as (rotation vector in radians,
            translation in metres) of a small correction applied on the
            world side, ``T <- exp(delta) T_world_sensor`` (the convention of
            `rangesurf.register.RegistrationResult.covariance` with the world
            model as target). Its projection onto each pixel's normal adds
            to that observation's variance: it lowers its weight and enters
            UL3. Must be finite and symmetric.
        mask : (H, W) bool array, optional
            Fuse only these pixels, e.g. the segments that are not planar
            (``labels`` of the non-planar segments), so that planar patches
            and the volume share one frame.

        Raises
        ------
        ValueError
            If the grid is not ``(H, W, 3)``, the pose not rigid, the sigma or
            covariance invalid, or the points too far from the origin for
            ``voxel_size``.
        """
        rays, range_image, sigma = self._unpack(frame_or_points, range_sigma)
        T_world_sensor = check_rigid_transform(T_world_sensor, "T_world_sensor")
        covariance = _check_covariance(pose_covariance)
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != range_image.shape or mask.dtype != bool:
                raise ValueError(
                    f"mask must be a boolean array of the range image's shape {range_image.shape}, "
                    f"got {mask.dtype} {mask.shape}"
                )
            range_image = np.where(mask, range_image, np.nan)
        range_image = np.ascontiguousarray(range_image, dtype=np.float32)
        rays = np.ascontiguousarray(rays, dtype=np.float32)
        points = rays * range_image[..., None]
        normals = _pixel_normals(points, range_image, rays, _NORMAL_JUMP)
        rotation, origin = T_world_sensor[:3, :3], T_world_sensor[:3, 3]
        # Readings without a normal (isolated, or on a one-pixel-wide strip) carry no plane to measure
        # from, and oblique ones an unreliable one: `_prepare_rays` keeps the others, in world coordinates.
        world_points, world_rays, world_normals, weight, pose_variance, behind, start, n_steps = _prepare_rays(
            points, range_image, rays, normals, np.ascontiguousarray(sigma, dtype=np.float64), rotation, origin,
            np.zeros((6, 6)) if covariance is None else covariance, covariance is not None, self.angle_weighting,
            self.voxel_size, self.truncation, _MIN_COSINE, _MAX_BAND_STRETCH, _BEHIND_VOXELS,
        )
        farthest = float(np.abs(world_points).max(initial=0.0))
        if (farthest + 4 * self.truncation) / self.voxel_size > _MAX_VOXEL_INDEX:
            raise ValueError(
                f"points lie up to {farthest:.4g} m from the world origin, too far for "
                f"voxel_size {self.voxel_size} m (voxel indices must stay below 2**30)"
            )
        self.n_frames += 1
        step = 0.5 * self.voxel_size
        next_ray = 0
        while next_ray < len(start):
            # The kernel allocates blocks as the rays reach them and stops before a ray that might not
            # fit; the arrays then double and it goes on from that ray.
            self._n_blocks, next_ray = _integrate_rays(
                self._table_keys, self._table_slots, self._coords, self._distance, self._weight, self._m2,
                self._n_blocks, next_ray, origin, world_points, world_rays, world_normals, weight, pose_variance,
                behind, start, n_steps, step, self.voxel_size, self.truncation,
                np.inf if self.max_weight is None else self.max_weight,
            )
            if next_ray < len(start):
                self._grow()

    def _unpack(self, frame_or_points: Any, range_sigma: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays (H, W, 3), range (H, W) with NaN, and sigma (H, W) float64 of the input."""
        if isinstance(frame_or_points, RangeFrame):
            frame = frame_or_points
            rays, range_image = frame.rays, frame.range
            if frame.sensor.beyond_max_range == "clamp":
                # The cut-off value is "nothing within range" (thesis Section 2.1), not a surface.
                with np.errstate(invalid="ignore"):
                    range_image = np.where(range_image >= frame.sensor.max_range, np.nan, range_image)
            if range_sigma is None:
                finite = np.where(np.isfinite(range_image), range_image, 1.0)
                sigma = np.asarray(frame.sensor.range_sigma(finite, frame.intensity), np.float64)
                sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, self.voxel_size)
                return rays, range_image, np.broadcast_to(sigma, range_image.shape)
        else:
            points = check_point_grid(frame_or_points, "points")
            range_image = np.linalg.norm(points, axis=-1)
            range_image[~(range_image > 0)] = np.nan
            with np.errstate(invalid="ignore", divide="ignore"):
                rays = points / range_image[..., None]
        if range_sigma is None:
            return rays, range_image, np.full(range_image.shape, self.voxel_size)
        return rays, range_image, check_range_sigma(range_image, range_sigma)

    def _grow(self) -> None:
        """Double the block arrays and the hash table (rehashing the blocks)."""
        capacity = 2 * len(self._coords)
        n = self._n_blocks
        self._table_keys = np.zeros((2 * capacity, 3), np.int32)
        self._table_slots = np.full(2 * capacity, -1, np.int32)
        coords = np.zeros((capacity, 3), np.int32)
        coords[:n] = self._coords[:n]
        self._coords = coords
        _rehash(self._table_keys, self._table_slots, self._coords, n)
        for name in ("_distance", "_weight", "_m2"):
            grown = np.zeros((capacity, _BLOCK, _BLOCK, _BLOCK), np.float32)
            grown[:n] = getattr(self, name)[:n]
            setattr(self, name, grown)

    # ------------------------------------------------------------------
    # Read-out.
    # ------------------------------------------------------------------

    def query(self, points: ArrayLike) -> VoxelSample:
        """Fused values of the voxel nearest to each world point.

        Parameters
        ----------
        points : (N, 3) array
            World coordinates in metres.

        Returns
        -------
        VoxelSample
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {points.shape}")
        if not np.all(np.isfinite(points)):
            raise ValueError("points contain NaN or Inf")
        index = np.floor(points / self.voxel_size + 0.5)
        if index.size and np.abs(index).max() > _MAX_VOXEL_INDEX:
            raise ValueError(f"points too far from the origin for voxel_size {self.voxel_size}")
        distance, weight, m2 = _query(
            self._table_keys, self._table_slots, self._distance, self._weight, self._m2, index.astype(np.int64)
        )
        observed = weight > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            spread = np.where(observed, np.sqrt(np.maximum(m2, 0) / weight), np.nan)
        return VoxelSample(
            distance=np.where(observed, distance, np.nan).astype(np.float32),
            weight=weight.astype(np.float32),
            spread=spread.astype(np.float32),
        )

    def extract_mesh(self, *, min_weight: float = 0.0) -> Surface:
        """The zero level set as a triangle mesh, by marching cubes over the allocated blocks.

        A cube (eight neighbouring voxels, across block borders too) gives
        triangles only if all its corners were observed with weight above
        ``min_weight`` and no two corners of opposite sign differ by more
        than ``sqrt(3) * min(truncation, 2 voxels)`` (a signed distance
        changes by at most sqrt(3) voxels across a cube; a jump from a
        clipped ``+truncation`` to negative is a silhouette or a thin wall
        seen from both sides, not a surface crossing). Vertices are
        shared between cubes, so a closed, fully observed object gives a
        closed mesh.

        Parameters
        ----------
        min_weight : float
            Minimum total weight (1/m^2) of every corner, >= 0.

        Returns
        -------
        Surface
            World coordinates. ``vertices`` (N, 3) float32, ``faces`` (M, 3)
            int32 counter-clockwise seen from the front (free space, where the
            sensors were), ``normals`` (N, 3) float32 pointing to the front,
            ``pixels`` -1, ``plane`` NaN, and ``uncertainty["UL3"]`` (N,)
            float32: ``sqrt(M2 / W)`` of the cube corners (see the class
            Notes), interpolated linearly along the edge that holds the
            vertex -- the weighted standard deviation, in metres along the
            normal, of the signed distances fused there, plus the
            registration variance when poses came with a covariance.
        """
        min_weight = float(min_weight)
        if not (math.isfinite(min_weight) and min_weight >= 0):
            raise ValueError(f"min_weight must be finite and >= 0, got {min_weight}")
        n = self._n_blocks
        neighbours = _block_neighbours(self._table_keys, self._table_slots, self._coords, n)
        # The signed distance changes by at most a voxel per voxel: a larger jump is no crossing.
        max_jump = min(self.truncation, 2.0 * self.voxel_size)
        counts, cube_indices = _count_triangles(
            self._distance, self._weight, neighbours, n, _TRIANGLES, _CORNERS, min_weight, max_jump
        )
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        n_triangles = int(offsets[-1])
        if n_triangles == 0:
            empty = np.zeros((0, 3))
            return Surface(vertices=empty, faces=np.zeros((0, 3), np.int32), normals=empty,
                           pixels=np.zeros((0, 2), np.int32), uncertainty={"UL3": np.zeros(0, np.float32)})
        edge_ids, positions, variance = _emit_triangles(
            self._distance, self._weight, self._m2, self._coords, neighbours, n, cube_indices, _TRIANGLES, _CORNERS,
            _EDGES, min_weight, max_jump, offsets, self.voxel_size,
        )
        _, first, inverse = np.unique(edge_ids, return_index=True, return_inverse=True)
        # The table winds triangles clockwise seen from the corners it marks (behind the surface).
        faces = inverse.reshape(-1, 3)[:, ::-1].astype(np.int32)
        # Triangles collapsed onto a corner (two of their vertices on it).
        faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
        # Keep only the vertices some triangle still uses (numbered in the order of their grid edges).
        used = np.zeros(len(first), bool)
        used[faces] = True
        renumber = np.cumsum(used) - 1
        faces = renumber[faces].astype(np.int32)
        first = first[used]
        vertices = positions[first]
        uncertainty = np.sqrt(np.maximum(variance[first], 0.0)).astype(np.float32)
        return Surface(
            vertices=vertices, faces=faces, normals=_vertex_normals(vertices, faces),
            pixels=np.full((len(vertices), 2), -1, np.int32), uncertainty={"UL3": uncertainty},
        )


def _check_covariance(covariance: Any) -> np.ndarray | None:
    if covariance is None:
        return None
    matrix = np.asarray(covariance, dtype=np.float64)
    if matrix.shape != (6, 6):
        raise ValueError(f"pose_covariance must be a (6, 6) matrix, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise ValueError("pose_covariance must be finite (a degenerate registration has Inf: do not fuse it, or cap it)")
    if not np.allclose(matrix, matrix.T, rtol=1e-6, atol=1e-12):
        raise ValueError("pose_covariance must be symmetric")
    return matrix


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (the faces' winding sets their side)."""
    corners = vertices[faces].astype(np.float64)
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.stack(
        [np.bincount(faces.ravel(), np.repeat(face_normals[:, k], 3), minlength=len(vertices)) for k in range(3)],
        axis=1,
    )
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.full_like(normals, np.nan), where=length > 0).astype(np.float32)


# --------------------------------------------------------------------------
# Kernels (compiled; NumPy references in the tests).
# --------------------------------------------------------------------------


@numba.njit(**_JIT)
def _difference(points, range_image, row, col, d_row, d_col, jump):  # pragma: no cover - compiled
    """Central (or one-sided) difference of the point grid along one grid axis, without crossing depth steps."""
    height, width = range_image.shape
    here = range_image[row, col]
    forward = False
    backward = False
    r, c = row + d_row, col + d_col
    if r < height and c < width:
        value = range_image[r, c]
        forward = np.isfinite(value) and abs(value - here) <= jump * here
    r, c = row - d_row, col - d_col
    if r >= 0 and c >= 0:
        value = range_image[r, c]
        backward = np.isfinite(value) and abs(value - here) <= jump * here
    a_row, a_col, b_row, b_col = row, col, row, col
    if forward:
        a_row, a_col = row + d_row, col + d_col
    if backward:
        b_row, b_col = row - d_row, col - d_col
    ok = forward or backward
    return (points[a_row, a_col, 0] - points[b_row, b_col, 0], points[a_row, a_col, 1] - points[b_row, b_col, 1],
            points[a_row, a_col, 2] - points[b_row, b_col, 2], ok)


@numba.njit(**_JIT)
def _pixel_normals(points, range_image, rays, jump):  # pragma: no cover - compiled
    """Unit normals (H, W, 3) float32 of an organized grid facing the sensor; NaN where unknown.

    Unknown: no return, or no neighbour with a return across a grid row or column (isolated readings,
    silhouettes), or a degenerate cross product.
    """
    height, width = range_image.shape
    normals = np.empty((height, width, 3), np.float32)
    for row in range(height):
        for col in range(width):
            rx, ry, rz = rays[row, col, 0], rays[row, col, 1], rays[row, col, 2]
            nx, ny, nz = np.nan, np.nan, np.nan
            if np.isfinite(range_image[row, col]):
                ux, uy, uz, ok_u = _difference(points, range_image, row, col, 0, 1, jump)
                vx, vy, vz, ok_v = _difference(points, range_image, row, col, 1, 0, jump)
                if ok_u and ok_v:
                    cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
                    length = math.sqrt(cx * cx + cy * cy + cz * cz)
                    if length > 0:
                        if cx * rx + cy * ry + cz * rz > 0:
                            length = -length
                        nx, ny, nz = cx / length, cy / length, cz / length
            normals[row, col, 0] = nx
            normals[row, col, 1] = ny
            normals[row, col, 2] = nz
    return normals


@numba.njit(**_JIT)
def _prepare_rays(
    points, range_image, rays, normals, sigma, rotation, origin, covariance, use_covariance, angle_weighting,
    voxel_size, truncation, min_cosine, max_stretch, behind_voxels,
):  # pragma: no cover - compiled
    """World point, ray and normal of every reading to fuse, its weight, pose variance and ray band.

    Kept: readings with a normal seen at an incidence cosine >= ``min_cosine``. The band runs from
    ``truncation`` in front of the reading to ``behind`` behind it (along the normal), stretched along
    the ray by ``1 / max(cos, 1 / max_stretch)``; ``n_steps`` samples half a voxel apart from ``start``.
    """
    height, width = range_image.shape
    capacity = height * width
    world_points = np.empty((capacity, 3))
    world_rays = np.empty((capacity, 3))
    world_normals = np.empty((capacity, 3))
    weight = np.empty(capacity)
    pose_variance = np.zeros(capacity)
    behind = np.empty(capacity)
    start = np.empty(capacity)
    n_steps = np.empty(capacity, np.int64)
    lever = np.empty(6)
    step = 0.5 * voxel_size
    n = 0
    for row in range(height):
        for col in range(width):
            if not np.isfinite(normals[row, col, 0]):
                continue
            cosine = 0.0
            for a in range(3):
                ray = (rotation[a, 0] * rays[row, col, 0] + rotation[a, 1] * rays[row, col, 1]
                       + rotation[a, 2] * rays[row, col, 2])
                normal = (rotation[a, 0] * normals[row, col, 0] + rotation[a, 1] * normals[row, col, 1]
                          + rotation[a, 2] * normals[row, col, 2])
                point = (origin[a] + rotation[a, 0] * points[row, col, 0] + rotation[a, 1] * points[row, col, 1]
                         + rotation[a, 2] * points[row, col, 2])
                world_rays[n, a], world_normals[n, a], world_points[n, a] = ray, normal, point
                cosine -= ray * normal
            if cosine < min_cosine:
                continue
            variance = sigma[row, col] ** 2
            if use_covariance:
                px, py, pz = world_points[n, 0], world_points[n, 1], world_points[n, 2]
                nx, ny, nz = world_normals[n, 0], world_normals[n, 1], world_normals[n, 2]
                lever[0], lever[1], lever[2] = py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx
                lever[3], lever[4], lever[5] = nx, ny, nz
                total = 0.0
                for a in range(6):
                    for b in range(6):
                        total += lever[a] * covariance[a, b] * lever[b]
                pose_variance[n] = max(total, 0.0)
            weight[n] = (cosine if angle_weighting else 1.0) / (variance + pose_variance[n])
            behind[n] = min(truncation, max(behind_voxels * voxel_size, 3.0 * math.sqrt(variance)))
            stretch = 1.0 / max(cosine, 1.0 / max_stretch)
            reading = np.float64(range_image[row, col])
            start[n] = max(reading - truncation * stretch, step)
            n_steps[n] = np.int64(math.floor((reading + behind[n] * stretch - start[n]) / step)) + 1
            n += 1
    return (world_points[:n], world_rays[:n], world_normals[:n], weight[:n], pose_variance[:n], behind[:n],
            start[:n], n_steps[:n])


@numba.njit(**_JIT)
def _sample_voxel(origin, ray, t, voxel_size):  # pragma: no cover - compiled
    """Voxel index nearest to ``origin + t * ray`` (voxel centres at integer multiples of the size)."""
    return (np.int64(math.floor((origin[0] + t * ray[0]) / voxel_size + 0.5)),
            np.int64(math.floor((origin[1] + t * ray[1]) / voxel_size + 0.5)),
            np.int64(math.floor((origin[2] + t * ray[2]) / voxel_size + 0.5)))


@numba.njit(**_JIT)
def _integrate_rays(
    keys, slots, coords, distance, weight, m2, n_blocks, first_ray, origin, points, rays, normals,
    observation_weight, pose_variance, behind, start, n_steps, step, voxel_size, truncation, max_weight,
):  # pragma: no cover - compiled
    """Weighted running mean and squared deviations of point-to-plane distances along each ray's band.

    Allocates blocks on the way; returns ``(n_blocks, next_ray)``, ``next_ray < len(start)`` when the
    arrays may be too small for that ray (grow them and call again from there).
    """
    capacity = len(coords)
    for i in range(first_ray, len(start)):
        # A ray visits at most n_steps blocks: room for them all before touching anything.
        if n_blocks + n_steps[i] > capacity:
            return n_blocks, i
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        ray_weight = observation_weight[i]
        dropoff_end = behind[i]
        v = pose_variance[i]
        last_x, last_y, last_z = np.int64(-(2**40)), np.int64(0), np.int64(0)
        cached_x, cached_y, cached_z, cached = np.int64(-(2**40)), np.int64(0), np.int64(0), -1
        for s in range(n_steps[i]):
            vx, vy, vz = _sample_voxel(origin, rays[i], start[i] + s * step, voxel_size)
            if vx == last_x and vy == last_y and vz == last_z:
                continue
            last_x, last_y, last_z = vx, vy, vz
            d = nx * (vx * voxel_size - px) + ny * (vy * voxel_size - py) + nz * (vz * voxel_size - pz)
            if d < -dropoff_end:
                continue
            if d > truncation:
                d = truncation
            w = ray_weight
            if d < -voxel_size:
                # Behind the surface the reading says less and less (Curless & Levoy's ramp).
                w *= (dropoff_end + d) / (dropoff_end - voxel_size)
                if not w > 0:
                    continue
            bx, by, bz = vx >> 3, vy >> 3, vz >> 3
            if bx != cached_x or by != cached_y or bz != cached_z:
                cached_x, cached_y, cached_z = bx, by, bz
                cached = _lookup(keys, slots, bx, by, bz)
                if cached < 0:
                    cached = n_blocks
                    coords[cached, 0], coords[cached, 1], coords[cached, 2] = bx, by, bz
                    _insert(keys, slots, bx, by, bz, cached)
                    n_blocks += 1
            li, lj, lk = vx - (bx << 3), vy - (by << 3), vz - (bz << 3)
            old_weight = np.float64(weight[cached, li, lj, lk])
            old_m2 = np.float64(m2[cached, li, lj, lk])
            if old_weight + w > max_weight:
                # A running average: old observations fade, mean and spread keep their meaning.
                keep = max(max_weight - w, 0.0) / old_weight
                old_weight *= keep
                old_m2 *= keep
            new_weight = old_weight + w
            mean = np.float64(distance[cached, li, lj, lk])
            delta = d - mean
            mean += delta * (w / new_weight)
            distance[cached, li, lj, lk] = mean
            weight[cached, li, lj, lk] = new_weight
            m2[cached, li, lj, lk] = old_m2 + w * delta * (d - mean) + w * v
    return n_blocks, len(start)


@numba.njit(**_JIT)
def _query(keys, slots, distance, weight, m2, index):  # pragma: no cover - compiled
    n = len(index)
    out_distance = np.zeros(n)
    out_weight = np.zeros(n)
    out_m2 = np.zeros(n)
    for i in range(n):
        vx, vy, vz = index[i, 0], index[i, 1], index[i, 2]
        bx, by, bz = vx >> 3, vy >> 3, vz >> 3
        slot = _lookup(keys, slots, bx, by, bz)
        if slot >= 0:
            li, lj, lk = vx - (bx << 3), vy - (by << 3), vz - (bz << 3)
            out_distance[i] = distance[slot, li, lj, lk]
            out_weight[i] = weight[slot, li, lj, lk]
            out_m2[i] = m2[slot, li, lj, lk]
    return out_distance, out_weight, out_m2


@numba.njit(**_JIT)
def _block_neighbours(keys, slots, coords, n_blocks):  # pragma: no cover - compiled
    """Slots of each block's +x/+y/+z neighbours, ``[b, dx, dy, dz]`` for offsets in {0, 1}; -1 if absent."""
    neighbours = np.full((n_blocks, 2, 2, 2), -1, np.int32)
    for b in range(n_blocks):
        for dx in range(2):
            for dy in range(2):
                for dz in range(2):
                    neighbours[b, dx, dy, dz] = _lookup(
                        keys, slots, coords[b, 0] + dx, coords[b, 1] + dy, coords[b, 2] + dz
                    )
    return neighbours


@numba.njit(**_JIT)
def _cube_index(distance, weight, neighbours, b, i, j, k, corners, min_weight, max_jump, values, slot_of, local_of):
    # pragma: no cover - compiled
    """Marching-cubes index of cube (i, j, k) of block b, or -1 if it is not usable.

    Fills ``values`` (8,) with the corners' distances, ``slot_of`` and ``local_of`` with where they are stored.
    """
    index = 0
    for m in range(8):
        ci, cj, ck = i + corners[m, 0], j + corners[m, 1], k + corners[m, 2]
        slot = neighbours[b, ci >> 3, cj >> 3, ck >> 3]
        if slot < 0:
            return -1
        li, lj, lk = ci & 7, cj & 7, ck & 7
        if not weight[slot, li, lj, lk] > min_weight:
            return -1
        value = distance[slot, li, lj, lk]
        values[m] = value
        slot_of[m] = slot
        local_of[m] = (li * _BLOCK + lj) * _BLOCK + lk
        if value < 0:
            index |= 1 << m
    if index == 0 or index == 255:
        return 0
    # Opposite signs across more than a voxel's worth of distance: a clipped band edge, not a crossing.
    for a in range(8):
        for c in range(a + 1, 8):
            if (values[a] < 0) != (values[c] < 0) and abs(values[a] - values[c]) > max_jump * 1.7320508075688772:
                return -1
    return index


@numba.njit(**_JIT)
def _count_triangles(distance, weight, neighbours, n_blocks, triangles, corners, min_weight, max_jump):
    # pragma: no cover - compiled
    """Triangles per block, and every cube's marching-cubes index (0: no triangles) for the second pass."""
    counts = np.zeros(n_blocks, np.int64)
    indices = np.zeros((n_blocks, _BLOCK**3), np.uint8)
    values = np.empty(8)
    slot_of = np.empty(8, np.int64)
    local_of = np.empty(8, np.int64)
    for b in range(n_blocks):
        count = 0
        for i in range(_BLOCK):
            for j in range(_BLOCK):
                for k in range(_BLOCK):
                    index = _cube_index(distance, weight, neighbours, b, i, j, k, corners, min_weight, max_jump,
                                        values, slot_of, local_of)
                    if index > 0:
                        indices[b, (i * _BLOCK + j) * _BLOCK + k] = index
                        m = 0
                        while m < 16 and triangles[index, m] >= 0:
                            m += 3
                        count += m // 3
        counts[b] = count
    return counts, indices


@numba.njit(**_JIT)
def _emit_triangles(
    distance, weight, m2, coords, neighbours, n_blocks, cube_indices, triangles, corners, edges, min_weight,
    max_jump, offsets, voxel_size,
):  # pragma: no cover - compiled
    """Per triangle corner: the id of the grid edge (or voxel) it lies on, its position and its UL3 variance."""
    n_corners = 3 * offsets[n_blocks]
    edge_ids = np.empty(n_corners, np.int64)
    positions = np.empty((n_corners, 3), np.float32)
    variance = np.empty(n_corners, np.float32)
    values = np.empty(8)
    slot_of = np.empty(8, np.int64)
    local_of = np.empty(8, np.int64)
    base = np.empty(3)
    cube_corner = np.empty(3)
    m2_flat = m2.reshape(len(m2), _BLOCK**3)
    weight_flat = weight.reshape(len(weight), _BLOCK**3)
    for b in range(n_blocks):
        out = 3 * offsets[b]
        for a in range(3):
            base[a] = np.float64(coords[b, a]) * _BLOCK
        for cube in range(_BLOCK**3):
            if cube_indices[b, cube] == 0:
                continue
            i, j, k = cube // (_BLOCK * _BLOCK), (cube // _BLOCK) % _BLOCK, cube % _BLOCK
            cube_corner[0], cube_corner[1], cube_corner[2] = i, j, k
            index = _cube_index(distance, weight, neighbours, b, i, j, k, corners, min_weight, max_jump,
                                values, slot_of, local_of)
            m = 0
            while m < 16 and triangles[index, m] >= 0:
                edge = triangles[index, m]
                low, high, axis = edges[edge, 0], edges[edge, 1], edges[edge, 2]
                t = values[low] / (values[low] - values[high])
                for a in range(3):
                    along = t if a == axis else 0.0
                    positions[out, a] = (base[a] + cube_corner[a] + corners[low, a] + along) * voxel_size
                ls, ll = slot_of[low], local_of[low]
                hs, hl = slot_of[high], local_of[high]
                low_variance = m2_flat[ls, ll] / weight_flat[ls, ll]
                high_variance = m2_flat[hs, hl] / weight_flat[hs, hl]
                variance[out] = (1 - t) * low_variance + t * high_variance
                # A vertex on a corner (distance exactly 0) is shared by all the corner's edges.
                if values[low] == 0:
                    edge_ids[out] = (ls * _BLOCK**3 + ll) * 4 + 3
                elif values[high] == 0:
                    edge_ids[out] = (hs * _BLOCK**3 + hl) * 4 + 3
                else:
                    edge_ids[out] = (ls * _BLOCK**3 + ll) * 4 + axis
                out += 1
                m += 1
    return edge_ids, positions, variance
