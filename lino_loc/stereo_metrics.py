"""Quality of a sparse disparity map against ground truth: density, bad-pixel rates, RMSE.

Definitions (all over the pixels where the ground truth is known, i.e. finite and, for PNG
ground truth, non-zero):

- ``density``     = valid disparity pixels / pixels with known ground truth
  (``density_all`` = valid pixels / all pixels of the image is reported too);
- ``bad1``/``bad2`` = share of the *valid* pixels with known ground truth whose absolute
  error exceeds 1 / 2 pixels (Middlebury's bad-pixel rates, restricted to the pixels the
  matcher dared to answer: a sparse map is judged on what it returns, and its density says
  how much it returns);
- ``rmse_px``     = root mean square error over the same pixels.

Ground truth files: ``.npz`` (key ``arr_0``, else the first array), ``.npy`` (float,
non-finite = unknown), or PNG (8- or 16-bit, value / ``png_scale`` = disparity in pixels,
0 = unknown). Unreadable or malformed files raise :class:`LinoLocError` naming the file.

Usage::

    from lino_loc.stereo_metrics import load_disparity_truth, stereo_metrics
    m = stereo_metrics(disp, load_disparity_truth("gt.npz"))
    m.density, m.bad1, m.bad2, m.rmse_px
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel

from lino_loc.errors import LinoLocError


class StereoMetrics(BaseModel):
    """Figures of one disparity map against ground truth (``None`` when undefined)."""

    density: float
    density_all: float
    bad1: float | None
    bad2: float | None
    rmse_px: float | None
    n_pixels: int
    n_known: int
    n_valid: int
    n_evaluated: int


def stereo_metrics(disparity: ArrayLike, truth: ArrayLike) -> StereoMetrics:
    """Density, bad1, bad2 and RMSE of ``disparity`` (NaN = no value) against ``truth`` (NaN/inf = unknown)."""
    d = np.asarray(disparity, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if d.shape != t.shape:
        raise LinoLocError(f"disparity map {d.shape} and ground truth {t.shape} differ in shape")
    valid = np.isfinite(d)
    known = np.isfinite(t)
    ev = valid & known
    n_known = int(known.sum())
    n_ev = int(ev.sum())
    err = np.abs(d[ev] - t[ev])
    return StereoMetrics(
        density=float(n_ev / n_known) if n_known else 0.0,
        density_all=float(valid.sum() / valid.size) if valid.size else 0.0,
        bad1=float((err > 1.0).mean()) if n_ev else None,
        bad2=float((err > 2.0).mean()) if n_ev else None,
        rmse_px=float(np.sqrt(np.mean(err**2))) if n_ev else None,
        n_pixels=int(valid.size),
        n_known=n_known,
        n_valid=int(valid.sum()),
        n_evaluated=n_ev,
    )


def load_disparity_truth(path: str | Path, png_scale: float = 1.0) -> NDArray[np.float32]:
    """Ground-truth disparity in pixels, float32, NaN = unknown (see the module docstring)."""
    p = Path(path)
    if not p.is_file():
        raise LinoLocError(f"{p}: ground truth file not found")
    suffix = p.suffix.lower()
    try:
        if suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                if not z.files:
                    raise LinoLocError(f"{p}: .npz holds no array")
                arr = z["arr_0"] if "arr_0" in z.files else z[z.files[0]]
        elif suffix == ".npy":
            arr = np.load(p, allow_pickle=False)
        elif suffix == ".png":
            if not png_scale > 0:
                raise LinoLocError(f"png scale must be positive, got {png_scale}")
            raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise LinoLocError(f"{p}: not a readable PNG")
            if raw.ndim == 3:
                if not (
                    np.array_equal(raw[..., 0], raw[..., 1])
                    and np.array_equal(raw[..., 1], raw[..., 2])
                ):
                    raise LinoLocError(f"{p}: colour PNG; ground truth must be a single channel")
                raw = raw[..., 0]
            if raw.dtype not in (np.uint8, np.uint16):
                raise LinoLocError(f"{p}: PNG must be 8- or 16-bit, got {raw.dtype}")
            out = raw.astype(np.float32) / np.float32(png_scale)
            out[raw == 0] = np.nan
            return out
        else:
            raise LinoLocError(f"{p}: unknown ground truth format (use .npz, .npy or .png)")
    except LinoLocError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise LinoLocError(f"{p}: cannot read ground truth ({type(exc).__name__}: {exc})") from None
    arr = np.asarray(arr)
    if arr.ndim != 2 or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise LinoLocError(
            f"{p}: ground truth must be a 2-D numeric array, got {arr.dtype} {arr.shape}"
        )
    out = arr.astype(np.float32)
    out[~np.isfinite(out)] = np.nan
    return out


def load_grey(path: str | Path, name: str = "image") -> NDArray[np.uint8]:
    """An 8-bit grey image (colour is converted); LinoLocError naming the file otherwise."""
    p = Path(path)
    if not p.is_file():
        raise LinoLocError(f"{p}: {name} file not found")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise LinoLocError(f"{p}: not a readable image")
    if img.dtype != np.uint8:
        raise LinoLocError(f"{p}: {name} must be 8-bit, got {img.dtype}")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return img
