"""Probabilistic PCA with missing data, fitted by EM as a MAP estimate, and projection of sparse samples.

Sparse disparity maps (paper section 5, Fig. 2) cannot be compressed with standard PCA: many
pixels have no value. Following the paper's reference [11] (Porta, Verbeek, Kroese,
"Enhancing appearance-based robot localization using sparse disparity maps"), which uses
the EM algorithm for PCA (Roweis 1998, "EM algorithms for PCA and SPCA") in its
probabilistic form (Tipping & Bishop 1999, PPCA), each sample contributes only its observed
pixels.

Model: ``x = W z + mu + eps`` with ``z ~ N(0, I_d)``, ``eps ~ N(0, sigma^2 I_D)``, so a
sample's observed pixels o (mask ``m_n``) are ``x_o ~ N(mu_o, C_oo)``, ``C = W W^T + sigma^2 I``.

Objective (the log posterior, up to a constant). With values missing in blocks the
likelihood alone is nearly flat along whole ridges (covariances between pixels rarely or
never observed together are barely constrained, W's scale can keep growing): ML EM creeps
along them for hundreds of iterations and fits of nearly equal likelihood differ in their
features. A weak conjugate prior on the model covariance makes the answer well defined::

    L(W, mu, sigma^2) = sum_n log N(x_n,o | mu_o, C_oo)                  (the data)
                        + nu * log N_S(C)                                 (the prior)
    log N_S(C) = -1/2 (D log 2 pi + log|C| + tr(C^-1 S))

``S`` is the data's pairwise-available covariance (``S_jk`` averaged over the samples that
observe both j and k, 0 for pairs never seen together; D counts the pixels observed at
least once) and ``nu = prior_weight * N`` (default 0.1 N): the prior is the likelihood of
nu *complete* pseudo-samples of second moment S, an inverse-Wishart-type prior on C whose
mode is PPCA of S (Tipping & Bishop's closed form). It fills in what the data leave
undetermined and elsewhere weighs a tenth as much as the data; ``prior_weight = 0`` is the ML fit
(flat prior). On complete data ``S`` is the sample covariance, and the MAP subspace is
PCA's for every nu. mu and sigma^2 have flat priors. An available-case covariance need not
be positive semi-definite; where the mean of its eigenvalues beyond the d-th is not
positive the prior is improper (the objective grows without bound as sigma^2 -> 0), and
those eigenvalues are raised just enough to make it proper (:func:`_proper_shift`; S is
unchanged otherwise).

EM for L (exact: the pseudo-samples are complete data of the same model):

- E-step: ``M_n = W_o^T W_o + sigma^2 I``, ``E[z_n] = M_n^-1 W_o^T (x_o - mu_o)``,
  ``E[z_n z_n^T] = sigma^2 M_n^-1 + E[z_n] E[z_n]^T``; for the pseudo-samples (centred,
  complete) ``E[z z^T] = sigma^2 M^-1 + M^-1 W^T S W M^-1``, ``E[x z^T] = S W M^-1`` with
  ``M = W^T W + sigma^2 I`` (O(D^2 d)).
- M-step, per pixel j, from the samples that observe it and the nu pseudo-samples, jointly
  for ``theta_j = (w_j, mu_j)`` with the augmented latent ``z~ = (z, 1)``:
  ``theta_j = (sum_n m_nj E[z~ z~^T]_n + nu E_S)^-1 (sum_n m_nj x_nj E[z~_n] + nu e_Sj)``;
  ``sigma^2`` = the mean expected squared residual over observed values and pseudo-values.
- Parameter expansion (PX-EM, Liu, Rubin & Wu 1998): the latent mean and covariance are
  re-estimated from the E-step moments (the pseudo-samples inform the covariance) and
  folded back into mu and W, so the scale of W converges in a few iterations instead of
  hundreds. With the prior this step is not exact EM: an iterate whose objective falls
  below its predecessor's is replaced by the plain EM step (monotonicity safeguard).
- Acceleration (SQUAREM, Varadhan & Roland 2008): the (PX-)EM map is extrapolated every
  two steps, kept only if the objective does not decrease. Same fixed points as EM.

The recorded objective (``log_likelihood``, per observed value and pseudo-value) never
decreases. The start is the prior's mode (PPCA of S: deterministic, no random numbers), or
without the prior plain PCA of the mean-imputed data.

Everything is vectorized: the N (d x d) matrices ``M_n = sum_j m_nj w_j w_j^T`` are one matrix
product of the mask with the D x d(d+1)/2 table of products ``w_jk w_jl``; the D per-pixel
(d+1) x (d+1) systems are one product of the transposed mask with the N x (d+1)(d+2)/2 table
of ``E[z~ z~^T]``; the small systems are solved in batches. The observed-data log-likelihood
(Woodbury / matrix determinant lemma) plus the prior's term is tracked for convergence.
Pixels never observed are dropped before the fit (no work is spent on them).

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
from typing import NamedTuple

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


def _sym_index(d: int) -> NDArray[np.intp]:
    """(d * d,) position in the packed upper triangle (:func:`_triu` order) of each entry
    (k, l) of a d x d symmetric matrix, row-major."""
    pos = np.empty((d, d), dtype=np.intp)
    iu = _triu(d)
    pos[iu[0], iu[1]] = np.arange(iu[0].size)
    pos[iu[1], iu[0]] = pos[iu[0], iu[1]]
    return pos.reshape(-1)


def _unpack_sym(flat: F64, d: int, iu: tuple[NDArray[np.intp], NDArray[np.intp]]) -> F64:
    """(B, P) upper-triangle entries (in ``iu`` = :func:`_triu` order) -> (B, d, d)
    symmetric float64 matrices, by one gather."""
    del iu  # the order is _triu's
    return np.asarray(flat, dtype=np.float64)[:, _sym_index(d)].reshape(flat.shape[0], d, d)


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
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        M = _restore_definite(M, sigma2)
        L = np.linalg.cholesky(M)
    Minv = np.linalg.inv(M)  # batched LU: cheaper than the inverse from L in numpy
    Ez = np.einsum("nij,nj->ni", Minv, b)
    # x_o ~ N(mu_o, C), C = W_o W_o^T + sigma^2 I: log|C| by the determinant lemma,
    # r^T C^-1 r = (|r|^2 - b^T M^-1 b) / sigma^2 by Woodbury.
    logdetM = 2.0 * np.log(np.diagonal(L, axis1=1, axis2=2)).sum(1)
    logdet = (rowcount - d) * math.log(sigma2) + logdetM
    quad = (r2 - np.einsum("ni,ni->n", b, Ez)) / sigma2
    ll = -0.5 * (rowcount * _LOG_2PI + logdet + quad)
    ll = np.where(rowcount > 0, ll, 0.0)
    return Ez, Minv, ll


def _restore_definite(M: F64, sigma2: float) -> F64:
    """The matrices ``M = W_o^T W_o + sigma^2 I`` (B, d, d) with each one's diagonal raised so
    that its smallest eigenvalue is at least ``sigma2``, as it is in exact arithmetic: the
    products of the mask with ``w_k w_l`` are summed in the data's dtype (float32 for maps),
    and over thousands of pixels their rounding can make a near-singular ``W_o^T W_o``
    indefinite. Matrices already above the bound are returned unchanged."""
    lam = np.linalg.eigvalsh(M)[:, 0]
    shift = np.maximum(float(sigma2) - lam, 0.0)
    return M + shift[:, None, None] * np.eye(M.shape[1])


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
        a = np.asarray(X)
        single = a.ndim == 1
        if single:
            a = a[None, :]
        if a.ndim != 2 or a.shape[1] != self.n_features_in:
            raise LinoLocError(
                f"sample shape {np.shape(X)} does not match the model's {self.n_features_in} pixels"
            )
        if a.shape[0] > _PROJECT_BLOCK:  # by blocks: the float64 work arrays stay bounded
            parts = [self._project_rows(a[lo : lo + _PROJECT_BLOCK])
                     for lo in range(0, a.shape[0], _PROJECT_BLOCK)]
            Y, has = np.concatenate([y for y, _ in parts]), np.concatenate([h for _, h in parts])
        else:
            Y, has = self._project_rows(a)
        if single:
            return (Y[0], bool(has[0])) if return_valid else Y[0]
        return (Y, has) if return_valid else Y

    def _project_rows(self, X: NDArray) -> tuple[F64, NDArray[np.bool_]]:
        """:meth:`project` of (N, D) samples: their features and which had a valid pixel."""
        a = np.asarray(X, dtype=np.float64)
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
        return Y, has

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


def _init_subspace(Xc: NDArray, d: int, rng: np.random.Generator) -> tuple[F64, F64]:
    """Leading d right singular vectors (D, d) and singular values of Xc (mean-imputed, centred).

    Exact SVD for small problems, randomized range finder with power iterations otherwise
    (Halko, Martinsson & Tropp 2011).
    """
    n, D = Xc.shape
    if min(n, D) <= 600:
        _, s, vt = np.linalg.svd(Xc, full_matrices=False)
        return vt[:d].T.astype(np.float64), s[:d].astype(np.float64)
    k = min(d + 15, min(n, D))
    Q = Xc @ rng.standard_normal((D, k)).astype(Xc.dtype)
    for _ in range(4):
        Q, _ = np.linalg.qr(Q)
        Q, _ = np.linalg.qr(Xc.T @ Q)
        Q = Xc @ Q
    Q, _ = np.linalg.qr(Q)
    B = Q.T @ Xc  # (k, D)
    _, s, vt = np.linalg.svd(B.astype(np.float64), full_matrices=False)
    return vt[:d].T, s[:d]


#: Default weight of the prior on the model covariance, in samples per sample with data
#: (nu = weight x N pseudo-samples; see :func:`fit_pca_missing`).
DEFAULT_PRIOR_WEIGHT = 0.1

#: Default stopping tolerance: the objective's change over one EM iteration, in nats per
#: observed value and pseudo-value (see :func:`fit_pca_missing`). That is a change of the
#: log posterior of tol x (number of values) per iteration, tens of nats for a survey's
#: millions of disparity values, far inside the posterior's own spread (of the order of
#: half the number of parameters, D (d + 1) / 2 nats: tens of thousands for a map).
DEFAULT_TOL = 5e-6

_PROJECT_BLOCK = 2048  # samples per block of :meth:`MissingDataPCA.project` (3 float64 (B, D) work arrays)
_SOLVE_BLOCK = 512  # pixels per batch of M-step solves (bounds the (D, d+1, d+1) temporaries)


@dataclass
class _EMData:
    """The fixed arrays of one fit: data with 0 where missing, mask, per-row statistics."""

    X0: NDArray
    maskf: NDArray
    rowcount: F64
    xx_rows: F64
    xsq_total: float
    n_obs: float
    seen: NDArray[np.bool_]
    active: NDArray[np.bool_]
    sigma2_floor: float
    px_em: bool
    prior: _CovPrior | None = None


@dataclass
class _CovPrior:
    """The prior's fixed parts: nu pseudo-samples (complete, centred) of second moment S."""

    nu: float
    S: F64  # (D, D) pairwise-available covariance of the data (0 where never co-observed)
    trace: float  # tr(S)


