"""Scale of the joint rig refinement: C cameras x ~10k residuals each, one least-squares problem.

A rig of C random cameras (0.3 px noise) sees a dense box corner with 3 n^2 dots (n = 41: 5043
dots, 10086 residuals per camera). `mvcalib.refine_rig` refines all cameras jointly (pinhole
model, known target); the script prints wall time (first call, compile included), steps,
RMS before/after and peak resident memory. `--quick`: 16 cameras x 864 residuals.

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

import mvcalib as mc  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "refine_rig.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    n, C = (12, 16) if args.quick else (41, 64)
    target = mc.targets.box_corner_grid(n)
    rig = mc.synthetic.random_rig(jax.random.key(0), C, target=target, noise=0.3, fill=(0.8, 0.95))
    seed = mc.calibrate(rig.world, rig.pixels, rig.mask).cameras
    seed = eqx.tree_at(lambda c: c.skew, seed, jnp.zeros(C))
    start = time.perf_counter()
    out = mc.refine_rig(seed, rig.world, rig.pixels, rig.mask, distortion=())
    jax.block_until_ready(out)
    seconds = time.perf_counter() - start
    row = {
        "cameras": C,
        "residuals_per_camera": 2 * len(target.points),
        "residuals_total": int(2 * rig.mask.sum()),
        "seconds_first_call": round(seconds, 2),
        "steps": int(out.iterations),
        "result": out.messages(),
        "rms_before": float(out.rms_before.mean()),
        "rms_after": float(out.rms_after.mean()),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024,
    }
    for k, v in row.items():
        print(f"{k:>22}: {v}")
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(row, indent=2) + "\n")


if __name__ == "__main__":
    main()
