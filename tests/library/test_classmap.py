"""Class maps: hand-computed remaps, the exact samples path against the independence
approximation, jit/vmap, properties, bad tables, files, the shipped tables and `run
--class-map`."""

import json
import pathlib
import tomllib

import hypothesis
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import strategies as st

import jaxfusion as jf
from jaxfusion import classmap
from jaxfusion import datasets
from jaxfusion import io
from jaxfusion.datasets import classes

ROOT = pathlib.Path(__file__).resolve().parents[2]
SOURCES = ("armchair", "stool", "desk", "lamp")        # 0, 1 → chair; 2 → table; 3 unmapped


def _map(unmapped=None, targets=("chair", "table")):
  return jf.ClassMap.from_table({"armchair": "chair", "stool": "chair", "desk": "table"},
                                source_classes=SOURCES, target_classes=targets,
                                unmapped=unmapped)


def _np(x):
  return None if x is None else np.asarray(x)


# --- Hand-computed cases ----------------------------------------------------------------------

def test_exports_and_sizes():
  cm = _map("drop")
  assert jf.ClassMap is jf.sources.ClassMap is classmap.ClassMap
  assert (cm.num_source_classes, cm.num_target_classes) == (4, 2)
  assert cm.source_classes == SOURCES and cm.target_classes == ("chair", "table")
  np.testing.assert_array_equal(cm.matrix, [[1, 0], [1, 0], [0, 1], [0, 0]])
  assert cm.matrix.dtype == jnp.float32 and cm.dropped_classes == ("lamp",)


def test_many_to_one_sums_probabilities_and_variances_into_other():
  cm = _map(targets=("chair", "table", "other"))            # default: the "other" class
  assert not cm.renormalize and cm.dropped_classes == ()
  probs = np.array([0.1, 0.2, 0.3, 0.4], np.float32)
  var = np.array([0.01, 0.02, 0.03, 0.04], np.float32)
  p, v = cm.remap(probs, var)
  np.testing.assert_allclose(p, [0.3, 0.3, 0.4], rtol=1e-6)
  np.testing.assert_allclose(v, [0.03, 0.03, 0.04], rtol=1e-6)   # Σ var: independence assumed
  assert p.dtype == v.dtype == jnp.float32


def test_other_is_appended_when_asked_for_and_missing():
  cm = _map("other")
  assert cm.target_classes == ("chair", "table", "other")
  cm = jf.ClassMap.from_table({0: 0, 1: 0, 2: 1}, source_classes=4, target_classes=2,
                              unmapped="other", other="misc")
  assert cm.target_classes == ("0", "1", "misc")
  np.testing.assert_array_equal(cm.matrix[3], [0, 0, 1])
  # An index names an existing target class as "other", which also makes it the default.
  cm = jf.ClassMap.from_table({0: 0, 2: 1}, source_classes=4, target_classes=2, other=1)
  np.testing.assert_array_equal(cm.matrix, [[1, 0], [0, 1], [0, 1], [0, 1]])


def test_drop_renormalises_and_scales_the_variance_by_one_over_the_mass_squared():
  cm = _map("drop")
  probs = np.array([0.1, 0.2, 0.3, 0.4], np.float32)      # kept mass s = 0.6
  var = np.array([0.01, 0.02, 0.03, 0.04], np.float32)
  p, v = cm.remap(probs, var)
  np.testing.assert_allclose(p, [0.5, 0.5], rtol=1e-6)
  np.testing.assert_allclose(v, [0.03 / 0.36, 0.03 / 0.36], rtol=1e-5)
  p_only, v_none = cm.remap(probs)
  np.testing.assert_allclose(p_only, p)
  assert v_none is None


def test_drop_with_nothing_dropped_is_a_plain_sum():
  cm = jf.ClassMap.from_table({"a": "x", "b": "x"}, source_classes=["a", "b"],
                              target_classes=["x", "y"], unmapped="drop")
  assert not cm.renormalize
  p, _ = cm.remap(np.array([0.2, 0.3], np.float32))      # not a distribution: kept as summed
  np.testing.assert_allclose(p, [0.5, 0.0])


