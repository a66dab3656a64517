"""Benchmark: the joint rig refinement of mvcalib against one sparse SciPy least_squares call.

What is measured
----------------
A rig of C = 64 random cameras (`mvcalib.synthetic.random_rig`, seed 0, `fill=(0.8, 0.95)`,
0.3 px Gaussian noise, float64) sees the dense box corner `mvcalib.targets.box_corner_grid(41)`
(3 n^2 = 5043 dots, 10086 residuals per camera). Every camera is seeded by the closed-form DLT
(`mvcalib.calibrate`) with the skew set to zero, and all of them are refined jointly, as one
least-squares problem, to the minimum of the reprojection error over 10 parameters per camera
(alpha_u, alpha_v, u0, v0, rotation, translation: the pinhole model, zero skew and no
distortion held fixed; the target's points known and fixed, no anchors). A camera's residuals
depend on its own parameters only, so the Jacobian is block diagonal: C blocks of 10 columns.

- **mvcalib**: the public `mvcalib.refine_rig(seed, world, pixels, mask, distortion=())` with its
  defaults; for a rig of more than a few cameras (here 645k residuals x 640 unknowns) that is
  matrix-free LM, each step solved by LSMR on Jacobian-vector products, preconditioned per
  camera (`mvcalib._bundle.default_solver`, `_BlockLSMR`). Each call
  ends with `jax.block_until_ready` on the returned `RigRefinement`. Two calls on the same
  inputs: the first (trace + compile + run) and a warm second one.
- **scipy**: one `scipy.optimize.least_squares` call over all cameras jointly, x = the
  concatenation of every camera's [fx, fy, cx, cy, rvec (3), tvec (3)] (`rvec =
  cv2.Rodrigues(seed.R)`), with `method="trf"`, `tr_solver="lsmr"` (SciPy's large-scale path),
  `x_scale="jac"`, `ftol = xtol = gtol = 1e-12` and LSMR's stopping tolerances `atol = btol =
  1e-12` (`tr_options`; those of mvcalib's own LSMR). Residuals: every camera's
  `cv2.projectPoints(world, rvec, tvec, K, 0) - pixels` over its visible points
  (`refine.residuals`: OpenCV's implementation of the same camera model, independent of
  mvcalib's), concatenated. Jacobian: a `scipy.sparse` CSR block-diagonal matrix of the cameras'
  analytic Jacobians from `cv2.projectPoints` (`refine.jacobian`) restricted to the 10 pinhole
  columns, the distortion fixed at zero; it is built from the blocks on a sparsity structure
  computed once (equal to `scipy.sparse.block_diag` of the blocks, which takes ~20x longer to
  build at full size; both checked once per run, the Jacobian also against central finite
  differences). The inputs (visible points, seed vector, sparsity structure) are extracted to
  NumPy once, outside the timed region. One call (there is nothing to compile).

  Why LSMR's tolerances: with its defaults (`atol = btol = 1e-6`) the Gauss–Newton direction of
  each step is too inexact for this ill-conditioned Jacobian (focal length against distance,
  principal point against rotation; `x_scale="jac"` only rescales the columns), and trf crawls:
  on the `--quick` rig it took 11678 evaluations (251 s) to stop on `ftol`, 1.5e-7 (relative)
  off mvcalib's RMS; at full size that would be hours (~0.5 s an evaluation). Looser outer
  tolerances stop early, off the minimum: `ftol = xtol = gtol = 1e-8`, 12 evaluations, 2.6e-6
  above mvcalib's RMS at full size (1e-10 on the quick rig: 252 evaluations, 9e-7 off). With
  `atol = btol = 1e-12` trf takes 4 evaluations at full size and ends at mvcalib's minimum to
  ~1e-14, in 19-43 s (measured): its 3 LSMR solves took 640 (LSMR's limit, min(m, n)), 640 and
  172 iterations.

Both run on the CPU as installed: XLA may spread its work over both cores, SciPy's sparse
products run on one. Times are the wall times (`time.perf_counter`) of single calls, run one
after the other (mvcalib's first call, its warm call, SciPy's call): on the shared machine one
call moved by up to 2x between runs (SciPy's at full size: 19-43 s). The ratio is SciPy's time
over mvcalib's warm call (above 1: mvcalib is faster).

Equal final RMS: the per-camera reprojection RMS (sqrt(sum of squared residuals / visible
points)) at the end of each method should be the same minimum; the script prints the mean over
the cameras of each and the largest relative difference over the cameras, |RMS_scipy -
RMS_mvcalib| / RMS_scipy. Iterations: mvcalib's LM steps (`RigRefinement.iterations`), SciPy's
residual and Jacobian evaluations (`nfev`, `njev`). Peak memory: the process's peak resident set
(`ru_maxrss`) after mvcalib's two calls, and after SciPy's call (before the checks of its
Jacobian, which build `block_diag`).

`--quick`: 16 cameras x grid 12 (432 dots, 864 residuals per camera).

The results are printed and written to `benchmarks/results/refine_rig.json`.

Run from the repository root: `python benchmarks/refine_rig.py [--quick]`.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.sparse  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

try:
    from . import refine
    from ._common import first_and_warm
except ImportError:  # run as a script
    import refine
    from _common import first_and_warm

import mvcalib as mc  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "refine_rig.json"
P = 10  # pinhole parameters per camera: fx, fy, cx, cy, rvec (3), tvec (3)
SCIPY_TOL = 1e-12
SCIPY_LSMR_TOL = 1e-12  # LSMR's atol, btol: see the docstring


def peak_rss_mb() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024


# ---------------------------------------------------------------------------------- SciPy
def scipy_rig_inputs(world, pixels, mask, seed):
    """Per camera (visible world points, their pixels), the joint seed x0 and the CSR structure
    (indptr, indices) of the block-diagonal Jacobian, as NumPy arrays."""
    per_camera = refine.scipy_inputs(world, pixels, mask, seed)
    cams = [(w, p) for w, p, _ in per_camera]
    x0 = np.concatenate([x[:P] for _, _, x in per_camera])
    rows = [len(p) for _, p in cams]  # residuals per camera
    # every row of camera i holds its P columns P i, ..., P i + P - 1
    indptr = P * np.arange(sum(rows) + 1)
    indices = (P * np.repeat(np.arange(len(cams)), rows)[:, None] + np.arange(P)).ravel()
    return cams, x0, (indptr, indices)


def _pinhole(x, i):
    """Camera i's 10 parameters as `refine`'s 14 (distortion k1 = k2 = p1 = p2 = 0)."""
    return np.concatenate([x[P * i : P * i + P], np.zeros(4)])


def jacobian_blocks(x, cams):
    """Each camera's dense d residuals / d its 10 parameters (`refine.jacobian`'s first 10)."""
    return [refine.jacobian(_pinhole(x, i), w, p)[:, :P] for i, (w, p) in enumerate(cams)]


def rig_residuals(x, cams, structure):
    """Every camera's `refine.residuals`, concatenated (`structure`: unused, least_squares passes
    the Jacobian's arguments to both)."""
    return np.concatenate([refine.residuals(_pinhole(x, i), w, p) for i, (w, p) in enumerate(cams)])


