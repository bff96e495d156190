"""The viewer as a person sees it: the page opened in headless Chromium (software WebGL), with
screenshots checked for the map's class colours and for a colour-mode switch.

Needs the `chromium` executable; without it these tests skip, except where
JAXFUSION_REQUIRE_BROWSER=1 (set by .ci/run, which installs chromium), where they fail.
"""

import os
import threading
import time

import numpy as np
import pytest

pytest.importorskip("viser")

from jaxfusion import datasets   # noqa: E402
from jaxfusion.datasets.classes import CHAIR, PLANT, TV   # noqa: E402
from jaxfusion.lab.viewer import browser   # noqa: E402
from jaxfusion.lab.viewer import scene_data as sd   # noqa: E402
from jaxfusion.lab.viewer import server   # noqa: E402
from tests.lab.test_viewer_server import GEOMETRY, save_floor_maps   # noqa: E402

# End-to-end: a headless browser opens the served page. The slow tier.
pytestmark = pytest.mark.slow

WIDTH, HEIGHT = 1280, 800
COLORS = np.asarray(datasets.CLASS_COLORS, np.int64)
SHOWN = (0, 2, 4, 6)         # background, chair, plant, TV: the stripes of the floor map
ABSENT = (1, 3, 5)           # bottle, table, sofa
ENOUGH = 40                  # pixels of a colour for it to count as on the picture


def _open(tmp_path_factory, geometry=None, *, mesh=True, **viewer_options):
  """`(viewer, page, shots folder)` of the floor maps (with a geometry layer if given; loaded
  without their meshes unless `mesh`), the viewer made with `viewer_options`."""
  if browser.find_chromium() is None:
    reason = "chromium is not installed (apt-get install chromium; .ci/run installs it)"
    if os.environ.get("JAXFUSION_REQUIRE_BROWSER") == "1":
      pytest.fail(reason)
    pytest.skip(reason)
  maps = sd.load_maps(save_floor_maps(tmp_path_factory.mktemp("maps"), geometry=geometry),
                      mesh=mesh)
  viewer = server.MapViewer(maps, port=0, **viewer_options)
  try:
    page = browser.HeadlessPage(viewer.url, width=WIDTH, height=HEIGHT)
  except BaseException:
    viewer.stop()
    raise
  return viewer, page, tmp_path_factory.mktemp("shots")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
  viewer, page, shots = _open(tmp_path_factory)
  yield viewer, page, shots
  page.close()
  viewer.stop()


@pytest.fixture(scope="module")
def mesh_session(tmp_path_factory):
  """The floor maps with a geometry layer: the viewer opens on their mesh."""
  viewer, page, shots = _open(tmp_path_factory, geometry=GEOMETRY)
  yield viewer, page, shots
  page.close()
  viewer.stop()


def _scene(image):
  """The part of the page where only the 3-D scene is drawn (no GUI panel, no axes gizmo)."""
  return image[:HEIGHT - 120, 120:WIDTH - 400].reshape(-1, 3).astype(np.int64)


def _count(pixels, color, tol=3):
  return int(np.sum(np.max(np.abs(pixels - np.asarray(color)), axis=1) <= tol))


def _show(viewer, **values):
  for name, value in values.items():
    viewer.controls[name].value = value


def _wait(page, check, path, timeout=60):
  """Screenshots until `check(pixels)` returns "" (else it returns what is wrong)."""
  try:
    image = page.wait_for(lambda im: not check(_scene(im)), timeout=timeout)
  except TimeoutError:
    image = page.screenshot()
    browser_log = page.log_tail(500)
  else:
    browser_log = ""
  import cv2
  cv2.imwrite(str(path), image[:, :, ::-1])
  problem = check(_scene(image))
  assert not problem, f"{problem} (screenshot: {path}) {browser_log}"
  return image


def _class_colours_problem(pixels):
  shown = {datasets.CLASS_NAMES[k]: _count(pixels, COLORS[k]) for k in SHOWN}
  absent = {datasets.CLASS_NAMES[k]: _count(pixels, COLORS[k]) for k in ABSENT}
  if min(shown.values()) < ENOUGH or max(absent.values()) > 5:
    return f"class colours on the picture: map's {shown}, others {absent}"
  return ""


def test_page_shows_the_class_colours_of_the_map(session):
  viewer, page, shots = session
  _show(viewer, color="class", draw="points")   # points are drawn unlit: exact colours
  _wait(page, _class_colours_problem, shots / "class_points.png")


