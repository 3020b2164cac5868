"""Fusion of the intensity and disparity sensor models (paper, section 5, eq. 7 and 8).

* Disjunctive (eq. 8, the paper's choice): ``p(y_d, y_i | x) = w_d p_d(x) + w_i p_i(x)``, a
  mixture of the two channel mixtures: the components are concatenated and their log-weights
  shifted by ``log w_d`` and ``log w_i``. Each channel contributes its own J nearest map
  entries (``j_disparity`` and ``j_intensity``, 5 + 5 in the paper's Fig. 5).
* Conjunctive (eq. 7): ``p(y_d, y_i | x) = p_d(x) p_i(x)``. Sampling a product is usually not
  closed form, but here it is: every kernel is an isotropic Gaussian in (x, y) times a von
  Mises density in theta, and both families are closed under products. Gaussian:
  ``N(m_a, s_a^2) N(m_b, s_b^2) = N(m_a - m_b; 0, s_a^2 + s_b^2) N(m, s^2)`` with
  ``s^2 = s_a^2 s_b^2 / (s_a^2 + s_b^2)`` and ``m = (m_a s_b^2 + m_b s_a^2) / (s_a^2 + s_b^2)``;
  von Mises: ``k_a cos(t - mu_a) + k_b cos(t - mu_b) = R cos(t - mu)`` with
  ``R e^{i mu} = k_a e^{i mu_a} + k_b e^{i mu_b}``, so the product is ``VM(mu, R)`` times
  ``2 pi I0(R) / (2 pi I0(k_a) 2 pi I0(k_b))``. The product of a J_a- and a J_b-component
  mixture is therefore an exact J_a * J_b-component mixture (plus the cross terms with the
  uniform outlier components); its normalizer is kept in ``PoseMixture.log_scale`` so that
  ``log_pdf`` equals ``log p_d + log p_i`` (inside the mapped area) and ``sample`` draws
  exactly from the normalized product. When the channels disagree the normalizer is tiny:
  that is the "almost null sensor model" the paper warns about, and the filter's likelihood
  tracking (w_slow / w_fast) sees it.

Usage::

    fused = fuse({"intensity": m_i, "disparity": m_d}, FusionConfig(mode="disjunctive"))
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.fusion_weights import AdaptiveWeightsConfig
from lino_loc.poses import wrap_angle
from lino_loc.resampling import logsumexp
from lino_loc.sensor_model import LOG_2PI, Bounds, PoseMixture, log_von_mises_norm


class FusionConfig(BaseModel):
    """How the intensity and disparity channels are combined (eq. 7 / eq. 8)."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["disjunctive", "conjunctive"] = "disjunctive"
    weights: Literal["fixed", "adaptive"] = Field(
        "fixed", description="disjunctive weights: fixed (w_d, w_i: the paper's) or adaptive (each "
        "channel's recent predictive likelihood, lino_loc/fusion_weights.py)"
    )
    w_d: float = Field(0.5, ge=0.0, description="weight of the disparity channel (eq. 8, fixed weights)")
    w_i: float = Field(0.5, ge=0.0, description="weight of the intensity channel (eq. 8, fixed weights)")
    adaptive: AdaptiveWeightsConfig = Field(default_factory=AdaptiveWeightsConfig)
    j_intensity: int = Field(5, ge=1)
    j_disparity: int = Field(5, ge=1)


def _from_unnormalized(
    poses: np.ndarray,
    log_w: np.ndarray,
    sigma_xy: np.ndarray,
    sigma_theta: np.ndarray,
    outlier_log_w: float,
    bounds: Bounds | None,
) -> PoseMixture:
    """A PoseMixture from unnormalized log-weights; the total goes to ``log_scale``."""
    total = float(logsumexp(np.append(log_w, outlier_log_w)))
    if not math.isfinite(total):
        raise ValueError("fused mixture has no weight")
    return PoseMixture(
        poses,
        log_w - total,
        sigma_xy,
        sigma_theta,
        outlier_log_w - total if math.isfinite(outlier_log_w) else -math.inf,
        bounds,
        total,
    )


def disjunctive(mixtures: list[PoseMixture], weights: list[float]) -> PoseMixture:
    """Eq. 8: sum_c w_c p_c(x) with sum_c w_c = 1 (weights are normalized here).

    The components (and outlier weights) of every channel with w_c > 0 are concatenated with
    their log-weights shifted by log w_c + the channel's ``log_scale``; the total weight goes to
    the result's ``log_scale`` and the outlier uses the first channel's bounds. ValueError for
    no mixtures, a weight count that differs, a negative weight or all weights zero.
    """
    if len(mixtures) != len(weights) or not mixtures:
        raise ValueError("need one weight per mixture")
    w = np.asarray(weights, dtype=np.float64)
    if np.any(w < 0) or w.sum() <= 0:
        raise ValueError("fusion weights must be non-negative and not all zero")
    with np.errstate(divide="ignore"):
        logw = np.log(w / w.sum())
    keep = [(m, lw) for m, lw in zip(mixtures, logw, strict=True) if np.isfinite(lw)]
    poses = np.concatenate([m.poses for m, _ in keep])
    lws = np.concatenate([m.log_weights + lw + m.log_scale for m, lw in keep])
    sxy = np.concatenate([m.sigma_xy for m, _ in keep])
    sth = np.concatenate([m.sigma_theta for m, _ in keep])
    out = float(logsumexp([m.outlier_log_weight + lw + m.log_scale for m, lw in keep]))
    bounds = next((m.bounds for m, _ in keep if m.bounds is not None), None)
    return _from_unnormalized(poses, lws, sxy, sth, out, bounds)


