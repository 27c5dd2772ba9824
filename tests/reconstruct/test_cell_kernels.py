"""The cell matcher's window fit (``cell_window``) against a direct weighted least-squares fit per cell."""

from __future__ import annotations

import numpy as np

from appliance.reconstruct import _cell_kernels as K


def _raw(ncv: int, ncu: int, seed: int = 3) -> np.ndarray:
    """Cells on a regular lattice (cam0 centroid = 1.7 px per step), a tilted disparity plane with noise,
    some cells unseen, one disparity step (a second surface) in the lower right."""
    rng = np.random.default_rng(seed)
    raw = np.zeros((K.N_RAW, ncv, ncu), np.float32)
    jj, ii = np.mgrid[0:ncv, 0:ncu]
    w = rng.uniform(0.5, 2.0, (ncv, ncu))
    w[rng.random((ncv, ncu)) < 0.1] = 0.0
    d = 40.0 + 0.03 * ii - 0.02 * jj + rng.normal(0.0, 0.05, (ncv, ncu))
    d[(ii > 0.6 * ncu) & (jj > 0.6 * ncv)] += 25.0
    raw[K.RAW_W] = w
    raw[K.RAW_D] = np.where(w > 0, d, 0.0)
    raw[K.RAW_E] = np.where(w > 0, rng.normal(0.2, 0.1, (ncv, ncu)), 0.0)
    raw[K.RAW_HI] = np.where(w > 0, d, -np.inf)
    raw[K.RAW_LO] = np.where(w > 0, d, np.inf)
    raw[K.RAW_X] = 1.7 * ii
    raw[K.RAW_Y] = 1.7 * jj
    return raw


def test_window_fit_is_the_weighted_least_squares_plane_of_its_window() -> None:
    ncv, ncu, radius, span = 37, 53, 2, 3.0
    raw = _raw(ncv, ncu)
    fits = np.empty((ncv * ncu, K.FIT_COLS), np.float32)
    K.cell_window(raw, radius, span, 4, fits)
    w, d, e = (raw[p].astype(np.float64) for p in (K.RAW_W, K.RAW_D, K.RAW_E))
    checked = marked = 0
    for cv in range(ncv):
        for cu in range(ncu):
            f = fits[cv * ncu + cu]
            sl = (slice(max(0, cv - radius), min(ncv, cv + radius + 1)),
                  slice(max(0, cu - radius), min(ncu, cu + radius + 1)))
            ww, dd = w[sl], d[sl]
            if w[cv, cu] == 0.0:
                assert np.isnan(f[0]) and f[5] == 0.0
                continue
            seen = ww > 0
            if dd[seen].max() - dd[seen].min() > span:  # a jump in the window: left to the robust fit
                assert np.isnan(f[0]) and f[5] == -1.0
                marked += 1
                continue
            dv, du = np.mgrid[sl[0], sl[1]]
            a = np.stack([np.ones(seen.sum()), (du - cu)[seen], (dv - cv)[seen]], 1)
            sw = np.sqrt(ww[seen])
            coef, *_ = np.linalg.lstsq(a * sw[:, None], dd[seen] * sw, rcond=None)
            inv = np.linalg.inv(a.T @ (a * ww[seen][:, None]))
            assert abs(f[0] - coef[0]) < 2e-4 * abs(coef[0])
            # lattice gradient -> rectified px: the lattice step is 1.7 px on both axes here
            assert abs(f[1] - coef[1] / 1.7) < 1e-3 and abs(f[2] - coef[2] / 1.7) < 1e-3
            assert abs(f[3] - inv[0, 0]) < 1e-4 * inv[0, 0]
            assert abs(f[4] - (ww[seen] * e[sl][seen]).sum() / ww[seen].sum()) < 1e-4
            assert abs(f[5] - ww[seen].sum()) < 1e-4 * ww[seen].sum()
            checked += 1
    assert checked > 1000 and marked > 20


def test_window_fit_does_not_depend_on_the_chunking() -> None:
    raw = _raw(61, 47, seed=5)
    ref = np.empty((61 * 47, K.FIT_COLS), np.float32)
    K.cell_window(raw, 3, 3.0, 1, ref)
    for nch in (2, 7, 61, 100):
        got = np.empty_like(ref)
        K.cell_window(raw, 3, 3.0, nch, got)
        fitted = np.isfinite(ref[:, 0])  # the other columns of an unfitted cell are not written
        assert np.array_equal(np.isfinite(got[:, 0]), fitted) and fitted.mean() > 0.5
        np.testing.assert_allclose(got[fitted], ref[fitted], rtol=1e-5, atol=1e-5)
        assert np.array_equal(got[~fitted, 5], ref[~fitted, 5])


