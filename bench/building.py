"""`python -m bench.building [--quick]`: a building-sized map, from 10⁴ to 10⁷ voxels.

The camera walks the whole embedded floor `floor:ROOMS` (`jaxfusion.datasets.floor`: N rooms of
the embedded world joined by corridors, one frame every 0.1 m, through every room) and every
frame is fused into one `Mapper` that grows: the semantic layer (K = the world's 7 classes, D+R
rule, the frame's GT labels as probabilities 0.8 on the label and the rest spread evenly, a
variance of 0.01) and a geometry layer (`TSDFConfig` of the same voxel size, 8³ blocks, τ = 4
voxels), both starting small (2^15 slots, 2^11 blocks; --quick 2^14, 2^10; growth factor 4),
until the map holds 1.1·10⁷ voxels or the walk ends (`--stop-at`). Frames are rendered
on the fly (their render time is reported apart, never counted as fusion).

Why 2 cm. A pixel adds at most one semantic voxel per frame and the walk sees each surface from
1–8 m, so the number of voxels held is about the surface seen divided by the voxel's face: a
12-room floor shows ~3,000 m² of walls, floor, ceiling and furniture, ~7·10⁶ faces of 2 cm (with
the sensor's depth noise spreading surfaces over more than one voxel, more), and ~1.9·10⁶ at
4 cm. The full run therefore uses 2 cm voxels in both layers and 16 rooms; it reports the
voxels it reached, whether or not that is 10⁷.

Measured:

* per-frame fuse time against the voxels held, two ways: the walk's own frames
  (`Mapper.fuse` + `jax.block_until_ready`) as the median over windows of frames, frames that
  grew a layer and the first frame (a compile) left out, against the voxels (and TSDF blocks)
  held at the window's end (but each window also sees other rooms: how many of its pixels
  hit new voxels changes); and, at every checkpoint once the walk has passed them, the same
  work at every size: the walk's first `PROBE_FRAMES` frames fused again with `fuse_frame`
  into a copy of the map (their voxels and blocks are all held: lookups and row updates, no
  insertion; compiled first, the copy then dropped), `PROBE_PASSES` passes, their median;
  each probe frame is first fused into a copy of a reference map (a fresh map of `REFERENCE`
  slots and blocks that holds the probe frames only, the same at every checkpoint), and the
  median of the frames' ratios (map over reference) is the cost against the map's size with
  the machine's drift between checkpoints taken out;
* each growth: the frame, the layer, old → new capacity and that frame's time;
* peak process memory (`resource.getrusage(...).ru_maxrss`) and the map arrays' bytes
  (`nbytes` of the semantic table and the block table) at every checkpoint;
* at checkpoints (the first frame where the map holds ≥ 10⁴, 3·10⁴, 10⁵, … voxels, and the
  end): `jf.read_map` (all voxels to the host), `jf.query` of a fixed set of 2^16 points, and
  `jf.extract_mesh` of the geometry layer, each timed after a warm-up call at that size
  (their compiles left out), with what each returned, so that time per returned item shows
  whether each is linear in its output;
* bytes per voxel: ours (the semantic table's arrays per slot, and per stored voxel at the
  load factor reached; the block table's per voxel slot and per allocated voxel) beside
  Open3D's `t.geometry.VoxelBlockGrid` and nvblox's layers, whose layouts are read from their
  source (`PEERS`).

Writes `bench/results/building.json` and the scale curve `building.png` (`building_quick.*` for
`--quick`) and prints a Markdown table.

    .venv/bin/python -m bench.building            # floor:16, 120×160, 2 cm, to 1.1·10⁷ voxels
    .venv/bin/python -m bench.building --quick    # floor:2, 160 frames (every 2nd), 48×64, 5 cm
"""

import argparse
import dataclasses
import json
import os
import pathlib
import resource
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxfusion as jf
from jaxfusion.datasets import floor as floor_lib
from jaxfusion.datasets.classes import CLASS_NAMES
from jaxfusion.lab import hugepages