class _PriorStats(NamedTuple):
    """The prior's E-step at (W, sigma2): its log density and its M-step terms."""

    log_density: float
    Ezz: F64  # (d, d) E[z z^T] of one pseudo-sample
    Exz: F64  # (D, d) E[x z^T] of one pseudo-sample


def _prior_stats(W: F64, sigma2: float, prior: _CovPrior) -> _PriorStats:
    """``nu * log N(S | 0, C)`` with ``C = W W^T + sigma2 I`` (a Gaussian log-likelihood of
    nu complete centred samples of second moment S: ``-nu/2 (D log 2 pi + log|C| + tr(C^-1
    S))``, by the determinant lemma and Woodbury in O(D^2 d)), and the pseudo-samples'
    posterior moments ``E[z z^T] = sigma2 M^-1 + M^-1 W^T S W M^-1``, ``E[x z^T] = S W M^-1``
    with ``M = W^T W + sigma2 I``."""
    D, d = W.shape
    M = W.T @ W
    M[np.diag_indices(d)] += sigma2
    Minv = np.linalg.inv(M)
    SW = np.asarray(prior.S @ W.astype(prior.S.dtype, copy=False), dtype=np.float64)
    G = W.T @ SW
    logdet = (D - d) * math.log(sigma2) + float(np.linalg.slogdet(M)[1])
    trace_term = (prior.trace - float(np.sum(Minv * G))) / sigma2
    log_density = -0.5 * prior.nu * (D * _LOG_2PI + logdet + trace_term)
    return _PriorStats(log_density, sigma2 * Minv + Minv @ G @ Minv, SW @ Minv)