def product(a: PoseMixture, b: PoseMixture) -> PoseMixture:
    """Eq. 7 for two mixtures: the exact (renormalized) product mixture, normalizer in log_scale.

    The outlier components are uniform densities over ``a.bounds`` (``b``'s bounds are assumed
    to be the same area); inside that area ``log_pdf`` of the result equals
    ``a.log_pdf + b.log_pdf`` exactly. Components: the J_a * J_b kernel products
    (:func:`_kernel_products`), then the cross terms with the outliers
    (:func:`_outlier_cross_terms`).
    """
    bounds = a.bounds if a.bounds is not None else b.bounds
    kp_poses, kp_lw, kp_sxy, kp_sth = _kernel_products(a, b)
    poses, lws, sxy, sth = [kp_poses], [kp_lw], [kp_sxy], [kp_sth]
    out = -math.inf
    if bounds is not None:
        out = _outlier_cross_terms(a, b, bounds.log_uniform_density, poses, lws, sxy, sth)
    mix = _from_unnormalized(
        np.concatenate(poses),
        np.concatenate(lws),
        np.concatenate(sxy),
        np.concatenate(sth),
        out,
        bounds,
    )
    return PoseMixture(
        mix.poses,
        mix.log_weights,
        mix.sigma_xy,
        mix.sigma_theta,
        mix.outlier_log_weight,
        mix.bounds,
        mix.log_scale + a.log_scale + b.log_scale,
    )


def _kernel_products(
    a: PoseMixture, b: PoseMixture
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All J_a * J_b products of a kernel of ``a`` and one of ``b`` (row-major in (a, b)):
    poses (J_a J_b, 3), unnormalized log-weights, sigma_xy and sigma_theta (J_a J_b,), by the
    Gaussian and von Mises product formulas of the module docstring.

    A vanishing R (opposite headings, equal kappas) gives a flat theta factor: R is floored
    at 1e-9 so that sigma_theta stays finite (the kernel is then ~uniform in theta).
    """
    ma, mb = a.poses[:, None, :], b.poses[None, :, :]
    sa2, sb2 = a.sigma_xy[:, None] ** 2, b.sigma_xy[None, :] ** 2
    ssum = sa2 + sb2
    dxy2 = (ma[..., 0] - mb[..., 0]) ** 2 + (ma[..., 1] - mb[..., 1]) ** 2
    log_c_xy = -dxy2 / (2.0 * ssum) - (LOG_2PI + np.log(ssum))
    mx = (ma[..., 0] * sb2 + mb[..., 0] * sa2) / ssum
    my = (ma[..., 1] * sb2 + mb[..., 1] * sa2) / ssum
    s_xy = np.sqrt(sa2 * sb2 / ssum)
    ka, kb = a.kappa[:, None], b.kappa[None, :]
    cx = ka * np.cos(ma[..., 2]) + kb * np.cos(mb[..., 2])
    cy = ka * np.sin(ma[..., 2]) + kb * np.sin(mb[..., 2])
    r = np.hypot(cx, cy)
    mth = wrap_angle(np.arctan2(cy, cx))
    log_c_th = log_von_mises_norm(r) - log_von_mises_norm(ka) - log_von_mises_norm(kb)
    r = np.maximum(r, 1e-9)
    log_w = a.log_weights[:, None] + b.log_weights[None, :] + log_c_xy + log_c_th
    return (
        np.stack([mx, my, mth], axis=-1).reshape(-1, 3),
        log_w.reshape(-1),
        s_xy.reshape(-1),
        (1.0 / np.sqrt(r)).reshape(-1),
    )


def _outlier_cross_terms(
    a: PoseMixture,
    b: PoseMixture,
    lu: float,
    poses: list[np.ndarray],
    lws: list[np.ndarray],
    sxy: list[np.ndarray],
    sth: list[np.ndarray],
) -> float:
    """Append the components uniform_a x kernels_b and kernels_a x uniform_b (each present
    when that mixture has an outlier) to the component lists, with ``lu`` the log uniform
    density of the area; return the log-weight of uniform_a x uniform_b."""
    if a.outlier_log_weight > -math.inf:
        poses.append(b.poses)
        lws.append(b.log_weights + a.outlier_log_weight + lu)
        sxy.append(b.sigma_xy)
        sth.append(b.sigma_theta)
    if b.outlier_log_weight > -math.inf:
        poses.append(a.poses)
        lws.append(a.log_weights + b.outlier_log_weight + lu)
        sxy.append(a.sigma_xy)
        sth.append(a.sigma_theta)
    return a.outlier_log_weight + b.outlier_log_weight + lu


def conjunctive(mixtures: list[PoseMixture]) -> PoseMixture:
    """Eq. 7: the product of the channel mixtures (see :func:`product`)."""
    if not mixtures:
        raise ValueError("need at least one mixture")
    out = mixtures[0]
    for m in mixtures[1:]:
        out = product(out, m)
    return out


def fuse(mixtures: dict[str, PoseMixture], config: FusionConfig | None = None) -> PoseMixture:
    """Combine channel mixtures ("intensity", "disparity") as configured (eq. 7 or eq. 8).

    A single channel is returned unchanged. Disjunctive weights are ``w_d`` for
    "disparity", ``w_i`` for "intensity" and 1 for any other name, normalized to sum to one.
    """
    c = config or FusionConfig()
    if len(mixtures) == 1:
        return next(iter(mixtures.values()))
    if c.mode == "conjunctive":
        return conjunctive(list(mixtures.values()))
    weight = {"disparity": c.w_d, "intensity": c.w_i}
    names = list(mixtures)
    return disjunctive([mixtures[n] for n in names], [weight.get(n, 1.0) for n in names])


__all__ = ["FusionConfig", "conjunctive", "disjunctive", "fuse", "product"]
