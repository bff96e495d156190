"""The `jaxfusion` commands keep their compiled programs between runs.

XLA compiles each of the engine's programs once per shape, and on a CPU that is most of what a
short command or a map's growth costs (`bench/growth.py` measures a growth with and without
the cache: bench/RESULTS.md). The commands therefore turn on JAX's persistent compilation
cache, in a folder of the user's cache directory:

* `JAXFUSION_COMPILE_CACHE=off` (or `0`, `no`, `false`): no cache;
* `JAXFUSION_COMPILE_CACHE=DIR`: that folder;
* otherwise `$XDG_CACHE_HOME/jaxfusion/xla` (default `~/.cache/jaxfusion/xla`).

Where JAX's own `JAX_COMPILATION_CACHE_DIR` is set, JAX's settings are left as they are. The
library never does this itself: a program that imports `jaxfusion` chooses its own JAX config.
"""

import os
import pathlib
from typing import Mapping, Optional

OFF = ("off", "0", "no", "false", "none")
MAX_BYTES = 4 * 2**30            # least recently used entries go beyond this size
# Programs that compile faster are not worth a file (a Mapper table half takes ~0.5 s).
MIN_COMPILE_SECONDS = 0.1


def cache_dir(environ: Mapping[str, str]) -> Optional[pathlib.Path]:
  """The folder the commands' compile cache lives in under `environ`, or None for no cache
  (switched off, or JAX's own `JAX_COMPILATION_CACHE_DIR` in charge)."""
  if environ.get("JAX_COMPILATION_CACHE_DIR"):
    return None
  chosen = environ.get("JAXFUSION_COMPILE_CACHE", "").strip()
  if chosen.lower() in OFF and chosen:
    return None
  if chosen:
    return pathlib.Path(chosen).expanduser()
  base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
  return pathlib.Path(base) / "jaxfusion" / "xla"


def enable(environ: Optional[Mapping[str, str]] = None) -> Optional[pathlib.Path]:
  """Turns on JAX's persistent compilation cache in `cache_dir(environ)` (default
  `os.environ`) and returns that folder, or None when there is none to use (switched off,
  JAX's own settings, or a folder that cannot be made)."""
  folder = cache_dir(os.environ if environ is None else environ)
  if folder is None:
    return None
  try:
    folder.mkdir(parents=True, exist_ok=True)
  except OSError:
    return None          # a read-only home: the commands run as before, compiling each time
  import jax   # pylint: disable=import-outside-toplevel
  jax.config.update("jax_compilation_cache_dir", str(folder))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
  jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
  return folder