def _n_values(data: _EMData) -> float:
    """Observed values plus the prior's pseudo-values (nu per pixel observed)."""
    return data.n_obs + (data.prior.nu * float(data.seen.sum()) if data.prior is not None else 0.0)


def _pairwise_covariance(data: _EMData) -> F64:
    """(D, D) available-case covariance of the centred data: ``S_jk = sum_n m_nj m_nk x_nj
    x_nk / sum_n m_nj m_nk`` (0 for pairs never observed together). Two symmetric rank-N
    updates (BLAS syrk) of the (N, D) arrays."""
    from scipy.linalg.blas import dsyrk, ssyrk

    syrk = ssyrk if data.X0.dtype == np.float32 else dsyrk
    S = syrk(1.0, data.X0, trans=1, lower=0)  # upper triangles, Fortran order
    C = syrk(1.0, data.maskf, trans=1, lower=0)
    pairs = C > 0.5
    np.divide(S, C, out=S, where=pairs)
    del C
    S[~pairs] = 0.0
    del pairs
    for lo in range(0, S.shape[0], _SOLVE_BLOCK):  # the lower triangle from the upper, by blocks
        sl = slice(lo, lo + _SOLVE_BLOCK)
        S[sl, :lo] = S[:lo, sl].T
        S[sl, sl] = np.triu(S[sl, sl]) + np.triu(S[sl, sl], 1).T
    return np.ascontiguousarray(S)


def _solve_pixels(A_packed: NDArray, B: F64, seen: NDArray[np.bool_], d1: int) -> F64:
    """The (D, d1) solutions theta_j of the per-pixel (d1 x d1) normal equations (packed
    upper triangles ``A_packed``, right-hand sides B), by blocks of pixels; 0 for pixels
    never observed."""
    iu1 = _triu(d1)
    theta = np.zeros((B.shape[0], d1))
    for lo in range(0, B.shape[0], _SOLVE_BLOCK):
        sl = slice(lo, lo + _SOLVE_BLOCK)
        A = _unpack_sym(np.asarray(A_packed[sl], dtype=np.float64), d1, iu1)
        A[~seen[sl]] = np.eye(d1)
        theta[sl] = np.linalg.solve(A, B[sl, :, None])[:, :, 0]
    return theta


def _px_fold(
    W: F64, mu: F64, Ez: F64, S_sum: F64, ps: _PriorStats | None, data: _EMData
) -> tuple[F64, F64]:
    """PX-EM (Liu, Rubin & Wu 1998): the latent mean m and covariance C of the expanded model
    z ~ N(m, C), estimated from the E-step moments of the samples with data (Ez, the sum
    S_sum of their E[z z^T]) and, for C, the prior's centred pseudo-samples; mapped back to
    z ~ N(0, I) by ``mu += W m``, ``W <- W C^1/2``. Any square root of C gives the same
    model; the symmetric one turns the latent coordinates the least, so successive iterates
    of W differ only by what changes the model (which the SQUAREM extrapolation relies on).
    Unchanged if C is not positive definite."""
    n = Ez.shape[0]
    m_z = Ez.sum(0) / n
    C = S_sum / n - np.outer(m_z, m_z)
    if ps is not None:
        nu = data.prior.nu  # type: ignore[union-attr]
        C = (n * C + nu * ps.Ezz) / (n + nu)
    evals, evecs = np.linalg.eigh(C)
    if evals[0] <= 0:
        return W, mu
    return W @ ((evecs * np.sqrt(evals)) @ evecs.T), mu + W @ m_z


