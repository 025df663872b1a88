"""Batches of independent rollouts spread over every local device (`jax.sharding`).

Evaluation and data generation integrate many initial conditions that never interact:
`batch_jit(fn)` is `jax.jit(fn)` with the leading (batch) axis of every argument and
output split across the local devices (`local_devices`) on a one-axis mesh named `"batch"`;
`axis_sharding(axis)` splits another axis (or none: arrays whole on every device), for
programs whose arguments are batched differently (`lgnn.engines.rollouts`). The same
code then uses one CPU, every GPU of a host, or forced host devices
(`XLA_FLAGS=--xla_force_host_platform_device_count=N`, as the tests do); there is no
hand-made multiprocessing and no communication between devices.

A batch must be a whole multiple of the device count: `padded_size` rounds a size up
and `pad_batch` fills a short batch by repeating its last element (callers drop the
padding from the results).

The local devices are those of `platform()`: JAX's default backend, or the host's CPU
inside `on_platform("cpu")` on a GPU machine (a small batch of ground-truth rollouts
there: `lgnn.engines.rollouts.ground_truth_platform`). The context is JAX's own `jax.default_device`,
so everything computed in it, sharded here or not, goes to the same place; like JAX's,
it holds in the thread that entered it.
"""

from __future__ import annotations

import contextlib
from typing import Callable, Iterator

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec


def platform() -> str:
    """Where this thread's computations go: the platform ("cpu", "gpu", "tpu") of the
    default device an `on_platform` (or `jax.default_device`) context set, else JAX's
    default backend's."""
    device = jax.config.jax_default_device
    if device is None:
        return jax.default_backend()
    return device if isinstance(device, str) else device.platform


def local_devices() -> list:
    """This process's devices of `platform()`."""
    return jax.local_devices(backend=platform())


@contextlib.contextmanager
def on_platform(name: str | None) -> Iterator[None]:
    """Compute on this process's devices of platform `name` (e.g. "cpu" on a GPU
    machine) inside the block; None changes nothing."""
    if name is None or name == platform():
        yield
        return
    with jax.default_device(jax.local_devices(backend=name)[0]):
        yield


def device_count() -> int:
    return len(local_devices())


def axis_sharding(axis: int | None) -> NamedSharding:
    """Axis `axis` of every array split over the local devices (None: arrays whole on
    each device)."""
    spec = PartitionSpec() if axis is None else PartitionSpec(*([None] * axis), "batch")
    return NamedSharding(Mesh(np.asarray(local_devices()), ("batch",)), spec)


def batch_sharding() -> NamedSharding:
    """Leading axis split over the local devices, other axes whole on each."""
    return axis_sharding(0)


def batch_jit(fn: Callable) -> Callable:
    """`jax.jit(fn)` with every argument and output sharded along its leading axis."""
    sharding = batch_sharding()
    return jax.jit(fn, in_shardings=sharding, out_shardings=sharding)


def padded_size(size: int) -> int:
    """The smallest multiple of the device count that holds `size` elements."""
    n = device_count()
    return -(-size // n) * n


def pad_batch(array: np.ndarray, size: int) -> np.ndarray:
    """`array` (B, ...) with B <= size, its last element repeated up to `size`."""
    missing = size - len(array)
    if missing < 0:
        raise ValueError(f"batch of {len(array)} does not fit {size}")
    return np.concatenate([array, np.repeat(array[-1:], missing, axis=0)]) if missing else array
