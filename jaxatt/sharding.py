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
its chunk up to one (padding runs are computed and dropped); :func:`jaxatt.fit` with ``devices=None`` runs on the
most devices its minibatches split over (with a warning when that is fewer than all), and a minibatch that is not
a multiple of an explicit device count raises.
The results do not depend on the device count beyond rounding: run k's noise comes from its own key
(``fold_in(PRNGKey(seed), k)``), never from its position in the batch.

CPU check: ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (set before JAX is imported) makes two CPU
devices of one machine; tests/test_sharding.py compares sharded and single-device results that way. On a
2-core CPU machine XLA already uses both cores for some operations, so expect well under 2x from sharding there;
on several GPUs the speed-up is about the device count once each device has a few thousand runs.

Several processes (``jax.distributed``; several hosts, or several processes on one machine): start every
process with the same script and arguments, and call :func:`initialize_distributed` (or
``jax.distributed.initialize``) first, before any other JAX call. Every process then calls the same function
with the same arguments (the same chunks, keys, params, in the same order); the runs axis splits over every
global device (``jax.devices()``), and :func:`to_host` gathers the results to every process
(``multihost_utils.process_allgather``), so each process holds the whole result. Files (JSON, gains, NPZ, plots)
are written by process 0 only (:func:`jaxatt.io.is_main_process`). With ``devices=1`` each process runs every run
on its own first local device, without communication. Checked with two CPU processes on one machine (gloo
collectives) by tests/test_distributed.py; the same code is the path on a GPU cluster.
"""

from __future__ import annotations

import os
from typing import Any, Callable, Mapping, Optional, Sequence, Union

import jax
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

__all__ = [
    "resolve_devices",
    "seed_mesh",
    "shard_runs",
    "to_host",
    "agree",
    "initialize_distributed",
    "distributed_settings",
    "AXIS",
    "ENV_COORDINATOR",
    "ENV_NUM_PROCESSES",
    "ENV_PROCESS_ID",
]

#: Name of the mesh axis that carries the runs.
AXIS = "runs"
#: Environment variables read by :func:`initialize_distributed` (and so by the ``jaxatt`` command).
ENV_COORDINATOR = "JAXATT_COORDINATOR"
ENV_NUM_PROCESSES = "JAXATT_NUM_PROCESSES"
ENV_PROCESS_ID = "JAXATT_PROCESS_ID"

Devices = Union[None, int, Sequence[Any]]


def _check_own(devs: tuple, what: str) -> tuple:
    """With several processes every process must own one of ``devs`` (it runs its share of the runs there)."""
    if jax.process_count() > 1:
        mine = {d.id for d in jax.local_devices()}
        if not any(d.id in mine for d in devs):
            raise ValueError(
                f"{what}: process {jax.process_index()} owns none of these devices ({list(devs)}); with several "
                "processes every process must own at least one (use devices=None for every device, or 1)"
            )
    return devs


def resolve_devices(devices: Devices = None) -> tuple:
    """The devices to shard over (see the module docstring): a tuple of ``jax.Device``.

    ``None``: every global device (all processes'); ``1``: this process's first local device (with several
    processes each process then runs every run itself); ``n > 1``: the first ``n`` global devices; a sequence:
    those devices. With several processes every process must own one of them (ValueError otherwise).
    """
    all_devices = jax.devices()
    if devices is None:
        return tuple(all_devices)
    if isinstance(devices, (int, np.integer)) and not isinstance(devices, bool):
        n = int(devices)
        if not 1 <= n <= len(all_devices):
            raise ValueError(f"devices={n}: need 1 <= n <= {len(all_devices)} (visible devices: {all_devices})")
        if n == 1:
            return (jax.local_devices()[0],)
        return _check_own(tuple(all_devices[:n]), f"devices={n}")
    if isinstance(devices, (str, bytes, bool)) or not hasattr(devices, "__iter__"):
        raise ValueError(f"devices must be None, a number of devices or a sequence of jax.Device, got {devices!r}")
    out = tuple(devices)
    if not out:
        raise ValueError("devices: empty sequence")
    return _check_own(out, "devices")


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
    inside a jitted function); its ``keys`` length must be a multiple of the device count. With several processes
    the inputs are host values (numpy or single-device arrays), equal in every process: they enter as replicated
    values and each device takes its slice of the keys.
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


def _host(a):
    if a is None:
        return None
    if isinstance(a, jax.Array) and not a.is_fully_addressable:
        # spread over several processes (sharded runs, or a replicated loss): every process gets the whole value
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(a)


def to_host(tree):
    """Fetch (possibly sharded, possibly multi-process) arrays as numpy arrays with their global shapes.

    An array spread over several processes is gathered to every process (a collective: every process must call
    this with the same tree); an array held by this process alone (``devices=1``) is read as it is.
    """
    return jax.tree_util.tree_map(_host, tree)


def agree(tree):
    """Numpy copies of ``tree`` (:func:`to_host`), equal in every process: with several processes process 0's
    values are broadcast (``multihost_utils.broadcast_one_to_all``), so decisions taken on them (a non-finite
    loss, early stopping) are the same everywhere and no process waits for a collective the others skip. With one
    process: :func:`to_host`."""
    host = to_host(tree)
    if jax.process_count() == 1:
        return host
    from jax.experimental import multihost_utils

    return jax.tree_util.tree_map(np.asarray, multihost_utils.broadcast_one_to_all(host))


def distributed_settings(environ: Optional[Mapping[str, str]] = None) -> Optional[dict]:
    """The ``jax.distributed.initialize`` arguments named by the environment, or None when none is set.

    ``JAXATT_COORDINATOR`` (``host:port`` of process 0's coordinator; JAX's own ``JAX_COORDINATOR_ADDRESS`` is
    read when unset), ``JAXATT_NUM_PROCESSES`` and ``JAXATT_PROCESS_ID`` (0 ... n-1). Setting some but not all of
    them is an error (ValueError naming the missing ones); so is a non-integer or out-of-range value.
    """
    env = os.environ if environ is None else environ
    coordinator = env.get(ENV_COORDINATOR) or None
    n_raw, pid_raw = env.get(ENV_NUM_PROCESSES) or None, env.get(ENV_PROCESS_ID) or None
    if coordinator is None and n_raw is None and pid_raw is None:
        return None
    coordinator = coordinator or env.get("JAX_COORDINATOR_ADDRESS") or None
    missing = [
        k
        for k, v in ((ENV_COORDINATOR, coordinator), (ENV_NUM_PROCESSES, n_raw), (ENV_PROCESS_ID, pid_raw))
        if v is None
    ]
    if missing:
        raise ValueError(f"several processes: set {', '.join(missing)} too (or none of the JAXATT_* variables)")
    try:
        n, pid = int(str(n_raw)), int(str(pid_raw))
    except ValueError:
        raise ValueError(f"{ENV_NUM_PROCESSES}={n_raw!r} and {ENV_PROCESS_ID}={pid_raw!r} must be integers") from None
    if n < 1 or not 0 <= pid < n:
        raise ValueError(f"need {ENV_NUM_PROCESSES} >= 1 and 0 <= {ENV_PROCESS_ID} < {n}, got {n_raw}, {pid_raw}")
    if ":" not in str(coordinator):
        raise ValueError(f"{ENV_COORDINATOR}={coordinator!r}: expected host:port (e.g. 10.0.0.1:12345)")
    return {"coordinator_address": str(coordinator), "num_processes": n, "process_id": pid}


def initialize_distributed(
    coordinator: Optional[str] = None,
    num_processes: Optional[int] = None,
    process_id: Optional[int] = None,
    *,
    timeout_s: int = 300,
    environ: Optional[Mapping[str, str]] = None,
) -> bool:
    """Join a multi-process run (``jax.distributed.initialize``) before any other JAX call; True when it did.

    ``coordinator`` (``host:port`` reachable from every process, served by process 0), ``num_processes`` and
    ``process_id`` (0 ... n-1); when all three are None they are read from the environment
    (:func:`distributed_settings`), and with none set nothing happens (one process; returns False). On CPU the
    cross-process collectives use gloo (``jax_cpu_collectives_implementation``, set here unless already chosen);
    GPUs use NCCL, TPUs their own. ``timeout_s``: how long to wait for the other processes (s). Calling it again
    once initialized returns True and does nothing. Every process must then run the same program (same
    functions, same arguments, same order); see the module docstring.
    """
    if jax.distributed.is_initialized():
        return True
    if coordinator is None and num_processes is None and process_id is None:
        settings = distributed_settings(environ)
        if settings is None:
            return False
    else:
        if coordinator is None or num_processes is None or process_id is None:
            raise ValueError("initialize_distributed: give coordinator, num_processes and process_id together")
        settings = {
            "coordinator_address": coordinator,
            "num_processes": int(num_processes),
            "process_id": int(process_id),
        }
    if not getattr(jax.config, "jax_cpu_collectives_implementation", None):  # older JAX: no default
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(**settings, initialization_timeout=int(timeout_s))
    return True