def _em_step(
    W: F64, mu: F64, sigma2: float, data: _EMData, px: bool = True
) -> tuple[F64, F64, float, float]:
    """One EM (or PX-EM) iteration: the E-step at (W, mu, sigma2), then the M-step.

    Returns the new (W, mu, sigma2) and the objective (log posterior per observed value and
    pseudo-value) at the *input* parameters. ``px``: with the parameter-expanded fold (if
    the fit uses it).
    """
    X0, maskf = data.X0, data.maskf
    n = X0.shape[0]
    dt = X0.dtype
    d = W.shape[1]
    d1 = d + 1
    iu1 = _triu(d1)
    seen, active = data.seen, data.active
    # ---- E-step
    Ez, Minv, ll = _posterior(W, mu, sigma2, X0, maskf, data.rowcount, data.xx_rows)
    ps = _prior_stats(W, sigma2, data.prior) if data.prior is not None else None
    ll_obs = float((ll.sum() + (ps.log_density if ps else 0.0)) / _n_values(data))
    # ---- M-step for (w_j, mu_j) with z~ = (z, 1): E[z~ z~^T] per sample, packed
    St = np.empty((n, d1, d1))
    Minv *= sigma2
    Minv += Ez[:, :, None] * Ez[:, None, :]  # E[z z^T] = sigma^2 M^-1 + E[z] E[z]^T
    St[:, :d, :d] = Minv
    St[:, :d, d] = Ez
    St[:, d, :d] = Ez
    St[:, d, d] = 1.0
    del Minv
    S_active = St[active, :d, :d].sum(0)  # for PX-EM
    # sum_n m_nj E[z~ z~^T]_n for all pixels j: (D, P1) packed, one product with the mask
    A_packed = maskf.T @ _pack_sym(St, iu1).astype(dt, copy=False)
    Zt = St[:, d, :]  # (N, d1) = (E[z], 1)
    B = np.asarray(X0.T @ Zt.astype(dt, copy=False), dtype=np.float64)  # (D, d1)
    if ps is not None:  # the prior's nu complete pseudo-samples
        nu = data.prior.nu  # type: ignore[union-attr]
        B[:, :d] += nu * ps.Exz
        A_packed = A_packed.astype(np.float64)
        A_packed += nu * _pack_sym(np.pad(ps.Ezz, ((0, 1), (0, 1)))[None], iu1)
    B[~seen] = 0.0
    theta = _solve_pixels(A_packed, B, seen, d1)
    del A_packed, St
    W_new = theta[:, :d]
    mu_new = theta[:, d].copy()
    xsq = data.xsq_total + (data.prior.nu * data.prior.trace if ps is not None else 0.0)  # type: ignore[union-attr]
    sse = xsq - float(np.einsum("ji,ji->", theta, B))
    sigma2_new = max(sse / _n_values(data), data.sigma2_floor)
    if px and data.px_em and active.any():
        W_new, mu_new = _px_fold(W_new, mu_new, Ez[active], S_active, ps, data)
    return np.ascontiguousarray(W_new), mu_new, sigma2_new, ll_obs


def fit_pca_missing(
    X: ArrayLike,
    n_components: int,
    *,
    max_iter: int = 200,
    tol: float = DEFAULT_TOL,
    seed: int = 0,
    subspace_tol: float = 1e-6,
    min_sigma2: float = 1e-9,
    dtype: type = np.float64,
    px_em: bool = True,
    accelerate: bool = True,
    prior_weight: float = DEFAULT_PRIOR_WEIGHT,
) -> MissingDataPCA:
    """Fit probabilistic PCA to (N, D) data with NaN for missing values: the MAP estimate
    of the module docstring's objective by EM.

    ``prior_weight`` (>= 0, default :data:`DEFAULT_PRIOR_WEIGHT` = 0.1) is nu / N, the weight
    of the prior on the covariance in samples per sample with data; 0 is the ML fit. With
    the prior the start is PPCA of the pairwise-available covariance S; without it plain
    PCA of the mean-imputed data (``seed`` drives its randomized SVD on large problems).
    Stops when the objective (nats per observed value and pseudo-value) changes by less
    than ``tol`` over one EM iteration (absolute: the data's units shift it by a constant);
    or when one iteration turns span(W) by less than ``subspace_tol`` radians (largest
    principal angle) while W's singular values and sigma^2 change by less than ``10 *
    subspace_tol`` (relative); or when an EM step cannot raise the objective beyond rounding
    (:meth:`_EMLoop.advance`); or after ``max_iter`` E-steps (then ``converged`` is False).
    ``min_sigma2`` is a floor on sigma^2 relative to the data's mean observed variance
    (keeps noiseless data well posed; at least 1e-6 with float32). ``dtype`` is the
    precision of the large (N x D) matrix products: float64 (default) or float32 (faster,
    half the memory). ``px_em`` (default on) adds the parameter-expanded M-step (latent mean
    and covariance estimated, then folded back into mu and W; Liu, Rubin & Wu 1998), which
    removes plain EM's very slow convergence of the scale of W when values are missing.

    ``accelerate`` (default on) wraps the (PX-)EM map in SQUAREM (Varadhan & Roland 2008,
    scheme S3, adaptive step bound): every two EM steps the parameters are extrapolated
    along the EM direction, kept only if the objective does not drop (see
    :func:`_squarem_step`). The fixed points are those of EM; the recorded objective
    (``log_likelihood``, at the accepted iterates) never decreases. Deterministic. The
    (N, D) work arrays are one copy of the data's observed columns in ``dtype`` plus its
    mask, and with the prior the (D, D) matrix S. LinoLocError for data that is not 2-D or
    has no valid value, ``n_components`` outside [1, min(N, D)], another ``dtype``, or a
    negative or non-finite ``prior_weight``.
    """
    a, d = _checked_data(X, n_components, dtype)
    if not (math.isfinite(prior_weight) and prior_weight >= 0.0):
        raise LinoLocError(f"prior_weight must be finite and >= 0, got {prior_weight}")
    rng = np.random.default_rng(seed)
    full_d = a.shape[1]
    a, cols = _observed_part(a)
    data, mu0, colcount = _centred_data(a, dtype, min_sigma2, px_em)
    W, sigma2 = _start(data, d, prior_weight, rng)
    mu = np.zeros(data.X0.shape[1])
    fit = _run_em(W, mu, sigma2, data, max_iter, tol, subspace_tol, accelerate)
    if not fit.converged:
        log.info("EM-PCA stopped after max_iter=%d iterations without reaching the tolerance", fit.n_iter)
    model = _fitted_model(fit, mu0, data.seen, colcount)
    return model if cols.all() else _expanded(model, cols, full_d)


