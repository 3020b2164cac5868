"""The PNG of ``lino-loc map check``: the plan coloured by coverage, ambiguity and leave-out
error (matplotlib, the ``eval`` extra).

:func:`plot_quality` draws one panel per measure of a :class:`lino_loc.map_quality.MapQuality`
over its cells (x east, y north, metres): the heading sectors each cell's views face (0-8),
the share of ambiguous entries per cell, and, when the report has it, the mean leave-out
error per cell. Heading and position holes are outlined in red on the coverage panel.
:func:`matplotlib_missing` says whether the extra is absent (the CLI then prints one line).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from lino_loc.map_quality import MapQuality

DPI = 110


def matplotlib_missing() -> bool:
    """True when matplotlib (the ``eval`` extra) is not installed."""
    return importlib.util.find_spec("matplotlib") is None


def _grid(rows: list[list[float | None]]) -> np.ndarray:
    return np.array([[np.nan if v is None else float(v) for v in r] for r in rows], dtype=float)


def plot_quality(q: MapQuality, out: Path | str, title: str = "") -> Path:
    """Write the PNG to ``out`` and return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    ny, nx = q.shape
    x0, y0 = q.origin
    ext = (x0, x0 + nx * q.cell_m, y0, y0 + ny * q.cell_m)
    panels: list[tuple[str, np.ndarray, str, float | None]] = [
        ("heading sectors faced per cell", np.array(q.sector_count, dtype=float), "viridis", float(len(q.sectors))),
        (f"ambiguous entries (nearest view > {q.thresholds.ambiguous_m:g} m away)", _grid(q.ambiguous_share_grid),
         "magma_r", 1.0),
    ]
    if q.leave_out_grid is not None:
        lo = _grid(q.leave_out_grid)
        panels.append(("mean leave-out error per cell [m]", lo, "inferno_r",
                       float(np.nanmax(lo)) if np.isfinite(lo).any() else 1.0))
    width = max(6.0, min(14.0, 1.0 + nx * 0.45))
    fig, axes = plt.subplots(len(panels), 1, figsize=(width, 1.2 + len(panels) * (0.6 + ny * 0.45)), squeeze=False)
    for ax, (name, data, cmap, vmax) in zip(axes[:, 0], panels, strict=True):
        masked = np.ma.masked_invalid(np.where(np.array(q.sector_count) == 0, np.nan, data))
        im = ax.imshow(masked, origin="lower", extent=ext, cmap=cmap, vmin=0.0, vmax=vmax, interpolation="nearest")
        fig.colorbar(im, ax=ax, fraction=0.03)
        ax.set_title(name, fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    ax0 = axes[0, 0]
    for f in q.findings:
        if f.kind in ("heading_hole", "position_hole"):
            ax0.add_patch(Rectangle((f.x[0], f.y[0]), f.x[1] - f.x[0], f.y[1] - f.y[0], fill=False,
                                    edgecolor="red", linewidth=1.2, linestyle="--" if f.kind == "heading_hole" else "-"))
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=DPI)
    plt.close(fig)
    return out
