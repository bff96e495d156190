"""Every matplotlib figure of the lab, written as PNG: the paper's Fig. 2 outlier example
(computed by the engine), per-class IoU bars per method, maps side by side (the paper's Fig. 5),
the study's curves over the domain shift with interval bands, voxel-headroom bars and α
histograms, the tuning commands' β plots and the simulated front end's heatmap."""

from typing import Optional, Sequence

import numpy as np

import jaxfusion as jf
from jaxfusion import io


def _pyplot():
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  return plt


def _save(fig, path, *, dpi: int = 120, tight: bool = True):
  """Writes `fig` as a PNG (atomically) and closes it."""
  plt = _pyplot()
  extra = {"bbox_inches": "tight"} if tight else {}
  io.atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png", **extra))
  plt.close(fig)


def outlier_example(*, num_agree: int = 5, agree=(0.6, 0.25, 0.15), outlier=(0.001, 0.998, 0.001),
                    var_agree: float = 0.002, var_outlier: float = 0.08, beta: float = 0.3):
  """The paper's Fig. 2 numbers, computed by fusing a one-voxel map with the engine.

  `num_agree` observations agree on class 0; then one confident but wrong observation (with the
  high epistemic variance of unfamiliar data) votes for class 1.

  Returns:
    dict: `prior` (posterior before the outlier, per rule), `posterior` (after it, per rule),
    `observation` and `regularized` (p̃ of the outlier); rules: Bayesian, R, D, D+R.
  """
  agree, outlier = np.asarray(agree, np.float32), np.asarray(outlier, np.float32)
  cam = jf.Camera(10.0, 10.0, 0.0, 0.0)
  pose = np.eye(4, dtype=np.float32)
  pose[:3, 3] = 0.5

  def frame(p, var):
    return jf.Frame(np.full((1, 1), 0.2, np.float32), pose, p.reshape(1, 1, -1),
                    np.full((1, 1, len(p)), var, np.float32))

  rules = {"Bayesian": jf.rules.bayes(),
           "R": jf.rules.robust(beta=beta, dirichlet=False),
           "D": jf.rules.robust(regularize=False),
           "D+R": jf.rules.robust(beta=beta)}
  prior, posterior = {}, {}
  for name, rule in rules.items():
    state = jf.init_map(capacity=8, num_classes=len(agree), voxel_size=1.0, rule=rule)
    for _ in range(num_agree):
      state = jf.fuse_frame(state, frame(agree, var_agree), cam, rule)
    prior[name] = jf.read_map(state)["posterior"][0]
    state = jf.fuse_frame(state, frame(outlier, var_outlier), cam, rule)
    posterior[name] = jf.read_map(state)["posterior"][0]
  regularized = (1 - beta) * outlier + beta / len(outlier)
  return {"prior": prior, "posterior": posterior, "observation": outlier,
          "regularized": regularized, "num_agree": num_agree}


def outlier_figure(path: str, **kwargs) -> dict:
  """Writes the Fig. 2-style PNG: the belief before the outlier, the outlier (raw and
  regularised), and the posterior after it under Bayes vs the robust rules."""
  ex = outlier_example(**kwargs)
  plt = _pyplot()
  k = len(ex["observation"])
  classes = [f"class {i}" for i in range(k)]
  fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), sharey=True)
  names = list(ex["prior"])
  width = 0.8 / len(names)
  for ax, key, title in ((axes[0], "prior", f"after {ex['num_agree']} agreeing observations"),
                         (axes[2], "posterior", "after one confident outlier")):
    for i, name in enumerate(names):
      ax.bar(np.arange(k) + (i - (len(names) - 1) / 2) * width, ex[key][name], width,
             label=name)
    ax.set_title(title)
    ax.set_xticks(np.arange(k), classes)
  axes[1].bar(np.arange(k) - 0.2, ex["observation"], 0.4, label="network output p̄",
              color="tab:red")
  axes[1].bar(np.arange(k) + 0.2, ex["regularized"], 0.4, label="regularised p̃",
              color="tab:orange")
  axes[1].set_title("the outlier observation")
  axes[1].set_xticks(np.arange(k), classes)
  axes[0].set_ylabel("probability")
  axes[0].legend(fontsize=8)
  axes[1].legend(fontsize=8)
  fig.suptitle("One confident wrong observation: Bayesian fusion flips, robust fusion holds")
  _save(fig, path)
  return ex


