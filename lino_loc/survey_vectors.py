"""A survey's images as PCA input vectors: decode, preprocess, area-average (eq. 1's ``z``).

The unit of work of every map build: the local build's loading threads
(:func:`lino_loc.appearance_map.load_vectors`) and the Dask build's tasks
(:mod:`lino_loc.pca_dask`) each turn a block of image files into a block of rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lino_loc.dataset import Dataset
from lino_loc.errors import LinoLocError
from lino_loc.preprocessing import Preprocess, preprocess, to_vector


def vectors_of_files(
    paths: Sequence[Path | str], method: Preprocess, size: tuple[int, int], camera_size: tuple[int, int]
) -> np.ndarray:
    """Read, preprocess and area-average the image files ``paths`` -> (len(paths), w*h) float32
    (eq. 1's ``z``). ``camera_size`` = (width, height): an image of another size is a
    LinoLocError naming the file (area averaging would hide it). One block of
    :func:`load_vectors`, and one task of the Dask build (:mod:`lino_loc.pca_dask`)."""
    w, h = int(size[0]), int(size[1])
    cw, chh = int(camera_size[0]), int(camera_size[1])
    X = np.empty((len(paths), w * h), dtype=np.float32)
    for i, path in enumerate(paths):
        img = Dataset.read_grey(path)
        if img.shape != (chh, cw):
            raise LinoLocError(
                f"{path}: {img.shape[1]}x{img.shape[0]} pixels, the camera of the dataset "
                f"is {cw}x{chh}"
            )
        X[i] = to_vector(preprocess(img, method), (w, h))
    return X
