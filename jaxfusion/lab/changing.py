"""`jaxfusion changing-world`: a map in a world that changes — free-space clearing on moved
objects, and re-integration after drifting poses (docs/results/changing_world.md).

For each layout seed and trajectory of the embedded world it runs four sequences through the
network front end (MC dropout) and fuses each with Bayes, D+R and the shipped learned rule:
- `ENV:T:sS:moved`: two passes of the room, some objects moved, one removed, one added between
  them (`datasets.changes`); scored against the GT of the final scene, with clearing off and on;
- `ENV:T:sS:final`: the same two passes with the objects always where they end (the reference);
- `ENV:T:sS`: the static sequence (what clearing costs where nothing moves);
- `ENV:T:sS:drift`: one pass whose poses drift as odometry's would; fused at the drifted poses,
  then corrected to the true ones (`Mapper.reintegrate` for Bayes, `Mapper.rebuild` for D+R),
  against fusing at the true poses from scratch.

Measured (docs/equations.md §10–§11):
- ghost share: of the voxels that a moved or removed object filled in the first pass and that
  are free in the final scene (the *ghost region*), the share still read out with that object's
  class; over all of them, and over those a second-pass ray passes in front of its surface by
  0.2 m or more (the part any clearing could reach);
- final-scene mIoU beside the always-there map; the static sequence's mIoU with clearing on;
- mesh ghosts: ghost-region voxels that hold a vertex of the geometry layer's mesh (the TSDF is
  not cleared) and those whose vertex is still labelled with the object's class;
- drift: mIoU and the mesh's Chamfer distance to the true surface, drifted, corrected and from
  scratch; seconds per frame of fusing and of correcting.
"""

import argparse
import dataclasses
import json
import os
import time
from typing import Optional

import numpy as np
from tqdm.auto import tqdm

import jaxfusion as jf
from jaxfusion import datasets
from jaxfusion import metrics
from jaxfusion.datasets import surfaces
from jaxfusion.lab import figures
from jaxfusion.lab import flags
from jaxfusion.lab import frontend
from jaxfusion.lab import mesh_study
from jaxfusion.lab import sequences

RULES = ("bayes", "robust_dr", "learned")
# A second-pass ray must pass this far in front of its surface for a ghost voxel to count as
# reachable (independent of the engine's own test, docs/equations.md §10.1).
REACH = 0.2


@dataclasses.dataclass(frozen=True)
class ChangingConfig:
  """What `changing-world` runs.

  Attributes:
    env: embedded environment.
    layout_seeds: layout seeds (the study's judged seeds by default).
    trajectories: trajectory indices.
    num_frames: frames per sequence (the two-pass ones: half a pass each).
    height, width: image size.
    shift: domain shift of the test appearance.
    voxel_size: semantic voxel edge, metres.
    geometry_voxel: the geometry layer's voxel edge, metres.
    num_samples: MC-dropout samples.
    rules: rules to fuse with.
    calibration_seeds: layout seeds on which the clamp of the occupancy is chosen (never the
      judged ones).
    clamp_grid: upper clamps of the occupancy probability tried there (0.971: OctoMap's).
  """
  env: str = "office"
  layout_seeds: tuple = (1, 2, 3)
  trajectories: tuple = (0,)
  num_frames: int = 60
  height: int = 96
  width: int = 128
  shift: float = 1.0
  voxel_size: float = 0.1
  geometry_voxel: float = 0.05
  num_samples: int = 16
  rules: tuple = RULES
  calibration_seeds: tuple = (11, 12)
  clamp_grid: tuple = (0.971, 0.9, 0.8, 0.7)

  @classmethod
  def quick(cls) -> "ChangingConfig":
    return cls(layout_seeds=(1,), num_frames=16, height=48, width=64, num_samples=4,
               rules=("bayes", "robust_dr"), calibration_seeds=(11,), clamp_grid=(0.971, 0.7))


def _options(config: ChangingConfig) -> sequences.DataOptions:
  return sequences.DataOptions(num_frames=config.num_frames, height=config.height,
                               width=config.width, shift=config.shift,
                               voxel_size=config.voxel_size, num_samples=config.num_samples)