def iou_bars(path: str, iou: dict, class_names: Sequence[str],
             colors: Optional[np.ndarray] = None) -> None:
  """Per-class IoU bars, one group per class, one bar per method.

  Args:
    path: PNG destination.
    iou: method name -> `(K,)` IoU (NaN for absent classes).
    class_names: K names.
    colors: optional `(K, 3) uint8` class colours for the tick labels.
  """
  plt = _pyplot()
  k = len(class_names)
  fig, ax = plt.subplots(figsize=(max(8, 1.3 * k), 3.8))
  width = 0.8 / max(1, len(iou))
  for i, (name, values) in enumerate(iou.items()):
    ax.bar(np.arange(k) + (i - (len(iou) - 1) / 2) * width, np.nan_to_num(values) * 100, width,
           label=name)
  ax.set_xticks(np.arange(k), class_names)
  if colors is not None:
    for tick, c in zip(ax.get_xticklabels(), np.asarray(colors) / 255.0):
      tick.set_color(c if np.mean(c) < 0.85 else "black")
  ax.set_ylabel("IoU (%)")
  ax.legend(fontsize=8, ncol=min(6, len(iou)))
  _save(fig, path)


def map_views(path: str, maps: dict, *, voxel_size: float, colors: np.ndarray,
              ceiling_cut: float = 0.35) -> None:
  """Renders maps side by side from the same oblique viewpoint (the paper's Fig. 5).

  Args:
    path: PNG destination.
    maps: title -> dict with `coords (N, 3)` and `labels (N,)` (read_map output or GT labels).
    voxel_size: voxel edge in metres.
    colors: `(K, 3) uint8` class colours.
    ceiling_cut: voxels higher than (top − ceiling_cut) metres are hidden to see into rooms.
  """
  plt = _pyplot()
  all_z = np.concatenate([(np.asarray(m["coords"])[:, 2] + 0.5) * voxel_size
                          for m in maps.values() if len(m["coords"])] or [np.zeros(1)])
  z_max = all_z.max() - ceiling_cut
  fig, axes = plt.subplots(1, len(maps), figsize=(5 * len(maps), 4.6), squeeze=False)
  # Oblique view: look along (1, 1, -1.2); screen x ⟂ view in the ground plane.
  view = np.array([1.0, 1.0, -1.2])
  view /= np.linalg.norm(view)
  right = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
  up = np.cross(right, view)
  for ax, (title, m) in zip(axes[0], maps.items()):
    centers = (np.asarray(m["coords"]) + 0.5) * voxel_size
    labels = np.asarray(m["labels"])
    keep = centers[:, 2] <= z_max
    centers, labels = centers[keep], labels[keep]
    order = np.argsort(centers @ view)[::-1]   # far first: painter's algorithm
    ax.scatter(centers[order] @ right, centers[order] @ up, c=np.asarray(colors)[labels[order]]
               / 255.0, s=4, marker="s", linewidths=0)
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.axis("off")
  _save(fig, path)