def _observed_part(a: NDArray) -> tuple[NDArray, NDArray[np.bool_]]:
    """The rows and columns of (N, D) ``a`` with at least one finite value, and the mask
    (D,) of those columns. Pixels never observed get no parameters (zeros in the model);
    samples with no valid pixel add nothing to any E- or M-step sum (nor to the prior's
    weight, which counts samples with data), so dropping them leaves the MAP fit's iterates
    as they are (the ML fit's start, PCA of the mean-imputed data, no longer counts them)
    and saves their share of the (N, D) products."""
    finite = np.isfinite(a)
    cols, rows = finite.any(0), finite.any(1)
    if not rows.all():
        a = a[rows]
    if not cols.all():
        a = a[:, cols]
    return a, cols


def _start(data: _EMData, d: int, prior_weight: float, rng: np.random.Generator) -> tuple[F64, float]:
    """Set up the prior (``prior_weight`` > 0) in ``data`` and return the start (W, sigma^2):
    the prior's mode, or without a prior :func:`_initial_params`. The prior's second moment
    is S, or where that prior is improper ``S + delta (I - U U^T)`` (U: S's top d
    eigenvectors, delta from :func:`_proper_shift`): the top d eigenpairs kept, the others
    raised by delta (for delta below the gap lam_d - lam_{d+1}, U stays on top)."""
    if prior_weight <= 0.0:
        return _initial_params(data, d, rng)
    S = _pairwise_covariance(data)
    lam, U = _top_eigen(S, d)
    delta = _proper_shift(float(np.trace(S)), lam, S.shape[0])
    if delta > 0.0:  # S + delta (I - U U^T): the eigenvalues beyond the d-th raised by delta
        S[np.diag_indices(S.shape[0])] += delta
        Ud = U.astype(S.dtype)
        S -= (delta * Ud) @ Ud.T
        log.info("EM-PCA: the pairwise covariance gives an improper prior; its eigenvalues beyond "
                 "the %d-th raised by %.4g", lam.shape[0], delta)
    data.prior = _CovPrior(nu=prior_weight * float(data.active.sum()), S=S, trace=float(np.trace(S)))
    return _prior_mode(lam, U, data.prior.trace, S.shape[0], data.sigma2_floor)


#: The prior's noise part, the mean of its second moment's eigenvalues beyond the d-th, is at
#: least this fraction of the mean per-pixel variance tr(S) / D (see :func:`_proper_shift`).
PRIOR_MIN_NOISE = 1e-3


def _proper_shift(trace: float, lam: F64, D: int) -> float:
    """The ridge delta >= 0 added to S's diagonal so that the prior is proper.

    ``nu log N_S(C)`` is bounded above over ``C = W W^T + sigma^2 I`` only if the mean of S's
    eigenvalues beyond the d-th, ``r = (tr S - sum_{k<=d} lam_k) / (D - d)``, is positive
    (its sigma^2 part is ``-nu/2 ((D - d) log sigma^2 + (D - d) r / sigma^2)`` at best). A
    sample covariance has r >= 0, but an available-case one need not be positive
    semi-definite: with values missing in blocks its negative eigenvalues can outweigh the
    small positive ones, r < 0, and the objective then grows without bound as sigma^2 -> 0
    (EM runs sigma^2 to its floor and W's scale away). Raising the eigenvalues beyond the
    d-th by ``delta = max(0, PRIOR_MIN_NOISE tr(S) / D - r)`` is the smallest change that
    makes r at least that fraction of the mean variance; 0 (S unchanged) whenever r already
    is. ``lam``: S's top d eigenvalues."""
    d = lam.shape[0]
    if D <= d:
        return 0.0
    rest = (trace - float(lam.sum())) / (D - d)
    return max(0.0, PRIOR_MIN_NOISE * trace / D - rest)