K = len(CLASS_NAMES)
NUM_QUERY = 2**16
# The probe: the walk's first frames, fused again into a copy of the map at each checkpoint.
PROBE_FRAMES = 20
PROBE_PASSES = 3
# The probe's point of comparison: a fresh map of these (slots, blocks) holding only the probe
# frames, fused frame by frame beside the map's copy at every checkpoint (`probe`).
REFERENCE = (2**21, 2**17)
CHECKPOINTS = tuple(int(m * 10**e) for e in range(4, 9) for m in (1, 3))

# Per-voxel layouts of the peers, from their source.
PEERS = {
    "open3d_voxel_block_grid": {
        "source": "isl-org/Open3D@22a6a307: cpp/open3d/t/geometry/VoxelBlockGrid.h "
                  "(block_resolution = 16 by default), VoxelBlockGrid.cpp (a core::HashMap "
                  "keyed by Int32×3 block coordinates, one value tensor per attribute of shape "
                  "block_resolution³ × channels), examples/python/t_reconstruction_system/"
                  "integrate.py (tsdf, weight float32; color float32×3)",
        "voxels_per_block": 16**3,
        "bytes_per_voxel": {"tsdf + weight (float32)": 8,
                            "tsdf + weight + color (float32 ×5)": 20},
        "key_bytes_per_block": 12,
    },
    "nvblox": {
        "source": "nvidia-isaac/nvblox@7c76f907: nvblox/include/nvblox/map/voxels.h "
                  "(TsdfVoxel: float distance, float weight; ColorVoxel: Color (4 × uint8, "
                  "core/color.h) + float weight; OccupancyVoxel: float log_odds), "
                  "map/blox.h (VoxelBlock: kVoxelsPerSide = 8), map/layer.h (a hash of "
                  "Index3D block indices to block pointers)",
        "voxels_per_block": 8**3,
        "bytes_per_voxel": {"TsdfVoxel": 8, "ColorVoxel": 8, "OccupancyVoxel": 4},
        "key_bytes_per_block": 12 + 8,     # Index3D (3 × int32) → block pointer
    },
}


def probabilities(labels: np.ndarray) -> np.ndarray:
  """`(H, W, K) float32`: 0.8 on the GT label (background where none), the rest spread."""
  onehot = np.eye(K, dtype=np.float32)[np.clip(labels, 0, K - 1)]
  return 0.8 * onehot + 0.2 / K


def _rss_mb() -> float:
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # Linux: KiB


def _nbytes(tree) -> int:
  return int(sum(x.nbytes for x in jax.tree_util.tree_leaves(tree) if hasattr(x, "nbytes")))


def map_bytes(state) -> dict:
  """The semantic table's and the geometry block table's array bytes."""
  geometry = state.geometry
  semantic = _nbytes(state.replace(geometry=None))
  return {"semantic": semantic, "geometry": 0 if geometry is None else _nbytes(geometry)}


def per_voxel(state) -> dict:
  """Bytes per slot / stored voxel of both layers (ours)."""
  sizes = map_bytes(state)
  geometry = state.geometry
  voxels_per_block = int(geometry.sdf.shape[1])
  occupied, blocks = int(state.num_occupied), int(geometry.num_blocks)
  return {
      "semantic_per_slot": sizes["semantic"] / state.capacity,
      "semantic_load": occupied / state.capacity,
      "semantic_per_voxel": sizes["semantic"] / max(occupied, 1),
      "semantic_per_voxel_at_half_load": 2 * sizes["semantic"] / state.capacity,
      "tsdf_per_voxel_slot": sizes["geometry"] / (geometry.capacity * voxels_per_block),
      "tsdf_load": blocks / geometry.capacity,
      "tsdf_per_allocated_voxel": sizes["geometry"] / max(blocks * voxels_per_block, 1),
      "voxels_per_block": voxels_per_block,
  }


def _timed(fn, repeats: int = 3) -> tuple:
  """`(median seconds of `repeats` calls after one warm-up, last result)`."""
  out = jax.block_until_ready(fn())
  seconds = []
  for _ in range(repeats):
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    seconds.append(time.perf_counter() - start)
  return float(np.median(seconds)), out