def rig_jacobian(x, cams, structure):
    """The block-diagonal Jacobian, CSR: the blocks' rows laid end to end are its data."""
    indptr, indices = structure
    data = np.concatenate(jacobian_blocks(x, cams)).ravel()
    return scipy.sparse.csr_array((data, indices, indptr), shape=(len(indptr) - 1, x.size))


def scipy_rig(cams, x0, structure):
    return least_squares(
        rig_residuals,
        x0,
        jac=rig_jacobian,
        args=(cams, structure),
        method="trf",
        tr_solver="lsmr",
        x_scale="jac",
        ftol=SCIPY_TOL,
        xtol=SCIPY_TOL,
        gtol=SCIPY_TOL,
        tr_options={"atol": SCIPY_LSMR_TOL, "btol": SCIPY_LSMR_TOL},
    )


def check_jacobian(cams, x0, structure):
    """The CSR Jacobian equals `scipy.sparse.block_diag` of the blocks (asserted), and its
    largest |analytic - central finite difference| relative to its largest |entry| (camera 0)."""
    J = rig_jacobian(x0, cams, structure)
    assert (J != scipy.sparse.block_diag(jacobian_blocks(x0, cams), format="csr")).nnz == 0
    world, pixels = cams[0]
    return refine.check_jacobian((world, pixels, _pinhole(x0, 0)))


