"""Spreading a batch of members over the available devices (both CPU cores, or the GPUs).

On import, lvenv asks XLA for one CPU device per core (``jax_num_cpu_devices``) unless JAX's
backend is already initialised or ``LVENV_CPU_DEVICES`` says otherwise. Batch-last arrays are
then padded (with copies of the last member, which cannot affect the others: members never
interact) and sharded along the batch axis.

Padding also makes a member's result independent of the batch it runs in (in float64, the
default). XLA vectorises the elementwise loops over members, and how it handles a loop depends
on the trip count: measured on AVX-512 (AMD EPYC), a member's metrics in a batch of 8 differ in
the last bit from the same member's in a batch of 16 or more, while all multiples of 16 agree, on
one device or sharded over two. Every batch is therefore padded to a multiple of :data:`LANES`
= 16 members per device (two vectors of 8 float64), which costs a single simulation about a
third more time than padding to 8 did, and buys bit-identical members across batch sizes
(``tests/lvenv/test_batching.py``). In float32, sharding over two devices still changes the
last bits; float32 runs agree within its precision only.
"""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["request_cpu_devices", "shard_members", "padded_size", "MIN_MEMBERS_PER_DEVICE", "LANES"]

MIN_MEMBERS_PER_DEVICE = 64
#: Members per device are padded to a multiple of this (module docstring).
LANES = 16


def request_cpu_devices() -> None:
    """Ask for one XLA CPU device per core; a no-op once JAX's backends exist."""
    count = int(os.environ.get("LVENV_CPU_DEVICES", os.cpu_count() or 1))
    try:
        jax.config.update("jax_num_cpu_devices", max(count, 1))
    except (RuntimeError, AttributeError, ValueError):
        pass


def _devices_used(n_members: int) -> int:
    count = len(jax.devices())
    return 1 if count == 1 or n_members < MIN_MEMBERS_PER_DEVICE * count else count


def padded_size(n_members: int) -> int:
    """Members after padding: a multiple of :data:`LANES` times the devices used."""
    block = LANES * _devices_used(n_members)
    return -(-n_members // block) * block


def shard_members(tree, n_members: int, batch_axis_of=lambda leaf: leaf.ndim - 1):
    """Pad every leaf along its batch axis to :func:`padded_size` and shard it over the devices
    (small batches, fewer than :data:`MIN_MEMBERS_PER_DEVICE` per device, stay on one).
    Returns ``(tree, padded_size)``."""
    size = padded_size(n_members)
    used = _devices_used(n_members)

    def pad(leaf):
        leaf = np.asarray(leaf)
        axis = batch_axis_of(leaf)
        if size == n_members:
            return leaf
        widths = [(0, 0)] * leaf.ndim
        widths[axis] = (0, size - n_members)
        return np.pad(leaf, widths, mode="edge")

    if used == 1:
        return jax.tree.map(pad, tree), size
    mesh = Mesh(np.array(jax.devices()), ("members",))

    def place(leaf):
        leaf = pad(leaf)
        spec = [None] * leaf.ndim
        spec[batch_axis_of(leaf)] = "members"
        return jax.device_put(leaf, NamedSharding(mesh, PartitionSpec(*spec)))

    return jax.tree.map(place, tree), size
