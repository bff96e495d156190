"""The embedded world's commands: `jaxfusion list | render | save | show | bench` (also
`python -m jaxfusion.datasets ...`).

Examples:
  jaxfusion list
  jaxfusion bench --height 120 --width 160
  jaxfusion render --env office --trajectory 0 --frame 0 --out frame.png
  jaxfusion save --env house --trajectory 2 --out seqs/house_2
  jaxfusion save --format scannet --num-frames 30 --out scans/scene0000_00
  jaxfusion save --format tum --num-frames 30 --out tum/embedded_office
  jaxfusion show --path seqs/house_2 --frame 3 --out frame.png
"""

import argparse
import os
import sys
import time

import numpy as np

from jaxfusion.datasets import camera_model, export, preview, synthetic
from jaxfusion.datasets.classes import palette
from jaxfusion.datasets.camera_model import SensingConfig
from jaxfusion.datasets.sequence import RGBDSequence
from jaxfusion.lab import flags


SAVE_FORMATS = ("saved", "scannet", "tum")
# The rendered image size of `save` by format when --height/--width are not given.
SAVE_SIZES = {"saved": (240, 320), "scannet": (480, 640), "tum": (240, 320)}


def _add_synthetic_args(p: argparse.ArgumentParser) -> None:
  p.add_argument("--env", choices=synthetic.ENVIRONMENTS, default="office")
  p.add_argument("--trajectory", type=int, choices=range(synthetic.NUM_TRAJECTORIES), default=0)
  p.add_argument("--domain", choices=("train", "test"), default="test")
  p.add_argument("--num-frames", type=int, default=60)
  p.add_argument("--height", type=int, default=240)
  p.add_argument("--width", type=int, default=320)
  flags.add_layout_seeds(p, default=[0], aliases=("--seed",), help_suffix=" (one; default 0)")
  p.add_argument("--shift", type=float, default=1.0)
  p.add_argument("--no-realism", action="store_true", help="exact depth and colour")
  p.add_argument("--no-sensing", action="store_true",
                 help="plain sensor model instead of the view-dependent camera model")




def camera_effects(seq: RGBDSequence, config: SensingConfig) -> dict:
  """Per-frame size of the camera model's blur in a synthetic sequence.

  Returns:
    dict of `(T,)` arrays: `motion_blur_px` (median over pixels of the length of the motion
    streak), `defocus_sigma_px` (median thin-lens + optical σ), `exposure`.
  """
  states = seq.info["camera_states"]
  dt = states["frame_interval_s"]
  motion, defocus = [], []
  for t in range(len(seq)):
    other = seq.T_world_cam[t - 1] if t > 0 else seq.T_world_cam[min(1, len(seq) - 1)]
    v, w = camera_model.velocity(other, seq.T_world_cam[t], dt)
    path = camera_model.motion_from_velocity(v, w, states["exposure_time_s"][t])
    du, dv = camera_model.motion_flow(seq.depth[t], seq.camera, path)
    motion.append(float(np.median(np.hypot(du[-1], dv[-1]))))
    defocus.append(float(np.median(camera_model.defocus_sigma(
        seq.depth[t], seq.camera.fx, aperture=config.aperture,
        focus_distance=config.focus_distance, optical_blur=config.optical_blur))))
  return {"motion_blur_px": np.array(motion), "defocus_sigma_px": np.array(defocus),
          "exposure": np.array(states["exposure"])}


def add_parser(subparsers) -> None:
  """Adds `list`, `render`, `save`, `show` and `bench`."""
  subparsers.add_parser("list", help="list the embedded sequences (environment, trajectory)"
                        ).set_defaults(func=main)
  render = subparsers.add_parser("render", help="render one embedded frame as an RGB | depth | "
                                                "labels PNG")
  _add_synthetic_args(render)
  render.add_argument("--frame", type=int, default=0)
  render.add_argument("--out", default="frame.png")
  render.set_defaults(func=main)
  save = subparsers.add_parser("save", help="render a whole embedded sequence and save it to a "
                                            "folder (jaxfusion's, ScanNet's or TUM's layout)")
  _add_synthetic_args(save)
  save.add_argument("--out", required=True)
  save.add_argument("--format", choices=SAVE_FORMATS, default="saved",
                    help="saved: jaxfusion's own folder (bit-exact); scannet: a SensReader "
                         "export with NYU40 label images and the labelled GT mesh; tum: the TUM "
                         "RGB-D layout (default: saved)")
  save.add_argument("--color-size", type=int, nargs=2, metavar=("H", "W"), default=None,
                    help="colour and label image size for --format scannet (default "
                         f"{export.SCANNET_COLOR_SIZE[0]} {export.SCANNET_COLOR_SIZE[1]})")
  save.add_argument("--overwrite", action="store_true",
                    help="with --format scannet | tum: write into a non-empty folder that is "
                         "not such an export")
  # --height/--width default by format: 480x640 (ScanNet's depth) for scannet, else 240x320.
  save.set_defaults(func=main, height=None, width=None)
  show = subparsers.add_parser("show", help="preview a frame of a saved sequence folder")
  show.add_argument("--path", required=True)
  show.add_argument("--frame", type=int, default=0)
  show.add_argument("--out", default="frame.png")
  show.set_defaults(func=main)
  bench = subparsers.add_parser("bench", help="time rendering with and without the camera model")
  _add_synthetic_args(bench)
  bench.set_defaults(func=main)