def _fuse(loaded, rule, *, free_space=False, geometry=None, poses=None, keep=False):
  """A `Mapper` that fused the loaded sequence (at `poses` if given), 30 frames per compiled
  scan; `(mapper, seconds)`."""
  seq, preds = loaded.sequence, loaded.predictions
  num_classes = int(preds["mean"].shape[-1])
  mapper = jf.Mapper(rule, num_classes=num_classes, voxel_size=0.1, capacity=2**15,
                     geometry=geometry, free_space=free_space,
                     keep_frames=len(seq) if keep else 0)
  poses = np.asarray(seq.T_world_cam if poses is None else poses, np.float32)
  var = preds["var"] if rule.requires_var else None
  frames = jf.Frame(np.asarray(seq.depth, np.float32), poses, preds["mean"], var,
                    np.asarray(seq.rgb) if rule.context else None)
  start = time.perf_counter()
  mapper.fuse_sequence(frames, seq.camera, chunk=30)
  mapper.state.keys.block_until_ready()
  return mapper, time.perf_counter() - start


def _keys_of_pixels(seq, frames, mask_fn, voxel_size):
  """Voxel keys (a set of tuples) of the pixels `mask_fn(t) (H, W) bool` of `frames`."""
  out = set()
  cam = seq.camera
  h, w = seq.image_size
  v, u = np.mgrid[0:h, 0:w]
  for t in frames:
    d = np.asarray(seq.depth[t], np.float64)
    m = mask_fn(t) & np.isfinite(d) & (d > 0)
    z = d[m]
    pts = np.stack([(u[m] - cam.cx) / cam.fx * z, (v[m] - cam.cy) / cam.fy * z, z], -1)
    T = np.asarray(seq.T_world_cam[t], np.float64)
    world = pts @ T[:3, :3].T + T[:3, 3]
    out |= set(map(tuple, np.floor(world / voxel_size).astype(np.int64)))
  return out


def ghost_region(loaded, voxel_size: float) -> dict:
  """The voxels that moved or removed objects filled in the first pass and that hold no
  surface of the final scene, with each one's class, and whether a second-pass ray passes in
  front of it by `REACH` (reachable).

  Returns:
    dict with `coords (G, 3) int64`, `labels (G,) int64`, `reachable (G,) bool`.
  """
  seq = loaded.sequence
  info = seq.info
  (p0, p1), (q0, q1) = info["passes"]
  gone = [int(i) for i in info["changes"]["moved"] + info["changes"]["removed"]]
  final = set(map(tuple, np.asarray(loaded.gt["coords"]).astype(np.int64)))
  coords, labels = [], []
  for instance in gone:
    label = None
    keys = set()
    for t in range(p0, p1):
      m = np.asarray(seq.instances[t]) == instance
      if m.any():
        label = int(np.bincount(np.asarray(seq.labels[t])[m]).argmax())
        keys |= _keys_of_pixels(seq, [t], lambda _t, m=m: m, voxel_size)
    for k in sorted(keys - final):
      coords.append(k)
      labels.append(label)
  coords = np.asarray(coords, np.int64).reshape(-1, 3)
  reachable = np.zeros(len(coords), bool)
  centres = (coords + 0.5) * voxel_size
  cam = seq.camera
  h, w = seq.image_size
  for t in range(q0, q1):
    T = np.asarray(seq.T_world_cam[t], np.float64)
    pc = (centres - T[:3, 3]) @ T[:3, :3]
    z = pc[:, 2]
    ok = z > 0.05
    zs = np.where(ok, z, 1.0)
    u = np.floor(cam.fx * pc[:, 0] / zs + cam.cx + 0.5).astype(np.int64)
    v = np.floor(cam.fy * pc[:, 1] / zs + cam.cy + 0.5).astype(np.int64)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    d = np.asarray(seq.depth[t], np.float64)[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)]
    reachable |= ok & np.isfinite(d) & (d > z + REACH)
  return {"coords": coords, "labels": np.asarray(labels, np.int64), "reachable": reachable}


