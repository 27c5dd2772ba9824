"""Data types passed between decoding, triangulation and output."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import numpy.typing as npt


class Reason(IntEnum):
    """Why a camera pixel has no point (``DecodedMaps.reason``); 0 where it has one.

    The decoder sets ``SHADOW`` .. ``WEAK_CODE``, ``MIXED``, ``INTERREFLECTION`` and ``EDGE`` (0 there: decoded);
    the reconstruction then sets its own on the decoded pixels that gave no point (``NOT_MATCHED``,
    ``OUT_OF_RANGE``, ``FILTERED``, ``EPIPOLAR``, ``HIDDEN``), so that after it 0 means "has a point" and every
    other pixel has exactly one reason.
    """

    DECODED = 0
    #: no projector light reaches the pixel (white - black at the noise floor)
    SHADOW = 1
    #: lit, but the pattern's contrast is below the lit threshold: a longer exposure would help
    TOO_DARK = 2
    #: a sample the code needs is at the sensor's full scale: a shorter exposure would help
    SATURATED = 3
    #: lit, but a code bit or phase has too little contrast, or the codes disagree (an edge, a mixed pixel,
    #: interreflection)
    WEAK_CODE = 4
    #: camera-camera: no partner pixel on the other camera
    NOT_MATCHED = 5
    #: no point inside the working range (depth range; or none at all: a code off the projector's image, a
    #: point behind a device)
    OUT_OF_RANGE = 6
    #: removed by a filter (neighbours disagree, sigma too large; camera-camera fusion: the two disagree)
    FILTERED = 7
    #: both projector axes coded, but the (u, v) pair lies off the pixel's epipolar line by more than the code
    #: noise allows: the light came another way (a mirror-like surface re-projecting the pattern)
    EPIPOLAR = 8
    #: multi-exposure: the pixel decoded only in passes where a neighbour clipped; that neighbour's light (of
    #: unknown level) reaches it through the lens blur, so its code is partly the neighbour's (a bright-dark edge)
    MIXED = 9
    #: two copies of the pattern reach the pixel (a mirror-like face re-projects it, strong interreflection): several
    #: of its finest Gray bits have the contrast of a difference of two lights; its code would be neither's
    INTERREFLECTION = 10
    #: a point the projector cannot light: another point lies nearer the projector on the same projector ray (by
    #: more than the surface's slope and the errors allow), so its light came by a reflection (the camera sees a
    #: lit surface in a mirror-like face, or a mirror lights a face the projector's shadow hides); its code belongs
    #: to another surface (a ghost)
    HIDDEN = 11
    #: lit over a small part of its footprint, beside a pixel with no projector light: its centre most likely sees
    #: the unlit surface (a self-shadowed silhouette, a shadow's edge), and its light, so its code, comes from the
    #: lit surface beside it, at another depth where that is an occluding edge (``_decode_kernels.COVER_RATIO``)
    EDGE = 12


#: Plain-words name of each reason (sidecar keys, reports).
REASON_NAMES: dict[int, str] = {
    Reason.DECODED: "decoded",
    Reason.SHADOW: "shadow",
    Reason.TOO_DARK: "too dark",
    Reason.SATURATED: "saturated",
    Reason.WEAK_CODE: "weak or inconsistent code",
    Reason.NOT_MATCHED: "not matched",
    Reason.OUT_OF_RANGE: "out of range",
    Reason.FILTERED: "filtered",
    Reason.EPIPOLAR: "off the epipolar line",
    Reason.MIXED: "next to a clipped pixel",
    Reason.INTERREFLECTION: "two copies of the pattern",
    Reason.HIDDEN: "hidden from the projector",
    Reason.EDGE: "edge of a shadow or silhouette",
}


@dataclass
class DecodedMaps:
    """Projector coordinates decoded for every pixel of one camera.

    Attributes
    ----------
    u, v : ndarray, shape (H, W), float32
        Projector column / row (projector pixels, centres at integers); NaN where not decoded or not coded.
    mask : ndarray, shape (H, W), bool
        True where every coded axis decoded.
    quality : ndarray, shape (H, W), float32
        Decoding confidence: the weakest signal contrast of the pixel (digital numbers, DN); 0 where masked.
    ignored : list of str
        Human descriptions of frames the decoder did not use.
    levels : ndarray, shape (2, H, W), uint8, optional
        Per axis (x, y), how many of the finest Gray bits the pixel could not resolve and dropped: its code
        is a stripe of ``stripe * 2**level`` projector px (0 where undecoded). None when not computed.
    reason : ndarray, shape (H, W), uint8, optional
        Per pixel a :class:`Reason`: 0 where decoded, else why not. None when not computed.
    blend_codes : ndarray, shape (N, 4), float32, optional
        The pixels the check for two copies of the pattern undecoded (reason ``INTERREFLECTION``): row, column,
        u, v (projector px; v NaN when not coded) of the stronger copy. Never a point: the reconstruction uses
        them only as evidence of a surface that the projector lights in front of another point.
    fringe : ndarray, shape (H, W), uint8, optional
        Per decoded pixel its ``quality`` as a share of its white - black range (percent, at most 255; 0 where
        undecoded): how much of the pixel's projector light carries the pattern. Light that came another way
        (diffuse interreflection, subsurface scattering) adds to the range, not to the pattern's contrast. None
        when not computed.
    radiance : ndarray, shape (H, W), float32, optional
        White-light level per pixel in one scale across exposure passes (DN per unit of the brightest pass's
        light; see :func:`appliance.reconstruct.hdr.radiance`), for the albedo-edge correction. None: the white
        image is that level (one exposure).
    separated : ndarray, shape (N, 3), float32, optional
        The pixels of the blend check whose direct code was taken apart from a second copy of the pattern
        (:mod:`appliance.reconstruct.ghosts`): row, column, and the code variance (projector px^2) their sigma
        gains. They are decoded (and still in ``blend_codes``, with the separated code, as evidence of a
        reflection). None: none.
    """

    u: npt.NDArray[np.float32]
    v: npt.NDArray[np.float32]
    mask: npt.NDArray[np.bool_]
    quality: npt.NDArray[np.float32]
    ignored: list[str] = field(default_factory=list)
    levels: npt.NDArray[np.uint8] | None = None
    reason: npt.NDArray[np.uint8] | None = None
    blend_codes: npt.NDArray[np.float32] | None = None
    fringe: npt.NDArray[np.uint8] | None = None
    radiance: npt.NDArray[np.float32] | None = None
    separated: npt.NDArray[np.float32] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the camera image."""
        return (int(self.mask.shape[0]), int(self.mask.shape[1]))


