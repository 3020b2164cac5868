"""Probabilistic PCA with missing data, fitted by EM, and projection of sparse samples.

Sparse disparity maps (paper section 5, Fig. 2) cannot be compressed with standard PCA: many
pixels have no value. Following the paper's reference [11] (Porta, Verbeek, Kroese,
"Enhancing appearance-based robot localization using sparse disparity maps"), which uses
the EM algorithm for PCA (Roweis 1998, "EM algorithms for PCA and SPCA") in its
probabilistic form (Tipping & Bishop 1999, PPCA), each sample contributes only its observed
pixels.

Model: ``x = W z + mu + eps`` with ``z ~ N(0, I_d)``, ``eps ~ N(0, sigma^2 I_D)``. For a
sample n with observed coordinates o (mask ``m_n``):

- E-step: ``M_n = W_o^T W_o + sigma^2 I``, ``E[z_n] = M_n^-1 W_o^T (x_o - mu_o)``,
  ``E[z_n z_n^T] = sigma^2 M_n^-1 + E[z_n] E[z_n]^T``.
- M-step, per pixel j, from the samples that observe it, jointly for ``theta_j = (w_j, mu_j)``
  with the augmented latent ``z~ = (z, 1)``:
  ``theta_j = (sum_n m_nj E[z~ z~^T]_n)^-1 sum_n m_nj x_nj E[z~_n]``;
  ``sigma^2 = sum_nj m_nj E[(x_nj - theta_j^T z~_n)^2] / sum_nj m_nj``.
- Parameter expansion (PX-EM): the latent mean and covariance are re-estimated from the
  E-step moments and folded back into mu and W, so the scale of W converges in a few
  iterations instead of hundreds.

Everything is vectorized: the N (d x d) matrices ``M_n = sum_j m_nj w_j w_j^T`` are one matrix
product of the mask with the D x d(d+1)/2 table of products ``w_jk w_jl``; the D per-pixel
(d+1) x (d+1) systems are one product of the transposed mask with the N x (d+1)(d+2)/2 table
of ``E[z~ z~^T]``; the small systems are solved in batches. The observed-data log-likelihood
(Woodbury / matrix determinant lemma) is tracked for convergence.

After convergence the principal subspace span(W) is given an orthonormal basis ordered by
variance (``components``, like plain PCA: eq. 1's projection rows), and a sample's feature
vector is the posterior mean of its latent computed from its valid pixels alone, written in
that basis: ``y = U^T W E[z | x_o]``. Map features (training maps) and query features are
computed the same way, so they are comparable. Samples with no valid pixel get ``y = 0``
(the prior mean) and are flagged. Pixels never observed get zero loadings and mean 0.

Usage::

    from lino_loc.pca_missing import fit_pca_missing
    model = fit_pca_missing(X, n_components=20, seed=0)   # X: (N, D), NaN = missing
    Y, has_data = model.project(X, return_valid=True)      # (N, 20)
    y = model.project(x_query)                             # (20,)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lino_loc.errors import LinoLocError

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

_LOG_2PI = math.log(2.0 * math.pi)


def _triu(d: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    return np.triu_indices(d)


def _pairs(a: F64, iu: tuple[NDArray[np.intp], NDArray[np.intp]]) -> F64:
    """(..., K) -> (..., P) products a_k a_l for k <= l."""
    return a[..., iu[0]] * a[..., iu[1]]


def _unpack_sym(flat: F64, d: int, iu: tuple[NDArray[np.intp], NDArray[np.intp]]) -> F64:
    """(B, P) upper-triangle entries -> (B, d, d) symmetric matrices."""
    out = np.zeros((flat.shape[0], d, d), dtype=np.float64)
    out[:, iu[0], iu[1]] = flat
    out[:, iu[1], iu[0]] = flat
    return out


def _pack_sym(mats: F64, iu: tuple[NDArray[np.intp], NDArray[np.intp]]) -> F64:
    """(B, d, d) symmetric -> (B, P) upper-triangle entries."""
    return mats[:, iu[0], iu[1]]


def _design(W: F64, mu: F64) -> tuple[F64, F64]:
    """The (D, P + d + 1) and (D, d + 1) right-hand factors of the E-step products."""
    iu = _triu(W.shape[1])
    right_m = np.concatenate([_pairs(W, iu), mu[:, None] * W, (mu * mu)[:, None]], axis=1)
    right_x = np.concatenate([W, mu[:, None]], axis=1)
    return right_m, right_x


def _posterior(
    W: F64,
    mu: F64,
    sigma2: float,
    X0: NDArray,
    mask: NDArray,
    rowcount: F64,
    xx: F64,
    design: tuple[F64, F64] | None = None,
) -> tuple[F64, F64, F64]:
    """Posterior of the latents of samples with missing pixels (the E-step).

    X0: (N, D) data with 0 where missing; mask (N, D) 0/1 of the same dtype; rowcount (N,)
    valid pixels per sample; xx (N,) sum of squares of the valid values per sample.
    Returns E[z] (N, d), M^-1 (N, d, d), and the per-sample observed-data log-likelihood (N,).
    Two matrix products with the (N, D) arrays; the rest is O(N d^3).
    """
    d = W.shape[1]
    iu = _triu(d)
    P = iu[0].size
    dt = X0.dtype
    # mask @ [w_k w_l (k<=l) | mu w | mu^2] and X0 @ [W | mu]
    right_m, right_x = design if design is not None else _design(W, mu)
    gm = np.asarray(mask @ right_m.astype(dt, copy=False), dtype=np.float64)
    gx = np.asarray(X0 @ right_x.astype(dt, copy=False), dtype=np.float64)
    M = _unpack_sym(gm[:, :P], d, iu)
    M[:, np.arange(d), np.arange(d)] += sigma2
    b = gx[:, :d] - gm[:, P : P + d]  # W_o^T (x_o - mu_o)
    r2 = xx - 2.0 * gx[:, d] + gm[:, P + d]  # |x_o - mu_o|^2
    L = np.linalg.cholesky(M)
    eye = np.broadcast_to(np.eye(d), M.shape)
    Linv = np.linalg.solve(L, eye)
    Minv = np.einsum("nji,njk->nik", Linv, Linv)
    Ez = np.einsum("nij,nj->ni", Minv, b)
    # x_o ~ N(mu_o, C), C = W_o W_o^T + sigma^2 I: log|C| by the determinant lemma,
    # r^T C^-1 r = (|r|^2 - b^T M^-1 b) / sigma^2 by Woodbury.
    logdetM = 2.0 * np.log(np.diagonal(L, axis1=1, axis2=2)).sum(1)
    logdet = (rowcount - d) * math.log(sigma2) + logdetM
    quad = (r2 - np.einsum("ni,ni->n", b, Ez)) / sigma2
    ll = -0.5 * (rowcount * _LOG_2PI + logdet + quad)
    ll = np.where(rowcount > 0, ll, 0.0)
    return Ez, Minv, ll


def _basis(W: F64) -> tuple[F64, F64]:
    """Orthonormal basis of span(W) and W's singular values (via QR, cheap for D >> d)."""
    q, r = np.linalg.qr(W)
    return q, np.linalg.svd(r, compute_uv=False)


