"""Sharded against unsharded mvcalib on 2 host devices; run by tests/test_sharding.py.

It must run in a fresh process: the number of host devices is fixed when JAX initialises, from
XLA_FLAGS=--xla_force_host_platform_device_count=2 (and JAX_ENABLE_X64=1). It prints one JSON
object: per result, whether the sharded value is bitwise the unsharded one and the largest
difference relative to the largest entry; how the sharded results are laid out; and the
collectives and custom calls in the compiled sharded programs.
"""

from __future__ import annotations

import json
import re
import time

COLLECTIVES = ("all-gather", "all-reduce", "all-to-all", "collective-permute", "reduce-scatter")


def compare(ref, out, where=None) -> dict:
    """Bitwise equality, and the largest difference relative to the largest |ref| (NaN in the
    same places counts as equal); over the entries `where` (leading axes) only, if given."""
    import numpy as np

    a, b = np.asarray(ref), np.asarray(out)
    if where is not None:
        a, b = a[np.asarray(where)], b[np.asarray(where)]
    floating = a.dtype.kind == "f"
    finite = np.isfinite(a) & np.isfinite(b) if floating else np.ones(a.shape, bool)
    x, y = a[finite].astype(float), b[finite].astype(float)
    scale = float(np.max(np.abs(x), initial=0.0))
    diff = float(np.max(np.abs(x - y), initial=0.0))
    return {
        "bitwise": bool(np.array_equal(a, b, equal_nan=floating)),
        "same_nan": bool(np.array_equal(np.isnan(a), np.isnan(b))) if floating else True,
        "absolute": diff,
        "relative": diff / scale if scale > 0 else diff,
    }


def layout(x) -> dict:
    """How a jax.Array is laid out: its spec, the devices, the shape of each device's shard."""
    s = x.sharding
    return {
        "spec": [None if p is None else str(p) for p in getattr(s, "spec", ())],
        "devices": len(s.device_set),
        "shard_shapes": [list(d.data.shape) for d in x.addressable_shards],
        "axis_types": [str(t) for t in getattr(getattr(s, "mesh", None), "axis_types", ())],
    }


def hlo_facts(text: str) -> dict:
    """Collectives, and custom calls with their per-device result shapes, in compiled HLO."""
    counts = {op: len(re.findall(rf"= [^=]*\b{op}(-start)?\(", text)) for op in COLLECTIVES}
    calls = set(re.findall(r"= \(?(\w+\[[0-9,]*\])[^=\n]*custom_call_target=\"([\w.]+)\"", text))
    reduced = re.findall(r"= (\w+\[[0-9,]*\])[^\n]*all-reduce(?:-start)?\(", text)
    return {
        "collectives": counts,
        "all_reduce_shapes": reduced,
        "custom_calls": sorted(f"{target} {shape}" for shape, target in calls),
    }


