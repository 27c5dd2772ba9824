"""High dynamic range: one pattern sequence captured at several exposures (or projector intensities), fused
per pixel.

Each exposure is a full pass of the sequence and is decoded on its own (a clipped sample carries no code, see
:mod:`appliance.reconstruct.decode`), so a pixel decodes in every pass where its light is neither clipped nor
too dark. Per pixel the fusion takes the brightest pass that did not clip it, which has the most contrast over
the read noise. Its coordinates, quality (DN of that pass, so the per-point error model still applies) and grey
value are taken whole, or, where that pass found no reliable code, its reason: a darker pass has less signal, so
it is not trusted over the brighter one's verdict. Nothing is averaged across passes, so no pass's bias leaks
into another's.

The neighbours: at a bright-dark edge (albedo 0.95 beside 0.03) the lens blur carries the bright side's light
into the dark pixel, so the dark pixel's code is partly the neighbour's. The reconstruction corrects that from
the white level in one scale across the passes (:func:`radiance`; :mod:`appliance.reconstruct.albedo_edges`),
which knows a neighbour's level from a darker pass where it clipped in the chosen one. Without that correction
(``reconstruction.edge_blur_px: 0``, ``DecodeParams.clean_neighbours``) the fusion takes only a *clean* pass, in
which none of the 8 neighbours clipped either: a clipped neighbour's true level is unknown and can be tens of
times the dark pixel's own. Measured on the dark-and-shiny scene with tune's three exposures: the brightest pass
that did not clip the pixel, uncorrected, left 1.27 % of the points beyond 5 sigma (|err|/sigma RMS 1.96), all
within 1.5 px of such an edge; clean passes 0.10 % (0.96) at 93.4 % complete; corrected, 0 % (0.87) at 98.1 %. A
pixel that decoded only where a neighbour clipped is then ``mixed`` ("next to a clipped pixel"); one every pass
clipped is ``saturated``. The correction is first order in the blur: optics blurrier than
``decode_plan.CORRECTABLE_BLUR_PX`` take clean passes again, over a square of ``CLEAN_SIGMAS`` times the blur
(``DecodeParams.clean_radius``; :func:`_hdr_kernels.clipped_near`): the default scene at 1.5 px blur, 10 and
40 ms, gave 0.34 % beyond 5 sigma (|err|/sigma RMS 5.1) with the 8 neighbours and an edge blur of 0.5 px, 0.10 %
(2.3) corrected at 1.49 px, and 0.05 % (0.89) at 96.9 % complete with clean passes over 5 px.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import replace
from typing import cast

import numpy as np
import numpy.typing as npt

from appliance.errors import DecodeError, PatternError
from appliance.patterns.sequence import Sequence as PatternSequence
from appliance.reconstruct import _hdr_kernels as _k
from appliance.reconstruct.decode import DecodeParams, StreamingDecoder, decode, plan_decode
from appliance.reconstruct.decode_batch import drop_partial_cover
from appliance.reconstruct.decode_plan import DecodePlan
from appliance.reconstruct.decode_stream import needed_frames
from appliance.reconstruct.types import DecodedMaps, Reason


def exposure_passes(keys: Sequence[Hashable], light: Sequence[float]) -> list[tuple[float, list[int]]]:
    """Frame indices of each exposure pass, darkest pass first.

    Parameters
    ----------
    keys : sequence
        Per frame, what identifies its pass (e.g. ``(exposure_us, intensity)``).
    light : sequence of float
        Per frame, its relative light (exposure x intensity); equal within a pass.

    Returns
    -------
    list of (float, list of int)
        Per pass its light and its frame indices in capture order, sorted by light.
    """
    if len(keys) != len(light):
        raise DecodeError(f"exposure passes: {len(keys)} keys for {len(light)} frames: one each")
    passes: dict[Hashable, tuple[float, list[int]]] = {}
    for i, (k, lv) in enumerate(zip(keys, light, strict=True)):
        if not (float(lv) > 0.0 and np.isfinite(lv)):
            raise DecodeError(f"exposure passes: frame {i} has light {lv}: must be a finite number > 0")
        passes.setdefault(k, (float(lv), []))[1].append(i)
    return sorted(passes.values(), key=lambda p: p[0])


def fuse_exposures(
    passes: Sequence[DecodedMaps], clean_radius: int = 1
) -> tuple[DecodedMaps, npt.NDArray[np.uint8]]:
    """Fuse the decodes of one scene's exposure passes, given darkest first.

    Parameters
    ----------
    passes : sequence of DecodedMaps
        One decode per pass, same shape, ordered by increasing light, each with ``reason``.
    clean_radius : int
        ``DecodeParams.fusion_radius``: the clean rule's square (px; 1: the 8 neighbours; 0: no rule, the
        brightest pass that did not clip the pixel itself).

    Returns
    -------
    maps : DecodedMaps
        Per pixel the brightest pass that clipped neither it nor any pixel of its square (``u``, ``v``, ``mask``,
        ``quality`` in that pass's DN, ``levels``; with ``clean_radius`` 0 the brightest that did not clip it),
        and the fused ``reason`` (``MIXED`` where the pixel decoded only in passes with a clipped neighbour:
        undecoded here).
    choice : ndarray, shape (H, W), uint8
        Index of the pass each pixel's result came from (the pass its reason came from where undecoded).
    """
    if not passes:
        raise DecodeError("fuse exposures: no pass given")
    shape = passes[0].shape
    for m in passes:
        if m.shape != shape or m.reason is None or m.levels is None:
            raise DecodeError(f"fuse exposures: every pass needs {shape} maps with reason and levels")
    n = len(passes)
    if n > 255:
        raise DecodeError(f"fuse exposures: {n} passes: at most 255")
    stacks = _PassStacks(
        np.stack([m.u for m in passes]), np.stack([m.v for m in passes]), np.stack([m.mask for m in passes]),
        np.stack([m.quality for m in passes]), np.stack([m.levels for m in passes if m.levels is not None]),
        np.stack([m.reason for m in passes if m.reason is not None]),
        np.stack([m.fringe for m in passes if m.fringe is not None]) if all(m.fringe is not None for m in passes)
        else None,
    )  # fmt: skip
    return stacks.fuse(sorted({s for m in passes for s in m.ignored}), _blend_codes(passes), clean_radius,
                       [m.separated for m in passes])  # fmt: skip


def _blend_codes(passes: Sequence[DecodedMaps]) -> npt.NDArray[np.float32] | None:
    """Every pass's codes of pixels lit by two copies of the pattern, one array (evidence only: a pixel may be
    in several passes' lists)."""
    codes = [m.blend_codes for m in passes if m.blend_codes is not None and len(m.blend_codes)]
    if not codes:
        return None
    return codes[0] if len(codes) == 1 else np.concatenate(codes)


class _PassStacks:
    """Every pass's maps stacked along a first axis (P, ...): the fusion kernels read them in place."""

    def __init__(
        self,
        u: npt.NDArray[np.float32],
        v: npt.NDArray[np.float32],
        mask: npt.NDArray[np.bool_],
        quality: npt.NDArray[np.float32],
        levels: npt.NDArray[np.uint8],
        reason: npt.NDArray[np.uint8],
        fringe: npt.NDArray[np.uint8] | None = None,
    ) -> None:
        self.u, self.v, self.mask, self.quality, self.levels, self.reason = u, v, mask, quality, levels, reason
        self.fringe = fringe

    @classmethod
    def empty(cls, n: int, shape: tuple[int, int]) -> _PassStacks:
        return cls(np.empty((n, *shape), np.float32), np.empty((n, *shape), np.float32),
                   np.empty((n, *shape), np.bool_), np.empty((n, *shape), np.float32),
                   np.empty((n, 2, *shape), np.uint8), np.empty((n, *shape), np.uint8),
                   np.empty((n, *shape), np.uint8))  # fmt: skip

    def maps(self, k: int) -> DecodedMaps:
        """Pass ``k``'s maps as views of the stacks (a decoder's ``out``)."""
        return DecodedMaps(self.u[k], self.v[k], self.mask[k], self.quality[k], levels=self.levels[k],
                           reason=self.reason[k], fringe=None if self.fringe is None else self.fringe[k])  # fmt: skip

    def fuse(
        self, ignored: list[str], blend_codes: npt.NDArray[np.float32] | None = None, clean_radius: int = 1,
        separated: Sequence[npt.NDArray[np.float32] | None] = (),
    ) -> tuple[DecodedMaps, npt.NDArray[np.uint8]]:
        shape = (int(self.u.shape[1]), int(self.u.shape[2]))
        choice = np.empty(shape, np.uint8)
        out = DecodedMaps(
            np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.bool_),
            np.empty(shape, np.float32), ignored=ignored, levels=np.empty((2, *shape), np.uint8),
            reason=np.empty(shape, np.uint8), blend_codes=blend_codes,
        )  # fmt: skip
        assert out.levels is not None and out.reason is not None
        near = np.empty((0, 0, 0), np.uint8)
        if clean_radius > 1:  # optics that blur farther than a pixel: a wider square
            near = np.empty(self.reason.shape, np.uint8)
            _k.clipped_near(self.reason, int(Reason.SATURATED), int(clean_radius), np.empty_like(near), near)
        _k.choose_pass(self.mask, self.reason, int(Reason.SATURATED), int(Reason.DECODED), int(Reason.MIXED),
                       clean_radius > 0, near, choice, out.reason)  # fmt: skip
        _k.gather_pass(choice, out.reason, int(Reason.DECODED), self.mask, self.u, self.v, self.quality,
                       self.levels, out.u, out.v, out.mask, out.quality, out.levels)  # fmt: skip
        if self.fringe is not None:  # the chosen pass's share (0 where the fused pixel is undecoded)
            fringe = np.take_along_axis(self.fringe, choice[None], 0)[0]
            fringe[~out.mask] = 0
            out.fringe = fringe
        out.separated = _fused_separated(separated, choice, out.mask)
        return out, choice


