"""Physical limit: this machine's FLOP/s and memory bandwidth, and what each kernel must do.

What is measured
----------------
- **FLOP/s**: a large float64 matrix product in NumPy (OpenBLAS, all cores), 2 n^3 floating-point
  operations per call; the best of several calls.
- **Memory bandwidth**: `np.copyto` of a large float64 array, with one and with two threads
  (each copying half); bytes read + bytes written per second (a write-allocate cache may add a
  third stream, so the true traffic is higher); the best of several calls.

Per kernel, `*_flops` count the floating-point operations (add, multiply, divide, square root: 1
each; a multiply-add: 2) one camera (or one point) needs with the textbook method, and
`*_bytes` the bytes it must read and write at least (its inputs and outputs, nothing else). The
bound on its time is `max(flops / FLOP/s, bytes / bandwidth)`: neither the arithmetic nor the
data movement can go faster than the machine's best on a large, ideal problem. "x from the
bound" is a measured time divided by that bound. The counts are written out below, operation by
operation. A second, "minimal" count gives the work of the cheapest method we know (the
structure of the DLT matrix exploited, the smallest eigenvector alone by inverse iteration), for
a tighter bound.

XLA's own estimate, where the backend provides one: `jax.jit(f).lower(*args).compile()
.cost_analysis()` gives the flops and bytes accessed of the compiled mvcalib function. Library
calls inside it (LAPACK eigensolvers and SVDs on the CPU) are not counted by XLA.

Run from the repository root: `python benchmarks/bound.py [--quick]`; results go to
`benchmarks/results/bound.json`.
"""

from __future__ import annotations

import argparse
import threading
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

try:
    from ._common import machine_info, results_path, write_results
except ImportError:  # run as a script
    from _common import machine_info, results_path, write_results

import mvcalib as mc  # noqa: E402

_LIMITS: dict = {}


# ---------------------------------------------------------------------------------- machine
def measure_flops(n: int, repeats: int) -> float:
    """Best FLOP/s of `repeats` float64 matrix products of n x n matrices (2 n^3 flops each)."""
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((n, n)), rng.standard_normal((n, n))
    out = np.empty((n, n))
    np.matmul(a, b, out=out)  # warm-up: threads started, pages touched
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.matmul(a, b, out=out)
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n**3 / best


