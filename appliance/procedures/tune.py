"""``scan3d tune``: a capture assistant that chooses the exposures of a scan for the scene in front of the rig.

A short probe projects white and black at a few exposures (:data:`PROBE_FACTORS` of the configured one) on the
configured rig. From it each lit pixel gets its projector contrast and its white level per microsecond of
exposure (from the longest probe exposure that did not clip it). A pixel is *decodable* at an exposure when its
contrast reaches :data:`DECODABLE_CONTRAST` times ``reconstruction.min_contrast_dn`` and its white level stays
below :data:`CLIP_MARGIN` of the sensor's full scale. Over a ladder of exposures (:data:`LADDER_FACTORS`, steps
of sqrt 2) the fewest that bring at least :data:`TARGET_SHARE` of the lit pixels into a decodable range within
the time budget are chosen and, of those that cover within :data:`COVERAGE_TOLERANCE` as much as the most
covering, the most precise: the one whose passes give the lowest mean code variance by the camera noise model
(each pixel from its brightest unclipped pass, as the fusion takes it). What no exposure recovers is named with
its cause (too dark even at the longest, clipped even at the shortest). ``--apply`` writes the choice to
``sequence.exposures_us`` of the configuration file, validated first and written atomically, as an edit over SSH
would be (a running service reloads it).

The probe also projects fringes at two periods at the configured exposure and measures the optics' blur from
their contrast (:mod:`appliance.procedures.optics_blur`); the cameras' blur is chosen for
``reconstruction.edge_blur_px`` (the albedo-edge correction and its sigma assume it) and written with the
exposures, unless the scene's surfaces cannot tell it from the projector's.

A projector that can dim between passes (lightcrafter4500, sim: see
:func:`~appliance.hardware.base.intensity_control`) adds one probe pass at the shortest exposure and
:data:`PROBE_DIM` of its intensity, which measures the pixels that clip at every full-intensity probe exposure
(specular highlights). The choice may then also take passes at the shortest exposure with the projector dimmed
(:data:`DIM_LADDER`), written to ``sequence.intensities``. Dimming the projector leaves the ambient light as it
is, so a pixel's white level at exposure ``t`` and intensity ``i`` is modelled as ``ambient_rate * t +
contrast_rate * t * i``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import yaml

from appliance.config import AppConfig
from appliance.config.loader import parse_config
from appliance.errors import ConfigError, HardwareError
from appliance.hardware.base import ExposureControl, exposure_control, intensity_control
from appliance.output.atomic import write_bytes_atomic
from appliance.patterns.from_config import build_sequence
from appliance.patterns.sequence import BlackFrame, Sequence, WhiteFrame
from appliance.procedures.optics_blur import BlurEstimate, estimate, fringe_frames, in_range
from appliance.reconstruct.uncertainty import ROUNDING_VAR_DN2

if TYPE_CHECKING:
    from appliance.hardware.registry import Rig

PROBE_FACTORS = (0.25, 1.0, 4.0)
"""Exposures of the probe, relative to the configured exposure."""
LADDER_FACTORS = tuple(2.0 ** (k / 2) for k in range(-4, 11))
"""Exposures the choice may use, relative to the configured exposure (1/4x .. 32x, steps of sqrt 2; none
shorter than the probe's shortest, which is all that says a pixel is not clipped)."""
DECODABLE_CONTRAST = 5.0
"""A pixel decodes well when white - black reaches this many times ``reconstruction.min_contrast_dn``."""
CLIP_MARGIN = 0.95
"""... and its white level stays below this share of the sensor's full scale (noise headroom)."""
LIT_CONTRAST = 1.0
"""A pixel is lit when its contrast at the longest probe exposure reaches this many ``min_contrast_dn``
(or it clips)."""
TARGET_SHARE = 0.99
"""Share of the lit pixels the choice must bring into a decodable range."""
DIM_LADDER = tuple(round(2.0 ** (-k / 2), 3) for k in range(1, 9))
"""Projector intensities a dimmed pass may use (0.707 .. 0.0625 of full scale, steps of sqrt 2), at the ladder's
shortest exposure; only with a projector that can dim."""
PROBE_DIM = 1.0 / 16.0
"""Projector intensity of the probe's dimmed pass (at its shortest exposure)."""
COVERAGE_TOLERANCE = 0.002
"""Choices that reach the target and cover within this share of the lit pixels of the most covering one are
compared by their predicted precision."""
MODEL_PIXELS = 400_000
"""The precision model pools at most about this many lit pixels (an even sample of all cameras')."""
MAX_EXPOSURES = 4
"""The most exposures (capture passes) a choice may have."""
FRAME_PERIOD_US = 16_667.0
"""Frame period of the projector when the exposure is shorter (µs; 60 Hz)."""
PROBE_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class Probe:
    """White and black images of every camera at each probe exposure.

    Attributes
    ----------
    exposures_us : tuple of float
        Exposure of each probe pass (µs), its light (exposure times intensity) ascending.
    white, black : dict of str to ndarray, shape (E, H, W), float64
        DN per probe pass.
    full_scale : dict of str to float
        The sensor's largest value (DN) per camera.
    projector_size : (int, int)
        The projector's width and height (px): the sequence's frame count depends on it.
    intensities : tuple of float
        Projector intensity (0-1] of each probe pass; empty: every pass at full intensity (a projector that
        cannot dim, whose passes the choice then cannot dim either).
    blur : tuple of BlurEstimate
        Per camera the optics' blur measured by the probe's fringes (:mod:`appliance.procedures.optics_blur`);
        a camera whose scene gave too few usable pixels is left out.
    """

    exposures_us: tuple[float, ...]
    white: dict[str, npt.NDArray[np.float64]]
    black: dict[str, npt.NDArray[np.float64]]
    full_scale: dict[str, float]
    projector_size: tuple[int, int] = (1280, 800)
    intensities: tuple[float, ...] = ()
    blur: tuple[BlurEstimate, ...] = ()

    @property
    def can_dim(self) -> bool:
        """True when the probe had a dimmed pass (the projector can set its intensity between passes)."""
        return any(i < 1.0 for i in self.intensities)


@dataclass(frozen=True)
class TuneChoice:
    """The exposures chosen and what they reach.

    Attributes
    ----------
    exposures_us : tuple of int
        Exposure of each capture pass (µs), in the order of the passes' light (exposure times intensity).
    scan_ms : float
        Expected capture time of the scan (ms).
    covered : float
        Share (0..1) of the lit pixels in a decodable range at one of the exposures.
    lit_pixels : int
        Lit pixels of all cameras.
    too_dark, clipped : float
        Shares of the lit pixels that no pass recovers: too dark even at the longest exposure, clipped even at
        the shortest (and, with a projector that can dim, at its lowest intensity).
    dynamic_range : float
        Ratio of the brightest to the darkest lit pixel's contrast per µs.
    within_budget : bool
        False when no choice reaching :data:`TARGET_SHARE` fits the budget (then the best that fits).
    ladder_us : tuple of int
        The exposures the choice could take (µs).
    intensities : tuple of float
        Projector intensity (0-1] of each pass, for ``sequence.intensities``; empty when every pass is at full
        intensity.
    dim_floor : float
        The lowest projector intensity the choice could take (1.0: the projector cannot dim).
    ambient_limited : float
        Share of the lit pixels that no pass recovers because the ambient light clips them before their
        projector contrast is enough (dark parts in a bright room).
    most_covering_passes : tuple of (int, float)
        Where the most precise choice is not the most covering one: the most covering one's passes (exposure µs,
        intensity); empty otherwise.
    most_covering : float
        ... its share of the lit pixels in a decodable range.
    noise_ratio : float
        The chosen passes' predicted code noise (RMS) over the most covering one's (1.0 where they are the same).
    blur : tuple of BlurEstimate
        The optics' blur per camera, measured by the probe.
    edge_blur_px : float or None
        The cameras' blur (camera px, their mean) for ``reconstruction.edge_blur_px``; None when the probe could
        not tell the cameras' blur from the projector's (then the setting is left as it is).
    edge_blur_now : float or None
        ``reconstruction.edge_blur_px`` as configured.
    """

    exposures_us: tuple[int, ...]
    scan_ms: float
    covered: float
    lit_pixels: int
    too_dark: float
    clipped: float
    dynamic_range: float
    within_budget: bool
    ladder_us: tuple[int, ...]
    intensities: tuple[float, ...] = ()
    dim_floor: float = 1.0
    ambient_limited: float = 0.0
    most_covering_passes: tuple[tuple[int, float], ...] = ()
    most_covering: float = 0.0
    noise_ratio: float = 1.0
    blur: tuple[BlurEstimate, ...] = ()
    edge_blur_px: float | None = None
    edge_blur_now: float | None = None

    def lines(self, time_budget_ms: float) -> list[str]:
        """The plain-words report printed by ``scan3d tune``."""
        ex = ", ".join(str(e) for e in self.exposures_us)
        n = len(self.exposures_us)
        what = f"{n} exposure{'s' if n > 1 else ''}"
        if self.intensities:
            ex += "], sequence.intensities = [" + ", ".join(f"{i:g}" for i in self.intensities)
            what = f"{n} passes, {sum(i < 1.0 for i in self.intensities)} with the projector dimmed"
        out = [
            f"lit pixels: {self.lit_pixels}; their contrast spans 1:{self.dynamic_range:.0f}",
            f"choice: sequence.exposures_us = [{ex}] ({what}): expected scan time "
            f"{self.scan_ms:.0f} ms, {100 * self.covered:.1f} % of the lit pixels in a decodable range",
        ]
        if self.most_covering_passes:
            alt = ", ".join(f"{e}" if i >= 1.0 else f"{e} at {i:g}" for e, i in self.most_covering_passes)
            out.append(f"the most precise of the choices covering within {100 * COVERAGE_TOLERANCE:g} % of the most: "
                       f"predicted code noise {self.noise_ratio:.2f}x that of the most covering one ([{alt}] µs, "
                       f"{100 * self.most_covering:.1f} %)")
        if not self.within_budget:
            out.append(f"no choice brings {100 * TARGET_SHARE:.0f} % of the lit pixels into range within "
                       f"{time_budget_ms:.0f} ms: this is the best that fits; raise --time-budget-ms")
        lost = []
        if self.too_dark >= 5e-4:
            lost.append(f"{100 * self.too_dark:.1f} % too dark even at {max(self.ladder_us)} µs (raise the "
                        "projector's brightness or the camera gain, or bring the part closer)")
        if self.clipped >= 5e-4 and self.dim_floor < 1.0:
            lost.append(f"{100 * self.clipped:.1f} % clipped even at {min(self.ladder_us)} µs with the projector at "
                        f"{self.dim_floor:g} of its intensity (specular highlights: tilt the part)")
        elif self.clipped >= 5e-4:
            lost.append(f"{100 * self.clipped:.1f} % clipped even at {min(self.ladder_us)} µs (specular "
                        "highlights: tilt the part, or use a projector that can dim between passes: "
                        "lightcrafter4500)")
        if self.ambient_limited >= 5e-4:
            lost.append(f"{100 * self.ambient_limited:.1f} % too dark for the ambient light (it clips them before "
                        "the projector's contrast is enough: shade the part from room light)")
        out.append("cannot recover: " + "; ".join(lost) if lost else "cannot recover: nothing")
        out.extend(f"optics: {b.line()}" for b in self.blur)
        now = "" if self.edge_blur_now is None else f" (now {self.edge_blur_now:g})"
        if self.edge_blur_px is not None:
            out.append(f"choice: reconstruction.edge_blur_px = {self.edge_blur_px:g}{now}: the cameras' blur, which "
                       "the albedo-edge correction and its sigma assume")
        else:
            out.append(f"reconstruction.edge_blur_px stays as it is{now}: the probe could not measure the cameras' "
                       "blur on this scene")
        out.append("not measured by the probe: interreflections (a mirror-like face lighting another); the "
                   "decoder's consistency checks drop those pixels")
        return out


def base_exposure_us(cfg: AppConfig) -> float:
    """The exposure the configuration scans with now (µs): the middle of ``sequence.exposures_us``, else the
    first camera's own."""
    if cfg.sequence.exposures_us:
        ex = sorted(cfg.sequence.exposures_us)
        return float(ex[len(ex) // 2])
    name, cam = next(iter(cfg.cameras.items()))
    own = getattr(cam, "exposure_us", None)
    if own is not None:
        return float(own)
    if cam.type == "sim":
        return float(cfg.virtual_rig.imaging.exposure_us)
    raise ConfigError(f"camera {name!r} ({cam.type}): has no exposure_us the scan can set; scan3d tune needs "
                      "a camera whose exposure is set in microseconds (aravis or sim)")


async def probe(cfg: AppConfig, exposures_us: tuple[float, ...]) -> Probe:
    """White and black frames of every configured camera at each exposure (µs) on the configured rig (built,
    opened and closed here)."""
    def build() -> tuple[Rig, tuple[int, int]]:  # the imports too (the decoder's kernels): off the event loop
        from appliance.hardware.registry import build_rig
        from appliance.scan import load_calibration_for

        rig = build_rig(cfg)
        proj = load_calibration_for(cfg, rig).devices["projector"]
        return rig, (proj.width, proj.height)

    rig, size = await asyncio.get_running_loop().run_in_executor(None, build)
    try:
        return await probe_rig(rig, size, exposures_us)
    finally:
        for cam in rig.cameras.values():
            await cam.close()
        await rig.projector.close()


async def probe_rig(rig: Rig, projector_size: tuple[int, int], exposures_us: tuple[float, ...]) -> Probe:
    """White and black frames of every camera of ``rig`` at each exposure (µs).

    The devices are opened (opening is idempotent: an open rig, the service's, is used as it is) and left open;
    the projector is left with the probe's two frames loaded (at full intensity) and the cameras at the last
    exposure, so the caller closes the rig or rebuilds it. A projector that can dim gets one more pass first: the
    shortest exposure at :data:`PROBE_DIM` of its intensity.

    Parameters
    ----------
    rig : Rig
        The cameras and the projector.
    projector_size : (int, int)
        The projector's width and height (px).
    exposures_us : tuple of float
        The probe's exposures (µs).
    """
    from appliance.scan import pixel_format_bits

    seq = Sequence(projector_size[0], projector_size[1], (WhiteFrame(), BlackFrame()))
    white: dict[str, npt.NDArray[np.float64]] = {}
    black: dict[str, npt.NDArray[np.float64]] = {}
    full: dict[str, float] = {}
    bufs: dict[str, npt.NDArray[Any]] = {}
    controls: dict[str, ExposureControl] = {}
    dim = intensity_control(rig.projector)
    passes = [(float(e), 1.0) for e in exposures_us]  # (exposure, intensity), their light ascending
    if dim is not None and exposures_us:
        passes.insert(0, (float(min(exposures_us)), PROBE_DIM))
    for name, cam in rig.cameras.items():
        info = await cam.open()
        bits = pixel_format_bits(info.pixel_format)
        full[name] = float((1 << bits) - 1)
        control = exposure_control(cam)
        if control is None:
            raise HardwareError(f"camera {name!r}: cannot set its exposure between passes; scan3d tune "
                                "needs one that can (sim, aravis, uvc with manual exposure)")
        controls[name] = control
        # a few MB per camera: allocated off the event loop
        bufs[name], white[name], black[name] = await asyncio.to_thread(
            _probe_buffers, len(passes), info.height, info.width, bits)
    await rig.projector.open()
    await rig.projector.load(seq)
    try:
        for k, (exposure, intensity) in enumerate(passes):
            if dim is not None:
                await dim.set_intensity(intensity)
            for name, cam in rig.cameras.items():
                await controls[name].set_exposure(exposure)
                await cam.arm(2, bufs[name])
            await rig.projector.start()
            software = [c for c in rig.cameras.values() if c.needs_software_trigger]
            for i in range(2 if software else 0):
                await asyncio.gather(*(c.trigger(i) for c in software))
            await asyncio.gather(*(c.wait_frames(PROBE_TIMEOUT_S) for c in rig.cameras.values()))
            # the copies into float64 take ~10 ms a megapixel: off the event loop
            await asyncio.to_thread(_store_probe, bufs, white, black, k)
        if dim is not None:
            await dim.set_intensity(1.0)
        blur = await _probe_blur(rig, projector_size, controls, bufs, white, black, full, passes)
    finally:
        if dim is not None:
            await dim.set_intensity(1.0)  # a scan without sequence.intensities does not set it
    return Probe(tuple(e for e, _ in passes), white, black, full, (int(projector_size[0]), int(projector_size[1])),
                 tuple(i for _, i in passes) if dim is not None else (), blur)


async def _probe_blur(rig: Rig, projector_size: tuple[int, int], controls: dict[str, ExposureControl],
                      bufs: dict[str, npt.NDArray[Any]], white: dict[str, npt.NDArray[np.float64]],
                      black: dict[str, npt.NDArray[np.float64]], full: dict[str, float],
                      passes: list[tuple[float, float]]) -> tuple[BlurEstimate, ...]:
    """The optics' blur per camera: :func:`~appliance.procedures.optics_blur.fringe_frames` at the full-intensity
    probe exposure that has the most pixels in range (lit well, not clipped: a bright part clips at the configured
    one), measured against that pass's white and black."""
    full_passes = [k for k, (_, i) in enumerate(passes) if i >= 1.0]
    if not full_passes:
        return ()

    def usable(k: int) -> int:
        return sum(int(np.count_nonzero(in_range(white[n][k], black[n][k], full[n]))) for n in white)

    counts = await asyncio.to_thread(lambda: [usable(k) for k in full_passes])
    k = full_passes[int(np.argmax(counts))]
    seq = Sequence(projector_size[0], projector_size[1], fringe_frames())
    n = len(seq)
    frames = {name: await asyncio.to_thread(np.zeros, (n, *buf.shape[1:]), buf.dtype) for name, buf in bufs.items()}
    await rig.projector.load(seq)
    for name, cam in rig.cameras.items():
        await controls[name].set_exposure(passes[k][0])
        await cam.arm(n, frames[name])
    await rig.projector.start()
    software = [c for c in rig.cameras.values() if c.needs_software_trigger]
    for i in range(n if software else 0):
        await asyncio.gather(*(c.trigger(i) for c in software))
    await asyncio.gather(*(c.wait_frames(PROBE_TIMEOUT_S) for c in rig.cameras.values()))

    def measure() -> tuple[BlurEstimate, ...]:
        got = (estimate(name, frames[name], white[name][k], black[name][k], full[name]) for name in frames)
        return tuple(e for e in got if e is not None)

    return await asyncio.to_thread(measure)


def _probe_buffers(n: int, height: int, width: int, bits: int) -> tuple[npt.NDArray[Any], npt.NDArray[np.float64],
                                                                         npt.NDArray[np.float64]]:
    """A camera's frame buffer for the probe's two frames, and its white and black images per exposure."""
    frames = np.zeros((2, height, width), np.uint8 if bits == 8 else np.uint16)
    return frames, np.zeros((n, height, width)), np.zeros((n, height, width))


def _store_probe(bufs: dict[str, npt.NDArray[Any]], white: dict[str, npt.NDArray[np.float64]],
                 black: dict[str, npt.NDArray[np.float64]], k: int) -> None:
    """Copy each camera's probe frames (white, black) into pass ``k`` of ``white`` / ``black``."""
    for name, buf in bufs.items():
        white[name][k] = buf[0]
        black[name][k] = buf[1]


def choose(pr: Probe, min_contrast_dn: float, frames_per_pass: int, time_budget_ms: float,
           base_us: float, read_noise_dn: float = 2.0, electrons_per_dn: float = 25.0,
           coverage_tolerance: float = COVERAGE_TOLERANCE) -> TuneChoice:
    """The fewest passes that bring :data:`TARGET_SHARE` of the lit pixels into range, the most precise of them.

    A pass is an exposure of the ladder at full intensity or, when the probe could dim the projector, the
    ladder's shortest exposure at an intensity of :data:`DIM_LADDER`. Among the fewest that reach the target, those
    covering within :data:`COVERAGE_TOLERANCE` of the most are compared by the mean code variance they predict for
    the pixels they cover (each pixel from its brightest pass whose white does not clip, the camera noise model of
    :class:`~appliance.reconstruct.uncertainty.CodeNoise`): the most precise, then the quickest, then the one with
    fewest dimmed passes. When none reaches the target within the budget: the most covering that fits, then the
    quickest.

    Parameters
    ----------
    pr : Probe
        The probe's images.
    min_contrast_dn : float
        ``reconstruction.min_contrast_dn`` (8-bit DN; scaled to each camera's bit depth).
    frames_per_pass : int
        Frames of one pass of the configured sequence.
    time_budget_ms : float
        The longest expected capture time allowed (ms).
    base_us : float
        The configured exposure the ladder is relative to (µs).
    read_noise_dn, electrons_per_dn : float
        ``reconstruction.camera_read_noise_dn`` and ``camera_electrons_per_dn``: the noise model that weighs the
        read noise against the shot noise in the predicted precision.
    coverage_tolerance : float
        Share of the lit pixels by which a choice may cover less than the most covering one and still be
        compared by precision (0: the most covering, then the quickest).
    """
    ladder = np.asarray(sorted({round(base_us * f) for f in LADDER_FACTORS}), dtype=np.float64)
    # the passes a choice may take: (exposure µs, intensity); the dimmed ones after, so that ties keep full
    settings = [(float(t), 1.0) for t in ladder]
    if pr.can_dim:
        settings += [(float(ladder[0]), i) for i in DIM_LADDER]
    s_t = np.asarray([t for t, _ in settings])
    s_i = np.asarray([i for _, i in settings])
    masks: list[npt.NDArray[np.int64]] = []
    dark_n = clip_n = ambient_n = 0
    rates: list[npt.NDArray[np.float64]] = []
    pix_c: list[npt.NDArray[np.float64]] = []  # per lit pixel its contrast and ambient rates (DN per µs)
    pix_a: list[npt.NDArray[np.float64]] = []
    fusable: list[npt.NDArray[np.int64]] = []  # per lit pixel the settings the fusion could take it from
    e = np.asarray(pr.exposures_us)
    light = e * (np.asarray(pr.intensities) if pr.intensities else 1.0)  # µs at full intensity, ascending
    for name in pr.white:
        w, b, full = pr.white[name], pr.black[name], pr.full_scale[name]
        scale = (full + 1) / 256.0
        ok = w < CLIP_MARGIN * full  # per probe pass: this pixel's white did not clip
        # the brightest unclipped probe pass of each pixel; -1 where every one clipped
        idx = np.where(ok.any(axis=0), len(e) - 1 - np.argmax(ok[::-1], axis=0), -1)
        k = np.clip(idx, 0, None)
        wk = np.take_along_axis(w, k[None], 0)[0]
        bk = np.take_along_axis(b, k[None], 0)[0]
        c_rate = (wk - bk) / light[k]  # contrast per µs at full intensity
        a_rate = bk / e[k]  # black (ambient) per µs: dimming the projector leaves it
        clipped_all = idx < 0
        # lit: clipped at some probe pass, or with contrast at the brightest
        lit = (idx < len(e) - 1) | (w[-1] - b[-1] >= LIT_CONTRAST * min_contrast_dn * scale)
        need = DECODABLE_CONTRAST * min_contrast_dn * scale
        # per lit pixel and pass (t, i): its contrast and white level (a pixel that clipped in every probe pass
        # has no measured rate: it counts as clipped)
        contrast = c_rate[lit, None] * (s_t * s_i)
        white = a_rate[lit, None] * s_t + contrast
        enough = (contrast >= need) & ~clipped_all[lit, None]
        # decodable: contrast reaches need and white stays below the margin
        bits = _setting_bits(enough & (white < CLIP_MARGIN * full))
        masks.append(bits)
        # the passes the fusion could take the pixel from: its white below full scale (the decoder drops a
        # pixel only where a pattern sample clips, and the samples peak below the white), contrast enough
        fusable.append(_setting_bits(enough & (white < full)))
        none = bits == 0
        too_dark = none & (c_rate[lit] * ladder[-1] < need)  # the brightest pass: the longest, full
        # clipped even in the dimmest pass; the rest reach the contrast only where the ambient light clips them
        dimmest = a_rate[lit] * s_t[0] + c_rate[lit] * s_t[0] * s_i.min() >= CLIP_MARGIN * full
        clipped = none & ~too_dark & (dimmest | clipped_all[lit])
        dark_n += int(too_dark.sum())
        clip_n += int(clipped.sum())
        ambient_n += int((none & ~too_dark & ~clipped).sum())
        rates.append(c_rate[lit & ~clipped_all])
        pix_c.append(c_rate[lit])  # DN of the frames per µs, the noise model's scale
        pix_a.append(a_rate[lit])
    allbits = np.concatenate(masks) if masks else np.zeros(0, np.int64)
    lit_n = int(allbits.size)
    uniq, counts = np.unique(allbits, return_counts=True)
    best: tuple[float, float, int, tuple[int, ...]] | None = None
    within = False
    # the most covering choice when the most precise is another: its passes, coverage, and the noise ratio
    most_covering: tuple[tuple[tuple[int, float], ...], float, float] | None = None
    for n in range(1, MAX_EXPOSURES + 1):
        # (coverage, -time, -dimmed passes, combo) of every combination of n passes that fits the budget
        fits: list[tuple[float, float, int, tuple[int, ...]]] = []
        for combo in itertools.combinations(range(len(settings)), n):
            t_ms = scan_time_ms([float(s_t[i]) for i in combo], frames_per_pass)
            if t_ms > time_budget_ms:
                continue
            m = sum(1 << i for i in combo)
            cov = float(counts[(uniq & m) != 0].sum()) / lit_n if lit_n else 1.0
            fits.append((cov, -t_ms, -sum(i >= ladder.size for i in combo), combo))  # the dimmed after the ladder
        for key in fits:
            if best is None or key[:3] > best[:3]:
                best = key
        if best is not None and best[0] >= TARGET_SHARE:
            within = True
            top = best[0]
            close = [k for k in fits if k[0] >= max(TARGET_SHARE, top - coverage_tolerance)]
            if len(close) > 1:
                var = _predicted_variance(
                    np.concatenate(pix_c) if pix_c else np.zeros(0), np.concatenate(pix_a) if pix_a else np.zeros(0),
                    allbits, np.concatenate(fusable), s_t, s_i, [k[3] for k in close], read_noise_dn,
                    electrons_per_dn)  # fmt: skip
                v_best, pick = min(zip(var.tolist(), close, strict=True),
                                   key=lambda vk: (vk[0], -vk[1][1], -vk[1][2]))  # fmt: skip
                v_first = float(var[close.index(best)])
                if pick != best and v_first > 0 and math.isfinite(v_first):
                    most_covering = (_passes(best[3], s_t, s_i), best[0], math.sqrt(v_best / v_first))
                best = pick
            break
    chosen = sorted(best[3] if best is not None else (), key=lambda i: (s_t[i] * s_i[i], s_t[i]))
    cov = best[0] if best is not None else 0.0
    ex = tuple(int(s_t[i]) for i in chosen)
    levels = tuple(float(s_i[i]) for i in chosen)
    r = np.concatenate(rates) if rates else np.zeros(0)
    r = r[r > 0]
    dr = float(np.percentile(r, 99.9) / np.percentile(r, 0.1)) if r.size else 1.0
    return TuneChoice(ex, scan_time_ms([float(x) for x in ex], frames_per_pass), cov, lit_n,
                      dark_n / lit_n if lit_n else 0.0, clip_n / lit_n if lit_n else 0.0, dr, within,
                      tuple(int(x) for x in ladder), levels if any(i < 1.0 for i in levels) else (),
                      float(s_i.min()), ambient_n / lit_n if lit_n else 0.0, *(most_covering or ((), 0.0, 1.0)))


def _setting_bits(per_setting: npt.NDArray[np.bool_]) -> npt.NDArray[np.int64]:
    """Per pixel its (pixels, settings) flags as one integer, bit ``s`` for setting ``s``."""
    weights = 1 << np.arange(per_setting.shape[1], dtype=np.int64)
    return np.asarray((per_setting * weights).sum(axis=1), np.int64)


def _passes(combo: tuple[int, ...], s_t: npt.NDArray[np.float64],
            s_i: npt.NDArray[np.float64]) -> tuple[tuple[int, float], ...]:
    """A combination's passes as (exposure µs, intensity), their light ascending."""
    order = sorted(combo, key=lambda i: (s_t[i] * s_i[i], s_t[i]))
    return tuple((int(s_t[i]), float(s_i[i])) for i in order)


def _predicted_variance(c_rate: npt.NDArray[np.float64], a_rate: npt.NDArray[np.float64],
                        good_bits: npt.NDArray[np.int64], fused_bits: npt.NDArray[np.int64],
                        s_t: npt.NDArray[np.float64], s_i: npt.NDArray[np.float64], combos: list[tuple[int, ...]],
                        read_noise_dn: float, electrons_per_dn: float) -> npt.NDArray[np.float64]:
    """Per combination of passes the mean code variance (relative units) of the lit pixels it covers.

    The pixels a combination covers are those decodable in one of its passes (``good_bits``, one bit per
    setting); each is decoded from the brightest pass of the combination in which its white does not clip
    (``fused_bits``), as the fusion takes the brightest unclipped pass; its variance there is ``(read var + A /
    e-) / q^2`` with the contrast ``q = c_rate t i`` and the mean level ``A = a_rate t + q / 2``
    (:class:`~appliance.reconstruct.uncertainty.CodeNoise` without the pattern's constant factor). The pixels
    are sampled evenly (at most :data:`MODEL_PIXELS`) and pooled in bins of their rates (1/8 octave of contrast,
    1/2 octave of ambient).
    """
    if not combos:
        return np.zeros(0)
    ok = (c_rate > 0) & (good_bits != 0)
    c, a, g, f = c_rate[ok], np.maximum(a_rate[ok], 0.0), good_bits[ok], fused_bits[ok]
    step = max(1, c.size // MODEL_PIXELS)  # an even sample of the lit pixels bounds the cost on large cameras
    c, a, g, f = c[::step], a[::step], g[::step], f[::step]
    if c.size == 0:
        return np.zeros(len(combos))
    lc = np.floor(np.log2(c) * 8).astype(np.int64)
    la = np.floor(np.log2(a + 1e-9) * 2).astype(np.int64)
    keys = np.stack([lc, la, g, f], axis=1)
    uk, inv, n = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    cm = np.bincount(inv, c) / n  # each bin's mean rates
    am = np.bincount(inv, a) / n
    light = s_t * s_i
    q = cm[:, None] * light[None, :]  # (bins, settings) contrast, DN
    mean = am[:, None] * s_t[None, :] + 0.5 * q
    inv_e = 0.0 if math.isinf(electrons_per_dn) else 1.0 / electrons_per_dn
    var = (read_noise_dn**2 + ROUNDING_VAR_DN2 + mean * inv_e) / (q * q)
    bit = np.arange(len(s_t))[None, :]
    good = ((uk[:, 2:3] >> bit) & 1).astype(bool)
    fused = ((uk[:, 3:4] >> bit) & 1).astype(bool)
    order = np.argsort(light)  # a pixel's pass: the brightest one of the combination it does not clip in
    out = np.empty(len(combos))
    for j, combo in enumerate(combos):
        ranked = [i for i in order if i in combo][::-1]
        v = np.full(len(uk), np.nan)
        for i in ranked:
            take = np.isnan(v) & fused[:, i]
            v[take] = var[take, i]
        has = ~np.isnan(v) & good[:, list(combo)].any(axis=1)
        out[j] = float(np.sum(v[has] * n[has]) / np.sum(n[has])) if has.any() else math.inf
    return out


def scan_time_ms(exposures_us: list[float], frames_per_pass: int) -> float:
    """Expected capture time (ms): each pass shows every frame for its exposure or the frame period."""
    return sum(frames_per_pass * max(e, FRAME_PERIOD_US) for e in exposures_us) / 1000.0


async def tune(cfg: AppConfig, time_budget_ms: float) -> TuneChoice:
    """Probe the configured rig and choose its exposures (see the module docstring)."""
    check_time_budget(time_budget_ms)
    base = base_exposure_us(cfg)
    pr = await probe(cfg, tuple(base * f for f in PROBE_FACTORS))
    return await _choose_for(cfg, pr, time_budget_ms, base)


async def tune_rig(cfg: AppConfig, rig: Rig, projector_size: tuple[int, int], time_budget_ms: float) -> TuneChoice:
    """:func:`tune` on a rig that is already built (the service's, open): probe it, choose (in a thread).

    The rig is left as :func:`probe_rig` leaves it: the caller rebuilds it (or closes it).
    """
    check_time_budget(time_budget_ms)
    base = base_exposure_us(cfg)
    pr = await probe_rig(rig, projector_size, tuple(base * f for f in PROBE_FACTORS))
    return await _choose_for(cfg, pr, time_budget_ms, base)


def check_time_budget(time_budget_ms: float) -> None:
    """Raise :class:`ConfigError` unless ``time_budget_ms`` is a positive, finite number of ms."""
    if not (time_budget_ms > 0 and math.isfinite(time_budget_ms)):
        raise ConfigError(f"scan3d tune: --time-budget-ms = {time_budget_ms}: must be a positive number of ms")


async def _choose_for(cfg: AppConfig, pr: Probe, time_budget_ms: float, base: float) -> TuneChoice:
    seq = build_sequence(cfg.sequence, *pr.projector_size)  # the Gray bits depend on the projector's size
    rc = cfg.reconstruction
    choice = await asyncio.to_thread(choose, pr, rc.min_contrast_dn, len(seq), time_budget_ms, base,
                                     rc.camera_read_noise_dn, rc.camera_electrons_per_dn)
    return dataclasses.replace(choice, blur=pr.blur, edge_blur_px=edge_blur_choice(pr.blur, len(pr.white)),
                               edge_blur_now=float(rc.edge_blur_px))


EDGE_BLUR_FLOOR_PX = 0.05
"""The smallest ``reconstruction.edge_blur_px`` tune writes (0 would turn the albedo-edge correction off, and with
it the HDR fusion's use of pixels beside a clipped one)."""


def edge_blur_choice(blur: tuple[BlurEstimate, ...], cameras: int) -> float | None:
    """``reconstruction.edge_blur_px`` from the probe's blur estimates (camera px, the cameras' mean, two
    decimals); None unless every one of the ``cameras`` told its blur from the projector's."""
    known = [b.camera_px for b in blur if b.camera_px is not None]
    if not known or len(known) < cameras:
        return None
    return max(EDGE_BLUR_FLOOR_PX, round(float(np.mean(known)), 2))


_SEQ_KEY = re.compile(r"^sequence:[ \t]*(#.*)?$")


def _key_line(key: str) -> re.Pattern[str]:
    return re.compile(r"^([ \t]+)" + re.escape(key) + r":.*$")


def _flow(values: tuple[float, ...]) -> str:
    """A YAML flow list: whole numbers as integers, others as Python writes them (exactly)."""
    return "[" + ", ".join(str(int(v)) if float(v).is_integer() else repr(float(v)) for v in values) + "]"


def with_exposures(text: str, exposures_us: tuple[int, ...], intensities: tuple[float, ...] | None = None) -> str:
    """The configuration text with ``sequence.exposures_us`` set, and ``sequence.intensities`` set to
    ``intensities`` or, when None, removed (every pass at the projector's full intensity, which is what the probe
    measured); comments and layout kept where the ``sequence`` section is a block.

    An ``intensities`` list left from an earlier configuration would no longer match the passes (one per
    exposure): the file would be refused.
    """
    keys: dict[str, tuple[float, ...] | None] = {"exposures_us": tuple(exposures_us), "intensities": intensities}
    lines = text.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if _SEQ_KEY.match(ln.rstrip("\r\n"))), None)
    if start is None:
        doc = yaml.safe_load(text) or {}
        if "sequence" in doc:  # a flow-style section: rewritten (its comments are lost)
            seq = dict(doc["sequence"] or {})
            for key, values in keys.items():
                if values is None:
                    seq.pop(key, None)
                else:
                    seq[key] = list(values)
            doc["sequence"] = seq
            return str(yaml.safe_dump(doc, sort_keys=False))
        sep = "" if not text or text.endswith("\n") else "\n"
        body = "".join(f"  {k}: {_flow(v)}\n" for k, v in keys.items() if v is not None)
        return f"{text}{sep}sequence:\n{body}"
    for key, values in keys.items():
        lines = _set_in_block(lines, start, key, None if values is None else _flow(values))
    return "".join(lines)


def with_setting(text: str, section: str, key: str, value: float) -> str:
    """The configuration text with ``section.key`` set to the number ``value``; comments and layout kept where
    the section is a block (a flow-style section is rewritten, its comments lost; a missing one is added)."""
    rendered = str(int(value)) if float(value).is_integer() else repr(float(value))
    header = re.compile(r"^" + re.escape(section) + r":[ \t]*(#.*)?$")
    lines = text.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if header.match(ln.rstrip("\r\n"))), None)
    if start is None:
        doc = yaml.safe_load(text) or {}
        if section in doc:
            doc[section] = {**dict(doc[section] or {}), key: value}
            return str(yaml.safe_dump(doc, sort_keys=False))
        sep = "" if not text or text.endswith("\n") else "\n"
        return f"{text}{sep}{section}:\n  {key}: {rendered}  # chosen by scan3d tune\n"
    return "".join(_set_in_block(lines, start, key, rendered))


