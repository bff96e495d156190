"""The suite's environment.

- The `jaxfusion` commands that tests run in-process keep no compile cache in the user's home
  (`lab.compile_cache`; its own tests give it a folder).
- One persistent compile cache serves the whole run: JAX's own `JAX_COMPILATION_CACHE_DIR`, a
  fresh temporary folder that the pytest-xdist workers (and the processes tests start) inherit
  from the process that starts them, removed when the run ends (a folder the environment
  already names is used as it is and kept). Programs are the same objects either way; a module
  that compiles what another module or worker has compiled loads it instead (the datasets
  tests: 96 s → 70 s on 2 cores). Without it, every module compiled again what the modules
  before it had, since the caches are dropped between modules (below).
- After each test module, JAX's in-memory caches of compiled programs are dropped. XLA-CPU maps
  every compiled program's code and data as their own small memory regions, and a pytest worker
  that runs a few hundred modules compiles several thousand distinct programs (every test has its
  own shapes): the worker then reaches the kernel's limit of 65 530 memory maps per process
  (`vm.max_map_count`) and XLA segfaults inside a compile (CI 12-06: two workers of the slow
  tier died this way at 93-96 %). Tests inside a module still share what they compiled, and each
  test dispatches exactly as a user's call does: the fixture runs between modules, never around
  the behaviour under test.
"""

import gc
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("JAXFUSION_COMPILE_CACHE", "off")

# Set before JAX is imported (JAX reads these at import). Only the first process of a run makes
# the folder: the workers see it in the environment they were started with.
_OWN_CACHE = None
if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
  _OWN_CACHE = tempfile.mkdtemp(prefix="jaxfusion-tests-xla-")
  os.environ["JAX_COMPILATION_CACHE_DIR"] = _OWN_CACHE
  os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.05")


def pytest_unconfigure(config):
  """Removes the run's compile cache, in the process that made it."""
  del config
  if _OWN_CACHE is not None:
    shutil.rmtree(_OWN_CACHE, ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs_after_module():
  """Frees the module's compiled programs (and their memory maps) once its tests are done."""
  yield
  import jax  # pylint: disable=import-outside-toplevel

  jax.clear_caches()
  gc.collect()
