"""A compact DeepLab-v3-style segmentation network with Monte-Carlo dropout (Flax NNX).

The paper's front end is DeepLab-v3 with a dropout layer (rate 0.3) after each ResNet block,
kept active at test time. This is the same recipe sized for a CPU: a strided stem, residual
blocks (GroupNorm, so the model has no batch statistics and is a pure function of its
parameters), a dropout layer after every block, an atrous spatial pyramid pooling (ASPP) head
and bilinear upsampling of the logits to the input size. Width, depth, strides, dilations and
ASPP rates are configuration (`SegNetConfig`), never constants; checkpoints store their own.
The default (493 k parameters) is the first shipped net's architecture (`segnet_v1`); the
default shipped net is wider (`models/weights/segnet.json`, 980 k parameters, `input_norm`);
`resnet18_config()` is the deeper ResNet-18-like variant (2.9 M parameters) that a 45-minute
CPU budget could not train well (see models/weights/MODEL_CARD.md).

Dropout draws its mask from a key passed at call time, so the module holds no RNG state:
`nnx.split(model)` yields only `nnx.Param`s and `apply` is a pure function of
`(params, key, images)`.

Shape legend: B images, H×W pixels, K classes, C channels.
"""

import dataclasses
import functools
import json
from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

# The embedded world's classes, in label order (see jaxfusion.datasets.synthetic).
DEFAULT_CLASS_NAMES = ("background", "bottle", "chair", "table", "plant", "sofa", "tv")


