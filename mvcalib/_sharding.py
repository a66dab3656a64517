"""Spreading a rig (or a cloud of points) over several devices with `jax.sharding`.

Nothing in mvcalib needs to know about devices: every batched kernel is one camera (or one point)
vmapped over a leading axis, so when the inputs of a compiled call are sharded along that axis,
XLA's sharding propagation (GSPMD) splits the whole computation the same way and each device
solves its own cameras. `shard` only puts the arrays there.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["shard"]


def _auto_mesh(mesh: Mesh | None) -> Mesh:
    """`mesh`, or a 1-D mesh over all devices, with GSPMD's automatic ("Auto") axes.

    `jax.make_mesh` builds "Explicit" axes in recent JAX, where every operation must have a
    sharding rule at trace time; mvcalib's kernels are written for GSPMD's propagation, and are
    tested that way, so the same devices and names are used with Auto axes.
    """
    if mesh is None:
        return Mesh(np.array(jax.devices()), ("batch",))
    if not isinstance(mesh, Mesh):
        raise ValueError(f"`mesh` must be a jax.sharding.Mesh; got {type(mesh).__name__}.")
    auto = getattr(getattr(jax.sharding, "AxisType", None), "Auto", None)
    if auto is None or all(t == auto for t in getattr(mesh, "axis_types", ())):
        return mesh
    return Mesh(mesh.devices, mesh.axis_names, axis_types=(auto,) * len(mesh.axis_names))


def shard(tree, mesh: Mesh | None = None, *, axis: int | None = 0):
    """Split axis `axis` of every array in `tree` across the devices of `mesh`.

    mvcalib's functions respect sharded inputs: `calibrate`, `dlt`, `Camera.from_projection`,
    `refine`, `to_global` and `reproject` on arrays whose camera axis is split across devices run
    split the same way (each device solves its own cameras, no data moves between devices) and
    return results split the same way; `triangulate` does the same with the point axis. Results
    equal the single-device ones to rounding (the compiler may fuse the per-device program
    differently; integer outputs such as statuses are identical). See docs/scaling.md for several
    GPUs or hosts.

    **Arguments:**

    - `tree`: an array, a `Camera`, or any pytree of them (a tuple `(pixels, mask)`, ...). NumPy
      arrays are placed too; other leaves (Python numbers, None) are returned as they are.
    - `mesh`: the devices, a `jax.sharding.Mesh`; default: a 1-D mesh over all of `jax.devices()`
      (every process's devices after `jax.distributed.initialize`). With several mesh axes the
      array axis is split over all of them. Explicit mesh axes are used as automatic ones (see
      docs/scaling.md).
    - `axis`: which array axis to split, counted from the front, the same for every array:
      `0` for the camera axis of `pixels (C, N, 2)`, `mask (C, N)`, a rig `Camera (C,)` or
      per-camera `world (C, N, 3)`; `1` for the point axis of `triangulate`'s `pixels (C, N, 2)`
      and `mask (C, N)`. `None` replicates every array on all devices (the cameras given to a
      sharded `triangulate`, a target's world points shared by the rig). Arrays with no axis
      `axis` (scalars) are replicated.

    **Returns:** `tree` with each array a `jax.Array` on the mesh, split along `axis`.

    **Raises:** `ValueError` if an array's axis `axis` is not a multiple of the number of
    devices: JAX cannot split it evenly. Pad it with masked-out cameras or points (`mask` False:
    a padded camera gets `Status.TOO_FEW_POINTS`, a padded point NaN, and neither changes the
    others), or use fewer devices.

    Leave a target's world points `(N, 3)` shared by the whole rig out of `tree` (or pass them
    with `axis=None`): split along the points, every device would need all of them and XLA would
    gather them back.

    **Example:**

    ```python
    >>> import jax, jax.numpy as jnp, mvcalib as mc
    >>> rig = mc.Camera(alpha_u=jnp.array([800.0, 850.0, 900.0, 950.0]), alpha_v=800.0,
    ...                 u0=320.0, v0=240.0, R=jnp.eye(3), t=jnp.array([0.0, 0.0, 5.0]))
    >>> split = mc.shard(rig)  # 4 cameras over all devices
    >>> split.R.sharding.num_devices == jax.device_count()
    True
    >>> pixels = mc.reproject(split, jnp.array([[1.0, 0.0, 0.0]]))  # each device its cameras
    >>> pixels.sharding.is_equivalent_to(split.t.sharding, 3), pixels[:, 0, 0].tolist()
    (True, [480.0, 490.0, 500.0, 510.0])

    ```

    Calibration the same way: `mc.calibrate(world, *mc.shard((pixels, mask)))`.
    """
    mesh = _auto_mesh(mesh)
    if axis is not None and (isinstance(axis, bool) or not isinstance(axis, int) or axis < 0):
        raise ValueError(
            f"`axis` must be a non-negative int (counted from the front, the same for every "
            f"array) or None; got {axis!r}."
        )
    n_devices = mesh.devices.size
    names = tuple(mesh.axis_names)
    split = names[0] if len(names) == 1 else names

    def put(x, sharding):
        # Across processes, from each process's own slices of its (identical) host array:
        # `jax.device_put` would first check that every process passed the same array, with
        # `np.equal`, and fail on any NaN (the unseen pixels of a correspondences file).
        if jax.process_count() > 1 and isinstance(x, np.ndarray):
            return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])
        return jax.device_put(x, sharding)

    def place(x):
        if not isinstance(x, (jax.Array, np.ndarray)):
            return x
        ndim = np.ndim(x)
        if axis is None or ndim <= axis:
            return put(x, NamedSharding(mesh, PartitionSpec()))
        size = np.shape(x)[axis]
        if size % n_devices:
            raise ValueError(
                f"an array of shape {tuple(np.shape(x))} cannot be split along axis {axis} "
                f"(length {size}) over {n_devices} devices: the length must be a multiple of "
                f"{n_devices}. Pad it with masked-out cameras or points (mask False), or "
                "use fewer devices."
            )
        spec = PartitionSpec(*([None] * axis), split)
        return put(x, NamedSharding(mesh, spec))

    return jax.tree_util.tree_map(place, tree)


def cpu_chunk(n: int, size: int) -> int | None:
    """`size`, the most entries of a batch of `n` to run side by side in one step of a loop, on one
    CPU device where `n > size`; else None: run all `n` at once.

    On a CPU a chunk's intermediate arrays stay in cache, and a loop of vmapped solves pays each
    chunk's slowest member rather than the whole batch's. Accelerators want the whole batch, and
    an axis sharded over several devices must not be cut into a sequential loop.
    """
    if jax.default_backend() != "cpu" or jax.device_count() > 1 or n <= size:
        return None
    return size


def batched_lapack_may_hang() -> bool:
    """Whether a batch of LAPACK factorisations could hang here: on several CPU devices, jaxlib
    runs each device's batch through XLA's CPU thread pool, and when every device's program calls
    one at once, each holds a worker and waits for sub-tasks queued behind the others'
    (docs/scaling.md). Small solves are then written out, without LAPACK."""
    return jax.default_backend() == "cpu" and jax.device_count() > 1


def chunked_map(fn, inputs: tuple, size: int | None, *, axis: int = 0):
    """`fn(*inputs)` for a `fn` batched along `axis` of every input array and along the leading
    axis of every output, run as a `lax.map` over equal chunks of at most `size` entries (all at
    once if `size` is None).

    The chunks are equal, padded with copies of the last entry (at most one fewer than the number
    of chunks), so that the loop body compiles once: `lax.map` compiles a ragged last chunk
    separately. The padding's outputs are dropped.
    """
    if size is None:
        return fn(*inputs)
    n = jax.tree_util.tree_leaves(inputs)[0].shape[axis]
    n_chunks = -(-n // size)
    size = -(-n // n_chunks)
    pad = n_chunks * size - n

    def split(a):
        last = jax.lax.slice_in_dim(a, n - 1, n, axis=axis)
        a = jnp.concatenate([a, jnp.repeat(last, pad, axis)], axis)
        return jnp.moveaxis(
            a.reshape(a.shape[:axis] + (n_chunks, size) + a.shape[axis + 1 :]), axis, 0
        )

    out = jax.lax.map(lambda chunk: fn(*chunk), jax.tree_util.tree_map(split, inputs))
    return jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:])[:n], out)