def test_the_variance_is_clipped_to_the_largest_a_mean_allows():
  # Two classes that always share their mass: Σ var = 0.5, but their sum is constantly 1.
  cm = jf.ClassMap.from_table({0: 0, 1: 0, 2: 1}, source_classes=3, target_classes=2)
  samples = np.array([[1, 0, 0], [0, 1, 0]], np.float32)[:, None, None]   # (2, 1, 1, 3)
  mean, var = jf.mc_moments(samples)
  np.testing.assert_allclose(var[0, 0], [0.25, 0.25, 0.0])
  p, v = cm.remap(mean, var)
  np.testing.assert_allclose(p[0, 0], [1.0, 0.0])
  np.testing.assert_allclose(v[0, 0], [0.0, 0.0], atol=1e-7)   # min(0.5, 1·(1 − 1)) = 0


def test_zero_kept_mass_gives_the_uniform_distribution_and_its_largest_variance():
  cm = _map("drop")
  probs = np.array([[0, 0, 0, 1], [1e-14, 0, 0, 1]], np.float32)    # all (or ~all) on "lamp"
  var = np.array([[0, 0, 0, 0], [1e-15, 0, 0, 0]], np.float32)
  p, v = cm.remap(probs, var)
  np.testing.assert_allclose(p, np.full((2, 2), 0.5))
  np.testing.assert_allclose(v, np.full((2, 2), 0.25))
  np.testing.assert_allclose(cm.remap_samples(probs[None]), np.full((1, 2, 2), 0.5))
  grad = jax.grad(lambda x: jnp.sum(cm.remap(x, jnp.asarray(var))[1]))(jnp.asarray(probs))
  assert np.all(np.isfinite(grad))


@pytest.mark.parametrize("unmapped", ["other", "drop"])
def test_finite_outputs_on_one_hot_and_zero_probabilities(unmapped):
  cm = _map(unmapped)
  probs = np.concatenate([np.eye(4, dtype=np.float32), np.zeros((1, 4), np.float32)])
  var = np.zeros_like(probs)
  for p, v in (cm.remap(probs, var), (cm.remap_samples(probs[:, None]), None)):
    assert np.all(np.isfinite(p)) and (v is None or np.all(np.isfinite(v)))
    assert np.all(np.asarray(p) >= 0)
  p, v = cm.remap(probs, var)
  assert np.all(np.asarray(v) == 0) if unmapped == "other" else np.all(np.asarray(v)[:3] == 0)
  for g in jax.grad(lambda x, y: jnp.sum(cm.remap(x, y)[0] + cm.remap(x, y)[1]),
                    argnums=(0, 1))(jnp.asarray(probs), jnp.asarray(var)):
    assert np.all(np.isfinite(g))


# --- The exact path (samples) against the independence approximation (moments) ---------------

def _independent_samples(key, num):
  """(num, 4, 4, 3) samples whose classes 0 and 1 are independent U(0, 0.4); 2 the rest."""
  u = jax.random.uniform(key, (num, 4, 4, 2), maxval=0.4)
  return jnp.concatenate([u, 1.0 - u.sum(-1, keepdims=True)], axis=-1)


SUM_01 = jf.ClassMap.from_table({0: "a", 1: "a", 2: "b"}, source_classes=3,
                                target_classes=["a", "b"])


def test_remap_samples_then_moments_has_the_remapped_mean_exactly():
  samples = jax.random.dirichlet(jax.random.key(0), jnp.ones(4), (6, 5, 7))   # (6, 5, 7, 4)
  cm = _map("other")
  exact_mean, _ = jf.mc_moments(cm.remap_samples(samples))
  mean, var = jf.mc_moments(samples)
  np.testing.assert_allclose(exact_mean, cm.remap(mean, var)[0], atol=1e-6)


def test_with_independent_classes_the_sum_of_variances_matches_the_samples():
  samples = _independent_samples(jax.random.key(1), 20000)
  _, exact_var = jf.mc_moments(SUM_01.remap_samples(samples))
  _, approx_var = SUM_01.remap(*jf.mc_moments(samples))
  # Var U(0, 0.4) = 0.16/12 each; the sample covariance is O(1/√M) ≈ 1% of the sum here.
  np.testing.assert_allclose(approx_var[..., 0], 2 * 0.16 / 12, rtol=0.05)
  np.testing.assert_allclose(exact_var, approx_var, rtol=0.05)


