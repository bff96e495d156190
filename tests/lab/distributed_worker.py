"""One process of tests/lab/test_processes.py's two-process runs (started by
`lab.processes.launch`): `python tests/lab/distributed_worker.py MODE OUT`.

MODE `fuse`: joins the runtime, fuses `batch_inputs()` with `fuse_batch` and `fuse_sweep`
sharded over the devices of both processes, gathers them, exchanges a Python object with
`allgather_objects`, and process 0 saves everything to OUT (.npz).
MODE `die`: joins, then process 1 exits with status 3 while process 0 waits on a collective.
MODE `late`: process 1 reaches `gather_items` and `batch.gather` `LATE_S` after process 0,
longer than the 30 s in which gloo's collectives let processes meet; process 0 saves both.
MODE `absent`: process 0 waits at a barrier of 3 s that process 1 never reaches; process 0
prints the `DistributedError` and exits with status 4.
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from jaxfusion import distributed  # pylint: disable=wrong-import-position

K, CAPACITY = 5, 2**10
LATE_S = 40


def batch_inputs():
  """B = 3 sequences of 2 frames at 12×16 (3 does not divide 2 devices: padding is used),
  a camera, and R = 3 stacked D+R rules."""
  import numpy as np
  import jaxfusion as jf
  rng = np.random.default_rng(7)
  depth = rng.uniform(0.6, 2.4, (3, 2, 12, 16)).astype(np.float32)
  depth[:, :, 0, :3] = 0.0
  poses = np.tile(np.eye(4, dtype=np.float32), (3, 2, 1, 1))
  poses[..., 0, 3] = rng.uniform(-0.3, 0.3, (3, 2)).astype(np.float32)
  probs = rng.dirichlet(np.ones(K), (3, 2, 12, 16)).astype(np.float32)
  var = rng.uniform(0.0, 0.05, (3, 2, 12, 16, K)).astype(np.float32)
  camera = jf.Camera(10.0, 10.0, 7.5, 5.5)
  rules = jf.rules.stack([jf.rules.robust(beta=b) for b in (0.1, 0.3, 0.6)])
  return jf.Frame(depth, poses, probs, var), camera, rules


def fuse(mesh=None):
  """`fuse_batch` (D+R β = 0.3) and `fuse_sweep` (of sequence 0) as NumPy dicts."""
  import jax
  import numpy as np
  import jaxfusion as jf
  frames, camera, rules = batch_inputs()
  states = jf.fuse_batch(frames, camera, jf.rules.robust(beta=0.3), capacity=CAPACITY,
                         mesh=mesh)
  seq0 = jax.tree.map(lambda x: x[0], frames)
  swept = jf.fuse_sweep(seq0, camera, rules, capacity=CAPACITY, mesh=mesh)
  out = {}
  for name, tree in (("batch", states), ("sweep", swept)):
    tree = jf.batch.gather(tree)
    out.update({f"{name}_keys": np.asarray(tree.keys), f"{name}_hits": np.asarray(tree.hits)})
    out.update({f"{name}_rows_{k}": np.asarray(v) for k, v in tree.rows.items()})
  return out


def main(mode: str, out: str) -> int:
  distributed.initialize()
  import numpy as np
  if mode == "die":
    distributed.barrier("joined")
    if distributed.process_index() == 1:
      os._exit(3)
    distributed.allgather_objects("waiting for process 1")   # never answered
    return 0
  import jaxfusion as jf
  if mode == "absent":
    if distributed.process_index() == 0:
      try:
        distributed.barrier("never reached", timeout_s=3)
      except distributed.DistributedError as err:
        print(f"DistributedError: {err}", flush=True)
        os._exit(4)
    else:
      import time
      time.sleep(20)
    return 0
  if mode == "late":
    import time
    if distributed.process_index() == 1:
      time.sleep(LATE_S)
    gathered = distributed.gather_items({i: f"item {i}" for i in distributed.my_items(3)}, 3)
    if distributed.process_index() == 0:
      time.sleep(LATE_S)     # now process 0 comes late
    ones = jf.batch.gather(jf.batch.put_sharded(np.arange(4.0), jf.make_mesh(), sharded=True))
    if distributed.is_main():
      np.savez(out, gathered=np.array(gathered), ones=ones)
    return 0
  arrays = fuse(jf.make_mesh())
  objects = distributed.allgather_objects({"process": distributed.process_index(),
                                           "items": distributed.my_items(5)})
  gathered = distributed.gather_items({i: f"item {i}" for i in distributed.my_items(5)}, 5)
  if distributed.is_main():
    np.savez(out, num_devices=len(jf.make_mesh().devices.ravel()),
             process_count=distributed.process_count(), objects=np.array(repr(objects)),
             gathered=np.array(gathered), **arrays)
  distributed.barrier("saved")
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv[1], sys.argv[2]))
