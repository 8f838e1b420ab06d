"""The closed-form numpy twin of the whole-utterance synthesis density (DESIGN.md §6).

:class:`UtteranceDensity` evaluates ln p(X* | Ŷ) of :func:`bayes_talk.synthesis.joint.synthesis_model`
(the Pyro program, the reference; see its module for the terms) with its gradient, a
value-only variant and its Hessian, for the optimiser and the samplers: every GP predictive
through the compiled, packed predictives of :mod:`bayes_talk.gp.predictive_fused`. A test
checks it equals the Pyro log joint to 1e-8 relative (``tests/test_posterior.py``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bayes_talk.gp.predictive_fused import PackedGPs, Runs
from bayes_talk.synthesis.segment_objective import LOG_2PI, numpy_gp

if TYPE_CHECKING:
    from bayes_talk.synthesis.joint import UtterancePlan


class UtteranceDensity:
    """The same log density in closed form with its gradient (numpy), for speed.

    ``__call__(X)`` returns (ln p, ∂ ln p/∂X) for X of shape (T, d); :meth:`batch` does K
    points at once. The terms are grouped once per plan (:class:`_Terms`): all audio terms
    of the utterance go through one compiled call over the packed audio GPs of its state
    models (:class:`~bayes_talk.gp.predictive_fused.PackedGPs`), all dynamics steps through
    another, the smoothness factors through three, each model's Cholesky factor read once
    per call. ``hessian(X)`` is exact-gradient central differences term by term: each term
    depends on one frame (audio) or one pair of neighbouring frames (dynamics, smoothness),
    so its d×d or 2d×2d Hessian block comes from 2·d or 2·2d perturbed copies of its own
    rows; the entry densities' blocks are exact (−Σ_π⁻¹). The result is block-tridiagonal.
    """

    def __init__(self, plan: UtterancePlan):
        self.plan = plan
        self.T, self.d = plan.n_frames, plan.latent_dim
        self.n_evals = 0
        self.terms = _Terms(plan)

    def __call__(self, X: np.ndarray) -> tuple[float, np.ndarray]:
        X = np.asarray(X, dtype=np.float64).reshape(self.T, self.d)
        lp, G = self.batch(X[None])
        return float(lp[0]), G[0]

    def batch(self, Xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ln p, ∂ ln p/∂X) at K points at once: Xb (K, T, d) → ((K,), (K, T, d)).
        The K copies of each term's row are laid out next to each other (one GP run)."""
        Xb = np.asarray(Xb, dtype=np.float64).reshape(-1, self.T, self.d)
        K, d = Xb.shape[0], self.d
        self.n_evals += K
        tm = self.terms
        lp = np.zeros(K)
        G = np.zeros_like(Xb)

        def rows(idx: np.ndarray) -> np.ndarray:      # frames idx of every point, row-major by frame
            return Xb[:, idx].transpose(1, 0, 2).reshape(-1, d)

        def add(idx: np.ndarray, g: np.ndarray) -> None:
            G[:, idx] += g.reshape(len(idx), K, d).transpose(1, 0, 2)

        if len(tm.a_idx):
            ll, gx = tm.audio_grad(rows(tm.a_idx), K)
            lp += ll.reshape(-1, K).sum(0)
            add(tm.a_idx, gx)
        if len(tm.d_src):
            ll, g = tm.dynamics_grad(np.concatenate([rows(tm.d_src), rows(tm.d_dst)], 1), K)
            lp += ll.reshape(-1, K).sum(0)
            add(tm.d_src, g[:, :d])
            add(tm.d_dst, g[:, d:])
        if len(tm.e_idx):
            ll, g = tm.entry_grad(Xb[:, tm.e_idx])
            lp += ll
            G[:, tm.e_idx] += g
        if len(tm.s_idx):
            ll, g = tm.smooth_grad(np.concatenate([rows(tm.s_idx - 1), rows(tm.s_idx)], 1), K)
            lp += ll.reshape(-1, K).sum(0)
            add(tm.s_idx - 1, g[:, :d])
            add(tm.s_idx, g[:, d:])
        return lp, G

    def values(self, Xb: np.ndarray) -> np.ndarray:
        """ln p at K points (K, T, d) → (K,), without the gradient: only the forward
        substitutions of the predictive variances (emcee's walkers, the k̂ draws)."""
        Xb = np.asarray(Xb, dtype=np.float64).reshape(-1, self.T, self.d)
        K, d = Xb.shape[0], self.d
        self.n_evals += K
        tm = self.terms

        def rows(idx: np.ndarray) -> np.ndarray:
            return Xb[:, idx].transpose(1, 0, 2).reshape(-1, d)

        def gauss(y: np.ndarray, mu: np.ndarray, var: np.ndarray) -> np.ndarray:   # per-row ln N, summed per point
            r = y - mu
            return (-0.5 * (LOG_2PI + np.log(var) + r * r / var)).sum(1).reshape(-1, K).sum(0)

        lp = np.zeros(K)
        if len(tm.a_idx):
            mu, s = tm.audio_gps.mean_var(tm.a_runs.repeat(K), rows(tm.a_idx))
            lp += gauss(np.repeat(tm.a_Y, K, axis=0), mu, s[:, None] / tm.audio_gps.w2[tm.a_runs.row_gp(K)])
        if len(tm.d_src):
            mu, s = tm.dyn_gps.mean_var(tm.d_runs.repeat(K), rows(tm.d_src))
            lp += gauss(rows(tm.d_dst), mu, s[:, None] / tm.dyn_gps.w2[tm.d_runs.row_gp(K)])
        if len(tm.e_idx):
            lp += tm.entry_grad(Xb[:, tm.e_idx])[0]
        if len(tm.s_idx):
            lp += tm.smooth_grad(np.concatenate([rows(tm.s_idx - 1), rows(tm.s_idx)], 1), K)[0].reshape(-1, K).sum(0)
        return lp

    def hessian(self, X: np.ndarray, h: float = 1e-6) -> np.ndarray:
        """Dense (T·d)×(T·d) Hessian of ln p at X (block-tridiagonal, symmetrised), term by
        term (class docstring)."""
        X = np.asarray(X, dtype=np.float64).reshape(self.T, self.d)
        T, d = self.T, self.d
        H4 = np.zeros((T, d, T, d))
        tm = self.terms
        if len(tm.a_idx):
            H4[tm.a_idx, :, tm.a_idx, :] += _fd_blocks(lambda R, k: tm.audio_grad(R, k)[1], X[tm.a_idx], h)
        if len(tm.d_src):
            Hb = _fd_blocks(lambda R, k: tm.dynamics_grad(R, k)[1], np.concatenate([X[tm.d_src], X[tm.d_dst]], 1), h)
            _add_pairs(H4, tm.d_src, tm.d_dst, Hb, d)
        if len(tm.e_idx):                                              # −Σ⁻¹ = −L⁻ᵀL⁻¹
            H4[tm.e_idx, :, tm.e_idx, :] -= np.einsum("eki,ekj->eij", tm.e_chol_inv, tm.e_chol_inv)
        if len(tm.s_idx):
            Hb = _fd_blocks(lambda R, k: tm.smooth_grad(R, k)[1], np.concatenate([X[tm.s_idx - 1], X[tm.s_idx]], 1), h)
            _add_pairs(H4, tm.s_idx - 1, tm.s_idx, Hb, d)
        H = H4.reshape(T * d, T * d)
        return 0.5 * (H + H.T)