def run(argv=None) -> int:
  """`python -m jaxfusion.datasets`: parses `argv` and runs the command."""
  parser = argparse.ArgumentParser(prog="python -m jaxfusion.datasets",
                                   description="The embedded synthetic world and its sequences.")
  add_parser(parser.add_subparsers(dest="command", required=True))
  args = parser.parse_args(argv)
  try:
    return main(args)
  except ValueError as e:
    parser.error(str(e))


def main(args: argparse.Namespace) -> int:
  """Runs the parsed command; returns the exit status."""
  if args.command == "list":
    for env, t in synthetic.list_sequences():
      print(f"{env}\t{t}\t{synthetic.trajectories.TRAJECTORY_NAMES[t]}")
    return 0
  if args.command == "show":
    seq = RGBDSequence.load(args.path)
    preview.render_preview(seq[args.frame], args.out, class_colors=palette(seq.class_names))
    print(f"wrote {args.out} (frame {args.frame} of {seq!r})")
    return 0
  sensing = SensingConfig.off() if getattr(args, "no_sensing", False) else SensingConfig()
  seed = flags.one_layout_seed(args)
  if args.command == "bench":
    for name, config in (("sensing off", SensingConfig.off()), ("sensing on", SensingConfig())):
      kwargs = dict(domain=args.domain, num_frames=args.num_frames, height=args.height,
                    width=args.width, seed=seed, shift=args.shift, sensing=config)
      synthetic.make_sequence(args.env, args.trajectory, **kwargs)  # compile
      wall, cpu = time.perf_counter(), time.process_time()
      synthetic.make_sequence(args.env, args.trajectory, **kwargs)
      wall = 1e3 * (time.perf_counter() - wall) / args.num_frames
      cpu = 1e3 * (time.process_time() - cpu) / args.num_frames
      print(f"{name}: {wall:.1f} ms/frame wall, {cpu:.1f} ms/frame CPU (all threads) "
            f"({args.env} trajectory {args.trajectory}, {args.num_frames} frames at "
            f"{args.width}x{args.height})", flush=True)
    seq = synthetic.make_sequence(args.env, args.trajectory, **kwargs)
    blur = camera_effects(seq, SensingConfig())
    print("per frame, median over pixels (and over frames: median / 90th percentile): "
          + ", ".join(f"{k} {np.median(v):.2f} / {np.percentile(v, 90):.2f}"
                      for k, v in blur.items()), flush=True)
    return 0
  if args.command == "render":
    if not 0 <= args.frame < args.num_frames:
      raise ValueError(f"--frame must lie in [0, {args.num_frames})")
    world = synthetic.make_scene(args.env, seed=seed, domain=args.domain, shift=args.shift)
    pose = synthetic.trajectories.trajectory(world.layout.room, args.trajectory,
                                             args.num_frames)[args.frame]
    frame = synthetic.render(world, pose, synthetic.default_camera(args.height, args.width),
                             height=args.height, width=args.width, realism=not args.no_realism,
                             sensing=sensing)
    preview.render_preview(frame, args.out)
    print(f"wrote {args.out} ({args.env} trajectory {args.trajectory} frame {args.frame}, "
          f"{args.domain} domain, {args.width}x{args.height})")
    return 0
  return _save(args, seed, sensing)


def _save(args: argparse.Namespace, seed: int, sensing: SensingConfig) -> int:
  """`save`: renders the sequence and writes it in the chosen layout."""
  fmt = args.format
  if args.color_size is not None and fmt != "scannet":
    raise ValueError("--color-size is for --format scannet")
  if args.overwrite and fmt == "saved":
    raise ValueError("--overwrite is for --format scannet | tum (a saved folder is rewritten "
                     "in place)")
  if fmt != "saved":   # refuse a bad target before rendering
    export.check_target(args.out, fmt, overwrite=args.overwrite)
  height = SAVE_SIZES[fmt][0] if args.height is None else args.height
  width = SAVE_SIZES[fmt][1] if args.width is None else args.width
  seq = synthetic.make_sequence(args.env, args.trajectory, domain=args.domain,
                                num_frames=args.num_frames, height=height, width=width,
                                seed=seed, shift=args.shift, realism=not args.no_realism,
                                sensing=sensing)
  if fmt == "saved":
    seq.save(args.out)
    print(f"saved {seq!r} to {args.out}")
  elif fmt == "scannet":
    color_size = export.SCANNET_COLOR_SIZE if args.color_size is None else args.color_size
    mesh = export.embedded_labelled_mesh(args.env, seed, args.shift, domain=args.domain)
    export.save_scannet(seq, args.out, color_size=color_size, labelled_mesh=mesh,
                        overwrite=args.overwrite)
    name = os.path.basename(os.path.abspath(args.out)) + export.LABELS_PLY_SUFFIX
    print(f"wrote {seq!r} to {args.out} in ScanNet's layout: {len(seq)} frames, colour "
          f"{color_size[1]}x{color_size[0]}, depth {width}x{height}, NYU40 labels, mesh {name} "
          f"({len(mesh['vertices'])} vertices); read it with --data scannet:{args.out} "
          "--label-space embedded")
  else:
    export.save_tum(seq, args.out, overwrite=args.overwrite)
    c = seq.camera
    print(f"wrote {seq!r} to {args.out} in TUM RGB-D's layout: {len(seq)} frames at "
          f"{width}x{height}, no labels")
    print(f"camera: fx={c.fx!r} fy={c.fy!r} cx={c.cx!r} cy={c.cy!r} (in its calibration.txt, "
          f"which load_tum reads; elsewhere pass camera=Camera({c.fx!r}, {c.fy!r}, {c.cx!r}, "
          f"{c.cy!r}))")
  return 0


if __name__ == "__main__":
  sys.exit(run())
