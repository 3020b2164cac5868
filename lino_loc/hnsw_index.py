"""Approximate J-nearest search in feature space: a hierarchical navigable small-world graph.

The sensor model's ``index = "hnsw"`` search (lino_loc.sensor_model). HNSW (Malkov and
Yashunin, "Efficient and robust approximate nearest neighbor search using Hierarchical
Navigable Small World graphs", IEEE TPAMI 2020) links every map entry to about ``M``
neighbours on a few layers of a proximity graph and answers a query by a greedy best-first
walk that keeps the ``ef`` best candidates. Its query cost grows about as log N where an
exact search of a large map grows about as N (brute force) or worse than log N in 20
dimensions (a KD-tree); it may miss a true neighbour (recall below 1, measured against exact
search in docs/scale.md). The graph is hnswlib's (the optional extra ``scale``:
``pip install 'lino-loc[scale]'``), imported only when this search is used.

Determinism: the graph is built by one thread from a fixed seed, so the same features give
the same graph and the same answers on every start (a replay gives the same weights).

Building the graph of a large map takes a while (tens of seconds per 100k entries, one
thread), so it can be kept in a cache folder (``cache_dir``): the file
``hnsw-<key>.bin`` with ``key`` the SHA-256 of the features' bytes, shape and dtype and of
the graph's parameters, and beside it ``hnsw-<key>.sha256`` holding the SHA-256 of the
graph file. A cached graph is used only when both files are there and the graph file's hash
matches (a truncated or modified file is rebuilt, never read: hnswlib does not check the
files it loads); both are written atomically (temporary file + rename).

Usage::

    index = HnswIndex.build_or_load(features, cache_dir=Path("/var/lib/lino-loc"))
    idx = index.query(q, j)          # (B, j) int64, approximate J nearest
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lino_loc.atomic_file import atomic_write, temp_name
from lino_loc.errors import LinoLocError

log = logging.getLogger(__name__)

#: Graph degree and build-time candidate list: on the synthetic floor map of 100k entries (20
#: features) ef_construction = 200 doubled the build time of 100 for the same recall
#: (docs/scale.md).
HNSW_M = 16
HNSW_EF_CONSTRUCTION = 100
#: Query-time candidate list: max(HNSW_EF_MIN, HNSW_EF_PER_J * J). At J = 10, ef = 40 gave
#: recall@10 0.99 at 100k entries but 0.97 at 1M, ef = 80 gave 0.999 and 0.996 (docs/scale.md);
#: the query time grows about linearly with ef and stays a tenth of the update's at 80.
HNSW_EF_MIN = 80
HNSW_EF_PER_J = 8
HNSW_SEED = 0
MISSING_EXTRA = "the 'hnsw' J-nearest search needs hnswlib: pip install 'lino-loc[scale]'"


def _hnswlib() -> Any:
    """The hnswlib module, or a one-line LinoLocError naming the extra to install."""
    try:
        import hnswlib
    except ImportError:
        raise LinoLocError(MISSING_EXTRA) from None
    return hnswlib


def features_key(features: NDArray[Any], m: int = HNSW_M, ef_construction: int = HNSW_EF_CONSTRUCTION) -> str:
    """SHA-256 (hex, first 24 digits) of the float32 features' shape and bytes and of the graph
    parameters: the name of a cached graph of exactly these features."""
    f = np.ascontiguousarray(features, dtype=np.float32)
    h = hashlib.sha256(f"hnsw-v1 {f.shape} M={m} efc={ef_construction} seed={HNSW_SEED}\0".encode())
    h.update(memoryview(f).cast("B") if f.size else b"")
    return h.hexdigest()[:24]


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class HnswIndex:
    """An hnswlib graph over N feature vectors (float32, L2), answering J-nearest queries."""

    graph: Any
    n: int
    dim: int
    source: str = "built"  # "built" or "cache": where the graph came from

    @classmethod
    def build(cls, features: NDArray[Any], m: int = HNSW_M, ef_construction: int = HNSW_EF_CONSTRUCTION) -> HnswIndex:
        """The graph of ``features`` (N, d), built by one thread from a fixed seed."""
        hnswlib = _hnswlib()
        f = np.ascontiguousarray(features, dtype=np.float32)
        n, d = f.shape
        graph = hnswlib.Index(space="l2", dim=d)
        graph.init_index(max_elements=max(n, 1), M=m, ef_construction=ef_construction, random_seed=HNSW_SEED)
        graph.set_num_threads(1)
        graph.add_items(f, np.arange(n), num_threads=1)
        return cls(graph, n, d)

    @classmethod
    def build_or_load(cls, features: NDArray[Any], cache_dir: Path | None = None) -> HnswIndex:
        """The graph of ``features``, from ``cache_dir`` when a verified copy is there (see the
        module docstring), else built (and then saved there when ``cache_dir`` is given, the
        folder made if missing). A cache folder that cannot be made or written only logs a
        warning."""
        if cache_dir is None:
            return cls.build(features)
        key = features_key(features)
        path, digest = Path(cache_dir) / f"hnsw-{key}.bin", Path(cache_dir) / f"hnsw-{key}.sha256"
        n, d = np.shape(features)
        if path.is_file() and digest.is_file():
            try:
                ok = digest.read_text().strip() == _file_sha256(path)
            except OSError:
                ok = False
            if ok:
                hnswlib = _hnswlib()
                graph = hnswlib.Index(space="l2", dim=int(d))
                graph.load_index(str(path), max_elements=max(int(n), 1))
                graph.set_num_threads(1)
                if graph.get_current_count() == n:
                    return cls(graph, int(n), int(d), "cache")
            log.warning("%s: cached search graph does not match its map; rebuilding it", path)
        index = cls.build(features)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            index.save(path, digest)
        except OSError as exc:
            log.warning("%s: cannot cache the search graph (%s)", path, exc)
        return index

    def save(self, path: Path, digest: Path) -> None:
        """Write the graph to ``path`` and its SHA-256 to ``digest``, each atomically."""
        tmp = temp_name(path)
        try:
            self.graph.save_index(str(tmp))
            sha = _file_sha256(tmp)
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
        with atomic_write(digest, "w") as fh:
            fh.write(sha + "\n")

    def query(self, q: NDArray[np.float64], j: int) -> NDArray[np.int64]:
        """Indices (B, j), nearest first as far as the graph found them, of the approximate j
        nearest entries to each row of ``q`` (B, d); ``ef`` = max(HNSW_EF_MIN, HNSW_EF_PER_J j)."""
        self.graph.set_ef(max(HNSW_EF_MIN, HNSW_EF_PER_J * j, j))
        labels, _ = self.graph.knn_query(np.asarray(q, dtype=np.float32), k=j, num_threads=1)
        return np.asarray(labels, dtype=np.int64).reshape(q.shape[0], j)

    @property
    def nbytes(self) -> int:
        """Bytes the graph holds in memory (hnswlib's own estimate is not exposed: the size of
        its saved file, which is its memory image)."""
        return int(self.graph.index_file_size())
