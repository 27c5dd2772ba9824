"""The virtual rig: ground-truth cameras and projector, a scene, and images of any pattern sequence.

For each camera the geometry is computed once: the (distorted) pixel rays are cast into the scene, the
nearest hit ``X`` is projected into the projector with its distortion (exact projector coordinates),
a shadow ray from ``X`` to the projector's centre finds projector shadows and self-occlusion, and the
albedo and incidence give each pixel's gain. A frame then only evaluates the pattern at the projector
coordinates, blurs, adds noise and quantises (:mod:`appliance.sim.render`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from appliance.config.schema import DeviceOptics, VirtualRigConfig
from appliance.errors import ConfigError, PatternError
from appliance.geometry.camera import CameraModel, look_at
from appliance.patterns.sequence import Frame, Sequence
from appliance.sim import _sim_kernels as _k
from appliance.sim.render import FrameRenderer, ImageArray, Layer, blur_margin
from appliance.sim.scene import Scene

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
I32 = npt.NDArray[np.int32]
BoolArray = npt.NDArray[np.bool_]

SHADOW_OFFSET_MM = 1e-4
"""Shadow rays start this far off the surface (along its normal) so they do not hit it again (mm)."""

PROJECTOR_NAME = "projector"

SUBSURFACE_TAPS = 7
"""Shifted copies of the pattern that make up the blur of a translucent material."""
# the taps: normal quantiles at (k + 0.5) / K, scaled to unit variance
_q = np.array([-1.4652337926855228, -0.7916386077433745, -0.36610635680056974, 0.0, 0.36610635680056974,
               0.7916386077433745, 1.4652337926855228])
_SUBSURFACE_NODES = _q / np.sqrt(np.mean(_q**2))

CHUNK_ROWS = 64
"""Camera rows cast into the scene at a time (bounds the temporaries of the geometry to a few MB)."""


def device_model(name: str, optics: DeviceOptics) -> CameraModel:
    """The ground-truth :class:`CameraModel` of a virtual camera or projector.

    Parameters
    ----------
    name : str
        Device name.
    optics : DeviceOptics
        Size, focal length (px), principal point (centre when unset), distortion and pose
        (``position_mm`` looking at ``look_at_mm``, image rows pointing to world +y as far as possible).
    """
    cx, cy = optics.principal_px or ((optics.width - 1) / 2.0, (optics.height - 1) / 2.0)
    K = np.array([[optics.focal_px, 0.0, cx], [0.0, optics.focal_px, cy], [0.0, 0.0, 1.0]])
    dist = np.asarray(optics.dist, dtype=np.float64)
    if dist.size not in (0, 4, 5, 8):
        dist = np.concatenate([dist, np.zeros(5 - dist.size)]) if dist.size < 5 else np.concatenate(
            [dist, np.zeros(8 - dist.size)])
    try:
        R, T = look_at(np.asarray(optics.position_mm), np.asarray(optics.look_at_mm))
    except Exception as exc:  # a degenerate pose
        raise ConfigError(f"virtual_rig {name}: position_mm {optics.position_mm} / look_at_mm "
                          f"{optics.look_at_mm}: {exc}") from exc
    return CameraModel(name, K, dist, optics.width, optics.height, R, T, rms=0.0)


@dataclass(frozen=True)
class GroundTruth:
    """Exact geometry seen by one camera of the virtual rig (per camera pixel).

    Attributes
    ----------
    xyz : ndarray, shape (H, W, 3), float64
        Surface point seen by the pixel centre (mm, world frame); NaN where the ray hits nothing.
    depth : ndarray, shape (H, W), float64
        z of that point in the camera frame (mm); NaN where no hit.
    hit : ndarray, shape (H, W), bool
        The pixel's ray hits an object.
    lit : ndarray, shape (H, W), bool
        Hit, facing the projector, not in a projector shadow, inside the projector image.
    proj_uv : ndarray, shape (H, W, 2), float64
        Exact projector coordinates (u = column, v = row, px) of the point; NaN where no hit or behind
        the projector.
    normal : ndarray, shape (H, W, 3), float64
        Unit surface normal facing the camera (world); NaN where no hit.
    object_id : ndarray, shape (H, W), int32
        Index of the hit object in ``virtual_rig.scene``; -1 where no hit.
    """

    xyz: F64
    depth: F64
    hit: BoolArray
    lit: BoolArray
    proj_uv: F64
    normal: F64
    object_id: I32


_CONFIG_SEED: Literal["config"] = "config"


def _dot(a: F64, b: F64) -> F64:
    """Row-wise dot products of (N, 3) arrays."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


