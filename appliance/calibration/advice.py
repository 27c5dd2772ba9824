"""When a calibration is weak, and which board poses to add.

:func:`assess` looks at a calibrated device's views: how many there are, which parts of the image the
board covered, how much the board distance and tilt varied, how large the board was in the image, and
whether one view decided an intrinsic on its own (leaving it out moves the intrinsic by more than
``DOMINANCE_SIGMAS`` standard deviations). Each finding comes with the poses to add.
:func:`missing_regions` and :func:`next_pose_hint` guide a live calibration from the detections alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from appliance.calibration.intrinsics import MIN_VIEWS_WARN, CameraResult, coverage_map

if TYPE_CHECKING:
    from appliance.calibration.selection import ModelChoice

F64 = npt.NDArray[np.float64]

REGIONS = (
    ("top-left", "top", "top-right"),
    ("left", "centre", "right"),
    ("bottom-left", "bottom", "bottom-right"),
)
MIN_REGION_COVER = 0.25
"""A third-by-third region of the image counts as covered when this share of its cells was covered."""
MIN_DEPTH_SPREAD = 0.15
"""Board distances should span at least this share of their median."""
MIN_TILT_DEG = 20.0
"""Some view should tilt the board at least this much against the viewing axis (it fixes the focal length)."""
MIN_BOARD_AREA = 0.08
"""In a typical (median) view the board should cover at least this share of the image."""
DOMINANCE_SIGMAS = 2.0
"""One view dominates when leaving it out moves an intrinsic by more than this many standard deviations."""


@dataclass(frozen=True)
class Weakness:
    """One reason a calibration is weak.

    Attributes
    ----------
    kind : str
        ``few_views``, ``image_coverage``, ``depth_range``, ``tilt``, ``board_small`` or ``dominant_view``.
    message : str
        What is wrong, with the numbers.
    poses : list of str
        Board poses to add.
    """

    kind: str
    message: str
    poses: list[str] = field(default_factory=list)

    def line(self) -> str:
        """One human line: the message, then the poses to add."""
        return self.message + ("; add: " + "; ".join(self.poses) if self.poses else "")


def region_cover(coverage: npt.NDArray[np.int32]) -> F64:
    """Share of covered cells in each third-by-third region, shape (3, 3)."""
    gh, gw = coverage.shape
    out = np.zeros((3, 3))
    for r in range(3):
        for c in range(3):
            cell = coverage[r * gh // 3 : (r + 1) * gh // 3, c * gw // 3 : (c + 1) * gw // 3]
            out[r, c] = float(np.mean(cell > 0)) if cell.size else 1.0
    return out


def missing_regions(image_points: Sequence[F64], image_size: tuple[int, int]) -> list[str]:
    """Regions of the image (``top-left`` .. ``bottom-right``) no view has covered well, emptiest first."""
    cov = region_cover(coverage_map(list(image_points), image_size))
    order = np.argsort(cov, axis=None, kind="stable")
    return [REGIONS[i // 3][i % 3] for i in order if cov.flat[i] < MIN_REGION_COVER]


def board_area_fraction(image_points: F64, image_size: tuple[int, int]) -> float:
    """Share of the image inside the convex hull of one view's board points."""
    import cv2

    pts = np.asarray(image_points, np.float32).reshape(-1, 1, 2)
    if len(pts) < 3:
        return 0.0
    return float(cv2.contourArea(cv2.convexHull(pts))) / float(image_size[0] * image_size[1])


def next_pose_hint(image_points: Sequence[F64], image_size: tuple[int, int], device: str) -> str | None:
    """Where to put the board next for ``device`` (None when every region is covered)."""
    missing = missing_regions(image_points, image_size)
    if not missing:
        return None
    more = f" (then: {', '.join(missing[1:4])})" if len(missing) > 1 else ""
    return f"next pose: put the board into the {missing[0]} of {device}'s image{more}"


def _board_geometry(result: CameraResult) -> tuple[F64, F64]:
    """Per view: distance of the board centre (mm) and tilt of the board against the viewing ray (deg)."""
    import cv2

    dist, tilt = [], []
    for obj, rv, tv in zip(result.object_points, result.rvecs, result.tvecs, strict=False):
        R, _ = cv2.Rodrigues(np.asarray(rv, np.float64).reshape(3, 1))
        centre = R @ np.asarray(obj, np.float64).mean(axis=0) + np.asarray(tv, np.float64).ravel()
        normal = R[:, 2]
        dist.append(float(np.linalg.norm(centre)))
        cosang = abs(float(normal @ centre)) / max(float(np.linalg.norm(centre)), 1e-12)
        tilt.append(float(np.degrees(np.arccos(np.clip(cosang, 0.0, 1.0)))))
    return np.asarray(dist), np.asarray(tilt)