def ghost_shares(voxels: dict, region: dict) -> dict:
  """Shares of the ghost region that a map still reads out (any class, the object's class),
  over all of it and over its reachable part, in %."""
  if len(region["coords"]) == 0:
    return {"ghost": float("nan"), "ghost_reachable": float("nan"), "read_out": float("nan")}
  index = {tuple(c): i for i, c in enumerate(np.asarray(voxels["coords"]).astype(np.int64))}
  found = np.array([tuple(c) in index for c in region["coords"]])
  label = np.array([voxels["labels"][index[tuple(c)]] if f else -1
                    for c, f in zip(region["coords"], found)])
  ghost = found & (label == region["labels"])
  reach = region["reachable"]
  share = lambda x, m: float(100.0 * x[m].mean()) if m.any() else float("nan")
  return {"ghost": share(ghost, np.ones_like(ghost)), "ghost_reachable": share(ghost, reach),
          "read_out": share(found, np.ones_like(found))}


def mesh_ghosts(state, region: dict) -> dict:
  """Ghost-region voxels holding a mesh vertex (geometry), and those whose vertex there is
  labelled with the object's class (semantics on the mesh), in %."""
  if state.geometry is None or len(region["coords"]) == 0:
    return {"mesh_ghost": float("nan"), "mesh_labelled_ghost": float("nan")}
  mesh = jf.extract_mesh(state)
  keys = np.floor(np.asarray(mesh.vertices, np.float64) / 0.1).astype(np.int64)
  where = {}
  for k, lab in zip(map(tuple, keys), np.asarray(mesh.labels)):
    where.setdefault(k, set()).add(int(lab))
  geo = np.array([tuple(c) in where for c in region["coords"]])
  lab = np.array([int(l) in where.get(tuple(c), ()) for c, l in
                  zip(region["coords"], region["labels"])])
  return {"mesh_ghost": float(100 * geo.mean()), "mesh_labelled_ghost": float(100 * lab.mean())}


def _miou(state, gt, num_classes) -> float:
  ev = metrics.evaluate_map(jf.read_map(state), gt, num_classes,
                            ignore_label=datasets.IGNORE_LABEL)
  return float(100 * ev["miou"])


def _chamfer(state, surface) -> float:
  """Chamfer-L1 (cm) of the geometry layer's mesh to the true surface, as the mesh study
  scores it (`mesh_study.geometry_scores`)."""
  return float(100 * mesh_study.geometry_scores(jf.extract_mesh(state), surface)["chamfer_l1"])


def settings(clamp: float) -> dict:
  """The clearing settings compared: off, OctoMap's numbers, and the calibrated clamp."""
  out = {"off": False, "on": jf.FreeSpaceConfig()}
  if clamp != jf.FreeSpaceConfig().clamp_max:
    out["calibrated"] = jf.FreeSpaceConfig(clamp_max=clamp)
  return out


def calibrate(config: ChangingConfig, front_end) -> dict:
  """The upper clamp of the occupancy, chosen on the calibration layouts only: the one with the
  lowest ghost share (mean of Bayes and D+R) among those that cost the static sequence at most
  0.3 mIoU (OctoMap's if none does better)."""
  options = _options(config)
  rows = {c: {"ghost": [], "static_loss": []} for c in config.clamp_grid}
  for seed in config.calibration_seeds:
    for trajectory in config.trajectories:
      base = f"{config.env}:{trajectory}:s{seed}"
      moved = sequences.load(f"{base}:moved", options, front_end=front_end)
      static = sequences.load(base, options, front_end=front_end)
      k = int(moved.predictions["mean"].shape[-1])
      region = ghost_region(moved, config.voxel_size)
      for name in ("bayes", "robust_dr"):
        _, rule, _ = flags.resolve_rule(name, num_classes=k)
        static_off = _miou(_fuse(static, rule)[0].state, static.gt, k)
        for clamp in config.clamp_grid:
          free = jf.FreeSpaceConfig(clamp_max=clamp)
          voxels = jf.read_map(_fuse(moved, rule, free_space=free)[0].state)
          rows[clamp]["ghost"].append(ghost_shares(voxels, region)["ghost"])
          rows[clamp]["static_loss"].append(
              static_off - _miou(_fuse(static, rule, free_space=free)[0].state, static.gt, k))
  table = {str(c): {key: _mean(v) for key, v in r.items()} for c, r in rows.items()}
  ok = [c for c in config.clamp_grid if table[str(c)]["static_loss"] <= 0.3]
  chosen = min(ok, key=lambda c: (table[str(c)]["ghost"], -c)) if ok else (
      jf.FreeSpaceConfig().clamp_max)
  return {"table": table, "clamp_max": float(chosen)}