def reference_map(state, frames, camera, rule, sizes) -> object:
  """A fresh map as `state` (its voxel size, rule and geometry settings) at `sizes = (slots,
  blocks)` (`REFERENCE`), holding just the probe `frames`: the probe's fixed point of
  comparison (`probe`)."""
  geometry = dataclasses.replace(state.geometry.config(), capacity=int(sizes[1]))
  ref = jf.init_map(capacity=int(sizes[0]), num_classes=state.num_classes,
                    voxel_size=float(state.voxel_size), rule=rule, max_probes=state.max_probes,
                    geometry=geometry)
  for frame in frames:
    ref = jf.fuse_frame(ref, frame, camera, rule)
  return jax.block_until_ready(ref)


def probe(state, frames, camera, rule, passes: int = PROBE_PASSES, reference=None) -> dict:
  """`fuse_frame` of the probe frames (frames the map holds already) into a copy of `state`,
  `passes` times over (the frames' costs differ by up to 1.5×: one pass's median moved by
  ±10 % between checkpoints of the same table), after a warm-up call on another copy:
  `{"probe_ms": median, "probe_ms_all": [...], "probe_huge_bytes": the process's bytes in huge
  pages meanwhile}`. With a `reference` map (one that holds the probe frames, the same object
  at every checkpoint), each frame is fused into a copy of it just before it is fused into the
  map's copy, and the record adds `"reference_ms"` (its median) and `"relative"` (the median of
  the frames' ratios, map over reference): the map's cost with the machine's drift between
  checkpoints taken out (its speed moves by 20 % over minutes). The copies are dropped; `state`
  and `reference` are untouched."""
  copy = lambda tree: jax.tree_util.tree_map(jnp.copy, tree)

  def timed(tree, frame, seconds):
    start = time.perf_counter()
    tree = jf.fuse_frame(tree, frame, camera, rule)
    jax.block_until_ready(tree.rows)
    seconds.append(time.perf_counter() - start)
    return tree

  jax.block_until_ready(jf.fuse_frame(copy(state), frames[0], camera, rule).rows)   # compile
  work, seconds = copy(state), []
  ref, ref_seconds = (None, None) if reference is None else (copy(reference), [])
  jax.block_until_ready((work.rows, None if ref is None else ref.rows))
  huge = hugepages.anon_huge_bytes()      # the copy's pages (and the map's) as the probe runs
  for _ in range(passes):
    for frame in frames:
      if ref is not None:
        ref = timed(ref, frame, ref_seconds)
      work = timed(work, frame, seconds)
  del work, ref
  out = {"probe_ms": 1e3 * float(np.median(seconds)),
         "probe_ms_all": [1e3 * x for x in seconds], "probe_huge_bytes": huge}
  if reference is not None:
    out.update(reference_ms=1e3 * float(np.median(ref_seconds)),
               reference_ms_all=[1e3 * x for x in ref_seconds],
               relative=float(np.median(np.array(seconds) / np.array(ref_seconds))))
  return out


def checkpoint(state, points, frame: int) -> dict:
  """Read-out, query and meshing times at the map's current size."""
  read_s, voxels = _timed(lambda: jf.read_map(state), repeats=2)
  query_s, _ = _timed(lambda: jf.query(state, points).found)
  mesh_s, surface = _timed(lambda: jf.extract_mesh(state), repeats=2)
  n = len(voxels["coords"])
  return {"frame": frame, "voxels": int(state.num_occupied),
          "blocks": int(state.geometry.num_blocks), "capacity": state.capacity,
          "block_capacity": state.geometry.capacity,
          "read_s": read_s, "read_voxels": n, "read_ns_per_voxel": 1e9 * read_s / max(n, 1),
          "query_s": query_s, "query_points": int(points.shape[0]),
          "mesh_s": mesh_s, "mesh_faces": surface.num_faces,
          "mesh_vertices": surface.num_vertices,
          "mesh_us_per_face": 1e6 * mesh_s / max(surface.num_faces, 1),
          "map_bytes": map_bytes(state), "peak_rss_mb": _rss_mb()}


