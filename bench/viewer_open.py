"""`python -m bench.viewer_open [--quick]`: how long the viewer takes to show a building-sized map.

A camera walks down a 60 m corridor (4.5 m wide, 3.7 m high, cabinets, sofas, plants and screens
along its walls, depth ray-cast exactly, 5 m sensor range), fused through a growing `Mapper`
with 10 cm semantic voxels and a 5 cm geometry layer, and saved as `jaxfusion run` saves a map.
Then, on that file:

1. the stages of preparing its mesh, timed one by one in a fresh process (load, marching
   cubes, labelling, the preview, colouring, the GLB): cold, as a new `jaxfusion view` pays
   them (compilation included), and warm;
2. `jaxfusion view FILE` started as a user starts it, and the page opened in headless Chromium
   (software WebGL) as soon as the command prints its address: the time from the command's
   start and from the page's opening to the first picture of the map (the first frame WebGL
   draws it in: ≥ 10 000 mesh triangles or points, or ≥ 1 000 cubes, counted by wrapping
   WebGL's draw calls) and to the full mesh (the first frame that draws all its faces), with
   the progress lines the command printed and the panel showed on the way; then the same for
   a second page opened once the first shows the mesh.

`--label NAME` names the run in `bench/results/viewer_open.json` (the runs there under other
names are kept, so that a run of an older viewer — the same script run from a checkout of it
— sits beside it) and prints a table of all of them.
"""

import argparse
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

import jaxfusion as jf
from jaxfusion import io
from jaxfusion.datasets import classes

# The corridor: x along it, y across, z up (metres).
LENGTH, WIDTH, HEIGHT = 60.0, 4.5, 3.7
RANGE = 5.0   # the sensor's range: farther depths are holes
K = len(classes.CLASS_NAMES)


def corridor_boxes(seed: int = 0) -> tuple:
  """`(lo (M, 3), hi (M, 3), labels (M,))`: the furniture along both walls."""
  rng = np.random.default_rng(seed)
  lo, hi, labels = [], [], []
  x = 1.0
  while x < LENGTH - 2.0:
    side = rng.integers(2)
    kind = rng.choice([classes.TABLE, classes.SOFA, classes.PLANT, classes.TV])
    length = {classes.TABLE: 1.2, classes.SOFA: 2.0, classes.PLANT: 0.5, classes.TV: 1.0}[kind]
    depth = {classes.TABLE: 0.6, classes.SOFA: 0.8, classes.PLANT: 0.5, classes.TV: 0.08}[kind]
    z0, z1 = {classes.TABLE: (0.0, 0.9), classes.SOFA: (0.0, 0.8), classes.PLANT: (0.0, 1.3),
              classes.TV: (1.1, 1.8)}[kind]
    y0, y1 = (-WIDTH / 2, -WIDTH / 2 + depth) if side == 0 else (WIDTH / 2 - depth, WIDTH / 2)
    lo.append((x, y0, z0))
    hi.append((x + length, y1, z1))
    labels.append(kind)
    x += length + rng.uniform(0.3, 1.2)
  return np.array(lo, np.float64), np.array(hi, np.float64), np.array(labels, np.int32)


def _look(position: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
  """Camera-to-world pose (OpenCV axes: x right, y down, z forward) at `position`, looking
  `yaw` radians left of +x and `pitch` radians up."""
  forward = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
  right = np.cross(forward, [0.0, 0.0, 1.0])
  right /= np.linalg.norm(right)
  down = np.cross(forward, right)
  T = np.eye(4)
  T[:3, :3] = np.stack([right, down, forward], axis=1)
  T[:3, 3] = position
  return T


def ray_cast(T_world_cam: np.ndarray, camera: jf.Camera, size: tuple, boxes: tuple) -> tuple:
  """`(depth (H, W) float32, labels (H, W) int32)` of the corridor seen from `T_world_cam`
  (depth 0 beyond `RANGE`)."""
  h, w = size
  v, u = np.mgrid[0:h, 0:w].astype(np.float64)
  rays_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy,
                       np.ones_like(u)], axis=-1).reshape(-1, 3)
  d = rays_cam @ T_world_cam[:3, :3].T          # z-depth t: point = o + t d
  o = T_world_cam[:3, 3]
  inside_lo = np.array([0.0, -WIDTH / 2, 0.0])
  inside_hi = np.array([LENGTH, WIDTH / 2, HEIGHT])
  with np.errstate(divide="ignore", invalid="ignore"):
    exit_t = np.where(d > 0, (inside_hi - o) / d, np.where(d < 0, (inside_lo - o) / d, np.inf))
  depth = exit_t.min(axis=1)
  labels = np.full(len(d), classes.BACKGROUND, np.int32)
  lo, hi, box_labels = boxes
  with np.errstate(divide="ignore", invalid="ignore"):
    t0 = (lo[None] - o) / d[:, None]
    t1 = (hi[None] - o) / d[:, None]
  near = np.nanmax(np.minimum(t0, t1), axis=2)
  far = np.nanmin(np.maximum(t0, t1), axis=2)
  hit = (near <= far) & (near > 0)
  near = np.where(hit, near, np.inf)
  first = near.argmin(axis=1)
  t_box = near[np.arange(len(d)), first]
  closer = t_box < depth
  depth = np.where(closer, t_box, depth)
  labels[closer] = box_labels[first[closer]]
  depth[depth > RANGE] = 0.0
  return depth.reshape(h, w).astype(np.float32), labels.reshape(h, w)


