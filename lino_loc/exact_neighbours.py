"""The J nearest map entries from a search's candidates, the same whichever search found them.

A J-nearest search (brute force, a KD-tree, an HNSW graph) returns J entries, but not always
the same J: brute force ranks by |f|^2 - 2 f.y + |y|^2, whose round-off differs from the
tree's, and among entries at the same distance (identical map rows: a virtual translation with
no depth to move is its source image again) each search keeps whichever it meets first. Then
the J set, and with it the likelihood, depends on which search ``index = "auto"`` timed faster
on a loaded machine, and a run is not the same to the bit from one start to the next.

:func:`settle` fixes one answer: the search returns J + :data:`MARGIN` candidates; their
squared distances are computed one way, sum_k (f_k - y_k)^2, and they are ranked by distance
and then by index; when the candidates' last distance is within round-off of the J-th (a tie
reaching past the candidates), that query is answered by the exact ranking of every entry.
So the J set is the J entries nearest by sum_k (f_k - y_k)^2, ties to the lowest indices,
whatever the search (for the approximate HNSW graph: up to the entries it misses).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: candidates asked of the search beyond the J kept (round-off between two searches' rankings
#: moves an entry by a rank or two, not more)
MARGIN = 2

#: relative distance within which two squared distances count as a tie (round-off of a
#: 20-term sum of squares is about 1e-15 relative)
TIE_RTOL = 1e-9

#: map entries per block of the exact ranking of every entry
BLOCK = 65536


def settle(features: FloatArray, q: FloatArray, candidates: IntArray, j: int) -> tuple[IntArray, FloatArray]:
    """The ``j`` nearest entries to each query row: ``features`` (N, d) the map, ``q`` (B, d)
    the queries, ``candidates`` (B, m) indices from any search, m >= j (m = min(j + MARGIN, N)
    for the answer to be the search-independent one). Returns (indices (B, j), squared
    distances (B, j)), sorted by distance, ties by index."""
    idx, d2 = _ranked(candidates, _distances(features, q, candidates))
    m = idx.shape[1]
    if m > j:
        for b in np.flatnonzero(_tied(d2[:, m - 1], d2[:, j - 1])):
            idx[b], d2[b] = _every_entry(features, q[b : b + 1], m)
    return np.ascontiguousarray(idx[:, :j]), np.ascontiguousarray(d2[:, :j])


def _tied(d2: FloatArray, ref: FloatArray | float) -> NDArray[np.bool_]:
    """Squared distances ``d2`` no farther than ``ref`` beyond round-off (:data:`TIE_RTOL`)."""
    return d2 <= ref * (1.0 + TIE_RTOL) + np.finfo(np.float64).tiny


def _distances(features: FloatArray, q: FloatArray, idx: IntArray) -> FloatArray:
    """sum_k (f_k - y_k)^2 of the entries ``idx`` (B, m) to the queries ``q`` (B, d)."""
    diff = features[idx] - q[:, None, :]
    return np.einsum("bjk,bjk->bj", diff, diff)


def _ranked(idx: IntArray, d2: FloatArray) -> tuple[IntArray, FloatArray]:
    """``idx`` and ``d2`` (B, m) sorted by distance, ties by index."""
    order = np.lexsort((idx, d2), axis=1)
    return np.take_along_axis(idx, order, axis=1), np.take_along_axis(d2, order, axis=1)


def _every_entry(features: FloatArray, y: FloatArray, m: int) -> tuple[IntArray, FloatArray]:
    """The ``m`` entries nearest to one query ``y`` (1, d) by the exact ranking of all of them:
    every entry's distance (by blocks of :data:`BLOCK` entries, so the work arrays stay
    bounded on large maps), then the m nearest and every entry within round-off of the m-th
    ranked as :func:`settle` ranks its candidates."""
    n = features.shape[0]
    d2 = np.empty(n)
    for lo in range(0, n, BLOCK):
        diff = features[lo : lo + BLOCK] - y[0]
        d2[lo : lo + diff.shape[0]] = np.einsum("nk,nk->n", diff, diff)
    kth = np.partition(d2, m - 1)[m - 1]
    near = np.flatnonzero(_tied(d2, kth))[None, :]
    idx, dist = _ranked(near, _distances(features, y, near))
    return idx[0, :m], dist[0, :m]