def run_unit(config: ChangingConfig, front_end, seed: int, trajectory: int,
             clamp: float) -> dict:
  """Every measurement of one layout seed and trajectory."""
  options = _options(config)
  base = f"{config.env}:{trajectory}:s{seed}"
  load = lambda spec: sequences.load(spec, options, front_end=front_end)
  moved, final, static, drift = (load(f"{base}{tail}") for tail in (":moved", ":final", "",
                                                                      ":drift"))
  k = int(moved.predictions["mean"].shape[-1])
  region = ghost_region(moved, config.voxel_size)
  geometry = jf.TSDFConfig(voxel_size=config.geometry_voxel, capacity=2**12)
  out = {"unit": base, "ghost_region": int(len(region["coords"])),
         "ghost_region_reachable": int(region["reachable"].sum()),
         "changes": moved.sequence.info["changes"], "rules": {}}
  for name in config.rules:
    _, rule, _ = flags.resolve_rule(name, num_classes=k)
    row = {}
    for tag, on in settings(clamp).items():
      mapper, seconds = _fuse(moved, rule, free_space=on, geometry=geometry)
      voxels = jf.read_map(mapper.state)
      row[tag] = dict(ghost_shares(voxels, region), **mesh_ghosts(mapper.state, region))
      row[tag]["miou_final"] = _miou(mapper.state, moved.gt, k)
      row[tag]["seconds_per_frame"] = seconds / len(moved.sequence)
      row[tag]["miou_always"] = _miou(_fuse(final, rule, free_space=on)[0].state, final.gt, k)
      row[tag]["miou_static"] = _miou(_fuse(static, rule, free_space=on)[0].state, static.gt, k)
      if name == "robust_dr" and seed == config.layout_seeds[0] and trajectory == \
          config.trajectories[0]:
        out.setdefault("views", {})[tag] = {"coords": voxels["coords"].tolist(),
                                            "labels": voxels["labels"].tolist()}
        out["views_region"] = region["coords"].tolist()
    out["rules"][name] = row
  out["views_gt"] = {"coords": np.asarray(moved.gt["coords"]).tolist(),
                     "labels": np.asarray(moved.gt["labels"]).tolist()}
  out["drift"] = run_drift(config, drift, k, geometry)
  return out


def run_drift(config: ChangingConfig, drift, k: int, geometry) -> dict:
  """Drifted, corrected and from-scratch maps of a drift sequence."""
  seq = drift.sequence
  true = np.asarray(seq.info["true_poses"], np.float32)
  surface = surfaces.sequence_surface(
      config.env, drift.spec.layout_seed, drift.spec.shift,
      dataclasses.replace(seq, T_world_cam=true), domain=drift.spec.domain)
  ends = np.linalg.norm(np.asarray(seq.T_world_cam)[:, :3, 3] - true[:, :3, 3], axis=-1)
  out = {"drift_end_m": float(ends[-1]), "drift_max_m": float(ends.max()), "rules": {}}
  for name in ("bayes", "robust_dr"):
    if name not in config.rules:
      continue
    _, rule, _ = flags.resolve_rule(name, num_classes=k)
    mapper, fuse_s = _fuse(drift, rule, geometry=geometry, keep=True)
    row = {"drifted": {"miou": _miou(mapper.state, drift.gt, k),
                       "chamfer_cm": _chamfer(mapper.state, surface)}}
    start = time.perf_counter()
    if rule.remove is not None:
      mapper.reintegrate(list(mapper.kept), true)
      how = "reintegrate"
    else:
      mapper.rebuild(dict(zip(list(mapper.kept), true)))
      how = "rebuild"
    mapper.state.keys.block_until_ready()
    correct_s = time.perf_counter() - start
    row["corrected"] = {"miou": _miou(mapper.state, drift.gt, k),
                        "chamfer_cm": _chamfer(mapper.state, surface), "how": how}
    scratch, _ = _fuse(drift, rule, geometry=geometry, poses=true)
    row["scratch"] = {"miou": _miou(scratch.state, drift.gt, k),
                      "chamfer_cm": _chamfer(scratch.state, surface)}
    row["fuse_s_per_frame"] = fuse_s / len(seq)
    row["correct_s_per_frame"] = correct_s / len(seq)
    out["rules"][name] = row
  return out