def corridor_walk(num_frames: int, size: tuple, seed: int = 0):
  """The frames of the walk: poses from one end to the other, looking left and right."""
  h, w = size
  camera = jf.Camera(0.6 * w, 0.6 * w, (w - 1) / 2, (h - 1) / 2)
  boxes = corridor_boxes(seed)
  rng = np.random.default_rng(seed + 1)
  poses, depths, labels = [], [], []
  for t in range(num_frames):
    s = t / max(num_frames - 1, 1)
    x = 0.3 + s * (LENGTH - 0.6)
    yaw = 1.1 * np.sin(2 * np.pi * t / 24)
    pitch = 0.35 * np.sin(2 * np.pi * t / 17)
    T = _look(np.array([x, 0.3 * np.sin(t / 9), 1.5]), yaw, pitch)
    depth, label = ray_cast(T, camera, size, boxes)
    noise = rng.normal(0.0, 0.005, depth.shape).astype(np.float32)
    depths.append(np.where(depth > 0, depth + noise, 0.0))
    poses.append(T.astype(np.float32))
    labels.append(label)
  return camera, np.stack(poses), np.stack(depths), np.stack(labels)


def make_map(path: str, *, num_frames: int, size: tuple, chunk: int = 50) -> dict:
  """Fuses the corridor walk into a growing Mapper and saves it at `path`; returns its sizes."""
  import jax
  start = time.perf_counter()
  camera, poses, depths, labels = corridor_walk(num_frames, size)
  rule = jf.rules.robust()
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.1, capacity=2**14,
                     geometry=jf.TSDFConfig(voxel_size=0.05, capacity=2**10))
  rng = np.random.default_rng(2)
  for s in range(0, num_frames, chunk):
    lab = labels[s:s + chunk]
    probs = 0.3 / K + 0.7 * np.eye(K, dtype=np.float32)[lab]
    probs = probs * rng.uniform(0.8, 1.2, probs.shape).astype(np.float32)
    probs /= probs.sum(-1, keepdims=True)
    var = np.full(probs.shape, 0.01, np.float32)
    frames = jf.Frame(depths[s:s + chunk], poses[s:s + chunk], probs.astype(np.float32), var)
    mapper.fuse_sequence(frames, camera)
  jax.block_until_ready(mapper.state)
  state = mapper.state
  io.save_map(path, state, rule, class_names=classes.CLASS_NAMES,
              extra={"sequence": "corridor"}, poses=poses, camera=camera, image_size=size)
  return {"frames": num_frames, "image": list(size), "voxels": int(state.num_occupied),
          "geometry_blocks": int(state.geometry.num_blocks),
          "file_mb": os.path.getsize(path) / 2**20,
          "make_s": time.perf_counter() - start}