def _fused_separated(
    separated: Sequence[npt.NDArray[np.float32] | None], choice: npt.NDArray[np.uint8], mask: npt.NDArray[np.bool_]
) -> npt.NDArray[np.float32] | None:
    """The fused maps' separated pixels (``DecodedMaps.separated``): each pass's where the fusion took the pixel
    from that pass, row-major."""
    parts = []
    for k, sep in enumerate(separated):
        if sep is None or len(sep) == 0:
            continue
        r, c = sep[:, 0].astype(np.int64), sep[:, 1].astype(np.int64)
        parts.append(sep[(choice[r, c] == k) & mask[r, c]])
    if not parts or sum(len(p) for p in parts) == 0:
        return None
    allsep = np.concatenate(parts)
    w = mask.shape[1]
    order = np.argsort(allsep[:, 0].astype(np.int64) * w + allsep[:, 1].astype(np.int64), kind="stable")
    return np.ascontiguousarray(allsep[order])


def pick_per_pixel(images: Sequence[npt.NDArray[np.generic]], choice: npt.NDArray[np.uint8]) -> npt.NDArray[np.generic]:
    """Per pixel the image of the pass ``choice`` names (e.g. each pass's grey value under white light).

    Parameters
    ----------
    images : sequence of ndarray, shape (H, W)
        One image per pass, same dtype, in the order given to :func:`fuse_exposures`.
    choice : ndarray, shape (H, W), uint8
        From :func:`fuse_exposures`.

    Returns
    -------
    ndarray, shape (H, W)
        The chosen pass's value at every pixel.
    """
    stack = np.stack([np.asarray(im) for im in images])
    picked: npt.NDArray[np.generic] = np.take_along_axis(stack, choice[None].astype(np.intp), axis=0)[0]
    return picked