def _mean(values) -> float:
  values = [v for v in values if v == v]
  return float(np.mean(values)) if values else float("nan")


def summarise(units: list, config: ChangingConfig) -> dict:
  """Means over units, per rule and clearing setting."""
  rows = {}
  for name in config.rules:
    for tag in units[0]["rules"][name]:
      keys = units[0]["rules"][name][tag].keys()
      rows[f"{name}/{tag}"] = {key: _mean([u["rules"][name][tag][key] for u in units])
                               for key in keys}
  drift = {}
  for name in ("bayes", "robust_dr"):
    if name not in config.rules:
      continue
    drift[name] = {stage: {key: _mean([u["drift"]["rules"][name][stage][key] for u in units])
                           for key in ("miou", "chamfer_cm")}
                   for stage in ("drifted", "corrected", "scratch")}
    for key in ("fuse_s_per_frame", "correct_s_per_frame"):
      drift[name][key] = _mean([u["drift"]["rules"][name][key] for u in units])
  return {"rows": rows, "drift": drift,
          "drift_end_m": _mean([u["drift"]["drift_end_m"] for u in units]),
          "ghost_region": int(sum(u["ghost_region"] for u in units)),
          "ghost_region_reachable": int(sum(u["ghost_region_reachable"] for u in units))}


def _f(x, digits=1) -> str:
  return "–" if x != x else f"{x:.{digits}f}"


def crop_to_region(maps: dict, region: np.ndarray, pad: int = 6) -> dict:
  """The maps cut to the box around the ghost region (±`pad` voxels, 1.2 m up): where the moved
  and removed objects stood."""
  if len(region) == 0:
    return maps
  lo, hi = region.min(0) - pad, region.max(0) + pad
  hi[2] = min(hi[2], lo[2] + pad + 12)
  out = {}
  for title, m in maps.items():
    keep = np.all((m["coords"] >= lo) & (m["coords"] <= hi), axis=-1)
    out[title] = {"coords": m["coords"][keep], "labels": m["labels"][keep]}
  return out


GHOST_COLORS = np.array([[200, 200, 200], [220, 0, 160]], np.uint8)


def ghost_figure(path: str, maps: dict, region: np.ndarray, voxel_size: float) -> None:
  """The maps cut to the ghost region's box, every voxel grey except those of the ghost region
  that the map still reads out (magenta)."""
  ghost = {tuple(c) for c in np.asarray(region, np.int64)}
  marked = {}
  for title, m in crop_to_region(maps, region).items():
    inside = np.array([tuple(c) in ghost for c in np.asarray(m["coords"], np.int64)], bool)
    marked[f"{title}: {int(inside.sum())} of {len(ghost)} ghost voxels"] = {
        "coords": m["coords"], "labels": inside.astype(np.int64)}
  figures.map_views(path, marked, voxel_size=voxel_size, colors=GHOST_COLORS)