def _fd_blocks(grad, R: np.ndarray, h: float) -> np.ndarray:
    """Per-row Hessian blocks (n, m, m) of a sum of row-wise terms, by central differences:
    ``grad(rows, k)`` is the gradient of every row of a layout in which each of the n rows
    is repeated k times in place; here k = 2m (each coordinate perturbed by ±h)."""
    n, m = R.shape
    E = np.concatenate([h * np.eye(m), -h * np.eye(m)])              # (2m, m)
    Gp = grad((R[:, None, :] + E[None]).reshape(-1, m), 2 * m).reshape(n, 2 * m, m)
    return np.transpose((Gp[:, :m] - Gp[:, m:]) / (2 * h), (0, 2, 1))  # (n, i, j): ∂g_i/∂r_j


def _add_pairs(H4: np.ndarray, src: np.ndarray, dst: np.ndarray, Hb: np.ndarray, d: int) -> None:
    """Add 2d×2d blocks over (x_src, x_dst) pairs to the (T, d, T, d) Hessian."""
    H4[src, :, src, :] += Hb[:, :d, :d]
    H4[src, :, dst, :] += Hb[:, :d, d:]
    H4[dst, :, src, :] += Hb[:, d:, :d]
    H4[dst, :, dst, :] += Hb[:, d:, d:]