def _top_eigen(S: F64, d: int) -> tuple[F64, F64]:
    """The top d eigenvalues (d,) and eigenvectors (D, d) of symmetric S, in decreasing
    order (dense for small S, Lanczos with a fixed start vector otherwise)."""
    D = S.shape[0]
    if D <= 600 or d >= D - 1:
        lam, U = np.linalg.eigh(np.asarray(S, dtype=np.float64))
        return lam[::-1][:d], U[:, ::-1][:, :d]
    from scipy.sparse.linalg import eigsh

    v0 = np.ones(D) / math.sqrt(D)
    lam, U = eigsh(S, k=d, which="LA", v0=v0.astype(S.dtype), tol=1e-6)
    order = np.argsort(lam)[::-1]
    return lam[order].astype(np.float64), U[:, order].astype(np.float64)


def _prior_mode(lam: F64, U: F64, trace: float, D: int, floor: float) -> tuple[F64, float]:
    """PPCA's closed-form maximum for a second moment S (Tipping & Bishop 1999) from its top
    d eigenpairs (lam, U) and trace: ``sigma2`` the mean of the other eigenvalues (at least
    the floor), ``W = U diag(sqrt(max(lam - sigma2, 1e-3 lam_1)))``. Deterministic (signs
    fixed by the largest loading)."""
    d = lam.shape[0]
    sigma2 = max((trace - float(lam.sum())) / max(D - d, 1), floor)
    U = U * np.sign(U[np.argmax(np.abs(U), axis=0), np.arange(d)])[None, :]
    return U * np.sqrt(np.maximum(lam - sigma2, 1e-3 * max(float(lam[0]), floor)))[None, :], sigma2


def _expanded(model: MissingDataPCA, cols: NDArray[np.bool_], D: int) -> MissingDataPCA:
    """The model of a fit on the observed columns ``cols`` written for all D pixels (zero
    mean, loadings and components, count 0 for the others)."""

    def wide(a: NDArray, axis: int) -> NDArray:
        shape = list(a.shape)
        shape[axis] = D
        out = np.zeros(shape, dtype=a.dtype)
        if axis == 0:
            out[cols] = a
        else:
            out[:, cols] = a
        return out

    return MissingDataPCA(
        mean=wide(model.mean, 0), components=wide(model.components, 1),
        explained_variance=model.explained_variance, W=wide(model.W, 0), sigma2=model.sigma2,
        observed_count=wide(model.observed_count, 0), log_likelihood=model.log_likelihood,
        n_iter=model.n_iter, converged=model.converged,
    )


def _checked_data(X: ArrayLike, n_components: int, dtype: type) -> tuple[NDArray, int]:
    """X as a floating (N, D) array (other dtypes cast to float64) and the number of
    components d; LinoLocError if X is not 2-D, d is not in [1, min(N, D)] or ``dtype`` is
    neither float64 nor float32."""
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
    return a, d


def _centred_data(
    a: NDArray, dtype: type, min_sigma2: float, px_em: bool
) -> tuple[_EMData, F64, NDArray[np.intp]]:
    """The fixed arrays of a fit, the observed per-pixel means mu0 (D,) (0 for pixels never
    observed) and the per-pixel counts of valid values (D,).

    The data are copied in the working precision ``dtype``, centred by mu0 and set to 0
    where missing. The sigma^2 floor is ``min_sigma2`` (at least 1e-6 in float32) times the
    mean observed variance. LinoLocError if no value is valid.
    """
    mask_b = np.isfinite(a)
    colcount = mask_b.sum(0)
    if colcount.sum() == 0:
        raise LinoLocError("PCA data has no valid value at all")
    seen = colcount > 0
    # (N, D) copy in the working precision, centred by the observed per-pixel means, 0 where
    # missing (in place: no N x D temporaries). The fit runs on the centred data and adds
    # the means back at the end: the same model (mu is a free parameter), but the sums of
    # squares of the log-likelihood no longer cancel large terms, so it stays accurate to
    # ~1e-7 even with float32 products (the convergence test and SQUAREM compare it).
    X0 = np.array(a, dtype=dtype, copy=True)
    np.copyto(X0, 0.0, where=~mask_b)
    maskf = mask_b.astype(dtype)
    del mask_b
    mu0 = np.divide(X0.sum(0, dtype=np.float64), colcount, out=np.zeros(a.shape[1]), where=seen)
    X0 -= mu0.astype(dtype)
    X0 *= maskf
    n_obs = float(colcount.sum())
    rowcount = np.asarray(maskf.sum(1, dtype=np.float64))
    xx_rows = np.einsum("nj,nj->n", X0, X0, dtype=np.float64)  # (N,) sum_j m (x - mu0)^2
    total_var = float(xx_rows.sum() / n_obs)
    # float32 products carry ~1e-7 relative error: keep M_n = W_o^T W_o + sigma^2 I well
    # inside positive definiteness with a larger floor in that precision.
    floor_rel = max(min_sigma2, 1e-6) if dtype == np.float32 else min_sigma2
    data = _EMData(
        X0=X0,
        maskf=maskf,
        rowcount=rowcount,
        xx_rows=xx_rows,
        xsq_total=float(xx_rows.sum()),
        n_obs=n_obs,
        seen=seen,
        active=rowcount > 0,
        sigma2_floor=max(floor_rel * total_var, 1e-300),
        px_em=px_em,
    )
    return data, mu0, colcount


