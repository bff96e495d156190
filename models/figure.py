"""The paper's Fig. 3 for our network: RGB | ground truth | prediction | epistemic uncertainty.

`python -m models.figure --out fig3.png` renders views of the embedded world's shifted test
domain, runs the shipped (or a given) checkpoint with MC dropout, and writes one row per view:
the image, its ground-truth labels and the MC-mean prediction in the class colours, and the
total epistemic variance Σ_k var_k per pixel (brighter = more uncertain). Misclassified pixels
are outlined on the uncertainty panel so one can see that the variance concentrates there.

Shape legend: N views, H×W pixels, K classes.
"""

import argparse
import pathlib

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.patches  # noqa: E402  (backend must be chosen first)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from . import checkpoint, evaluate  # noqa: E402
from . import data as data_lib  # noqa: E402


def colorize(labels: np.ndarray, colors: np.ndarray) -> np.ndarray:
  """`(H, W)` int labels → `(H, W, 3)` uint8 RGB; labels outside the table are black."""
  labels = np.asarray(labels)
  valid = (labels >= 0) & (labels < len(colors))
  out = np.zeros(labels.shape + (3,), np.uint8)
  out[valid] = colors[labels[valid]]
  return out


def render_figure(rgb: np.ndarray, labels: np.ndarray, mean: np.ndarray, var: np.ndarray, *,
                  class_names, colors: np.ndarray, out: str | pathlib.Path,
                  title: str | None = None) -> pathlib.Path:
  """Writes the four-column figure as PNG.

  Args:
    rgb: `(N, H, W, 3)` uint8 images.
    labels: `(N, H, W)` int ground truth.
    mean: `(N, H, W, K)` MC-mean probabilities.
    var: `(N, H, W, K)` epistemic variances.
    class_names: K names (legend).
    colors: `(K, 3)` uint8 class colours.
    out: PNG path; parent folders are created.
    title: optional figure title.

  Returns:
    The path written.
  """
  n = rgb.shape[0]
  pred = mean.argmax(-1)
  uncertainty = var.sum(-1)
  vmax = float(np.percentile(uncertainty, 99.5)) or 1e-6
  fig, axes = plt.subplots(n, 4, figsize=(4 * 2.6, n * 2.1 + 0.8), squeeze=False)
  for i in range(n):
    acc = float((pred[i] == labels[i]).mean())
    panels = [(rgb[i], "RGB"), (colorize(labels[i], colors), "ground truth"),
              (colorize(pred[i], colors), f"prediction ({100 * acc:.0f}% px)")]
    for j, (img, name) in enumerate(panels):
      axes[i, j].imshow(img, interpolation="nearest")
      axes[i, j].set_title(name, fontsize=8)
    im = axes[i, 3].imshow(uncertainty[i], cmap="inferno", vmin=0.0, vmax=vmax,
                           interpolation="nearest")
    axes[i, 3].contour(pred[i] != labels[i], levels=[0.5], colors="cyan", linewidths=0.4)
    axes[i, 3].set_title("epistemic var (cyan: errors)", fontsize=8)
    fig.colorbar(im, ax=axes[i, 3], fraction=0.046, pad=0.02)
    for ax in axes[i]:
      ax.set_axis_off()
  handles = [matplotlib.patches.Patch(color=np.asarray(c) / 255.0, label=name)
             for name, c in zip(class_names, colors)]
  fig.legend(handles=handles, loc="lower center", ncol=len(class_names), fontsize=7,
             frameon=False)
  if title:
    fig.suptitle(title, fontsize=9)
  fig.tight_layout(rect=(0, 0.04, 1, 0.97 if title else 1))
  out = pathlib.Path(out)
  out.parent.mkdir(parents=True, exist_ok=True)
  fig.savefig(out, dpi=120)
  plt.close(fig)
  return out


def main(argv: list[str] | None = None) -> pathlib.Path:
  p = argparse.ArgumentParser(prog="python -m models.figure", description=__doc__.split("\n")[0])
  p.add_argument("--out", default="fig3.png", help="PNG to write")
  p.add_argument("--checkpoint", default=str(checkpoint.PRETRAINED_PATH))
  p.add_argument("--domain", default="test", choices=("train", "test"))
  p.add_argument("--num-views", type=int, default=4)
  p.add_argument("--num-samples", type=int, default=32, help="M dropout samples")
  p.add_argument("--height", type=int, default=None, help="default: the training size")
  p.add_argument("--width", type=int, default=None)
  p.add_argument("--seed", type=int, default=3)
  p.add_argument("--cache", default=None, help="folder to cache rendered views in")
  args = p.parse_args(argv)

  from jaxfusion.datasets import classes
  model, height, width = evaluate.load_with_training_size(args.checkpoint, args.height,
                                                          args.width)
  rgb, labels = data_lib.load_domain(args.domain, args.num_views, height=height, width=width,
                                     seed=args.seed, cache_dir=args.cache)
  preds = evaluate.predict_arrays(model.graphdef, model.params, rgb,
                                  key=jax.random.key(args.seed), num_samples=args.num_samples)
  out = render_figure(
      rgb, labels, preds["mc_mean"], preds["mc_var"], class_names=model.class_names,
      colors=classes.CLASS_COLORS, out=args.out,
      title=f"{args.domain} domain, MC dropout M={args.num_samples}")
  print(f"wrote {out}")
  return out


if __name__ == "__main__":
  main()
