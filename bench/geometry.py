"""The geometry layer's speed, memory and quality, beside Open3D's VoxelBlockGrid on the same
frames (bench room, `bench.scene`, 640×480 by default).

    .venv/bin/python -m bench.geometry            # 12 frames, voxels 0.10 / 0.05 / 0.02 m
    .venv/bin/python -m bench.geometry --quick    # 4 frames of 240×320, voxels 0.10 / 0.05 m

Per voxel size, in one process: TSDF integration alone (`tsdf.integrate`), the semantics alone
(`fuse_frame`, D+R, 0.1 m) and both in one call (`fuse_frame` on a map with the geometry layer),
each the median ms per frame over the sequence after a warm-up pass (TSDF alone also with
blocks found from every pixel, `block_stride=1`, and the blocks each lattice finds); mesh
extraction (median of
repeats) and its triangle count, `marching_cubes` alone and `extract_mesh` as users call it
(labels from the semantic layer included); bytes per allocated geometry voxel and the meshing programs'
scratch (XLA's `memory_analysis` of the two compiled programs: temporaries plus outputs);
Open3D's integrate / extract_triangle_mesh on the same frames with the same voxel size,
truncation (4 voxels), blocks (8³) and constant weights (`bench.open3d_peer.tsdf_peer`), when
installed. Quality against the room's exact faces (not the fused depth): both meshes and the GT
surface sampled evenly (1 cm), GT culled to what some frame saw, accuracy / completeness /
Chamfer-L1 in cm and precision / recall / F-score at 5 and 2 cm (`jaxfusion.surface_metrics`).
Writes `bench/results/geometry.json`.
"""

import argparse
import dataclasses
import json
import os
import time

import jax
import numpy as np

import jaxfusion as jf
from bench import open3d_peer
from bench import scene
from bench import suite
from jaxfusion import mesh as mesh_lib
from jaxfusion import surface_metrics
from jaxfusion import tsdf

RESULTS = os.path.join(os.path.dirname(__file__), "results", "geometry.json")
TRUNC_VOXELS = 4.0
DEPTH_MAX = 6.5
GT_SPACING = 0.01


def _capacity(voxel_size: float) -> int:
  """Block slots for the bench room at `voxel_size` (its ~150 m² of surface, a 2-block band,
  load ≤ ~0.4)."""
  edge = voxel_size * 8
  need = 5.0 * 150.0 / (edge * edge)
  return max(2**10, 1 << int(np.ceil(np.log2(need))))


def _median_ms(step, count: int, passes: int) -> float:
  times = []
  for _ in range(passes):
    for t in range(count):
      t0 = time.perf_counter()
      step(t)
      times.append(time.perf_counter() - t0)
  return 1e3 * float(np.median(times))


def _sample_box_faces(lo, hi, spacing, rng, *, skip_bottom=False):
  """Even samples of an axis-aligned box's faces (`(S, 3)`)."""
  lo, hi = np.asarray(lo, float), np.asarray(hi, float)
  points = []
  for axis in range(3):
    a, b = [i for i in range(3) if i != axis]
    area = (hi[a] - lo[a]) * (hi[b] - lo[b])
    n = rng.poisson(area / spacing**2)
    for side, value in ((0, lo[axis]), (1, hi[axis])):
      if skip_bottom and axis == 2 and side == 0:
        continue
      p = np.empty((n, 3))
      p[:, a] = rng.uniform(lo[a], hi[a], n)
      p[:, b] = rng.uniform(lo[b], hi[b], n)
      p[:, axis] = value
      points.append(p)
  return np.concatenate(points)


