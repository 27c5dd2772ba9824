"""The virtual rig's scene: analytic primitives and triangle meshes, ray casting and surface albedo.

Every object of ``virtual_rig.scene`` becomes one object id (its index in the list). Planes, spheres,
boxes and cylinders are intersected analytically; meshes through a bounding volume hierarchy, with
Möller–Trumbore triangle tests, in numba kernels (``_sim_kernels.py``). Normals are geometric (flat per
triangle). Albedo is a per-object function of the 3-D point, so an object's texture can be swapped, e.g.
for a printed calibration board (:class:`PlaneImageAlbedo`).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from appliance.config.schema import (
    BoxObject,
    CylinderObject,
    MeshObject,
    PlaneObject,
    SceneObject,
    SphereObject,
)
from appliance.errors import ConfigError
from appliance.sim import _sim_kernels as _k

F64 = npt.NDArray[np.float64]
I32 = npt.NDArray[np.int32]
I64 = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

AlbedoFn = Callable[[F64], F64]
"""Albedo of an object: world points (N, 3) mm -> reflectance (N,) in [0, 1]."""

_LEAF_TRIANGLES = 4


@dataclass(frozen=True)
class RayHits:
    """Nearest hits of N rays.

    Attributes
    ----------
    t : ndarray, shape (N,), float64
        Ray parameter of the hit (mm for unit directions); ``inf`` where nothing was hit.
    object_id : ndarray, shape (N,), int32
        Index of the hit object in the scene; -1 where nothing was hit.
    normal : ndarray, shape (N, 3), float64
        Unit outward geometric normal at the hit (planes: their configured normal); 0 where no hit.
    """

    t: F64
    object_id: I32
    normal: F64


# --- geometry helpers ---------------------------------------------------------------------------------------


def rotation_xyz_deg(angles_deg: Iterable[float]) -> F64:
    """Rotation matrix (3, 3) of rotations about x, then y, then z (degrees): ``Rz @ Ry @ Rx``."""
    ax, ay, az = (math.radians(a) for a in angles_deg)
    cx, sx = math.cos(ax), math.sin(ax)
    cy, sy = math.cos(ay), math.sin(ay)
    cz, sz = math.cos(az), math.sin(az)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray(rz @ ry @ rx, dtype=np.float64)


def _unit(v: Iterable[float], what: str) -> F64:
    a = np.asarray(tuple(v), dtype=np.float64)
    n = float(np.linalg.norm(a))
    if not n > 0:
        raise ConfigError(f"scene: {what} = {tuple(a)}: must be a non-zero vector")
    return a / n


def icosphere(center_mm: Iterable[float], radius_mm: float, subdivisions: int = 3) -> tuple[F64, I64]:
    """Triangle mesh of a sphere: an icosahedron subdivided ``subdivisions`` times, vertices on the sphere.

    Parameters
    ----------
    center_mm : (3,) float
        Centre (mm).
    radius_mm : float
        Radius (mm); every vertex lies on the sphere.
    subdivisions : int
        Each subdivision splits every triangle in four (20 * 4**subdivisions triangles).

    Returns
    -------
    vertices : ndarray, shape (V, 3), float64
        Vertices (mm).
    triangles : ndarray, shape (T, 3), int64
        Vertex indices, counter-clockwise seen from outside.
    """
    g = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [(-1, g, 0), (1, g, 0), (-1, -g, 0), (1, -g, 0), (0, -1, g), (0, 1, g), (0, -1, -g), (0, 1, -g),
             (g, 0, -1), (g, 0, 1), (-g, 0, -1), (-g, 0, 1)]
    tris = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
            (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
            (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    v = [np.asarray(p, dtype=np.float64) / np.linalg.norm(p) for p in verts]
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}
        new: list[tuple[int, int, int]] = []
        for a, b, c in tris:
            ab, bc, ca = (_midpoint(v, cache, p, q) for p, q in ((a, b), (b, c), (c, a)))
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        tris = new
    vertices = np.asarray(v) * float(radius_mm) + np.asarray(tuple(center_mm), dtype=np.float64)
    return vertices, np.asarray(tris, dtype=np.int64)


def _midpoint(v: list[F64], cache: dict[tuple[int, int], int], a: int, b: int) -> int:
    key = (min(a, b), max(a, b))
    if key not in cache:
        m = v[a] + v[b]
        v.append(m / np.linalg.norm(m))
        cache[key] = len(v) - 1
    return cache[key]


def load_mesh(path: Path) -> tuple[F64, I64]:
    """Read a triangle mesh from an OBJ, STL (ASCII or binary) or PLY file (PLY needs ``plyfile``).

    Polygons are fan-triangulated.

    Returns
    -------
    vertices : ndarray, shape (V, 3), float64
        In the file's units (taken as mm).
    triangles : ndarray, shape (T, 3), int64
    """
    suffix = path.suffix.lower()
    try:
        if path.exists() and not path.is_file():  # a FIFO or a device would block or never end
            raise ConfigError(f"scene mesh {path}: not a regular file; give a mesh file")
        if suffix == ".obj":
            return _load_obj(path)
        if suffix == ".stl":
            return _load_stl(path)
        if suffix == ".ply":
            return _load_ply(path)
    except OSError as exc:
        raise ConfigError(f"scene mesh {path}: cannot read: {exc}; check the path") from exc
    except (ValueError, IndexError, struct.error) as exc:
        raise ConfigError(f"scene mesh {path}: malformed {suffix[1:].upper()} file: {exc}") from exc
    raise ConfigError(f"scene mesh {path}: suffix {suffix!r}: must be .obj, .stl or .ply")


def _fan(poly: list[int]) -> list[tuple[int, int, int]]:
    return [(poly[0], poly[i], poly[i + 1]) for i in range(1, len(poly) - 1)]


def _load_obj(path: Path) -> tuple[F64, I64]:
    verts: list[tuple[float, float, float]] = []
    tris: list[tuple[int, int, int]] = []
    for line in path.read_text().splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            verts.append((float(parts[1]), float(parts[2]), float(parts[3])))
        elif parts[0] == "f":
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            tris += _fan([i - 1 if i > 0 else len(verts) + i for i in idx])
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _load_stl(path: Path) -> tuple[F64, I64]:
    data = path.read_bytes()
    if len(data) >= 84:
        (count,) = struct.unpack_from("<I", data, 80)
        if len(data) == 84 + 50 * count:
            rec = np.frombuffer(data, dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]),
                                count=count, offset=84)
            v = rec["v"].astype(np.float64).reshape(-1, 3)
            return v, np.arange(v.shape[0], dtype=np.int64).reshape(-1, 3)
    pts = [tuple(float(x) for x in ln.split()[1:4]) for ln in data.decode("ascii").splitlines()
           if ln.strip().startswith("vertex")]
    v = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    return v, np.arange(v.shape[0], dtype=np.int64).reshape(-1, 3)


def _load_ply(path: Path) -> tuple[F64, I64]:
    try:
        from plyfile import PlyData
    except ImportError as exc:
        raise ConfigError(
            f"scene mesh {path}: reading PLY needs the 'plyfile' package; pip install plyfile"
        ) from exc
    ply = PlyData.read(str(path))
    vx = ply["vertex"]
    v = np.stack([np.asarray(vx["x"]), np.asarray(vx["y"]), np.asarray(vx["z"])], axis=1).astype(np.float64)
    faces = ply["face"].data
    key = "vertex_indices" if "vertex_indices" in faces.dtype.names else "vertex_index"
    tris: list[tuple[int, int, int]] = []
    for f in faces[key]:
        tris += _fan([int(i) for i in f])
    return v, np.asarray(tris, dtype=np.int64).reshape(-1, 3)


# --- albedo -------------------------------------------------------------------------------------------------

# three plane waves in different directions; wavelengths well above the camera's footprint (mm)
_TEX_DIRS = np.array([[0.8, 0.6, 0.0], [-0.3, 0.7, 0.648], [0.5, -0.4, 0.768]])
_TEX_WAVELENGTHS_MM = np.array([23.0, 37.0, 61.0])


@dataclass(frozen=True)
class ProceduralAlbedo:
    """Smooth albedo ``albedo * (1 + texture * s(X))``, ``s`` a mean of three sines of the point, in [-1, 1].

    Parameters
    ----------
    albedo : float
        Mean reflectance 0..1.
    texture : float
        Relative texture amplitude 0..1.
    phase : float
        Phase offset of the sines (radians), so objects differ.
    """

    albedo: float
    texture: float = 0.0
    phase: float = 0.0

    def __call__(self, points: F64) -> F64:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.texture == 0.0:
            return np.full(p.shape[0], self.albedo)
        k = _TEX_DIRS * (2.0 * np.pi / _TEX_WAVELENGTHS_MM)[:, None]
        s = np.zeros(p.shape[0])
        for j, ph in enumerate((1.0, 1.7, 2.3)):
            s += np.sin(p[:, 0] * k[j, 0] + p[:, 1] * k[j, 1] + p[:, 2] * k[j, 2] + ph * self.phase)
        return np.clip(self.albedo * (1.0 + self.texture * s / 3.0), 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class PlaneImageAlbedo:
    """Albedo from a 2-D image laid on a plane (e.g. a printed calibration board).

    A point X maps to image coordinates ``col = (X - origin) . x_axis / mm_per_px``,
    ``row = (X - origin) . y_axis / mm_per_px`` (pixel centres at integers), bilinear interpolation;
    outside the image the albedo is ``outside``.

    Parameters
    ----------
    origin_mm : (3,) float
        World point of image pixel (0, 0) (mm).
    x_axis, y_axis : (3,) float
        Unit vectors of image columns and rows in the world frame.
    image : ndarray, shape (H, W)
        Reflectance 0..1.
    mm_per_px : float
        Image pixel size (mm).
    outside : float
        Albedo beyond the image.
    """

    origin_mm: F64
    x_axis: F64
    y_axis: F64
    image: F64
    mm_per_px: float
    outside: float = 0.0

    def __call__(self, points: F64) -> F64:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3) - np.asarray(self.origin_mm)
        xa = np.asarray(self.x_axis, dtype=np.float64)
        ya = np.asarray(self.y_axis, dtype=np.float64)
        col = (p[:, 0] * xa[0] + p[:, 1] * xa[1] + p[:, 2] * xa[2]) / self.mm_per_px
        row = (p[:, 0] * ya[0] + p[:, 1] * ya[1] + p[:, 2] * ya[2]) / self.mm_per_px
        img = np.asarray(self.image, dtype=np.float64)
        h, w = img.shape
        inside = (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
        c0 = np.clip(np.floor(col), 0, max(w - 2, 0)).astype(np.int64)
        r0 = np.clip(np.floor(row), 0, max(h - 2, 0)).astype(np.int64)
        fc = np.clip(col - c0, 0.0, 1.0)
        fr = np.clip(row - r0, 0.0, 1.0)
        c1 = np.minimum(c0 + 1, w - 1)
        r1 = np.minimum(r0 + 1, h - 1)
        val = ((img[r0, c0] * (1 - fc) + img[r0, c1] * fc) * (1 - fr)
               + (img[r1, c0] * (1 - fc) + img[r1, c1] * fc) * fr)
        return np.where(inside, val, self.outside)


@dataclass(frozen=True)
class PatchAlbedo:
    """Albedo in square patches on world x/y: ``patches[(ix + 3 * iy) % n] * (1 + texture * s(X))``.

    ``ix = floor(x / patch_mm)``, ``iy = floor(y / patch_mm)``; ``s`` as in :class:`ProceduralAlbedo`.

    Parameters
    ----------
    patches : tuple of float
        Albedos 0..1, cycled over the patches.
    patch_mm : float
        Side of a patch (mm).
    texture, phase : float
        As in :class:`ProceduralAlbedo`.
    """

    patches: tuple[float, ...]
    patch_mm: float
    texture: float = 0.0
    phase: float = 0.0

    def __call__(self, points: F64) -> F64:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ix = np.floor(p[:, 0] / self.patch_mm).astype(np.int64)
        iy = np.floor(p[:, 1] / self.patch_mm).astype(np.int64)
        base: F64 = np.asarray(self.patches, dtype=np.float64)[(ix + 3 * iy) % len(self.patches)]
        if self.texture == 0.0:
            return base
        rel = ProceduralAlbedo(1.0, self.texture, self.phase)(p)
        out: F64 = np.clip(base * rel, 0.0, 1.0)
        return out


def configured_albedo(obj: SceneObject, object_id: int) -> AlbedoFn:
    """The albedo function an object's configuration gives (patches when its material has them)."""
    if obj.material.patches:
        return PatchAlbedo(tuple(obj.material.patches), obj.material.patch_mm, obj.texture, phase=1.3 * object_id)
    return ProceduralAlbedo(obj.albedo, obj.texture, phase=1.3 * object_id)


