"""What per-pixel context costs: `python -m bench.context [--quick] [--out DIR]`.

On the bench room (`scene.make_frames`, 640×480, K = 13 by default) with a colour image made
from its depths and labels, each row times `jf.fuse_frame` as users call it (plain, donated map,
median of repeats after the warm-up) for one rule, beside its peer in the same run:

- the six-feature learned rule (no context) against D+R, its special case;
- the learned rule reading every context feature (and per-class weights, γ of 5) against the
  learned rule without context;
- GLFS (depth and incidence) against Bayes, its special case;
- `context.pixel_context` alone (every feature), against the fusion of one frame by D+R;
- the rule family (docs/equations.md §3.11) at the structure of its fits (GLFS's table, per-class
  moment and geometry-context weights; with R and D switched in too), and its parts (the table
  alone; the table and the moment weights), against D+R;
- `read_map` of a family map with the spatial term (§4.1) against `read_map` of the same map
  without it.

Rules that read no context run the program they ran before (tests/engine/test_context.py checks
that their traced program holds no context computation), so their rows are the reference. Writes
`context.json` under `--out` (default `bench/results/`) and prints a Markdown table.
"""

import argparse
import json
import pathlib
import time

import jax
import numpy as np

import jaxfusion as jf
from bench import scene
from bench import suite


def colour_images(frames: scene.BenchFrames) -> np.ndarray:
  """`(T, H, W, 3) uint8` images: a per-class colour, shaded by depth, with a fine texture."""
  t, h, w, k = frames.probs.shape
  rng = np.random.default_rng(0)
  palette = rng.integers(40, 220, (k, 3)).astype(np.float32)
  labels = frames.probs.argmax(-1)
  shade = np.clip(1.2 - 0.12 * frames.depth, 0.3, 1.0)[..., None]
  texture = rng.normal(0.0, 12.0, (t, h, w, 1)).astype(np.float32)
  return np.clip(palette[labels] * shade + texture, 0, 255).astype(np.uint8)


def _rules(k: int) -> dict:
  zeros = lambda *shape: np.zeros(shape, np.float32)
  full = {"theta": zeros(k, 6), "bias": np.full(k, 3.0, np.float32),
          "context_theta": zeros(k, len(jf.context.FEATURES)),
          "gate": np.array([3.0, 0.0, 0.0, 0.0, 0.0], np.float32)}
  return {
      "robust_dr": jf.rules.robust(),
      "learned": jf.rules.learned({"bias": 3.0, "gate": [3.0, 0.0, 0.0]}),
      "learned_context": jf.rules.learned(full, context=jf.context.FEATURES),
      "bayes": jf.rules.bayes(),
      "glfs": jf.rules.glfs(num_classes=k),
      "family_table": jf.rules.family({"table": _family_params(k)["table"]}, context=()),
      "family_moments": jf.rules.family(
          {key: v for key, v in _family_params(k).items() if key != "context_weights"},
          context=()),
      "family": jf.rules.family(_family_params(k), context=FAMILY_CONTEXT),
      "family_rd": jf.rules.family({**_family_params(k), "beta": np.full(k, 0.01, np.float32),
                                    "mix": 0.01}, context=FAMILY_CONTEXT),
  }


# The geometry context of the family's fits (`learn-rule --context geometry`).
FAMILY_CONTEXT = ("depth", "incidence", "depth_edge", "label_edge", "radius")


def _family_params(k: int) -> dict:
  return {"table": np.ones((k, 5, 4), np.float32), "moment_weights": np.zeros((k, 6), np.float32),
          "context_weights": np.zeros((k, len(FAMILY_CONTEXT)), np.float32)}


PAIRS = (("learned", "robust_dr"), ("learned_context", "learned"), ("glfs", "bayes"),
         ("family_table", "robust_dr"), ("family_moments", "robust_dr"),
         ("family", "robust_dr"), ("family_rd", "robust_dr"))


