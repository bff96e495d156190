"""The suite's environment.

- The `jaxfusion` commands that tests run in-process keep no compile cache in the user's home
  (`lab.compile_cache`; its own tests give it a folder).
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

import pytest

os.environ.setdefault("JAXFUSION_COMPILE_CACHE", "off")


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs_after_module():
  """Frees the module's compiled programs (and their memory maps) once its tests are done."""
  yield
  import jax  # pylint: disable=import-outside-toplevel

  jax.clear_caches()
  gc.collect()