def mesh_views(path: str, meshes: dict, *, ceiling_cut: float = 0.35) -> None:
  """Renders meshes side by side from the same oblique viewpoint as `map_views`, each face
  in its class colour with Lambert shading (painter's algorithm, far faces first).

  Args:
    path: PNG destination.
    meshes: title -> `(vertices (P, 3), faces (F, 3), face_rgb (F, 3) uint8)`.
    ceiling_cut: faces whose centroid is higher than (top − ceiling_cut) metres are hidden.
  """
  plt = _pyplot()
  from matplotlib.collections import PolyCollection
  tops = [np.asarray(v)[:, 2].max() for v, f, _ in meshes.values() if len(f)]
  z_max = (max(tops) if tops else 0.0) - ceiling_cut
  fig, axes = plt.subplots(1, len(meshes), figsize=(5 * len(meshes), 4.6), squeeze=False)
  view = np.array([1.0, 1.0, -1.2])
  view /= np.linalg.norm(view)
  right = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
  up = np.cross(right, view)
  light = -view + np.array([0.0, 0.0, 0.6])
  light /= np.linalg.norm(light)
  for ax, (title, (vertices, faces, rgb)) in zip(axes[0], meshes.items()):
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    tri = vertices[faces]                                   # (F, 3, 3)
    keep = tri.mean(axis=1)[:, 2] <= z_max
    tri, rgb = tri[keep], np.asarray(rgb, np.float64)[keep] / 255.0
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    shade = 0.35 + 0.65 * np.abs(normal @ light)
    order = np.argsort(tri.mean(axis=1) @ view)[::-1]       # far first
    xy = np.stack([tri @ right, tri @ up], axis=-1)[order]
    ax.add_collection(PolyCollection(xy, facecolors=rgb[order] * shade[order, None],
                                     edgecolors="none", antialiased=False))
    if len(xy):
      ax.set_xlim(xy[..., 0].min(), xy[..., 0].max())
      ax.set_ylim(xy[..., 1].min(), xy[..., 1].max())
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.axis("off")
  _save(fig, path)


def bands_vs_shift(path: str, shifts, panels: dict, *, ylabel: str = "%",
                   zero_line: bool = False, scale: float = 100.0) -> None:
  """Curves over the domain shift with shaded interval bands, one panel per quantity.

  Args:
    path: PNG destination.
    shifts: `(S,)` shift values (x axis).
    panels: panel title -> {curve name -> `(estimate, low, high)`, each `(S,)`}.
    ylabel: y-axis label.
    zero_line: draw y = 0 (for differences).
    scale: factor applied to all values (100: fractions shown in %).
  """
  plt = _pyplot()
  shifts = np.asarray(shifts, np.float64)
  fig, axes = plt.subplots(1, len(panels), figsize=(5.6 * len(panels), 4.0), squeeze=False)
  for ax, (title, curves) in zip(axes[0], panels.items()):
    for i, (name, (est, low, high)) in enumerate(curves.items()):
      color = f"C{i % 10}"
      ax.plot(shifts, scale * np.asarray(est), "o-", color=color, label=name, lw=1.6, ms=4)
      ax.fill_between(shifts, scale * np.asarray(low), scale * np.asarray(high), color=color,
                      alpha=0.15, lw=0)
    if zero_line:
      ax.axhline(0.0, color="black", lw=0.8)
    ax.set_title(title)
    ax.set_xlabel("domain shift")
    ax.set_ylabel(ylabel)
    ax.set_xticks(shifts)
    ax.grid(alpha=0.3)
  axes[0][0].legend(fontsize=8)
  _save(fig, path)


def headroom_bars(path: str, shifts, shares, category_names: Sequence[str],
                  recovered: dict) -> None:
  """Where a better fusion rule can win: the voxel headroom per shift and what rules recover.

  Args:
    path: PNG destination.
    shifts: `(S,)` shift values.
    shares: `(S, 3)` fractions of the scored GT voxels per headroom category (rows sum to 1).
    category_names: the 3 category labels (stacked bottom to top).
    recovered: method -> `(S,)` fraction of the middle category ("outvoted right") voxels the
      method labels correctly.
  """
  plt = _pyplot()
  shifts = np.asarray(shifts, np.float64)
  shares = np.asarray(shares, np.float64)
  labels = [f"{s:g}" for s in shifts]
  x = np.arange(len(shifts))
  fig, axes = plt.subplots(1, 2, figsize=(12, 4.0))
  bottom = np.zeros(len(shifts))
  for j, (name, color) in enumerate(zip(category_names, ("tab:green", "tab:orange", "tab:red"))):
    axes[0].bar(x, 100 * shares[:, j], 0.6, bottom=100 * bottom, label=name, color=color)
    bottom = bottom + shares[:, j]
  axes[0].set_xticks(x, labels)
  axes[0].set_xlabel("domain shift")
  axes[0].set_ylabel("% of scored GT voxels")
  axes[0].set_title("voxel headroom")
  axes[0].legend(fontsize=8)
  width = 0.8 / max(1, len(recovered))
  for i, (name, values) in enumerate(recovered.items()):
    axes[1].bar(x + (i - (len(recovered) - 1) / 2) * width, 100 * np.nan_to_num(values), width,
                label=name)
  axes[1].set_xticks(x, labels)
  axes[1].set_xlabel("domain shift")
  axes[1].set_ylabel("% recovered")
  axes[1].set_title(f"{category_names[1]} voxels a rule labels correctly")
  axes[1].legend(fontsize=8, ncol=2)
  _save(fig, path)


