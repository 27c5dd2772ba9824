"""The virtual rig's hard scenes (issue 25), small renders with exact truth, and their error statistics.

Each scene is a YAML config text (camera 480x384, the default projector and sequence: periods [16, 8]); a
test renders it (one pass per exposure) into a manifest and reconstructs it with ``scan3d decode``, the service's
reconstruction, then compares each point with the truth of its pixel.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence as Sequence_
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance import cli
from appliance.config import AppConfig, parse_config
from appliance.geometry.calibration_file import write_calibration
from appliance.output.ply import read_ply_vertices
from appliance.patterns.from_config import build_sequence
from appliance.patterns.manifest import write_manifest
from appliance.patterns.sequence import Sequence
from appliance.reconstruct.types import PointCloud
from appliance.scan import virtual_calibration
from appliance.sim.rig import VirtualRig

CAMERA = "cam0: {width: 480, height: 384, focal_px: 900, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}"

#: albedo patches of the dark-and-shiny plane: black rubber (0.03) to white paper (0.95)
PATCHES = "[0.03, 0.95, 0.05, 0.5, 0.08, 0.2, 0.03, 0.7, 0.12, 0.35]"

_BASE = """
sequence:
  kind: gray_phase
  axes: %(axes)s
  periods_px: %(periods)s
virtual_rig:
  cameras:
    %(camera)s
  scene:
%(scene)s
  imaging: {ambient_dn: %(ambient)s, projector_gain_dn: %(gain)s, exposure_us: %(exposure)s, seed: 3,
            interreflection_samples: %(bounce)s}
