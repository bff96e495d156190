"""Several processes, one result: JAX's distributed runtime for the research loops.

A sweep or study that outgrows one machine runs as N processes of one program. Each process
calls `initialize` first (before any JAX computation), then:

* `fuse_batch` / `fuse_sweep` with `mesh=make_mesh()` shard the batch over the devices of all
  processes; each process builds only its own shards, and `batch.gather` returns the full
  result on every process (it needs the CPU collectives `initialize` switches on).
* A loop over independent items (the study's sequences) takes this process's share with
  `my_items(n)` and collects everyone's results, in item order, with `gather_items`.

How the processes are started is the launcher's business, not this module's: on a cluster,
`initialize()` without arguments lets JAX read the environment of SLURM, Open MPI, Kubernetes
or a TPU pod; on one machine `jaxfusion.lab.processes.launch` (`jaxfusion study --processes N`)
starts N local processes with a coordinator on the loopback address and passes the three
values in `COORDINATOR_ENV`, `NUM_PROCESSES_ENV` and `PROCESS_ID_ENV`, which `initialize()`
reads too.

A process that never joins makes `initialize` fail after `timeout_s` in every process that did;
a process that dies later is noticed by JAX's coordination service after `heartbeat_s`, which
then stops every other process (the local launcher notices a dead process at once and stops
the others itself). Nothing waits forever.

Processes finish their shards at different times, and the CPU collectives (gloo) give a
process 30 s to meet the others in a collective's first call: so every exchange here
(`allgather_objects`, `gather_items`, `batch.gather`) first waits at a barrier of the
coordination service (`barrier`), which waits up to `WAIT_TIMEOUT_S`
(`JAXFUSION_WAIT_TIMEOUT_S`) and costs no collective.
"""

import itertools
import os
import pickle
import sys
import threading
from typing import Any, Optional, Sequence

import jax
import numpy as np
from jax.experimental import multihost_utils

COORDINATOR_ENV = "JAXFUSION_COORDINATOR"
NUM_PROCESSES_ENV = "JAXFUSION_NUM_PROCESSES"
PROCESS_ID_ENV = "JAXFUSION_PROCESS_ID"
TIMEOUT_ENV = "JAXFUSION_JOIN_TIMEOUT_S"   # the launcher's join timeout, optional
DEFAULT_TIMEOUT_S = 60
DEFAULT_HEARTBEAT_S = 30
# How long a process waits at a barrier for the others to finish their shards (a process that
# dies meanwhile is noticed sooner, by the heartbeat); `WAIT_TIMEOUT_ENV` overrides it.
WAIT_TIMEOUT_S = 24 * 3600
WAIT_TIMEOUT_ENV = "JAXFUSION_WAIT_TIMEOUT_S"


class DistributedError(RuntimeError):
  """The processes could not be joined (a process never came, or the coordinator is wrong)."""


def from_environment() -> Optional[dict]:
  """The coordinator address, process count and id a local launcher set (`*_ENV`), or None."""
  values = {name: os.environ.get(name) for name in (COORDINATOR_ENV, NUM_PROCESSES_ENV,
                                                    PROCESS_ID_ENV)}
  if all(v is None for v in values.values()):
    return None
  missing = [name for name, v in values.items() if v is None]
  if missing:
    raise DistributedError(f"the launcher set some of {', '.join(values)} but not "
                           f"{', '.join(missing)}")
  try:
    num, pid = int(values[NUM_PROCESSES_ENV]), int(values[PROCESS_ID_ENV])
  except ValueError:
    raise DistributedError(f"{NUM_PROCESSES_ENV} and {PROCESS_ID_ENV} must be integers; got "
                           f"{values[NUM_PROCESSES_ENV]!r} and {values[PROCESS_ID_ENV]!r}"
                           ) from None
  if not 0 <= pid < num:
    raise DistributedError(f"process id {pid} does not lie in [0, {num})")
  return {"coordinator_address": values[COORDINATOR_ENV], "num_processes": num,
          "process_id": pid}


def initialize(coordinator_address: Optional[str] = None,
               num_processes: Optional[int] = None, process_id: Optional[int] = None, *,
               timeout_s: int = DEFAULT_TIMEOUT_S,
               heartbeat_s: int = DEFAULT_HEARTBEAT_S, name: str = "jaxfusion") -> None:
  """Joins this process to the others (`jax.distributed.initialize`), with CPU collectives.

  Call it first, before any JAX computation. Without arguments it takes the values a local
  launcher set (`from_environment`), else lets JAX detect a cluster (SLURM, …).

  Args:
    coordinator_address: `host:port` of process 0's coordinator.
    num_processes: N.
    process_id: this process's index in [0, N).
    timeout_s: how long to wait for every process to join before failing.
    heartbeat_s: how long a silent process may go before the others are stopped.
    name: the program's name, which begins the line the join watchdog prints.

  Raises:
    DistributedError: with one line saying why, when the processes could not be joined
      within `timeout_s` (e.g. a process never started). Where JAX would instead abort the
      process (the one hosting the coordinator), a watchdog prints
      `NAME: error: could not join …` and ends the process with status 2.
  """
  if jax.distributed.is_initialized():
    return
  if os.environ.get(TIMEOUT_ENV):
    timeout_s = int(os.environ[TIMEOUT_ENV])
  if coordinator_address is None and num_processes is None and process_id is None:
    env = from_environment()
    if env is not None:
      coordinator_address, num_processes, process_id = (
          env["coordinator_address"], env["num_processes"], env["process_id"])
  # The CPU backend's cross-process collectives (gather, the study's result exchange); GPU and
  # TPU backends bring their own and ignore this setting.
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  where = coordinator_address or "the cluster's coordinator"
  message = (f"could not join {num_processes or 'the'} processes at {where} within "
             f"{timeout_s} s (process {process_id})")
  # JAX's own timeout raises in the processes that reach the coordinator, but aborts the
  # process hosting it with a fatal log (a stack dump, no exception). A watchdog keeps the
  # promise of one line: it fires first, says why, and ends the process with status 2.
  joined = threading.Event()
  watchdog = threading.Thread(target=_watch, args=(joined, float(timeout_s), f"{name}: error: {message}"),
                              name="jaxfusion-join-watchdog", daemon=True)
  watchdog.start()
  try:
    jax.distributed.initialize(coordinator_address, num_processes, process_id,
                               initialization_timeout=int(timeout_s) + _JAX_TIMEOUT_MARGIN_S,
                               heartbeat_timeout_seconds=int(heartbeat_s))
  except (RuntimeError, ValueError) as err:   # XlaRuntimeError is a RuntimeError
    raise DistributedError(f"{message}: {_first_line(err)}") from None
  finally:
    joined.set()