def run(*, rooms: int, seed: int, height: int, width: int, voxel_size: float,
        num_frames=None, stride: int = 1, window: int = 50, capacity: int = 2**14,
        blocks: int = 2**10, stop_at=None, probe_frames: int = PROBE_FRAMES,
        reference=(2**16, 2**12), log=None) -> dict:
  """The walk fused into a growing `Mapper`; returns the JSON record (module docstring)."""
  walk = floor_lib.FloorWalk(floor_lib.make_floor(rooms, seed=seed), num_frames=num_frames,
                             stride=stride, height=height, width=width)
  camera = walk.camera
  rule = jf.rules.robust()
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=voxel_size, capacity=capacity,
                     geometry=jf.tsdf.TSDFConfig(voxel_size=voxel_size, capacity=blocks),
                     growth_factor=4)
  rng = np.random.default_rng(0)
  lo = walk.T_world_cam[:, :3, 3].min(0) - 2.0
  hi = walk.T_world_cam[:, :3, 3].max(0) + 2.0
  points = jnp.asarray(rng.uniform(lo, hi, (NUM_QUERY, 3)), jnp.float32)
  var = np.full((height, width, K), 0.01, np.float32)
  probes, ref = [], None
  frames, checks, growths = [], [], []
  targets = list(CHECKPOINTS)
  render_s = []
  start_all = time.perf_counter()
  for t in range(len(walk)):
    start = time.perf_counter()
    f = walk.frame(t)
    render_s.append(time.perf_counter() - start)
    frame = jf.Frame(f.depth, f.T_world_cam, probabilities(f.labels), var)
    if t < probe_frames:
      probes.append(frame)
    n_sem, n_geo = len(mapper.growths), len(mapper.geometry_growths)
    start = time.perf_counter()
    jax.block_until_ready(mapper.fuse(frame, camera).rows)
    seconds = time.perf_counter() - start
    grew = len(mapper.growths) > n_sem or len(mapper.geometry_growths) > n_geo
    for layer, new in (("semantic", mapper.growths[n_sem:]),
                       ("geometry", mapper.geometry_growths[n_geo:])):
      growths += [{"frame": t, "layer": layer, "old": int(o), "new": int(c), "s": seconds}
                  for _, o, c in new]
    voxels, num_blocks = int(mapper.state.num_occupied), int(mapper.state.geometry.num_blocks)
    frames.append((t, seconds, voxels, num_blocks, grew))
    last = t == len(walk) - 1 or (stop_at is not None and voxels >= stop_at)
    if targets and voxels >= targets[0] or last:
      while targets and voxels >= targets[0]:
        targets.pop(0)
      held = t >= probe_frames - 1       # the probe frames are all in the map
      if held and ref is None:
        ref = reference_map(mapper.state, probes, camera, rule, reference)
      checks.append(probe(mapper.state, probes, camera, rule, reference=ref) if held
                    else {"probe_ms": None})
      checks[-1].update(checkpoint(mapper.state, points, t))
      if log:
        c = checks[-1]
        probed = "—" if c["probe_ms"] is None else (
            f"{c['probe_ms']:.1f} (reference {c['reference_ms']:.1f}, ×{c['relative']:.2f})")
        log(f"frame {t}: {voxels:,} voxels, {num_blocks:,} blocks; probe {probed} "
            f"ms/frame; read {c['read_s']:.3f} s, "
            f"query {c['query_s']:.3f} s, mesh {c['mesh_s']:.2f} s; {_rss_mb():.0f} MB; "
            f"{time.perf_counter() - start_all:.0f} s so far")
    if last:
      break
  windows = []
  for w0 in range(1, len(frames), window):
    chunk = [r for r in frames[w0:w0 + window] if not r[4]]
    if chunk:
      windows.append({"frames": [chunk[0][0], chunk[-1][0]],
                      "median_ms": 1e3 * float(np.median([r[1] for r in chunk])),
                      "voxels": chunk[-1][2], "blocks": chunk[-1][3]})
  return {
      "spec": f"floor:{rooms}:s{seed}", "frames": len(frames), "stop_at": stop_at, "walk_frames": walk.walk_frames,
      "stride": stride, "height": height, "width": width, "voxel_size": voxel_size, "K": K,
      "rule": rule.name, "device": jax.devices()[0].device_kind,
      "first_frame_s": frames[0][1], "render_median_ms": 1e3 * float(np.median(render_s[1:]))
      if len(render_s) > 1 else None,
      "probe_frames": probe_frames, "reference": [int(x) for x in reference],
      "windows": windows, "growths": growths,
      "checkpoints": checks,
      "voxels": int(mapper.state.num_occupied), "dropped": int(mapper.state.num_dropped),
      "blocks": int(mapper.state.geometry.num_blocks),
      "peak_rss_mb": _rss_mb(), "per_voxel": per_voxel(mapper.state), "peers": PEERS,
      "huge_pages": hugepages.status(),
      "wall_s": time.perf_counter() - start_all,
  }