class _Terms:
    """The density's terms as rows, grouped by GP once per plan.

    Audio rows: frames ``a_idx`` (sorted by state model) under the packed audio GPs;
    dynamics rows: steps x_src → x_dst (``d_src`` = ``d_dst`` − 1, inside blocks and across
    linked boundaries) under the packed dynamics GPs; smoothness rows: block starts
    ``s_idx`` (pairs x_{a−1}, x_a) under the packed visual GPs; entries: frames ``e_idx``
    (unlinked block starts) with μ_π and the inverse Cholesky factor of Σ_π. No frame repeats within a kind of row,
    so scattered gradients are added with fancy indexing. The ``*_grad`` methods take rows
    in which each term's row is repeated k times in place (k batched points or k perturbed
    copies) and return per-row (ℓ, gradient)."""

    def __init__(self, plan: UtterancePlan):
        packs: dict[str, dict[int, object]] = {"audio": {}, "dyn": {}, "vis": {}}

        def gp_index(kind: str, pred) -> int:
            """The index of predictor ``pred`` in the pack of its kind (added if new)."""
            pack = packs[kind]
            if id(pred) not in pack:
                pack[id(pred)] = numpy_gp(pred)
            return list(pack).index(id(pred))

        audio, dyn, smooth, entries = [], [], [], []
        blocks = plan.blocks
        for i, b in enumerate(blocks):
            a, e = b.start, b.stop
            g = gp_index("audio", b.model.predictors_["audio"])
            audio += [(g, t) for t in range(a, e)]
            lo = a - 1 if b.linked else a
            if b.model.dynamics_predictor_ is not None and e - lo > 1:
                g = gp_index("dyn", b.model.dynamics_predictor_)
                dyn += [(g, t) for t in range(lo + 1, e)]
            if not b.linked:
                entries.append(b)
            if b.smooth:
                smooth.append((gp_index("vis", blocks[i - 1].model.predictors_["visual"]),
                               gp_index("vis", b.model.predictors_["visual"]), a))
        audio.sort()
        dyn.sort()
        smooth.sort()
        self.audio_gps = PackedGPs(list(packs["audio"].values()))
        self.a_idx = np.array([t for _, t in audio], dtype=np.int64)
        self.a_runs = Runs.of(np.array([g for g, _ in audio]))
        self.a_Y = plan.audio[self.a_idx]
        self.dyn_gps = PackedGPs(list(packs["dyn"].values())) if dyn else None
        self.d_dst = np.array([t for _, t in dyn], dtype=np.int64)
        self.d_src = self.d_dst - 1
        self.d_runs = Runs.of(np.array([g for g, _ in dyn]))
        self.vis_gps = PackedGPs(list(packs["vis"].values())) if smooth else None
        self.s_idx = np.array([a for _, _, a in smooth], dtype=np.int64)   # sorted by the previous model
        self.s_prev_runs = Runs.of(np.array([p for p, _, _ in smooth]))
        order = np.argsort([v for _, v, _ in smooth], kind="stable")        # the same rows by this block's model
        self.s_order = order
        self.s_vis_runs = Runs.of(np.array([smooth[j][1] for j in order]))
        self.motion_var = plan.motion_var
        self.e_idx = np.array([b.start for b in entries], dtype=np.int64)
        self.e_mean = np.array([b.entry_mean for b in entries]).reshape(len(entries), plan.latent_dim)
        self.e_chol_inv = np.array([np.linalg.inv(b.entry_chol) for b in entries]).reshape(
            len(entries), plan.latent_dim, plan.latent_dim)
        self.e_const = sum(b.entry_logdet_half + 0.5 * plan.latent_dim * LOG_2PI for b in entries)

    def entry_grad(self, Xe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Σ_e ln N(x_e; μ_e, Σ_e) (K,) and its gradient (K, E, d) at the entry frames Xe (K, E, d)."""
        u = np.einsum("eij,kej->kei", self.e_chol_inv, Xe - self.e_mean)        # L_e⁻¹ (x − μ)
        return -0.5 * (u * u).sum((1, 2)) - self.e_const, -np.einsum("eji,kej->kei", self.e_chol_inv, u)

    def audio_grad(self, R: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-row ℓ and ∂ℓ/∂x of the audio terms at rows R (len(a_idx)·k, d)."""
        ll, gx, _ = self.audio_gps.loglik(self.a_runs.repeat(k), np.repeat(self.a_Y, k, axis=0), R)
        return ll, gx

    def dynamics_grad(self, R: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-row ℓ and ∂ℓ/∂(x_src, x_dst) of the dynamics steps at rows R = [x_src, x_dst]."""
        d = R.shape[1] // 2
        ll, g_in, g_out = self.dyn_gps.loglik(self.d_runs.repeat(k), R[:, d:], R[:, :d])
        return ll, np.concatenate([g_in, g_out], 1)

    def smooth_grad(self, R: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-row smoothness factor ln N(μ_Z^{π'}(x_{a−1}); μ_Z^π(x_a), σ²_Z^π(x_a)/w² + s²_Δ) and
        its gradient in (x_{a−1}, x_a) at rows R = [x_{a−1}, x_a] (through π''s visual mean)."""
        d = R.shape[1] // 2
        prev_runs = self.s_prev_runs.repeat(k)
        z_prev, _ = self.vis_gps.mean_var(prev_runs, R[:, :d])
        perm = (self.s_order[:, None] * k + np.arange(k)).reshape(-1)   # rows in this block's model order
        ll_p, g_a_p, g_z_p = self.vis_gps.loglik(self.s_vis_runs.repeat(k), z_prev[perm], R[perm, d:], self.motion_var)
        ll, g_a, g_z = np.empty_like(ll_p), np.empty_like(g_a_p), np.empty_like(g_z_p)
        ll[perm], g_a[perm], g_z[perm] = ll_p, g_a_p, g_z_p
        return ll, np.concatenate([self.vis_gps.mean_vjp(prev_runs, R[:, :d], g_z), g_a], 1)


__all__ = ["UtteranceDensity"]
