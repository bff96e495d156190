"""The web viewer of saved maps, built on viser (the optional `viewer` extra).

`MapViewer` serves one page: the voxels of the chosen map as cubes (points beyond
`max_cubes`), a colour mode with its legend, toggles to hide classes, a height cut, and the
camera trajectory as frustums. Switching maps replaces the voxels only, so the camera stays
where the user left it. What is drawn is computed by `scene_data`; this module only shows it.
"""

import signal
import threading
import time
from typing import Optional, Sequence

import numpy as np
import viser
import viser.transforms as vtf

from jaxfusion.lab.viewer import scene_data as sd

_UP_AXIS = 2   # jaxfusion's worlds are z-up
_BOX_VERTICES = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5)
                          for z in (-0.5, 0.5)], np.float32)
# 12 outward-facing triangles of the unit cube over _BOX_VERTICES (index = 4x + 2y + z).
_BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
                      np.uint32)


class MapViewer:
  """A running viewer of maps (of one or more sequences) with the same class list.

  Attributes:
    server: the `viser.ViserServer`.
    controls: the GUI handles by role — "sequence", "map", "color", "draw" (dropdowns), "height"
      (slider), "trajectory" (checkbox) and "hide" (class name → checkbox). Setting a
      handle's `value` from Python redraws the scene as a click in the page does.
  """

  def __init__(self, maps: Sequence[sd.ViewMap], *, host: str = "127.0.0.1", port: int = 8080,
               max_cubes: int = sd.DEFAULT_MAX_CUBES, max_frustums: int = 40,
               verbose: bool = False):
    if not maps:
      raise ValueError("MapViewer needs at least one map")
    sd.check_same_classes(maps)
    if max_cubes < 0:
      raise ValueError(f"max_cubes must be ≥ 0; got {max_cubes}")
    self._maps = sd.by_sequence(maps)
    self._all = list(maps)
    self._palette = sd.class_palette(maps[0].class_names)
    self._max_cubes = int(max_cubes)
    self._max_frustums = int(max_frustums)
    self._lock = threading.RLock()
    self._trajectory_of = None   # path of the map whose trajectory is drawn
    self._trajectory_root = None
    self.last_drawn = {}
    self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
    scene = self.server.scene
    scene.set_up_direction("+z")
    scene.configure_environment_map(hdri=None)
    scene.configure_default_lights(enabled=False)
    # Soft light from above one corner: faces stay distinguishable, colours near the palette.
    scene.add_light_ambient("/light/ambient", intensity=0.55)
    scene.add_light_directional("/light/sun", intensity=0.9, position=(-1.0, -2.0, 3.0),
                                cast_shadow=False)
    position, look_at = sd.initial_camera(self._all, _UP_AXIS)
    self.server.initial_camera.position = tuple(float(x) for x in position)
    self.server.initial_camera.look_at = tuple(float(x) for x in look_at)
    self.server.initial_camera.up = (0.0, 0.0, 1.0)
    self._build_gui()
    self.redraw()

  @property
  def url(self) -> str:
    return f"http://{self.server.get_host()}:{self.server.get_port()}"

  def current_map(self) -> sd.ViewMap:
    return self._maps[self.controls["sequence"].value][self.controls["map"].value]

  def _build_gui(self):
    gui = self.server.gui
    sequences = list(self._maps)
    first = self._maps[sequences[0]]
    c = {}
    gui.add_markdown(f"**jaxfusion** · {len(self._all)} map(s)")
    c["sequence"] = gui.add_dropdown("Sequence", sequences, initial_value=sequences[0],
                                     visible=len(sequences) > 1)
    c["map"] = gui.add_dropdown("Map", list(first), initial_value=next(iter(first)))
    modes = sd.color_modes(first[next(iter(first))])
    c["color"] = gui.add_dropdown("Colour by", [sd.COLOR_MODES[m] for m in modes],
                                  initial_value=sd.COLOR_MODES["class"])
    c["draw"] = gui.add_dropdown("Draw as", list(sd.DRAW_CHOICES), initial_value="auto",
                                 hint=f"auto: cubes up to {self._max_cubes} voxels, then points")
    self._legend = gui.add_html("")
    self._status = gui.add_markdown("")
    lo, hi = sd.height_range(self._all, _UP_AXIS)
    step = min(m.voxel_size for m in self._all)
    self._height_max = hi + step
    c["height"] = gui.add_slider("Height cut (m)", min=float(np.floor(lo / step) * step),
                                 max=float(self._height_max), step=float(step),
                                 initial_value=float(self._height_max))
    c["trajectory"] = gui.add_checkbox("Camera trajectory", initial_value=True,
                                       visible=any(m.poses is not None for m in self._all))
    c["hide"] = {}
    with gui.add_folder("Hide classes", expand_by_default=False):
      for name in first[next(iter(first))].class_names:
        c["hide"][name] = gui.add_checkbox(name, initial_value=False)
    self.controls = c

    c["sequence"].on_update(lambda _: self._sequence_changed())
    c["map"].on_update(lambda _: self._map_changed())
    for handle in [c["color"], c["draw"], c["height"], c["trajectory"], *c["hide"].values()]:
      handle.on_update(lambda _: self.redraw())

  def _sequence_changed(self):
    with self._lock:
      names = list(self._maps[self.controls["sequence"].value])
      if self.controls["map"].value in names:
        self.controls["map"].options = names
        self._map_changed()
      else:
        self.controls["map"].options = names   # moves the value, which calls _map_changed

  def _map_changed(self):
    with self._lock:
      modes = [sd.COLOR_MODES[m] for m in sd.color_modes(self.current_map())]
      if self.controls["color"].value in modes:
        self.controls["color"].options = modes
        self.redraw()
      else:
        self.controls["color"].options = modes   # falls back to "class" and redraws

  def _mode(self, m: sd.ViewMap) -> str:
    title = self.controls["color"].value
    mode = next(k for k, v in sd.COLOR_MODES.items() if v == title)
    return mode if mode in sd.color_modes(m) else "class"

  def redraw(self):
    """Draws the current map with the current colour mode, classes and height cut."""
    with self._lock:
      m = self.current_map()
      mode = self._mode(m)
      hidden = [i for i, box in enumerate(self.controls["hide"].values()) if box.value]
      cut = float(self.controls["height"].value)
      keep = sd.visible_mask(m, hidden_classes=hidden,
                             max_height=None if cut >= self._height_max else cut,
                             up_axis=_UP_AXIS)
      colors = sd.voxel_colors(m, mode, self._palette)[keep]
      centers = m.centers[keep]
      kind = sd.representation(len(centers), self._max_cubes, self.controls["draw"].value)
      scene = self.server.scene
      if len(centers) == 0:
        scene.remove_by_name("/voxels")
      elif kind == "cubes":
        scene.add_batched_meshes_simple(
            "/voxels", _BOX_VERTICES * m.voxel_size, _BOX_FACES,
            batched_wxyzs=np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0], np.float32),
                                          (len(centers), 4)),
            batched_positions=centers, batched_colors=colors, flat_shading=True, lod="off",
            cast_shadow=False, receive_shadow=False)
      else:
        scene.add_point_cloud("/voxels", centers, colors, point_size=m.voxel_size,
                              point_shape="square", point_shading="flat", precision="float32")
      self._legend.content = sd.legend_html(sd.legend(m, mode, self._palette))
      self._status.content = (f"{len(centers)} of {len(m)} voxels ({m.voxel_size:g} m), "
                              f"drawn as {kind}")
      self._draw_trajectory(m)
      self.last_drawn = {"map": m.path, "mode": mode, "kind": kind, "count": int(len(centers))}

  def _draw_trajectory(self, m: sd.ViewMap):
    """Frustums along the map's saved camera path, under one node the checkbox hides."""
    show = bool(self.controls["trajectory"].value)
    scene = self.server.scene
    if self._trajectory_of != m.path:
      self._trajectory_of = m.path
      if self._trajectory_root is not None:
        self._trajectory_root.remove()
        self._trajectory_root = None
      if m.poses is None:
        return
      poses = m.poses
      extent = float(np.linalg.norm(np.ptp(m.centers, axis=0))) if len(m) else 1.0
      fov, aspect = sd.frustum_shape(m.camera)
      self._trajectory_root = scene.add_frame("/trajectory", show_axes=False, visible=show)
      for i in sd.frustum_indices(len(poses), self._max_frustums):
        scene.add_camera_frustum(
            f"/trajectory/frame_{int(i):04d}", fov=fov, aspect=aspect,
            scale=max(0.02 * extent, 2 * m.voxel_size), color=(40, 40, 40),
            wxyz=vtf.SO3.from_matrix(poses[i, :3, :3].astype(np.float64)).wxyz,
            position=poses[i, :3, 3].astype(np.float64))
      if len(poses) > 1:
        path = poses[:, :3, 3]
        scene.add_line_segments("/trajectory/path", np.stack([path[:-1], path[1:]], axis=1),
                                (230, 120, 20), thickness=max(0.004 * extent, 0.005))
    if self._trajectory_root is not None:
      self._trajectory_root.visible = show

  def stop(self):
    self.server.stop()


