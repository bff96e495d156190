"""The commands' persistent compile cache: where it lives, and that a second run loads what
the first compiled."""

import json
import os
import pathlib
import subprocess
import sys

from jaxfusion.lab import compile_cache


def test_cache_dir_follows_the_environment(tmp_path):
  assert compile_cache.cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == (
      tmp_path / "jaxfusion" / "xla")
  assert compile_cache.cache_dir({"JAXFUSION_COMPILE_CACHE": str(tmp_path / "c")}) == (
      tmp_path / "c")
  for off in ("off", "0", "No", "FALSE"):
    assert compile_cache.cache_dir({"JAXFUSION_COMPILE_CACHE": off}) is None
  # JAX's own setting wins: the commands leave it alone.
  assert compile_cache.cache_dir({"JAX_COMPILATION_CACHE_DIR": "/x",
                                  "JAXFUSION_COMPILE_CACHE": str(tmp_path)}) is None
  default = compile_cache.cache_dir({})
  assert default == pathlib.Path(os.path.expanduser("~")) / ".cache" / "jaxfusion" / "xla"


def test_enable_without_a_usable_folder_leaves_jax_as_it_is(tmp_path):
  blocker = tmp_path / "file"
  blocker.write_text("")
  assert compile_cache.enable({"JAXFUSION_COMPILE_CACHE": str(blocker / "sub")}) is None
  assert compile_cache.enable({"JAXFUSION_COMPILE_CACHE": "off"}) is None


_RUN = """
import json, sys, time
from jaxfusion.lab import compile_cache
compile_cache.MIN_COMPILE_SECONDS = 0.0
folder = compile_cache.enable({"JAXFUSION_COMPILE_CACHE": sys.argv[1]})
import jax, jax.numpy as jnp
hits = []
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(event) if event == "/jax/compilation_cache/cache_hits" else None)
f = jax.jit(lambda x: jnp.cumsum(jnp.sin(x) @ x.T, axis=0))
y = f(jnp.ones((64, 64)))
print(json.dumps({"folder": str(folder), "hits": len(hits), "sum": float(y.sum())}))
"""


def test_a_second_process_loads_what_the_first_compiled(tmp_path):
  cache = tmp_path / "cache"
  env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
  runs = [json.loads(subprocess.run([sys.executable, "-c", _RUN, str(cache)], env=env,
                                    capture_output=True, text=True, check=True
                                    ).stdout.strip().splitlines()[-1]) for _ in range(2)]
  assert runs[0]["folder"] == str(cache) and any(cache.iterdir())
  assert runs[0]["hits"] == 0 and runs[1]["hits"] >= 1
  assert runs[0]["sum"] == runs[1]["sum"]
