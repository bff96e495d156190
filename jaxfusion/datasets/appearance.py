"""Appearance domains: palettes, procedural textures, lighting and shading.

Two domains exist, `"train"` and `"test"`. Each material slot (a class part such as a chair
seat, or a structure such as the floor) has a train palette, a test palette and texture
choices per domain. A domain is reduced to one number, the *shift* `s ∈ [0, 1]`: `s = 0` is
the train domain, and the test domain with `shift` uses `s = shift`. Colours, lighting and
shape proportions are interpolated between the train and the test extremes by `s`; discrete
choices (which texture) switch to the test choice with probability `s`. So `shift = 0` makes
"test" identical to "train", and `shift = 1` gives the full domain gap.

Shape legend: N pixels.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion.datasets.primitives import (CHECKER, NOISE, PLAIN, SCREEN, STRIPES, WOOD,
                                           Material)

DOMAINS = ("train", "test")


def domain_shift(domain: str, shift: float) -> float:
  """The interpolation weight `s` of a domain: 0 for "train", `shift` for "test"."""
  if domain not in DOMAINS:
    raise ValueError(f"unknown domain {domain!r}; expected one of {DOMAINS}")
  if not 0.0 <= shift <= 1.0:
    raise ValueError(f"shift must lie in [0, 1]; got {shift}")
  return 0.0 if domain == "train" else float(shift)


def lerp(a, b, s):
  """`a + s·(b − a)` on NumPy values."""
  return np.asarray(a, np.float64) + s * (np.asarray(b, np.float64) - np.asarray(a, np.float64))


def _rgb(*hexes):
  return np.array([[int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4)] for h in hexes])


class Palette(NamedTuple):
  """Colours and textures of one material slot in the two domains."""
  train: np.ndarray  # (n, 3) colours
  test: np.ndarray  # (m, 3) colours
  train_textures: tuple
  test_textures: tuple
  scale: tuple  # (low, high) texture frequency in cycles per metre
  contrast: tuple  # (train, test) strength of the secondary texture colour


PALETTES = {
    # Classes.
    "chair": Palette(_rgb("2B2B2E", "3A4A6B", "6B4A2E", "50555C"),
                     _rgb("F08A24", "E9E4D8", "2E7D4F", "D46A9B"),
                     (PLAIN, NOISE), (STRIPES, CHECKER), (8, 20), (0.15, 0.5)),
    "chair_legs": Palette(_rgb("1E1E1E", "8A8D91"), _rgb("C9A227", "F2F2F2"),
                          (PLAIN,), (PLAIN,), (1, 2), (0.0, 0.0)),
    "table": Palette(_rgb("C8A27A", "E8E6E1", "2A2A2A"), _rgb("4A2C1A", "6FA8A0", "A9A9B3"),
                     (WOOD, PLAIN), (NOISE, CHECKER), (4, 10), (0.25, 0.45)),
    "table_legs": Palette(_rgb("2A2A2A", "B0B3B8", "8C6A48"), _rgb("D4AF37", "1B3F8B"),
                          (PLAIN,), (PLAIN,), (1, 2), (0.0, 0.0)),
    "sofa": Palette(_rgb("7D7F83", "C9B79C", "2F3B57"), _rgb("D9A520", "1F7A5A", "9E2B25"),
                    (NOISE, PLAIN), (STRIPES, CHECKER), (6, 14), (0.15, 0.5)),
    "tv_frame": Palette(_rgb("151515", "2A2A2C"), _rgb("C8CCD0", "F4F4F4", "B5653A"),
                        (PLAIN,), (PLAIN,), (1, 2), (0.0, 0.0)),
    "tv_screen": Palette(_rgb("08090B", "10141A"), _rgb("3A6FD8", "E04A8A", "38B26A"),
                         (PLAIN,), (SCREEN,), (6, 14), (0.0, 1.0)),
    "bottle": Palette(_rgb("2F6B3A", "A8C0C8", "6B3A1E"), _rgb("D7263D", "F5F5F5", "5B2A86"),
                      (PLAIN,), (STRIPES, PLAIN), (20, 40), (0.0, 0.6)),
    "bottle_cap": Palette(_rgb("D9D9D9", "1A1A1A"), _rgb("F2C14E", "2B9EB3"),
                          (PLAIN,), (PLAIN,), (1, 2), (0.0, 0.0)),
    "foliage": Palette(_rgb("3E8E3A", "2F7D32", "4FA345"), _rgb("6B7D2A", "1E4D2B", "9DB82E"),
                       (NOISE,), (NOISE, STRIPES), (10, 25), (0.35, 0.6)),
    "pot": Palette(_rgb("B5562B", "8F4A2C"), _rgb("F0F0F0", "1C1C1C", "2F5D9E"),
                   (PLAIN,), (CHECKER, PLAIN), (10, 20), (0.0, 0.4)),
    # Background structure and clutter.
    "wall": Palette(_rgb("EDEAE3", "E4E1D6", "D9DCDF"), _rgb("A9C6E0", "E8B7B0", "C7D9B7"),
                    (PLAIN, NOISE), (STRIPES, NOISE), (2, 5), (0.05, 0.25)),
    "floor": Palette(_rgb("6E6E70", "8A8178", "5A5F66"), _rgb("9C6B3E", "C2B59B", "3D3D3D"),
                     (NOISE,), (WOOD, CHECKER), (2, 6), (0.2, 0.45)),
    "ceiling": Palette(_rgb("F2F2F2"), _rgb("E9E1D0", "DDE4EA"), (PLAIN,), (PLAIN, NOISE),
                       (1, 3), (0.0, 0.1)),
    "door": Palette(_rgb("B08A60", "E6E3DC"), _rgb("5C3A21", "2E4E6F", "8C2F39"),
                    (WOOD, PLAIN), (PLAIN, STRIPES), (3, 8), (0.2, 0.3)),
    "window": Palette(_rgb("BFD9F2", "CFE3F5"), _rgb("F7D9A8", "9FC5E8"), (PLAIN,), (PLAIN,),
                      (1, 2), (0.0, 0.0)),
    "frame": Palette(_rgb("F4F4F4", "3B3B3B"), _rgb("6B4226", "B0B0B0"), (PLAIN,), (PLAIN,),
                     (1, 2), (0.0, 0.0)),
    "shelf": Palette(_rgb("B8925F", "EFEFEF", "3C3C3C"), _rgb("5E3B22", "7A8C99", "C04E2E"),
                     (WOOD, PLAIN), (NOISE, PLAIN), (4, 9), (0.2, 0.35)),
    "cardboard": Palette(_rgb("B48A57", "C49A66"), _rgb("8E6B45", "D8C3A5", "4F6D7A"),
                         (NOISE,), (NOISE, STRIPES), (10, 20), (0.15, 0.3)),
    "lamp": Palette(_rgb("F3E9D2", "FFFFFF"), _rgb("F2B705", "E8E0FF"), (PLAIN,), (PLAIN,),
                    (1, 2), (0.0, 0.0)),
    "metal": Palette(_rgb("3A3A3A", "9A9EA3"), _rgb("B8860B", "D9D9D9"), (PLAIN,), (PLAIN,),
                     (1, 2), (0.0, 0.0)),
    "picture": Palette(_rgb("3F6FB5", "C9463D", "E0B13A", "2F8F6F"),
                       _rgb("111111", "6A1B9A", "00897B", "F4511E"),
                       (STRIPES, CHECKER, NOISE), (SCREEN, NOISE, STRIPES), (4, 12), (0.6, 0.7)),
    "rug": Palette(_rgb("8C2F39", "3D5A80", "9C8F7A"), _rgb("2A9D8F", "E9C46A", "6D597A"),
                   (STRIPES, NOISE), (CHECKER, NOISE), (3, 8), (0.3, 0.45)),
    "light_panel": Palette(_rgb("FFFFFF"), _rgb("FFF1D6"), (PLAIN,), (PLAIN,), (1, 2),
                           (0.0, 0.0)),
}


# Glossiness of each material slot, the same in both domains (a property of what the surface
# is made of, not of its colour): glass, screens, lacquer and metal are glossy; fabric, foliage,
# cardboard, rugs and painted walls and ceilings are (nearly) matte. Used by `sensing` only.
GLOSS = {
    "chair": 0.35, "chair_legs": 0.8, "table": 0.6, "table_legs": 0.8, "sofa": 0.1,
    "tv_frame": 0.7, "tv_screen": 1.0, "bottle": 1.0, "bottle_cap": 0.6, "foliage": 0.3,
    "pot": 0.7, "wall": 0.05, "floor": 0.35, "ceiling": 0.0, "door": 0.4, "window": 1.0,
    "frame": 0.5, "shelf": 0.4, "cardboard": 0.05, "lamp": 0.3, "metal": 0.9, "picture": 0.5,
    "rug": 0.0, "light_panel": 0.0,
}


def material(slot: str, u, s: float, *, emission: float = 0.0) -> Material:
  """Picks the material of one part, deterministically from 4 uniform draws.

  Args:
    slot: key of `PALETTES`.
    u: `(4,)` uniforms in [0, 1): colour pick, brightness, texture pick, texture scale.
    s: domain interpolation weight (0 = train, 1 = full test domain).
    emission: self-illumination.

  Returns:
    A `Material` whose colour lies `s` of the way from the train pick to the test pick, with
    the slot's glossiness `GLOSS[slot]`.
  """
  pal = PALETTES[slot]
  u = np.asarray(u, np.float64)
  train_col = pal.train[int(u[0] * len(pal.train)) % len(pal.train)]
  test_col = pal.test[int(u[0] * len(pal.test)) % len(pal.test)]
  color = np.clip(lerp(train_col, test_col, s) * (0.85 + 0.3 * u[1]), 0.0, 1.0)
  textures = pal.test_textures if u[2] < s else pal.train_textures
  texture = textures[int(u[3] * 7919) % len(textures)]
  contrast = float(lerp(pal.contrast[0], pal.contrast[1], s))
  if texture == SCREEN:
    color2 = color
  else:
    # The secondary colour: darker (train) or hue-rotated (test) version of the base colour.
    color2 = lerp(color * (1.0 - contrast), np.roll(color, 1) * (1.0 - 0.5 * contrast), s)
  scale = float(lerp(pal.scale[0], pal.scale[1], u[3]))
  return Material(color, np.clip(color2, 0.0, 1.0), int(texture), scale, float(emission),
                  GLOSS[slot])


class Lighting(NamedTuple):
  """Scene lighting (all `float32` arrays, a pytree).

  Attributes:
    ambient: `(3,)` ambient light colour.
    sun_dir: `(3,)` unit direction the directional light travels.
    sun_color: `(3,)` directional light colour.
    lamp_pos: `(3,)` point light position (world).
    lamp_color: `(3,)` point light colour.
    specular: scalar strength of the specular highlight.
    exposure: scalar multiplier of the final colour.
  """
  ambient: np.ndarray
  sun_dir: np.ndarray
  sun_color: np.ndarray
  lamp_pos: np.ndarray
  lamp_color: np.ndarray
  specular: np.ndarray
  exposure: np.ndarray


def lighting(room_size, u, s: float) -> Lighting:
  """Lighting of a room in a domain.

  Args:
    room_size: `(3,)` room extent in metres (x, y, height).
    u: `(4,)` uniforms that jitter the light.
    s: domain interpolation weight.

  Returns:
    `Lighting`: neutral, bright and diffuse for "train"; warm, dimmer, directional with strong
    highlights for "test".
  """
  u = np.asarray(u, np.float64)
  room = np.asarray(room_size, np.float64)
  sun_train = np.array([0.3 + 0.2 * u[0], 0.5, -1.0])
  sun_test = np.array([-0.8, 0.2 + 0.3 * u[0], -0.45])
  sun = lerp(sun_train, sun_test, s)
  f32 = lambda x: np.asarray(x, np.float32)
  return Lighting(
      ambient=f32(lerp([0.42, 0.42, 0.43], [0.22, 0.19, 0.17], s) * (0.9 + 0.2 * u[1])),
      sun_dir=f32(sun / np.linalg.norm(sun)),
      sun_color=f32(lerp([0.45, 0.45, 0.45], [0.85, 0.62, 0.38], s)),
      lamp_pos=f32([room[0] * (0.3 + 0.4 * u[2]), room[1] * (0.3 + 0.4 * u[3]), room[2] - 0.3]),
      lamp_color=f32(lerp([0.35, 0.35, 0.35], [0.9, 0.7, 0.45], s)),
      specular=f32(lerp(0.05, 0.35, s)),
      exposure=f32(lerp(1.0, 1.15, s)),
  )


def _hash_bits(ix, iy, iz):
  """`uint32` pseudo-random bits per integer cell (integer mixing, no trigonometry)."""
  h = (ix.astype(jnp.uint32) * jnp.uint32(73856093)) ^ (
      iy.astype(jnp.uint32) * jnp.uint32(19349663)) ^ (iz.astype(jnp.uint32) * jnp.uint32(83492791))
  h = (h ^ (h >> 15)) * jnp.uint32(0x2C1B3C6D)
  h = (h ^ (h >> 12)) * jnp.uint32(0x297A2D39)
  return h ^ (h >> 15)


def _unit(bits, shift: int):
  """8 bits of `bits` starting at `shift`, as a float in [0, 1)."""
  return ((bits >> shift) & 0xFF).astype(jnp.float32) / 256.0


def value_noise(p):
  """Smooth 3-D value noise in [0, 1) at points `p (..., 3)` (trilinear over hashed cells)."""
  cell = jnp.floor(p)
  f = p - cell
  w = f * f * (3.0 - 2.0 * f)
  i = cell.astype(jnp.int32)
  ix, iy, iz = i[..., 0], i[..., 1], i[..., 2]
  wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]

  def corner(dx, dy, dz):
    return _unit(_hash_bits(ix + dx, iy + dy, iz + dz), 8)

  def along_x(dy, dz):
    a = corner(0, dy, dz)
    return a + wx * (corner(1, dy, dz) - a)

  y0 = along_x(0, 0) + wy * (along_x(1, 0) - along_x(0, 0))
  y1 = along_x(0, 1) + wy * (along_x(1, 1) - along_x(0, 1))
  return y0 + wz * (y1 - y0)


def texture(p_local, texture_id, scale, color, color2, *, footprint=None):
  """Solid procedural textures evaluated at local hit points.

  Args:
    p_local: `(N, 3) float32` hit points in the primitive frame (metres).
    texture_id: `(N,) int32` texture ids.
    scale: `(N,) float32` cycles per metre.
    color: `(N, 3)` base colour.
    color2: `(N, 3)` secondary colour.
    footprint: optional `(N,)` σ in metres of the pixel's filter on the surface (see
      `sensing.pixel_footprint`). A camera pixel integrates light over its area, so pattern
      detail finer than the pixel averages out: each pattern's contrast is scaled by the
      Gaussian filter's response `exp(−2π² (freq · footprint)²)` at its frequency, fading far
      and grazing textures to their mean colour. None: point samples, as a plain ray caster.

  Returns:
    `(N, 3) float32` albedo.
  """
  f = p_local * scale[:, None] + 0.37
  stripes = (jnp.sin(2 * jnp.pi * (f[:, 0] + 0.2 * f[:, 2])) > 0).astype(jnp.float32)
  checker = jnp.mod(jnp.sum(jnp.floor(f), axis=-1), 2.0)
  n1 = value_noise(f)
  cell = jnp.floor(4.0 * f).astype(jnp.int32)
  fine = _unit(_hash_bits(cell[:, 0], cell[:, 1], cell[:, 2]), 0)  # speckle on the noise
  grain = jnp.mod(f[:, 0] * 0.5 + 0.15 * jnp.sin(2.0 * f[:, 1]) + 0.6 * n1, 1.0)
  wood = jnp.clip(jnp.abs(2.0 * grain - 1.0) ** 2, 0.0, 1.0)
  block = jnp.floor(f * jnp.array([1.0, 1.0, 0.5])).astype(jnp.int32)
  bits = _hash_bits(block[:, 0], block[:, 1], block[:, 2])
  screen_rgb = jnp.stack([_unit(bits, 0), _unit(bits, 8), _unit(bits, 16)], -1)
  if footprint is not None:
    response = lambda freq: jnp.exp(-2.0 * jnp.pi ** 2 * jnp.square(freq * footprint))
    base, speckle = response(scale), response(4.0 * scale)
    toward = lambda x, mean, r: mean + r * (x - mean)  # contrast around the pattern's mean
    stripes, checker = toward(stripes, 0.5, base), toward(checker, 0.5, base)
    n1, fine = toward(n1, 0.5, base), toward(fine, 0.5, speckle)
    wood = toward(wood, 1.0 / 3.0, base)
    screen_rgb = toward(screen_rgb, 0.5, base[:, None])
  noise = jnp.clip(0.75 * n1 + 0.25 * fine, 0.0, 1.0)
  mix = jnp.select([texture_id == STRIPES, texture_id == CHECKER, texture_id == WOOD,
                    texture_id == NOISE], [stripes, checker, wood, noise], 0.0)
  albedo = color + mix[:, None] * (color2 - color)
  screen = 0.35 * color + 0.65 * screen_rgb
  return jnp.where((texture_id == SCREEN)[:, None], screen, albedo)


def shade(albedo, normal, p_world, view_dir, emission, light: Lighting, *, clip: bool = True):
  """Lambert + Blinn-Phong shading with a directional and a point light.

  Args:
    albedo: `(N, 3)` surface colour.
    normal: `(N, 3)` unit normals facing the camera.
    p_world: `(N, 3)` hit points.
    view_dir: `(N, 3)` unit ray directions.
    emission: `(N,)` self-illumination in [0, 1].
    light: `Lighting`.
    clip: clip to [0, 1] (a fixed-exposure image); False returns the radiance (≥ 0) that
      `sensing.camera_image` exposes.

  Returns:
    `(N, 3) float32` linear colour in [0, 1] (or ≥ 0 without `clip`).
  """
  to_sun = -light.sun_dir
  sun = jnp.maximum(jnp.sum(normal * to_sun, -1, keepdims=True), 0.0) * light.sun_color
  to_lamp = light.lamp_pos - p_world
  dist2 = jnp.sum(to_lamp * to_lamp, -1, keepdims=True)
  to_lamp = to_lamp * jax.lax.rsqrt(jnp.maximum(dist2, 1e-6))
  lamp = (jnp.maximum(jnp.sum(normal * to_lamp, -1, keepdims=True), 0.0)
          * light.lamp_color / (1.0 + 0.08 * dist2))
  half = to_lamp - view_dir
  half = half / jnp.maximum(jnp.linalg.norm(half, axis=-1, keepdims=True), 1e-6)
  spec = light.specular * jnp.maximum(jnp.sum(normal * half, -1, keepdims=True), 0.0) ** 24
  lit = albedo * (light.ambient + sun + lamp) + spec
  lit = lit + emission[:, None] * (1.1 * albedo - lit)
  if not clip:
    return jnp.maximum(lit * light.exposure, 0.0)
  return jnp.clip(lit * light.exposure, 0.0, 1.0)