def _reading(s: dict, rules) -> list:
  """The page's summary sentences, from the numbers."""
  r = lambda name, tag, key: s["rows"].get(f"{name}/{tag}", {}).get(key, float("nan"))
  tags = [t for t in ("on", "calibrated") if f"{rules[0]}/{t}" in s["rows"]]
  worst = {t: max(r(n, t, "ghost") for n in rules) for t in ["off"] + tags}
  loss = max(abs(r(n, t, "miou_final") - r(n, t, "miou_always")) for n in rules for t in tags)
  static = max(r(n, "off", "miou_static") - r(n, t, "miou_static") for n in rules for t in tags)
  lines = [f"- Without clearing, up to {_f(worst['off'])} % of the ghost region keeps the moved "
           f"object's class; OctoMap's numbers leave up to {_f(worst.get('on', float('nan')))} %"
           + (f", the calibrated clamp {_f(worst['calibrated'])} %." if "calibrated" in worst
              else "."),
           f"- With clearing on, the final-scene mIoU is within {_f(loss, 2)} points of the "
           f"always-there map, and the static sequence loses at most {_f(static, 2)} mIoU: the "
           "ghost region is small beside the room, so mIoU hardly sees it.",
           "- The TSDF is not cleared: its mesh keeps the old geometry where the semantic layer "
           "no longer reads the object (mesh % against mesh labelled %)."]
  for name, d in s["drift"].items():
    lines.append(f"- Drift, {name}: corrected {_f(d['corrected']['miou'])} mIoU and "
                 f"{_f(d['corrected']['chamfer_cm'], 2)} cm Chamfer against "
                 f"{_f(d['scratch']['miou'])} and {_f(d['scratch']['chamfer_cm'], 2)} from scratch "
                 f"(drifted: {_f(d['drifted']['chamfer_cm'], 2)} cm).")
  return lines