def _max_angle(q1: F64, q2: F64) -> float:
    """Largest principal angle (radians) between the spans of orthonormal q1 and q2."""
    r = q1 - q2 @ (q2.T @ q1)
    s = np.linalg.norm(r, 2) if r.size else 0.0
    return float(np.arcsin(min(s, 1.0)))


@dataclass
class MissingDataPCA:
    """A fitted PPCA model for data with missing values.

    Attributes
    ----------
    mean : (D,) per-pixel mean (0 for pixels never observed).
    components : (d, D) orthonormal basis of the principal subspace, rows ordered by variance.
    explained_variance : (d,) model variance along each component (``s_k^2 + sigma^2``).
    W : (D, d) loadings of the probabilistic model (zero rows for never-observed pixels).
    sigma2 : noise variance.
    observed_count : (D,) number of training samples in which each pixel was valid.
    log_likelihood : observed-data log-likelihood per observed value, one per EM iteration.
    n_iter, converged : EM iterations run and whether the tolerance was reached.
    """

    mean: F64
    components: F64
    explained_variance: F64
    W: F64
    sigma2: float
    observed_count: NDArray[np.int64]
    log_likelihood: list[float] = field(default_factory=list)
    n_iter: int = 0
    converged: bool = False
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def _projection_factors(self) -> tuple[tuple[F64, F64], F64]:
        key = (id(self.W), id(self.mean), id(self.components))
        if self._cache.get("key") != key:
            self._cache.update(
                key=key,
                design=_design(self.W, self.mean),
                to_feat=self.W.T @ self.components.T,  # (d, d): E[z] -> U^T W E[z]
            )
        return self._cache["design"], self._cache["to_feat"]

    @property
    def n_components(self) -> int:
        return int(self.components.shape[0])

    @property
    def n_features_in(self) -> int:
        return int(self.mean.shape[0])

    def project(
        self, X: ArrayLike, return_valid: bool = False
    ) -> F64 | tuple[F64, NDArray[np.bool_]]:
        """Features of sparse samples from their valid pixels alone.

        ``y = U^T W E[z | x_o]`` with ``E[z | x_o] = (W_o^T W_o + sigma^2 I)^-1 W_o^T (x_o - mu_o)``:
        least squares on the observed rows regularised by sigma^2 (the PPCA posterior mean),
        in the coordinates of ``components``. X: (D,) or (N, D), NaN (or inf) = missing.
        Samples with no valid pixel get zeros; with ``return_valid`` a boolean array (or
        bool for one sample) says which samples had at least one valid pixel.
        """
        a = np.asarray(X, dtype=np.float64)
        single = a.ndim == 1
        if single:
            a = a[None, :]
        if a.ndim != 2 or a.shape[1] != self.n_features_in:
            raise LinoLocError(
                f"sample shape {np.shape(X)} does not match the model's {self.n_features_in} pixels"
            )
        mask = np.isfinite(a)
        design, to_feat = self._projection_factors()
        rowcount = mask.sum(1).astype(np.float64)
        if a.shape[0] <= 8:
            # per-frame path: gather the observed rows (small products, no big BLAS calls)
            d = self.n_components
            Ez = np.zeros((a.shape[0], d))
            for i in range(a.shape[0]):
                o = mask[i]
                Wo = self.W[o]
                M = Wo.T @ Wo
                M[np.diag_indices(d)] += self.sigma2
                Ez[i] = np.linalg.solve(M, Wo.T @ (a[i, o] - self.mean[o]))
        else:
            X0 = np.where(mask, a, 0.0)
            xx = np.einsum("nj,nj->n", X0, X0)
            Ez, _, _ = _posterior(
                self.W, self.mean, self.sigma2, X0, mask.astype(np.float64), rowcount, xx, design
            )
        Y = Ez @ to_feat  # (N, d): U^T W E[z]
        has = rowcount > 0
        Y[~has] = 0.0
        if single:
            return (Y[0], bool(has[0])) if return_valid else Y[0]
        return (Y, has) if return_valid else Y

    @classmethod
    def from_projection(
        cls,
        mean: ArrayLike,
        components: ArrayLike,
        explained_variance: ArrayLike,
        sigma2: float,
    ) -> MissingDataPCA:
        """Rebuild a model (e.g. from a map file) from mean, components, variances, sigma^2.

        The projection only depends on span(W) and W's singular values (it is invariant to
        a rotation of the latent space), so ``W = components^T diag(sqrt(var - sigma^2))``
        gives exactly the features of the fitted model.
        """
        mu = np.asarray(mean, dtype=np.float64)
        comps = np.asarray(components, dtype=np.float64)
        var = np.asarray(explained_variance, dtype=np.float64)
        if comps.ndim != 2 or comps.shape[1] != mu.shape[0] or var.shape != (comps.shape[0],):
            raise LinoLocError(
                f"inconsistent projection: mean {mu.shape}, components {comps.shape}, "
                f"variances {var.shape}"
            )
        if not (sigma2 > 0 and np.all(np.isfinite(comps)) and np.all(np.isfinite(mu))):
            raise LinoLocError(f"bad projection: sigma2 {sigma2} or non-finite arrays")
        W = comps.T * np.sqrt(np.maximum(var - sigma2, 0.0))[None, :]
        observed = np.any(comps != 0.0, axis=0).astype(np.int64)
        return cls(
            mean=mu,
            components=comps,
            explained_variance=var,
            W=W,
            sigma2=float(sigma2),
            observed_count=observed,
        )

    def reconstruct(self, Y: ArrayLike) -> F64:
        """Map features back to pixels: ``mean + Y components``."""
        return self.mean + np.asarray(Y, dtype=np.float64) @ self.components