def _initial_params(data: _EMData, d: int, rng: np.random.Generator) -> tuple[F64, float]:
    """(W (D, d), sigma^2) from plain PCA of the mean-imputed data (the centred ``X0``).

    With the leading singular vectors V and ML (1/N) variances lam_k = s_k^2 / N of X0:
    sigma^2 = the mean squared residual of the rank-d fit over the observed values (at
    least the floor), ``W = V diag(sqrt(max(lam - sigma^2, 1e-3 max(lam) + floor)))``, zero
    rows for pixels never observed. Complete data start at the PPCA solution.
    """
    X0, maskf = data.X0, data.maskf
    n = X0.shape[0]
    V, s = _init_subspace(X0, d, rng)
    lam = s.astype(np.float64) ** 2 / n
    sse = 0.0
    Vd = V.astype(X0.dtype)
    for lo in range(0, n, 512):  # residual of the rank-d fit on observed values, by row blocks
        blk = X0[lo : lo + 512]
        r = blk - (blk @ Vd) @ Vd.T
        r *= maskf[lo : lo + 512]
        sse += float(np.einsum("nj,nj->", r, r, dtype=np.float64))
        del blk, r
    sigma2 = max(sse / data.n_obs, data.sigma2_floor)
    W = (
        V.astype(np.float64)
        * np.sqrt(np.maximum(lam - sigma2, 1e-3 * lam.max() + data.sigma2_floor))[None, :]
    )
    W[~data.seen] = 0.0
    return W, sigma2


def _fitted_model(
    fit: _EMResult, mu0: F64, seen: NDArray[np.bool_], colcount: NDArray[np.intp]
) -> MissingDataPCA:
    """The model of an EM result on data centred by mu0: the means added back, loadings
    and means of pixels never observed set to 0, span(W) given an orthonormal basis ordered
    by variance (``explained_variance = s_k^2 + sigma^2`` with s_k W's singular values)."""
    W = fit.W
    W[~seen] = 0.0
    mu = fit.mu + mu0
    mu[~seen] = 0.0
    comps, sv = _ordered_basis(W, seen)
    return MissingDataPCA(
        mean=mu,
        components=comps,
        explained_variance=sv**2 + fit.sigma2,
        W=W,
        sigma2=float(fit.sigma2),
        observed_count=colcount.astype(np.int64),
        log_likelihood=fit.history,
        n_iter=fit.n_iter,
        converged=fit.converged,
    )


def _ordered_basis(W: F64, seen: NDArray[np.bool_]) -> tuple[F64, F64]:
    """(d, D) orthonormal basis of span(W), rows ordered by variance (like plain PCA), and
    W's singular values (d,). Deterministic signs: the largest |loading| of each row is
    positive; columns of pixels never observed are 0."""
    U, sv, _ = np.linalg.svd(W, full_matrices=False)  # U (D, d)
    comps = U.T.copy()
    big = np.argmax(np.abs(comps), axis=1)
    signs = np.sign(comps[np.arange(comps.shape[0]), big])
    signs[signs == 0] = 1.0
    comps *= signs[:, None]
    comps[:, ~seen] = 0.0
    return comps, sv


_Params = tuple[F64, F64, float]


class _EMResult(NamedTuple):
    """The outcome of :func:`_run_em`."""

    W: F64
    mu: F64
    sigma2: float
    history: list[float]  # log-likelihood per observed value at the accepted iterates
    n_iter: int  # E-steps run
    converged: bool


class _EMLoop:
    """The EM map of one fit with its counters: E-steps run and the recorded log-likelihoods.

    The stopping rule (:meth:`done`) is that of :func:`fit_pca_missing`.
    """

    def __init__(self, data: _EMData, tol: float, subspace_tol: float) -> None:
        self.data = data
        self.tol = tol
        self.subspace_tol = subspace_tol
        self.history: list[float] = []
        self.it = 0
        self.last: _Params | None = None  # the iterate whose objective is history[-1]
        self.fallbacks = 0
        self.plain_image = False  # the next advance starts from a plain EM image of last

    def step(self, p: _Params, px: bool = True) -> tuple[_Params, float]:
        """One EM step from p: the next parameters and the objective at p."""
        self.it += 1
        W1, mu1, s1, ll = _em_step(p[0], p[1], p[2], self.data, px)
        return (W1, mu1, s1), ll

    def record(self, p: _Params, ll: float) -> None:
        """Record p as the current iterate, of objective ll."""
        self.history.append(ll)
        self.last = p

    def advance(self, p: _Params) -> tuple[_Params, float, bool]:
        """One EM step from p, its objective recorded: (next parameters, objective at p,
        whether the stopping rule holds).

        Monotonicity safeguard: the parameter-expanded step is exact EM only without the
        prior; if p (the image of such a step) has a lower objective than the last recorded
        iterate, p is dropped and a plain EM step (whose image never lowers the objective)
        is taken from that iterate instead; nothing is recorded then. If that plain EM
        image is lower too, which only rounding can make it (float32 products near the
        optimum), the objective cannot be raised measurably: the rule holds, and the last
        recorded iterate is returned."""
        p_next, ll = self.step(p)
        prev = self.history[-1] if self.history else None
        plain_image, self.plain_image = self.plain_image, False
        if prev is not None and self.last is not None and ll < prev - 1e-12 * abs(prev):
            if plain_image:
                log.debug("EM-PCA iter %d: an EM step lowers the objective by rounding alone: converged", self.it)
                return self.last, prev, True
            self.fallbacks += 1
            p_next, _ = self.step(self.last, px=False)
            self.plain_image = True
            return p_next, prev, False
        stop = self.done(p, p_next, ll, prev)
        self.record(p, ll)
        return p_next, ll, stop

    def done(self, p: _Params, p_next: _Params, ll: float, ll_prev: float | None) -> bool:
        """The stopping rule on one EM step p -> p_next (ll at p, ll_prev at the previous
        recorded iterate; None: log only)."""
        q_old, sv_old = _basis(p[0])
        q_new, sv_new = _basis(p_next[0])
        dangle = _max_angle(q_old, q_new)
        dscale = float(np.max(np.abs(sv_new - sv_old) / np.maximum(sv_new, 1e-300)))
        s2_change = abs(p_next[2] - p[2]) / p[2]
        log.debug(
            "EM-PCA iter %d ll/obs %.8g sigma2 %.4g dangle %.2e dscale %.2e",
            self.it,
            ll,
            p_next[2],
            dangle,
            dscale,
        )
        if ll_prev is None:
            return False
        tol = self.subspace_tol
        settled = dangle < tol and max(dscale, s2_change) < 10 * tol
        return abs(ll - ll_prev) < self.tol or settled