def radiance(
    greys: Sequence[npt.NDArray[np.uint8]], lights: Sequence[float], top: int = 255
) -> npt.NDArray[np.float32]:
    """White-light level per pixel in one scale across exposure passes (``DecodedMaps.radiance``).

    Parameters
    ----------
    greys : sequence of ndarray, shape (H, W), uint8
        Each pass's grey image under white light (darkest pass first, as ``passes``).
    lights : sequence of float
        Each pass's relative light (exposure x intensity).
    top : int
        The grey value at which a pixel clipped.

    Returns
    -------
    ndarray, shape (H, W), float32
        Per pixel its grey in the brightest pass that did not clip it, times the brightest pass's light over
        that pass's (DN of the brightest pass, beyond 255 where it clipped there); the darkest pass's where
        every pass clipped it.
    """
    if not greys or len(greys) != len(lights):
        raise DecodeError(f"radiance: {len(greys)} grey images for {len(lights)} lights: one per pass, at least one")
    top_light = float(max(lights))
    out = greys[0].astype(np.float32) * np.float32(top_light / float(lights[0]))
    for g, lv in zip(greys[1:], lights[1:], strict=True):
        ok = g < top
        np.multiply(g, np.float32(top_light / float(lv)), out=out, where=ok, casting="unsafe")
    return out