def table_sizes(*, rooms: int = 16, seed: int = 0, height: int = 120, width: int = 160,
                voxel_size: float = 0.02, sizes=((2**21, 2**17), (2**25, 2**19)),
                load: float = 0.3) -> list:
  """What the probe costs in a table of each size, the map's content aside: the walk's first
  `PROBE_FRAMES` frames fused (a first pass inserts them, the second is timed) into fresh maps
  of `(slots, blocks)` in `sizes`, nearly empty and with the semantic table filled to about
  `load` by voxels far from the floor (x ≥ 10⁶ voxels: none is a probe voxel, but they fill
  the same table and lengthen its probe chains). Returns one row per size and fill."""
  from jaxfusion import hashing   # pylint: disable=import-outside-toplevel
  walk = floor_lib.FloorWalk(floor_lib.make_floor(rooms, seed=seed), num_frames=PROBE_FRAMES,
                             height=height, width=width)
  var = np.full((height, width, K), 0.01, np.float32)
  frames = [jf.Frame(f.depth, f.T_world_cam, probabilities(f.labels), var)
            for f in (walk.frame(t) for t in range(len(walk)))]
  rule = jf.rules.robust()
  rows = []
  for capacity, blocks in sizes:
    for fill in (0.0, load):
      state = jf.init_map(capacity=capacity, num_classes=K, voxel_size=voxel_size, rule=rule,
                          geometry=jf.tsdf.TSDFConfig(voxel_size=voxel_size, capacity=blocks))
      if fill:
        rng = np.random.default_rng(0)
        n = int(fill * capacity)
        keys = np.unique(np.stack([rng.integers(10**6, 10**6 + 4000, n),
                                   rng.integers(0, 4000, n), rng.integers(0, 150, n)],
                                  1).astype(np.int32), axis=0)
        table, claims = state.keys, state.claims
        for i in range(0, len(keys), 2**20):
          part = jnp.asarray(keys[i:i + 2**20])
          placed = hashing.insert(table, claims, part, jnp.ones(len(part), bool),
                                  max_probes=state.max_probes)
          table, claims = placed.table, placed.claims
        state = state.replace(
            keys=table, claims=jnp.zeros_like(claims),
            hits=(table[:, 0] != hashing.EMPTY).astype(jnp.int32),
            num_occupied=jnp.int32(len(keys)))
      for frame in frames:
        state = jf.fuse_frame(state, frame, walk.camera, rule)
      jax.block_until_ready(state.rows)
      seconds = []
      for frame in frames:
        start = time.perf_counter()
        state = jf.fuse_frame(state, frame, walk.camera, rule)
        jax.block_until_ready(state.rows)
        seconds.append(time.perf_counter() - start)
      rows.append({"slots": capacity, "blocks": blocks,
                   "load": int(state.num_occupied) / capacity,
                   "probe_ms": 1e3 * float(np.median(seconds))})
      del state
  return rows


