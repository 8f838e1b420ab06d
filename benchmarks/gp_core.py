"""Benchmark of the GP core against GPy.

Everything below is measured in one run, on the same machine load:

(a) like for like: one objective + gradient evaluation of our single-view GPLVM
    (``SGPDM(latent_dim=8, dynamics=False, learn_w=False)``, D = 50) against
    ``GPy.models.GPLVM`` with the same N, d = 8, D = 50, an isotropic RBF kernel and a
    Gaussian likelihood (the same free parameters: X, α, γ ↔ lengthscale, β ↔ noise).
    * gpy:        what GPy's optimiser does per step, ``m._objective_grads(x)``, i.e.
                  ``m.optimizer_array = x`` (recomputes K, its Cholesky/inverse and all
                  gradients in ``parameters_changed``), then ``m.objective_function()``
                  and ``m.objective_function_gradients()`` (transformed to x-space).
                  x alternates between two nearby vectors so no cache can answer.
    * ours_pyro:  ``loss = -m.log_joint(); loss.backward()`` through the Pyro trace
                  (``sgpdm_program.trace_log_joint``: X prior, observation term, 1/θ hyperprior).
    * ours_direct: the same, by the model's default path (the same site
                  log-densities summed without the trace, equal bit for bit:
                  ``sgpdm_program.sgpdm_log_joint``).
    * ours_np:    the same objective and gradient as the fit evaluates them in its
                  direct fit: ``models.sgpdm_objective.SGPDMObjective`` on the flat
                  parameters (hand-written gradient, NumPy, no autograd).
    * ours_raw:   ``bayes_talk.gp.terms.observation_loglik(Y, X, α, γ, β, w)`` with X and
                  log α, log γ, log β requiring grad, plus backward (no Pyro overhead).
    * ours_raw_torch: the same term through the torch path (``train_cov`` + the Cholesky
                  autograd function of terms.py), the alternative to the fused
                  path, measured side by side.
    * floor_ours / floor_gpy: the LAPACK calls alone on this N×N kernel matrix, timed
                  without the copy that precedes them: ours ``dpotrf`` + ``dpotri``
                  (bayes_talk.gp.lapack's provider), GPy's ``pdinv`` ``dpotrf`` +
                  ``dtrtri`` + ``dpotri`` (scipy). The SGPDM has three kernels (two views
                  and the dynamics), so its floor is about 3 × floor_ours.
(b) sgpdm_full: the two-view SGPDM with dynamics (views D = 20 + 30,
    ``SGPDM(latent_dim=8, max_iter=1)``, default fixed dynamics): one log joint +
    gradient (autograd of the direct log joint; ``sgpdm_full_pyro`` through the trace;
    ``sgpdm_full_np`` the fit's NumPy objective and gradient); reported
    as a ratio to the same GPy figure.

Every timing is the median of ``--repeats`` calls after one warm-up; the
variants are interleaved within each repeat so they see the same machine load. With
``--block K`` (default 1) each variant runs K times in a row within a repeat and only the
K-th call is timed: the steady state of an optimiser's loop, where one library's calls follow
its own. With K = 1 each timed call follows another variant's, so a call pays for what the
previous one left behind (other BLAS/OpenMP pools still spinning, cold caches).
A correctness check compares our GPLVM objective with GPy's at one small N, and a
profile splits one of our evaluations at the largest N into its parts.

Run:  .venv/bin/python benchmarks/gp_core.py [--quick] [--out PATH] [--repeats 5] [--block 1]
      [--threads 1] [--sizes 1000,2000] [--no-fused] [--lapack scipy]
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import result_path, write_result

D_GPLVM = 50
D_VIEWS = {"audio": 20, "visual": 30}
LATENT = 8
FULL_SIZES = (200, 500, 1000, 2000)
QUICK_SIZES = (200, 400)
CHECK_N = 200


# ---------------------------------------------------------------------------- data
def synthetic(N: int, D: int, seed: int) -> np.ndarray:
    """Smooth 8-d latent trajectory pushed through a random nonlinear map, plus noise."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 20.0, N)[:, None]
    freqs = rng.uniform(0.2, 1.5, LATENT)
    phases = rng.uniform(0, 2 * np.pi, LATENT)
    Xt = np.sin(t * freqs + phases)
    A = rng.standard_normal((LATENT, D))
    return np.tanh(Xt @ A) + 0.1 * rng.standard_normal((N, D))