def fused_white(
    maps: DecodedMaps,
    greys: Sequence[npt.NDArray[np.uint8]],
    passes: Sequence[tuple[float, list[int]]],
    choice: npt.NDArray[np.uint8],
) -> npt.NDArray[np.uint8]:
    """A fused capture's grey image; its white level in one scale goes into ``maps.radiance``, and by it the
    edge pixels leave ``maps`` (:func:`appliance.reconstruct.decode_batch.drop_partial_cover`): as the scan and
    the replay both take them.

    Parameters
    ----------
    maps : DecodedMaps
        The fused decode (:func:`fuse_exposures`); ``radiance`` set and edge pixels undecoded in place.
    greys : sequence of ndarray, shape (H, W), uint8
        Each pass's grey image under white light, in the order of ``passes`` (darkest first).
    passes : sequence of (float, list of int)
        Per pass its relative light and frame indices (:func:`decode_passes`, ``HdrStreamingDecoder.passes``).
    choice : ndarray, shape (H, W), uint8
        The pass each pixel came from.

    Returns
    -------
    ndarray, shape (H, W), uint8
        Per pixel the chosen pass's grey (intensity and noise model of its point).
    """
    level = radiance(greys, [light for light, _idx in passes])  # the albedo-edge correction's level too
    maps.radiance = level
    drop_partial_cover(maps, level, choice, len(passes))
    return np.asarray(pick_per_pixel(greys, choice), np.uint8)


def capture_summary(
    exposures: Sequence[tuple[float, float]],
    passes: Sequence[tuple[float, list[int]]],
    choice: npt.NDArray[np.uint8],
    mask: npt.NDArray[np.bool_],
) -> dict[str, object]:
    """What each exposure pass of one camera's capture gave, for the sidecar (JSON-ready).

    Parameters
    ----------
    exposures : sequence of (float, float)
        Per frame of the capture its ``(exposure_us, intensity)``.
    passes : sequence of (float, list of int)
        Per pass (darkest first) its light and frame indices (:func:`exposure_passes`).
    choice : ndarray, shape (H, W), uint8
        The pass each pixel's result came from (:func:`fuse_exposures`).
    mask : ndarray, shape (H, W), bool
        The fused decode's mask.

    Returns
    -------
    dict
        ``passes``: per pass, darkest first, its ``exposure_us`` (µs), ``intensity`` (0-1), ``decoded_pixels``
        (the decoded pixels whose code it gave), ``decoded_share`` (their share of all decoded pixels) and
        ``pixel_share`` (the share of the image whose result, decoded or not, it gave).
    """
    k = len(passes)
    decoded = np.bincount(choice[mask], minlength=k)
    chosen = np.bincount(choice.ravel(), minlength=k)
    total, size = max(int(mask.sum()), 1), max(int(choice.size), 1)
    out = []
    for j, (_light, idx) in enumerate(passes):
        e, i = exposures[idx[0]]
        out.append({"exposure_us": float(e), "intensity": float(i), "decoded_pixels": int(decoded[j]),
                    "decoded_share": round(float(decoded[j]) / total, 6),
                    "pixel_share": round(float(chosen[j]) / size, 6)})  # fmt: skip
    return {"passes": out}