def write_page(path: str, result: dict, command: str) -> None:
  """docs/results/changing_world.md from a result."""
  s, config = result["summary"], result["config"]
  names = {"bayes": "Bayes", "robust_dr": "D+R", "learned": "Learned (v1)"}
  lines = [
      "# A changing world: free-space clearing and re-integration",
      "",
      f"Made by `{command}` ({result['timing']['seconds']:.0f} s on this machine); the numbers "
      "live in `outputs/changing/changing.json`. What is computed: docs/equations.md §10–§11; "
      "how: `jaxfusion/lab/changing.py`.",
      "",
      f"Embedded {config['env']} rooms, layout seeds {config['layout_seeds']}, trajectories "
      f"{config['trajectories']}, {config['num_frames']} frames of {config['height']}×"
      f"{config['width']} (two passes of {config['num_frames'] // 2} for the changing "
      f"sequences), the network front end (MC dropout, M = {config['num_samples']}), test "
      f"appearance at shift {config['shift']:g}, 0.1 m semantic voxels, a "
      f"{config['geometry_voxel']:g} m geometry layer. Clearing uses OctoMap's numbers and a "
      "margin of one voxel (**on**); **calibrated** changes one number, the upper clamp of the "
      "occupancy, chosen on the calibration layouts "
      f"{config['calibration_seeds']} only (lowest ghost share with a static-scene loss ≤ 0.3 "
      f"mIoU, from {list(config['clamp_grid'])}): "
      f"{result['calibration']['clamp_max']:g}. Means over the units.",
      "",
      "## What it shows",
      "",
      *_reading(s, config["rules"]),
      "",
      "## Moved objects",
      "",
      f"Ghost region: {s['ghost_region']} voxels that moved or removed objects filled in the "
      f"first pass and that hold no surface of the final scene ({s['ghost_region_reachable']} "
      f"of them passed by a second-pass ray at least {REACH:g} m in front of its surface). "
      "**Ghost**: share of the region still read out with the object's class (all / "
      "reachable); **read out**: with any class. **Mesh**: region voxels holding a vertex of "
      "the TSDF mesh / a vertex still labelled with the object's class. mIoU against the final "
      "scene's GT: the changing sequence, the always-there sequence, the static sequence.",
      "",
      "| rule | clearing | ghost % | ghost % (reachable) | read out % | mesh % | mesh labelled % "
      "| mIoU final | mIoU always-there | mIoU static |",
      "|---|---|---|---|---|---|---|---|---|---|",
  ]
  for name in config["rules"]:
    for tag in ("off", "on", "calibrated"):
      if f"{name}/{tag}" not in s["rows"]:
        continue
      r = s["rows"][f"{name}/{tag}"]
      lines.append(
          f"| {names.get(name, name)} | {tag} | {_f(r['ghost'])} | {_f(r['ghost_reachable'])} | "
          f"{_f(r['read_out'])} | {_f(r['mesh_ghost'])} | {_f(r['mesh_labelled_ghost'])} | "
          f"{_f(r['miou_final'])} | {_f(r['miou_always'])} | {_f(r['miou_static'])} |")
  lines += ["", "![cleared and uncleared maps](../changing_world_maps.png)", "",
            "D+R maps of the first unit after both passes, clearing off and with the "
            "calibrated clamp, cut to where the moved and removed objects stood: in magenta the "
            "ghost voxels each still reads out. By class, beside the final scene's GT: "
            "[changing_world_maps_classes.png](../changing_world_maps_classes.png); PLY files of "
            "both maps: `outputs/changing/`.", "", "## Drifting poses", "",
            f"One pass whose poses drift (the end {s['drift_end_m']:.2f} m off on average), fused "
            "at the drifted poses, then corrected to the true ones (Bayes: `Mapper.reintegrate`, "
            "exact de-integration; D+R cannot be inverted: `Mapper.rebuild` fuses every kept "
            "frame again), against fusing at the true poses from scratch. Chamfer-L1 of the "
            "mesh to the true surface, in cm.", "",
            "| rule | drifted mIoU | corrected mIoU | scratch mIoU | drifted Chamfer | corrected "
            "Chamfer | scratch Chamfer |",
            "|---|---|---|---|---|---|---|"]
  for name, r in s["drift"].items():
    lines.append(
        f"| {names.get(name, name)} | {_f(r['drifted']['miou'])} | {_f(r['corrected']['miou'])} | "
        f"{_f(r['scratch']['miou'])} | {_f(r['drifted']['chamfer_cm'], 2)} | "
        f"{_f(r['corrected']['chamfer_cm'], 2)} | {_f(r['scratch']['chamfer_cm'], 2)} |")
  cal = result["calibration"]["table"]
  lines += ["", "## Calibration of the clamp (calibration layouts only)", "",
            "| clamp_max | ghost % (Bayes, D+R) | static mIoU loss |", "|---|---|---|"]
  lines += [f"| {c} | {_f(r['ghost'])} | {_f(r['static_loss'], 2)} |" for c, r in cal.items()]
  lines += ["", "What each setting costs per frame, measured plainly beside the same frame "
            "without clearing, is in bench/RESULTS.md (`python -m bench.changing`).", ""]
  os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
  with open(path, "w") as f:
    f.write("\n".join(lines))