def alpha_histograms(path: str, shifts, bin_edges, right, wrong) -> None:
  """Distributions of the Dirichlet weight α of right and wrong pixel observations per shift.

  Args:
    path: PNG destination.
    shifts: `(S,)` shift values, one panel each.
    bin_edges: `(nb + 1,)` α bin edges.
    right: `(S, nb)` counts of right pixel observations per bin.
    wrong: `(S, nb)` counts of wrong pixel observations per bin.
  """
  plt = _pyplot()
  edges = np.asarray(bin_edges, np.float64)
  right = np.asarray(right, np.float64)
  wrong = np.asarray(wrong, np.float64)
  occupied = np.nonzero((right + wrong).sum(0))[0]
  lo, hi = (edges[occupied[0]], edges[occupied[-1] + 1]) if occupied.size else (edges[0],
                                                                                edges[-1])
  fig, axes = plt.subplots(1, len(shifts), figsize=(3.6 * len(shifts), 3.2), squeeze=False,
                           sharey=True)
  for ax, s, r, w in zip(axes[0], shifts, right, wrong):
    for counts, name, color in ((r, "right", "tab:green"), (w, "wrong", "tab:red")):
      total = counts.sum()
      density = counts / (total * np.diff(edges)) if total else counts
      ax.stairs(density, edges, label=f"{name} ({int(total)} px)", color=color, fill=True,
                alpha=0.35)
    ax.set_xlim(lo, hi)
    ax.set_title(f"shift {s:g}")
    ax.set_xlabel("α = −log var of the predicted class")
    ax.legend(fontsize=7)
  axes[0][0].set_ylabel("density")
  _save(fig, path)


def miou_vs_beta(path: str, betas, miou, *, title: str) -> None:
  """`jaxfusion sweep --plot`'s PNG: mIoU (%) against β."""
  plt = _pyplot()
  fig, ax = plt.subplots(figsize=(5, 3.2))
  ax.plot(betas, 100 * np.asarray(miou), "o-", ms=3)
  ax.set_xlabel("β")
  ax.set_ylabel("mIoU (%)")
  ax.set_title(title)
  ax.grid(alpha=0.3)
  fig.tight_layout()
  _save(fig, path, tight=False)


def objective_comparison(path: str, result: dict) -> None:
  """`jaxfusion tune-compare`'s PNG: mIoU and the two surrogates (rescaled to [0, 1], higher is
  better) against β on the calibration and held-out batches, with each objective's β*."""
  plt = _pyplot()
  betas = result["betas"]
  colors = {"soft_iou": "tab:orange", "cross_entropy": "tab:green"}
  fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharex=True)
  for ax, name in zip(axes, ("calibration", "held_out")):
    g = result["grid"][name]
    ax.plot(betas, 100 * g["miou"], "o-", ms=3, color="tab:blue", label="mIoU")
    ax.set_ylabel("mIoU (%)")
    ax.set_xlabel("β")
    ax.set_title(name.replace("_", "-"))
    twin = ax.twinx()
    for obj, color in colors.items():
      loss = np.asarray(g[obj], np.float64)
      span = np.nanmax(loss) - np.nanmin(loss)
      score = (np.nanmax(loss) - loss) / span if span > 0 else np.zeros_like(loss)
      twin.plot(betas, score, "--", color=color, label=f"−{obj} (rescaled)")
      ax.axvline(result["objectives"][obj]["beta_star"], color=color, lw=1)
    twin.set_ylim(-0.05, 1.05)
    twin.set_yticks([])
    if name == "held_out":
      lines = ax.get_legend_handles_labels()
      more = twin.get_legend_handles_labels()
      ax.legend(lines[0] + more[0], lines[1] + more[1], fontsize=7, loc="lower left")
  fig.suptitle("surrogate optima (vertical lines: β* by gradient on calibration)", fontsize=9)
  fig.tight_layout()
  _save(fig, path, tight=False)


