"""Streaming decoding: frames pushed one at a time as a scan captures them; :meth:`StreamingDecoder.finish`
equals :func:`appliance.reconstruct.decode_batch.decode` bit for bit.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from appliance.errors import DecodeError
from appliance.patterns.sequence import Sequence
from appliance.reconstruct import _decode_kernels as _k
from appliance.reconstruct.decode_batch import _outputs, _saturation_and_reasons
from appliance.reconstruct.decode_plan import (
    COEFFICIENT_QUANTUM,
    DEFAULT_PARAMS,
    DecodeParams,
    DecodePlan,
    _as_plan,
    _clip_plan,
    _describe,
    _hist_layout,
    _int_sums,
    _max_value,
    lit_threshold,
)
from appliance.reconstruct.types import DecodedMaps


class StreamingDecoder:
    """Decode frames one at a time, as they arrive; :meth:`finish` equals :func:`decode` bit for bit.

    Every frame does its share of the work in :meth:`push` (a Gray pair when both frames are in, a
    Gray frame without inverse once its reference is in: white and black, or the whole mean phase set;
    a phase step at once). All state is allocated here and reused after :meth:`reset`.

    Parameters
    ----------
    sequence : Sequence or DecodePlan
        What each frame shows.
    shape : tuple of int
        (H, W) of the camera images.
    dtype : numpy dtype
        ``np.uint8`` or ``np.uint16``.
    params : DecodeParams
        Thresholds (``max_value`` gives the significant bits of uint16 data).
    borrow_frames : bool
        The caller keeps every pushed frame unchanged until :meth:`finish` (a scan's frame buffer): the first
        frame of a Gray pair, or a Gray frame waiting for its reference, is kept by reference instead of
        copied, which saves one image per Gray bit (10 MB for 8 bits of 1280x1024).
    """

    def __init__(
        self,
        sequence: Sequence | DecodePlan,
        shape: tuple[int, int],
        dtype: Any = np.uint8,
        params: DecodeParams = DEFAULT_PARAMS,
        *,
        borrow_frames: bool = False,
    ) -> None:
        self.plan = _as_plan(sequence)
        self.params = params
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.uint8, np.uint16):
            raise DecodeError(f"streaming decoder: dtype {self.dtype}: must be uint8 or uint16")
        if len(shape) != 2 or min(shape) < 1:
            raise DecodeError(f"streaming decoder: shape {shape}: must be (height, width) >= 1")
        self.shape = (int(shape[0]), int(shape[1]))
        h, w = self.shape
        t = self.plan.tables
        self._maxval = 255 if self.dtype == np.uint8 else 65535
        # hi/lo: white/black, or running max/min when the sequence has no white/black
        self._hi = np.empty((h, w), self.dtype)
        self._lo = np.empty((h, w), self.dtype)
        self._code = np.empty((2, h, w), np.uint32)
        self._gray_axes = sorted({int(a) for a in t.gray_tab[:, 0]})
        # per-bit contrasts: |pos - neg| of 8-bit pairs fits uint8; a single frame against white and black
        # (|2 f - w - b|, up to 510) or 16-bit data needs uint16
        pairs_only = bool(np.all(t.gray_tab[:, 2:] >= 0)) if len(t.gray_tab) else True
        cst_dtype = np.uint8 if self.dtype == np.uint8 and pairs_only else np.uint16
        self._cst = np.zeros((max(len(t.gray_tab), 1), h, w), cst_dtype)
        nset = len(self.plan.phase)
        # phase sums: int32 in units of the coefficient quantum where no sum can leave int32, else float64;
        # both exact, so the order of the pushes does not matter
        self._int_sums = _int_sums(t, self._maxval)
        sum_dtype = np.int32 if self._int_sums else np.float64
        self._quantum = COEFFICIENT_QUANTUM if self._int_sums else 1.0
        self._ssum = np.empty((max(nset, 1), h, w), sum_dtype)
        self._csum = np.empty((max(nset, 1), h, w), sum_dtype)
        self._mean = frozenset(self.plan.mean_frames) if self.plan.white < 0 else frozenset()
        self._msum = np.empty((h, w) if self._mean else (0, 0), np.int32)
        # role of each frame: ("white"|"black"|"pos"|"neg"|"single"|"phase"|"mean", row in its table)
        self._role: dict[int, tuple[str, int]] = {}
        if self.plan.white >= 0:
            self._role[self.plan.white] = ("white", 0)
            self._role[self.plan.black] = ("black", 0)
        # the first-arrived frame of each Gray pair, or a single Gray frame waiting for its reference
        self._borrow = borrow_frames
        self._pending: dict[int, npt.NDArray[Any]] = {}
        self._pending_index: dict[int, int] = {}  # Gray row -> index of the frame held for it
        for g, (a, bit, pos, neg) in enumerate(t.gray_tab.tolist()):
            del a, bit
            if pos >= 0 and neg >= 0:
                self._role[pos] = ("pos", g)
                self._role[neg] = ("neg", g)
            else:
                self._role[pos if pos >= 0 else neg] = ("single", g)
            if not borrow_frames:
                self._pending[g] = np.empty((h, w), self.dtype)
        for k, idx in enumerate(t.ph_idx.tolist()):
            self._role[idx] = ("phase", k)
        for idx in self._mean:
            self._role.setdefault(idx, ("mean", 0))
        self._ph_set = np.repeat(np.arange(nset), [p.steps for p in self.plan.phase]).astype(np.int64)
        self._pushed: set[int] = set()
        self._waiting: set[int] = set()  # gray rows with one frame stored in _pending
        self._levels_shape = (2, h, w)
        # samples at full scale, per pixel (flags of _decode_kernels.CLIP_*), and which frames set which flag
        self._full = int(_max_value(self.dtype, params))
        self._clip = np.zeros((h, w), np.uint8)
        phase, pairs = _clip_plan(self.plan)
        self._clip_flag = dict(phase)
        del pairs
        self.reset()

    def reset(self) -> None:
        """Forget the frames pushed so far; buffers are kept for the next scan."""
        # the per-bit contrasts need no reset: every Gray row's push overwrites all of its row; an axis without
        # Gray bits is never read, and left untouched its pages stay unmapped (5 MB a 1280x1024 camera)
        for a in self._gray_axes:
            self._code[a].fill(0)
        self._ssum.fill(0)
        self._csum.fill(0)
        self._msum.fill(0)
        self._clip.fill(0)
        if self.plan.white < 0:
            self._hi.fill(0)
            self._lo.fill(self._maxval)
        self._pushed.clear()
        self._waiting.clear()
        if self._borrow:
            self._pending.clear()

    def _reference_ready(self) -> bool:
        """Whether single Gray frames can be thresholded: white and black, or every mean frame, pushed."""
        if self.plan.white >= 0:
            return self.plan.white in self._pushed and self.plan.black in self._pushed
        return bool(self._mean) and self._mean <= self._pushed

    def push(self, index: int, frame: npt.NDArray[Any]) -> None:
        """Add frame ``index`` of the sequence (any order).

        Parameters
        ----------
        index : int
            Position of the frame in the sequence.
        frame : ndarray, shape (H, W), the decoder's dtype
            The camera image.

        Raises
        ------
        DecodeError
            Bad index, shape or dtype, or a frame pushed twice (call :meth:`reset` between scans).
        """
        n = len(self.plan.sequence)
        if not 0 <= index < n:
            raise DecodeError(f"streaming decoder: frame index {index}: must be in 0..{n - 1}")
        img = np.asarray(frame)
        if img.shape != self.shape or img.dtype != self.dtype:
            raise DecodeError(
                f"streaming decoder: frame {index} is {img.shape} {img.dtype}: "
                f"must be {self.shape} {self.dtype}"
            )
        if index in self._pushed:
            raise DecodeError(f"streaming decoder: frame {index} pushed twice; call reset() between scans")
        self._pushed.add(index)
        role = self._role.get(index)
        if role is None:
            return
        img = np.ascontiguousarray(img)
        kind, row = role
        t = self.plan.tables
        if kind in ("white", "black"):
            np.copyto(self._hi if kind == "white" else self._lo, img)
            self._flush_singles()
            return
        if self.plan.white < 0:
            _k.stream_minmax(img, self._hi, self._lo)
        if index in self._mean:
            _k.stream_sum(img, self._msum)
        if kind == "phase":
            _k.mark_clipped(img, self._full, self._clip_flag[index], self._clip)
            s = int(self._ph_set[row])
            if self._int_sums:
                sk, ck = int(t.ph_sin_q[row]), int(t.ph_cos_q[row])
                _k.stream_phase(img, sk, ck, self._ssum[s], self._csum[s])
            else:
                fs, fc = float(t.ph_sin[row]), float(t.ph_cos[row])
                _k.stream_phase(img, fs, fc, self._ssum[s], self._csum[s])
        elif kind == "single":
            if self._reference_ready():
                self._single(row, img)
            else:
                self._keep(row, img, index)
        elif kind in ("pos", "neg"):
            if row in self._waiting:
                a, bit, _, _ = (int(x) for x in t.gray_tab[row])
                other = self._pending[row]
                pos, neg = (img, other) if kind == "pos" else (other, img)
                _k.stream_pair(pos, neg, bit, self._code[a], self._cst[row])
                _k.mark_clipped_pair(pos, neg, self._full, self._pair_flag_of(row), self._clip)
                self._waiting.discard(row)
            else:
                self._keep(row, img, index)
        if index in self._mean:
            self._flush_singles()

    def _pair_flag_of(self, row: int) -> int:
        a = int(self.plan.tables.gray_tab[row, 0])
        return int(_k.CLIP_PAIR_X if a == 0 else _k.CLIP_PAIR_Y)

    def _keep(self, row: int, img: npt.NDArray[Any], index: int) -> None:
        """Hold Gray row ``row``'s frame until its partner (or reference) arrives: a reference or a copy."""
        if self._borrow:
            self._pending[row] = img
        else:
            np.copyto(self._pending[row], img)
        self._pending_index[row] = index
        self._waiting.add(row)

    @property
    def borrowed(self) -> frozenset[int]:
        """Indices of the pushed frames this decoder still reads from the caller's memory (``borrow_frames``);
        every other pushed frame may be overwritten or released."""
        if not self._borrow:
            return frozenset()
        return frozenset(self._pending_index[r] for r in self._waiting)

    def _flush_singles(self) -> None:
        if not self._reference_ready():
            return
        gray_tab = self.plan.tables.gray_tab
        for g in sorted(self._waiting):
            if min(int(gray_tab[g, 2]), int(gray_tab[g, 3])) < 0:  # a single, not a pair
                self._single(g, self._pending[g])
                self._waiting.discard(g)

    def _single(self, g: int, img: npt.NDArray[Any]) -> None:
        a, bit, pos, _ = (int(x) for x in self.plan.tables.gray_tab[g])
        sign = 1 if pos >= 0 else -1
        if self.plan.white >= 0:
            _k.stream_single(img, sign, self._hi, self._lo, bit, self._code[a], self._cst[g])
        else:
            _k.stream_single_mean(img, sign, self._msum, len(self._mean), bit, self._code[a], self._cst[g])

    def _sums(self, s: int, ys: npt.NDArray[np.int64], xs: npt.NDArray[np.int64]) -> tuple[
            npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Phase set ``s``'s accumulated sums at pixels (ys, xs), in real units (see ``ghosts.Sums``)."""
        q = float(self._quantum)
        return self._ssum[s][ys, xs].astype(np.float64) * q, self._csum[s][ys, xs].astype(np.float64) * q

    @property
    def missing(self) -> list[int]:
        """Indices of the frames the decoder still needs."""
        return [i for i in needed_frames(self.plan) if i not in self._pushed]

    def finish(self, *, out: DecodedMaps | None = None) -> DecodedMaps:
        """Final per-pixel step; identical to :func:`decode` on the same frames.

        Raises
        ------
        DecodeError
            When frames the decoder needs were not pushed (names their indices).
        """
        missing = self.missing
        if missing:
            desc = ", ".join(f"{i} ({_describe(self.plan.sequence.frames[i])})" for i in missing[:12])
            more = f" and {len(missing) - 12} more" if len(missing) > 12 else ""
            raise DecodeError(
                f"streaming decoder: {len(missing)} frame(s) not pushed: {desc}{more}; push every frame "
                "of the sequence before finish()"
            )
        out, v_arg = _outputs(self.plan, self.shape, out)
        assert out.levels is not None and out.fringe is not None
        t = self.plan.tables
        shift, nbins = _hist_layout(self.dtype, self.params)
        hist = _k.range_hist(self._hi, self._lo, shift, nbins)
        thr = lit_threshold(hist, self.dtype, self.params)
        _k.stream_finish(
            self._hi, self._lo, self._code, self._cst, t.gray_tab, self._ssum, self._csum, self._quantum,
            t.axis_tab,
            t.ph_tab, t.ph_period, float(self.params.relative_contrast), float(self.params.blend_ratio), float(thr),
            bool(self.params.finest_bit), numba.get_num_threads(), out.u, v_arg, out.mask, out.quality,
            out.levels, out.fringe,
        )  # fmt: skip
        _saturation_and_reasons(out, v_arg, self._clip, self._hi, self._lo, thr, self.dtype, self.params, self.plan,
                                self._sums)  # fmt: skip
        out.ignored = list(self.plan.ignored)
        return out


def needed_frames(plan: DecodePlan) -> list[int]:
    """Indices (in ``plan``'s sequence, ascending) of the frames a decode of ``plan`` reads."""
    need = plan.used + ((plan.white, plan.black) if plan.white >= 0 else ())
    return sorted(set(need))
