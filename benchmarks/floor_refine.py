"""How fast a batched Levenberg–Marquardt refinement can be in XLA on this machine: the least time
of the pieces every step must run, and the largest ratio to the SciPy loop that it allows.

What is measured
----------------
The refine benchmark's problem (`refine.py`: 256 cameras of the 108-dot box corner grid with
distortion, 14 free parameters, seeded by the DLT). Each step of a Gauss–Newton-type method
(Levenberg–Marquardt, mvcalib's `SecantLM`, MINPACK's lm) evaluates the residuals and their
Jacobian at a trial point, forms the normal matrix `J^T J` (or factorises `J`, which costs more),
and solves a 14 x 14 system. Each piece runs here alone, as one compiled, vmapped call over B
cameras, B = 16, 64, 256:

- **residuals + Jacobian**: mvcalib's written-out `_residuals` and `_residual_jacobian_t`;
- **J^T J**: the batched product in XLA's faster form of the two (`einsum` on the transposed
  Jacobian, or a product with a transposed copy made beforehand, not timed);
- **solve**: Cholesky factorisation and two triangular solves (LAPACK, batched).

B = 1024 repeats the 256 cameras four times. From each call's time the cost of calling a
compiled function at all is taken off (the median time of a call that adds 1 to a number), so
that the floor is not raised by dispatch; at small B a call's own overheads (its arguments and
outputs) still weigh, so each piece counts at its best batch size. The floor of one camera-step
is the sum of each piece's least time per camera over the batch sizes: no loop, no acceptance
test, no damping, no bookkeeping of the state, no waiting for the slowest camera of a batch.
Times are medians of
per-call wall times. In the same run: the SciPy lm loop of `refine.py` (its peer; on the first
64 cameras, per camera) and the steps mvcalib's refinement takes per camera (mean over the 256).
The ceiling of the ratio is `scipy time per camera / (mean steps x floor per camera-step)`.

This is a tool for working on the refinement's speed, not part of the suite (`python -m
benchmarks`), and writes no results. Run from the repository root:
`python benchmarks/floor_refine.py`.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

try:
    from . import refine
except ImportError:  # run as a script
    import refine

from mvcalib import _refine  # noqa: E402


def median_time(fn, *args, calls=40):
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=256, help="the rig (B goes to 4x that)")
    parser.add_argument("--scipy-cameras", type=int, default=64)
    parser.add_argument("--calls", type=int, default=40, help="timed calls of each piece")
    args = parser.parse_args(argv)
    C, calls = args.cameras, args.calls
    batches = sorted({min(B, 4 * C) for B in (16, 64, C, 4 * C)})
    world, pixels, mask, seed = refine.make_problem(C)
    free = _refine._free_parameters(("k1", "k2", "p1", "p2"), (), False)  # noqa: SLF001

    def arguments(cam, pix, m):  # as `_refine._refine_one` builds them
        return _refine._arguments(cam, world, pix, m, None)  # noqa: SLF001

    def evaluate(y, args):
        residuals = _refine._residuals(y, args, free).reshape(-1)  # noqa: SLF001
        return residuals, _refine._residual_jacobian_t(y, args, free)  # noqa: SLF001

    inputs = jax.jit(jax.vmap(arguments))(seed, pixels, mask)
    inputs = jax.tree_util.tree_map(lambda x: jnp.concatenate([x] * 4), inputs)
    y = jnp.full((4 * C, len(free)), 1e-6)  # a trial point off the seed
    trivial = jax.jit(lambda x: x + 1.0)
    dispatch = median_time(trivial, jnp.zeros(()), calls=200)
    evaluated = jax.jit(jax.vmap(evaluate))
    normal = jax.jit(lambda Jt: jnp.einsum("bpm,bqm->bpq", Jt, Jt))
    normal_transposed = jax.jit(lambda Jt, J: Jt @ J)

    def cholesky_solve(H, g):
        return jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(H), True), g)

    solve = jax.jit(jax.vmap(cholesky_solve))
    r, Jt = evaluated(y, inputs)
    J = jnp.swapaxes(Jt, 1, 2).copy()
    H = normal(Jt) + 1e-3 * jnp.eye(len(free))
    g = jnp.einsum("bpm,bm->bp", Jt, r)

    print(f"floor of one LM step per camera in XLA ({len(free)} parameters, 108 points), µs")
    print(f"(each call less {1e6 * dispatch:.1f} µs, the time of a trivial call):")
    print(f"{'B':>5}{'residuals + J':>16}{'J^T J':>8}{'solve':>8}{'floor':>8}")
    best = {"evaluate": np.inf, "normal": np.inf, "solve": np.inf}
    for B in batches:
        part = jax.tree_util.tree_map(lambda x, B=B: x[:B], inputs)

        def per_camera(seconds, B=B):
            return 1e6 * max(seconds - dispatch, 0.0) / B

        t_eval = per_camera(median_time(evaluated, y[:B], part, calls=calls))
        t_normal = per_camera(
            min(
                median_time(normal, Jt[:B], calls=calls),
                median_time(normal_transposed, Jt[:B], J[:B], calls=calls),
            )
        )
        t_solve = per_camera(median_time(solve, H[:B], g[:B], calls=calls))
        for name, t in (("evaluate", t_eval), ("normal", t_normal), ("solve", t_solve)):
            best[name] = min(best[name], t)
        row = (t_eval, t_normal, t_solve, t_eval + t_normal + t_solve)
        print(f"{B:>5}{row[0]:>16.2f}" + "".join(f"{t:>8.2f}" for t in row[1:]))
    floor = sum(best.values())
    row = (best["evaluate"], best["normal"], best["solve"], floor)
    print(f"{'best':>5}{row[0]:>16.2f}" + "".join(f"{t:>8.2f}" for t in row[1:]))

    steps = float(np.mean(np.asarray(refine.mvcalib_refine(seed, world, pixels, mask).iterations)))
    problems = refine.scipy_inputs(world, pixels, mask, seed)[: args.scipy_cameras]
    n_scipy = len(problems)
    refine.scipy_loop(problems[:4], "lm")  # warm
    scipy_us = 1e6 * median_time(lambda: refine.scipy_loop(problems, "lm"), calls=3) / n_scipy
    print(f"\nmvcalib's steps per camera (mean over {C}): {steps:.2f}")
    print(f"SciPy lm loop: {scipy_us:.0f} µs/camera (first {n_scipy} cameras)")
    print(
        f"ceiling of scipy lm / mvcalib at the floor ({floor:.2f} µs/camera-step): "
        f"{scipy_us / (steps * floor):.1f}x; 20x would need {scipy_us / 20 / floor:.1f} steps "
        "a camera at that floor"
    )


if __name__ == "__main__":
    main()