@dataclasses.dataclass(frozen=True)
class SegNetConfig:
  """Architecture of `SegNet`. Everything that changes parameter shapes lives here.

  Attributes:
    num_classes: K, the number of output classes.
    stem_width: channels of the stride-2 stem convolution.
    widths: channels of each encoder stage.
    strides: stride of each stage's first block (the stem adds a factor 2).
    dilations: dilation of each stage's 3×3 convolutions (atrous stages keep resolution).
    blocks_per_stage: residual blocks per stage; each block is followed by dropout.
    aspp_width: channels of every ASPP branch and of the head.
    aspp_rates: dilation rates of the 3×3 ASPP branches (besides the 1×1 and pooling branches).
    dropout_rate: probability of zeroing an activation; 0.3 in the paper.
    norm_groups: GroupNorm groups; must divide every width.
    input_norm: standardise each image per colour channel (zero mean, unit standard deviation
      over its pixels) before the stem, so a global colour cast, exposure or contrast change
      of the whole frame does not reach the network. False keeps the raw [0, 1] input (the
      first shipped net, segnet_v1; the default shipped net uses True).
  """

  num_classes: int = 7
  stem_width: int = 24
  widths: tuple[int, ...] = (24, 48, 64, 96)
  strides: tuple[int, ...] = (1, 2, 2, 1)
  dilations: tuple[int, ...] = (1, 1, 1, 2)
  blocks_per_stage: int = 1
  aspp_width: int = 64
  aspp_rates: tuple[int, ...] = (2, 4, 6)
  dropout_rate: float = 0.3
  norm_groups: int = 8
  input_norm: bool = False

  def __post_init__(self):
    if self.num_classes < 2:
      raise ValueError(f"num_classes must be >= 2; got {self.num_classes}")
    if not (len(self.widths) == len(self.strides) == len(self.dilations)) or not self.widths:
      raise ValueError(
          "widths, strides and dilations must be non-empty and of equal length; got "
          f"{self.widths}, {self.strides}, {self.dilations}")
    if self.blocks_per_stage < 1:
      raise ValueError(f"blocks_per_stage must be >= 1; got {self.blocks_per_stage}")
    if not 0.0 <= self.dropout_rate < 1.0:
      raise ValueError(f"dropout_rate must be in [0, 1); got {self.dropout_rate}")
    for width in (self.stem_width, self.aspp_width, *self.widths):
      if width % self.norm_groups:
        raise ValueError(
            f"norm_groups={self.norm_groups} must divide every width; {width} is not divisible")

  @property
  def output_stride(self) -> int:
    """Downsampling factor of the encoder (stem × stage strides)."""
    stride = 2
    for s in self.strides:
      stride *= s
    return stride

  @property
  def num_dropout_layers(self) -> int:
    """Dropout layers: one after each residual block and one after the ASPP projection."""
    return len(self.widths) * self.blocks_per_stage + 1

  def to_dict(self) -> dict[str, Any]:
    """JSON-ready dict (tuples become lists)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

  @classmethod
  def from_dict(cls, data: dict[str, Any]) -> "SegNetConfig":
    """Inverse of `to_dict`; unknown keys are an error."""
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - fields
    if unknown:
      raise ValueError(f"unknown SegNetConfig fields {sorted(unknown)}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})

  def to_json(self) -> str:
    return json.dumps(self.to_dict(), sort_keys=True)


def tiny_config(num_classes: int = 7) -> SegNetConfig:
  """A very small configuration for tests: one residual stage, ~3k parameters, output
  stride 4, two dropout layers (compiles in seconds on a CPU)."""
  return SegNetConfig(
      num_classes=num_classes, stem_width=8, widths=(8,), strides=(2,), dilations=(1,),
      blocks_per_stage=1, aspp_width=8, aspp_rates=(2,), dropout_rate=0.3, norm_groups=4)


def resnet18_config(num_classes: int = 7) -> SegNetConfig:
  """ResNet-18-like DeepLab-v3: four stages of two basic blocks (widths 32/64/128/192), a
  stride-4 entry (stem and first stage), atrous rates 2 and 4 in the last two stages for output
  stride 8, a 128-channel ASPP; dropout 0.3 after each of the 8 blocks and the ASPP. 2.9 M
  parameters, about twice the training cost per step of the default on a CPU."""
  return SegNetConfig(
      num_classes=num_classes, stem_width=24, widths=(32, 64, 128, 192), strides=(2, 2, 1, 1),
      dilations=(1, 1, 2, 4), blocks_per_stage=2, aspp_width=128, aspp_rates=(2, 4, 6),
      dropout_rate=0.3, norm_groups=8)


class ConvNormAct(nnx.Module):
  """Conv → GroupNorm → ReLU."""

  def __init__(self, in_ch: int, out_ch: int, kernel: int, *, stride: int = 1,
               dilation: int = 1, groups: int, act: bool = True, rngs: nnx.Rngs):
    self.conv = nnx.Conv(in_ch, out_ch, (kernel, kernel), strides=stride,
                         kernel_dilation=dilation, padding="SAME", use_bias=False, rngs=rngs)
    self.norm = nnx.GroupNorm(out_ch, num_groups=groups, rngs=rngs)
    self.act = act

  def __call__(self, x: jax.Array) -> jax.Array:
    x = self.norm(self.conv(x))
    return jax.nn.relu(x) if self.act else x


class ResidualBlock(nnx.Module):
  """Basic ResNet block: two 3×3 convs, projection shortcut when the shape changes."""

  def __init__(self, in_ch: int, out_ch: int, *, stride: int, dilation: int, groups: int,
               rngs: nnx.Rngs):
    self.conv1 = ConvNormAct(in_ch, out_ch, 3, stride=stride, dilation=dilation, groups=groups,
                             rngs=rngs)
    self.conv2 = ConvNormAct(out_ch, out_ch, 3, dilation=dilation, groups=groups, act=False,
                             rngs=rngs)
    if stride != 1 or in_ch != out_ch:
      self.shortcut = ConvNormAct(in_ch, out_ch, 1, stride=stride, groups=groups, act=False,
                                  rngs=rngs)
    else:
      self.shortcut = None

  def __call__(self, x: jax.Array) -> jax.Array:
    skip = x if self.shortcut is None else self.shortcut(x)
    return jax.nn.relu(self.conv2(self.conv1(x)) + skip)


class ASPP(nnx.Module):
  """Atrous spatial pyramid pooling: 1×1, dilated 3×3 branches and image pooling, projected."""

  def __init__(self, in_ch: int, width: int, rates: tuple[int, ...], *, groups: int,
               rngs: nnx.Rngs):
    self.branch1x1 = ConvNormAct(in_ch, width, 1, groups=groups, rngs=rngs)
    self.atrous = nnx.List([
        ConvNormAct(in_ch, width, 3, dilation=r, groups=groups, rngs=rngs) for r in rates])
    self.pool = ConvNormAct(in_ch, width, 1, groups=groups, rngs=rngs)
    self.project = ConvNormAct(width * (len(rates) + 2), width, 1, groups=groups, rngs=rngs)

  def __call__(self, x: jax.Array) -> jax.Array:
    branches = [self.branch1x1(x)] + [branch(x) for branch in self.atrous]
    pooled = self.pool(jnp.mean(x, axis=(1, 2), keepdims=True))
    branches.append(jnp.broadcast_to(pooled, branches[0].shape))
    return self.project(jnp.concatenate(branches, axis=-1))


class SegNet(nnx.Module):
  """DeepLab-v3-style segmentation net with a dropout layer after each residual block."""

  def __init__(self, config: SegNetConfig, *, rngs: nnx.Rngs):
    self.config = config
    groups = config.norm_groups
    self.stem = ConvNormAct(3, config.stem_width, 3, stride=2, groups=groups, rngs=rngs)
    blocks = []
    in_ch = config.stem_width
    for width, stride, dilation in zip(config.widths, config.strides, config.dilations):
      for b in range(config.blocks_per_stage):
        blocks.append(ResidualBlock(in_ch, width, stride=stride if b == 0 else 1,
                                    dilation=dilation, groups=groups, rngs=rngs))
        in_ch = width
    self.blocks = nnx.List(blocks)
    self.aspp = ASPP(in_ch, config.aspp_width, config.aspp_rates, groups=groups, rngs=rngs)
    self.head = ConvNormAct(config.aspp_width, config.aspp_width, 3, groups=groups, rngs=rngs)
    self.classifier = nnx.Conv(config.aspp_width, config.num_classes, (1, 1), rngs=rngs)
    # Masks come from the key passed to __call__; the layer itself holds no RNG state.
    self.dropout = nnx.Dropout(config.dropout_rate, rngs=None)

  def __call__(self, images: jax.Array, *, key: jax.Array | None,
               deterministic: bool) -> jax.Array:
    """Per-pixel class logits.

    Args:
      images: `(B, H, W, 3)` float32 RGB in [0, 1].
      key: PRNG key for the dropout masks; may be None when `deterministic`.
      deterministic: True turns dropout off (the baselines); False is MC dropout.

    Returns:
      `(B, H, W, K)` float32 logits at the input resolution.
    """
    return self.from_shared(self.shared(images), (images.shape[1], images.shape[2]), key=key,
                            deterministic=deterministic)

  def shared(self, images: jax.Array) -> jax.Array:
    """The part of the forward pass before the first dropout layer (input normalisation, stem
    and first residual block): the same for every MC-dropout sample of an image.

    Args:
      images: `(B, H, W, 3)` float32 RGB in [0, 1].

    Returns:
      `(B, h, w, C)` float32 features of the first block, before its dropout.
    """
    assert images.ndim == 4 and images.shape[-1] == 3, images.shape
    if self.config.input_norm:
      images = standardize(images)
    return self.blocks[0](self.stem(images))

  def from_shared(self, features: jax.Array, size: tuple[int, int], *, key: jax.Array | None,
                  deterministic: bool) -> jax.Array:
    """The rest of the forward pass, from `shared`'s features: every dropout layer and after.

    `from_shared(shared(x), x.shape[1:3], key=k, ...)` is `__call__(x, key=k, ...)`, so an MC
    sampler computes `shared` once per image and this once per dropout key.

    Args:
      features: `(B, h, w, C)` from `shared`.
      size: `(H, W)` of the input images (the logits are resized to it).
      key: PRNG key for the dropout masks; may be None when `deterministic`.
      deterministic: True turns dropout off.

    Returns:
      `(B, H, W, K)` float32 logits.
    """
    if not deterministic and key is None:
      raise ValueError("MC dropout (deterministic=False) needs a PRNG key")
    keys = (jax.random.split(key, self.config.num_dropout_layers) if not deterministic
            else [None] * self.config.num_dropout_layers)
    x = self.dropout(features, deterministic=deterministic, rngs=keys[0])
    for i, block in enumerate(self.blocks[1:], start=1):
      x = self.dropout(block(x), deterministic=deterministic, rngs=keys[i])
    x = self.dropout(self.aspp(x), deterministic=deterministic, rngs=keys[-1])
    logits = self.classifier(self.head(x))
    return jax.image.resize(
        logits, (logits.shape[0], size[0], size[1], logits.shape[-1]), method="bilinear")


def standardize(images: jax.Array, eps: float = 0.02) -> jax.Array:
  """Per-image, per-channel standardisation: `(x − mean) / max(std, eps)`.

  Args:
    images: `(B, H, W, C)` float32.
    eps: floor of the standard deviation, so a flat (e.g. all-black) image stays finite.

  Returns:
    `(B, H, W, C)` float32 with zero mean and (unless flat) unit standard deviation per image
    and channel.
  """
  mean = jnp.mean(images, axis=(1, 2), keepdims=True)
  std = jnp.sqrt(jnp.mean(jnp.square(images - mean), axis=(1, 2), keepdims=True))
  return (images - mean) / jnp.maximum(std, eps)


def init(config: SegNetConfig, *, key: jax.Array) -> tuple[nnx.GraphDef, nnx.State]:
  """Builds a `SegNet` and splits it into a static graph and its parameters.

  Args:
    config: the architecture.
    key: PRNG key for the initial weights.

  Returns:
    `(graphdef, params)`: `graphdef` is static (hashable, pass it as a static jit argument);
    `params` is an `nnx.State` pytree of float32 arrays.
  """
  graphdef, _ = abstract_params(config)
  return graphdef, _init_params(config, key)


def _split(config: SegNetConfig, key: jax.Array) -> tuple[nnx.GraphDef, nnx.State]:
  model = SegNet(config, rngs=nnx.Rngs(params=key))
  graphdef, params, rest = nnx.split(model, nnx.Param, ...)
  assert not jax.tree_util.tree_leaves(rest), "SegNet must hold nothing but parameters"
  return graphdef, params


@functools.partial(jax.jit, static_argnums=0)
def _init_params(config: SegNetConfig, key: jax.Array) -> nnx.State:
  # One compiled call instead of dozens of eagerly dispatched initialiser ops.
  return _split(config, key)[1]


def abstract_params(config: SegNetConfig) -> tuple[nnx.GraphDef, nnx.State]:
  """`(graphdef, params)` with `jax.ShapeDtypeStruct` leaves; allocates nothing."""
  return nnx.eval_shape(lambda: _split(config, jax.random.key(0)))


def apply(graphdef: nnx.GraphDef, params: nnx.State, key: jax.Array | None,
          images: jax.Array, *, deterministic: bool) -> jax.Array:
  """Pure forward pass: `(B, H, W, 3)` float32 images → `(B, H, W, K)` float32 logits."""
  model = nnx.merge(graphdef, params)
  return model(images, key=key, deterministic=deterministic)


def apply_shared(graphdef: nnx.GraphDef, params: nnx.State, images: jax.Array) -> jax.Array:
  """`SegNet.shared` as a pure function: the key-independent start of the forward pass."""
  return nnx.merge(graphdef, params).shared(images)


def apply_from_shared(graphdef: nnx.GraphDef, params: nnx.State, key: jax.Array | None,
                      features: jax.Array, size: tuple[int, int], *,
                      deterministic: bool) -> jax.Array:
  """`SegNet.from_shared` as a pure function: `apply` = `apply_from_shared ∘ apply_shared`."""
  return nnx.merge(graphdef, params).from_shared(features, size, key=key,
                                                 deterministic=deterministic)


def count_params(params: nnx.State) -> int:
  """Total number of scalar parameters."""
  return int(sum(leaf.size for leaf in jax.tree_util.tree_leaves(params)))
