"""The configuration schema of the appliance (one YAML file; see ``config/appliance.yaml``).

Every model rejects unknown keys; every number has bounds and its unit in its name.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from appliance.config.backends import (
    CameraConfig,
    ProjectorConfig,
    SimCameraConfig,
    SimProjectorConfig,
    SimTriggerConfig,
    TriggerConfig,
)
from appliance.config.strict import StrictModel

Vec3 = tuple[float, float, float]


class _Strict(StrictModel):
    """Unknown keys, NaN and infinity refused; integers and booleans strictly typed (see config/strict.py)."""


# --- the pattern sequence -----------------------------------------------------------------------------


class SequenceConfig(_Strict):
    """Which patterns a scan projects."""

    kind: Literal["gray_phase", "gray"] = Field(
        "gray_phase", description="Gray + phase shift (sub-pixel) or Gray code only (stripe centres)."
    )
    axes: Literal["x", "y", "xy"] = Field("x", description="Coded projector axes; 'xy' allows ray-ray triangulation.")
    periods_px: tuple[int, ...] = Field(
        (16, 8),
        min_length=1,
        max_length=4,
        description="Fringe periods (projector px, 4..8192), coarsest first; Gray stripe = half the coarsest.",
    )
    steps: int = Field(4, ge=3, le=16, description="Phase steps per period.")
    stripe_px: int = Field(1, ge=1, le=256, description="Gray stripe width for kind 'gray' (projector px).")
    inverses: bool = Field(True, description="Project the inverse of every Gray bit.")
    code: Literal["gray", "xor"] = Field(
        "gray",
        description="Gray bits as plain Gray code, or as XOR codes: every bit above xor_base_bit projected XOR "
        "that base bit, so every pattern stays fine-striped and interreflected light splits evenly between a "
        "pattern and its inverse (the same frame count).",
    )
    xor_base_bit: int = Field(
        0, ge=0, le=8, description="For code 'xor': the Gray bit the coarser bits are XORed with (0 = the finest)."
    )
    exposures_us: tuple[int, ...] = Field(
        (),
        max_length=8,
        description="Camera exposure of each capture pass (µs), e.g. [2500, 10000, 40000] for HDR (scan3d tune "
        "chooses them); empty: one pass at each camera's own exposure.",
    )

    intensities: tuple[float, ...] = Field(
        (),
        max_length=8,
        description="Projector intensity of each capture pass (0-1 of full scale), one per exposures_us entry, "
        "e.g. exposures_us: [10000, 10000] with intensities: [0.25, 1.0] takes the bright parts' pass by dimming "
        "the projector instead of shortening the exposure (lightcrafter4500: its LED currents; sim). Empty: every "
        "pass at full intensity.",
    )

    @field_validator("exposures_us")
    @classmethod
    def _exposures_positive(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        for e in v:
            if not 0 < e <= 10_000_000:
                raise ValueError(f"exposures_us: {e} must be > 0 and at most 10000000 (µs)")
        return v

    @field_validator("intensities")
    @classmethod
    def _intensities_in_range(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        for i in v:
            if not (0.0 < i <= 1.0):  # NaN fails too
                raise ValueError(f"intensities: {i} must be > 0 and at most 1 (of the projector's full scale)")
        return v

    @model_validator(mode="after")
    def _passes_distinct(self) -> SequenceConfig:
        ex, it = list(self.exposures_us), list(self.intensities)
        if it and len(it) != len(ex):
            raise ValueError(f"intensities: {len(it)} value(s) for {len(ex)} exposures_us {ex}: give one intensity "
                             "per pass (per exposures_us entry), or remove intensities")  # fmt: skip
        if not it and len(set(ex)) != len(ex):
            raise ValueError(f"exposures_us: {ex} lists an exposure twice; list each once (or give each pass its own "
                             "projector intensity in intensities)")  # fmt: skip
        pairs = list(zip(ex, it, strict=True)) if it else []
        if len(set(pairs)) != len(pairs):
            raise ValueError(f"exposures_us {ex} with intensities {it}: two passes have the same exposure and "
                             "intensity; list each pass once")  # fmt: skip
        return self

    @model_validator(mode="after")
    def _periods_even(self) -> SequenceConfig:
        for p in self.periods_px:
            if p < 4 or p % 2 or p > 8192:
                raise ValueError(f"periods_px: {p} must be an even number from 4 to 8192 (projector px)")
        if list(self.periods_px) != sorted(self.periods_px, reverse=True):
            raise ValueError(f"periods_px: {list(self.periods_px)} must be listed coarsest first")
        return self


# --- reconstruction -----------------------------------------------------------------------------------


class ReconstructionConfig(_Strict):
    """Decoding thresholds, triangulation and filters."""

    mode: Literal["projector", "stereo", "both"] = Field(
        "projector",
        description="Camera-projector per camera, camera-camera (needs two cameras), or both: camera-projector "
        "for every camera, the first camera's points fused with camera-camera by their expected errors.",
    )
    min_contrast_dn: float = Field(
        6.0, ge=0, le=65535, description="Floor of the white-black contrast for a lit pixel (DN, 8-bit scale)."
    )
    relative_contrast: float = Field(
        0.15,
        ge=0,
        le=1,
        description="A Gray pair must differ by this share of the pixel's white-black range.",
    )
    blend_ratio: float = Field(
        0.4,
        ge=0,
        lt=1,
        description="Two copies of the pattern (a mirror-like face): a pixel is dropped where two of its fine Gray "
        "bits (period up to 512 projector px) have less than this share of its white-black contrast. 0: no check.",
    )
    separate_copies: bool = Field(
        True,
        description="Where the check for two copies of the pattern finds them (a mirror lights a surface a second "
        "time), take the direct copy apart from the mirrored one and keep its point: needs two or more phase periods "
        "per coded axis, each dividing the coarsest (the default [16, 8]); a pixel whose copies do not come apart "
        "stays dropped. false: drop every such pixel.",
    )
    hidden_check: Literal["auto", "always", "off"] = Field(
        "auto",
        description="Camera-projector: drop a point when another lies nearer the projector on its projector ray (by "
        "more than a surface 10 degrees from the ray spreads over 2 projector px, plus 5 of its sigmas): the projector "
        "cannot light it, its light came by a reflection (a ghost of a mirror-like face). auto: when a scan shows "
        "reflections (>= 0.1 % of the decoded pixels lit by two copies of the pattern, or off their epipolar lines); "
        "always: every scan (about 25 ns a point); off: never.",
    )
    indirect_sigma: bool = Field(
        True,
        description="Camera-projector with a phase code: widen a point's sigma by the shift light that came another "
        "way may give its code (diffuse interreflection near a concave corner, subsurface scattering), judged by how "
        "much of its white - black range lacks the pattern's contrast against the scan's median; max_sigma_mm then "
        "drops such points too. Off: sigma is the camera noise's alone.",
    )
    edge_blur_px: float = Field(
        0.5, ge=0, le=5,
        description="Camera-projector with a phase code: the cameras' lens blur (Gaussian sigma, camera px) by which "
        "a bright neighbour pulls a dark pixel's code at an albedo edge (print on a part, a label, dark rubber beside "
        "white); each code is corrected by blur^2 grad(white) / white along its code's slope, and its sigma gains "
        "(0.5 + that pull in camera px) times the shift. With several exposures and up to 0.75 px a pixel may then "
        "come from a pass where a neighbour clipped; blurrier optics (and 0, which turns the correction off) take a "
        "pixel only from a pass where nothing within 3 x this (at least its 8 neighbours) clipped. scan3d tune "
        "measures it (fringes at two periods) and --apply writes it. Too large a value is worse than too small.",
    )
    min_depth_mm: float = Field(100.0, ge=0, description="Points nearer than this are dropped (mm).")
    max_depth_mm: float = Field(3000.0, gt=0, description="Points farther than this are dropped (mm).")
    min_neighbours: int = Field(
        8,
        ge=0,
        le=8,
        description="Keep a point when this many of its 8 neighbours are valid and near (8 drops mixed edge pixels); "
        "camera-camera: when no more than 8 minus this many of its valid neighbours disagree (beyond the pair's "
        "sigmas) and 2 agree, missing neighbours counting neither way (holes do not grow).",
    )
    max_neighbour_jump_mm: float | None = Field(
        None,
        gt=0,
        description="Fixed jump limit: a neighbour counts when nearer than this plus two pixel footprints at mid "
        "range (mm); unset: the limit of each point follows from its expected error and footprint (below).",
    )
    neighbour_jump_sigmas: float = Field(
        6.0, ge=0, le=100, description="Jump limit per point: this many of its expected errors (sigma_mm) ..."
    )
    neighbour_jump_footprints: float = Field(
        6.0, ge=0, le=100, description="... plus this many pixel footprints (depth / focal length, mm)."
    )
    max_sigma_mm: float | None = Field(
        None, gt=0, description="Drop points whose expected 1-sigma error exceeds this (mm); unset: keep all."
    )
    camera_read_noise_dn: float = Field(
        2.0, ge=0, le=10000, description="Camera read noise, 1 sigma, for the per-point error (DN of the frames)."
    )
    camera_electrons_per_dn: float = Field(
        25.0, gt=0, description="Camera conversion gain for the shot noise of the per-point error (e- per DN)."
    )
    stereo_max_epipolar_px: float | None = Field(
        None,
        gt=0,
        description="Stereo with rows coded: reject matches this far from the epipolar line (rectified px); "
        "unset: from the calibration's stated RMS and this scan's own residuals.",
    )
    stereo_drift: Literal["refuse", "correct"] = Field(
        "refuse",
        description="Stereo with rows coded: an epipolar offset beyond max(5 px, 10x the calibration's stated RMS) "
        "means the calibration does not fit the rig: 'refuse' writes no camera-camera points for the pair (the scan "
        "fails in mode stereo) and says so; 'correct' fits and removes it like a small drift. Smaller offsets are "
        "always measured and corrected.",
    )
    normals: bool = Field(False, description="Estimate normals from the organised cloud.")
    normal_radius_px: int = Field(
        3, ge=1, le=10, description="Normals: half size of the pixel window a plane is fitted to (px)."
    )

    @model_validator(mode="after")
    def _range(self) -> ReconstructionConfig:
        if self.max_depth_mm <= self.min_depth_mm:
            raise ValueError(f"max_depth_mm {self.max_depth_mm} must be > min_depth_mm {self.min_depth_mm}")
        return self


# --- the virtual rig ----------------------------------------------------------------------------------


MAX_VIRTUAL_PIXELS = 20_000_000
"""Largest virtual camera or projector image (pixels)."""


class DeviceOptics(_Strict):
    """Intrinsics and pose of a virtual camera or projector (ground truth of the virtual rig)."""

    width: int = Field(ge=16, le=10000, description="Image width (px).")
    height: int = Field(ge=16, le=10000, description="Image height (px).")
    focal_px: float = Field(gt=0, le=1_000_000, description="Focal length (px).")
    principal_px: tuple[float, float] | None = Field(None, description="Principal point (px); centre when unset.")
    dist: tuple[float, ...] = Field((), max_length=8, description="Distortion k1 k2 p1 p2 k3 (OpenCV order).")
    position_mm: Vec3 = Field((0.0, 0.0, 0.0), description="Optical centre in the world frame (mm).")
    look_at_mm: Vec3 = Field((0.0, 0.0, 600.0), description="A point on the optical axis (mm).")

    @model_validator(mode="after")
    def _size(self) -> DeviceOptics:
        # the virtual rig renders every pattern of a scan as float images of this size, and the reconstruction
        # keeps several per-pixel maps: 20 Mpx (a 5472x3648 sensor) keeps a scan within a few GB
        if self.width * self.height > MAX_VIRTUAL_PIXELS:
            raise ValueError(f"{self.width}x{self.height} = {self.width * self.height / 1e6:.0f} Mpx is more than "
                             f"the virtual rig renders ({MAX_VIRTUAL_PIXELS / 1e6:.0f} Mpx); use a smaller size")
        gap = sum((a - b) ** 2 for a, b in zip(self.look_at_mm, self.position_mm, strict=True)) ** 0.5
        if not gap >= 1.0:  # no optical axis: the pose is undefined (NaN rotation, then a wrong or no cloud)
            raise ValueError(f"look_at_mm {list(self.look_at_mm)} is {gap:g} mm from position_mm "
                             f"{list(self.position_mm)}: it must be a point at least 1 mm along the optical axis")
        return self


class Material(_Strict):
    """Surface physics of a virtual-rig object beyond its diffuse albedo (all off by default)."""

    patches: tuple[float, ...] = Field(
        (), max_length=64,
        description="Albedo patches 0..1 (replace 'albedo'): squares of patch_mm on world x/y, cycling the list.",
    )
    patch_mm: float = Field(20.0, gt=0, le=10_000, description="Side of an albedo patch (mm).")
    specular: float = Field(
        0.0, ge=0, le=1000, description="Peak of the specular lobe, relative to a white diffuse surface."
    )
    shininess: float = Field(50.0, gt=0, le=100_000, description="Blinn-Phong exponent of the specular lobe.")
    mirror: float = Field(
        0.0, ge=0, le=1,
        description="Mirror reflectance 0..1 (planar objects: a plane or a flat mesh): one-bounce reflections of "
        "the projector onto what the mirror faces, and of the scene into the camera.",
    )
    subsurface_mm: float = Field(
        0.0, ge=0, le=100,
        description="Translucency: the pattern on the surface is blurred by a Gaussian of this sigma (mm).",
    )

    @field_validator("patches")
    @classmethod
    def _patches_in_range(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        for a in v:
            if not 0.0 <= a <= 1.0:
                raise ValueError(f"patches: {a} must be in 0..1")
        return v


class PlaneObject(_Strict):
    type: Literal["plane"] = "plane"
    point_mm: Vec3 = Field(description="A point on the plane (mm).")
    normal: Vec3 = Field((0.0, 0.0, -1.0), description="Plane normal (any length).")
    albedo: float = Field(0.8, ge=0, le=1, description="Reflectance 0..1.")
    texture: float = Field(0.0, ge=0, le=1, description="Albedo texture amplitude (share of albedo).")
    material: Material = Field(default_factory=Material, description="Specular, mirror, patches.")


class SphereObject(_Strict):
    type: Literal["sphere"] = "sphere"
    center_mm: Vec3
    radius_mm: float = Field(gt=0)
    albedo: float = Field(0.8, ge=0, le=1)
    texture: float = Field(0.0, ge=0, le=1)
    material: Material = Field(default_factory=Material, description="Specular, mirror, patches.")


class BoxObject(_Strict):
    type: Literal["box"] = "box"
    center_mm: Vec3
    size_mm: Vec3
    rotation_deg: Vec3 = Field((0.0, 0.0, 0.0), description="Rotation about x, y, z (degrees, x then y then z).")
    albedo: float = Field(0.8, ge=0, le=1)
    texture: float = Field(0.0, ge=0, le=1)
    material: Material = Field(default_factory=Material, description="Specular, mirror, patches.")


class CylinderObject(_Strict):
    type: Literal["cylinder"] = "cylinder"
    center_mm: Vec3 = Field(description="Centre of the axis segment (mm).")
    axis: Vec3 = Field((0.0, 1.0, 0.0), description="Axis direction.")
    radius_mm: float = Field(gt=0)
    height_mm: float = Field(gt=0)
    albedo: float = Field(0.8, ge=0, le=1)
    texture: float = Field(0.0, ge=0, le=1)
    material: Material = Field(default_factory=Material, description="Specular, mirror, patches.")


class MeshObject(_Strict):
    type: Literal["mesh"] = "mesh"
    path: Path | None = Field(None, description="PLY/OBJ/STL triangle mesh (mm), relative to the config file.")
    vertices_mm: tuple[Vec3, ...] = Field((), description="Inline vertices (mm) when no path is given.")
    triangles: tuple[tuple[int, int, int], ...] = Field((), description="Inline triangles (vertex indices).")
    position_mm: Vec3 = Field((0.0, 0.0, 0.0), description="Translation applied to the mesh (mm).")
    rotation_deg: Vec3 = Field((0.0, 0.0, 0.0))
    scale: float = Field(1.0, gt=0)
    albedo: float = Field(0.8, ge=0, le=1)
    texture: float = Field(0.0, ge=0, le=1)
    material: Material = Field(default_factory=Material, description="Specular, mirror, patches.")

    @model_validator(mode="after")
    def _source(self) -> MeshObject:
        if self.path is None and not (self.vertices_mm and self.triangles):
            raise ValueError("a mesh needs 'path' or both 'vertices_mm' and 'triangles'")
        return self


SceneObject = Annotated[
    PlaneObject | SphereObject | BoxObject | CylinderObject | MeshObject, Field(discriminator="type")
]


class ImagingConfig(_Strict):
    """Photometry of the virtual rig."""

    projector_gamma: float = Field(2.2, gt=0.1, le=5, description="Projector intensity = value^gamma.")
    gamma_corrected: bool = Field(True, description="Patterns are pre-corrected for the projector gamma.")
    projector_gain_dn: float = Field(
        180.0, ge=0, le=1_000_000, description="Camera DN for a white projector on albedo 1."
    )
    ambient_dn: float = Field(10.0, ge=0, le=1_000_000, description="Ambient light (DN at albedo 1).")
    reference_exposure_us: float = Field(
        10000.0, gt=0, le=10_000_000, description="Exposure at which projector_gain_dn and ambient_dn hold (µs)."
    )
    exposure_us: float = Field(
        10000.0, gt=0, le=10_000_000,
        description="The cameras' exposure (µs) until a scan sets another; light scales with it before noise.",
    )
    projector_intensity: float = Field(
        1.0, gt=0, le=1, description="Projector intensity 0..1; scales the projector's light, not the ambient."
    )
    read_noise_dn: float = Field(2.0, ge=0, le=65535, description="Read noise sigma (DN).")
    shot_noise: bool = Field(True, description="Poisson shot noise.")
    electrons_per_dn: float = Field(
        25.0, gt=0, le=1_000_000,
        description="Conversion gain for shot noise (e- per DN, 8-bit scale; ~6000 e- full well).",
    )
    projector_blur_px: float = Field(
        0.6, ge=0, le=20, description="Projector defocus (Gaussian sigma, projector px, at most 20)."
    )
    camera_blur_px: float = Field(
        0.5, ge=0, le=20, description="Camera defocus (Gaussian sigma, camera px, at most 20)."
    )
    bit_depth: Literal[8, 12, 16] = Field(8, description="Camera bit depth; saturates at full scale.")
    interreflection_samples: int = Field(
        0, ge=0, le=64,
        description="One-bounce diffuse interreflection between objects: hemisphere samples per pixel "
        "(each a light layer; 0: off).",
    )
    seed: int | None = Field(
        1, ge=0, le=2**63 - 1, description="Noise seed, a whole number >= 0 (None: different noise each scan)."
    )


def _default_cameras() -> dict[str, DeviceOptics]:
    return {
        "cam0": DeviceOptics(width=1280, height=1024, focal_px=2400.0, dist=(-0.08, 0.12, 0.0005, -0.0003, 0.0),
                             position_mm=(0.0, 0.0, 0.0), look_at_mm=(0.0, 0.0, 600.0)),
    }


def _default_projector() -> DeviceOptics:
    # 190 mm baseline; its image covers the camera's whole view of the scene (520-650 mm)
    return DeviceOptics(width=1280, height=800, focal_px=1750.0, dist=(0.02, -0.01, 0.0, 0.0, 0.0),
                        position_mm=(190.0, 0.0, 0.0), look_at_mm=(0.0, 0.0, 600.0))


def _default_scene() -> tuple[SceneObject, ...]:
    return (
        PlaneObject(point_mm=(0.0, 0.0, 630.0), normal=(0.0, 0.1, -1.0), texture=0.3),
        SphereObject(center_mm=(-20.0, 10.0, 560.0), radius_mm=40.0, texture=0.2),
        BoxObject(center_mm=(70.0, -40.0, 600.0), size_mm=(60.0, 50.0, 40.0), rotation_deg=(10.0, 25.0, 5.0)),
    )


class VirtualRigConfig(_Strict):
    """The simulated rig: ground-truth optics, the scene and the photometry."""

    projector: DeviceOptics = Field(default_factory=_default_projector)
    cameras: dict[str, DeviceOptics] = Field(default_factory=_default_cameras)
    scene: tuple[SceneObject, ...] = Field(default_factory=_default_scene)
    imaging: ImagingConfig = Field(default_factory=ImagingConfig)

    @field_validator("scene")
    @classmethod
    def _some_scene(cls, v: tuple[SceneObject, ...]) -> tuple[SceneObject, ...]:
        if not v:  # validated, then every scan gave 0 points
            raise ValueError("an empty scene gives no points; add an object, or leave scene out for the default one")
        return v


# --- output and service -------------------------------------------------------------------------------


class OutputConfig(_Strict):
    """Where clouds go."""

    directory: Path = Field(Path("out/scans"), description="Share or local folder; files go under YYYY-MM-DD/.")
    spool_directory: Path = Field(Path("out/spool"), description="Local spool while the share is away.")
    spool_max_mb: float = Field(2048.0, gt=0, description="Spool size limit (MB); oldest dropped beyond it.")
    spool_max_age_days: float = Field(14.0, gt=0, description="Spooled scans older than this are dropped (days).")
    min_free_mb: float = Field(200.0, ge=0, description="Refuse a scan when less than this is free (MB).")
    preview: bool = Field(True, description="Write a preview PNG beside each cloud.")
    normals: bool = Field(False, description="Write normals into the PLY.")
    require_mount: bool = Field(
        False, description="The share counts as present only when output.directory is a mount point."
    )
    share_timeout_s: float = Field(
        10.0, gt=0, le=600, description="An operation on the share (stat, statvfs, one write of up to 4 MB, "
        "fsync, rename, listing) that takes longer counts the share as away; scans spool (s)."
    )


class MdnsConfig(_Strict):
    enabled: bool = Field(True, description="Announce the appliance with mDNS.")
    interfaces: tuple[str, ...] = Field(("127.0.0.1",), description="Addresses to announce on (loopback by default).")
    instance_name: str | None = Field(None, description="Service instance name; hostname when unset.")
    announce_smb_share: str | None = Field(None, description="Also announce this SMB share name (_smb._tcp).")
    port: int = Field(0, ge=0, le=65535, description="Port in the _scan3d._tcp SRV record (0: none; the "
                      "control socket is local).")


_LISTEN_RE = r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):[0-9]{1,5}$"


class HttpConfig(_Strict):
    """HTTP API and status page (aiohttp); off unless ``listen`` is set."""

    listen: str | None = Field(None, description="HOST:PORT to serve the API and status page on, e.g. "
                               "'127.0.0.1:8080' or '0.0.0.0:8080'; null: off.")
    token_file: Path | None = Field(None, description="File holding the bearer token every write (POST) needs; "
                                    "unset: writes are refused.")
    max_request_kb: int = Field(16, ge=1, le=1024, description="Largest request accepted (KiB).")
    rate_per_s: float = Field(20.0, gt=0, le=1000, description="Requests per second per client address "
                              "(bursts of twice this); beyond it: 429.")
    max_event_clients: int = Field(16, ge=1, le=256, description="Concurrent /api/events streams.")

    @field_validator("listen")
    @classmethod
    def _host_port(cls, v: str | None) -> str | None:
        if v is not None and (not re.match(_LISTEN_RE, v) or int(v.rpartition(":")[2]) > 65535):
            raise ValueError("must be HOST:PORT with a port up to 65535, e.g. '127.0.0.1:8080' or '0.0.0.0:8080' "
                             "(null: off)")
        return v


class MqttConfig(_Strict):
    """MQTT client (aiomqtt): state, scans and a trigger command on a broker."""

    enabled: bool = Field(False, description="Connect to the broker.")
    host: str = Field("127.0.0.1", min_length=1, description="Broker host name or address.")
    port: int = Field(1883, ge=1, le=65535, description="Broker port (8883 is usual with TLS).")
    username: str | None = Field(None, description="User name at the broker; none: anonymous.")
    password_file: Path | None = Field(None, description="File holding the broker password.")
    tls: bool = Field(False, description="Connect with TLS (system CA store, host name checked).")
    ca_file: Path | None = Field(None, description="CA bundle for TLS instead of the system store.")
    topic_prefix: str = Field("scan3d/{serial}", min_length=1, max_length=200,
                              description="Topic prefix; {serial} is replaced by the appliance serial.")
    keepalive_s: int = Field(30, ge=5, le=3600, description="MQTT keep-alive (s).")
    reconnect_max_s: float = Field(30.0, ge=0.1, le=3600, description="Longest wait between reconnects (s).")
    queue_max: int = Field(100, ge=1, le=10000, description="Scan messages kept while the broker is away; "
                           "the oldest are dropped beyond it.")


OpcUaPolicy = Literal["None", "Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt"]


class OpcUaConfig(_Strict):
    """OPC UA server (asyncua): the Scanner object; anonymous read-only, Trigger for a user."""

    enabled: bool = Field(False, description="Serve OPC UA.")
    endpoint: str = Field("opc.tcp://127.0.0.1:4840/scan3d", pattern=r"^opc\.tcp://[^/\s]+:[0-9]{1,5}(/\S*)?$",
                          description="Endpoint URL to listen on, e.g. opc.tcp://0.0.0.0:4840/scan3d.")
    username: str | None = Field(None, min_length=1, description="The user allowed to call Trigger; unset: "
                                 "Trigger is disabled (anonymous clients only read).")
    password_file: Path | None = Field(None, description="File holding that user's password.")
    security_policies: tuple[OpcUaPolicy, ...] = Field(
        ("None",), min_length=1, description="Offered security policies; the Basic256Sha256 ones need "
        "certificate_file and private_key_file.")
    certificate_file: Path | None = Field(None, description="Server certificate (DER or PEM).")
    private_key_file: Path | None = Field(None, description="Server private key (PEM).")

    @model_validator(mode="after")
    def _keys(self) -> OpcUaConfig:
        if (self.username is None) != (self.password_file is None):
            raise ValueError("service.opcua.username and password_file go together; set both (or neither: "
                             "Trigger disabled)")
        if any(p != "None" for p in self.security_policies) and (
                self.certificate_file is None or self.private_key_file is None):
            raise ValueError("service.opcua.security_policies: Basic256Sha256 needs certificate_file and "
                             "private_key_file; set them or use ['None']")
        return self


class ServiceConfig(_Strict):
    control_socket: Path = Field(Path("out/control.sock"), description="Unix socket for scan3d status/trigger.")
    state_directory: Path = Field(Path("out/state"), description="State files (last scans, counters).")
    numba_cache_dir: Path | None = Field(None, description="numba kernel cache; NUMBA_CACHE_DIR when unset.")
    busy_policy: Literal["refuse", "queue"] = Field("refuse", description="A trigger while busy is refused or queued.")
    queue_max: int = Field(1, ge=1, le=16, description="Queued triggers kept when busy_policy is 'queue'.")
    scan_timeout_s: float = Field(30.0, gt=0, le=600, description="Fail a scan that takes longer (s).")
    watchdog: bool = Field(True, description="Send WATCHDOG=1 to systemd when WatchdogSec is set.")
    config_poll_s: float = Field(2.0, ge=0, le=3600, description="Check the config file's mtime this often "
                                 "(s); 0: only on SIGHUP.")
    retry_max_s: float = Field(30.0, gt=0, le=3600, description="Longest wait between hardware retries (s).")
    stop_grace_s: float = Field(20.0, ge=0, le=600, description="On SIGTERM, let a running scan finish this "
                                "long before aborting it (s).")
    mdns: MdnsConfig = Field(default_factory=MdnsConfig)
    http: HttpConfig = Field(default_factory=HttpConfig)
    mqtt: MqttConfig = Field(default_factory=MqttConfig)
    opcua: OpcUaConfig = Field(default_factory=OpcUaConfig)


# --- calibration and verification ---------------------------------------------------------------------

ARUCO_DICTIONARIES = (
    "DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000",
    "DICT_5X5_50", "DICT_5X5_100", "DICT_5X5_250", "DICT_5X5_1000",
    "DICT_6X6_50", "DICT_6X6_100", "DICT_6X6_250", "DICT_6X6_1000",
    "DICT_7X7_50", "DICT_7X7_100", "DICT_7X7_250", "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h10",
    "DICT_APRILTAG_36h11",
)  # fmt: skip


DistortionName = Literal["auto", "none", "k1", "k2", "k2p", "k3", "k3p", "rational", "standard", "simple"]


MAX_BOARD_FEATURE_MM = 10_000
"""Largest square side, dot pitch or marker of a calibration board (mm), in the configuration and on the command
line (1e308 overflows the fit)."""


class BoardConfig(_Strict):
    """A calibration board (``appliance.calibration.boards.BoardSpec`` adds detection helpers to it)."""

    type: Literal["chessboard", "circles", "acircles", "charuco"] = Field(
        "chessboard", description="Board kind: chessboard, circles, acircles or charuco."
    )
    cols: int = Field(
        15, ge=2, le=200, description="Inner corners (chessboard), dots per row, or squares (ChArUco)."
    )
    rows: int = Field(
        11, ge=2, le=200, description="Inner corners (chessboard), rows of dots, or squares (ChArUco)."
    )
    square_mm: float | None = Field(15.0, gt=0, le=MAX_BOARD_FEATURE_MM,
                                    description="Square side (chessboard, ChArUco), mm.")
    pitch_mm: float | None = Field(None, gt=0, le=MAX_BOARD_FEATURE_MM, description="Dot spacing (circle grids), mm.")
    marker_mm: float | None = Field(None, gt=0, le=MAX_BOARD_FEATURE_MM,
                                    description="ArUco marker side (ChArUco), mm.")
    dictionary: str = Field("DICT_6X6_250", description="ArUco dictionary (ChArUco).")
    legacy_charuco: bool = Field(False, description="Pre-4.6 OpenCV ChArUco layout (even rows only).")

    @model_validator(mode="after")
    def _complete(self) -> BoardConfig:
        if self.type in ("chessboard", "charuco") and self.square_mm is None:
            raise ValueError(f"board type {self.type!r} needs square_mm (square side, mm)")
        if self.type in ("circles", "acircles") and self.pitch_mm is None:
            raise ValueError(f"board type {self.type!r} needs pitch_mm (dot spacing, mm)")
        if self.type == "charuco":
            if self.marker_mm is None:
                raise ValueError("board type 'charuco' needs marker_mm (marker side, mm)")
            assert self.square_mm is not None
            if self.marker_mm >= self.square_mm:
                raise ValueError(f"marker_mm {self.marker_mm} must be < square_mm {self.square_mm}")
            if self.dictionary not in ARUCO_DICTIONARIES:
                known = ", ".join(ARUCO_DICTIONARIES)
                raise ValueError(f"dictionary {self.dictionary!r}: must be one of {known}")
        return self


class ArtefactSphere(_Strict):
    """A calibrated sphere of the verification artefact."""

    center_mm: Vec3 = Field(description="Nominal centre, world frame (mm); points are segmented around it.")
    diameter_mm: float = Field(gt=0, le=1000, description="Calibrated diameter (mm).")


class ArtefactPlane(_Strict):
    """The flat of the verification artefact."""

    point_mm: Vec3 = Field(description="Nominal point on the plane, world frame (mm).")
    normal: Vec3 = Field((0.0, 0.0, -1.0), description="Nominal normal (any length).")
    size_mm: tuple[float, float] = Field(
        (300.0, 200.0), description="Evaluated extent around point_mm (mm); unbounded on the virtual rig."
    )


def _default_spheres() -> tuple[ArtefactSphere, ...]:
    return (ArtefactSphere(center_mm=(-50.0, 0.0, 590.0), diameter_mm=30.0),
            ArtefactSphere(center_mm=(50.0, 0.0, 590.0), diameter_mm=30.0))  # fmt: skip


class ArtefactPosition(_Strict):
    """Where ``scan3d verify`` puts (or asks a person to put) the artefact: a move from its nominal place."""

    offset_mm: Vec3 = Field((0.0, 0.0, 0.0), description="Shift of the whole artefact, world frame (mm).")
    rotation_deg: float = Field(
        0.0, ge=-180, le=180, description="Turn about the world z axis through the sphere centres' mean (deg)."
    )


def _default_positions() -> tuple[ArtefactPosition, ...]:
    return (ArtefactPosition(), ArtefactPosition(offset_mm=(-35.0, -20.0, -30.0), rotation_deg=45.0),
            ArtefactPosition(offset_mm=(35.0, 20.0, 30.0), rotation_deg=-45.0),
            ArtefactPosition(offset_mm=(0.0, 0.0, 40.0), rotation_deg=90.0),
            ArtefactPosition(offset_mm=(0.0, 0.0, -40.0)))  # fmt: skip


class ArtefactConfig(_Strict):
    """The known artefact scanned by ``scan3d verify`` (a ball bar and a plane, VDI/VDE 2634 style)."""

    spheres: tuple[ArtefactSphere, ...] = Field(
        default_factory=_default_spheres, max_length=8, description="Spheres; two make a ball bar."
    )
    ball_bar_length_mm: float | None = Field(
        None, gt=0, description="Calibrated distance of the first two sphere centres (mm); unset: nominal."
    )
    plane: ArtefactPlane | None = Field(
        default_factory=lambda: ArtefactPlane(point_mm=(0.0, 0.0, 640.0), normal=(0.0, 0.1, -1.0)),
        description="The flat (none: no flatness check).",
    )
    search_margin_mm: float = Field(
        4.0, gt=0, le=100, description="Segmentation: points within this of the fitted sphere surfaces and "
        "plane (mm); the first search reaches 3x as far from the nominal ones.",
    )
    albedo: float = Field(0.8, ge=0, le=1, description="Reflectance of the artefact on the virtual rig.")
    positions: tuple[ArtefactPosition, ...] = Field(
        default_factory=_default_positions, min_length=1, max_length=20,
        description="Positions through the measuring volume (VDI/VDE 2634-2); each is scanned once.",
    )


class VerifyTolerances(_Strict):
    """Pass/fail limits of ``scan3d verify`` (mm)."""

    flatness_mm: float = Field(0.1, gt=0, description="Plane form error: peak-to-valley of cell means (mm).")
    probing_form_mm: float = Field(
        0.6, gt=0, description="MPE of the probing error form PF: peak-to-valley of a sphere's radial residuals, "
        "point noise included (mm).",
    )
    flatness_cell_mm: float = Field(
        10.0, ge=0, le=100, description="Cell size over which plane residuals are averaged before the "
        "peak-to-valley (mm); 0: raw points (noise included).",
    )
    sphere_diameter_mm: float = Field(
        0.05, gt=0, description="MPE of the probing error size PS: |fitted - calibrated| sphere diameter (mm)."
    )
    ball_bar_length_mm: float = Field(
        0.1, gt=0, description="MPE of the sphere-spacing error SD: |measured - calibrated| sphere distance (mm)."
    )
    exclude_fraction: float = Field(
        0.003, ge=0, le=0.1, description="Share of the largest residuals excluded before peak-to-valley "
        "values (VDI/VDE 2634: 0.3 %).",
    )


class CalibrationConfig(_Strict):
    """Calibration board, live capture and verification."""

    board: BoardConfig = Field(default_factory=BoardConfig)
    poses_wanted: int = Field(12, ge=3, le=100, description="Live calibration: enough board poses.")
    coverage_target: float = Field(
        0.6, gt=0, le=1, description="Live calibration: share of each camera's image the board must cover."
    )
    camera_model: DistortionName = Field(
        "auto", description="Camera distortion: auto (chosen by leave-one-view-out error among k2p, k3p, "
        "rational), kN radial k1..kN, p tangential, rational k1..k6 p1 p2.",
    )
    projector_model: DistortionName = Field("auto", description="Projector distortion (as camera_model).")
    health_tolerance_px: float | None = Field(
        None, gt=0, description="Calibration health: a scan's redundant residual (robust RMS, px) beyond this "
        "is 'bad'; unset: 3 x what the calibration promised (its stated RMS, at least 0.2 px).",
    )
    artefact: ArtefactConfig = Field(default_factory=ArtefactConfig)
    tolerances: VerifyTolerances = Field(default_factory=VerifyTolerances)


# --- the whole file -----------------------------------------------------------------------------------


def _default_camera_backends() -> dict[str, CameraConfig]:
    return {"cam0": SimCameraConfig()}


class AppConfig(_Strict):
    """The whole configuration file."""

    serial: str = Field(
        "SIM-0001",
        description="Appliance serial number (in mDNS, topics, sidecars and file names): letters, digits, '.', "
        "'_' and '-', at most 64.",
    )
    cameras: dict[str, CameraConfig] = Field(
        default_factory=_default_camera_backends,
        min_length=1,
        max_length=4,
        description="Cameras by name; the first is the reference (world) camera.",
    )
    projector: ProjectorConfig = Field(default_factory=SimProjectorConfig)
    trigger: TriggerConfig = Field(default_factory=SimTriggerConfig)
    calibration_file: Path | None = Field(
        None, description="Calibration (OpenCV YAML); unset on the virtual rig = its exact calibration."
    )
    sequence: SequenceConfig = Field(default_factory=SequenceConfig)
    reconstruction: ReconstructionConfig = Field(default_factory=ReconstructionConfig)
    virtual_rig: VirtualRigConfig = Field(default_factory=VirtualRigConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    service: ServiceConfig = Field(default_factory=ServiceConfig)
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)

    @field_validator("serial")
    @classmethod
    def _serial_is_a_name(cls, v: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}", v):
            raise ValueError("must be 1-64 letters, digits, '.', '_' or '-' starting with a letter or digit (it "
                             "goes into file names, MQTT topics and mDNS)")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> AppConfig:
        names = list(self.cameras)
        for name, cam in self.cameras.items():
            if cam.type == "sim" and name not in self.virtual_rig.cameras:
                raise ValueError(
                    f"camera {name!r} is type sim but virtual_rig.cameras has no {name!r} "
                    f"(it has {sorted(self.virtual_rig.cameras)}); add its optics there"
                )
        if self.reconstruction.mode in ("stereo", "both") and len(names) < 2:
            raise ValueError(
                f"reconstruction.mode '{self.reconstruction.mode}' needs two cameras; add one or use mode 'projector'"
            )
        if self.calibration_file is None and (
            self.projector.type != "sim" or any(c.type != "sim" for c in self.cameras.values())
        ):
            raise ValueError("calibration_file must be set when any device is real hardware")
        if self.output.normals and not self.reconstruction.normals:
            raise ValueError(
                "output.normals: true writes normals, but reconstruction.normals is false so none are estimated; "
                "set reconstruction.normals: true as well (or output.normals: false)"
            )
        return self

    @property
    def is_virtual(self) -> bool:
        """True when every device is simulated."""
        return self.projector.type == "sim" and all(c.type == "sim" for c in self.cameras.values())
