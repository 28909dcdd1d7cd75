"""Scale-out: the seed (run) axis of Monte Carlo and of tuning losses split over devices.

Every Monte Carlo run is independent, so a batch of run keys splits over devices with no communication until
the end: :func:`shard_runs` wraps a batch function ``fn(scenario, params, keys)`` in :func:`jax.shard_map`
over a one-axis mesh named ``"runs"``; each device runs ``B / n_devices`` runs (scenario and params are
replicated), and the runs-first outputs come back as one array sharded over the devices. A tuning loss (a mean
over runs) is averaged over the devices with ``pmean``, so its gradient is the gradient of the mean over all
runs.

Devices (``devices`` argument of :func:`jaxatt.montecarlo.monte_carlo`, :func:`jaxatt.fitting.losses.make_loss_fn`,
:func:`jaxatt.fit`):

* ``None`` (default): every device JAX sees (``jax.devices()``): one GPU, all GPUs of the machine, a TPU host,
  or - after ``jax.distributed.initialize()`` - the devices of every host. With one device nothing is sharded.
* an int ``n``: the first ``n`` devices; ``1`` switches sharding off.
* a sequence of ``jax.Device``.

The batch of each call must be a multiple of the device count: :func:`jaxatt.montecarlo.monte_carlo` rounds
its chunk up to one (padding runs are computed and dropped); a tuning minibatch that is not a multiple raises.
The results do not depend on the device count beyond rounding: run k's noise comes from its own key
(``fold_in(PRNGKey(seed), k)``), never from its position in the batch.

CPU check: ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (set before JAX is imported) makes two CPU
devices of one machine; tests/test_sharding.py compares sharded and single-device results that way. On a
2-core CPU machine XLA already uses both cores for some operations, so expect well under 2x from sharding there;
on several GPUs the speed-up is about the device count once each device has a few thousand runs.

Several hosts (``jax.distributed``): every process calls the same function with the same arguments; outputs
are gathered to every process with ``jax.experimental.multihost_utils.process_allgather``. That path is
written to the documented API but has not been run on more than one host here.
"""

from __future__ import annotations

from typing import Any, Callable, Optional, Sequence, Union

import jax
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

__all__ = ["resolve_devices", "seed_mesh", "shard_runs", "to_host", "AXIS"]

#: Name of the mesh axis that carries the runs.
AXIS = "runs"

Devices = Union[None, int, Sequence[Any]]


def resolve_devices(devices: Devices = None) -> tuple:
    """The devices to shard over (see the module docstring): a tuple of ``jax.Device``."""
    all_devices = jax.devices()
    if devices is None:
        return tuple(all_devices)
    if isinstance(devices, (int, np.integer)):
        n = int(devices)
        if not 1 <= n <= len(all_devices):
            raise ValueError(f"devices={n}: need 1 <= n <= {len(all_devices)} (visible devices: {all_devices})")
        return tuple(all_devices[:n])
    out = tuple(devices)
    if not out:
        raise ValueError("devices: empty sequence")
    return out


def seed_mesh(devices: Devices = None) -> Optional[Mesh]:
    """A one-axis mesh (``"runs"``) over ``devices``, or None when there is only one device."""
    devs = resolve_devices(devices)
    if len(devs) == 1:
        return None
    return Mesh(np.asarray(devs, dtype=object), (AXIS,))


def shard_runs(fn: Callable, mesh: Optional[Mesh], *, out_specs: Any = None, reduce: Optional[Callable] = None):
    """``fn(scenario, params, keys)`` with the runs (axis 0 of ``keys``) split over ``mesh``.

    ``out_specs``: partition specs of the outputs (default: every output runs-first, split over the runs).
    ``reduce(outputs) -> outputs`` runs on each device after ``fn`` (e.g. ``pmean`` of a loss over ``"runs"``).
    Returns ``fn`` unchanged when ``mesh`` is None. The wrapped function is not jitted (jit it, or call it
    inside a jitted function); its ``keys`` length must be a multiple of the device count.
    """
    out_specs = P(AXIS) if out_specs is None else out_specs
    if mesh is None:
        return fn if reduce is None else (lambda *a: reduce(fn(*a)))
    body = fn if reduce is None else (lambda *a: reduce(fn(*a)))
    # check_vma=False: the scan carries mix replicated (step counter) and per-device (run state) values,
    # which the replication checker rejects; every output spec below is correct by construction (the runs
    # are independent) and tests/test_sharding.py checks values and gradients against one device.
    return jax.shard_map(body, mesh=mesh, in_specs=(P(), P(), P(AXIS)), out_specs=out_specs, check_vma=False)


def check_batch(n_runs: int, mesh: Optional[Mesh]) -> None:
    """Raise if ``n_runs`` does not split evenly over ``mesh``."""
    if mesh is not None and n_runs % mesh.size:
        raise ValueError(
            f"a batch of {n_runs} runs does not split over {mesh.size} devices: use a multiple of "
            f"{mesh.size} (or devices=1)"
        )


def to_host(tree):
    """Fetch (possibly sharded, possibly multi-host) arrays as numpy arrays."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return multihost_utils.process_allgather(tree, tiled=True)
    return jax.tree_util.tree_map(lambda a: None if a is None else np.asarray(a), tree)