def quiet_fit(model, views):
    logging.getLogger("bayes_talk").setLevel(logging.ERROR)
    return model.fit(views)


# ---------------------------------------------------------------------------- setups
def pyro_log_joint(m):
    """The model's log joint as its Pyro trace's ``log_prob_sum()``
    (``sgpdm_program.trace_log_joint``), on the threads ``SGPDM.log_joint`` uses."""
    from bayes_talk.gp.threads import problem_threads
    from bayes_talk.models.sgpdm_program import trace_log_joint

    with problem_threads(sum(m.seq_lengths_)):
        return trace_log_joint(m._Y, m._latents(), m._hyper(), m.seq_lengths_, m.config, m._learned_thetas())


class Ours:
    """Our single-view GPLVM: Pyro log joint and the raw observation term."""

    def __init__(self, N: int):
        from bayes_talk.models.sgpdm import SGPDM

        Y = synthetic(N, D_GPLVM, seed=N)
        self.m = quiet_fit(SGPDM(latent_dim=LATENT, dynamics=False, learn_w=False, max_iter=1), {"y": Y})
        self.free = self.m._free_tensors()
        # raw variant: copies of the fitted state, independent leaves
        self.Y = self.m._Y["y"]
        self.w = self.m._fixed["w/y"]
        self.X = self.m._X.detach().clone().requires_grad_(True)
        self.logs = [self.m._log[f"{k}/y"].detach().clone().requires_grad_(True)
                     for k in ("alpha", "gamma", "beta")]

    def pyro_eval(self) -> float:
        for t in self.free:
            t.grad = None
        loss = -pyro_log_joint(self.m)
        loss.backward()
        return float(loss.detach())

    def direct_eval(self) -> float:
        for t in self.free:
            t.grad = None
        loss = -self.m.log_joint()
        loss.backward()
        return float(loss.detach())

    def np_eval(self) -> float:
        return _np_objective(self)

    def raw_eval(self) -> float:
        from bayes_talk.gp.terms import observation_loglik

        for t in [self.X, *self.logs]:
            t.grad = None
        a, g, b = (torch.exp(v) for v in self.logs)
        loss = -observation_loglik(self.Y, self.X, a, g, b, self.w)
        loss.backward()
        return float(loss.detach())

    def raw_torch_eval(self) -> float:
        from bayes_talk.base import settings

        with settings.override(fused=False):
            return self.raw_eval()

    def kernel_matrix(self) -> np.ndarray:
        """K at the fitted state, Fortran-ordered (what the LAPACK floors factorise)."""
        from bayes_talk.gp.kernels import train_cov

        a, g, b = (torch.exp(v.detach()) for v in self.logs)
        return np.asfortranarray(train_cov(self.X.detach(), a, g, b).numpy())

    def hyper(self) -> tuple[float, float, float]:
        return tuple(float(torch.exp(self.m._log[f"{k}/y"].detach())) for k in ("alpha", "gamma", "beta"))


class Gpy:
    """GPy's GPLVM at the same point as ours (X, α, γ, β, data scaled by w)."""

    def __init__(self, ours: Ours):
        import GPy

        alpha, gamma, beta = ours.hyper()
        Yw = (ours.Y * ours.w).numpy()
        X = ours.m._X.detach().numpy().copy()
        kern = GPy.kern.RBF(LATENT, variance=alpha, lengthscale=1.0 / math.sqrt(gamma), ARD=False)
        self.m = GPy.models.GPLVM(Yw, LATENT, X=X, kernel=kern)
        self.m.likelihood.variance = 1.0 / beta
        self.x0 = self.m.optimizer_array.copy()
        self.x1 = self.x0 * (1.0 + 1e-12)
        self.flip = False

    def eval(self) -> float:
        # what paramz's Model._objective_grads does for the optimiser on every step
        self.flip = not self.flip
        x = self.x1 if self.flip else self.x0
        self.m.optimizer_array = x
        obj = self.m.objective_function()
        grad = self.m._transform_gradients(self.m.objective_function_gradients())
        assert np.all(np.isfinite(grad))
        return float(obj)