def test_cell_lookup_matches_integer_arithmetic_and_counts_every_pixel_once() -> None:
    """``_row_cells`` (float32 codes, a vectorised floor division for ku, kv > 1) against plain integer
    arithmetic on the same float32 values; ``cell_sums`` against ``np.add.at`` with those cells."""
    rng = np.random.default_rng(11)
    h, w = 23, 97
    for ku, kv in ((1, 1), (3, 2), (7, 5)):
        origin_u, step_u, origin_v, step_v = -0.25, 1.5, -0.5, 2.0
        ncu, ncv = 700 // ku + 1, 400 // kv + 1
        # stripe centres, coarser stripe centres (on cell boundaries) and a few codes outside the grid
        iu = rng.integers(-3, 703, (h, w))
        u = (origin_u + step_u * (iu + rng.choice([0.0, 0.5], (h, w)))).astype(np.float32)
        v = (origin_v + step_v * rng.integers(-2, 403, (h, w))).astype(np.float32)
        u[rng.random((h, w)) < 0.05] = np.nan
        mask = rng.random((h, w)) < 0.9
        grid = np.array([origin_u, 1.0 / step_u, origin_v, 1.0 / step_v, ku, kv])
        fi = (u - np.float32(origin_u)) * np.float32(1.0 / step_u) + np.float32(0.5)
        fj = (v - np.float32(origin_v)) * np.float32(1.0 / step_v) + np.float32(0.5)
        with np.errstate(invalid="ignore"):
            good = mask & (fi >= 0) & (fj >= 0) & (fi < ncu * ku) & (fj < ncv * kv)
        cu = np.where(good, np.nan_to_num(fi), 0).astype(np.int64) // ku
        cv = np.where(good, np.nan_to_num(fj), 0).astype(np.int64) // kv
        expect = np.where(good, cv * ncu + cu, -1)
        kr = np.empty(w, np.int32)
        for r in range(h):
            K._row_cells(u[r], v[r], mask[r], grid, ncu, ncv, kr)
            assert np.array_equal(kr, expect[r]), (ku, kv, r)
        rect = rng.uniform(0, 100, (h, w, 2)).astype(np.float32)
        n = ncu * ncv
        cnt0, cnt1 = np.empty(n, np.int32), np.empty(n, np.int32)
        acc0, acc1 = np.empty((n, 2), np.float32), np.empty((n, 2), np.float32)
        K.cell_sums(u, v, mask, rect, 1, u, v, mask, rect, 1, grid, ncu, ncv, cnt0, acc0, cnt1, acc1)
        ref_n = np.zeros(n, np.int64)
        ref_a = np.zeros((n, 2))
        sel = expect >= 0
        np.add.at(ref_n, expect[sel], 1)
        np.add.at(ref_a, expect[sel], rect[sel].astype(np.float64))
        assert np.array_equal(cnt0, ref_n) and np.array_equal(cnt1, ref_n)
        assert np.allclose(acc0, ref_a, rtol=1e-5, atol=1e-3) and np.array_equal(acc0, acc1)
        assert int(ref_n.sum()) == int(sel.sum()) > 0.5 * h * w


def test_code_max_is_the_largest_decoded_code_at_least_zero() -> None:
    """code_max orders the codes' float32 bits as integers: the same maxima as numpy on decoded pixels, with
    NaN on undecoded ones, codes below 0, an all-negative or empty mask, and odd shapes."""
    rng = np.random.default_rng(7)
    for h, w in ((37, 53), (1, 1), (64, 1920)):
        u = rng.uniform(-5.0, 1300.0, (h, w)).astype(np.float32)
        v = rng.uniform(-5.0, 800.0, (h, w)).astype(np.float32)
        mask = rng.random((h, w)) < 0.6
        top_u, top_v = float(u.max()), float(v.max())
        u[~mask] = np.nan
        v[~mask] = np.nan
        if h > 1:  # the largest values on undecoded pixels do not count
            u[0, 0], v[0, 0], mask[0, 0] = top_u + 50.0, top_v + 50.0, False
        want = (max(0.0, float(np.max(u[mask], initial=0.0))), max(0.0, float(np.max(v[mask], initial=0.0))))
        assert K.code_max(u, v, mask) == want
        assert K.code_max(u, v, np.zeros_like(mask)) == (0.0, 0.0)
        neg = np.full((h, w), -2.5, np.float32)
        assert K.code_max(neg, neg, np.ones_like(mask)) == (0.0, 0.0)