def _set_in_block(lines: list[str], start: int, key: str, rendered: str | None) -> list[str]:
    """Set ``key`` to the YAML text ``rendered`` (None: remove it) in the block-style section whose header is
    ``lines[start]``."""
    end = start + 1
    indent = "  "
    while end < len(lines) and (lines[end].startswith((" ", "\t")) or not lines[end].strip()):
        if lines[end].strip() and not lines[end].lstrip().startswith("#"):
            indent = lines[end][: len(lines[end]) - len(lines[end].lstrip())]
        end += 1
    new = [] if rendered is None else [f"{indent}{key}: {rendered}  # chosen by scan3d tune\n"]
    pattern = _key_line(key)
    for i in range(start + 1, end):
        m = pattern.match(lines[i].rstrip("\r\n"))
        if m:
            # a block-style list under the key goes with it ("- 10000" lines, indented or at the key's level)
            key_indent = len(m.group(1))
            j = i + 1
            while j < end:
                body = lines[j].lstrip(" \t")
                ind = len(lines[j]) - len(body)
                if body.strip() and not (ind > key_indent or (ind == key_indent and body.startswith("-"))):
                    break
                j += 1
            while j > i + 1 and not lines[j - 1].strip():  # blank lines after the list stay
                j -= 1
            return lines[:i] + new + lines[j:]
    return lines[: start + 1] + new + lines[start + 1 :]