class Full:
    """The two-view SGPDM with (fixed) dynamics."""

    def __init__(self, N: int):
        from bayes_talk.models.sgpdm import SGPDM

        views = {v: synthetic(N, D, seed=N + i + 1) for i, (v, D) in enumerate(D_VIEWS.items())}
        self.m = quiet_fit(SGPDM(latent_dim=LATENT, max_iter=1), views)
        self.free = self.m._free_tensors()

    def eval(self) -> float:
        for t in self.free:
            t.grad = None
        loss = -self.m.log_joint()
        loss.backward()
        return float(loss.detach())

    def pyro_eval(self) -> float:
        for t in self.free:
            t.grad = None
        loss = -pyro_log_joint(self.m)
        loss.backward()
        return float(loss.detach())

    def np_eval(self) -> float:
        return _np_objective(self)


def _np_objective(ours) -> float:
    """One evaluation of the fit's NumPy objective and gradient at ``ours.m``'s parameters."""
    from bayes_talk.models.sgpdm_objective import SGPDMObjective

    if not hasattr(ours, "_np"):
        m = ours.m
        ours._np = SGPDMObjective({v: Y.numpy() for v, Y in m._Y.items()}, m.seq_lengths_, m.config,
                                  {k: tuple(t.shape) for k, t in m._log.items()},
                                  {k: t.detach().numpy() for k, t in m._fixed.items()}, m._learned_thetas())
        ours._np_x = torch.cat([t.detach().reshape(-1) for t in ours.free]).numpy()
    f, _ = ours._np(ours._np_x)
    return float(f)


# ---------------------------------------------------------------------------- timing
def timed(fn) -> tuple[float, float]:
    """(wall, CPU) seconds of one call; CPU time (all threads of this process) is robust to
    other processes on a shared machine, and with ``--threads 1`` it is the work done."""
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t0, time.process_time() - c0


def lapack_floors(K: np.ndarray) -> dict:
    """Timers of the LAPACK calls alone on copies of K: ours (dpotrf + dpotri through
    bayes_talk.gp.lapack) and GPy's pdinv (scipy dpotrf + dtrtri + dpotri)."""
    from scipy.linalg import lapack as sl

    from bayes_talk.gp.lapack import potrf_lower, potri_lower

    work = np.empty_like(K, order="F")

    def ours() -> tuple[float, float]:
        np.copyto(work, K)
        t0, c0 = time.perf_counter(), time.process_time()
        if potrf_lower(work) != 0 or potri_lower(work) != 0:
            raise RuntimeError("LAPACK floor: K is not positive definite")
        return time.perf_counter() - t0, time.process_time() - c0

    def gpy() -> tuple[float, float]:
        np.copyto(work, K)
        t0, c0 = time.perf_counter(), time.process_time()
        L, info = sl.dpotrf(work, lower=1, overwrite_a=1)
        _Li, info2 = sl.dtrtri(L, lower=1)
        _Ki, info3 = sl.dpotri(L, lower=1)
        if info or info2 or info3:
            raise RuntimeError("LAPACK floor: K is not positive definite")
        return time.perf_counter() - t0, time.process_time() - c0

    return {"floor_ours": ours, "floor_gpy": gpy}


RATIO_KEYS = ("ours_pyro", "ours_direct", "ours_np", "ours_raw", "ours_raw_torch", "sgpdm_full", "sgpdm_full_pyro",
              "sgpdm_full_np", "floor_ours", "floor_gpy")