def capture_record(exposures: Sequence[tuple[float, float]], cameras: Mapping[str, object]) -> dict[str, object]:
    """The sidecar's ``extra.hdr`` of a multi-pass capture, the same for a scan and the offline decode of its
    recording.

    Parameters
    ----------
    exposures : sequence of (float, float)
        Per frame of the capture its ``(exposure_us, intensity)``; a pass is the frames sharing one pair.
    cameras : dict
        Per camera what each pass gave (:func:`capture_summary`).

    Returns
    -------
    dict
        ``exposures_us`` (µs, per pass in capture order), ``intensities`` (0-1, only when a pass is dimmed),
        ``frames_per_pass``, ``frames`` and ``cameras``.
    """
    pairs = list(dict.fromkeys(exposures))  # the passes, in capture order
    dimmed = any(i != 1.0 for _e, i in pairs)
    return {"exposures_us": [float(e) for e, _i in pairs],
            **({"intensities": [float(i) for _e, i in pairs]} if dimmed else {}),
            "frames_per_pass": len(exposures) // len(pairs), "frames": len(exposures), "cameras": cameras}  # fmt: skip


def decode_passes(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
    sequence: PatternSequence,
    exposures: Sequence[tuple[float, float]],
    params: DecodeParams,
) -> tuple[DecodedMaps, npt.NDArray[np.uint8], list[tuple[float, list[int]]]]:
    """Decode a multi-exposure frame stack: each pass on its own, then :func:`fuse_exposures`.

    Parameters
    ----------
    frames : ndarray, shape (F, H, W), uint8 or uint16
        One camera's frames in the order of ``sequence``.
    sequence : Sequence
        Every frame of every pass, in capture order.
    exposures : sequence of (float, float)
        Per frame its ``(exposure_us, intensity)``; a pass is the frames sharing one pair.
    params : DecodeParams
        Thresholds (the same for every pass).

    Returns
    -------
    maps : DecodedMaps
        The fused maps.
    choice : ndarray, shape (H, W), uint8
        The pass each pixel came from (index into ``passes``).
    passes : list of (float, list of int)
        Per pass (darkest first) its relative light and its frame indices.

    Raises
    ------
    PatternError
        A pass whose frames cannot be decoded on their own (names the pass).
    """
    passes, plans = _pass_plans(sequence, exposures)
    one_pass = replace(params, partial_cover=False)  # judged on the fused maps (drop_partial_cover)
    decoded = []
    for (_lv, idx), plan in zip(passes, plans, strict=True):
        sub_frames = cast("npt.NDArray[np.uint8] | npt.NDArray[np.uint16]", np.ascontiguousarray(frames[idx]))
        m = decode(sub_frames, plan, one_pass)
        decoded.append(_owned(m))
    fused, choice = fuse_exposures(decoded, params.fusion_radius)
    return fused, choice, passes


def _owned(m: DecodedMaps) -> DecodedMaps:
    """A copy of maps that may be views of the decoder's reused output blocks (the pixels lit by two copies of
    the pattern too: the reconstruction's reflection checks read them, as the streaming fusion's do)."""
    return DecodedMaps(
        m.u.copy(), m.v.copy(), m.mask.copy(), m.quality.copy(), list(m.ignored),
        None if m.levels is None else m.levels.copy(), None if m.reason is None else m.reason.copy(),
        None if m.blend_codes is None else m.blend_codes.copy(), fringe=None if m.fringe is None else m.fringe.copy(),
        separated=None if m.separated is None else m.separated.copy(),
    )  # fmt: skip


def _pass_plans(
    sequence: PatternSequence, exposures: Sequence[tuple[float, float]]
) -> tuple[list[tuple[float, list[int]]], list[DecodePlan]]:
    """The exposure passes of a capture (darkest first, see :func:`exposure_passes`) and each pass's plan."""
    if len(exposures) != len(sequence):
        raise DecodeError(f"exposure passes: {len(exposures)} exposures for {len(sequence)} frames: one per frame")
    keys = [(float(e), float(i)) for e, i in exposures]
    light = [(e if e > 0 else 1.0) * i for e, i in keys]
    passes = exposure_passes(keys, light)
    plans = []
    for lv, idx in passes:
        sub = PatternSequence(sequence.width, sequence.height, tuple(sequence.frames[i] for i in idx))
        try:
            plans.append(plan_decode(sub))
        except PatternError as exc:
            e, i = keys[idx[0]]
            raise PatternError(f"exposure pass exposure_us={e:g} intensity={i:g} (light {lv:g}): {exc}") from exc
    return passes, plans


class HdrStreamingDecoder:
    """Decode a multi-exposure capture as its frames arrive; :meth:`finish` equals :func:`decode_passes`.

    A pass is decoded by a :class:`~appliance.reconstruct.decode.StreamingDecoder` (per-pixel sums and codes); a
    pushed frame updates its pass's state and is not kept (unless ``borrow_frames``). A pass is finished (its
    maps written into preallocated per-pass stacks) by the push that completes it, in the pushing thread, while
    later passes are still being captured, and its decoder then serves the next pass of the same patterns: with
    the passes captured one after another the memory is that of one decoder and the per-pass maps, not of one
    decoder a pass (a frame of a pass that arrives before the one in progress is complete takes another
    decoder; decoders are kept for the next scan). :meth:`finish` then finishes what is left and fuses
    (:func:`fuse_exposures`' kernels on the stacks, no copies).

    Parameters
    ----------
    sequence : Sequence
        Every frame of every pass, in capture order.
    exposures : sequence of (float, float)
        Per frame its ``(exposure_us, intensity)``; a pass is the frames sharing one pair.
    shape : tuple of int
        (H, W) of the camera images.
    dtype : numpy dtype
        ``np.uint8`` or ``np.uint16``.
    params : DecodeParams
        Thresholds (the same for every pass).
    borrow_frames : bool
        See :class:`~appliance.reconstruct.decode.StreamingDecoder`.
    """

    def __init__(
        self,
        sequence: PatternSequence,
        exposures: Sequence[tuple[float, float]],
        shape: tuple[int, int],
        dtype: npt.DTypeLike = np.uint8,
        params: DecodeParams | None = None,
        *,
        borrow_frames: bool = False,
    ) -> None:
        prm = DecodeParams() if params is None else params
        self._clean_radius = prm.fusion_radius
        self.passes, plans = _pass_plans(sequence, exposures)
        self.shape = (int(shape[0]), int(shape[1]))
        self._plans = plans
        # partial cover is judged on the fused maps (drop_partial_cover)
        self._dtype, self._params, self._borrow = dtype, replace(prm, partial_cover=False), borrow_frames
        # passes of the same patterns share decoders: per distinct plan its free decoders
        self._plan_key = [tuple(p.sequence.frames) for p in plans]
        self._free: dict[tuple[object, ...], list[StreamingDecoder]] = {k: [] for k in self._plan_key}
        self._decoders: list[StreamingDecoder | None] = [None] * len(plans)  # the decoder of each pass in progress
        self._free[self._plan_key[0]].append(self._new_decoder(0))  # the first pass's, allocated now
        self._route: list[tuple[int, int]] = [(-1, -1)] * len(sequence)
        for k, (_lv, idx) in enumerate(self.passes):
            for j, i in enumerate(idx):
                self._route[i] = (k, j)
        if len(plans) > 255:
            raise DecodeError(f"HDR streaming decoder: {len(plans)} passes: at most 255")
        self._stacks = _PassStacks.empty(len(plans), self.shape)
        self._out = [self._stacks.maps(k) for k in range(len(plans))]
        self._pushed = [0] * len(plans)
        self._finished = [False] * len(plans)
        self.choice: npt.NDArray[np.uint8] | None = None

    def reset(self) -> None:
        """Forget the frames pushed so far; buffers are kept for the next scan."""
        for k in range(len(self._decoders)):
            self._release(k)
        self._pushed = [0] * len(self._decoders)
        self._finished = [False] * len(self._decoders)
        self.choice = None

    def _new_decoder(self, k: int) -> StreamingDecoder:
        return StreamingDecoder(self._plans[k], self.shape, self._dtype, self._params, borrow_frames=self._borrow)

    def _decoder(self, k: int) -> StreamingDecoder:
        """Pass ``k``'s decoder: the one it has, else a free one of its patterns (reset), else a new one."""
        d = self._decoders[k]
        if d is None:
            free = self._free[self._plan_key[k]]
            if free:
                d = free.pop()
                d.reset()
            else:
                d = self._new_decoder(k)
            self._decoders[k] = d
        return d

    def _release(self, k: int) -> None:
        """Give pass ``k``'s decoder back to its patterns' free list (its frames are no longer read)."""
        d = self._decoders[k]
        if d is not None:
            self._decoders[k] = None
            self._free[self._plan_key[k]].append(d)

    def push(self, index: int, frame: npt.NDArray[np.generic]) -> None:
        """Add frame ``index`` of the whole capture (any order); raises like ``StreamingDecoder.push``."""
        if not 0 <= index < len(self._route):
            raise DecodeError(f"HDR streaming decoder: frame index {index}: must be in 0..{len(self._route) - 1}")
        k, j = self._route[index]
        if self._finished[k]:
            raise DecodeError(f"HDR streaming decoder: frame {index} pushed twice; call reset() between scans")
        self._decoder(k).push(j, frame)
        self._pushed[k] += 1
        if self._pushed[k] == len(self.passes[k][1]):  # the pass is complete: finish it now
            self._finish_pass(k)

    def _finish_pass(self, k: int) -> None:
        self._decoder(k).finish(out=self._out[k])
        self._finished[k] = True
        self._release(k)

    @property
    def held_decoders(self) -> int:
        """How many pass decoders this holds, in use or free (one where the passes arrive one after another)."""
        return sum(d is not None for d in self._decoders) + sum(map(len, self._free.values()))

    @property
    def borrowed(self) -> frozenset[int]:
        """Indices (of the whole capture) of the pushed frames still read from the caller's memory
        (``borrow_frames``); every other pushed frame may be overwritten or released."""
        return frozenset(self.passes[k][1][j] for k, d in enumerate(self._decoders) if d is not None
                         for j in d.borrowed)  # fmt: skip

    @property
    def missing(self) -> list[int]:
        """Indices (of the whole capture) of the frames the decoder still needs."""
        out: list[int] = []
        for k, d in enumerate(self._decoders):
            if self._finished[k]:
                continue
            idx = self.passes[k][1]
            out += [idx[j] for j in (needed_frames(self._plans[k]) if d is None else d.missing)]
        return sorted(out)

    def finish(self) -> DecodedMaps:
        """Finish every pass and fuse them per pixel (:func:`fuse_exposures`); ``choice`` then names the pass
        of each pixel (use :func:`pick_per_pixel` for its grey value).

        Raises
        ------
        DecodeError
            When frames of some pass were not pushed.
        """
        missing = self.missing
        if missing:
            raise DecodeError(
                f"HDR streaming decoder: {len(missing)} frame(s) not pushed (first: {missing[:12]}); push every "
                "frame of every exposure pass before finish()"
            )
        for k, done in enumerate(self._finished):
            if not done:
                self._finish_pass(k)
        fused, self.choice = self._stacks.fuse(sorted({s for o in self._out for s in o.ignored}),
                                               _blend_codes(self._out), self._clean_radius,
                                               [o.separated for o in self._out])  # fmt: skip
        return fused