def _first_line(err: BaseException) -> str:
  """The first line of a runtime's error (at most 300 characters), or its type's name."""
  text = str(err).strip()
  return text.splitlines()[0][:300] if text else type(err).__name__


# JAX's initialization timeout lies this far past ours, so that the watchdog speaks first.
_JAX_TIMEOUT_MARGIN_S = 30


def _watch(joined: threading.Event, timeout_s: float, line: str) -> None:
  """Ends the process with `line` on stderr unless `joined` is set within `timeout_s`."""
  if joined.wait(timeout_s):
    return
  sys.stderr.write(f"{line}\n")
  sys.stderr.flush()
  os._exit(2)   # pylint: disable=protected-access


def process_index() -> int:
  """This process's index (0 without the distributed runtime)."""
  return jax.process_index()


def process_count() -> int:
  """The number of processes (1 without the distributed runtime)."""
  return jax.process_count()


def is_main() -> bool:
  """True on process 0, the one that writes a run's outputs."""
  return jax.process_index() == 0


def my_items(num_items: int) -> list:
  """The indices in [0, num_items) this process takes: every N-th, from its own index (so
  neighbouring items, which often cost alike, go to different processes)."""
  return list(range(jax.process_index(), int(num_items), jax.process_count()))


def allgather_objects(obj: Any) -> list:
  """Every process's `obj` (any picklable value), as a list in process order, on every
  process. One process: `[obj]`. The bytes travel through JAX's collectives
  (`multihost_utils.process_allgather`); every process must call it."""
  if jax.process_count() == 1:
    return [obj]
  payload = np.frombuffer(pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL), np.uint8)
  barrier("allgather_objects")   # a process that comes later than gloo's 30 s is no error
  sizes = np.asarray(multihost_utils.process_allgather(np.array([payload.size], np.int64)))
  sizes = sizes.reshape(-1)
  padded = np.zeros(int(sizes.max()), np.uint8)
  padded[:payload.size] = payload
  everyone = np.asarray(multihost_utils.process_allgather(padded))   # (N, max size)
  return [pickle.loads(everyone[p, :int(sizes[p])].tobytes()) for p in range(len(sizes))]


def gather_items(local: dict, num_items: int) -> list:
  """The results of all processes in item order: `local` maps this process's item indices
  (`my_items`) to results; returns the list of `num_items` results on every process.

  Raises:
    DistributedError: if some item came from no process, or from two.
  """
  merged = {}
  for part in allgather_objects(dict(local)):
    for index, value in part.items():
      if index in merged:
        raise DistributedError(f"item {index} came from two processes")
      merged[index] = value
  missing = sorted(set(range(int(num_items))) - set(merged))
  if missing:
    raise DistributedError(f"items {missing[:10]} came from no process")
  return [merged[i] for i in range(int(num_items))]


_BARRIERS = itertools.count()   # every process passes the same barriers in the same order


def barrier(name: str, timeout_s: Optional[float] = None) -> None:
  """Waits until every process reaches `barrier(name)` (no-op with one process), for up to
  `timeout_s` (default `WAIT_TIMEOUT_S`, or `JAXFUSION_WAIT_TIMEOUT_S` seconds).

  It is the coordination service's barrier (`jax.distributed`'s client, as JAX's own array
  serialization waits), not a collective: a process may come hours after the others.

  Raises:
    DistributedError: not every process came within `timeout_s` (or one of them failed).
  """
  if jax.process_count() == 1:
    return
  if timeout_s is None:
    timeout_s = float(os.environ.get(WAIT_TIMEOUT_ENV) or WAIT_TIMEOUT_S)
  from jax._src import distributed as jax_distributed  # pylint: disable=import-outside-toplevel
  client = jax_distributed.global_state.client
  if client is None:       # processes joined without jax.distributed: a collective then
    multihost_utils.sync_global_devices(name)
    return
  try:
    client.wait_at_barrier(f"jaxfusion/{next(_BARRIERS)}/{name}",
                           timeout_in_ms=int(1000 * timeout_s))
  except RuntimeError as err:   # XlaRuntimeError: DEADLINE_EXCEEDED, or a process failed
    raise DistributedError(f"process {jax.process_index()} of {jax.process_count()}: not every "
                           f"process reached {name!r} within {timeout_s:g} s: "
                           f"{_first_line(err)}") from None


def shard_of(items: Sequence) -> list:
  """The items of `my_items(len(items))`, as `(index, item)` pairs."""
  return [(i, items[i]) for i in my_items(len(items))]