def bench_size(N: int, repeats: int, block: int = 1) -> dict:
    t0 = time.perf_counter()
    ours = Ours(N)
    gpy = Gpy(ours)
    full = Full(N)
    setup = time.perf_counter() - t0
    fns = {"gpy": gpy.eval, "ours_pyro": ours.pyro_eval, "ours_direct": ours.direct_eval, "ours_np": ours.np_eval,
           "ours_raw": ours.raw_eval, "ours_raw_torch": ours.raw_torch_eval, "sgpdm_full": full.eval,
           "sgpdm_full_pyro": full.pyro_eval, "sgpdm_full_np": full.np_eval}
    self_timed = lapack_floors(ours.kernel_matrix())
    for f in [*fns.values(), *self_timed.values()]:  # warm-up
        f()
    times: dict[str, list[float]] = {k: [] for k in [*fns, *self_timed]}
    cpu: dict[str, list[float]] = {k: [] for k in times}
    order = list(times)
    for r in range(repeats):
        # interleave, rotating the order so no variant always runs first
        for k in order[r % len(order):] + order[: r % len(order)]:
            run = self_timed[k] if k in self_timed else (lambda k=k: timed(fns[k]))
            for _ in range(block - 1):  # untimed calls of the same variant first (--block)
                run()
            w, c = run()
            times[k].append(w)
            cpu[k].append(c)
    med = {k: statistics.median(v) for k, v in times.items()}
    cmed = {k: statistics.median(v) for k, v in cpu.items()}
    return {
        "N": N,
        "setup_s": setup,
        "seconds": {k: {"median": med[k], "all": times[k]} for k in times},
        "cpu_seconds": {k: {"median": cmed[k], "all": cpu[k]} for k in times},
        "ratio_to_gpy": {k: med[k] / med["gpy"] for k in RATIO_KEYS},
        "cpu_ratio_to_gpy": {k: cmed[k] / cmed["gpy"] for k in RATIO_KEYS},
        "sgpdm_floor_estimate_ratio_to_gpy": 3.0 * med["floor_ours"] / med["gpy"],
        "sgpdm_floor_estimate_cpu_ratio_to_gpy": 3.0 * cmed["floor_ours"] / cmed["gpy"],
    }


# ---------------------------------------------------------------------------- correctness
def correctness(N: int) -> dict:
    """Our GPLVM objective against GPy's at the same point.

    GPy's GPLVM has NO prior on X and no hyperprior: its objective is
    −ln N(Yw; 0, K + (β⁻¹ + 1e-8) I) (GPy adds 1e-8 to the noise variance). Ours
    (the Pyro log joint) adds N Σ ln w_m (the paper's |W|^N), ln N(X; 0, I) and
    −Σ ln θ over α, γ, β. We report the raw difference and what is left after
    accounting for each of these terms.
    """
    from bayes_talk.gp.terms import log_hyperprior, observation_loglik

    ours = Ours(N)
    gpy = Gpy(ours)
    gpy.m.optimizer_array = gpy.x0
    gpy_obj = float(gpy.m.objective_function())
    gpy_grad_X = -np.asarray(gpy.m.X.gradient)  # d(objective)/dX
    ours_obj = float(-ours.m.log_joint().detach())
    alpha, gamma, beta = ours.hyper()
    X = ours.m._X.detach()
    w = ours.w
    Nn = ours.Y.shape[0]
    lnw = float(Nn * torch.log(w).sum())
    x_prior = float(-0.5 * (X * X).sum() - 0.5 * X.numel() * math.log(2 * math.pi))
    hyper = float(log_hyperprior([torch.tensor(v, dtype=torch.float64) for v in (alpha, gamma, beta)]))
    # our observation term with GPy's 1e-8 added to the noise variance, on Yw directly
    beta_g = 1.0 / (1.0 / beta + 1e-8)
    Xg = X.clone().requires_grad_(True)
    ones = torch.ones_like(w)
    obs_g = observation_loglik(ours.Y * w, Xg, torch.tensor(alpha, dtype=torch.float64),
                               torch.tensor(gamma, dtype=torch.float64),
                               torch.tensor(beta_g, dtype=torch.float64), ones)
    (-obs_g).backward()
    obs_plain = float(observation_loglik(ours.Y, X, *(torch.tensor(v, dtype=torch.float64)
                                                     for v in (alpha, gamma, beta)), w))
    explained = -(x_prior + hyper) - obs_plain  # obs_plain already holds N Σ ln w
    return {
        "N": N,
        "gpy_objective": gpy_obj,
        "ours_objective_pyro": ours_obj,
        "difference_ours_minus_gpy": ours_obj - gpy_obj,
        "terms_in_ours_not_in_gpy": {
            "N_sum_ln_w": lnw,
            "ln_N_X_0_I": x_prior,
            "hyperprior_minus_sum_ln_theta": hyper,
        },
        "ours_minus_extra_terms_minus_gpy": (ours_obj + lnw + x_prior + hyper) - gpy_obj,
        "check_explained_equals_ours": explained - ours_obj,
        "ours_obs_term_with_gpy_jitter_minus_gpy": float(-obs_g) - gpy_obj,
        "max_abs_dX_difference_obs_term_vs_gpy": float(np.abs(Xg.grad.numpy() - gpy_grad_X).max()),
        "max_abs_dX_gpy": float(np.abs(gpy_grad_X).max()),
        "note": "GPy GPLVM objective = -ln p(Yw|X) only (no prior on X, no hyperprior, "
                "noise variance + 1e-8); ours adds N*sum(ln w), ln N(X;0,I) and -sum ln theta.",
    }


