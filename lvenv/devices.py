"""Spreading a batch of members over the available devices (both CPU cores, or the GPUs).

On import, lvenv asks XLA for one CPU device per core (``jax_num_cpu_devices``) unless JAX's
backend is already initialised or ``LVENV_CPU_DEVICES`` says otherwise. Batch-last arrays are
then padded to a multiple of the device count (with copies of the last member, which cannot
affect the others: members never interact) and sharded along the batch axis.
"""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["request_cpu_devices", "shard_members", "MIN_MEMBERS_PER_DEVICE"]

MIN_MEMBERS_PER_DEVICE = 64


def request_cpu_devices() -> None:
    """Ask for one XLA CPU device per core; a no-op once JAX's backends exist."""
    count = int(os.environ.get("LVENV_CPU_DEVICES", os.cpu_count() or 1))
    try:
        jax.config.update("jax_num_cpu_devices", max(count, 1))
    except (RuntimeError, AttributeError, ValueError):
        pass


def shard_members(tree, n_members: int, batch_axis_of=lambda leaf: leaf.ndim - 1):
    """Pad and shard every leaf along its batch axis. Returns ``(tree, padded_size)``.

    Small batches (fewer than :data:`MIN_MEMBERS_PER_DEVICE` per device) stay on one device.
    """
    devices = jax.devices()
    if len(devices) == 1 or n_members < MIN_MEMBERS_PER_DEVICE * len(devices):
        return tree, n_members
    pad = (-n_members) % len(devices)
    mesh = Mesh(np.array(devices), ("members",))

    def place(leaf):
        leaf = np.asarray(leaf)
        axis = batch_axis_of(leaf)
        if pad:
            widths = [(0, 0)] * leaf.ndim
            widths[axis] = (0, pad)
            leaf = np.pad(leaf, widths, mode="edge")
        spec = [None] * leaf.ndim
        spec[axis] = "members"
        return jax.device_put(leaf, NamedSharding(mesh, PartitionSpec(*spec)))

    return jax.tree.map(place, tree), n_members + pad