def test_switching_the_colour_mode_changes_the_picture(session):
  viewer, page, shots = session
  _show(viewer, color="class", draw="points")
  before = _scene(_wait(page, _class_colours_problem, shots / "before.png"))
  viewer.controls["color"].value = "entropy"
  m = viewer.current_map()
  expected = sd.voxel_colors(m, "entropy", None)
  colours, counts = np.unique(expected, axis=0, return_counts=True)
  main = colours[np.argmax(counts)]   # the entropy colour of most voxels

  def problem(pixels):
    red = _count(pixels, COLORS[CHAIR])
    if _count(pixels, main) < ENOUGH or red > 5:
      return (f"after switching to entropy: {_count(pixels, main)} pixels of its colour "
              f"{main.tolist()}, {red} chair-red pixels")
    return ""

  after = _scene(_wait(page, problem, shots / "entropy.png"))
  changed = np.any(before != after, axis=1).mean()
  assert changed > 0.01, f"only {changed:.2%} of the scene's pixels changed"


def _hue(rgb):
  import colorsys
  return np.array([colorsys.rgb_to_hsv(*(c / 255.0))[0] * 360 for c in rgb])


HUED = {CHAIR: 0.0, PLANT: 120.0, TV: 240.0}   # the stripes' classes of pure hue


def _lit_class_hues_problem(what):
  """A check that the picture has lit (not exactly palette-coloured) pixels of each of the
  chair, plant and TV hues, as lit, tone-mapped surfaces of those classes give."""

  def problem(pixels):
    saturated = pixels[(pixels.max(1) - pixels.min(1)) >= 40]
    if len(saturated) == 0:
      return f"no coloured {what} on the picture"
    hue = _hue(saturated)
    ref = np.array(list(HUED.values()))
    nearest = np.argmin(np.abs((hue[:, None] - ref[None] + 180) % 360 - 180), axis=1)
    counts = np.bincount(nearest, minlength=len(ref))
    exact_red = _count(pixels, COLORS[CHAIR])
    if counts.min() < ENOUGH or exact_red > counts[0] / 2:
      return (f"{what} hues near chair/plant/TV: {counts.tolist()}; exactly chair-red "
              f"(unlit) pixels: {exact_red}")
    return ""

  return problem


def test_cubes_keep_the_class_hues(session):
  viewer, page, shots = session
  _show(viewer, color="class", draw="cubes")   # lit and tone-mapped: compare hues
  np.testing.assert_allclose(_hue(COLORS[list(HUED)]), list(HUED.values()), atol=1.0)
  _wait(page, _lit_class_hues_problem("cube"), shots / "class_cubes.png")
  assert viewer.last_drawn["kind"] == "cubes"


def _lit_colours(pixels):
  """`{class: (r, g, b)}`: the most common colour among pixels of each of the HUED hues."""
  saturated = pixels[(pixels.max(1) - pixels.min(1)) >= 40]
  hue = _hue(saturated)
  out = {}
  for k, ref in HUED.items():
    near = saturated[np.abs((hue - ref + 180) % 360 - 180) < 20]
    colours, counts = np.unique(near, axis=0, return_counts=True)
    out[k] = colours[np.argmax(counts)]
  return out


def test_page_shows_the_mesh_and_switches_to_the_voxels(mesh_session):
  viewer, page, shots = mesh_session
  m = viewer.current_map()
  assert viewer.controls["show"].value == "mesh"   # a map with a mesh opens on it
  assert viewer.last_drawn["mesh"] == m.mesh.num_faces and viewer.last_drawn["count"] == 0
  # The lit mesh, coloured by class, has the hues of the floor's stripes ...
  mesh = _scene(_wait(page, _lit_class_hues_problem("mesh"), shots / "mesh.png"))
  # ... and, facing up under the same lights, the colours of the cubes' tops.
  _show(viewer, show="voxels", draw="cubes")
  assert viewer.last_drawn["mesh"] == 0 and viewer.last_drawn["kind"] == "cubes"
  cubes = _scene(_wait(page, _lit_class_hues_problem("cube"), shots / "mesh_to_cubes.png"))
  on_mesh = {datasets.CLASS_NAMES[k]: _count(mesh, c, tol=6)
             for k, c in _lit_colours(cubes).items()}
  assert min(on_mesh.values()) >= ENOUGH, (
      f"pixels of the cubes' lit class colours {_lit_colours(cubes)} on the mesh: {on_mesh}; "
      f"the mesh's own: {_lit_colours(mesh)}")
  # The voxels as (unlit) points: the palette's exact colours, a changed picture.
  _show(viewer, draw="points")
  voxels = _scene(_wait(page, _class_colours_problem, shots / "mesh_to_points.png"))
  changed = np.any(mesh != voxels, axis=1).mean()
  assert changed > 0.05, f"only {changed:.2%} of the scene's pixels changed"
  assert _class_colours_problem(mesh) != ""   # the mesh is lit: not the exact palette