def room_surface(frames, *, spacing=GT_SPACING, seed=0, tolerance=0.05):
  """Even samples of the bench room's exact surfaces (walls, floor, ceiling, box faces but the
  bottoms, floor under boxes removed) in world coordinates, kept where some frame saw them: the
  point projects into the image with valid depth within `tolerance` of its own."""
  rng = np.random.default_rng(seed)
  room = _sample_box_faces(scene.ROOM_MIN, scene.ROOM_MAX, spacing, rng)
  inside = np.zeros(len(room), bool)
  for lo, hi, _ in scene.BOXES:
    inside |= np.all((room > np.array(lo) - 1e-9) & (room < np.array(hi) + 1e-9), axis=1)
  points = [room[~inside]] + [_sample_box_faces(lo, hi, spacing, rng, skip_bottom=True)
                              for lo, hi, _ in scene.BOXES]
  points = np.concatenate(points) + scene.OFF_GRID
  seen = np.zeros(len(points), bool)
  cam = frames.camera
  height, width = frames.depth.shape[1:]
  for depth, T in zip(frames.depth, frames.poses.astype(np.float64)):
    p = (points - T[:3, 3]) @ T[:3, :3]
    z = p[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    u = np.floor(cam.fx * p[:, 0] / zs + cam.cx + 0.5).astype(np.int64)
    v = np.floor(cam.fy * p[:, 1] / zs + cam.cy + 0.5).astype(np.int64)
    ok = (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    d = np.where(ok, depth[np.clip(v, 0, height - 1), np.clip(u, 0, width - 1)], 0.0)
    seen |= ok & (d > 0) & (np.abs(d - z) < tolerance)
  return points[seen]


def quality(vertices, faces, gt_points, *, seed=0) -> dict:
  """Accuracy, completeness, Chamfer-L1 (cm) and P/R/F at 5 and 2 cm of a mesh."""
  points, _, _ = surface_metrics.sample_mesh(np.asarray(vertices, np.float64),
                                             np.asarray(faces, np.int64), spacing=GT_SPACING,
                                             rng=np.random.default_rng(seed))
  scores = surface_metrics.reconstruction_scores(points, gt_points, thresholds=(0.05, 0.02))
  out = {}
  for key, value in scores.items():
    value = float(value)
    out[key] = 100.0 * value if key in ("accuracy", "completeness", "chamfer_l1") else value
  return out


def _meshing_scratch_bytes(layer) -> int:
  """Temporaries plus outputs of the two compiled meshing programs (XLA's memory analysis)."""
  weight = jax.numpy.float32(mesh_lib.DEFAULT_MIN_WEIGHT)
  total = 0
  max_blocks = mesh_lib._padded(max(int(layer.num_blocks), 1))
  compiled = mesh_lib._classify.lower(layer, weight, max_blocks=max_blocks).compile()
  stats = compiled.memory_analysis()
  total = max(total, stats.temp_size_in_bytes + stats.output_size_in_bytes)
  plan = mesh_lib._classify(layer, weight, max_blocks=max_blocks)
  compiled = mesh_lib._emit.lower(layer, plan,
                                  max_vertices=mesh_lib._bucket(int(plan.num_vertices)),
                                  max_faces=mesh_lib._bucket(int(plan.num_faces))).compile()
  stats = compiled.memory_analysis()
  return max(total, stats.temp_size_in_bytes + stats.output_size_in_bytes)


def measure(frames, voxel_size: float, *, passes: int = 2, mesh_repeats: int = 3,
            gt_points=None, semantic_capacity: int = 2**16, peer_memory: bool = True) -> dict:
  """One voxel size's row (see the module docstring); `semantic_capacity` slots of the 0.1 m
  semantic layer, `peer_memory` measures Open3D's memory in a child process."""
  count = frames.depth.shape[0]
  config = tsdf.TSDFConfig(voxel_size=voxel_size, truncation_voxels=TRUNC_VOXELS,
                           capacity=_capacity(voxel_size), max_depth=DEPTH_MAX)
  rule = jf.rules.robust()
  k = frames.probs.shape[-1]
  row = {"voxel_size": voxel_size, "frames": count,
         "image": f"{frames.depth.shape[1]}×{frames.depth.shape[2]}"}

  # TSDF alone: a fresh layer per pass, every frame integrated (the first pass compiles).
  layer = [tsdf.init_tsdf(config)]

  def integrate(t):
    layer[0] = tsdf.integrate(layer[0], frames.depth[t], frames.poses[t], frames.camera)
    jax.block_until_ready(layer[0].sdf)

  for t in range(count):
    integrate(t)
  layer[0] = tsdf.init_tsdf(config)
  row["tsdf_ms"] = _median_ms(integrate, count, 1)
  for _ in range(passes - 1):
    layer[0] = tsdf.init_tsdf(config)
    row["tsdf_ms"] = min(row["tsdf_ms"], _median_ms(integrate, count, 1))
  geometry = layer[0]

  # The same layer with blocks found from every pixel (block_stride 1, docs/equations.md §8.2).
  dense = dataclasses.replace(config, block_stride=1)
  layer[0] = tsdf.init_tsdf(dense)
  for t in range(count):
    integrate(t)
  blocks_every_pixel = int(layer[0].num_blocks)
  layer[0] = tsdf.init_tsdf(dense)
  row["tsdf_ms_every_pixel"] = _median_ms(integrate, count, 1)
  row["blocks_every_pixel"] = blocks_every_pixel

  # Semantics alone and both layers in one call.
  for key, geo in (("semantic_ms", None), ("both_ms", config)):
    state = [jf.init_map(capacity=semantic_capacity, num_classes=k, rule=rule, geometry=geo)]

    def fuse(t):
      state[0] = jf.fuse_frame(state[0], frames.frame(t), frames.camera, rule)
      jax.block_until_ready(state[0].hits)

    fuse(0)
    best = np.inf
    for _ in range(passes):
      state[0] = jf.init_map(capacity=semantic_capacity, num_classes=k, rule=rule,
                             geometry=geo)
      best = min(best, _median_ms(fuse, count, 1))
    row[key] = best

  # Meshing.
  vertices, faces = mesh_lib.marching_cubes(geometry)
  times = []
  for _ in range(mesh_repeats):
    t0 = time.perf_counter()
    vertices, faces = mesh_lib.marching_cubes(geometry)
    times.append(time.perf_counter() - t0)
  stats = tsdf.tsdf_stats(geometry)
  row.update(mesh_ms=1e3 * float(np.median(times)), triangles=int(len(faces)),
             blocks=stats["blocks"], voxels=stats["voxels"],
             bytes_per_voxel_rows=8.0 + 16.0 / 512,
             bytes_per_voxel_table=stats["bytes_per_voxel"],
             mesh_scratch_mb=_meshing_scratch_bytes(geometry) / 2**20)
  # What users call: `extract_mesh` of the map with both layers (the last "both" pass), the
  # vertices' and faces' labels read from the 0.1 m semantic layer (docs/equations.md §9.2).
  labelled = state[0]
  row["extract_mesh_ms"] = 1e3 * suite.median_time(lambda: jf.extract_mesh(labelled),
                                                   mesh_repeats)
  if gt_points is not None:
    row["quality"] = quality(vertices, faces, gt_points)

  peer = open3d_peer.tsdf_peer(frames, voxel_size=voxel_size, trunc_voxels=TRUNC_VOXELS,
                               depth_max=DEPTH_MAX, repeats=mesh_repeats, memory=peer_memory)
  if "vertices" in peer:
    if gt_points is not None:
      peer["quality"] = quality(peer["vertices"], peer["faces"], gt_points)
    peer = {key: value for key, value in peer.items() if key not in ("vertices", "faces")}
  row["open3d"] = peer
  return row


def _ratio(a, b):
  return a / b if b else float("nan")


def format_rows(rows) -> str:
  lines = ["| voxel | TSDF ms/frame (Open3D) | ratio | semantics | both | both − sem. "
           "| mesh ms (Open3D) | ratio | triangles (Open3D) |",
           "|---|---|---|---|---|---|---|---|---|"]
  for r in rows:
    o = r["open3d"]
    o_int = o.get("integrate_ms_per_frame", float("nan"))
    o_mesh = o.get("mesh_ms", float("nan"))
    lines.append(
        f"| {r['voxel_size']:.2f} m | {r['tsdf_ms']:.1f} ({o_int:.1f}) | "
        f"{_ratio(r['tsdf_ms'], o_int):.2f} | {r['semantic_ms']:.1f} | {r['both_ms']:.1f} | "
        f"{r['both_ms'] - r['semantic_ms']:.1f} | {r['mesh_ms']:.0f} ({o_mesh:.0f}) | "
        f"{_ratio(r['mesh_ms'], o_mesh):.2f} | {r['triangles']} ({o.get('num_triangles', '–')}) |")
  lines += ["", "| voxel | `marching_cubes` ms | `extract_mesh` ms, labels included | Open3D "
            "`extract_triangle_mesh` ms | `extract_mesh` / Open3D |", "|---|---|---|---|---|"]
  for r in rows:
    o_mesh = r["open3d"].get("mesh_ms", float("nan"))
    full = r.get("extract_mesh_ms", float("nan"))
    lines.append(f"| {r['voxel_size']:.2f} m | {r['mesh_ms']:.0f} | {full:.0f} | {o_mesh:.0f} | "
                 f"{_ratio(full, o_mesh):.2f} |")
  lines += ["", "| voxel | TSDF ms/frame, blocks from every 4th pixel | from every pixel | "
            "blocks found | from every pixel |", "|---|---|---|---|---|"]
  for r in rows:
    lines.append(f"| {r['voxel_size']:.2f} m | {r['tsdf_ms']:.1f} | "
                 f"{r.get('tsdf_ms_every_pixel', float('nan')):.1f} | {r['blocks']} | "
                 f"{r.get('blocks_every_pixel', '–')} |")
  quality_rows = [r for r in rows if "quality" in r]
  if quality_rows:
    lines += ["", "| voxel | mesh | acc. cm | comp. cm | Chamfer-L1 cm | P@5 | R@5 | F@5 | "
              "F@2 |", "|---|---|---|---|---|---|---|---|---|"]
    for r in quality_rows:
      for name, q in (("jaxfusion", r["quality"]), ("Open3D", r["open3d"].get("quality"))):
        if q is None:
          continue
        lines.append(
            f"| {r['voxel_size']:.2f} m | {name} | {q['accuracy']:.2f} | {q['completeness']:.2f}"
            f" | {q['chamfer_l1']:.2f} | {100 * q['precision@0.05']:.1f} | "
            f"{100 * q['recall@0.05']:.1f} | {100 * q['fscore@0.05']:.1f} | "
            f"{100 * q['fscore@0.02']:.1f} |")
  return "\n".join(lines)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--quick", action="store_true")
  parser.add_argument("--frames", type=int, default=None)
  parser.add_argument("--voxels", type=float, nargs="+", default=None)
  parser.add_argument("--out", default=RESULTS)
  args = parser.parse_args(argv)
  count = args.frames or (4 if args.quick else 12)
  height, width = (240, 320) if args.quick else (480, 640)
  voxels = args.voxels or ([0.10, 0.05] if args.quick else [0.10, 0.05, 0.02])
  frames = scene.make_frames(count, height=height, width=width, num_classes=13)
  gt = room_surface(frames)
  rows = []
  for v in voxels:
    rows.append(measure(frames, v, gt_points=gt, passes=1 if args.quick else 2))
    print(format_rows(rows[-1:]).splitlines()[2], flush=True)
  print(format_rows(rows))
  record = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
            "load_average": os.getloadavg()[0], "gt_points": int(len(gt)), "rows": rows}
  os.makedirs(os.path.dirname(args.out), exist_ok=True)
  with open(args.out, "w") as f:
    json.dump(record, f, indent=1, default=float)
  print(f"→ {args.out}")
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