class VirtualRig:
    """Simulated cameras and projector looking at a known scene.

    Parameters
    ----------
    cfg : VirtualRigConfig
        Optics (ground truth), scene and photometry.
    base_dir : Path, optional
        Folder that relative mesh paths resolve against (the configuration file's folder).
    scene : Scene, optional
        A prebuilt scene (e.g. with a swapped albedo) instead of ``cfg.scene``.
    keep_truth : bool
        Keep each camera's ground truth and pixel rays once computed (about 130 MB for 1280 x 1024).
        False (the service) keeps only what rendering needs; :meth:`ground_truth` then computes the
        truth on its first call.

    Attributes
    ----------
    cameras : dict of str to CameraModel
        Ground-truth camera models, in configuration order (the first is the reference camera).
    projector : CameraModel
        Ground-truth projector model.
    scene : Scene
        The scene.

    Notes
    -----
    Per-camera geometry is computed on first use of a camera (or by :meth:`prepare`), about a second
    for 1280 x 1024. Rendering different cameras from different threads is safe.
    """

    def __init__(self, cfg: VirtualRigConfig, base_dir: Path | None = None,
                 scene: Scene | None = None, keep_truth: bool = True) -> None:
        if not cfg.cameras:
            raise ConfigError("virtual_rig.cameras is empty: add at least one camera")
        self.cfg = cfg
        self.imaging = cfg.imaging
        self.keep_truth = keep_truth
        self.cameras: dict[str, CameraModel] = {n: device_model(n, o) for n, o in cfg.cameras.items()}
        self.projector: CameraModel = device_model(PROJECTOR_NAME, cfg.projector)
        self.scene = scene if scene is not None else Scene(cfg.scene, base_dir)
        self.coded_axes: frozenset[str] | None = None
        """The projector axes the renderers keep per-pixel coordinates for (None: both, 5 MB each for a
        1280x1024 camera); a frame of another axis rebuilds the camera's renderer with both."""
        self._truth: dict[str, GroundTruth] = {}
        self._renderers: dict[str, FrameRenderer] = {}
        self._rays: dict[str, F64] = {}
        self._lock = threading.Lock()
        seed = self.imaging.seed
        self._rng = {n: np.random.default_rng(None if seed is None else [seed, i])
                     for i, n in enumerate(self.cameras)}

    def camera_names(self) -> list[str]:
        """Camera names in configuration order."""
        return list(self.cameras)

    def prepare(self, camera: str | None = None) -> None:
        """Compute the per-camera geometry now (all cameras when ``camera`` is None)."""
        for name in [camera] if camera is not None else self.camera_names():
            self._state(name)

    def set_scene(self, scene: Scene) -> None:
        """Replace the scene (e.g. a calibration board at another pose).

        Geometry is recomputed lazily; with ``keep_truth`` the cameras' pixel rays are kept, so a new pose
        costs one ray cast.
        """
        with self._lock:
            self.scene = scene
            self._truth.clear()
            self._renderers.clear()

    # --- geometry ------------------------------------------------------------------------------------------

    def _check_camera(self, camera: str) -> CameraModel:
        try:
            return self.cameras[camera]
        except KeyError:
            raise ConfigError(
                f"virtual rig: camera {camera!r} is not in virtual_rig.cameras {self.camera_names()}"
            ) from None

    def _state(self, camera: str, frame: Frame | None = None) -> FrameRenderer:
        cam = self._check_camera(camera)
        axis = getattr(frame, "axis", None)
        with self._lock:
            have = self._renderers.get(camera)
            if have is None or (axis is not None and axis not in have.axes):
                axes = self.coded_axes if have is None else None
                # the camera's blur reads the scene beyond the image's border, as a lens does: render a margin
                m = blur_margin(self.imaging)
                big = _with_margin(cam, m)
                truth, uv, gain, ambient, layers = self._compute(big, self.keep_truth, key=f"{camera}+{m}",
                                                                 base=camera)  # fmt: skip
                if truth is not None:
                    self._truth[camera] = _crop_truth(truth, m)
                self._renderers[camera] = FrameRenderer(uv, gain, ambient, self.imaging, axes, layers, margin=m)
            return self._renderers[camera]

    def _rays_rows(self, cam: CameraModel, r0: int, r1: int, key: str | None = None) -> F64:
        """Unit world directions (n, 3) of the pixel rays of rows ``r0:r1`` (kept when ``keep_truth``)."""
        full = self._rays.get(cam.name if key is None else key)
        if full is not None:
            return full[r0 * cam.width: r1 * cam.width]
        rays = np.ascontiguousarray(cam.pixel_rays_device(r0, r1).reshape(-1, 3))
        dirs = np.empty_like(rays)
        with _k.KERNEL_LOCK:
            _k.affine_rows(rays, np.ascontiguousarray(cam.R.T), np.zeros(3), dirs)  # device -> world
        return dirs

    def _compute(self, cam: CameraModel, full: bool, key: str | None = None,
                 base: str | None = None) -> tuple[GroundTruth | None, F64, F32, F32, list[Layer]]:
        """Cast the camera's pixels into the scene, :data:`CHUNK_ROWS` rows at a time.

        Returns the ground truth (None unless ``full``), the projector coordinates (H, W, 2) (NaN where
        no hit), the gain and ambient light (H, W) float32 the renderer needs, and one light layer per
        planar mirror (the projector's light reaching the pixel by one mirror bounce).
        """
        h, w = cam.height, cam.width
        n = h * w
        uv = np.full((n, 2), np.nan)
        gain = np.zeros(n, dtype=np.float32)
        ambient = np.zeros(n, dtype=np.float32)
        rkey = cam.name if key is None else key  # the kept rays' key (a camera with a margin has its own)
        keep_rays = full and rkey not in self._rays
        rays = np.empty((n, 3)) if keep_rays else None
        if full:
            xyz_all = np.empty((n, 3))
            nrm_all = np.empty((n, 3))
            depth_all = np.empty(n)
            hit_all = np.empty(n, dtype=bool)
            lit_all = np.empty(n, dtype=bool)
            oid_all = np.empty(n, dtype=np.int32)
        proj = self.projector
        pw, ph = proj.width, proj.height
        mats = [o.material for o in self.scene.objects]
        spec_of = np.asarray([m.specular for m in mats] + [0.0])  # index -1 (no hit) -> 0
        shin_of = np.asarray([m.shininess for m in mats] + [1.0])
        n_bounce = self.imaging.interreflection_samples
        sub_of = np.asarray([m.subsurface_mm for m in mats] + [0.0])
        n_sub = SUBSURFACE_TAPS if sub_of.any() else 0
        layers: list[Layer] = [(np.full((n, 2), np.nan), np.zeros(n, dtype=np.float32))
                               for _ in range(len(self.scene.mirrors) + n_bounce + n_sub)]
        bounce_rng = np.random.default_rng([7, self.camera_names().index(cam.name if base is None else base)])
        for r0 in range(0, h, CHUNK_ROWS):
            r1 = min(h, r0 + CHUNK_ROWS)
            s = slice(r0 * w, r1 * w)
            dirs = self._rays_rows(cam, r0, r1, rkey)
            if rays is not None:
                rays[s] = dirs
            m = dirs.shape[0]
            centre = cam.center
            hits = self.scene.intersect(centre, dirs, t_min=1e-6)
            hit = hits.object_id >= 0
            xyz = centre + np.where(hit, hits.t, np.nan)[:, None] * dirs
            nrm = np.where(hit[:, None], hits.normal, np.nan)
            flip = _dot(nrm, dirs) > 0
            nrm[flip] *= -1.0
            puv = np.empty((m, 2))
            pz = np.empty(m)
            with _k.KERNEL_LOCK:
                _k.project_points(xyz, proj.R, proj.T, proj.K, proj.dist_padded(8), puv, pz)
            to_p = proj.center - xyz
            dist = np.sqrt(_dot(to_p, to_p))
            ldir = to_p / dist[:, None]
            cos_inc = _dot(nrm, ldir)
            candidate = hit & (pz > 0) & (cos_inc > 0)
            illum = np.zeros(m, dtype=bool)
            sel = np.flatnonzero(candidate)
            if sel.size:
                start = xyz[sel] + SHADOW_OFFSET_MM * nrm[sel]
                illum[sel] = ~self.scene.occluded(start, ldir[sel], dist[sel], t_min=1e-6)
            albedo = self.scene.albedo(xyz, hits.object_id)
            window = np.empty(m)
            with _k.KERNEL_LOCK:
                _k.projector_window(np.ascontiguousarray(puv[:, 0]), np.ascontiguousarray(puv[:, 1]), pw, ph,
                                    self.imaging.projector_blur_px, window)
            reflect = albedo * cos_inc
            spec = spec_of[hits.object_id]
            if spec.any():  # Blinn-Phong lobe of the projector (a point source): scales the same pixel's light
                half = ldir - dirs
                half /= np.linalg.norm(half, axis=1)[:, None]
                lobe = np.maximum(np.nan_to_num(_dot(nrm, half)), 0.0) ** shin_of[hits.object_id]
                reflect = reflect + spec * lobe
            gain[s] = np.where(illum, self.imaging.projector_gain_dn * reflect * window, 0.0)
            ambient[s] = self.imaging.ambient_dn * albedo
            for (luv, lgain), mirror in zip(layers, self.scene.mirrors, strict=False):
                self._mirror_light(cam, mirror, xyz, nrm, dirs, hits.object_id, luv[s], lgain[s], ambient[s])
            if n_bounce:
                self._bounce_light(xyz, nrm, albedo, hits.object_id, layers[len(self.scene.mirrors):][:n_bounce], s,
                                   bounce_rng)
            sub = sub_of[hits.object_id]
            if n_sub and sub.any():
                # translucency: the direct light moves into taps of projector coordinates shifted along both axes
                # (a Gaussian of sigma subsurface_mm on the surface, in projector px at the point's distance)
                blurred = np.flatnonzero(sub > 0)
                sigma_px = sub[blurred] * proj.K[0, 0] / dist[blurred]
                for tap, (luv, lgain) in zip(_SUBSURFACE_NODES, layers[-n_sub:], strict=True):
                    luv[s][blurred] = puv[blurred] + (tap * sigma_px)[:, None]
                    lgain[s][blurred] = gain[s][blurred] / n_sub
                gain[s][blurred] = 0.0
            uv[s] = puv
            if full:
                dev = np.empty((m, 3))
                with _k.KERNEL_LOCK:
                    _k.affine_rows(xyz, cam.R, cam.T, dev)
                with np.errstate(invalid="ignore"):
                    inside = ((puv[:, 0] >= -0.5) & (puv[:, 0] < pw - 0.5) & (puv[:, 1] >= -0.5)
                              & (puv[:, 1] < ph - 0.5))
                xyz_all[s] = xyz
                nrm_all[s] = nrm
                depth_all[s] = dev[:, 2]
                hit_all[s] = hit
                lit_all[s] = illum & inside
                oid_all[s] = hits.object_id
        if rays is not None:
            self._rays[rkey] = rays
        truth = None
        if full:
            truth = GroundTruth(
                xyz=xyz_all.reshape(h, w, 3),
                depth=depth_all.reshape(h, w),
                hit=hit_all.reshape(h, w),
                lit=lit_all.reshape(h, w),
                proj_uv=uv.reshape(h, w, 2),
                normal=nrm_all.reshape(h, w, 3),
                object_id=oid_all.reshape(h, w),
            )
            for arr in (truth.xyz, truth.depth, truth.hit, truth.lit, truth.proj_uv, truth.normal,
                        truth.object_id):
                arr.flags.writeable = False
        layers = [(luv.reshape(h, w, 2), lgain.reshape(h, w)) for luv, lgain in layers]
        return truth, uv.reshape(h, w, 2), gain.reshape(h, w), ambient.reshape(h, w), layers

    def _mirror_light(self, cam: CameraModel, mirror: tuple[int, F64, F64, float], xyz: F64, nrm: F64,
                      dirs: F64, oid: I32, luv: F64, lgain: F32, ambient: F32) -> None:
        """One planar mirror's one-bounce light on a chunk of pixels, written into ``luv``/``lgain``.

        Where the pixel sees another object: the projector mirrored in the mirror's plane lights it (the
        light of the projector pixel that sees the point's mirror image). Where it sees the mirror: the
        camera sees the mirrored scene, lit directly by the projector.
        """
        k, p0, nm, refl = mirror
        proj = self.projector
        pc = proj.center
        s_p = float(np.dot(pc - p0, nm))
        gain_dn = self.imaging.projector_gain_dn
        side = np.sign(s_p) * nm  # the mirror's face towards the projector
        hit = oid >= 0
        with np.errstate(invalid="ignore"):
            s_x = (xyz - p0) @ nm
        # (a) light reaching another object by the mirror: its path is X -> M (on the mirror) -> projector
        sel = np.flatnonzero(hit & (oid != k) & (s_x * s_p > 0))
        if sel.size and s_p != 0.0:
            x = xyz[sel]
            virt = pc - 2.0 * s_p * nm
            d = virt - x
            dist = np.sqrt(_dot(d, d))
            du = d / dist[:, None]
            cos_x = _dot(nrm[sel], du)
            front = cos_x > 0
            sel, x, du, dist, cos_x = sel[front], x[front], du[front], dist[front], cos_x[front]
            first = self.scene.intersect(x + SHADOW_OFFSET_MM * nrm[sel], du, t_min=1e-6, t_max=dist)
            on = first.object_id == k
            sel, x, du, cos_x, tm = sel[on], x[on], du[on], cos_x[on], first.t[on]
            m = x + tm[:, None] * du
            to_p = pc - m
            dp = np.sqrt(_dot(to_p, to_p))
            free = ~self.scene.occluded(m + SHADOW_OFFSET_MM * side, to_p / dp[:, None], dp, t_min=1e-6)
            sel, x, cos_x = sel[free], x[free], cos_x[free]
            image = x - 2.0 * ((x - p0) @ nm)[:, None] * nm
            self._light_from(image, sel, refl * self.scene.albedo(x, oid[sel]) * cos_x * gain_dn, luv, lgain)
        # (b) the camera sees the mirror: the reflected ray's first hit, lit directly
        s_c = float(np.dot(cam.center - p0, nm))
        sel = np.flatnonzero(oid == k)
        if sel.size and s_c != 0.0:
            r = dirs[sel] - 2.0 * (dirs[sel] @ nm)[:, None] * nm
            start = xyz[sel] + SHADOW_OFFSET_MM * np.sign(s_c) * nm
            seen = self.scene.intersect(start, r, t_min=1e-6)
            ok = (seen.object_id >= 0) & (seen.object_id != k)
            sel, r, y, ny, yid = sel[ok], r[ok], start[ok] + seen.t[ok][:, None] * r[ok], seen.normal[ok], \
                seen.object_id[ok]
            ny = np.where((_dot(ny, r) > 0)[:, None], -ny, ny)
            to_p = pc - y
            dp = np.sqrt(_dot(to_p, to_p))
            ly = to_p / dp[:, None]
            cos_y = _dot(ny, ly)
            lit = cos_y > 0
            sel, y, ny, yid, ly, dp, cos_y = sel[lit], y[lit], ny[lit], yid[lit], ly[lit], dp[lit], cos_y[lit]
            lit = ~self.scene.occluded(y + SHADOW_OFFSET_MM * ny, ly, dp, t_min=1e-6)
            sel, y, yid, cos_y = sel[lit], y[lit], yid[lit], cos_y[lit]
            alb = self.scene.albedo(y, yid)
            ambient[sel] += np.float32(self.imaging.ambient_dn * refl) * alb.astype(np.float32)
            self._light_from(y, sel, refl * alb * cos_y * gain_dn, luv, lgain)

    def _bounce_light(self, xyz: F64, nrm: F64, albedo: F64, oid: I32, layers: list[Layer], s: slice,
                      rng: np.random.Generator) -> None:
        """One-bounce diffuse interreflection on a chunk of pixels: one layer per hemisphere sample.

        Sample k of a pixel at X casts a cosine-weighted direction from X; where it hits a point Y lit by the
        projector, layer k carries Y's projector coordinates and the light ``gain * albedo_X * albedo_Y *
        cos_Y / K`` (Lambertian; the cosine-weighted estimate of the irradiance at X from Y's radiance).
        """
        k_total = len(layers)
        sel = np.flatnonzero(oid >= 0)
        if sel.size == 0 or k_total == 0:
            return
        pc = self.projector.center
        n = nrm[sel]
        # an orthonormal frame around each normal
        a = np.where((np.abs(n[:, 0]) < 0.9)[:, None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
        t1 = np.cross(n, a)
        t1 /= np.linalg.norm(t1, axis=1)[:, None]
        t2 = np.cross(n, t1)
        for k, (luv, lgain) in enumerate(layers):
            # stratified in the azimuth: sample k covers the k-th sector of every pixel's hemisphere
            u1 = rng.random(sel.size)
            phi = 2.0 * np.pi * (k + rng.random(sel.size)) / k_total
            r = np.sqrt(u1)
            d = (r * np.cos(phi))[:, None] * t1 + (r * np.sin(phi))[:, None] * t2 + np.sqrt(1.0 - u1)[:, None] * n
            start = xyz[sel] + SHADOW_OFFSET_MM * n
            hit = self.scene.intersect(start, d, t_min=1e-6)
            ok = hit.object_id >= 0
            idx, y = sel[ok], start[ok] + hit.t[ok][:, None] * d[ok]
            ny = hit.normal[ok]
            ny = np.where((_dot(ny, d[ok]) > 0)[:, None], -ny, ny)
            to_p = pc - y
            dp = np.sqrt(_dot(to_p, to_p))
            ly = to_p / dp[:, None]
            cos_y = _dot(ny, ly)
            front = cos_y > 0
            idx, y, ny, ly, dp, cos_y, yid = (idx[front], y[front], ny[front], ly[front], dp[front], cos_y[front],
                                              hit.object_id[ok][front])
            free = ~self.scene.occluded(y + SHADOW_OFFSET_MM * ny, ly, dp, t_min=1e-6)
            idx, y, cos_y, yid = idx[free], y[free], cos_y[free], yid[free]
            g = self.imaging.projector_gain_dn * albedo[idx] * self.scene.albedo(y, yid) * cos_y / k_total
            self._light_from(y, idx, g, luv[s], lgain[s])

    def _light_from(self, points: F64, sel: npt.NDArray[np.intp], gain: F64, luv: F64, lgain: F32) -> None:
        """Projector coordinates of world ``points`` and their light ``gain`` (DN) into rows ``sel``."""
        if sel.size == 0:
            return
        proj = self.projector
        puv = np.empty((sel.size, 2))
        pz = np.empty(sel.size)
        window = np.empty(sel.size)
        with _k.KERNEL_LOCK:
            _k.project_points(np.ascontiguousarray(points), proj.R, proj.T, proj.K, proj.dist_padded(8), puv, pz)
            _k.projector_window(np.ascontiguousarray(puv[:, 0]), np.ascontiguousarray(puv[:, 1]), proj.width,
                                proj.height, self.imaging.projector_blur_px, window)
        front = pz > 0
        luv[sel] = puv
        lgain[sel] = np.where(front, gain * window, 0.0)

    def ground_truth(self, camera: str) -> GroundTruth:
        """Exact per-pixel geometry of ``camera`` (read-only arrays); see :class:`GroundTruth`.

        Without ``keep_truth`` the first call computes it (about a second) and keeps it from then on.
        """
        cam = self._check_camera(camera)
        with self._lock:
            if camera not in self._truth:
                truth, _, _, _, _ = self._compute(cam, True)
                assert truth is not None
                self._truth[camera] = truth
            return self._truth[camera]

    # --- images --------------------------------------------------------------------------------------------

    @property
    def image_dtype(self) -> type[np.uint8] | type[np.uint16]:
        """uint8 for 8-bit cameras, uint16 for 12 and 16 bits."""
        return np.uint8 if self.imaging.bit_depth == 8 else np.uint16

    def render_frame(self, frame: Frame, camera: str, out: ImageArray | None = None,
                     rng: np.random.Generator | None = None, exposure_us: float | None = None,
                     intensity: float | None = None) -> ImageArray:
        """Camera image of one projected frame.

        Parameters
        ----------
        frame : Frame
            Gray, phase, white or black frame (projector coordinates of this rig's projector).
        camera : str
            Camera name.
        out : ndarray, shape (H, W), optional
            C-contiguous destination of the camera's dtype (see :attr:`image_dtype`).
        rng : numpy.random.Generator, optional
            Noise source; default the camera's own generator seeded from ``imaging.seed``.
        exposure_us : float, optional
            Camera exposure (µs; default ``imaging.exposure_us``): the light scales with it relative to
            ``imaging.reference_exposure_us`` before noise and clipping.
        intensity : float, optional
            Projector intensity 0..1 (default ``imaging.projector_intensity``): scales the projector's light.

        Returns
        -------
        ndarray, shape (H, W), uint8 (8-bit) or uint16 (12/16-bit)
        """
        renderer = self._state(camera, frame)
        if out is None:
            out = np.empty((renderer.height, renderer.width), dtype=self.image_dtype)
        exp, inten = self.light_scale(exposure_us, intensity)
        return renderer.render(frame, out, rng if rng is not None else self._rng[camera], exp, inten)

    def light_scale(self, exposure_us: float | None = None, intensity: float | None = None) -> tuple[float, float]:
        """Relative exposure and projector intensity of a render (the configured ones where None)."""
        im = self.imaging
        exp = im.exposure_us if exposure_us is None else float(exposure_us)
        inten = im.projector_intensity if intensity is None else float(intensity)
        if not (exp > 0 and 0 < inten <= 1):
            raise ConfigError(f"virtual rig: exposure_us = {exp}, intensity = {inten}: exposure must be > 0 "
                              "and intensity in (0, 1]")
        return exp / im.reference_exposure_us, inten

    def render_clean(self, frame: Frame, camera: str, blur: bool = True) -> npt.NDArray[np.float32]:
        """Noise-free camera image of ``frame`` before quantisation (the mean of :meth:`render_frame`).

        Parameters
        ----------
        frame : Frame
            The projected frame.
        camera : str
            Camera name.
        blur : bool
            Apply the camera defocus.

        Returns
        -------
        ndarray, shape (H, W), float32
            DN on the 8-bit scale (not clipped, not scaled to the bit depth).
        """
        return self._state(camera, frame).clean(frame, blur=blur)

    def render(self, sequence: Sequence, camera: str, out: ImageArray | None = None,
               seed: int | Literal["config"] | None = _CONFIG_SEED, exposure_us: float | None = None,
               intensity: float | None = None) -> ImageArray:
        """Camera images of every frame of ``sequence``.

        Parameters
        ----------
        sequence : Sequence
            Frames to project; its size must be the projector's.
        camera : str
            Camera name.
        out : ndarray, shape (F, H, W), optional
            C-contiguous destination of the camera's dtype.
        seed : int, None or 'config'
            Noise seed of this render ('config': ``imaging.seed`` mixed with the camera index, so a
            repeated render is identical; None: fresh noise).
        exposure_us, intensity : float, optional
            As in :meth:`render_frame`.

        Returns
        -------
        ndarray, shape (F, H, W), uint8 or uint16
        """
        cam = self._check_camera(camera)
        if (sequence.width, sequence.height) != (self.projector.width, self.projector.height):
            raise PatternError(
                f"virtual rig: sequence is {sequence.width}x{sequence.height} but the projector is "
                f"{self.projector.width}x{self.projector.height}; generate the sequence for the projector"
            )
        shape = (len(sequence), cam.height, cam.width)
        if out is None:
            out = np.empty(shape, dtype=self.image_dtype)
        elif out.shape != shape or out.dtype != self.image_dtype or not out.flags.c_contiguous:
            raise ValueError(f"out: shape {out.shape} dtype {out.dtype}: must be C-contiguous {shape} "
                             f"{np.dtype(self.image_dtype).name}")
        if isinstance(seed, str):
            base = self.imaging.seed
            idx = self.camera_names().index(camera)
            rng = np.random.default_rng(None if base is None else [base, idx])
        else:
            rng = np.random.default_rng(seed)
        for i, frame in enumerate(sequence):
            self.render_frame(frame, camera, out=out[i], rng=rng, exposure_us=exposure_us, intensity=intensity)
        return out


def _with_margin(cam: CameraModel, margin: int) -> CameraModel:
    """``cam`` seeing ``margin`` more pixels on each side: the same rays for the image's pixels (the principal
    point moves with the origin)."""
    if margin <= 0:
        return cam
    K = np.array(cam.K, dtype=np.float64)
    K[0, 2] += margin
    K[1, 2] += margin
    return CameraModel(cam.name, K, cam.dist, cam.width + 2 * margin, cam.height + 2 * margin, cam.R, cam.T, cam.rms)


def _crop_truth(truth: GroundTruth, margin: int) -> GroundTruth:
    """The image's part of a ground truth computed with a margin (read-only arrays)."""
    if margin <= 0:
        return truth
    sl = (slice(margin, -margin), slice(margin, -margin))
    parts = {name: np.ascontiguousarray(getattr(truth, name)[sl])
             for name in ("xyz", "depth", "hit", "lit", "proj_uv", "normal", "object_id")}  # fmt: skip
    for arr in parts.values():
        arr.flags.writeable = False
    return GroundTruth(**parts)