# ---------------------------------------------------------------------------- profile
def profile(N: int, repeats: int) -> dict:
    """Split one evaluation of our observation term at size N into its parts: the fused
    path's (bayes_talk/gp/fused.py) compiled passes and LAPACK calls, and the torch
    path's Cholesky and cholesky_inverse for comparison."""
    from bayes_talk.gp import fused
    from bayes_talk.gp.lapack import potrf_lower, potri_lower, potrs_lower

    ours = Ours(N)
    Xn = np.ascontiguousarray(ours.X.detach().numpy())
    V = np.asfortranarray((ours.Y * ours.w).numpy())
    a, g, b = (float(torch.exp(v.detach())) for v in ours.logs)
    buf = np.empty((N, N), order="F")
    A = np.empty_like(V, order="F")

    def parts() -> dict[str, float]:
        out = {}

        def step(name, fn):
            t = time.perf_counter()
            r = fn()
            out[name] = time.perf_counter() - t
            return r

        step("build_K_and_E", lambda: fused._build(Xn, a, g, 1.0 / b, buf, fused.N_CHUNKS))
        if step("dpotrf", lambda: potrf_lower(buf)) != 0:
            raise RuntimeError("profile: K is not positive definite")
        np.copyto(A, V)
        step("dpotrs", lambda: potrs_lower(buf, A))
        step("dpotri", lambda: potri_lower(buf))
        step("gradient_pass", lambda: fused._gradient(Xn, buf, np.ascontiguousarray(A), a, fused.N_CHUNKS))
        Kt = torch.from_numpy(ours.kernel_matrix())
        L = step("torch_cholesky", lambda: torch.linalg.cholesky(Kt))
        step("torch_cholesky_inverse", lambda: torch.cholesky_inverse(L))
        return out

    parts()
    runs = [parts() for _ in range(repeats)]
    res = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    return {"N": N, "parts_median_s": res}