# ---------------------------------------------------------------------------------- run
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    n, C = (12, 16) if args.quick else (41, 64)
    target = mc.targets.box_corner_grid(n)
    rig = mc.synthetic.random_rig(jax.random.key(0), C, target=target, noise=0.3, fill=(0.8, 0.95))
    seed = mc.calibrate(rig.world, rig.pixels, rig.mask).cameras
    seed = eqx.tree_at(lambda c: c.skew, seed, jnp.zeros(C))

    def mvcalib_call():
        out = mc.refine_rig(seed, rig.world, rig.pixels, rig.mask, distortion=())
        return jax.block_until_ready(out)

    seconds, warm_seconds, out = first_and_warm(mvcalib_call, warm_calls=1)
    mvcalib_peak = peak_rss_mb()

    cams, x0, structure = scipy_rig_inputs(rig.world, rig.pixels, rig.mask, seed)
    start = time.perf_counter()
    sol = scipy_rig(cams, x0, structure)
    scipy_seconds = time.perf_counter() - start
    scipy_peak = peak_rss_mb()
    jacobian_error = check_jacobian(cams, x0, structure)  # after the peak: block_diag is big

    visible = np.array([len(w) for w, _ in cams])
    ends = np.cumsum(2 * visible)[:-1]
    rms_scipy = np.array(
        [np.sqrt(np.sum(r**2) / k) for r, k in zip(np.split(sol.fun, ends), visible)]
    )
    rms_mvcalib = np.asarray(out.rms_after)
    rel = np.abs(rms_scipy - rms_mvcalib) / rms_scipy
    row = {
        "cameras": C,
        "residuals_per_camera": 2 * len(target.points),
        "residuals_total": int(2 * rig.mask.sum()),
        "seconds_first_call": round(seconds, 2),
        "seconds_warm_call": round(warm_seconds, 2),
        "steps": int(out.iterations),
        "result": out.messages(),
        "rms_before": float(out.rms_before.mean()),
        "rms_after": float(out.rms_after.mean()),
        "peak_rss_mb": mvcalib_peak,
        "scipy_seconds": round(scipy_seconds, 2),
        "ratio_scipy_over_mvcalib_warm": round(scipy_seconds / warm_seconds, 2),
        "scipy_rms_after": float(rms_scipy.mean()),
        "rms_max_rel_diff": float(rel.max()),
        "rms_worst_camera": int(np.argmax(rel)),
        "scipy_nfev": int(sol.nfev),
        "scipy_njev": int(sol.njev),
        "scipy_status": int(sol.status),
        "scipy_message": sol.message,
        "scipy_settings": f"trf, lsmr (atol=btol={SCIPY_LSMR_TOL}), x_scale='jac', "
        f"ftol=xtol=gtol={SCIPY_TOL}, sparse CSR block-diagonal cv2.projectPoints jacobian",
        "scipy_jacobian_max_rel_error_vs_fd": float(f"{jacobian_error:.1e}"),
        "peak_rss_mb_after_scipy": scipy_peak,
    }
    for k, v in row.items():
        print(f"{k:>34}: {v}")
    print()
    print("seconds_*:  mvcalib's refine_rig, first call (trace + compile + run) and warm call;")
    print("            scipy: one least_squares call (trf, lsmr, x_scale='jac', tolerances and")
    print("            LSMR's 1e-12) on a sparse block-diagonal cv2.projectPoints Jacobian.")
    print("ratio:      scipy_seconds / seconds_warm_call (> 1: mvcalib faster).")
    print("rms_*:      mean over cameras of the final reprojection RMS (px); rms_max_rel_diff:")
    print("            largest |RMS_scipy - RMS_mvcalib| / RMS_scipy over the cameras.")
    print("peak_rss:   after mvcalib's two calls; _after_scipy: after SciPy's call too.")
    if rel.max() > 1e-6:
        print(
            f"note: final RMS of mvcalib and scipy differ by {rel.max():.1e} (relative) at camera "
            f"{int(np.argmax(rel))}: not the same minimum."
        )
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(row, indent=2) + "\n")


if __name__ == "__main__":
    main()