def _init_subspace(Xc: F64, d: int, rng: np.random.Generator) -> tuple[F64, F64]:
    """Leading d right singular vectors (D, d) and singular values of Xc (mean-imputed, centred).

    Exact SVD for small problems, randomized range finder with power iterations otherwise.
    """
    n, D = Xc.shape
    if min(n, D) <= 600:
        _, s, vt = np.linalg.svd(Xc, full_matrices=False)
        return vt[:d].T, s[:d]
    k = min(d + 15, min(n, D))
    Q = Xc @ rng.standard_normal((D, k))
    for _ in range(4):
        Q, _ = np.linalg.qr(Q)
        Q, _ = np.linalg.qr(Xc.T @ Q)
        Q = Xc @ Q
    Q, _ = np.linalg.qr(Q)
    B = Q.T @ Xc  # (k, D)
    _, s, vt = np.linalg.svd(B, full_matrices=False)
    return vt[:d].T, s[:d]


def fit_pca_missing(
    X: ArrayLike,
    n_components: int,
    *,
    max_iter: int = 200,
    tol: float = 1e-6,
    seed: int = 0,
    subspace_tol: float = 1e-6,
    min_sigma2: float = 1e-9,
    dtype: type = np.float64,
    px_em: bool = True,
) -> MissingDataPCA:
    """Fit probabilistic PCA to (N, D) data with NaN for missing values, by EM.

    Initialised from plain PCA of the mean-imputed data. Stops when the relative change of
    the observed-data log-likelihood (per observed value) falls below ``tol``; or when one
    iteration turns the principal subspace by less than ``subspace_tol`` radians (largest
    principal angle between span(W) before and after) while W's singular values and sigma^2
    change by less than ``10 * subspace_tol`` (relative); or after ``max_iter`` iterations
    (then ``converged`` is False). ``min_sigma2`` is a floor on sigma^2 relative to the
    data's mean observed variance (keeps noiseless data well posed; at least 1e-6 with
    float32). ``dtype`` is the precision of the large (N x D) matrix products: float64
    (default) or float32 (faster, half the memory). ``px_em`` (default on) adds the parameter-expanded M-step (latent mean
    and covariance estimated, then folded back into mu and W; Liu, Rubin & Wu 1998), which
    removes plain EM's very slow convergence of the scale of W when values are missing.
    Deterministic for a given ``seed`` (used only by the randomized initial SVD of large
    problems).
    """
    a = np.asarray(X)
    if a.ndim != 2:
        raise LinoLocError(f"PCA data must be (N, D), got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    n, D = a.shape
    d = int(n_components)
    if not 1 <= d <= min(n, D):
        raise LinoLocError(f"n_components {d} must be between 1 and min(N, D) = {min(n, D)}")
    if dtype not in (np.float64, np.float32):
        raise LinoLocError(f"dtype must be float64 or float32, got {dtype}")
    rng = np.random.default_rng(seed)

    mask_b = np.isfinite(a)
    colcount = mask_b.sum(0)
    if colcount.sum() == 0:
        raise LinoLocError("PCA data has no valid value at all")
    seen = colcount > 0
    X0 = np.where(mask_b, a, 0.0).astype(dtype, copy=False)  # (N, D), 0 where missing
    del a
    mu = np.divide(X0.sum(0, dtype=np.float64), colcount, out=np.zeros(D), where=seen)
    n_obs = float(colcount.sum())

    # --- initialisation: plain PCA of the mean-imputed data (missing = mean)
    Xc = X0 - mu.astype(dtype)
    Xc[~mask_b] = 0.0
    total_var = float(np.einsum("nj,nj->", Xc, Xc, dtype=np.float64) / n_obs)
    # float32 products carry ~1e-7 relative error: keep M_n = W_o^T W_o + sigma^2 I well
    # inside positive definiteness with a larger floor in that precision.
    floor_rel = max(min_sigma2, 1e-6) if dtype == np.float32 else min_sigma2
    sigma2_floor = max(floor_rel * total_var, 1e-300)
    V, s = _init_subspace(Xc, d, rng)
    # ML (1/N) variances: complete data start at the PPCA solution
    lam = s.astype(np.float64) ** 2 / n
    sse = 0.0
    Vt = V.T.astype(dtype)
    for lo in range(0, n, 512):  # residual of the rank-d fit on observed values, by row blocks
        blk = Xc[lo : lo + 512]
        r = blk - (blk @ V.astype(dtype)) @ Vt
        r[~mask_b[lo : lo + 512]] = 0.0
        sse += float(np.einsum("nj,nj->", r, r, dtype=np.float64))
    del Xc, blk, r  # (blk is a view: it would keep Xc's buffer alive)
    sigma2 = max(sse / n_obs, sigma2_floor)
    W = (
        V.astype(np.float64)
        * np.sqrt(np.maximum(lam - sigma2, 1e-3 * lam.max() + sigma2_floor))[None, :]
    )
    W[~seen] = 0.0

    maskf = mask_b.astype(dtype)
    del mask_b
    rowcount = np.asarray(maskf.sum(1, dtype=np.float64))
    active = rowcount > 0
    n_active = int(active.sum())
    xx_rows = np.einsum("nj,nj->n", X0, X0, dtype=np.float64)  # (N,) sum_j m x^2
    xsq_total = float(xx_rows.sum())
    d1 = d + 1
    iu1 = _triu(d1)

    history: list[float] = []
    converged = False
    q_old, sv_old = _basis(W)
    it = 0
    for it in range(1, max_iter + 1):
        # ---- E-step
        Ez, Minv, ll = _posterior(W, mu, sigma2, X0, maskf, rowcount, xx_rows)
        history.append(float(ll.sum() / n_obs))
        # ---- M-step for (w_j, mu_j) with z~ = (z, 1)
        S = sigma2 * Minv + np.einsum("ni,nj->nij", Ez, Ez)  # (N, d, d)
        St = np.empty((n, d1, d1))
        St[:, :d, :d] = S
        St[:, :d, d] = Ez
        St[:, d, :d] = Ez
        St[:, d, d] = 1.0
        A = _unpack_sym(
            np.asarray(maskf.T @ _pack_sym(St, iu1).astype(dtype, copy=False), dtype=np.float64),
            d1,
            iu1,
        )  # (D, d1, d1)
        Zt = np.concatenate([Ez, np.ones((n, 1))], axis=1)
        B = np.asarray(X0.T @ Zt.astype(dtype, copy=False), dtype=np.float64)  # (D, d1)
        A[~seen] = np.eye(d1)
        B[~seen] = 0.0
        theta = np.linalg.solve(A, B[:, :, None])[:, :, 0]
        W_new = theta[:, :d]
        mu_new = theta[:, d]
        sse = xsq_total - float(np.einsum("ji,ji->", theta, B))
        sigma2_new = max(sse / n_obs, sigma2_floor)
        if px_em and n_active > 0:
            # PX-EM (Liu, Rubin & Wu 1998): estimate the latent mean m and covariance C in the
            # expanded model z ~ N(m, C), then map back to z ~ N(0, I): mu += W m, W <- W chol(C).
            # Same fixed points, likelihood still non-decreasing; removes EM's slow drift of
            # the scale of W at high signal-to-noise.
            m_z = Ez[active].sum(0) / n_active
            C = S[active].sum(0) / n_active - np.outer(m_z, m_z)
            try:
                Lc = np.linalg.cholesky(C)
            except np.linalg.LinAlgError:
                Lc = None
            if Lc is not None:
                mu_new = mu_new + W_new @ m_z
                W_new = W_new @ Lc

        q_new, sv_new = _basis(W_new)
        dangle = _max_angle(q_old, q_new)
        dscale = float(np.max(np.abs(sv_new - sv_old) / np.maximum(sv_new, 1e-300)))
        s2_change = abs(sigma2_new - sigma2) / sigma2
        q_old, sv_old = q_new, sv_new
        W, mu = W_new, mu_new
        sigma2 = sigma2_new
        log.debug(
            "EM-PCA iter %d ll/obs %.8g sigma2 %.4g dangle %.2e dscale %.2e",
            it,
            history[-1],
            sigma2,
            dangle,
            dscale,
        )
        if len(history) >= 2:
            rel = abs(history[-1] - history[-2]) / max(abs(history[-2]), 1e-12)
            settled = dangle < subspace_tol and max(dscale, s2_change) < 10 * subspace_tol
            if rel < tol or settled:
                converged = True
                break
    if not converged:
        log.info("EM-PCA stopped after max_iter=%d iterations without reaching the tolerance", it)

    W[~seen] = 0.0
    mu[~seen] = 0.0
    # ---- orthonormal basis of span(W), ordered by variance (like plain PCA)
    U, sv, _ = np.linalg.svd(W, full_matrices=False)  # U (D, d)
    comps = U.T.copy()
    # deterministic signs: the largest |loading| of each component is positive
    big = np.argmax(np.abs(comps), axis=1)
    signs = np.sign(comps[np.arange(d), big])
    signs[signs == 0] = 1.0
    comps *= signs[:, None]
    comps[:, ~seen] = 0.0
    return MissingDataPCA(
        mean=mu,
        components=comps,
        explained_variance=sv**2 + sigma2,
        W=W,
        sigma2=float(sigma2),
        observed_count=colcount.astype(np.int64),
        log_likelihood=history,
        n_iter=it,
        converged=converged,
    )


def plain_pca(X: ArrayLike, n_components: int) -> tuple[F64, F64, F64]:
    """Plain PCA of complete data: (mean (D,), components (d, D), variances (d,)). For checks."""
    a = np.asarray(X, dtype=np.float64)
    if not np.isfinite(a).all():
        raise LinoLocError("plain PCA needs complete data (no NaN); use fit_pca_missing")
    mu = a.mean(0)
    _, s, vt = np.linalg.svd(a - mu, full_matrices=False)
    return mu, vt[:n_components], s[:n_components] ** 2 / max(a.shape[0] - 1, 1)