def test_with_correlated_classes_only_the_samples_path_is_exact():
  neg = np.array([[0.6, 0.0, 0.4], [0.0, 0.6, 0.4]], np.float32)   # a + b constant: var 0
  pos = np.array([[0.4, 0.4, 0.2], [0.1, 0.1, 0.8]], np.float32)   # a, b move together
  for samples, true_var in ((neg, 0.0), (pos, 0.09)):
    samples = samples[:, None, None]
    _, exact_var = jf.mc_moments(SUM_01.remap_samples(samples))
    _, approx_var = SUM_01.remap(*jf.mc_moments(samples))
    np.testing.assert_allclose(exact_var[0, 0, 0], true_var, atol=1e-6)
    assert abs(float(approx_var[0, 0, 0]) - true_var) > 0.04     # 0.18 and 0.045
  assert float(approx_var[0, 0, 0]) < true_var                   # under-estimated when positive


def test_drop_on_samples_renormalises_each_sample():
  cm = _map("drop")
  samples = np.array([[0.1, 0.2, 0.3, 0.4], [0.3, 0.3, 0.2, 0.2]], np.float32)
  out = np.asarray(cm.remap_samples(samples[:, None, None]))[:, 0, 0]
  np.testing.assert_allclose(out, [[0.5, 0.5], [0.75, 0.25]], rtol=1e-6)
  # The delta method on the moments is first-order close to the exact renormalised moments.
  mean, var = jf.mc_moments(samples[:, None, None])
  exact = jf.mc_moments(cm.remap_samples(samples[:, None, None]))
  np.testing.assert_allclose(cm.remap(mean, var)[0], exact[0], atol=0.05)


# --- Transformations --------------------------------------------------------------------------

def test_jit_and_vmap_and_no_retrace():
  cm = _map("drop")
  traces = []

  def remap(c, p, v):
    traces.append(1)
    return c.remap(p, v)

  fn = jax.jit(remap)
  probs = jax.random.dirichlet(jax.random.key(2), jnp.ones(4), (3, 5, 6))   # (B, H, W, K)
  var = 0.01 * probs
  want = cm.remap(probs, var)
  for got in (fn(cm, probs, var), fn(cm, probs * 1.0, var * 1.0),
              jax.vmap(cm.remap)(probs, var)):
    for g, w in zip(got, want):
      np.testing.assert_allclose(g, w, rtol=1e-6)
  assert len(traces) == 1
  samples = jax.random.dirichlet(jax.random.key(3), jnp.ones(4), (2, 5, 6))
  np.testing.assert_allclose(jax.jit(jf.ClassMap.remap_samples)(cm, samples),
                             cm.remap_samples(samples))
  leaves = jax.tree_util.tree_leaves(cm)
  assert len(leaves) == 1 and leaves[0].shape == (4, 2)       # names and policy are static


@hypothesis.settings(max_examples=25, deadline=None)
@hypothesis.given(
    k_src=st.integers(1, 7), k_dst=st.integers(1, 4), seed=st.integers(0, 2**16),
    unmapped=st.sampled_from(["other", "drop"]))
def test_outputs_are_distributions_with_bounded_nonnegative_variances(k_src, k_dst, seed,
                                                                      unmapped):
  rng = np.random.default_rng(seed)
  dest = rng.integers(-1, k_dst, k_src)                      # -1: unmapped
  if np.all(dest < 0):
    dest[0] = 0
  cm = jf.ClassMap.from_table({i: (None if d < 0 else int(d)) for i, d in enumerate(dest)},
                              source_classes=k_src, target_classes=k_dst, unmapped=unmapped)
  alpha = rng.choice([0.05, 1.0], k_src)
  samples = rng.dirichlet(alpha, (5, 3, 2)).astype(np.float32)      # (M, H, W, K_src)
  mean, var = jf.mc_moments(samples)
  for p, v in (cm.remap(mean, var), jf.mc_moments(cm.remap_samples(samples))):
    p, v = np.asarray(p), np.asarray(v)
    assert p.shape == (3, 2, cm.num_target_classes) and np.all(np.isfinite(p))
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)
    assert np.all(p >= 0) and np.all(np.isfinite(v)) and np.all(v >= 0)
    assert np.all(v <= p * (1 - p) + 1e-6)


