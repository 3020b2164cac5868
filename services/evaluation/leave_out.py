"""Leave-out evaluation of the appearance sensor model on a dataset (paper, eq. 10 and Fig. 5).

Every ``every``-th frame of the dataset (rows 0, K, 2K, ...) is held out; an appearance map
(:func:`lino_loc.appearance_map.build_map`: ``features`` PCA features of the ``preprocess``ed
images) is built from all the other frames. Each held-out image is projected (eq. 1) and its
J nearest map entries in feature space are the ones the sensor model would use. Reported,
over the held-out frames (positions are camera positions on the floor plane, metres):

- ``error_m``: eq. 10, ``e = min_n |r - n|`` over the J map poses (position distance of the
  best of the J to the true pose; :func:`lino_loc.metrics.sensor_model_error`);
- ``top1_error_m``: the position error of the single nearest match;
- ``heading_error_deg``: the heading error of the single nearest match (wrapped);
- ``floor_m``: the distance from the held-out pose to the nearest map pose, the error no
  nearest-neighbour model can beat;
- ``heading_floor_deg``: the heading difference to the map pose nearest in heading (the
  heading error no nearest-neighbour model can beat);
- ``random_m``: the mean distance from the held-out pose to the map poses, i.e. what a
  match drawn at random would give (the chance level).

On a small dataset best-of-J is lenient (J = 10 of 56 map frames is a sixth of the map), so
the top-1 figure is the one to compare with the floor.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from lino_loc.appearance_map import DEFAULT_SIZE, build_map
from lino_loc.dataset import Dataset
from lino_loc.errors import LinoLocError
from lino_loc.metrics import sensor_model_error
from lino_loc.poses import pose_distance, wrap_angle
from lino_loc.sensor_model import NearestNeighbourSensorModel, SensorModelConfig


def _stats(v: np.ndarray, std: bool = True) -> dict[str, float]:
    out = {"mean": float(np.mean(v)), "median": float(np.median(v))}
    if std:
        out["std"] = float(np.std(v))
    return out


def split(n: int, every: int) -> tuple[np.ndarray, np.ndarray]:
    """(map rows, held-out rows): rows 0, K, 2K, ... are held out."""
    if every < 2:
        raise LinoLocError(f"--every {every}: must be at least 2 (every K-th frame is held out)")
    rows = np.arange(n)
    test = rows % every == 0
    return rows[~test], rows[test]


def run(
    dataset: Path | str | Dataset,
    every: int = 5,
    features: int = 20,
    j: int = 10,
    preprocess: str = "none",
    size: tuple[int, int] | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    ds = dataset if isinstance(dataset, Dataset) else Dataset.open(dataset)
    n = len(ds)
    map_rows, test_rows = split(n, every)
    if len(test_rows) == 0 or len(map_rows) < 2:
        raise LinoLocError(f"{ds.root}: {n} frames are too few to hold out every {every}-th")
    if features > len(map_rows) - 1:
        raise LinoLocError(
            f"--features {features}: the map of {len(map_rows)} frames allows at most {len(map_rows) - 1}"
        )
    if not 1 <= j <= len(map_rows):
        raise LinoLocError(f"--j {j}: must be between 1 and the map size {len(map_rows)}")
    if size is None:  # the map builder's working size, or the camera's when that is smaller
        cam = ds.meta.camera
        size = (min(DEFAULT_SIZE[0], cam.width), min(DEFAULT_SIZE[1], cam.height))
    amap = build_map(ds.subset(map_rows), n_features=features, preprocess=preprocess, size=size,  # type: ignore[arg-type]
                     seed=seed, workers=1)
    ch = amap.channels["intensity"]
    mp = np.asarray(amap.poses, dtype=np.float64)
    model = NearestNeighbourSensorModel(mp, np.asarray(ch.features, dtype=np.float64), SensorModelConfig(j=j), j=j)
    truth = ds.poses[test_rows]
    err = np.empty(len(test_rows))
    top1 = np.empty(len(test_rows))
    head = np.empty(len(test_rows))
    floor = np.empty(len(test_rows))
    rand = np.empty(len(test_rows))
    hfloor = np.empty(len(test_rows))
    for k, i in enumerate(test_rows):
        y = ch.project(ds.image(int(i)))
        idx, _ = model.neighbours(y)
        nb = mp[idx[0]]
        t = truth[k]
        err[k] = sensor_model_error(t, nb)
        top1[k] = float(pose_distance(t, nb[0]))
        head[k] = abs(math.degrees(float(wrap_angle(nb[0, 2] - t[2]))))
        d_all = pose_distance(t[None, :], mp)
        floor[k] = float(d_all.min())
        rand[k] = float(d_all.mean())
        hfloor[k] = float(np.degrees(np.min(np.abs(wrap_angle(mp[:, 2] - t[2])))))
    return {
        "dataset": str(ds.root),
        "J": int(j),
        "every": int(every),
        "features": int(features),
        "preprocess": preprocess,
        "size": [int(size[0]), int(size[1])],
        "frames_map": int(len(map_rows)),
        "frames_test": int(len(test_rows)),
        "error_m": _stats(err),
        "top1_error_m": _stats(top1),
        "heading_error_deg": _stats(head, std=False),
        "floor_m": _stats(floor, std=False),
        "random_m": _stats(rand, std=False),
        "heading_floor_deg": _stats(hfloor, std=False),
    }