"""

#: the projector's white level on albedo 1 (DN, the default imaging.projector_gain_dn)
WHITE_DN = 180.0

SCENES: dict[str, str] = {
    # a plane of albedo patches and a glossy metal sphere (diffuse 0.12, lobe peaking at 8x the white level)
    "dark_shiny": f"""
    - {{type: plane, point_mm: [0, 0, 630], normal: [0, 0.1, -1], material: {{patches: {PATCHES}, patch_mm: 30}}}}
    - {{type: sphere, center_mm: [-20, 10, 560], radius_mm: 40, albedo: 0.12,
        material: {{specular: 8, shininess: 60}}}}""",
    # a concave 90-degree corner; the left face is glossy metal (mirror reflectance 0.6), the right matte
    "mirror_groove": """
    - {type: mesh, albedo: 0.15, material: {mirror: 0.6},
       vertices_mm: [[-70, -90, 590], [0, -90, 660], [0, 90, 660], [-70, 90, 590]], triangles: [[0, 1, 2], [0, 2, 3]]}
    - {type: mesh, albedo: 0.9,
       vertices_mm: [[0, -90, 660], [70, -90, 590], [70, 90, 590], [0, 90, 660]], triangles: [[0, 1, 2], [0, 2, 3]]}
    - {type: plane, point_mm: [0, 0, 700], normal: [0, 0, -1], albedo: 0.5}""",
    # the same corner, both faces matte
    "diffuse_groove": """
    - {type: mesh, albedo: 0.9,
       vertices_mm: [[-70, -90, 590], [0, -90, 660], [0, 90, 660], [-70, 90, 590]], triangles: [[0, 1, 2], [0, 2, 3]]}
    - {type: mesh, albedo: 0.9,
       vertices_mm: [[0, -90, 660], [70, -90, 590], [70, 90, 590], [0, 90, 660]], triangles: [[0, 1, 2], [0, 2, 3]]}
    - {type: plane, point_mm: [0, 0, 700], normal: [0, 0, -1], albedo: 0.5}""",
    # the default scene's objects
    "default": """
    - {type: plane, point_mm: [0, 0, 630], normal: [0, 0.1, -1], texture: 0.3}
    - {type: sphere, center_mm: [-20, 10, 560], radius_mm: 40, texture: 0.2}
    - {type: box, center_mm: [70, -40, 600], size_mm: [60, 50, 40], rotation_deg: [10, 25, 5]}""",
}



def scene_text(scene: str, exposure_us: float = 10_000.0, ambient_dn: float = 10.0, gain_dn: float = WHITE_DN,
               bounce: int = 0, axes: str = "x", periods: str = "[16, 8]") -> str:
    """The config text of one hard scene at an exposure (µs; the reference is 10 000), ambient light, white
    level (DN at albedo 1), diffuse interreflection samples (0: off), coded axes ('x', or 'xy': both,
    ray-ray triangulation with its per-pixel epipolar check) and fringe periods (the default sequence's; "[16]":
    period 16 alone, the default before periods [16, 8])."""
    return _BASE % {"camera": CAMERA, "scene": SCENES[scene], "ambient": ambient_dn, "exposure": exposure_us,
                    "gain": gain_dn, "bounce": bounce, "axes": axes, "periods": periods}


def scene_config(scene: str, exposure_us: float = 10_000.0, ambient_dn: float = 10.0,
                 gain_dn: float = WHITE_DN, bounce: int = 0, axes: str = "x", periods: str = "[16, 8]") -> AppConfig:
    """The parsed config of :func:`scene_text`."""
    return parse_config(scene_text(scene, exposure_us, ambient_dn, gain_dn, bounce, axes, periods), f"{scene}.yaml")


@dataclass(frozen=True)
class SceneStats:
    """Error statistics of one scan against the truth (shares 0..1, mm)."""

    points: int
    completeness: float
    rms_mm: float
    over_1mm: float
    over_5sigma: float
    z_rms: float
    dark_completeness: float
    over_5mm: float = 0.0

    def line(self) -> str:
        return (f"{self.points} points, complete {100 * self.completeness:.1f} % (dark patches "
                f"{100 * self.dark_completeness:.1f} %), RMS {self.rms_mm:.3f} mm, > 1 mm "
                f"{100 * self.over_1mm:.3f} % (> 5 mm {100 * self.over_5mm:.3f} %), > 5 sigma "
                f"{100 * self.over_5sigma:.3f} %, |err|/sigma RMS {self.z_rms:.2f}")


def stats(cloud: PointCloud, rig: VirtualRig, camera: str = "cam0") -> SceneStats:
    """Completeness of the lit pixels (and of those with albedo < 0.1), errors and their sigma calibration."""
    gt = rig.ground_truth(camera)
    r, c = cloud.row, cloud.col
    truth = gt.xyz[r, c]
    ok = np.isfinite(truth).all(axis=1)
    err = np.full(len(cloud), np.inf)
    err[ok] = np.linalg.norm(cloud.xyz[ok].astype(np.float64) - truth[ok], axis=1)
    sigma = cloud.sigma_mm.astype(np.float64) if cloud.sigma_mm is not None else np.full(len(cloud), np.nan)
    z = err / sigma
    has = np.zeros(gt.lit.shape, bool)
    has[r, c] = True
    alb = rig.scene.albedo(np.nan_to_num(gt.xyz.reshape(-1, 3)), gt.object_id.ravel()).reshape(gt.lit.shape)
    dark = gt.lit & (alb < 0.1)
    fin = np.isfinite(err)
    zf = z[np.isfinite(z)]
    return SceneStats(
        points=len(cloud),
        completeness=float(has[gt.lit].mean()),
        rms_mm=float(np.sqrt(np.mean(err[fin] ** 2))) if fin.any() else float("inf"),
        over_1mm=float(np.mean(err > 1.0)) if len(err) else 0.0,
        over_5sigma=float(np.mean(~(z <= 5.0))) if len(z) else 0.0,
        z_rms=float(np.sqrt(np.mean(zf**2))) if zf.size else float("nan"),
        dark_completeness=float(has[dark].mean()) if dark.any() else float("nan"),
        over_5mm=float(np.mean(err > 5.0)) if len(err) else 0.0,
    )


def capture(cfg: AppConfig, folder: Path, name: str, exposures_us: Sequence_[float] = (),
            intensities: Sequence_[float] = ()) -> VirtualRig:
    """Render the configured scene (one pass per exposure, at its projector intensity, full where
    ``intensities`` is empty; none: the configured exposure) into a manifest.

    Writes ``folder/name.yaml`` (with ``exposure_us`` and ``intensity`` per frame when several passes), its
    stack and the rig's exact calibration ``folder/cal.yaml``; returns the rig (its ground truth).
    """
    rig = VirtualRig(cfg.virtual_rig)
    seq = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    passes = list(exposures_us) or [None]
    levels = list(intensities) or [1.0] * len(passes)
    stacks = [rig.render(seq, "cam0", seed=17 + k, exposure_us=e, intensity=i)
              for k, (e, i) in enumerate(zip(passes, levels, strict=True))]
    np.save(folder / f"{name}.npy", np.concatenate(stacks))
    frames = Sequence(seq.width, seq.height, tuple(seq.frames) * len(passes))
    exposures = ([(float(e), float(i)) for e, i in zip(exposures_us, levels, strict=True) for _ in seq.frames]
                 if len(passes) > 1 else None)
    write_manifest(folder / f"{name}.yaml", frames, ["cam0"], stacks={"cam0": f"{name}.npy"}, exposures=exposures)
    write_calibration(folder / "cal.yaml", virtual_calibration(rig))
    return rig


def decode(folder: Path, name: str, rig: VirtualRig, config: Path | None = None,
           tag: str = "") -> tuple[SceneStats, str]:
    """``scan3d decode`` of a captured manifest (the service's reconstruction); statistics and its output.

    The sidecar (``--report``) is ``folder/name{tag}.json``; ``config``: ``--config`` (reconstruction settings).
    """
    out = io.StringIO()
    extra = ["--config", str(config)] if config is not None else []
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["decode", str(folder / f"{name}.yaml"), "--calibration", str(folder / "cal.yaml"),
                       "--out", str(folder / f"{name}{tag}.ply"), "--report", str(folder / f"{name}{tag}.json"),
                       *extra])  # fmt: skip
    assert rc == 0, out.getvalue()
    v = read_ply_vertices(folder / f"{name}{tag}.ply")
    n = len(v)
    cloud = PointCloud(
        np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32), v["row"].astype(np.int32),
        v["col"].astype(np.int32), np.zeros(n, np.uint8), np.zeros(n, np.uint8), np.zeros(n, np.float32),
        sigma_mm=np.asarray(v["sigma_mm"], np.float32),
    )  # fmt: skip
    return stats(cloud, rig), out.getvalue()


def measure(cfg: AppConfig, folder: Path, name: str, exposures_us: Sequence_[float] = ()) -> SceneStats:
    """Capture and decode one scene; its statistics."""
    rig = capture(cfg, folder, name, exposures_us)
    return decode(folder, name, rig)[0]