def rig(n_cameras: int, world, seed: int, noise: float):
    """Cameras in the positive octant looking at the target (NumPy and OpenCV only, so that no
    compilation is spent on making data): K, R, t, dist, pixels."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    centre = world.mean(0)
    direction = np.ones(3) / np.sqrt(3) + 0.3 * rng.standard_normal((n_cameras, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    f = rng.uniform(900, 1600, n_cameras)
    eye = centre + (f / 2.5)[:, None] * direction
    z = centre + 5 * rng.standard_normal((n_cameras, 3)) - eye
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    R = np.stack([x, np.cross(z, x), z], axis=-2)
    t = -np.einsum("cij,cj->ci", R, eye)
    K = np.zeros((n_cameras, 3, 3))
    K[:, 0, 0], K[:, 1, 1] = f, f * rng.uniform(0.98, 1.02, n_cameras)
    K[:, :2, 2] = [550.0, 500.0] + rng.uniform(-30, 30, (n_cameras, 2))
    K[:, 2, 2] = 1.0
    dist = np.zeros((n_cameras, 5))
    pixels = np.stack(
        [
            cv2.projectPoints(world, cv2.Rodrigues(R[c])[0], t[c], K[c], dist[c])[0][:, 0]
            for c in range(n_cameras)
        ]
    )
    return K, R, t, dist, pixels + noise * rng.standard_normal(pixels.shape)


def main() -> None:
    import concurrent.futures

    import cv2
    import jax
    import jax.numpy as jnp
    import numpy as np

    import mvcalib as mc

    assert jax.device_count() == 2, jax.devices()
    assert jnp.zeros(()).dtype == jnp.float64, "run with JAX_ENABLE_X64=1"
    report: dict = {"devices": [str(d) for d in jax.devices()], "seconds": {}, "cpu": {}}
    tic, cpu = time.perf_counter(), time.process_time()

    def lap(name):
        nonlocal tic, cpu
        report["seconds"][name] = round(time.perf_counter() - tic, 2)
        report["cpu"][name] = round(time.process_time() - cpu, 2)
        tic, cpu = time.perf_counter(), time.process_time()

    # --- calibrate: 64 cameras of the 19-dot target, two of them broken, a hidden NaN pixel
    world = np.asarray(mc.targets.box_corner().points, float)
    K, R, t, _, pixels = rig(64, world, seed=7, noise=0.3)
    mask = np.ones(pixels.shape[:2], bool)
    mask[5, 5:] = False  # five points: too few
    mask[12] = world[:, 2] == 0  # only the floor z = 0: coplanar
    pixels[20, 3], mask[20, 3] = np.nan, False  # hidden, so it changes nothing
    truth = mc.Camera.from_matrices(K, R, t)

    # --- refine: 4 of those cameras, seeded with a perturbed truth (pinhole: the 19-dot target
    # cannot separate distortion from the pose)
    seed = mc.Camera.from_matrices(K[:4] * np.array([1.01, 1, 1])[:, None], R[:4], t[:4] + 1.0)

    # --- triangulate: 108 points seen by 8 distorted cameras, the point axis split
    grid = np.asarray(mc.targets.box_corner_grid(6).points, float)
    tK, tR, tt, _, _ = rig(8, grid, seed=8, noise=0.0)
    tdist = np.tile([-0.2, 0.1, 1e-3, 1e-3, 0.0], (8, 1))
    rng = np.random.default_rng(8)
    tpix = np.stack(
        [cv2.projectPoints(grid, cv2.Rodrigues(tR[c])[0], tt[c], tK[c], tdist[c])[0][:, 0]
         for c in range(8)]
    ) + 0.5 * rng.standard_normal((8, 108, 2))  # fmt: skip
    tmask = rng.random((8, 108)) > 0.3
    tmask[:, 7] = False  # a point nobody sees
    tmask[1:, 9] = False  # a point one camera sees
    tcams = mc.Camera.from_matrices(tK, tR, tt, tdist)
    transform = mc.RigidTransform(mc.rodrigues(jnp.array([0.1, -0.2, 0.3])), jnp.array([1.0, 2, 3]))
    lap("data")

    # Each public function under jax.jit, compiled once for unsharded and once for sharded
    # inputs (ahead of time, two compilations at a time), then run.
    jobs = {
        "calibrate": (
            lambda p, m: mc.calibrate(world, p, m),
            (pixels, mask),
            mc.shard((pixels, mask)),
        ),
        "refine": (
            lambda c, p, m: mc.refine(c, world, p, m, distortion=()),
            (seed, pixels[:4], mask[:4]),
            mc.shard((seed, pixels[:4], mask[:4])),
        ),
        "triangulate": (
            lambda c, p, m: mc.triangulate(c, p, m),
            (tcams, tpix, tmask),
            (mc.shard(tcams, axis=None), *mc.shard((tpix, tmask), axis=1)),
        ),
        "reproject": (lambda c: mc.reproject(c, world), (truth,), (mc.shard(truth),)),
        "to_global": (lambda c: mc.to_global(c, transform), (truth,), (mc.shard(truth),)),
    }

    def compile_one(fn, args):
        start = time.thread_time()
        out = jax.jit(fn).lower(*args).compile()
        return out, round(time.thread_time() - start, 2)

    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {
            (name, kind): pool.submit(compile_one, fn, args)
            for name, (fn, plain, sharded) in jobs.items()
            for kind, args in (("plain", plain), ("sharded", sharded))
        }
        done = {key: future.result() for key, future in futures.items()}
    compiled = {key: c for key, (c, _) in done.items()}
    report["compile_cpu"] = {f"{name} {kind}": s for (name, kind), (_, s) in done.items()}
    lap("compile")
    results = {}
    for name, (_, plain, sharded) in jobs.items():
        ref = compiled[name, "plain"](*plain)
        out = compiled[name, "sharded"](*sharded)
        paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(ref)]
        refs, outs = jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(out)
        results[name] = (ref, out)
        report[name] = {
            "compare": {p: compare(a, b) for p, a, b in zip(paths, refs, outs)},
            "layout": {p: layout(b) for p, b in zip(paths, outs)},
            "inputs": [layout(a) for a in jax.tree_util.tree_leaves(sharded)],
            "hlo": hlo_facts(compiled[name, "sharded"].as_text()),
        }  # fmt: skip
    lap("run")

    # Diagnostics that mean nothing where the answer is undefined, compared where it is not:
    # s_1 / s_11 of a degenerate camera (s_11 ~ 0) is rounding noise, and a point seen once has
    # no reprojection RMS or ray angle (0 or NaN, depending on rounding).
    ref, out = results["calibrate"]
    report["calibrate"]["compare"][".condition"] = compare(
        ref.condition, out.condition, ref.status == 0
    )
    ref, out = results["triangulate"]
    for name in ("rms", "angle"):
        report["triangulate"]["compare"][f".{name}"] = compare(
            getattr(ref, name), getattr(out, name), ref.views >= 2
        )

    # Against the truth, so that "equal" cannot mean "equally wrong".
    ref, out = results["calibrate"]
    report["calibrate"]["status"] = np.asarray(out.status).tolist()
    report["calibrate"]["alpha_u_error"] = float(
        np.nanmax(np.abs(np.asarray(out.cameras.alpha_u) / K[:, 0, 0] - 1))
    )
    report["calibrate"]["rms"] = float(np.nanmax(np.asarray(out.report.rms)))
    ref, out = results["refine"]
    report["refine"]["rms_after"] = np.asarray(out.rms_after).tolist()
    report["refine"]["focal_error"] = float(
        np.max(np.abs(np.asarray(out.cameras.alpha_u) / K[:4, 0, 0] - 1))
    )
    ref, out = results["triangulate"]
    err = np.linalg.norm(np.asarray(out.points) - grid, axis=-1)
    report["triangulate"]["error_median"] = float(np.nanmedian(err))
    report["triangulate"]["views"] = np.asarray(out.views).tolist()

    # The helper itself: uneven splits refused, Explicit meshes used as Auto ones.
    try:
        mc.shard(pixels[:63])
        report["odd_count_error"] = None
    except ValueError as e:
        report["odd_count_error"] = str(e)
    explicit = jax.make_mesh((2,), ("cameras",))  # Explicit axes in recent JAX
    report["explicit_mesh"] = layout(mc.shard(pixels, explicit))
    # The collective detector finds one where there must be one: a sum over the split axis.
    summed = jax.jit(lambda p: p.sum(0)).lower(mc.shard(pixels)).compile().as_text()
    report["detector"] = hlo_facts(summed)["collectives"]
    lap("helper")
    print(json.dumps(report))


if __name__ == "__main__":
    main()