def table_sizes_both(*, seed: int = 0, child_args=()) -> list:
  """`table_sizes` in two fresh processes, one after the other: with 4 KiB pages only
  (`JAXFUSION_HUGEPAGES=off`, the glibc tunable removed) and with transparent huge pages
  (`lab.hugepages`), where this machine offers them. Rows as `table_sizes`', each with
  `pages` ("4 KiB" or "huge") and the process's `huge_pages` status; `child_args` (the
  floor's `--rooms`, `--height`, …, and `--table-slots C:B,…`) go to both processes."""
  plain = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
  tunables = ":".join(t for t in os.environ.get("GLIBC_TUNABLES", "").split(":")
                      if t and not t.startswith(hugepages.TUNABLE))
  if tunables:
    plain["GLIBC_TUNABLES"] = tunables
  plain["JAXFUSION_HUGEPAGES"] = "off"
  huge = hugepages.environ_with({**plain, "JAXFUSION_HUGEPAGES": "on"},
                                mode=hugepages.thp_mode(), glibc=hugepages.glibc_version())
  rows = []
  for pages, env in (("4 KiB", plain), ("huge", huge)):
    if env is None:
      print("huge pages: not offered here (lab.hugepages); measured with 4 KiB pages only",
            file=sys.stderr)
      continue
    done = subprocess.run([sys.executable, "-m", "bench.building", "--table-sizes-rows",
                           "--seed", str(seed), *child_args], env=env, check=True,
                          stdout=subprocess.PIPE, cwd=pathlib.Path(__file__).resolve().parents[1])
    record = json.loads(done.stdout.decode().strip().splitlines()[-1])
    rows += [{**row, "pages": pages, "huge_pages": record["huge_pages"]}
             for row in record["rows"]]
  return rows


def table(result: dict) -> str:
  r = result
  lines = [
      f"{r['spec']}: {r['frames']} frames (every {r['stride']} of {r['walk_frames']}) at "
      f"{r['height']}×{r['width']}, {100 * r['voxel_size']:g} cm voxels and TSDF, K = {r['K']}, "
      f"{r['rule']}, {r['device']}; in the end {r['voxels']:,} voxels ({r['dropped']} dropped), "
      f"{r['blocks']:,} blocks; render {r['render_median_ms']:.0f} ms/frame (not counted); "
      f"peak RSS {r['peak_rss_mb']:,.0f} MB; {r['wall_s']:.0f} s in all.",
      "",
      "| frames | voxels held | blocks | fuse ms/frame (median) |",
      "|---|---|---|---|",
  ]
  lines += [f"| {w['frames'][0]}–{w['frames'][1]} | {w['voxels']:,} | {w['blocks']:,} | "
            f"{w['median_ms']:.1f} |" for w in r["windows"]]
  lines += ["", "| growth at frame | layer | capacity | frame s |", "|---|---|---|---|"]
  lines += [f"| {g['frame']} | {g['layer']} | {g['old']:,} → {g['new']:,} | {g['s']:.2f} |"
            for g in r["growths"]]
  sizes = r.get("reference")     # runs a–f (12-06, 12-07) had no reference map
  ref_head = "" if sizes is None else (
      f"reference map ms/frame (2^{int(sizes[0]).bit_length() - 1} slots, "
      f"2^{int(sizes[1]).bit_length() - 1} blocks) | probe / reference (median of frames) | ")
  lines += ["", f"| frame | voxels | probe fuse ms/frame (median) | {ref_head}"
                "read_map s (ns/voxel) | query 2^16 pts s | extract_mesh s (faces, µs/face) | "
                "map MB (sem + TSDF) | peak RSS MB |",
            "|---|---|---|" + ("" if sizes is None else "---|---|") + "---|---|---|---|---|"]
  for c in r["checkpoints"]:
    mb = c["map_bytes"]
    probed = "—" if c["probe_ms"] is None else f"{c['probe_ms']:.1f}"
    if sizes is not None:
      probed += " | — | —" if c.get("relative") is None else (
          f" | {c['reference_ms']:.1f} | {c['relative']:.2f}")
    lines.append(f"| {c['frame']} | {c['voxels']:,} | {probed} | {c['read_s']:.3f} "
                 f"({c['read_ns_per_voxel']:.0f}) | {c['query_s']:.4f} | {c['mesh_s']:.3f} "
                 f"({c['mesh_faces']:,}, {c['mesh_us_per_face']:.2f}) | "
                 f"{mb['semantic'] / 2**20:,.0f} + {mb['geometry'] / 2**20:,.0f} | "
                 f"{c['peak_rss_mb']:,.0f} |")
  p = r["per_voxel"]
  o3d, nvb = r["peers"]["open3d_voxel_block_grid"], r["peers"]["nvblox"]
  lines += [
      "", "| bytes per voxel | semantic (K = 7) | TSDF |", "|---|---|---|",
      f"| ours, per slot / per stored voxel at the end (load {p['semantic_load']:.2f} / "
      f"{p['tsdf_load']:.2f}) / at the Mapper's grow_at load 0.5 | "
      f"{p['semantic_per_slot']:.1f} / {p['semantic_per_voxel']:.1f} / "
      f"{p['semantic_per_voxel_at_half_load']:.1f} | "
      f"{p['tsdf_per_voxel_slot']:.2f} / {p['tsdf_per_allocated_voxel']:.2f} / "
      f"{2 * p['tsdf_per_voxel_slot']:.2f} ({p['voxels_per_block']} voxels a block) |",
      f"| Open3D VoxelBlockGrid ({o3d['voxels_per_block']} voxels a block) | — | "
      + ", ".join(f"{k}: {v}" for k, v in o3d["bytes_per_voxel"].items())
      + f" (+ {o3d['key_bytes_per_block']} B key a block) |",
      f"| nvblox ({nvb['voxels_per_block']} voxels a block) | — | "
      + ", ".join(f"{k}: {v}" for k, v in nvb["bytes_per_voxel"].items())
      + f" (+ ~{nvb['key_bytes_per_block']} B index a block) |",
  ]
  return "\n".join(lines)


