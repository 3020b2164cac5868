"""lino_loc: the localization method, free of hardware and transport.

Appearance map (PCA of images at known poses, eq. 1), auxiliary particle filter (eq. 2-6),
nearest-neighbour sensor model, active vision by expected entropy, and depth through
sparse disparity maps fused with intensity (eq. 7-8).

Nothing here imports ``drivers`` or ``services`` (checked by import-linter).
"""

__version__ = "0.1.0"