def serve(paths: Sequence[str], *, host: str = "127.0.0.1", port: int = 8080,
          max_cubes: int = sd.DEFAULT_MAX_CUBES, duration: Optional[float] = None) -> None:
  """Loads the maps named by `paths`, serves them, and blocks until Ctrl-C (or `duration` s).

  Raises:
    FileNotFoundError / ValueError: a bad path, a file that is not a map, maps of different
      class lists (see `scene_data.load_maps`).
  """
  maps = sd.load_maps(paths)
  viewer = MapViewer(maps, host=host, port=port, max_cubes=max_cubes)
  sequences = len({m.sequence for m in maps})
  print(f"viewing {len(maps)} map(s) of {sequences} sequence(s) at {viewer.url}  "
        "(Ctrl-C stops)", flush=True)
  start = time.monotonic()
  # A process started with SIGINT ignored (a background job of a non-interactive shell, or a
  # parent that ignores it) inherits that, and Python then installs no KeyboardInterrupt
  # handler: Ctrl-C / `kill -INT` would be lost and the server would run forever. The viewer
  # promises that Ctrl-C stops it, so it takes SIGINT for as long as it serves.
  previous = None
  if threading.current_thread() is threading.main_thread():
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
  try:
    while duration is None or time.monotonic() - start < duration:
      time.sleep(0.2)
  except KeyboardInterrupt:
    pass
  finally:
    viewer.stop()
    if previous is not None:
      signal.signal(signal.SIGINT, previous)
  print("viewer stopped", flush=True)