# ---------------------------------------------------------------------------- main
def machine_info() -> dict:
    import GPy
    import pyro
    import scipy

    info = {
        "nproc": os.cpu_count(),
        "sched_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "loadavg_at_start": os.getloadavg(),
        "torch_threads": torch.get_num_threads(),
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "versions": {"torch": torch.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
                     "GPy": GPy.__version__, "pyro": pyro.__version__},
    }
    try:
        from threadpoolctl import threadpool_info

        root = Path(__file__).resolve().parents[1]

        def where(path):   # a library inside the repository (its .venv) by a relative path
            p = Path(path) if path else None
            return str(p.relative_to(root)) if p is not None and p.is_relative_to(root) else path

        info["blas"] = [{**{k: d.get(k) for k in ("internal_api", "num_threads", "version")},
                         "filepath": where(d.get("filepath"))} for d in threadpool_info()]
    except ImportError:
        pass
    return info


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=None, help="default results/gp_core.json (--quick: results/quick/)")
    p.add_argument("--quick", action="store_true", help=f"N = {QUICK_SIZES} only, 2 repeats")
    p.add_argument("--repeats", type=int, default=None, help="default 5 (--quick: 2)")
    p.add_argument("--block", type=int, default=1,
                   help="calls of a variant in a row per repeat, the last one timed (default 1: "
                        "every timed call follows another variant's)")
    p.add_argument("--no-profile", action="store_true")
    p.add_argument("--no-fused", action="store_true",
                   help="our terms through the torch path instead of bayes_talk/gp/fused.py "
                        "(also BAYES_TALK_FUSED=0)")
    p.add_argument("--lapack", choices=("torch-mkl", "scipy"), default=None,
                   help="LAPACK provider of the fused path (default: bayes_talk.gp.lapack's)")
    p.add_argument("--sizes", default=None, help="comma-separated N (default: 200,500,1000,2000)")
    p.add_argument("--threads", type=int, default=None,
                   help="limit torch and BLAS/OpenMP threads (default: leave as found)")
    args = p.parse_args(argv)
    args.out = result_path("gp_core", args.quick, args.out)
    if args.repeats is None:
        args.repeats = 2 if args.quick else 5
    if args.block < 1:
        p.error(f"--block must be >= 1, got {args.block}")
    from bayes_talk.base import settings
    from bayes_talk.gp import lapack

    if args.no_fused:
        settings.set_switch("fused", False)
    if args.lapack:
        lapack.set_provider(args.lapack)
    limiter = None
    if args.threads is not None:
        torch.set_num_threads(args.threads)
        from threadpoolctl import threadpool_limits

        limiter = threadpool_limits(limits=args.threads)  # noqa: F841 (kept alive for the run)
    sizes = QUICK_SIZES if args.quick else FULL_SIZES
    if args.sizes:
        sizes = tuple(int(s) for s in args.sizes.split(",") if s.strip())
    t_start = time.perf_counter()
    result = {
        "benchmark": "gp_core",
        "machine": machine_info(),
        "settings": {"d": LATENT, "D_gplvm": D_GPLVM, "D_views": D_VIEWS, "repeats": args.repeats, "block": args.block,
                     "warmup": 1, "sizes": list(sizes),
                     "threads_limit": args.threads,
                     "fused": bool(settings.get("fused")), "lapack_provider": lapack.provider()},
        "correctness": correctness(CHECK_N),
        "sizes": [],
    }
    print(f"{'N':>5} {'gpy':>9} {'ours_pyro':>10} {'ours_raw':>9} {'sgpdm_full':>10}  "
          f"{'pyro/gpy':>8} {'direct/gpy':>10} {'raw/gpy':>8} {'full/gpy':>8} {'torch/gpy':>9} {'floor/gpy':>9} "
          f"{'gpyfloor/gpy':>12}")
    for N in sizes:
        r = bench_size(N, args.repeats, args.block)
        result["sizes"].append(r)
        s, q = r["seconds"], r["ratio_to_gpy"]
        print(f"{N:>5} {s['gpy']['median']:>9.4f} {s['ours_pyro']['median']:>10.4f} "
              f"{s['ours_raw']['median']:>9.4f} {s['sgpdm_full']['median']:>10.4f}  "
              f"{q['ours_pyro']:>8.2f} {q['ours_direct']:>10.2f} {q['ours_raw']:>8.2f} {q['sgpdm_full']:>8.2f} "
              f"{q['ours_raw_torch']:>9.2f} {q['floor_ours']:>9.2f} {q['floor_gpy']:>12.2f}", flush=True)
        c = r["cpu_ratio_to_gpy"]
        print(f"{'':>5} CPU-time ratios: pyro/gpy {c['ours_pyro']:.2f}  direct/gpy {c['ours_direct']:.2f}  "
              f"np/gpy {c['ours_np']:.2f}  full_np/gpy {c['sgpdm_full_np']:.2f}  "
              f"raw/gpy {c['ours_raw']:.2f}  "
              f"full/gpy {c['sgpdm_full']:.2f}  torch/gpy {c['ours_raw_torch']:.2f}  "
              f"floor/gpy {c['floor_ours']:.2f}  gpyfloor/gpy {c['floor_gpy']:.2f}", flush=True)
    if not args.no_profile:
        result["profile"] = profile(max(sizes), args.repeats)
        print(f"profile at N={max(sizes)} (median s):")
        for k, v in result["profile"]["parts_median_s"].items():
            print(f"  {k:<30} {v:.4g}")
    c = result["correctness"]
    print(f"correctness at N={c['N']}: ours-gpy objective {c['difference_ours_minus_gpy']:.6g}; "
          f"after removing prior/W terms {c['ours_minus_extra_terms_minus_gpy']:.3g}; "
          f"obs term with GPy jitter - gpy {c['ours_obs_term_with_gpy_jitter_minus_gpy']:.3g}; "
          f"max |dX diff| {c['max_abs_dX_difference_obs_term_vs_gpy']:.3g}")
    result["machine"]["loadavg_at_end"] = os.getloadavg()
    result["wall_s"] = time.perf_counter() - t_start
    write_result(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