# --- Bad tables -------------------------------------------------------------------------------

@pytest.mark.parametrize("table,kwargs,match", [
    ({"stoool": "chair"}, {}, r"unknown source class 'stoool'; did you mean 'stool'"),
    ({"stool": "chiar"}, {}, r"unknown target class 'chiar'"),
    ({7: "chair"}, {}, r"source class index 7 is out of range: there are 4 source classes"),
    ({-1: "chair"}, {}, r"source class index -1 is out of range"),
    ({"stool": 2}, {}, r"target class index 2 is out of range: there are 2 target classes"),
    ({"stool": "5"}, {}, r"target class index 5 is out of range"),
    ([("stool", "chair"), (1, "table")], {}, r"source class 'stool' is mapped twice"),
    ({"stool": "chair"}, {"source_classes": ["a", "a"]}, r"duplicate source class names"),
    ({"stool": "chair"}, {"target_classes": ["chair", ""]}, r"non-empty strings"),
    ({"stool": "chair"}, {"unmapped": "ignore"}, r"unmapped must be one of"),
    ({"stool": "chair"}, {"unmapped": None}, r"3 source classes with no target"),
    ({"stool": None}, {"unmapped": "drop"}, r"no source class has a target"),
    ([("stool",)], {}, r"\(source, target\) pair"),
])
def test_bad_tables_are_clear_value_errors(table, kwargs, match):
  kwargs = {"source_classes": SOURCES, "target_classes": ("chair", "table"),
            "unmapped": "drop", **kwargs}
  with pytest.raises(ValueError, match=match):
    jf.ClassMap.from_table(table, **kwargs)


def test_a_class_count_mismatch_is_a_value_error():
  cm = _map("drop")
  with pytest.raises(ValueError, match=r"has 4 source classes but the probabilities have 5"):
    cm.remap(np.full((2, 5), 0.2, np.float32))
  with pytest.raises(ValueError, match=r"must have the probabilities' shape"):
    cm.remap(np.full((2, 4), 0.25, np.float32), np.zeros((3, 4), np.float32))
  with pytest.raises(ValueError, match=r"but the samples have 3"):
    jax.jit(jf.ClassMap.remap_samples)(cm, jnp.ones((2, 1, 1, 3)) / 3)
  with pytest.raises(ValueError, match=r"float probabilities"):
    cm.remap(np.zeros((2, 4), np.int32))


# --- Files ------------------------------------------------------------------------------------

def test_json_round_trip_and_its_forms(tmp_path):
  cm = _map("drop")
  path = tmp_path / "map.json"
  path.write_text(json.dumps(cm.to_dict()))
  back = jf.ClassMap.from_file(path)
  np.testing.assert_array_equal(back.matrix, cm.matrix)
  assert (back.source_classes, back.target_classes, back.renormalize) == (
      cm.source_classes, cm.target_classes, True)
  # Indices (as JSON strings), a count of source classes, pairs, derived targets.
  path.write_text(json.dumps({"source_classes": 3, "target_classes": ["x", "y"],
                              "map": {"0": "y", "2": 0}, "unmapped": "other"}))
  cm = jf.ClassMap.from_file(path)
  assert cm.target_classes == ("x", "y", "other")
  np.testing.assert_array_equal(cm.matrix, [[0, 1, 0], [0, 0, 1], [1, 0, 0]])
  path.write_text(json.dumps({"map": [["a", "x"], ["b", None], ["c", "w"]],
                              "description": "pairs"}))
  cm = jf.ClassMap.from_file(path, unmapped="drop")
  assert cm.source_classes == ("a", "b", "c") and cm.target_classes == ("x", "w")
  assert cm.dropped_classes == ("b",)