@dataclass
class PointCloud:
    """A point cloud as a struct of arrays.

    Attributes
    ----------
    xyz : ndarray, shape (N, 3), float32
        Points in the world frame (the reference camera's frame), millimetres.
    row, col : ndarray, shape (N,), int32
        The camera pixel each point came from.
    camera : ndarray, shape (N,), uint8
        Index of the camera each point came from (order of the configuration).
    intensity : ndarray, shape (N,), uint8
        Grey value of the pixel under white light (0..255).
    quality : ndarray, shape (N,), float32
        Decoding quality of the point (see :class:`DecodedMaps`).
    normal : ndarray, shape (N, 3), float32, optional
        Unit surface normals pointing towards the camera.
    sigma_mm : ndarray, shape (N,), float32, optional
        Expected 1-sigma error of each point along its camera ray (mm), from its decode noise; NaN where
        unknown. None: unknown for every point.
    """

    xyz: npt.NDArray[np.float32]
    row: npt.NDArray[np.int32]
    col: npt.NDArray[np.int32]
    camera: npt.NDArray[np.uint8]
    intensity: npt.NDArray[np.uint8]
    quality: npt.NDArray[np.float32]
    normal: npt.NDArray[np.float32] | None = None
    sigma_mm: npt.NDArray[np.float32] | None = None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @staticmethod
    def empty() -> PointCloud:
        """A cloud with no points."""
        return PointCloud(
            np.zeros((0, 3), np.float32),
            np.zeros(0, np.int32),
            np.zeros(0, np.int32),
            np.zeros(0, np.uint8),
            np.zeros(0, np.uint8),
            np.zeros(0, np.float32),
        )

    def select(self, keep: npt.NDArray[np.bool_]) -> PointCloud:
        """The points where ``keep`` (shape (N,)) is True."""
        return PointCloud(
            self.xyz[keep],
            self.row[keep],
            self.col[keep],
            self.camera[keep],
            self.intensity[keep],
            self.quality[keep],
            None if self.normal is None else self.normal[keep],
            None if self.sigma_mm is None else self.sigma_mm[keep],
        )

    @staticmethod
    def concatenate(clouds: list[PointCloud]) -> PointCloud:
        """Join clouds (normals kept only when every cloud has them; sigma NaN where a cloud has none)."""
        if not clouds:
            return PointCloud.empty()
        normals = [c.normal for c in clouds]
        sigmas = None
        if any(c.sigma_mm is not None for c in clouds):
            sigmas = np.concatenate(
                [c.sigma_mm if c.sigma_mm is not None else np.full(len(c), np.nan, np.float32) for c in clouds]
            )
        return PointCloud(
            np.concatenate([c.xyz for c in clouds]),
            np.concatenate([c.row for c in clouds]),
            np.concatenate([c.col for c in clouds]),
            np.concatenate([c.camera for c in clouds]),
            np.concatenate([c.intensity for c in clouds]),
            np.concatenate([c.quality for c in clouds]),
            None if any(n is None for n in normals) else np.concatenate(normals),  # type: ignore[arg-type]
            sigmas,
        )


