"""torch's L-BFGS with the strong-Wolfe line search, on one flat NumPy vector.

A port of ``torch.optim.LBFGS`` (``line_search_fn="strong_wolfe"``; itself after
minFunc, Schmidt 2005, and torch7's ``lbfgs.lua`` / ``lswolfe.lua``) operation for
operation: the same two-loop recursion over at most ``history_size`` pairs

    s_k = t_k d_k,   y_k = g_{k+1} − g_k,   ρ_k = 1 / (y_kᵀ s_k)   (kept when y_kᵀ s_k > 1e-10),
    H₀ = y_kᵀ s_k / y_kᵀ y_k,

the same first step ``min(1, 1/‖g‖₁)·lr``, the same cubic interpolation, bracketing and
zoom, the same stopping rules (``tolerance_grad`` on max |g|, ``tolerance_change`` on
the step and on the loss, ``max_iter`` iterations and ``max_eval`` evaluations per
:meth:`LBFGS.step`) and the same state carried from one :meth:`LBFGS.step` to the next.
So it walks the path torch's optimiser walks, to rounding (its dot products are NumPy's,
its ``x + t·d`` is not fused), but each operation on a vector of a few hundred numbers
costs about a microsecond instead of torch's several: at the 60-400 frames of a
switching state the optimiser's own work was a large part of each evaluation.

Why not scipy's ``L-BFGS-B``: a different line search and update walk a different path,
and the state fits stop at their iteration budget, not at convergence, so the fitted
models would change; this keeps them (tests/models/test_sgpdm_direct.py compares the two).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

__all__ = ["LBFGS", "cubic_interpolate", "strong_wolfe"]

Objective = Callable[[np.ndarray], tuple[float, np.ndarray]]


def cubic_interpolate(x1, f1, g1, x2, f2, g2, bounds=None) -> float:
    """Minimiser of the cubic through (x1, f1, g1) and (x2, f2, g2), clipped to ``bounds``
    (default: the interval between x1 and x2); its midpoint when the cubic has none
    (torch.optim.lbfgs._cubic_interpolate)."""
    if bounds is not None:
        xmin_bound, xmax_bound = bounds
    else:
        xmin_bound, xmax_bound = (x1, x2) if x1 <= x2 else (x2, x1)
    d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
    d2_square = d1**2 - g1 * g2
    if d2_square >= 0:
        d2 = math.sqrt(d2_square)
        if x1 <= x2:
            min_pos = x2 - (x2 - x1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
        else:
            min_pos = x1 - (x1 - x2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
        return min(max(min_pos, xmin_bound), xmax_bound)
    return (xmin_bound + xmax_bound) / 2.0


def strong_wolfe(obj_func, x, t, d, f, g, gtd, c1=1e-4, c2=0.9, tolerance_change=1e-9, max_ls=25):
    """Line search for a step t along d satisfying the strong Wolfe conditions
    (torch.optim.lbfgs._strong_wolfe): ``obj_func(x, t, d)`` → (f, g) at x + t·d.
    Returns (f_new, g_new, t, evaluations)."""
    d_norm = float(np.abs(d).max())
    g = g.copy()
    f_new, g_new = obj_func(x, t, d)
    ls_func_evals = 1
    gtd_new = float(g_new @ d)
    t_prev, f_prev, g_prev, gtd_prev = 0, f, g, gtd
    done = False
    ls_iter = 0
    while ls_iter < max_ls:
        if f_new > (f + c1 * t * gtd) or (ls_iter > 1 and f_new >= f_prev):
            bracket, bracket_f = [t_prev, t], [f_prev, f_new]
            bracket_g, bracket_gtd = [g_prev, g_new.copy()], [gtd_prev, gtd_new]
            break
        if abs(gtd_new) <= -c2 * gtd:
            bracket, bracket_f, bracket_g = [t], [f_new], [g_new]
            done = True
            break
        if gtd_new >= 0:
            bracket, bracket_f = [t_prev, t], [f_prev, f_new]
            bracket_g, bracket_gtd = [g_prev, g_new.copy()], [gtd_prev, gtd_new]
            break
        min_step = t + 0.01 * (t - t_prev)
        max_step = t * 10
        tmp = t
        t = cubic_interpolate(t_prev, f_prev, gtd_prev, t, f_new, gtd_new, bounds=(min_step, max_step))
        t_prev, f_prev, g_prev, gtd_prev = tmp, f_new, g_new.copy(), gtd_new
        f_new, g_new = obj_func(x, t, d)
        ls_func_evals += 1
        gtd_new = float(g_new @ d)
        ls_iter += 1
    if ls_iter == max_ls:
        bracket, bracket_f, bracket_g = [0, t], [f, f_new], [g, g_new]

    insuf_progress = False
    low_pos, high_pos = (0, 1) if bracket_f[0] <= bracket_f[-1] else (1, 0)
    while not done and ls_iter < max_ls:
        if abs(bracket[1] - bracket[0]) * d_norm < tolerance_change:
            break
        t = cubic_interpolate(bracket[0], bracket_f[0], bracket_gtd[0], bracket[1], bracket_f[1], bracket_gtd[1])
        eps = 0.1 * (max(bracket) - min(bracket))
        if min(max(bracket) - t, t - min(bracket)) < eps:
            if insuf_progress or t >= max(bracket) or t <= min(bracket):
                if abs(t - max(bracket)) < abs(t - min(bracket)):
                    t = max(bracket) - eps
                else:
                    t = min(bracket) + eps
                insuf_progress = False
            else:
                insuf_progress = True
        else:
            insuf_progress = False
        f_new, g_new = obj_func(x, t, d)
        ls_func_evals += 1
        gtd_new = float(g_new @ d)
        ls_iter += 1
        if f_new > (f + c1 * t * gtd) or f_new >= bracket_f[low_pos]:
            bracket[high_pos], bracket_f[high_pos] = t, f_new
            bracket_g[high_pos], bracket_gtd[high_pos] = g_new.copy(), gtd_new
            low_pos, high_pos = (0, 1) if bracket_f[0] <= bracket_f[1] else (1, 0)
        else:
            if abs(gtd_new) <= -c2 * gtd:
                done = True
            elif gtd_new * (bracket[high_pos] - bracket[low_pos]) >= 0:
                bracket[high_pos], bracket_f[high_pos] = bracket[low_pos], bracket_f[low_pos]
                bracket_g[high_pos], bracket_gtd[high_pos] = bracket_g[low_pos], bracket_gtd[low_pos]
            bracket[low_pos], bracket_f[low_pos] = t, f_new
            bracket_g[low_pos], bracket_gtd[low_pos] = g_new.copy(), gtd_new
    return bracket_f[low_pos], bracket_g[low_pos], bracket[low_pos], ls_func_evals


class LBFGS:
    """Minimises ``fun(x) -> (loss, gradient)`` from ``x0`` like ``torch.optim.LBFGS(...,
    line_search_fn="strong_wolfe")``: :meth:`step` runs at most ``max_iter`` iterations
    (``max_eval``, fixed at construction as in torch, evaluations) and keeps the curvature
    pairs for the next call; :attr:`x` is the current point, :attr:`n_iter` the iterations
    run in all. ``max_iter`` may be changed between calls."""

    def __init__(self, x0: np.ndarray, *, lr: float = 1.0, max_iter: int = 20, max_eval: int | None = None,
                 tolerance_grad: float = 1e-7, tolerance_change: float = 1e-9, history_size: int = 100):
        self.x = np.array(x0, dtype=np.float64).reshape(-1)
        self.lr, self.max_iter = lr, max_iter
        self.max_eval = max_iter * 5 // 4 if max_eval is None else max_eval
        self.tolerance_grad, self.tolerance_change, self.history_size = tolerance_grad, tolerance_change, history_size
        self.n_iter = 0
        self.func_evals = 0
        self._d = self._t = self._H_diag = self._prev_flat_grad = self._prev_loss = None
        self._old_dirs: list[np.ndarray] = []
        self._old_stps: list[np.ndarray] = []
        self._ro: list[float] = []

    def step(self, fun: Objective) -> float:
        """One call of torch's ``LBFGS.step(closure)``; returns the loss at the start."""
        lr, max_iter, max_eval = self.lr, self.max_iter, self.max_eval
        tolerance_grad, tolerance_change = self.tolerance_grad, self.tolerance_change
        orig_loss, flat_grad = fun(self.x)
        loss = float(orig_loss)
        current_evals = 1
        self.func_evals += 1
        if np.abs(flat_grad).max() <= tolerance_grad:
            return orig_loss
        d, t, H_diag = self._d, self._t, self._H_diag
        old_dirs, old_stps, ro = self._old_dirs, self._old_stps, self._ro
        prev_flat_grad, prev_loss = self._prev_flat_grad, self._prev_loss
        n_iter = 0
        while n_iter < max_iter:
            n_iter += 1
            self.n_iter += 1
            if self.n_iter == 1:
                d = -flat_grad
                old_dirs, old_stps, ro = [], [], []
                H_diag = 1
            else:
                y = flat_grad - prev_flat_grad
                s = d * t
                ys = float(y @ s)
                if ys > 1e-10:
                    if len(old_dirs) == self.history_size:
                        old_dirs.pop(0)
                        old_stps.pop(0)
                        ro.pop(0)
                    old_dirs.append(y)
                    old_stps.append(s)
                    ro.append(1.0 / ys)
                    H_diag = ys / float(y @ y)
                num_old = len(old_dirs)
                al = [0.0] * num_old
                q = -flat_grad
                for i in range(num_old - 1, -1, -1):
                    al[i] = float(old_stps[i] @ q) * ro[i]
                    q -= al[i] * old_dirs[i]
                d = r = q * H_diag
                for i in range(num_old):
                    be_i = float(old_dirs[i] @ r) * ro[i]
                    r += (al[i] - be_i) * old_stps[i]
            prev_flat_grad = flat_grad.copy()
            prev_loss = loss
            t = min(1.0, 1.0 / float(np.abs(flat_grad).sum())) * lr if self.n_iter == 1 else lr
            gtd = float(flat_grad @ d)
            if gtd > -tolerance_change:
                break
            x_init = self.x

            def obj_func(x, t, d):
                return fun(x + t * d)

            loss, flat_grad, t, ls_func_evals = strong_wolfe(obj_func, x_init, t, d, loss, flat_grad, gtd,
                                                              max_ls=max_eval - current_evals)
            self.x = self.x + t * d
            opt_cond = np.abs(flat_grad).max() <= tolerance_grad
            current_evals += ls_func_evals
            self.func_evals += ls_func_evals
            if n_iter == max_iter or current_evals >= max_eval or opt_cond:
                break
            if np.abs(d * t).max() <= tolerance_change:
                break
            if abs(loss - prev_loss) < tolerance_change:
                break
        self._d, self._t, self._H_diag = d, t, H_diag
        self._old_dirs, self._old_stps, self._ro = old_dirs, old_stps, ro
        self._prev_flat_grad, self._prev_loss = prev_flat_grad, prev_loss
        return orig_loss