# Counts what WebGL draws in each animation frame: the page's own record of what it shows.
# `self.__jfFrames` holds `[epoch ms, triangles, instanced triangles, points, boxes]` each time
# a frame's counts change. A GLB mesh is drawn as plain triangles; cubes are instances of a
# 12-triangle box (counted in both instanced triangles and boxes).
_COUNT_DRAWN = """
(() => {
  const POINTS = 0, TRIANGLES = 4, STRIP = 5, FAN = 6;
  let current = [0, 0, 0, 0], last = "";
  self.__jfFrames = [];
  const triangles = (mode, count) => mode === TRIANGLES ? count / 3
      : (mode === STRIP || mode === FAN) ? Math.max(count - 2, 0) : 0;
  for (const C of [self.WebGLRenderingContext, self.WebGL2RenderingContext]) {
    if (!C) continue;
    const p = C.prototype;
    for (const [name, instanced] of [["drawElements", false], ["drawArrays", false],
                                     ["drawElementsInstanced", true],
                                     ["drawArraysInstanced", true]]) {
      const original = p[name];
      if (!original) continue;
      p[name] = function (...args) {
        const mode = args[0];
        const count = name.startsWith("drawElements") ? args[1] : args[2];
        const instances = instanced ? args[args.length - 1] : 1;
        if (mode === POINTS) current[2] += count * instances;
        else current[instanced ? 1 : 0] += triangles(mode, count) * instances;
        if (instanced && mode === TRIANGLES && count === 36) current[3] += instances;
        return original.apply(this, args);
      };
    }
  }
  const raf = self.requestAnimationFrame.bind(self);
  let frameTime = null;
  self.requestAnimationFrame = (callback) => raf((t) => {
    if (t !== frameTime) {   // a new frame: the one before is complete
      const key = current.join(",");
      if (frameTime !== null && key !== last) {
        self.__jfFrames.push([Date.now(), ...current]);
        last = key;
      }
      frameTime = t;
      current = [0, 0, 0, 0];
    }
    return callback(t);
  });
})();
"""
# A frame shows the map when it draws at least this many mesh triangles or points, or
# PICTURE_BOXES cubes. The page without the map draws < 2 000 plain triangles and no cubes
# (the corridor's camera trajectory: ~11 500 instanced triangles of lines).
PICTURE_COUNT = 10_000
PICTURE_BOXES = 1_000


def _shows_map(frame) -> bool:
  _, triangles, _, points, boxes = frame
  return triangles >= PICTURE_COUNT or points >= PICTURE_COUNT or boxes >= PICTURE_BOXES


_URL = re.compile(r"(http://\S+:\d+)")


def _stages_here(path: str) -> dict:
  """Seconds of each stage of preparing the map's mesh in this process: `{"cold": …,
  "warm": …}`, cold as a fresh `jaxfusion view` pays them (compilation included), warm the
  same calls again."""
  from jaxfusion import mesh as mesh_lib   # pylint: disable=import-outside-toplevel
  from jaxfusion.lab.viewer import scene_data as sd   # pylint: disable=import-outside-toplevel
  out = {"cold": {}, "warm": {}}
  for run in ("cold", "warm"):
    times = out[run]

    def timed(name, fn, times=times):
      begin = time.perf_counter()
      value = fn()
      times[name] = time.perf_counter() - begin
      return value

    state, _, _ = timed("load_map", lambda: io.load_map(path))
    timed("read_map", lambda: jf.read_map(state))
    vertices, faces = timed("marching_cubes", lambda: mesh_lib.marching_cubes(state.geometry))
    normals = timed("vertex_normals", lambda: mesh_lib.vertex_normals(vertices, faces))
    mesh = timed("label_mesh", lambda: mesh_lib.label_mesh(
        mesh_lib.Mesh(vertices, faces, normals), state))
    if hasattr(sd, "coarse_voxels"):   # (the viewer before the preview had none)
      voxels = sd.load_view_map(path, mesh=False)
      timed("coarse_voxels", lambda v=voxels: sd.coarse_voxels(v))
    palette = sd.class_palette(classes.CLASS_NAMES)
    m = sd.ViewMap(path=path, name="", sequence="", class_names=classes.CLASS_NAMES,
                   voxel_size=0.1, centers=np.zeros((0, 3), np.float32),
                   labels=np.zeros(0, np.int32), hits=np.zeros(0, np.int32),
                   entropy=np.zeros(0, np.float32), mesh=mesh)
    colors = timed("mesh_colors", lambda: sd.mesh_colors(m, "class", palette))
    part = timed("mesh_part", lambda: sd.mesh_part(m, sd.mesh_face_mask(m), colors))
    glb = timed("mesh_glb", lambda: sd.mesh_glb(*part))
    out["glb_mb"] = len(glb) / 2**20
    out["faces"] = mesh.num_faces
    out["vertices"] = mesh.num_vertices
  return out


