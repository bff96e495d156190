"""Every reader of a file the project writes or accepts, against damaged and wrong files.

The table crosses readers with corruptions (truncated at several points, one flipped byte,
empty, a PNG, a valid file of another kind, a right file with wrong contents). Each case ends in
a clear `ValueError`/`FileNotFoundError` naming the file, or (a flipped byte the format can
tell is harmless) the very data of the intact file; the front-end cache instead recomputes
after one line. The commands exit 2 with one line. Last, interrupted writes: a writer killed
mid-write, or raising mid-way, never leaves a file that reads back as whole.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap

import cv2
import jax
import numpy as np
import pytest
from flax import serialization

import jaxfusion as jf
import jaxfusion_models as models
from jaxfusion import datasets
from jaxfusion import io
from jaxfusion.lab import cli
from jaxfusion.lab import frontend
from jaxfusion.lab.viewer import scene_data
from models import train
from tests.datasets.test_loaders import write_scannet, write_tum

H, W, K, T = 24, 32, 3, 2
NAMES = ("a", "b", "c")
RECIPE = os.path.join(os.path.dirname(models.PRETRAINED_PATH), "segnet.json")


class FakeFrontEnd:
  """A front end whose outputs are fixed arrays; it counts its calls."""
  model_id = "fake0123456789ab"

  def __init__(self):
    self.calls = 0
    rng = np.random.default_rng(0)
    self.arrays = {k: rng.random((T, H, W, K)).astype(np.float32) for k in ("det", "mean", "var")}

  def predict(self, rgb, *, num_samples, key):
    del rgb, num_samples, key
    self.calls += 1
    return self.arrays["det"], self.arrays["mean"], self.arrays["var"]


class FakeSequence:
  name = "fuzz"
  rgb = np.zeros((T, H, W, 3), np.uint8)

  def __len__(self):
    return T


CACHE_KEY = dict(layout_seed=0, shift=0.0, num_samples=2, mc_seed=0)


def _png_bytes():
  return cv2.imencode(".png", np.full((4, 4, 3), 7, np.uint8))[1].tobytes()


def _rewrite_npz(path, change):
  arrays = io.read_npz(path, what="test file")
  change(arrays)
  with open(path, "wb") as f:
    np.savez(f, **arrays)


@pytest.fixture(scope="module")
def originals(tmp_path_factory):
  """One intact file (or folder) of every kind, in one folder."""
  root = tmp_path_factory.mktemp("originals")
  state = jf.init_map(capacity=64, num_classes=K, voxel_size=0.1, rule=jf.rules.bayes())
  poses = np.tile(np.eye(4, dtype=np.float32), (T, 1, 1))
  io.save_map(str(root / "map.npz"), state, jf.rules.bayes(), class_names=NAMES, poses=poses,
              camera=(20.0, 20.0, 16.0, 12.0), image_size=(H, W))
  np.savez(root / "map_gt.npz", coords=np.zeros((4, 3), np.int32),
           labels=np.arange(4, dtype=np.int32))
  fe = FakeFrontEnd()
  frontend.cached_predictions(fe, FakeSequence(), cache_dir=str(root / "cache"), **CACHE_KEY)
  src = datasets.synthetic.make_sequence("house", 0, num_frames=T, height=H, width=W)
  src.save(str(root / "seq"))
  rng = np.random.default_rng(1)
  for t in range(T):
    jf.sources.save_prediction(root / "preds" / f"{t:06d}.npz",
                               mean=rng.dirichlet(np.ones(K), (H, W)),
                               var=np.full((H, W, K), 0.01))
  config = models.tiny_config(K)
  _, params = models.init(config, key=jax.random.key(0, impl="rbg"))
  models.save(root / "tiny.msgpack", params, config=config, class_names=NAMES)
  shutil.copy(RECIPE, root / "recipe.json")
  (root / "classmap.json").write_text(json.dumps(
      {"source_classes": list(NAMES), "map": {"a": "x", "b": "x", "c": "y"}}))
  write_scannet(src, str(root / "scannet"))
  write_tum(src, str(root / "tum"))
  return root


def _cache_file(root):
  folder = root / "cache"
  return folder / next(f for f in os.listdir(folder) if f.endswith(".npz"))


def _map_arrays(root):
  state, rule, meta = io.load_map(str(root / "map.npz"))
  out = {k: np.asarray(getattr(state, k)) for k in ("keys", "hits", "claims", "voxel_size")}
  out.update({f"rows/{k}": np.asarray(v) for k, v in state.rows.items()})
  out["meta"] = json.dumps([rule.name, meta], sort_keys=True)
  return out


def _trajectory(root):
  traj = io.load_trajectory(str(root / "map.npz"))
  return {"poses": traj["T_world_cam"], "camera": json.dumps(traj["camera"], sort_keys=True)}


def _sequence(folder):
  def read(root):
    seq = datasets.load_sequence(str(root / folder)) if folder == "seq" else (
        datasets.load_scannet(str(root / folder)) if folder == "scannet" else
        datasets.load_tum(str(root / folder)))
    return {**seq.stacked(), "camera": np.asarray(seq.camera), "name": seq.name,
            "classes": json.dumps(seq.class_names)}
  return read


def _prediction(root):
  pred = jf.sources.precomputed_source(root / "preds").predict(None, None, index=0)
  return {"probs": np.asarray(pred.probs), "var": np.asarray(pred.var)}


def _checkpoint(root):
  model = models.load(root / "tiny.msgpack", class_names=NAMES)
  flat = models.checkpoint.flatten_params(model.params)
  return {**flat, "meta": json.dumps(model.metadata, sort_keys=True)}


def _recipe(root):
  return {"config": repr(train.load_recipe(root / "recipe.json"))}


def _class_map(root):
  return {"map": json.dumps(jf.ClassMap.from_file(root / "classmap.json").to_dict())}


def _gt(root):
  return scene_data.load_gt(str(root / "map_gt.npz"))


# -- Right files with wrong contents, one per reader. -------------------------------------------

def _keys_as_float(root):
  _rewrite_npz(root / "map.npz", lambda a: a.update(keys=a["keys"].astype(np.float32)))


def _rows_wrong_k(root):
  def change(a):
    name = next(k for k in a if k.startswith("rows/"))
    a[name] = np.concatenate([a[name], a[name][:, :1]], axis=1)
  _rewrite_npz(root / "map.npz", change)


def _poses_3x4(root):
  _rewrite_npz(root / "map.npz", lambda a: a.update(poses=a["poses"][:, :3]))


def _frame_rgb_float(root):
  _rewrite_npz(root / "seq" / "frames" / "000000.npz",
               lambda a: a.update(rgb=a["rgb"].astype(np.float32)))


def _mean_2d(root):
  _rewrite_npz(root / "preds" / "000000.npz", lambda a: a.update(mean=a["mean"][..., 0]))


def _gt_coords_2d(root):
  _rewrite_npz(root / "map_gt.npz", lambda a: a.update(coords=a["coords"][:, :2]))


def _param_wrong_shape(root):
  path = root / "tiny.msgpack"
  payload = serialization.msgpack_restore(path.read_bytes())
  name = sorted(payload["params"])[0]
  payload["params"][name] = np.zeros((1,), np.float32)
  payload.pop("digest")
  path.write_bytes(serialization.msgpack_serialize(payload))


def _recipe_list(root):
  (root / "recipe.json").write_text("[1, 2, 3]")


def _class_map_bad(root):
  (root / "classmap.json").write_text(json.dumps({"map": 5}))


def _depth_8bit(root):
  cv2.imwrite(str(root / "scannet" / "depth" / "0.png"), np.zeros((H, W), np.uint8))


def _tum_list_fields(root):
  (root / "tum" / "rgb.txt").write_text("100.0 rgb/a.png extra\n")


# reader name → (read(root) → comparable dict, the file it reads (relative), a valid file of
# another kind (relative), what makes a right file wrong inside).
READERS = {
    "load_map": (_map_arrays, "map.npz", "CACHE", _keys_as_float),
    "load_map rows": (_map_arrays, "map.npz", "preds/000000.npz", _rows_wrong_k),
    "load_trajectory": (_trajectory, "map.npz", "CACHE", _poses_3x4),
    "load_gt": (_gt, "map_gt.npz", "map.npz", _gt_coords_2d),
    "load_sequence frame": (_sequence("seq"), "seq/frames/000000.npz", "preds/000000.npz",
                            _frame_rgb_float),
    "load_sequence meta": (_sequence("seq"), "seq/meta.json", "recipe.json", None),
    "precomputed": (_prediction, "preds/000000.npz", "map.npz", _mean_2d),
    "checkpoint": (_checkpoint, "tiny.msgpack", "map.npz", _param_wrong_shape),
    "recipe": (_recipe, "recipe.json", "classmap.json", _recipe_list),
    "class map": (_class_map, "classmap.json", "recipe.json", _class_map_bad),
    "scannet depth": (_sequence("scannet"), "scannet/depth/0.png", "scannet/color/0.jpg",
                      _depth_8bit),
    "scannet pose": (_sequence("scannet"), "scannet/pose/0.txt", "scannet/depth/0.png", None),
    "scannet intrinsics": (_sequence("scannet"), "scannet/intrinsic/intrinsic_depth.txt",
                           "tiny.msgpack", None),
    "scannet colour": (_sequence("scannet"), "scannet/color/0.jpg", "map.npz", None),
    "tum list": (_sequence("tum"), "tum/rgb.txt", "tum/groundtruth.txt", _tum_list_fields),
    "tum poses": (_sequence("tum"), "tum/groundtruth.txt", "map.npz", None),
}
# Text lists carry no length or checksum: a cut at a line end reads as a shorter list (TUM's
# loader refuses a last line without its newline, so a row cut short is never read).
LINE_LISTS = ()
CORRUPTIONS = ("cut-1", "cut-half", "cut-tenth", "flip", "empty", "png", "other", "wrong")


def corrupt(root, target, how, other, wrong):
  """Damages `root/target` as `how` says; False when the case does not apply."""
  path = root / target
  data = path.read_bytes()
  if how.startswith("cut"):
    cut = {"cut-1": len(data) - 1, "cut-half": len(data) // 2,
           "cut-tenth": len(data) // 10}[how]
    path.write_bytes(data[:cut])
  elif how == "flip":
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(flipped))
  elif how == "empty":
    path.write_bytes(b"")
  elif how == "png":
    path.write_bytes(_png_bytes())
  elif how == "other":
    source = _cache_file(root) if other == "CACHE" else root / other
    path.write_bytes(source.read_bytes())
  elif how == "wrong":
    if wrong is None:
      return False
    wrong(root)
  return True


def _equal(a, b):
  assert a.keys() == b.keys()
  for k in a:
    if isinstance(a[k], np.ndarray):
      np.testing.assert_array_equal(a[k], b[k], err_msg=k)
      assert a[k].dtype == b[k].dtype, k
    else:
      assert a[k] == b[k], k


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("how", CORRUPTIONS)
@pytest.mark.parametrize("reader", sorted(READERS))
def test_reader_gives_a_clear_error_or_the_intact_data(originals, tmp_path, reader, how):
  read, target, other, wrong = READERS[reader]
  if reader == "scannet colour" and how == "flip":
    pytest.skip("JPEG has no checksum: a flipped byte in its entropy-coded data decodes")
  root = tmp_path / "files"
  shutil.copytree(originals, root)
  intact = read(root)
  if not corrupt(root, target, how, other, wrong):
    pytest.skip("no wrong-contents case for this reader")
  try:
    got = read(root)
  except (ValueError, FileNotFoundError) as e:
    message = str(e)
    assert os.path.basename(target) in message, message
    assert "\n" not in message.strip() or reader == "scannet intrinsics", message
    return
  # Read without an error: only a change the format shows to be harmless (a flipped byte in a
  # zip header field outside the data, whose CRCs are checked; a text file cut by its last
  # newline) may do that, and the data must be intact.
  assert how in ("flip", "cut-1") or reader in LINE_LISTS, f"{reader}: {how} read as whole"
  _equal(got, intact)


# -- The front-end cache: a damaged entry is reported in one line and recomputed. ----------------

CACHE_CASES = ("cut-1", "cut-half", "cut-tenth", "flip", "empty", "png", "map", "wrong-shape",
               "digest", "other-key")


def _corrupt_cache(path, how, originals):
  data = path.read_bytes()
  if how.startswith("cut") or how in ("flip", "empty", "png"):
    corrupt(path.parent, path.name, how, None, None)
  elif how == "map":
    path.write_bytes((originals / "map.npz").read_bytes())
  elif how == "wrong-shape":   # an old entry (no digest) whose arrays disagree in shape
    def change(a):
      a["det"] = a["det"][..., :2]
      meta = json.loads(bytes(a["meta"]).decode())
      meta.pop("digest")
      a["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    _rewrite_npz(path, change)
  elif how == "digest":        # whole zip, changed values: only the digest tells
    _rewrite_npz(path, lambda a: a.update(mean=a["mean"] + 1))
  elif how == "other-key":
    def change(a):
      meta = json.loads(bytes(a["meta"]).decode())
      meta["model"] = "another"
      a["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    _rewrite_npz(path, change)
  assert path.read_bytes() != data


@pytest.mark.parametrize("how", CACHE_CASES)
def test_damaged_cache_entry_is_reported_and_recomputed(originals, tmp_path, capsys, how):
  cache = tmp_path / "cache"
  shutil.copytree(originals / "cache", cache)
  path = _cache_file(tmp_path)
  _corrupt_cache(path, how, originals)
  fe = FakeFrontEnd()
  capsys.readouterr()
  got = frontend.cached_predictions(fe, FakeSequence(), cache_dir=str(cache), **CACHE_KEY)
  _equal(got, fe.arrays)
  out = capsys.readouterr().out
  if fe.calls == 0:          # used as it was: only a harmless flip may be
    assert how == "flip" and out == ""
    return
  assert fe.calls == 1
  lines = out.strip().splitlines()
  assert len(lines) == 1 and str(path) in lines[0] and lines[0].endswith("recomputing"), out
  assert ("was made for" if how == "other-key" else "is unreadable (") in lines[0]
  # The entry was rewritten whole: the next call reads it without recomputing.
  again = FakeFrontEnd()
  _equal(frontend.cached_predictions(again, FakeSequence(), cache_dir=str(cache), **CACHE_KEY),
         fe.arrays)
  assert again.calls == 0 and capsys.readouterr().out == ""


def test_cache_entries_without_a_digest_are_still_used(originals, tmp_path, capsys):
  cache = tmp_path / "cache"
  shutil.copytree(originals / "cache", cache)
  path = _cache_file(tmp_path)

  def old_format(a):
    meta = json.loads(bytes(a["meta"]).decode())
    assert meta.pop("digest")
    a["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
  _rewrite_npz(path, old_format)
  fe = FakeFrontEnd()
  _equal(frontend.cached_predictions(fe, FakeSequence(), cache_dir=str(cache), **CACHE_KEY),
         fe.arrays)
  assert fe.calls == 0 and capsys.readouterr().out == ""


# -- The commands: exit 2, one line naming the file, never a traceback. -------------------------

def _commands(root):
  saved = f"saved:{root / 'seq'}"
  return {
      "view": (["view", str(root / "map.npz"), "--port", "0"], "map.npz"),
      "export": (["export", "--map", str(root / "map.npz"), "--out", str(root / "o.ply")],
                 "map.npz"),
      "eval map": (["eval", "--map", str(root / "map.npz"), "--gt", str(root / "map_gt.npz")],
                   "map.npz"),
      "eval gt": (["eval", "--map", str(root / "map.npz"), "--gt", str(root / "map_gt.npz")],
                  "map_gt.npz"),
      "run data": (["run", "--data", saved, "--out", str(root / "out")], "000000.npz"),
      "run predictions": (["run", "--data", saved, "--predictions", str(root / "preds"),
                           "--rule", "bayes", "--out", str(root / "out")], "000000.npz"),
      "run class map": (["run", "--data", saved, "--predictions", str(root / "preds"),
                         "--class-map", str(root / "classmap.json"), "--out",
                         str(root / "out")], "classmap.json"),
  }


COMMAND_TARGETS = {"view": "map.npz", "export": "map.npz", "eval map": "map.npz",
                   "eval gt": "map_gt.npz", "run data": "seq/frames/000000.npz",
                   "run predictions": "preds/000000.npz", "run class map": "classmap.json"}


@pytest.mark.parametrize("how", ("cut-half", "empty", "png"))
@pytest.mark.parametrize("command", sorted(COMMAND_TARGETS))
def test_commands_exit_2_with_one_line(originals, tmp_path, capsys, command, how):
  if command == "view":
    pytest.importorskip("viser")
  root = tmp_path / "files"
  shutil.copytree(originals, root)
  corrupt(root, COMMAND_TARGETS[command], how, None, None)
  argv, name = _commands(root)[command]
  assert cli.main(argv) == 2
  err = capsys.readouterr().err
  last = err.rstrip("\n").split("\n")[-1]   # before it, at most a progress bar (tqdm)
  assert "Traceback" not in err and last.startswith(f"jaxfusion {argv[0]}: error: "), err
  assert name in last and err.count("error:") == 1, err


def _python(args, **kwargs):
  return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=300,
                        cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))),
                        **kwargs)


def test_model_commands_refuse_bad_files_with_exit_2(originals, tmp_path):
  bad = tmp_path / "bad.json"
  bad.write_bytes(_png_bytes())
  done = _python(["-m", "models.train", "--recipe", str(bad), "--out", str(tmp_path / "x")])
  assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
  assert "bad.json" in done.stderr.strip().splitlines()[-1]
  ckpt = tmp_path / "bad.msgpack"
  ckpt.write_bytes((originals / "tiny.msgpack").read_bytes()[:100])
  done = _python(["-m", "models.evaluate", "--checkpoint", str(ckpt)])
  assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
  assert "bad.msgpack" in done.stderr.strip().splitlines()[-1]


# -- Interrupted writes. ------------------------------------------------------------------------

WRITER = textwrap.dedent("""
    import io as _io, sys, time, numpy as np
    from jaxfusion import io
    path, flag = sys.argv[1], sys.argv[2]
    buf = _io.BytesIO()
    np.savez(buf, det=np.ones((4, 64, 64), np.float32))
    data = buf.getvalue()

    def write(tmp):
      with open(tmp, "wb") as f:
        f.write(data[:len(data) // 2])   # half an archive is on disk ...
        f.flush()
        open(flag, "w").close()          # ... tell the test, and stall as a slow disk would
        time.sleep(120)
        f.write(data[len(data) // 2:])

    io.atomic_write(path, write)
""")


def test_a_writer_killed_mid_write_leaves_no_partial_file(originals, tmp_path):
  folder = tmp_path / "maps"
  folder.mkdir()
  target = folder / "map.npz"
  shutil.copy(originals / "map.npz", target)     # the previous, whole file
  before = target.read_bytes()
  flag = tmp_path / "started"
  proc = subprocess.Popen([sys.executable, "-c", WRITER, str(target), str(flag)])
  try:
    for _ in range(600):
      if flag.exists() or proc.poll() is not None:
        break
      subprocess.run(["sleep", "0.05"], check=True)
    assert flag.exists(), "the writer did not start"
    proc.send_signal(signal.SIGKILL)
  finally:
    proc.wait(timeout=60)
  assert proc.returncode == -signal.SIGKILL
  # The target is the previous whole file; the broken temporary is never read as a map.
  assert target.read_bytes() == before
  io.load_map(str(target))
  leftovers = [f for f in os.listdir(folder) if f != "map.npz"]
  assert all(f.startswith(".tmp-") for f in leftovers)
  assert scene_data.find_map_files([str(folder)]) == [str(target)]
  for name in leftovers:
    with pytest.raises(ValueError, match="not a"):
      io.load_map(str(folder / name))


def test_a_writer_that_raises_mid_way_leaves_no_file(tmp_path):
  target = tmp_path / "out.npz"

  def write(tmp):
    with open(tmp, "wb") as f:
      f.write(b"PK\x03\x04 partial")
    raise OSError("No space left on device")

  with pytest.raises(OSError, match="No space"):
    io.atomic_write(str(target), write)
  assert os.listdir(tmp_path) == []


def test_an_interrupted_sequence_save_is_not_read_as_whole(originals, tmp_path, monkeypatch):
  seq = datasets.load_sequence(str(originals / "seq"))
  calls = []
  real = np.savez_compressed

  def failing(file, **arrays):
    calls.append(file)
    if len(calls) == 2:
      raise OSError("No space left on device")
    real(file, **arrays)

  monkeypatch.setattr(np, "savez_compressed", failing)
  with pytest.raises(OSError):
    seq.save(str(tmp_path / "seq"))
  monkeypatch.undo()
  assert os.listdir(tmp_path / "seq" / "frames") == ["000000.npz"]
  with pytest.raises(FileNotFoundError, match="meta.json"):
    datasets.load_sequence(str(tmp_path / "seq"))
