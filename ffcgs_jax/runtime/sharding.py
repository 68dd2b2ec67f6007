"""Splitting independent per-item work (wrist poses, sampler candidates) over the local devices.

Everything the pipeline does per pose or per candidate is independent of the other items, so each device runs its
share under `jax.shard_map` with every loop (descent steps, simplex pivots, decoder chunks) local to it, and the
devices exchange nothing until the results are gathered. Batches that do not divide evenly are padded by repeating
their last item; the padding is cut off the results.
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from ffcgs_jax.core.errors import FfcgsError

AXIS = "poses"


def device_mesh(devices: int = 0) -> Mesh:
    """A 1-D mesh over the first `devices` local devices of the default backend (0: all of them)."""
    local = jax.local_devices()
    if devices > len(local):
        raise FfcgsError(f"devices = {devices} asked for, but this machine has {len(local)} "
                         f"{jax.default_backend()} device(s)")
    return Mesh(np.array(local[:devices or len(local)]), (AXIS,))


def split(fn: Callable, mesh: Mesh | None, shared: tuple, items: tuple, out_specs=P(AXIS)):
    """fn(*shared, *items) with the leading axis of every `items` array split over the mesh's devices.

    `shared` go whole to every device. `out_specs` says where each output has the item axis (default: leading);
    a spec naming no axis means the output is the same on every device. With no mesh, or one device, fn runs as is.
    """
    if mesh is None or mesh.size == 1:
        return fn(*shared, *items)
    n = jax.tree.leaves(items)[0].shape[0]
    extra = (-n) % mesh.size
    padded = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], extra, 0)]) if extra else x, items)
    in_specs = (*(P(),) * len(shared), *(jax.tree.map(lambda _: P(AXIS), x) for x in padded))
    out = jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)(*shared, *padded)
    if not extra:
        return out

    def cut(spec, sub):
        axis = list(spec).index(AXIS) if AXIS in spec else None
        return jax.tree.map(lambda x: x if axis is None else jax.lax.slice_in_dim(x, 0, n, axis=axis), sub)

    if isinstance(out_specs, P):
        return cut(out_specs, out)
    return jax.tree.map(cut, out_specs, out, is_leaf=lambda x: isinstance(x, P))