def assess(
    result: CameraResult, choice: ModelChoice | None = None, pairwise: CameraResult | None = None
) -> list[Weakness]:
    """What makes a device's calibration weak, with the poses to add.

    Parameters
    ----------
    result : CameraResult
        The device's calibration (views, board points and poses).
    choice : ModelChoice, optional
        Its model selection; the left-out fits show whether one view dominates.
    pairwise : CameraResult, optional
        The pairwise calibration the left-out fits belong to (board poses, standard deviations);
        default ``result``.

    Returns
    -------
    list of Weakness
        Empty when nothing is weak.
    """
    base = pairwise if pairwise is not None else result
    cam = result.camera
    size = (cam.width, cam.height)
    out: list[Weakness] = []
    missing = missing_regions(result.image_points, size)
    area = [board_area_fraction(p, size) for p in result.image_points]
    dist, tilt = _board_geometry(base)
    n = len(result.views)
    if missing:
        out.append(Weakness(
            "image_coverage",
            f"the board never covered the {', '.join(missing)} of the image "
            f"({100 * result.coverage_fraction:.0f} % covered)",
            [f"board in the {m} of the image" for m in missing],
        ))  # fmt: skip
    if len(dist) >= 2:
        med = float(np.median(dist))
        spread = float(dist.max() - dist.min()) / max(med, 1e-9)
        if spread < MIN_DEPTH_SPREAD:
            out.append(Weakness(
                "depth_range",
                f"board distances span only {100 * spread:.0f} % ({dist.min():.0f} .. {dist.max():.0f} mm; "
                f"want >= {100 * MIN_DEPTH_SPREAD:.0f} %)",
                [f"board nearer, at about {0.85 * med:.0f} mm", f"board farther, at about {1.15 * med:.0f} mm"],
            ))  # fmt: skip
    if len(tilt) and float(tilt.max()) < MIN_TILT_DEG:
        out.append(Weakness(
            "tilt",
            f"the board is never tilted more than {tilt.max():.0f} deg against the view (want some views at "
            f">= {MIN_TILT_DEG:.0f} deg; tilt is what fixes the focal length)",
            ["board tilted about 30 deg left-right", "board tilted about 30 deg up-down"],
        ))  # fmt: skip
    if area and float(np.median(area)) < MIN_BOARD_AREA:
        out.append(Weakness(
            "board_small",
            f"the board fills only {100 * float(np.median(area)):.1f} % of the image in a typical view "
            f"(want >= {100 * MIN_BOARD_AREA:.0f} %)",
            ["board closer to the camera, or a larger board"],
        ))  # fmt: skip
    if choice is not None:
        out += _dominance(base, choice)
    if n < MIN_VIEWS_WARN:
        todo = [p for w in out for p in w.poses][: MIN_VIEWS_WARN - n]
        out.insert(0, Weakness(
            "few_views",
            f"only {n} views (want >= {MIN_VIEWS_WARN}); add {MIN_VIEWS_WARN - n} or more",
            todo or ["board in each corner of the image, tilted about 30 deg"],
        ))  # fmt: skip
    return out


def _dominance(base: CameraResult, choice: ModelChoice) -> list[Weakness]:
    ho = choice.best.held_out
    full = base.camera
    values = {"fx": full.K[0, 0], "fy": full.K[1, 1], "cx": full.K[0, 2], "cy": full.K[1, 2]}
    worst: dict[int, tuple[str, float, float]] = {}
    for view, cam, err in zip(ho.views, ho.cameras, ho.per_view_px, strict=False):
        if not np.isfinite(err):
            continue
        left = {"fx": cam.K[0, 0], "fy": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2]}
        for p, v in values.items():
            sd = base.std_devs.get(p, 0.0)
            if sd <= 0:
                continue
            k = abs(left[p] - v) / sd
            if k > DOMINANCE_SIGMAS and k > worst.get(view, ("", 0.0, 0.0))[2]:
                worst[view] = (p, left[p] - v, k)
    out = []
    for view, (p, delta, k) in sorted(worst.items()):
        out.append(Weakness(
            "dominant_view",
            f"view #{view} decides {p} on its own: without it {p} moves by {delta:+.1f} px ({k:.1f} std)",
            [f"more poses like view #{view} (similar place and tilt), so that no single view decides"],
        ))  # fmt: skip
    return out