STAGES = ("decode", "geometry", "epipolar", "depth_range", "neighbours", "sigma")
"""The stages of a camera-projector reconstruction, in order, each rejecting some of the candidates left."""


@dataclass(frozen=True)
class StageCounts:
    """How many candidates one camera's reconstruction had after each stage, and why the others went.

    Attributes
    ----------
    camera : str
        Camera name.
    pixels : int
        Pixels of the image (the candidates of the first stage).
    decoded : int
        Pixels that decoded a code (``decode`` rejects the rest: shadow, too little contrast).
    triangulated : int
        Decoded pixels the geometry turned into a point (``geometry`` rejects codes off the projector's image,
        rays along the coded light surfaces, points behind a device).
    in_range : int
        Points inside the depth range (``depth_range``).
    with_neighbours : int
        Points with enough near neighbours (``neighbours``).
    kept : int
        Points whose expected error is within ``max_sigma_mm`` (``sigma``): the points of the cloud.
    consistent : int, optional
        Triangulated points whose (u, v) lies on the pixel's epipolar line within the code noise (``epipolar``,
        both projector axes coded); None: not checked (every triangulated point passes).
    """

    camera: str
    pixels: int
    decoded: int
    triangulated: int
    in_range: int
    with_neighbours: int
    kept: int
    consistent: int | None = None

    def remaining(self) -> tuple[int, ...]:
        """Candidates before each stage and after the last: (pixels, decoded, ..., kept)."""
        cons = self.triangulated if self.consistent is None else self.consistent
        return (self.pixels, self.decoded, self.triangulated, cons, self.in_range, self.with_neighbours, self.kept)

    def rejected(self) -> dict[str, int]:
        """Candidates each stage rejected, by stage name (see :data:`STAGES`)."""
        n = self.remaining()
        return {stage: n[i] - n[i + 1] for i, stage in enumerate(STAGES)}

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: the counts and the rejections per stage."""
        return {
            "camera": self.camera,
            "pixels": self.pixels,
            "decoded": self.decoded,
            "triangulated": self.triangulated,
            "consistent": self.triangulated if self.consistent is None else self.consistent,
            "in_range": self.in_range,
            "with_neighbours": self.with_neighbours,
            "kept": self.kept,
            "rejected": self.rejected(),
        }
