"""Pairwise 2D registration by particle swarm optimisation, in rounds until a time budget.

The paper's PSO baseline [1] is iralabdisco/pso_registration (Fontana et al.): a swarm of
50 particles, each a rigid transformation, searches the whole domain (translations inside
the target's bounding box, all rotations) for the one that minimises the mean distance of
the moved source points to their nearest target points (its default "l1" score), with
constriction-factor velocity updates, velocities clamped to a quarter of the domain, a ring
neighbourhood and particles reflected at the domain's borders. "We run PSO for multiple
rounds until they consume the same time as DeepMapping" (§4.1): each round is a fresh
swarm, the best pose over all rounds is kept.

Here the same on SE(2) (x, y, theta), the score from a distance transform of the target
(:class:`~deepmapping.geometry.distance_field.DistanceField2D`) so that a swarm step is one
vectorised look-up, optionally trimmed (the largest residuals left out, as
:func:`deepmapping.methods.goicp.goicp_2d`). A round ends after ``iterations`` generations or
when its best score has not improved by ``tol`` (relative) for ``patience`` generations.

Why our own implementation: ``pyswarms`` (1.3.0, last release 2021) installs and works, but
constructing an optimizer reconfigures the root logger of the whole process (a stream
handler and a ``report.log`` file in the working directory, via logging.config.dictConfig),
keeps every generation's positions in memory, and has no time budget; ``pyswarm`` (1.1.2)
does not import here (its Fortran extension needs a libgfortran that is not shipped). The
swarm update is a few lines of numpy.
"""

from __future__ import annotations

import time

import numpy as np

from deepmapping.geometry import se2
from deepmapping.geometry.distance_field import DistanceField2D, clean_points_2d

__all__ = ["pso_register_2d", "incremental_pso"]

# Clerc & Kennedy's constriction (chi = 0.7298, phi = 4.1) in inertia form (pso_registration
# keeps the inertia 0.7298 but weights the attractions 2.1 and 1.9, which lets swarms diverge)
INERTIA, C_COGNITIVE, C_SOCIAL = 0.7298, 1.49618, 1.49618


def pso_register_2d(
    source,
    target,
    *,
    time_budget_s: float | None = None,
    rounds: int | None = None,
    particles: int = 50,
    iterations: int = 1000,
    patience: int = 50,
    tol: float = 1e-4,
    trim_fraction: float = 0.0,
    bounds: tuple | None = None,
    dt_size: int = 1024,
    seed: int = 0,
) -> tuple[np.ndarray, dict]:
    """Register ``source`` (N, 2) onto ``target`` (M, 2): returns (pose (3,), info).

    The pose T satisfies target ≈ T(source) (as :func:`deepmapping.methods.icp.icp_2d`).
    ``bounds``: ((x_lo, y_lo, theta_lo), (x_hi, y_hi, theta_hi)) of the search; None = the
    target's bounding box and all rotations (pso_registration's domain). Rounds run until
    ``time_budget_s`` is spent or ``rounds`` are done (at least one round; one when both are
    None). info: score (mean trimmed nearest-point distance of the pose, input units),
    rounds, generations, time_s.
    """
    t0 = time.perf_counter()
    src = clean_points_2d(source, "source")
    tgt = clean_points_2d(target, "target")
    if bounds is None:
        lo = np.r_[tgt.min(0), -np.pi]
        hi = np.r_[tgt.max(0), np.pi]
    else:
        lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in bounds)
    if not (hi > lo).all():
        raise ValueError("bounds: every upper bound must exceed its lower bound")
    # moved source points outside the grid get their distance to it added: still far
    field = DistanceField2D(tgt, half_extent=max(float(np.abs(tgt).max()), 1e-9) * 1.05, size=dt_size)
    n_in = max(1, src.shape[0] - int(np.floor(trim_fraction * src.shape[0])))
    rng = np.random.default_rng(seed)
    vmax = (hi - lo) / 4.0
    ring = (np.arange(particles)[:, None] + np.array([-1, 0, 1])[None]) % particles

    def score(pos: np.ndarray) -> np.ndarray:
        d = field.lookup(se2.transform_points(pos, src[None]))  # (P, N)
        if n_in < d.shape[1]:
            d = np.partition(d, n_in - 1, axis=1)[:, :n_in]
        return d.mean(axis=1)

    best_pos, best_score = None, np.inf
    done_rounds = generations = 0
    max_rounds = rounds if rounds is not None else (1 if time_budget_s is None else None)

    def time_left() -> bool:
        return time_budget_s is None or time.perf_counter() - t0 < time_budget_s

    while (max_rounds is None or done_rounds < max_rounds) and (done_rounds == 0 or time_left()):
        x = lo + rng.random((particles, 3)) * (hi - lo)
        v = np.zeros_like(x)
        f = score(x)
        pbest, pbest_f = x.copy(), f.copy()
        round_best, stale = f.min(), 0
        for _ in range(iterations):
            nb = ring[np.arange(particles), np.argmin(pbest_f[ring], axis=1)]
            r1, r2 = rng.random((2, particles, 3))
            v = INERTIA * v + C_COGNITIVE * r1 * (pbest - x) + C_SOCIAL * r2 * (pbest[nb] - x)
            v = np.clip(v, -vmax, vmax)
            x = x + v
            out = (x < lo) | (x > hi)
            x = np.clip(x, lo, hi)
            v = np.where(out, -rng.random(v.shape) * v, v)
            f = score(x)
            better = f < pbest_f
            pbest[better], pbest_f[better] = x[better], f[better]
            generations += 1
            now = pbest_f.min()
            if now < round_best * (1.0 - tol):
                round_best, stale = now, 0
            else:
                stale += 1
            if stale >= patience or not time_left():
                break
        done_rounds += 1
        i = int(np.argmin(pbest_f))
        if pbest_f[i] < best_score:
            best_score, best_pos = float(pbest_f[i]), pbest[i].copy()
    best_pos[2] = se2.wrap_angle(best_pos[2])
    return best_pos, {"score": best_score, "rounds": done_rounds, "generations": generations,
                      "time_s": time.perf_counter() - t0}


def incremental_pso(points, valid, *, time_budget_s: float | None = None, seed: int = 0, progress=None,
                    **kwargs) -> tuple[np.ndarray, dict]:
    """PSO registration of each scan onto its predecessor, relative motions chained.

    points (K, N, 2), valid (K, N); ``time_budget_s`` for the whole sequence, shared by the
    K - 1 pairs (time a pair leaves unused goes to the later ones); other keyword arguments
    go to :func:`pso_register_2d`. Returns (poses (K, 3), info: rounds per pair, time).
    """
    pts = np.asarray(points, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    k = pts.shape[0]
    rels = np.zeros((max(k - 1, 0), 3))
    rounds = []
    t0 = time.perf_counter()
    for i in range(1, k):
        budget = None
        if time_budget_s is not None:
            budget = max(0.0, time_budget_s - (time.perf_counter() - t0)) / (k - i)
        rel, info = pso_register_2d(pts[i][valid[i]], pts[i - 1][valid[i - 1]], time_budget_s=budget,
                                    seed=seed * 100003 + i, **kwargs)
        rels[i - 1] = rel
        rounds.append(info["rounds"])
        if progress is not None:
            progress(i, k)
    return se2.chain(rels), {"mean_rounds": float(np.mean(rounds)) if rounds else 0.0,
                             "time_s": time.perf_counter() - t0}