def _stage_times(path: str) -> dict:
  """`_stages_here` in a fresh process (so that "cold" is what a new `jaxfusion view` pays)."""
  done = subprocess.run([sys.executable, "-m", "bench.viewer_open", "--stages-of", path],
                        capture_output=True, text=True, check=True,
                        cwd=pathlib.Path(__file__).parent.parent)
  return json.loads(done.stdout.strip().splitlines()[-1])


def _watch(url: str, faces: int, start: float, timeout: float) -> dict:
  """Opens the page and watches it until it draws the `faces` faces of the full mesh:
  what the panel's progress lines said and what WebGL drew, when (seconds from opening)."""
  from jaxfusion.lab.viewer import browser
  page = browser.HeadlessPage(url, init_scripts=(_COUNT_DRAWN,))
  opened = time.time()
  panel, frames = [], []
  try:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
      text = page.evaluate("document.body ? document.body.innerText : ''") or ""
      status = [line for line in text.splitlines()
                if any(w in line for w in ("loading", "preparing", "sending", "ready",
                                           "mesh:"))]
      if status and (not panel or panel[-1][1] != status):
        panel.append((time.time() - opened, status))
      frames = page.evaluate("self.__jfFrames") or []
      if frames and max(f[1] for f in frames) >= faces:
        break
      time.sleep(0.25)
  finally:
    page.close()
  picture = next((f for f in frames if _shows_map(f)), None)
  mesh = next((f for f in frames if f[1] >= PICTURE_COUNT), None)
  full = next((f for f in frames if f[1] >= faces), None)
  when = lambda f: None if f is None else f[0] / 1e3 - opened
  return {
      "page_opened_s": opened - start,
      "panel": [(round(t, 2), lines) for t, lines in panel],
      "frames": [(round(t / 1e3 - opened, 2), *counts) for t, *counts in frames],
      "first_picture_s": when(picture),
      "first_picture_drawn": None if picture is None else dict(zip(
          ("triangles", "instanced_triangles", "points", "boxes"), picture[1:])),
      "first_mesh_s": when(mesh),
      "first_mesh_triangles": None if mesh is None else mesh[1],
      "full_mesh_s": when(full),
  }


