"""Do the channels of one view point at the same place? The overlap of two channel mixtures.

The fused sensor model (eq. 8) has one mixture per channel of the view (intensity,
disparity: ``PoseMixture.channels``), each built from that channel's own J nearest map
entries. Two channels that place the camera at different places cannot both be right. This
module measures, per view, how much the two channels' mixtures overlap, in closed form over
the whole pose space, so that it does not depend on the belief.

For mixtures p_a = sum_k a_k phi_k and p_b = sum_l b_l psi_l of the kernels of section 3
(isotropic Gaussian in (x, y) times von Mises in theta; the outlier components left out and
the kernel weights renormalized to sum to one), the L2 inner product is exact:

    <p_a, p_b> = sum_kl a_k b_l N(m_k - m_l; 0, (s_k^2 + s_l^2) I_2)
                 I0(R_kl) / (2 pi I0(kappa_k) I0(kappa_l)),
    R_kl = |kappa_k e^{i mu_k} + kappa_l e^{i mu_l}|

(the normaliser of the product of two kernels, ``lino_loc.fusion._kernel_products``). The
OVERLAP is the cosine of the two densities,

    overlap(p_a, p_b) = <p_a, p_b> / sqrt(<p_a, p_a> <p_b, p_b>)   in [0, 1],

1 for the same mixture (and for mixtures that differ only by a common relabelling of their
components), symmetric, invariant to each channel's ``log_scale`` and outlier weight, and
about exp(-d^2 / (4 s^2)) for two single kernels of equal width s whose positions are d
apart (same heading): channels whose kernels are a few widths apart give an overlap near 0.
A mixture without kernels, or a non-finite result, gives nan (no evidence either way).

Usage::

    o = overlap(mixture.channels["intensity"], mixture.channels["disparity"])
"""

from __future__ import annotations

import math

import numpy as np

from lino_loc.resampling import logsumexp
from lino_loc.sensor_model import LOG_2PI, PoseMixture, log_von_mises_norm


def log_inner(a: PoseMixture, b: PoseMixture) -> float:
    """log <p_a, p_b> of the kernel parts of two mixtures, each renormalized to one (module
    docstring); -inf when they do not overlap at all, nan without kernels."""
    if a.n_components == 0 or b.n_components == 0:
        return math.nan
    la = a.log_weights - logsumexp(a.log_weights)
    lb = b.log_weights - logsumexp(b.log_weights)
    ma, mb = a.poses[:, None, :], b.poses[None, :, :]
    s2 = a.sigma_xy[:, None] ** 2 + b.sigma_xy[None, :] ** 2
    d2 = (ma[..., 0] - mb[..., 0]) ** 2 + (ma[..., 1] - mb[..., 1]) ** 2
    log_xy = -d2 / (2.0 * s2) - (LOG_2PI + np.log(s2))
    ka, kb = a.kappa[:, None], b.kappa[None, :]
    r = np.hypot(ka * np.cos(ma[..., 2]) + kb * np.cos(mb[..., 2]),
                 ka * np.sin(ma[..., 2]) + kb * np.sin(mb[..., 2]))
    log_th = log_von_mises_norm(r) - log_von_mises_norm(ka) - log_von_mises_norm(kb)
    return float(logsumexp((la[:, None] + lb[None, :] + log_xy + log_th).reshape(-1)))


def overlap(a: PoseMixture, b: PoseMixture) -> float:
    """The cosine overlap of two channel mixtures in [0, 1] (module docstring); nan when it
    is not defined."""
    ab, aa, bb = log_inner(a, b), log_inner(a, a), log_inner(b, b)
    if not (math.isfinite(aa) and math.isfinite(bb)) or math.isnan(ab):
        return math.nan
    return min(1.0, math.exp(ab - 0.5 * (aa + bb)))


__all__ = ["log_inner", "overlap"]