# --- the scene ----------------------------------------------------------------------------------------------


class Scene:
    """Objects of the virtual rig packed for the ray-casting kernels.

    Parameters
    ----------
    objects : iterable of SceneObject
        Plane, sphere, box, cylinder and mesh objects (``virtual_rig.scene``); object id = list index.
    base_dir : Path, optional
        Folder that relative mesh paths are resolved against (the configuration file's folder).
    """

    def __init__(self, objects: Iterable[SceneObject], base_dir: Path | None = None) -> None:
        self.objects: tuple[SceneObject, ...] = tuple(objects)
        prim_type: list[int] = []
        prims: list[F64] = []
        prim_obj: list[int] = []
        tris: list[F64] = []
        tri_obj: list[I32] = []
        self._albedo: list[AlbedoFn] = []
        for i, obj in enumerate(self.objects):
            self._albedo.append(configured_albedo(obj, i))
            row = np.zeros(16)
            if isinstance(obj, MeshObject):
                tv = self._mesh_triangles(obj, i, base_dir)
                tris.append(tv)
                tri_obj.append(np.full(tv.shape[0], i, dtype=np.int32))
                continue
            if isinstance(obj, PlaneObject):
                prim_type.append(_k.PLANE)
                row[0:3] = obj.point_mm
                row[3:6] = _unit(obj.normal, f"scene[{i}].normal")
            elif isinstance(obj, SphereObject):
                prim_type.append(_k.SPHERE)
                row[0:3] = obj.center_mm
                row[3] = obj.radius_mm
            elif isinstance(obj, BoxObject):
                prim_type.append(_k.BOX)
                if min(obj.size_mm) <= 0:
                    raise ConfigError(f"scene[{i}].size_mm = {obj.size_mm}: every size must be > 0 mm")
                row[0:3] = obj.center_mm
                row[3:6] = np.asarray(obj.size_mm) / 2.0
                row[6:15] = rotation_xyz_deg(obj.rotation_deg).ravel()
            elif isinstance(obj, CylinderObject):
                prim_type.append(_k.CYLINDER)
                row[0:3] = obj.center_mm
                row[3:6] = _unit(obj.axis, f"scene[{i}].axis")
                row[6] = obj.radius_mm
                row[7] = obj.height_mm / 2.0
            else:  # pragma: no cover - the schema's union is exhaustive
                raise ConfigError(f"scene[{i}]: unknown object {obj!r}")
            prims.append(row)
            prim_obj.append(i)
        self._prim_type = np.asarray(prim_type, dtype=np.int64)
        self._prims = np.ascontiguousarray(np.asarray(prims, dtype=np.float64).reshape(-1, 16))
        self._prim_obj = np.asarray(prim_obj, dtype=np.int64)
        tri = np.concatenate(tris) if tris else np.zeros((0, 9))
        tobj = np.concatenate(tri_obj) if tri_obj else np.zeros(0, dtype=np.int32)
        self.mirrors: tuple[tuple[int, F64, F64, float], ...] = tuple(
            (i, *self._mirror_plane(obj, i, tris, tri_obj), float(obj.material.mirror))
            for i, obj in enumerate(self.objects) if obj.material.mirror > 0
        )
        """Planar mirrors: (object id, a point on the plane (mm), unit normal, reflectance)."""
        order, self._bvh = _build_bvh(tri)
        self._tri = np.ascontiguousarray(tri[order])
        self._tri_obj = np.ascontiguousarray(tobj[order].astype(np.int64))

    @staticmethod
    def _mirror_plane(obj: SceneObject, i: int, tris: list[F64], tri_obj: list[I32]) -> tuple[F64, F64]:
        if isinstance(obj, PlaneObject):
            return np.asarray(obj.point_mm, dtype=np.float64), _unit(obj.normal, f"scene[{i}].normal")
        if isinstance(obj, MeshObject):
            tv = next(t for t, o in zip(tris, tri_obj, strict=True) if o.size and o[0] == i).reshape(-1, 3, 3)
            p0 = tv[0, 0]
            nrm = np.cross(tv[0, 1] - p0, tv[0, 2] - p0)
            if np.linalg.norm(nrm) > 0:
                nrm = nrm / np.linalg.norm(nrm)
                off = np.abs((tv.reshape(-1, 3) - p0) @ nrm)
                if float(off.max()) <= 1e-6 * max(1.0, float(np.abs(tv).max())):
                    return p0, nrm
        raise ConfigError(
            f"scene[{i}].material.mirror = {obj.material.mirror}: a mirror must be planar; use a plane or a "
            "flat mesh (all vertices in one plane), or set mirror: 0"
        )

    @property
    def n_objects(self) -> int:
        """Number of objects (ids 0..n-1)."""
        return len(self.objects)

    @property
    def n_triangles(self) -> int:
        """Number of mesh triangles over all meshes."""
        return int(self._tri.shape[0])

    @staticmethod
    def _mesh_triangles(obj: MeshObject, i: int, base_dir: Path | None) -> F64:
        if obj.path is not None:
            path = obj.path if obj.path.is_absolute() or base_dir is None else base_dir / obj.path
            v, t = load_mesh(path)
        else:
            v = np.asarray(obj.vertices_mm, dtype=np.float64).reshape(-1, 3)
            t = np.asarray(obj.triangles, dtype=np.int64).reshape(-1, 3)
        if t.size == 0 or t.min() < 0 or t.max() >= v.shape[0]:
            raise ConfigError(
                f"scene[{i}] mesh: triangle indices must lie in 0..{v.shape[0] - 1} and there must be "
                f"at least one triangle; got {t.shape[0]} triangles"
            )
        v = (obj.scale * v) @ rotation_xyz_deg(obj.rotation_deg).T + np.asarray(obj.position_mm)
        return np.ascontiguousarray(v[t].reshape(-1, 9))

    def set_albedo(self, object_id: int, fn: AlbedoFn | None) -> None:
        """Replace the albedo function of one object (``None`` restores its configured texture).

        A :class:`~appliance.sim.rig.VirtualRig` reads albedo when it computes a camera's geometry: swap it
        before the first render, or pass the scene to ``VirtualRig.set_scene`` again.
        """
        if not 0 <= object_id < self.n_objects:
            raise ConfigError(f"scene: object_id = {object_id}: must be in 0..{self.n_objects - 1}")
        if fn is None:
            fn = configured_albedo(self.objects[object_id], object_id)
        self._albedo[object_id] = fn

    def albedo(self, points: F64, object_id: I32) -> F64:
        """Reflectance at hit points.

        Parameters
        ----------
        points : ndarray, shape (N, 3)
            World points (mm).
        object_id : ndarray, shape (N,)
            Object of each point; -1 gives 0.

        Returns
        -------
        ndarray, shape (N,), float64 in [0, 1]
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ids = np.asarray(object_id).ravel()
        out = np.zeros(p.shape[0])
        for i in np.unique(ids[ids >= 0]):
            sel = ids == i
            out[sel] = np.clip(self._albedo[int(i)](p[sel]), 0.0, 1.0)
        return out

    def _cast(self, origins: F64, dirs: F64, t_min: float, t_max: F64 | float, any_hit: bool) -> RayHits:
        d = np.ascontiguousarray(np.asarray(dirs, dtype=np.float64).reshape(-1, 3))
        o = np.ascontiguousarray(np.asarray(origins, dtype=np.float64).reshape(-1, 3))
        if o.shape[0] not in (1, d.shape[0]):
            raise ValueError(f"origins has {o.shape[0]} rows: must be 1 or {d.shape[0]} (one per direction)")
        tm = np.ascontiguousarray(np.asarray(t_max, dtype=np.float64).ravel())
        if tm.shape[0] not in (1, d.shape[0]):
            raise ValueError(f"t_max has {tm.shape[0]} values: must be 1 or {d.shape[0]}")
        n = d.shape[0]
        t = np.empty(n)
        obj = np.empty(n, dtype=np.int32)
        nrm = np.empty((n, 3))
        b = self._bvh
        with _k.KERNEL_LOCK:
            _k.cast_rays(o, d, float(t_min), tm, any_hit, self._prim_type, self._prims, self._prim_obj,
                         self._tri, self._tri_obj, b.bmin, b.bmax, b.left, b.right, b.start, b.count, t, obj,
                         nrm)
        return RayHits(t, obj, nrm)

    def intersect(self, origins: F64, dirs: F64, t_min: float = 0.0, t_max: F64 | float = np.inf) -> RayHits:
        """Nearest hit of each ray ``origin + t * dir`` with ``t_min < t < t_max``.

        Parameters
        ----------
        origins : ndarray, shape (N, 3) or (3,)
            Ray origins (mm, world); one origin is shared by all rays.
        dirs : ndarray, shape (N, 3)
            Directions (unit length for ``t`` in mm).
        t_min : float
            Hits at ``t <= t_min`` are ignored (self-intersection guard).
        t_max : float or ndarray, shape (N,)
            Hits at ``t >= t_max`` are ignored.

        Returns
        -------
        RayHits
        """
        return self._cast(origins, dirs, t_min, t_max, False)

    def occluded(self, origins: F64, dirs: F64, t_max: F64 | float, t_min: float = 0.0) -> BoolArray:
        """True where any object lies on the ray between ``t_min`` and ``t_max`` (shadow rays).

        Parameters as :meth:`intersect`; returns ndarray, shape (N,), bool.
        """
        return self._cast(origins, dirs, t_min, t_max, True).object_id >= 0


# --- bounding volume hierarchy ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Bvh:
    bmin: F64
    bmax: F64
    left: I64
    right: I64
    start: I64
    count: I64


def _build_bvh(tri: F64) -> tuple[I64, _Bvh]:
    """Median-split BVH over triangle centroids; returns the triangle order and the node arrays."""
    m = tri.shape[0]
    order = np.arange(m, dtype=np.int64)
    if m == 0:
        z3 = np.zeros((0, 3))
        zi = np.zeros(0, dtype=np.int64)
        return order, _Bvh(z3, z3, zi, zi, zi, zi)
    v = tri.reshape(m, 3, 3)
    tmin = v.min(axis=1)
    tmax = v.max(axis=1)
    cen = v.mean(axis=1)
    bmin: list[F64] = []
    bmax: list[F64] = []
    left: list[int] = []
    right: list[int] = []
    start: list[int] = []
    count: list[int] = []

    def new_node(lo: int, hi: int) -> int:
        idx = order[lo:hi]
        bmin.append(tmin[idx].min(axis=0))
        bmax.append(tmax[idx].max(axis=0))
        left.append(-1)
        right.append(-1)
        start.append(lo)
        count.append(hi - lo)
        return len(bmin) - 1

    todo = [(new_node(0, m), 0, m)]
    while todo:
        node, lo, hi = todo.pop()
        if hi - lo <= _LEAF_TRIANGLES:
            continue
        idx = order[lo:hi]
        c = cen[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        mid = (hi - lo) // 2
        part = np.argpartition(c[:, axis], mid)
        order[lo:hi] = idx[part]
        count[node] = 0
        left[node] = new_node(lo, lo + mid)
        right[node] = new_node(lo + mid, hi)
        todo += [(left[node], lo, lo + mid), (right[node], lo + mid, hi)]
    arr = np.asarray
    return order, _Bvh(np.ascontiguousarray(arr(bmin)), np.ascontiguousarray(arr(bmax)),
                       arr(left, dtype=np.int64), arr(right, dtype=np.int64), arr(start, dtype=np.int64),
                       arr(count, dtype=np.int64))