def open_in_browser(path: str, faces: int, *, timeout: float = 300.0) -> dict:
  """Starts `jaxfusion view path`, opens the page when it prints its address, and times the
  first picture and the full mesh of `faces` faces (see the module docstring)."""
  env = dict(os.environ, PYTHONUNBUFFERED="1")
  start = time.time()
  process = subprocess.Popen([sys.executable, "-m", "jaxfusion.lab.cli", "view", path,
                              "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True, env=env)
  lines, url_seen = [], threading.Event()

  def read():
    for line in process.stdout:
      lines.append((time.time() - start, line.rstrip("\n")))
      if _URL.search(line) and "viewing" in line:
        url_seen.set()

  reader = threading.Thread(target=read, daemon=True)
  reader.start()
  result = {"command_lines": lines}
  try:
    if not url_seen.wait(timeout):
      raise TimeoutError(f"`jaxfusion view` printed no address in {timeout} s: {lines}")
    url = next(_URL.search(text).group(1) for _, text in lines if "viewing" in text)
    result["address_printed_s"] = time.time() - start
    result.update(_watch(url, faces, start, timeout))
    # A second page, opened once the first shows the full mesh: the prepared scene is replayed.
    second = _watch(url, faces, start, timeout)
    result["second_page"] = {k: second[k] for k in ("page_opened_s", "first_picture_s",
                                                    "full_mesh_s")}
  finally:
    process.terminate()
    try:
      process.wait(timeout=20)
    except subprocess.TimeoutExpired:
      process.kill()
      process.wait()
    reader.join(timeout=5)
  result["command_lines"] = [(round(t, 2), s) for t, s in lines]
  return result


def _s(x) -> str:
  return "—" if x is None else f"{x:.1f}"


def table(runs: dict) -> str:
  """Markdown tables of the runs in `runs` (`{label: result}`)."""
  first = next(iter(runs.values()))
  m = first["map"]
  lines = [f"map: {m['frames']} frames of {m['image'][0]}×{m['image'][1]} down a "
           f"{LENGTH:g} m corridor; {m['voxels']} semantic voxels (10 cm), "
           f"{m['geometry_blocks']} TSDF blocks (5 cm); mesh {first['stages']['faces']} faces, "
           f"{first['stages']['vertices']} vertices; file {m['file_mb']:.1f} MB"]
  last_label, last = list(runs.items())[-1]
  if "cold" in last["stages"]:
    st = last["stages"]
    lines += ["", f"stages of preparing the mesh ({last_label}), seconds: cold (a fresh process, "
              "compilation included) and warm", "", "| stage | cold | warm |", "|---|---|---|"]
    for key in st["warm"]:
      lines.append(f"| {key} | {st['cold'][key]:.2f} | {st['warm'][key]:.2f} |")
    lines.append(f"| (the mesh's GLB: {st['glb_mb']:.1f} MB) | | |")
  lines += ["", "| `jaxfusion view`, seconds | " + " | ".join(runs) + " |",
            "|---|" + "---|" * len(runs)]
  rows = [("address printed (from start)", lambda b: b["address_printed_s"]),
          ("page opened (from start)", lambda b: b["page_opened_s"]),
          ("first progress line in the panel (from opening)",
           lambda b: next((t for t, s in b["panel"] if any(
               w in x for x in s for w in ("preparing", "sending"))), None)),
          ("first picture (from opening)", lambda b: b["first_picture_s"]),
          ("first picture (from start)",
           lambda b: None if b["first_picture_s"] is None else
           b["first_picture_s"] + b["page_opened_s"]),
          ("first mesh (from opening)", lambda b: b["first_mesh_s"]),
          ("full mesh (from opening)", lambda b: b["full_mesh_s"]),
          ("full mesh (from start)",
           lambda b: None if b["full_mesh_s"] is None else b["full_mesh_s"] + b["page_opened_s"]),
          ("second page: full mesh (from opening)",
           lambda b: b.get("second_page", {}).get("full_mesh_s")),
          ("progress lines on the command line",
           lambda b: float(sum(1 for _, s in b["command_lines"] if "…" in s)))]
  for name, get in rows:
    cells = []
    for r in runs.values():
      value = get(r["browser"])
      cells.append(f"{value:.0f}" if name.startswith("progress") and value is not None
                   else _s(value))
    lines.append(f"| {name} | " + " | ".join(cells) + " |")
  return "\n".join(lines)


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench.viewer_open",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("--quick", action="store_true", help="a small map (80 frames of 60×80)")
  parser.add_argument("--map", help="the map file: used if it exists, else made there "
                                    "(default: a temporary file)")
  parser.add_argument("--label", default="now",
                      help="the name of this run in the JSON (other runs there are kept)")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"))
  parser.add_argument("--stages-of", help=argparse.SUPPRESS)   # internal: _stage_times
  args = parser.parse_args(argv)
  if args.stages_of:
    print(json.dumps(_stages_here(args.stages_of)))
    return
  frames, size = (80, (60, 80)) if args.quick else (600, (120, 160))
  with tempfile.TemporaryDirectory() as tmp:
    path = args.map or os.path.join(tmp, "corridor.npz")
    made = None
    if not os.path.exists(path):
      print(f"making the corridor map ({frames} frames of {size[0]}×{size[1]}) …", flush=True)
      made = make_map(path, num_frames=frames, size=size)
    state, _, _ = io.load_map(path)
    info = {"frames": frames, "image": list(size), "voxels": int(state.num_occupied),
            "geometry_blocks": int(state.geometry.num_blocks),
            "file_mb": os.path.getsize(path) / 2**20}
    if made is not None:
      info.update(made)
    else:
      trajectory = io.load_trajectory(path)
      info["frames"] = len(trajectory["T_world_cam"])
      info["image"] = [trajectory["camera"]["height"], trajectory["camera"]["width"]]
    del state
    print("timing the stages …", flush=True)
    stages = _stage_times(path)
    print("opening the page …", flush=True)
    opened = open_in_browser(path, stages["faces"])
  import jax
  result = {"map": info, "stages": stages, "browser": opened, "cpus": os.cpu_count(),
            "device": jax.devices()[0].device_kind}
  out = pathlib.Path(args.out)
  out.mkdir(parents=True, exist_ok=True)
  file = out / ("viewer_open_quick.json" if args.quick else "viewer_open.json")
  runs = json.loads(file.read_text()) if file.exists() else {}
  runs[args.label] = result
  file.write_text(json.dumps(runs, indent=1, ensure_ascii=False))
  print(table(runs))
  print(f"\nwrote {file}")


if __name__ == "__main__":
  main()