def run(config: ChangingConfig, out_dir: str, *, front_end=None, page: Optional[str] = None,
        figure: Optional[str] = None, command: str = "jaxfusion changing-world") -> dict:
  """Runs every unit, writes `out_dir/changing.json`, the page and the figure."""
  start = time.perf_counter()
  front_end = front_end if front_end is not None else frontend.FrontEnd()
  calibration = calibrate(config, front_end)
  units = []
  todo = [(s, t) for s in config.layout_seeds for t in config.trajectories]
  for seed, trajectory in tqdm(todo, desc="changing world"):
    units.append(run_unit(config, front_end, seed, trajectory, calibration["clamp_max"]))
  result = {"config": dataclasses.asdict(config), "calibration": calibration, "units": units,
            "summary": summarise(units, config),
            "timing": {"seconds": time.perf_counter() - start}}
  os.makedirs(out_dir, exist_ok=True)
  views = units[0].pop("views", None)
  gt_view = units[0].pop("views_gt", None)
  region = np.asarray(units[0].pop("views_region", []), np.int64).reshape(-1, 3)
  for u in units[1:]:
    for key in ("views", "views_gt", "views_region"):
      u.pop(key, None)
  with open(os.path.join(out_dir, "changing.json"), "w") as f:
    json.dump(result, f, indent=1)
  colors = datasets.palette(datasets.CLASS_NAMES)
  if views is not None:
    last = "calibrated" if "calibrated" in views else "on"
    maps = {"D+R, clearing off": views["off"], f"D+R, clearing {last}": views[last],
            "GT, final scene": gt_view}
    maps = {k: {"coords": np.asarray(v["coords"]), "labels": np.asarray(v["labels"])}
            for k, v in maps.items()}
    np.savez_compressed(os.path.join(out_dir, "views.npz"), region=region, **{
        f"{k}/{f}": v[f] for k, v in maps.items() for f in ("coords", "labels")})
    for path in filter(None, (figure, os.path.join(out_dir, "changing_world_maps.png"))):
      ghost_figure(path, {k: v for k, v in maps.items() if not k.startswith("GT")}, region,
                   config.voxel_size)
      figures.map_views(path.replace(".png", "_classes.png"), crop_to_region(maps, region),
                        voxel_size=config.voxel_size, colors=colors)
    for tag in ("off", last):
      m = maps[f"D+R, clearing {tag}"]
      jf.io.export_ply(os.path.join(out_dir, f"moved_robust_dr_clearing_{tag}.ply"),
                       {"coords": m["coords"], "labels": m["labels"],
                        "centers": ((m["coords"] + 0.5) * config.voxel_size).astype(np.float32)},
                       voxel_size=config.voxel_size, colors=colors)
  if page is not None:
    write_page(page, result, command)
  return result


def main(args: argparse.Namespace) -> int:
  config = ChangingConfig.quick() if args.quick else ChangingConfig()
  if args.layout_seeds:
    config = dataclasses.replace(config, layout_seeds=flags.as_tuple(args.layout_seeds))
  if args.trajectories:
    config = dataclasses.replace(config, trajectories=flags.as_tuple(args.trajectories))
  page = None if args.quick else args.page
  figure = None if args.quick else args.figure
  command = "jaxfusion changing-world" + (" --quick" if args.quick else "")
  result = run(config, args.out, front_end=frontend.FrontEnd(args.checkpoint), page=page,
               figure=figure, command=command)
  s = result["summary"]
  for name, r in s["rows"].items():
    print(f"{name:16s} ghost {_f(r['ghost'])} %  (reachable {_f(r['ghost_reachable'])} %)  "
          f"mIoU final {_f(r['miou_final'])}  always {_f(r['miou_always'])}  static "
          f"{_f(r['miou_static'])}")
  for name, r in s["drift"].items():
    print(f"drift {name:10s} mIoU {_f(r['drifted']['miou'])} → {_f(r['corrected']['miou'])} "
          f"(scratch {_f(r['scratch']['miou'])}), Chamfer {_f(r['drifted']['chamfer_cm'], 2)} → "
          f"{_f(r['corrected']['chamfer_cm'], 2)} cm (scratch {_f(r['scratch']['chamfer_cm'], 2)})")
  print(f"→ {os.path.join(args.out, 'changing.json')}" + (f", {page}" if page else ""))
  return 0


def add_parser(subparsers) -> None:
  p = subparsers.add_parser("changing-world", help="free-space clearing on moved objects and "
                            "re-integration after drift (docs/results/changing_world.md)")
  p.add_argument("--quick", action="store_true", help="one small unit (a smoke run)")
  p.add_argument("--layout-seeds", default=None, help="comma-separated layout seeds")
  p.add_argument("--trajectories", default=None, help="comma-separated trajectories")
  p.add_argument("--checkpoint", default=None, help="front-end checkpoint (default: shipped)")
  p.add_argument("--out", default="outputs/changing", help="output folder")
  p.add_argument("--page", default="docs/results/changing_world.md", help="results page")
  p.add_argument("--figure", default="docs/changing_world_maps.png", help="map figure")
  p.set_defaults(func=main)