def measure_bandwidth(n_bytes: int, repeats: int) -> tuple[float, int]:
    """Best (bytes read + written) per second of copying `n_bytes` of float64, and the number
    of threads (1 or 2) that reached it."""
    src = np.random.default_rng(0).standard_normal(n_bytes // 8)
    dst = np.empty_like(src)
    np.copyto(dst, src)  # warm-up: the destination's pages are touched

    def copy_threads(k):
        edges = np.linspace(0, len(src), k + 1).astype(int)
        threads = [
            threading.Thread(target=np.copyto, args=(dst[lo:hi], src[lo:hi]))
            for lo, hi in zip(edges[:-1], edges[1:])
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()

    best = {}
    for k in (1, 2):
        for _ in range(repeats):
            t0 = time.perf_counter()
            copy_threads(k)
            dt = time.perf_counter() - t0
            best[k] = min(best.get(k, np.inf), dt)
    k = min(best, key=best.get)
    return 2.0 * src.nbytes / best[k], k


def machine_limits(*, quick: bool = False, smoke: bool = False) -> dict:
    """Measured FLOP/s and bandwidth of this machine, once per process (then reused)."""
    key = "smoke" if smoke else "quick" if quick else "full"
    if key not in _LIMITS:
        n, n_bytes, repeats = (
            (512, 2**24, 3) if smoke else (1536, 2**27, 4) if quick else (3072, 2**28, 7)
        )
        t0 = time.perf_counter()
        flop_s = measure_flops(n, repeats)
        bandwidth, threads = measure_bandwidth(n_bytes, repeats)
        _LIMITS[key] = {
            "flop_per_s": flop_s,
            "bandwidth_bytes_per_s": bandwidth,
            "matmul_n": n,
            "copy_mb": n_bytes / 2**20,
            "copy_threads": threads,
            "repeats": repeats,
            "seconds": time.perf_counter() - t0,
        }
    return _LIMITS[key]


def bound_seconds(flops: float, n_bytes: float, limits: dict) -> float:
    """max(flops / FLOP/s, bytes / bandwidth): no faster than either allows."""
    return max(flops / limits["flop_per_s"], n_bytes / limits["bandwidth_bytes_per_s"])


# ---------------------------------------------------------------------------------- counts
EIGH_FLOPS_PER_N3 = 9  # symmetric QR with eigenvectors (Golub & Van Loan, 4th ed., 8.3): ~9 n^3
SVD_3X3_FLOPS = 4 * 27 + 8 * 27 + 9 * 27  # R-SVD of m x n with U, S, V: 4m^2n + 8mn^2 + 9n^3


def dlt_flops(n: int, *, minimal: bool = False) -> int:
    """Floating-point operations of the normalised DLT of one camera from n points."""
    flops = 0
    # Hartley normalisation, world points (n x 3): centroid 3n adds; mean squared distance
    # 3n subtractions + 3n multiplications + 3n adds; applying it: 3n subtractions + 3n scalings.
    flops += 3 * n + 9 * n + 6 * n
    # ... and pixels (n x 2): 2n + 6n + 4n.
    flops += 2 * n + 6 * n + 4 * n
    # Design matrix A (2n x 12, eqs. 9-10): the products -u X and -v X, 8 multiplications a point.
    flops += 8 * n
    if minimal:
        # A^T A from A's non-zeros: each row has 8 of its 12 entries non-zero, so 8 * 9 / 2 = 36
        # distinct products (multiply-adds) per row.
        flops += 2 * n * 36 * 2
        # The smallest eigenvector alone by inverse iteration on the 12 x 12 matrix: a Cholesky
        # (LDL^T) factorisation, n^3 / 3, and 3 steps of two triangular solves (2 n^2 each).
        flops += 12**3 // 3 + 3 * 2 * 2 * 12**2
    else:
        # A^T A, dense and symmetric: 12 * 13 / 2 = 78 distinct entries, each a dot product over
        # the 2n rows (2n multiply-adds).
        flops += 2 * n * 78 * 2
        # Full symmetric eigendecomposition of the 12 x 12 normal matrix: ~9 n^3.
        flops += EIGH_FLOPS_PER_N3 * 12**3
    # De-normalisation P = T2^-1 V T3 as dense products: 3x3 @ 3x4 and 3x4 @ 4x4 (multiply-adds).
    flops += 2 * (3 * 3 * 4 + 3 * 4 * 4)
    # ||m3|| = 1: 3 multiplications, 2 adds, a square root, 12 divisions.
    flops += 3 + 2 + 1 + 12
    # The sign that puts the points in front: depth = X m3 + m34 (3 multiply-adds + 1 add a point),
    # summed over the points (n adds).
    flops += 7 * n + n
    return flops


def decomposition_flops() -> int:
    """Floating-point operations of the closed-form `P = K [R | t]` of one camera (with skew)."""
    flops = 0
    flops += 9 + 8  # det(M) of 3 x 3 (its sign): 9 multiplications, 8 adds/subtractions
    flops += 3 + 2 + 1 + 12  # ||m3|| (3 mul, 2 add, sqrt) and the 12 divisions scaling P
    flops += 2 * 5  # u0 = m1.m3, v0 = m2.m3: two 3-vector dot products (3 mul + 2 add each)
    flops += 6 + 6 + 3  # q2 = m2 - v0 m3 (6), alpha_v = ||q2|| (5 + sqrt), r2 = q2 / alpha_v (3)
    flops += 6 + 5 + 6  # q1 = m1 - u0 m3, skew = q1.r2, q1 -= skew r2
    flops += 6 + 3  # alpha_u = ||q1||, r1 = q1 / alpha_u
    flops += 3 + 5  # ty = (m24 - v0 tz) / alpha_v; tx = (m14 - u0 tz - skew ty) / alpha_u
    # Nearest rotation: SVD of the 3 x 3 [r1; r2; m3], R = U V^T (27 multiply-adds), det sign.
    flops += SVD_3X3_FLOPS + 2 * 27 + 17
    return flops


def dlt_decomposition_flops(n: int, *, minimal: bool = False) -> int:
    return dlt_flops(n, minimal=minimal) + decomposition_flops()


def dlt_bytes(n: int, *, n_cameras: int = 1, itemsize: int = 8) -> float:
    """Bytes one camera's DLT + decomposition must move: pixels (2n floats) and the visibility
    mask (n bytes) in, the world points (3n floats, shared by the rig: 1 / n_cameras of them),
    and 17 parameters out (alpha_u, alpha_v, u0, v0, skew, R 9, t 3)."""
    return itemsize * 2 * n + n + itemsize * 3 * n / n_cameras + itemsize * 17


def triangulation_flops(views: int, *, minimal: bool = False) -> int:
    """Floating-point operations of the linear triangulation of one point seen in `views`."""
    flops = 0
    # Pixels to normalised camera coordinates: y = (v - v0) / av (2), x = (u - u0 - s y) / au (4).
    flops += 6 * views
    # Two rows a view, x P3 - P1 and y P3 - P2: 4 multiplications + 4 subtractions each.
    flops += 16 * views
    # A^T A of the 2V x 4 system: 4 * 5 / 2 = 10 distinct entries, each 2V multiply-adds.
    flops += 2 * views * 10 * 2
    if minimal:
        # Smallest eigenvector by inverse iteration: 4 x 4 LDL^T (~n^3/3) + 3 steps of solves.
        flops += 4**3 // 3 + 3 * 2 * 2 * 4**2
    else:
        flops += EIGH_FLOPS_PER_N3 * 4**3  # full 4 x 4 symmetric eigendecomposition
    flops += 3  # dehomogenise: X = v[:3] / v[3]
    return flops


def triangulation_bytes(views: int, *, itemsize: int = 8) -> float:
    """Bytes one point's triangulation must move: its pixels in (2V floats), the point out (3).
    The cameras (12 floats each) are shared by all points and negligible."""
    return itemsize * (2 * views + 3)


def kernel_bounds(limits: dict) -> list[dict]:
    """The bound of every kernel of the suite, per camera or per point, in microseconds."""
    rows = []
    for n in (8, 19, 100, 1000):
        flops, minimal = dlt_decomposition_flops(n), dlt_decomposition_flops(n, minimal=True)
        n_bytes = dlt_bytes(n, n_cameras=4096)
        rows.append(
            _bound_row("DLT + decomposition", f"N={n}", "camera", flops, minimal, n_bytes, limits)
        )
    rows.append(
        _bound_row(
            "decomposition", "P 3x4", "camera", decomposition_flops(), None, 8 * (12 + 17), limits
        )
    )
    for v in (2, 8):
        rows.append(
            _bound_row(
                "triangulation",
                f"V={v}",
                "point",
                triangulation_flops(v),
                triangulation_flops(v, minimal=True),
                triangulation_bytes(v),
                limits,
            )
        )
    return rows


def _bound_row(kernel, setting, unit, flops, minimal, n_bytes, limits):
    return {
        "kernel": kernel,
        "setting": setting,
        "unit": unit,
        "flops": flops,
        "flops_minimal": minimal,
        "bytes": n_bytes,
        "bound_us": 1e6 * bound_seconds(flops, n_bytes, limits),
        "bound_minimal_us": None
        if minimal is None
        else 1e6 * bound_seconds(minimal, n_bytes, limits),
        "bound_by": "compute"
        if flops / limits["flop_per_s"] >= n_bytes / limits["bandwidth_bytes_per_s"]
        else "memory",
    }


# ---------------------------------------------------------------------------------- XLA
def xla_cost(jitted, *args) -> dict | None:
    """XLA's cost analysis of `jitted` compiled for `args`: flops and bytes accessed, or None."""
    try:
        cost = jitted.lower(*args).compile().cost_analysis()
    except Exception as error:  # not every backend implements it
        print(f"note: XLA cost analysis unavailable ({type(error).__name__}: {error})")
        return None
    if isinstance(cost, (list, tuple)):  # older JAX: one dict per computation
        cost = cost[0] if cost else None
    if not cost:
        return None
    flops, n_bytes = cost.get("flops", np.nan), cost.get("bytes accessed", np.nan)
    return {"flops": float(flops), "bytes": float(n_bytes)}


@jax.jit
def _mvcalib_dlt_decomposition(world, pixels, mask):
    return mc.Camera.from_projection(mc.dlt(world, pixels, mask))


@jax.jit
def _mvcalib_triangulate(cameras, pixels):
    return mc.triangulate(cameras, pixels)


def xla_costs(*, n_cameras: int, n_points: int) -> list[dict]:
    """XLA's flops and bytes of mvcalib's DLT + decomposition (C cameras, the 19-dot target) and
    of `mc.triangulate` (8 views), per camera / per point, beside our counts."""
    rows = []
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=n_cameras, noise=0.3)
    cost = xla_cost(_mvcalib_dlt_decomposition, rig.world, rig.pixels, rig.mask)
    n = rig.world.shape[0]
    rows.append(
        _xla_row(
            "DLT + decomposition",
            f"C={n_cameras}, N={n}",
            n_cameras,
            cost,
            dlt_decomposition_flops(n),
            dlt_bytes(n, n_cameras=n_cameras),
        )
    )
    cameras = mc.synthetic.random_cameras(jax.random.key(0), 8)
    world = np.random.default_rng(0).uniform(0.0, 160.0, (n_points, 3))
    pixels = cameras.project(world)
    cost = xla_cost(_mvcalib_triangulate, cameras, pixels)
    rows.append(
        _xla_row(
            "triangulation",
            f"{n_points} points, V=8",
            n_points,
            cost,
            triangulation_flops(8),
            triangulation_bytes(8),
        )
    )
    return rows


def _xla_row(kernel, setting, count, cost, flops, n_bytes):
    row = {"kernel": kernel, "setting": setting, "our_flops": flops, "our_bytes": n_bytes}
    if cost is None:
        return row | {"xla_flops": None, "xla_bytes": None}
    return row | {"xla_flops": cost["flops"] / count, "xla_bytes": cost["bytes"] / count}


# ---------------------------------------------------------------------------------- report
def print_report(limits, bounds, xla):
    print(
        f"machine: {limits['flop_per_s'] / 1e9:.1f} GFLOP/s (float64 matmul "
        f"{limits['matmul_n']}^2, best of {limits['repeats']}), "
        f"{limits['bandwidth_bytes_per_s'] / 1e9:.1f} GB/s "
        f"(copy of {limits['copy_mb']:.0f} MB, read + write, {limits['copy_threads']} thread(s))"
    )
    print()
    header = (
        f"{'kernel':<21}{'setting':>9}{'per':>7}{'flops':>9}{'minimal':>9}{'bytes':>8}"
        f"{'bound µs':>10}{'minimal':>9}{'by':>8}"
    )
    print(header)
    print("-" * len(header))
    for r in bounds:
        minimal = "" if r["flops_minimal"] is None else f"{r['flops_minimal']:>9}"
        bmin = "" if r["bound_minimal_us"] is None else f"{r['bound_minimal_us']:>9.4f}"
        print(
            f"{r['kernel']:<21}{r['setting']:>9}{r['unit']:>7}{r['flops']:>9}{minimal:>9}"
            f"{r['bytes']:>8.0f}{r['bound_us']:>10.4f}{bmin:>9}{r['bound_by']:>8}"
        )
    print()
    print("flops: textbook count (dense symmetric A^T A, full 12x12 / 4x4 eigensolve ~9 n^3);")
    print("minimal: A^T A from A's non-zeros, smallest eigenvector by inverse iteration.")
    print("bytes: inputs + outputs only. bound = max(flops / FLOP/s, bytes / bandwidth).")
    if xla:
        print()
        print(
            f"{'XLA cost analysis':<21}{'setting':>22}{'XLA flops':>11}{'ours':>8}"
            f"{'XLA bytes':>11}{'ours':>7}"
        )
        for r in xla:
            xf = "n/a" if r["xla_flops"] is None else f"{r['xla_flops']:.0f}"
            xb = "n/a" if r["xla_bytes"] is None else f"{r['xla_bytes']:.0f}"
            print(
                f"{r['kernel']:<21}{r['setting']:>22}{xf:>11}{r['our_flops']:>8}{xb:>11}"
                f"{r['our_bytes']:>7.0f}"
            )
        print("(per camera / per point; XLA does not count LAPACK calls such as eigh/SVD on CPU)")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller matmul and copy")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, for the smoke test")
    parser.add_argument("--no-xla", action="store_true", help="skip XLA's cost analysis")
    args = parser.parse_args(argv)
    wall = time.perf_counter()
    info = machine_info()
    limits = machine_limits(quick=args.quick, smoke=args.smoke)
    bounds = kernel_bounds(limits)
    xla = None
    if not args.no_xla:
        xla = xla_costs(
            n_cameras=64 if args.smoke else 4096, n_points=1000 if args.smoke else 10_000
        )
    print_report(limits, bounds, xla)
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")
    return write_results(
        results_path("bound.json"),
        "bound",
        quick=args.quick or args.smoke,
        machine=info,
        limits=limits,
        wall_time_s=wall,
        bounds=bounds,
        xla_cost_analysis=xla,
    )


if __name__ == "__main__":
    main()