def per_class_beta(path: str, result: dict, class_names: Sequence[str]) -> None:
  """`jaxfusion tune-protocol`'s PNG: the per-class β* as bars, the scalar β* and the baseline as
  lines."""
  plt = _pyplot()
  methods = result["methods"]
  per_class = methods["per-class β*"]["beta"]
  fig, ax = plt.subplots(figsize=(6, 3.2))
  x = np.arange(len(class_names))
  ax.bar(x, per_class, color="tab:orange", label="per-class β*")
  ax.axhline(methods["scalar β*"]["beta"], color="tab:green", ls="--",
             label=f"scalar β* = {methods['scalar β*']['beta']:.3f}")
  ax.axhline(methods[result["baseline"]]["beta"], color="grey", ls=":",
             label=result["baseline"])
  ax.set_xticks(x)
  ax.set_xticklabels(class_names, rotation=30, ha="right")
  ax.set_ylabel("β")
  ax.set_ylim(0, 1)
  ax.set_title(f"{result['rule']}: β tuned by {result['objective']} on "
               f"{len(result['calibration'])} calibration sequences", fontsize=9)
  ax.legend(fontsize=7)
  fig.tight_layout()
  _save(fig, path, tight=False)


def _param_label(param: str) -> str:
  return {"error_rate": "error rate e", "error_confidence": "error confidence c_e",
          "confidence": "confidence c", "variance_separation": "variance separation s (nats)",
          "cross_view_correlation": "cross-view correlation ρ",
          "alpha_right": "α on right pixels", "alpha_noise": "α scatter τ (nats)",
          "patch_size": "patch size ℓ (m)"}[param]


def simulation_heatmap(path: str, result: dict) -> None:
  """`jaxfusion simulate-sweep`'s 2×2 PNG: mIoU of Bayes and D+R, D+R − Bayes, oracle − Bayes (mean
  over draws, ± the standard deviation over draws in the difference panels when there are
  several); with a learned column, 2×3 with Learned − Bayes and Learned − D+R."""
  plt = _pyplot()
  rules = result["rules"]
  miou = 100.0 * np.asarray(result["miou"])           # (Y, X, D, R)
  bayes, dr, oracle = (miou[..., rules.index(n)] for n in ("Bayesian", "D+R", "Oracle"))
  panels = [("Bayesian mIoU (%)", bayes, "viridis", None),
            ("D+R mIoU (%)", dr, "viridis", None),
            ("D+R − Bayesian (mIoU points)", dr - bayes, "RdBu", "diff"),
            ("Oracle − Bayesian: headroom (mIoU points)", oracle - bayes, "RdBu", "diff")]
  if "Learned" in rules:                 # the learned rule's column: two more panels
    learned = miou[..., rules.index("Learned")]
    panels[2:2] = [("Learned − Bayesian (mIoU points)", learned - bayes, "RdBu", "diff")]
    panels.append(("Learned − D+R (mIoU points)", learned - dr, "RdBu", "diff"))
  x, y = result["x"], result["y"]
  cols = len(panels) // 2
  fig, axes = plt.subplots(2, cols, figsize=(5 * cols, 8))
  vmin = min(np.nanmin(bayes.mean(-1)), np.nanmin(dr.mean(-1)))
  vmax = max(np.nanmax(bayes.mean(-1)), np.nanmax(dr.mean(-1)))
  limit = max(max(np.nanmax(np.abs(v.mean(-1))) for _, v, _, kind in panels if kind), 0.5)
  for ax, (title, values, cmap, kind) in zip(axes.flat, panels):
    mean = values.mean(-1)
    std = values.std(-1)
    if kind == "diff":
      im = ax.imshow(mean, origin="lower", cmap=cmap, vmin=-limit, vmax=limit, aspect="auto")
    else:
      im = ax.imshow(mean, origin="lower", cmap=cmap, vmin=vmin, vmax=vmax, aspect="auto")
    for yi in range(len(y)):
      for xi in range(len(x)):
        text = f"{mean[yi, xi]:+.1f}" if kind else f"{mean[yi, xi]:.1f}"
        if kind and values.shape[-1] > 1:
          text += f"\n±{std[yi, xi]:.1f}"
        shade = im.norm(mean[yi, xi])        # white text on the dark ends of the colour map
        dark = shade < 0.35 if kind is None else abs(shade - 0.5) > 0.35
        ax.text(xi, yi, text, ha="center", va="center", fontsize=7,
                color="white" if dark else "black")
    ax.set_xticks(range(len(x)), [f"{v:g}" for v in x])
    ax.set_yticks(range(len(y)), [f"{v:g}" for v in y])
    ax.set_xlabel(_param_label(result["x_param"]))
    ax.set_ylabel(_param_label(result["y_param"]))
    ax.set_title(title, fontsize=10)
    fig.colorbar(im, ax=ax, shrink=0.8)
  fixed = ", ".join(f"{k} = {v:g}" for k, v in result["base"].items())
  spread = " (± s.d. over draws)" if result["num_draws"] > 1 else ""
  fig.suptitle(f"Simulated front end: {result['regions']} regions; {fixed}\n"
               f"{', '.join(result['sequences'])} × {result['num_draws']} draw(s){spread}, "
               f"β = {result['beta']:g}", fontsize=9)
  fig.tight_layout()

  _save(fig, path, dpi=110, tight=False)


