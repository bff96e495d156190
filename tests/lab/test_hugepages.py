"""Huge pages for the commands' maps (`lab.hugepages`): when a process re-executes itself with
glibc's hugetlb tunable, and that a process so started holds a large JAX array in huge pages
where the kernel offers them."""

import os
import subprocess
import sys

import pytest

from jaxfusion.lab import hugepages

_GLIBC = (2, 36)


def test_environ_with_adds_the_tunable_only_when_it_can_help():
  env = hugepages.environ_with({"PATH": "/bin"}, mode="madvise", glibc=_GLIBC)
  assert env == {"PATH": "/bin", "GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}
  # Other tunables are kept, the new one appended.
  env = hugepages.environ_with({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}, mode="madvise",
                               glibc=_GLIBC)
  assert env["GLIBC_TUNABLES"] == "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"
  # Already chosen (by the user, or this is the re-executed process): nothing to do.
  assert hugepages.environ_with({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, mode="madvise",
                                glibc=_GLIBC) is None
  for off in ("off", "0", "No", "FALSE"):
    assert hugepages.environ_with({"JAXFUSION_HUGEPAGES": off}, mode="madvise",
                                  glibc=_GLIBC) is None
  assert hugepages.environ_with({"JAXFUSION_HUGEPAGES": "on"}, mode="madvise",
                                glibc=_GLIBC) is not None
  # A kernel that gives huge pages always or never, no glibc, or one too old for the tunable.
  for mode, glibc in (("always", _GLIBC), ("never", _GLIBC), (None, _GLIBC),
                      ("madvise", None), ("madvise", (2, 34))):
    assert hugepages.environ_with({}, mode=mode, glibc=glibc) is None, (mode, glibc)


def test_thp_mode_reads_the_bracketed_word(tmp_path):
  path = tmp_path / "enabled"
  path.write_text("always [madvise] never\n")
  assert hugepages.thp_mode(str(path)) == "madvise"
  path.write_text("[always] madvise never\n")
  assert hugepages.thp_mode(str(path)) == "always"
  assert hugepages.thp_mode(str(tmp_path / "missing")) is None


def test_reexec_replaces_the_process_with_the_same_command_and_the_tunable(monkeypatch):
  calls = []
  monkeypatch.setattr(hugepages, "thp_mode", lambda: "madvise")
  monkeypatch.setattr(hugepages, "glibc_version", lambda: _GLIBC)
  monkeypatch.setattr(sys, "orig_argv", ["python", "-m", "bench.building", "--quick"])
  fake = lambda exe, argv, env: calls.append((exe, argv, env))
  assert hugepages.reexec(environ={"HOME": "/h"}, execve=fake)
  assert calls == [(sys.executable, ["python", "-m", "bench.building", "--quick"],
                    {"HOME": "/h", "GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"})]
  assert not hugepages.reexec(environ={"JAXFUSION_HUGEPAGES": "off"}, execve=fake)
  assert len(calls) == 1


_CHILD = """
import os, sys
from jaxfusion.lab import hugepages
hugepages.reexec()
import jax, jax.numpy as jnp
x = jax.block_until_ready(jnp.full((64 * 2**20 // 4,), 1.0, jnp.float32))   # 64 MiB, written
print(os.environ.get("GLIBC_TUNABLES", ""), hugepages.anon_huge_bytes(), flush=True)
"""


@pytest.mark.slow   # two fresh processes that import JAX: ~6 s
@pytest.mark.skipif(hugepages.environ_with({}, mode=hugepages.thp_mode(),
                                           glibc=hugepages.glibc_version()) is None,
                    reason="this machine offers no huge pages through glibc's tunable")
def test_a_reexecuted_process_holds_its_large_arrays_in_huge_pages():
  env = {k: v for k, v in os.environ.items()
         if k not in ("GLIBC_TUNABLES", "JAXFUSION_HUGEPAGES")}
  outs = {}
  for name, extra in (("huge", {}), ("plain", {"JAXFUSION_HUGEPAGES": "off"})):
    done = subprocess.run([sys.executable, "-c", _CHILD], env={**env, **extra}, check=True,
                          capture_output=True, text=True, timeout=120)
    tunables, held = done.stdout.split()[-2:] if name == "huge" else (
        "", done.stdout.split()[-1])
    outs[name] = (tunables, int(held))
  assert outs["huge"][0] == "glibc.malloc.hugetlb=1"
  assert outs["huge"][1] >= 32 * 2**20, outs           # most of the 64 MiB array
  assert outs["plain"][1] < outs["huge"][1] - 32 * 2**20, outs