def figure(result: dict, path) -> None:
  """The scale curve as a PNG: per-frame fuse time (window medians) against the voxels held,
  growth frames marked, and read-out and meshing time per checkpoint against the map's size."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
  w = result["windows"]
  left.plot([x["voxels"] for x in w], [x["median_ms"] for x in w], "o-", ms=3,
            label="the walk's frames, median of a window")
  probed = [x for x in result["checkpoints"] if x["probe_ms"] is not None]
  if probed:
    left.plot([x["voxels"] for x in probed], [x["probe_ms"] for x in probed], "s-", ms=4,
              label="the walk's first frames fused again, median")
  related = [x for x in probed if x.get("relative") is not None]
  if related:
    twin = left.twinx()
    twin.plot([x["voxels"] for x in related], [x["relative"] for x in related], "d--",
              color="C3", ms=4, label="the same, over the reference map beside it")
    twin.axhline(1.2, color="C3", lw=0.6, ls=":")
    twin.set(ylabel="probe / reference (dotted: 1.2)", ylim=(0.0, 2.0))
  voxels_at = {x["frames"][1]: x["voxels"] for x in w}
  for g in result["growths"]:
    near = min(voxels_at, key=lambda f: abs(f - g["frame"])) if voxels_at else None
    if near is not None:
      left.axvline(voxels_at[near], color="0.8", lw=0.8, zorder=0)
  left.set(xscale="log", xlabel="voxels held", ylabel="ms per frame",
           title=f"{result['spec']}, {result['height']}×{result['width']}, "
                 f"{100 * result['voxel_size']:g} cm (grey: growths)")
  left.set_ylim(bottom=0)
  handles = left.get_legend_handles_labels()
  if related:
    handles = tuple(a + b for a, b in zip(handles, twin.get_legend_handles_labels()))
  left.legend(*handles, loc="lower right", fontsize="small")
  c = result["checkpoints"]
  vox = [x["voxels"] for x in c]
  right.plot(vox, [x["read_s"] for x in c], "o-", ms=3, label="read_map (all voxels)")
  right.plot(vox, [x["query_s"] for x in c], "o-", ms=3, label="query of 2^16 points")
  right.plot(vox, [x["mesh_s"] for x in c], "o-", ms=3, label="extract_mesh")
  right.set(xscale="log", yscale="log", xlabel="voxels held", ylabel="s",
            title="read-out and meshing")
  right.legend(loc="upper left")
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench.building",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("--quick", action="store_true",
                      help="floor:2, 160 frames (every 2nd), 48×64, 5 cm voxels")
  parser.add_argument("--rooms", type=int, default=None, help="rooms of the floor (16)")
  parser.add_argument("--seed", type=int, default=0, help="layout seed")
  parser.add_argument("--voxel-size", type=float, default=None, help="metres (0.02)")
  parser.add_argument("--height", type=int, default=None, help="image rows (120)")
  parser.add_argument("--width", type=int, default=None, help="image columns (160)")
  parser.add_argument("--frames", type=int, default=None, help="the most frames (all)")
  parser.add_argument("--stride", type=int, default=None, help="every N-th frame of the walk")
  parser.add_argument("--stop-at", type=float, default=None,
                      help="stop once the map holds this many voxels (1.1e7; 0: never)")
  parser.add_argument("--table-sizes", action="store_true",
                      help="only the probe in fresh maps of 2^21 and 2^25 slots, nearly empty "
                           "and at load 0.3 (writes building_tables.json)")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"))
  parser.add_argument("--table-sizes-rows", action="store_true", help=argparse.SUPPRESS)
  parser.add_argument("--table-slots", default=None, help=argparse.SUPPRESS)   # "C:B,C:B"
  args = parser.parse_args(argv)
  if args.table_sizes_rows:      # one process of --table-sizes: its rows as JSON on stdout
    given = {name: getattr(args, name) for name in ("rooms", "height", "width", "voxel_size")
             if getattr(args, name) is not None}
    if args.table_slots:
      given["sizes"] = tuple(tuple(int(x) for x in pair.split(":"))
                             for pair in args.table_slots.split(","))
    print(json.dumps({"rows": table_sizes(seed=args.seed, **given),
                      "huge_pages": hugepages.status()}))
    return
  if args.table_sizes:
    rows = table_sizes_both(seed=args.seed)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "building_tables.json").write_text(json.dumps(rows, indent=1))
    print("| pages | semantic slots | TSDF blocks | load | probe ms / frame (median) |\n"
          "|---|---|---|---|---|")
    for r in rows:
      print(f"| {r['pages']} | 2^{r['slots'].bit_length() - 1} | "
            f"2^{r['blocks'].bit_length() - 1} | {r['load']:.3f} | {r['probe_ms']:.1f} |")
    return
  quick = dict(rooms=2, voxel_size=0.05, height=48, width=64, frames=160, stride=2, window=10,
               capacity=2**14, blocks=2**10, stop_at=None, reference=(2**16, 2**12))
  # Start at 2^15 slots / 2^11 blocks: with growth factor 4 the tables pass 2^25 and 2^19,
  # which hold 1.7·10⁷ voxels and 2.6·10⁵ blocks at load 0.5 (never 2^26 / 2^20).
  full = dict(rooms=16, voxel_size=0.02, height=120, width=160, frames=None, stride=1,
              window=50, capacity=2**15, blocks=2**11, stop_at=1.1e7, reference=REFERENCE)
  config = quick if args.quick else full
  for name in ("rooms", "voxel_size", "height", "width", "frames", "stride", "stop_at"):
    if getattr(args, name) is not None:
      config[name] = getattr(args, name)
  stop_at = config["stop_at"] or None
  result = run(rooms=config["rooms"], seed=args.seed, height=config["height"],
               width=config["width"], voxel_size=config["voxel_size"],
               num_frames=config["frames"], stride=config["stride"], window=config["window"],
               capacity=config["capacity"], blocks=config["blocks"], stop_at=stop_at,
               reference=config["reference"],
               log=lambda line: print(line, file=sys.stderr, flush=True))
  result["quick"] = bool(args.quick)
  out = pathlib.Path(args.out)
  out.mkdir(parents=True, exist_ok=True)
  name = "building_quick" if args.quick else "building"
  (out / f"{name}.json").write_text(json.dumps(result, indent=1))
  figure(result, out / f"{name}.png")
  print(table(result))


if __name__ == "__main__":
  hugepages.reexec()       # as the `jaxfusion` commands run: huge pages where Linux has them
  main()