def test_switching_maps_keeps_the_camera(session):
  viewer, page, shots = session
  _show(viewer, color="class", draw="points")
  start = _wait(page, _class_colours_problem, shots / "start.png")
  (client,) = viewer.server.get_clients().values()
  page.drag((560, 420), (700, 380))   # the user turns the view with the mouse

  def silhouette(pixels):
    return np.any(pixels < 245, axis=1)

  def moved(pixels):
    same = np.mean(silhouette(pixels) == silhouette(_scene(start)))
    shown = np.mean(silhouette(pixels))
    return "" if same < 0.97 and shown > 0.02 else (
        f"the view did not move ({same:.1%} of pixels unchanged, {shown:.1%} drawn)")

  before = _scene(_wait(page, moved, shots / "moved.png"))
  position = np.asarray(client.camera.position)
  other = next(name for name in viewer.controls["map"].options
               if name != viewer.controls["map"].value)
  viewer.controls["map"].value = other
  assert viewer.last_drawn["map"] == viewer.current_map().path

  def same_view(pixels):
    same = np.mean(silhouette(pixels) == silhouette(before))
    return "" if same > 0.995 else f"the view changed with the map ({same:.1%} of pixels same)"

  _wait(page, same_view, shots / "switched.png")
  np.testing.assert_allclose(client.camera.position, position, atol=1e-3)


def _panel_shows(page, text, timeout=60):
  """Waits until the page's panel shows `text`; returns the panel's text."""
  deadline = time.monotonic() + timeout
  while True:
    panel = page.evaluate("document.body ? document.body.innerText : ''") or ""
    if text in panel:
      return panel
    if time.monotonic() > deadline:
      raise AssertionError(f"the panel did not show {text!r} within {timeout} s: {panel!r}")
    time.sleep(0.2)


def test_page_says_what_it_prepares_and_then_shows_the_mesh(tmp_path_factory, monkeypatch):
  # The mesh's first stage waits for the test, so that the page can be seen meanwhile.
  gate, prepare_mesh = threading.Event(), sd.prepare_mesh

  def gated(m, *, progress=None):
    def say(line):
      progress(line)
      if line.startswith("marching cubes"):
        gate.wait(120)
    return prepare_mesh(m, progress=say)

  monkeypatch.setattr(sd, "prepare_mesh", gated)
  viewer, page, shots = _open(tmp_path_factory, geometry=GEOMETRY, mesh=False,
                              preview_voxels=300, prepare=False)
  try:
    m = viewer.current_map()
    assert viewer.last_drawn["preview"] > 0 and viewer.last_drawn["mesh"] == 0
    viewer.prepare_meshes()
    # The progress line in the panel, and the coarse preview's cubes in the class hues.
    panel = _panel_shows(page, "preparing mesh: marching cubes on")
    assert "mesh: being prepared; meanwhile" in panel
    preview = _scene(_wait(page, _lit_class_hues_problem("preview cube"),
                           shots / "preparing.png"))
    gate.set()
    assert viewer.ready.wait(120)
    faces = viewer.current_map().mesh.num_faces
    assert viewer.last_drawn["mesh"] == faces and "preview" not in viewer.last_drawn
    panel = _panel_shows(page, "ready: 2 mesh(es) prepared in")
    assert f"mesh: {faces} of {faces} faces" in panel and "being prepared" not in panel
    # The lit mesh replaced the cubes: the stripes' hues, on another picture.
    def mesh_problem(pixels):
      changed = np.any(pixels != preview, axis=1).mean()
      return _lit_class_hues_problem("mesh")(pixels) or (
          "" if changed > 0.05 else f"only {changed:.2%} of the preview's pixels changed")

    _wait(page, mesh_problem, shots / "ready.png")
    assert m.mesh is None and viewer.current_map().mesh is not None
  finally:
    gate.set()
    page.close()
    viewer.stop()