def _run_em(
    W: F64,
    mu: F64,
    sigma2: float,
    data: _EMData,
    max_iter: int,
    tol: float,
    subspace_tol: float,
    accelerate: bool,
) -> _EMResult:
    """The EM iterations, optionally accelerated by SQUAREM (see :func:`fit_pca_missing`):
    two EM steps p0 -> p1 -> p2, then (with ``accelerate``) :func:`_squarem_step` from p0."""
    loop = _EMLoop(data, tol, subspace_tol)
    p: _Params = (W, mu, sigma2)
    step_max = 1.0  # SQUAREM's adaptive bound on the step length (Varadhan & Roland 2008)
    while loop.it < max_iter:
        p0 = p
        fallbacks = loop.fallbacks
        p, _, stop = loop.advance(p0)
        if stop:
            return _EMResult(*p, loop.history, loop.it, True)
        if not accelerate or loop.it >= max_iter:
            continue
        p1 = p
        p, ll1, stop = loop.advance(p1)
        if stop:
            return _EMResult(*p, loop.history, loop.it, True)
        if loop.it >= max_iter or loop.fallbacks != fallbacks:  # not two EM steps: no extrapolation
            continue
        p, step_max = _squarem_step(loop, p0, p1, p, ll1, step_max)
    return _EMResult(*p, loop.history, loop.it, False)


def _squarem_step(
    loop: _EMLoop, p0: _Params, p1: _Params, p2: _Params, ll1: float, step_max: float
) -> tuple[_Params, float]:
    """SQUAREM S3 after the EM steps p0 -> p1 -> p2 (ll1 at p1): the next iterate and the
    updated step bound.

    ``r = p1 - p0``, ``v = p2 - 2 p1 + p0``, ``p' = p0 + 2 a r + a^2 v`` with
    ``a = |r| / |v|`` clipped to [1, step_max] (sigma^2 floored), then one stabilising EM
    step p' -> p3 whose E-step gives ll(p'). p3 is kept (and ll(p') recorded) if ll(p') is
    finite and not below ll1, otherwise p2. The bound grows by 4 when a reaches it and the
    step is kept (or a = 1 = bound), and shrinks by 4 (not below 1) when such a step is
    rejected. No extrapolation (p2 kept) when v = 0 or a = 1.
    """
    r = [p1[k] - p0[k] for k in range(3)]
    v = [p2[k] - p1[k] - r[k] for k in range(3)]
    sr2 = sum(float(np.vdot(x, x)) for x in r)
    sv2 = sum(float(np.vdot(x, x)) for x in v)
    if not sv2 > 0.0:
        return p2, step_max
    alpha = min(max(math.sqrt(sr2 / sv2), 1.0), step_max)
    if alpha <= 1.0:  # p' = p2: nothing to extrapolate
        return p2, step_max * 4.0 if alpha == step_max else step_max
    pp: _Params = (
        p0[0] + 2.0 * alpha * r[0] + alpha**2 * v[0],
        p0[1] + 2.0 * alpha * r[1] + alpha**2 * v[1],
        max(p0[2] + 2.0 * alpha * r[2] + alpha**2 * v[2], loop.data.sigma2_floor),
    )
    p3, llp = loop.step(pp)  # the stabilising EM step; its E-step gives ll(p')
    if math.isfinite(llp) and llp >= ll1:
        # (logged, not a convergence test: ll1 -> llp is an extrapolation, not an EM step)
        loop.done(pp, p3, llp, None)
        loop.record(pp, llp)
        return p3, step_max * 4.0 if alpha == step_max else step_max
    if alpha == step_max:  # rejected: continue from the EM iterate p2
        step_max = max(1.0, step_max / 4.0)
    return p2, step_max


def plain_pca(X: ArrayLike, n_components: int) -> tuple[F64, F64, F64]:
    """Plain PCA of complete data: (mean (D,), components (d, D), variances (d,)). For checks."""
    a = np.asarray(X, dtype=np.float64)
    if not np.isfinite(a).all():
        raise LinoLocError("plain PCA needs complete data (no NaN); use fit_pca_missing")
    mu = a.mean(0)
    _, s, vt = np.linalg.svd(a - mu, full_matrices=False)
    return mu, vt[:n_components], s[:n_components] ** 2 / max(a.shape[0] - 1, 1)
