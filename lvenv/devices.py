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
(``tests/lvenv/test_batching.py``). Values computed outside the members' loops can still differ
in the last bit between one device and two, where XLA compiles the program differently: the
fixed scheme's calcium transient, once precomputed for the whole beat, did for four of five
test hearts, so it is evaluated per step inside the loop (:func:`lvenv.simulation.beat`). In
float32, sharding over two devices still changes the last bits; float32 runs agree within its
precision only.

Layout (:func:`layout`): each device runs its own members with its own loops
(:func:`lvenv.simulation.run_beats_parallel`, ``shard_map``), and on the CPU in blocks of at
most :data:`CPU_BLOCK` members, one block after the other. Without blocks the throughput per
member fell with the batch (the states, Jacobian and LU entries of a step are each one array over
the members, and past a few hundred members they leave the core's cache); a member's result does
not depend on its block (``test_a_member_is_bit_identical_in_batches_of_any_size``).
"""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec, SingleDeviceSharding

__all__ = ["request_cpu_devices", "shard_members", "member_shardings", "padded_size", "layout", "member_mesh", "queue_lanes", "MIN_MEMBERS_PER_DEVICE", "LANES", "CPU_BLOCK",
           "QUEUE_MEMBERS_PER_LANE"]

MIN_MEMBERS_PER_DEVICE = 64
#: Members per device are padded to a multiple of this (module docstring).
LANES = 16
#: On the CPU a device runs its members in blocks of at most this many, one block after the other
#: (``LVENV_CPU_BLOCK`` overrides it; 0 turns blocks off). A block's working set stays in the core's
#: cache: measured on this 2-core EPYC (jitted core, 1000 fixed steps per beat), batches of 1,024
#: and 4,096 ran 9.3 k and 9.1 k beats/s without blocks and 14.8 k and 15.0 k with blocks of 256.
#: The adaptive scheme's replay grid (1,024 trial steps per member) is 2 MB at 256 members, and 64
#: were faster for both schemes (README, Performance).
CPU_BLOCK = 64
#: On the CPU the adaptive scheme to steady state queues a device's members through lanes
#: (:func:`queue_lanes`, :func:`lvenv.simulation.run_beats_queued`), this many members per lane
#: or more, between 32 lanes and :data:`CPU_BLOCK`. A lane idles from the moment the queue is
#: empty until the last member finishes, about one member's run, which matters when a lane has
#: only a few members. Measured on this 2-core EPYC, the env at 256 / 1,024 / 4,096 members (two
#: envs in one process, alternating, 5–9 steps each): 32 lanes ran 2,066–2,131 against 1,778–1,816
#: evaluations/s through 64 at 256 (128 members per device), 2,108–2,197 against 2,175–2,434
#: at 1,024 and 2,511–2,958 against 2,578–2,808 at 4,096.
QUEUE_MEMBERS_PER_LANE = 4


def request_cpu_devices() -> None:
    """Ask for one XLA CPU device per core; a no-op once JAX's backends exist."""
    count = int(os.environ.get("LVENV_CPU_DEVICES", os.cpu_count() or 1))
    try:
        jax.config.update("jax_num_cpu_devices", max(count, 1))
    except (RuntimeError, AttributeError, ValueError):
        pass


def _block_limit() -> int | None:
    if jax.default_backend() != "cpu":
        return None
    limit = int(os.environ.get("LVENV_CPU_BLOCK", CPU_BLOCK))
    return None if limit <= 0 else max(LANES, limit // LANES * LANES)


def queue_lanes(members: int) -> int | None:
    """Lanes through which the adaptive scheme to steady state runs a device's ``members`` on the
    CPU (:data:`QUEUE_MEMBERS_PER_LANE`; a multiple of :data:`LANES`, so a member's bits do not
    depend on them); ``LVENV_CPU_QUEUE_LANES`` overrides it. None off the CPU (no queue)."""
    if jax.default_backend() != "cpu":
        return None
    chosen = os.environ.get("LVENV_CPU_QUEUE_LANES")
    if chosen is None:
        return min(CPU_BLOCK, max(2 * LANES, members // QUEUE_MEMBERS_PER_LANE // LANES * LANES))
    if not chosen.isdigit() or int(chosen) < LANES or int(chosen) % LANES:
        raise ValueError(f"LVENV_CPU_QUEUE_LANES = {chosen!r} must be a positive multiple of {LANES} (lvenv.devices.LANES)")
    return int(chosen)


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


def _plan(n_members: int) -> tuple[int, int, int]:
    count = len(jax.devices())
    used = 1 if count == 1 or n_members < MIN_MEMBERS_PER_DEVICE * count else count
    per_device = _ceil_div(n_members, used)
    limit = _block_limit()
    blocks = 1 if limit is None else max(1, _ceil_div(per_device, limit))
    block = _ceil_div(_ceil_div(per_device, blocks), LANES) * LANES
    return used, blocks, block


def layout(n_members: int) -> tuple[int, int, int]:
    """``(devices, blocks per device, members per block)`` of a batch of ``n_members``.

    Their product is :func:`padded_size`, and ``layout(padded_size(n)) == layout(n)``, so jitted
    code can read the layout back from a padded batch's shape (:func:`lvenv.simulation.run_beats_jit`).
    """
    size = n_members
    while True:
        plan = _plan(size)
        if plan[0] * plan[1] * plan[2] == size:
            return plan
        size = plan[0] * plan[1] * plan[2]


def _devices_used(n_members: int) -> int:
    return layout(n_members)[0]


def padded_size(n_members: int) -> int:
    """Members after padding: devices used × blocks per device × members per block (a multiple of :data:`LANES`)."""
    used, blocks, block = layout(n_members)
    return used * blocks * block


def member_mesh() -> Mesh:
    """The one-axis (``"members"``) mesh over all devices that :func:`shard_members` shards along."""
    return Mesh(np.array(jax.devices()), ("members",))


def member_shardings(tree, n_members: int, batch_axis_of=lambda leaf: leaf.ndim - 1):
    """Where each leaf of a batch of ``n_members`` lives (a tree of the structure of ``tree``):
    split along its batch axis over :func:`member_mesh` (as :func:`shard_members` places it), or
    on every device whole where ``batch_axis_of`` says None; all on the first device when the
    batch stays on one.

    A jitted program is compiled again for inputs laid out differently, so a caller that feeds
    a program's outputs back into it (:class:`lvenv.env.LVHeartVectorEnv`'s state and key) puts
    them in these shardings before every call: XLA returns some outputs laid out otherwise (a
    replicated key, a constant flag), and on one device its outputs are committed to the device
    while the first call's host arrays were not."""
    if _devices_used(n_members) == 1:
        return jax.tree.map(lambda leaf: SingleDeviceSharding(jax.devices()[0]), tree)
    mesh = member_mesh()

    def sharding(leaf):
        axis = batch_axis_of(leaf)
        spec = [None] * np.ndim(leaf)
        if axis is not None:
            spec[axis] = "members"
        return NamedSharding(mesh, PartitionSpec(*spec))

    return jax.tree.map(sharding, tree)


def shard_members(tree, n_members: int, batch_axis_of=lambda leaf: leaf.ndim - 1):
    """Pad every leaf along its batch axis to :func:`padded_size` and shard it over the devices
    (:func:`member_shardings`). Small batches, fewer than :data:`MIN_MEMBERS_PER_DEVICE` members
    per device, stay host arrays, which a jitted call puts on one device. Returns
    ``(tree, padded_size)``."""
    size = padded_size(n_members)
    tree = jax.tree.map(np.asarray, tree)

    def pad(leaf):
        axis = batch_axis_of(leaf)
        if size == n_members:
            return leaf
        widths = [(0, 0)] * leaf.ndim
        widths[axis] = (0, size - n_members)
        return np.pad(leaf, widths, mode="edge")

    if _devices_used(n_members) == 1:
        return jax.tree.map(pad, tree), size
    return jax.tree.map(lambda leaf, sharding: jax.device_put(pad(leaf), sharding), tree, member_shardings(tree, n_members, batch_axis_of)), size
