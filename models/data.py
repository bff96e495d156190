"""The training and evaluation data: rendered views of the embedded world, its class names and
the version of its generator.

`train` (which renders its splits), `evaluate` and `figure` all read the same views from here,
so the commands do not import one another for their data. Only the commands need the world
(`jaxfusion.datasets.synthetic`), so it is imported inside the functions.

Shape legend: N images, H×W pixels.
"""

import pathlib
import subprocess

import numpy as np


def load_domain(domain: str, num_images: int, *, height: int, width: int, seed: int,
                shift: float = 1.0, cache_dir: str | None = None, sensing: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
  """Renders `num_images` views of the embedded world (`jaxfusion.datasets.synthetic`).

  Args:
    domain: "train" or "test" (shifted palettes, textures, lighting and shapes).
    num_images: N.
    height: H.
    width: W.
    seed: scene/view seed.
    shift: test-domain shift strength.
    cache_dir: if given, rendered views are stored there as `.npz` and reused when the same
      split is asked for again (rendering dominates start-up time on a CPU).
    sensing: render with the view-dependent camera model (`SensingConfig()`), else with
      `SensingConfig.off()` (the plain renderer).

  Returns:
    `(rgb (N, H, W, 3) uint8, labels (N, H, W) int32)`.
  """
  cache = None
  if cache_dir is not None:
    cache = pathlib.Path(cache_dir) / (
        f"{domain}_n{num_images}_{height}x{width}_seed{seed}_shift{shift:g}_"
        f"sensing{'on' if sensing else 'off'}_"
        f"{dataset_version()}.npz")
    if cache.is_file():
      with np.load(cache) as data:
        return data["rgb"], data["labels"]
  from jaxfusion.datasets import synthetic  # Application layer: only the commands need it.
  from jaxfusion.datasets import SensingConfig
  rgb, labels = synthetic.sample_views(domain, num_images, height=height, width=width,
                                       seed=seed, shift=shift,
                                       sensing=SensingConfig() if sensing else SensingConfig.off())
  rgb, labels = np.asarray(rgb, np.uint8), np.asarray(labels, np.int32)
  if cache is not None:
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, rgb=rgb, labels=labels)
  return rgb, labels


def dataset_class_names() -> tuple[str, ...]:
  """The embedded world's class names, in label order."""
  from jaxfusion.datasets import synthetic
  names = getattr(synthetic, "CLASS_NAMES", None)
  if names is None:
    from jaxfusion.datasets import classes
    names = classes.CLASS_NAMES
  return tuple(names)


def dataset_version() -> str:
  """Identifies the data generator: its declared version, else the git commit of its folder.

  A working tree with uncommitted changes under `jaxfusion/datasets` gets a `-dirty` suffix;
  the training record also stores SHA-256 digests of the rendered arrays.
  """
  from jaxfusion.datasets import synthetic
  declared = getattr(synthetic, "VERSION", getattr(synthetic, "__version__", None))
  if declared is not None:
    return str(declared)
  folder = pathlib.Path(synthetic.__file__).resolve().parent
  try:
    commit = subprocess.run(["git", "log", "-1", "--format=%h", "--", "."], cwd=folder,
                            capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--", "."], cwd=folder,
                           capture_output=True, text=True, timeout=10, check=True).stdout.strip()
  except (OSError, subprocess.SubprocessError):
    return "unversioned"
  return (commit or "uncommitted") + ("-dirty" if dirty else "")