def test_csv_files(tmp_path):
  path = tmp_path / "map.csv"
  path.write_text("# network class, map class\nsource,target\narmchair,chair\n\n"
                  "stool, chair\ndesk,table\nlamp,other\n")
  cm = jf.ClassMap.from_file(path)
  assert cm.source_classes == SOURCES and cm.target_classes == ("chair", "table", "other")
  np.testing.assert_array_equal(cm.matrix, [[1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
  path.write_text("armchair,chair\nstool,chair\ndesk,table\nlamp,\n")      # lamp unmapped
  with pytest.raises(ValueError, match=r"map.csv: 1 source class with no target \('lamp'\)"):
    jf.ClassMap.from_file(path)
  cm = jf.ClassMap.from_file(path, unmapped="drop")
  assert cm.dropped_classes == ("lamp",) and cm.target_classes == ("chair", "table")


@pytest.mark.parametrize("name,text,match", [
    ("m.csv", "a,x\nb,y,z\n", r"m.csv: line 2: a row is 'source,target'"),
    ("m.csv", "a,x\nb,y\na,y\n", r"line 3: source class 'a' is mapped twice \(first on line 1"),
    ("m.csv", "source,target\n", r"no 'source,target' rows"),
    ("m.json", "{\"map\": {\"a\": \"x\", \"a\": \"y\"}}", r"duplicate JSON keys \['a'\]"),
    ("m.json", "{\"map\": {\"a\": \"x\"", r"m.json: not valid JSON"),
    ("m.json", "{\"map\": {\"a\": \"x\"}, \"unmaped\": \"drop\"}", r"unknown class map keys"),
    ("m.json", "{\"source_classes\": [\"a\"]}", r"needs a 'map'"),
    ("m.json", "{\"map\": {\"a\": 0}}", r"give 'target_classes'"),
    ("m.json", "{\"source_classes\": [\"a\"], \"map\": {\"a\": \"x\", \"b\": \"x\"}}",
     r"unknown source class 'b'"),
    ("m.txt", "a,x\n", r"a .json or .csv file"),
])
def test_bad_files_name_the_file_and_the_problem(tmp_path, name, text, match):
  (tmp_path / name).write_text(text)
  with pytest.raises(ValueError, match=match):
    jf.ClassMap.from_file(tmp_path / name)


def test_a_missing_file_is_file_not_found(tmp_path):
  with pytest.raises(FileNotFoundError, match="no class map file"):
    jf.ClassMap.from_file(tmp_path / "none.json")


# --- Shipped tables ---------------------------------------------------------------------------

def test_nyu40_to_12_agrees_with_the_label_lut_on_every_id():
  cm = classes.nyu40_class_map("scannet12")
  assert cm.target_classes == datasets.SCANNET_CLASS_NAMES and cm.num_source_classes == 41
  matrix = np.asarray(cm.matrix)
  for nyu_id in range(256):
    label = datasets.NYU40_TO_SCANNET12[nyu_id]
    if nyu_id > 40:
      assert label == datasets.IGNORE_LABEL
      continue
    row = matrix[nyu_id]
    assert (row.sum() == 0) if label == datasets.IGNORE_LABEL else row[label] == row.sum() == 1
  assert cm.dropped_classes == ("unannotated", "wall") and cm.renormalize


def test_nyu40_to_20_is_the_benchmark_table():
  cm = classes.nyu40_class_map("scannet20")
  ids = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39)
  assert [i for i, _ in classes.SCANNET20_TABLE] == list(ids)
  assert cm.target_classes == classes.SCANNET20_CLASS_NAMES[:] and len(cm.target_classes) == 20
  assert cm.target_classes[-1] == "otherfurniture" and cm.target_classes[15] == "shower curtain"
  matrix = np.asarray(cm.matrix)
  for nyu_id in range(41):
    label = classes.NYU40_TO_SCANNET20[nyu_id]
    assert (matrix[nyu_id].sum() == 0) if label < 0 else matrix[nyu_id, label] == 1
    assert (label >= 0) == (nyu_id in ids)
    if label >= 0:     # the benchmark's names are the NYU40 names
      assert classes.NYU40_CLASS_NAMES[nyu_id] == cm.target_classes[label]
  without = classes.nyu40_class_map("scannet20", unannotated=False)
  np.testing.assert_array_equal(without.matrix, matrix[1:])
  with pytest.raises(ValueError, match="scannet12' or 'scannet20"):
    classes.nyu40_class_map("ade20k")


@pytest.mark.parametrize("name", classes.CLASS_MAPS)
def test_the_shipped_files_are_the_tables_and_are_package_data(name):
  shipped = jf.ClassMap.from_file(classes.class_map_path(name))
  table = classes.nyu40_class_map(name.split("_to_")[1])
  np.testing.assert_array_equal(shipped.matrix, table.matrix)
  assert (shipped.source_classes, shipped.target_classes, shipped.renormalize) == (
      table.source_classes, table.target_classes, table.renormalize)
  config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
  globs = config["package-data"]["jaxfusion.datasets"]
  assert "jaxfusion.datasets" in config["packages"]
  package = ROOT / "jaxfusion" / "datasets"
  assert any(classes.class_map_path(name) in {p.resolve() for p in package.glob(g)}
             for g in globs)


# --- `jaxfusion run --class-map` --------------------------------------------------------------

RUN_SOURCES = jf.datasets.CLASS_NAMES + ("stool", "unknown")        # 9 network classes


def _write_predictions(folder, *, samples: bool):
  """Predictions of 9 classes that follow the GT labels of office:0 (2 frames) once remapped:
  on chairs, "unknown" (dropped) comes first, then chair and stool, which sum to the most."""
  seq = datasets.load_spec("office:0", num_frames=2, height=24, width=32)
  labels = np.where(seq.labels < 0, 0, seq.labels)                       # (T, H, W)
  chair = labels == jf.datasets.CLASS_NAMES.index("chair")
  assert chair.any()
  rng = np.random.default_rng(0)
  for t in range(len(seq)):
    probs = np.full(labels[t].shape + (9,), 0.02, np.float32)
    np.put_along_axis(probs, labels[t][..., None], 0.5, axis=-1)
    probs[chair[t]] = [0.02, 0.02, 0.22, 0.02, 0.02, 0.02, 0.02, 0.22, 0.42]
    probs /= probs.sum(-1, keepdims=True)
    if samples:
      noisy = probs[None] * rng.uniform(0.8, 1.2, (3,) + probs.shape).astype(np.float32)
      jf.sources.save_prediction(folder / f"{t:06d}.npz",
                                 samples=noisy / noisy.sum(-1, keepdims=True))
    else:
      jf.sources.save_prediction(folder / f"{t:06d}.npz", mean=probs,
                                 var=np.full_like(probs, 1e-3))
  return seq


def _run(tmp_path, class_map, *extra):
  from jaxfusion.lab import cli  # pylint: disable=import-outside-toplevel
  return cli.main(["run", "--data", "office:0", "--frames", "2", "--height", "24",
                   "--width", "32", "--predictions", str(tmp_path / "preds"),
                   "--class-map", str(class_map), "--capacity", "4096",
                   "--out", str(tmp_path / "out"), *extra])


@pytest.mark.slow
def test_run_with_a_json_class_map_fuses_and_scores_the_remapped_map(tmp_path, capsys):
  _write_predictions(tmp_path / "preds", samples=True)          # samples: the exact path
  path = tmp_path / "map.json"
  path.write_text(json.dumps({"source_classes": list(RUN_SOURCES),
                              "target_classes": list(jf.datasets.CLASS_NAMES),
                              "map": {**{n: n for n in jf.datasets.CLASS_NAMES},
                                      "stool": "chair", "unknown": None},
                              "unmapped": "drop"}))
  assert _run(tmp_path, path) == 0
  out = capsys.readouterr().out
  assert "mIoU" in out and "IoU: background" in out and "chair 100.0" in out
  (saved,) = [p for p in (tmp_path / "out").glob("*.npz") if not p.stem.endswith("_gt")]
  state, _, meta = io.load_map(str(saved))
  assert state.num_classes == 7 and tuple(meta["class_names"]) == jf.datasets.CLASS_NAMES
  assert meta["extra"]["class_map"] == str(path)


@pytest.mark.slow
def test_run_with_a_csv_class_map_and_the_errors(tmp_path, capsys):
  _write_predictions(tmp_path / "preds", samples=False)
  path = tmp_path / "map.csv"
  rows = [f"{n},{n}" for n in jf.datasets.CLASS_NAMES] + ["stool,chair", "unknown,"]
  path.write_text("\n".join(rows) + "\n")
  assert _run(tmp_path, path) == 2                        # unmapped "unknown", no choice made
  err = capsys.readouterr().err
  assert "--class-map" in err and "choose unmapped" in err and len(err.splitlines()) == 1
  assert _run(tmp_path, path, "--unmapped", "drop", "--rule", "bayes") == 0
  assert "chair 100.0" in capsys.readouterr().out
  short = tmp_path / "short.csv"                          # 8 source classes, predictions have 9
  short.write_text("\n".join(rows[:-1]) + "\n")
  assert _run(tmp_path, short) == 2
  err = capsys.readouterr().err
  assert "maps 8 source classes but --predictions" in err and "has 9 classes" in err
  bad = tmp_path / "bad.json"
  bad.write_text(json.dumps({"source_classes": 9, "map": {"9": "chair"}}))
  assert _run(tmp_path, bad) == 2
  assert "source class index 9 is out of range" in capsys.readouterr().err
  assert _run(tmp_path, tmp_path / "none.json") == 2
  assert "no such file" in capsys.readouterr().err


@pytest.mark.slow
def test_run_remaps_the_networks_samples(tmp_path, capsys):
  from jaxfusion.lab import cli  # pylint: disable=import-outside-toplevel
  coarse = {"background": "background", "chair": "furniture", "table": "furniture",
            "sofa": "furniture", "bottle": "objects", "plant": "objects", "tv": "objects"}
  path = tmp_path / "coarse.json"
  path.write_text(json.dumps({"source_classes": list(jf.datasets.CLASS_NAMES), "map": coarse}))
  argv = ["run", "--data", "office:0", "--frames", "2", "--height", "24", "--width", "32",
          "--num-samples", "2", "--capacity", "4096", "--out", str(tmp_path / "out"),
          "--class-map", str(path)]
  assert cli.main(argv) == 0
  assert "the map is not scored" in capsys.readouterr().out
  (saved,) = (tmp_path / "out").glob("*.npz")
  state, _, meta = io.load_map(str(saved))
  assert state.num_classes == 3
  assert tuple(meta["class_names"]) == ("background", "furniture", "objects")
  swapped = ["bottle", "background"] + list(jf.datasets.CLASS_NAMES[2:])
  path.write_text(json.dumps({"source_classes": swapped, "map": coarse}))
  assert cli.main(argv) == 2
  assert "are not the network's" in capsys.readouterr().err


def test_remap_called_plainly_runs_one_compiled_program():
  # Like mc_moments, the remaps are called plainly on whole frames: each must run as one compiled
  # program per shape (not op by op over (H, W, K) arrays) and equal the call under jax.jit.
  cm = jf.ClassMap.from_table({0: 0, 1: 0, 2: 1, 3: None}, source_classes=4, target_classes=2,
                           unmapped="drop")
  rng = np.random.default_rng(3)
  probs = rng.dirichlet(np.ones(4), (5, 6)).astype(np.float32)
  var = (0.1 * probs * (1 - probs)).astype(np.float32)
  samples = rng.dirichlet(np.ones(4), (3, 5, 6)).astype(np.float32)
  before = (classmap._remap_moments._cache_size(),   # pylint: disable=protected-access
            classmap._remap_probs._cache_size())     # pylint: disable=protected-access
  out = cm.remap(probs, var)
  out_samples = cm.remap_samples(samples)
  cm.remap(probs + 0.0, var + 0.0)                    # same shapes: no new compilation
  cm.remap_samples(samples + 0.0)
  after = (classmap._remap_moments._cache_size(),    # pylint: disable=protected-access
           classmap._remap_probs._cache_size())      # pylint: disable=protected-access
  assert after == (before[0] + 1, before[1] + 1)
  jitted = jax.jit(lambda c, p, v, s: (c.remap(p, v), c.remap_samples(s)))(cm, probs, var, samples)
  for ours, theirs in zip(jax.tree.leaves((out, out_samples)), jax.tree.leaves(jitted)):
    np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))