def learned_rule_losses(path: str, result) -> None:
  """`learn-rule`'s loss curves: the training loss per step and the validation loss per
  evaluation, the kept step marked."""
  plt = _pyplot()
  fig, ax = plt.subplots(figsize=(5.5, 3.4))
  ax.plot(np.arange(len(result.train_losses)), result.train_losses, lw=1, label="training")
  steps, losses = zip(*result.validation)
  ax.plot(steps, losses, "o-", ms=3, label="validation (early stopping)")
  ax.axvline(result.best_step, color="gray", ls="--", lw=1, label=f"kept: step {result.best_step}")
  ax.set_xlabel("Adam step")
  ax.set_ylabel("cross-entropy −log P(gt)")
  ax.grid(alpha=0.3)
  ax.legend(fontsize=8)
  fig.tight_layout()
  _save(fig, path, tight=False)


def learned_rule_weights(path: str, hparams: dict, *, num_classes: int,
                         alpha_bar=(6.9078, 12.0)) -> None:
  """The learned per-pixel weight `w` over (α of the predicted class, max probability), beside
  D's weight of a pixel's log-likelihood relative to the voxel's running maximum, α/ᾱ."""
  from jaxfusion import learn  # pylint: disable=import-outside-toplevel
  plt = _pyplot()
  alphas = np.linspace(1.4, 14.0, 64)
  tops = np.linspace(1.0 / num_classes + 1e-3, 1.0, 64)
  grid = np.asarray(learn.weight_grid(hparams, alphas, tops, num_classes=num_classes))
  fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
  im = a.imshow(grid.T, origin="lower", aspect="auto", vmin=0, vmax=1, cmap="viridis",
                extent=(alphas[0], alphas[-1], tops[0], tops[-1]))
  fig.colorbar(im, ax=a, label="w")
  a.set_xlabel("α of the predicted class, −log(var + ε)")
  a.set_ylabel("max probability")
  a.set_title("learned weight w = sigmoid(θ·φ + b)")
  for bar in alpha_bar:
    b.plot(alphas, np.minimum(alphas / bar, 1.0), label=f"D: α/ᾱ, ᾱ = {bar:g}")
  b.plot(alphas, grid[:, -1], "k--", label="learned w at max prob 1")
  b.plot(alphas, grid[:, len(tops) // 2], "k:", label=f"learned w at max prob {tops[32]:.2f}")
  b.set_xlabel("α of the predicted class")
  b.set_ylabel("weight of the pixel's log-likelihood")
  b.set_ylim(0, 1.05)
  b.grid(alpha=0.3)
  b.legend(fontsize=8)
  fig.tight_layout()
  _save(fig, path, tight=False)
