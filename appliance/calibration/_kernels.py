"""numba kernels of the calibration numerics."""

from __future__ import annotations

import numpy as np
from numba import njit

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)


@njit(nogil=True, cache=True)
def cholesky_solve(A, B):  # type: ignore[no-untyped-def]
    """Solve ``A X = B`` for symmetric positive definite ``A`` (n, n) and ``B`` (n, k); False if not SPD.

    Small dense systems (a few hundred unknowns): single-threaded, so a busy machine's BLAS threads do not
    slow the refinement down.
    """
    n = A.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False, B.copy()
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / L[j, j]
    X = B.copy()
    for c in range(X.shape[1]):
        for i in range(n):
            t = X[i, c]
            for k in range(i):
                t -= L[i, k] * X[k, c]
            X[i, c] = t / L[i, i]
        for i in range(n - 1, -1, -1):
            t = X[i, c]
            for k in range(i + 1, n):
                t -= L[k, i] * X[k, c]
            X[i, c] = t / L[i, i]
    return True, X