def test_split_sums_count_a_code_half_way_between_cells_half_to_each() -> None:
    """``cell_sums_split`` against ``np.add.at``: a code half way between two stripe centres (a pixel that
    dropped finest Gray bits) counts half to each of the two cells (a quarter to each of four when it is half
    way on both axes), or all to one when both stripes are in one cell (ku, kv > 1); ``cell_raw`` then weighs
    a cell by whole pixels."""
    rng = np.random.default_rng(12)
    h, w = 29, 83
    origin_u, step_u, origin_v, step_v = -0.25, 1.5, -0.5, 2.0
    for ku, kv in ((1, 1), (2, 2), (3, 2)):
        ncu, ncv = 600 // ku, 300 // kv
        ju = rng.integers(0, ncu * ku - 1, (h, w)) + rng.choice([0.0, 0.5], (h, w))
        jv = rng.integers(0, ncv * kv - 1, (h, w)) + rng.choice([0.0, 0.5], (h, w), p=[0.7, 0.3])
        u = (origin_u + step_u * ju).astype(np.float32)
        v = (origin_v + step_v * jv).astype(np.float32)
        mask = rng.random((h, w)) < 0.9
        rect = rng.uniform(0, 100, (h, w, 2)).astype(np.float32)
        grid = np.array([origin_u, 1.0 / step_u, origin_v, 1.0 / step_v, ku, kv])
        n = ncu * ncv
        ref_n = np.zeros(n)
        ref_a = np.zeros((n, 2))
        for r, c in zip(*np.nonzero(mask), strict=True):
            su = {int(np.floor(ju[r, c])) // ku: 1.0} if ju[r, c] % 1 == 0 else None
            if su is None:
                lo, hi = int(np.floor(ju[r, c])) // ku, int(np.ceil(ju[r, c])) // ku
                su = {lo: 1.0} if lo == hi else {lo: 0.5, hi: 0.5}
            lo, hi = int(np.floor(jv[r, c])) // kv, int(np.ceil(jv[r, c])) // kv
            sv = {lo: 1.0} if lo == hi else {lo: 0.5, hi: 0.5}
            for cu, fu in su.items():
                for cv, fv in sv.items():
                    ref_n[cv * ncu + cu] += fu * fv
                    ref_a[cv * ncu + cu] += fu * fv * rect[r, c].astype(np.float64)
        cnt0, cnt1 = np.empty(n, np.int32), np.empty(n, np.int32)
        acc0, acc1 = np.empty((n, 2), np.float32), np.empty((n, 2), np.float32)
        K.cell_sums_split(u, v, mask, rect, 1, u, v, mask, rect, 1, grid, ncu, ncv, cnt0, acc0, cnt1, acc1)
        np.testing.assert_array_equal(cnt0, ref_n * K.SPLIT_UNIT)
        np.testing.assert_allclose(acc0, ref_a * K.SPLIT_UNIT, rtol=1e-5, atol=1e-2)
        assert np.array_equal(cnt0, cnt1) and np.array_equal(acc0, acc1)
        assert ref_n.sum() == mask.sum()
        raw = np.empty((K.N_RAW, ncv, ncu), np.float32)
        K.cell_raw(cnt0, acc0, cnt1, acc1, ncu, ncv, False, float(K.SPLIT_UNIT), raw)
        seen = ref_n.reshape(ncv, ncu) > 0
        np.testing.assert_allclose(raw[K.RAW_W][seen], 0.5 * ref_n.reshape(ncv, ncu)[seen], rtol=1e-6)
        np.testing.assert_allclose(raw[K.RAW_X][seen], (ref_a[:, 0] / np.maximum(ref_n, 1e-9)).reshape(ncv, ncu)[seen],
                                   rtol=1e-5)  # fmt: skip