def _time_read_out(frames, rgb, *, capacity, repeats, voxel_size) -> dict:
  """`read_map` of one family map fused from the frames, with and without the spatial kernel."""
  k = frames.probs.shape[-1]
  rule = jf.rules.family({**_family_params(k), "spatial": np.full((k, 3), 0.5, np.float32)},
                         context=FAMILY_CONTEXT)
  state = jf.init_map(capacity=capacity, num_classes=k, voxel_size=voxel_size, rule=rule)
  for t in range(len(frames.depth)):
    state = jf.fuse_frame(state, jf.Frame(frames.depth[t], frames.poses[t], frames.probs[t],
                                          frames.var[t], rgb[t]), frames.camera, rule)
  plain = state.replace(spatial=None)
  out = {}
  for name, s in (("read_map", plain), ("read_map_spatial", state)):
    seconds = suite.median_time(lambda s=s: jf.read_map(s)["posterior"], repeats)
    out[name] = {"ms_per_frame": 1e3 * seconds, "frames_per_s": 1.0 / seconds,
                 "voxels": int(state.num_occupied)}
  return out


def _time_rule(rule, frames, rgb, *, capacity, repeats, voxel_size) -> float:
  k = frames.probs.shape[-1]
  dev = [jax.device_put(jf.Frame(frames.depth[t], frames.poses[t], frames.probs[t],
                                 frames.var[t], rgb[t])) for t in range(len(frames.depth))]
  state = jf.init_map(capacity=capacity, num_classes=k, voxel_size=voxel_size, rule=rule)
  # pylint: disable-next=protected-access
  fuser = suite._Fuser(state, dev, frames.camera, rule, jf.fuse_frame)
  return suite.median_time(fuser, repeats)


def run(*, num_frames: int = 6, height: int = 480, width: int = 640, num_classes: int = 13,
        repeats: int = 12, capacity: int = 2**18, voxel_size: float = 0.1) -> dict:
  """Times every rule of `_rules` and `pixel_context`; returns the results dict."""
  frames = scene.make_frames(num_frames, height=height, width=width, num_classes=num_classes)
  rgb = colour_images(frames)
  rows = {}
  for name, rule in _rules(num_classes).items():
    seconds = _time_rule(rule, frames, rgb, capacity=capacity, repeats=repeats,
                         voxel_size=voxel_size)
    rows[name] = {"ms_per_frame": 1e3 * seconds, "frames_per_s": 1.0 / seconds}
  names = jf.context.FEATURES
  ctx = lambda t: jf.context.pixel_context_jit(frames.depth[t], frames.probs[t], frames.camera,
                                               names, rgb[t])
  counter = iter(range(10**9))
  seconds = suite.median_time(lambda: ctx(next(counter) % num_frames), repeats)
  rows["pixel_context"] = {"ms_per_frame": 1e3 * seconds, "frames_per_s": 1.0 / seconds}
  rows.update(_time_read_out(frames, rgb, capacity=capacity, repeats=repeats,
                             voxel_size=voxel_size))
  pairs = [{"rule": a, "peer": b, "ratio": rows[a]["ms_per_frame"] / rows[b]["ms_per_frame"]}
           for a, b in PAIRS + (("pixel_context", "robust_dr"),
                                ("read_map_spatial", "read_map"))]
  return {"machine": suite.machine(), "height": height, "width": width,
          "num_classes": num_classes, "num_frames": num_frames, "repeats": repeats,
          "rows": rows, "pairs": pairs, "date": time.strftime("%Y-%m-%d")}


def to_markdown(results: dict) -> str:
  rows = results["rows"]
  lines = [f"| row ({results['width']}×{results['height']}, K = {results['num_classes']}) | "
           "ms / frame | frames / s | peer | × peer |", "|---|---|---|---|---|"]
  peers = {p["rule"]: p for p in results["pairs"]}
  for name, row in rows.items():
    pair = peers.get(name)
    lines.append(f"| {name} | {row['ms_per_frame']:.1f} | {row['frames_per_s']:.1f} | "
                 f"{pair['peer'] if pair else '–'} | "
                 f"{'%.2f' % pair['ratio'] if pair else '–'} |")
  return "\n".join(lines)


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench.context",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("--quick", action="store_true", help="120×160, 3 frames, 3 repeats")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"))
  args = parser.parse_args(argv)
  kw = dict(num_frames=3, height=120, width=160, repeats=3) if args.quick else {}
  results = run(**kw)
  out = pathlib.Path(args.out)
  out.mkdir(parents=True, exist_ok=True)
  (out / "context.json").write_text(json.dumps(results, indent=2))
  print(to_markdown(results))
  print(f"wrote {out / 'context.json'}")


if __name__ == "__main__":
  main()