def apply_choice(path: Path, exposures_us: tuple[int, ...], intensities: tuple[float, ...] = (),
                 edge_blur_px: float | None = None) -> None:
    """Write ``sequence.exposures_us`` and ``sequence.intensities`` into the configuration file (``intensities``
    empty: every pass at full intensity, and the key is taken out) and, when given, ``reconstruction.edge_blur_px``:
    validated first, then written atomically (a running service reloads it as it would an edit over SSH)."""
    text = path.read_text()
    new = with_exposures(text, exposures_us, tuple(intensities) or None)
    if edge_blur_px is not None:
        new = with_setting(new, "reconstruction", "edge_blur_px", edge_blur_px)
    parse_config(new, str(path), path.parent)  # raises ConfigError with the file, line and rule
    write_bytes_atomic(path, new.encode())


async def tune_command(cfg: AppConfig, config_path: Path | None, time_budget_ms: float, apply: bool) -> int:
    """``scan3d tune``: probe, print the choice and, with ``apply``, write it into the configuration file."""
    choice = await tune(cfg, time_budget_ms)
    for line in choice.lines(time_budget_ms):
        print(line)
    if apply:
        if config_path is None:
            raise ConfigError("scan3d tune --apply: no configuration file to write; pass --config FILE")
        apply_choice(config_path, choice.exposures_us, choice.intensities, choice.edge_blur_px)
        said = f"sequence.exposures_us = {list(choice.exposures_us)}"
        if choice.intensities:
            said += f", sequence.intensities = {list(choice.intensities)}"
        if choice.edge_blur_px is not None:
            said += f", reconstruction.edge_blur_px = {choice.edge_blur_px:g}"
        print(f"written: {config_path}: {said}")
    return 0
