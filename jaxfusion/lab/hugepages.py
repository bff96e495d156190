"""The `jaxfusion` commands and the building bench ask Linux for huge pages.

A frame's fuse reads and writes a few rows at random places of the map's arrays. Once a map
holds millions of voxels its arrays span gigabytes, and with 4 KiB pages nearly every such
access also misses the TLB, so the same frame costs more in a larger table. Transparent huge
pages (2 MiB) cover the same arrays with 512 times fewer entries (bench/RESULTS.md, "A
building-sized map": `python -m bench.building --table-sizes` measures both). XLA allocates the
arrays with glibc's `malloc`, and glibc (≥ 2.35) marks its large allocations for huge pages
when the `glibc.malloc.hugetlb=1` tunable is set, which the kernel honours in its default
`madvise` mode. The tunable is read once, when a process starts: a command started without it
re-executes itself once with it added to `GLIBC_TUNABLES` (`reexec`), before anything is
allocated and before JAX is imported: `import jaxfusion` loads its names lazily, and this module
and `lab.cli` import neither JAX nor NumPy, so the first process is only Python's start.

* `JAXFUSION_HUGEPAGES=off` (or `0`, `no`, `false`): no re-execution, the process as started;
* a `GLIBC_TUNABLES` that already names `glibc.malloc.hugetlb`: left as it is;
* not Linux, no glibc ≥ 2.35, or transparent huge pages `never` (or `always`, which needs no
  tunable): nothing to do.

The library never does this itself (a program that imports `jaxfusion` owns its process); to
get huge pages in your own script on Linux, start Python with
`GLIBC_TUNABLES=glibc.malloc.hugetlb=1`.
"""

import os
import re
import sys
from typing import Callable, Mapping, Optional

from jaxfusion.lab.compile_cache import OFF   # the same words switch both off

TUNABLE = "glibc.malloc.hugetlb"
_THP_ENABLED = "/sys/kernel/mm/transparent_hugepage/enabled"
_MIN_GLIBC = (2, 35)     # the first glibc with the hugetlb tunable


def thp_mode(path: str = _THP_ENABLED) -> Optional[str]:
  """The kernel's transparent-huge-page mode (`always`, `madvise` or `never`; the bracketed
  word of `path`), or None where the kernel has no such setting (not Linux)."""
  try:
    with open(path, encoding="ascii") as f:
      text = f.read()
  except OSError:
    return None
  found = re.search(r"\[(\w+)\]", text)
  return found.group(1) if found else None


def glibc_version() -> Optional[tuple]:
  """`(major, minor)` of the C library this Python runs on if it is glibc, else None."""
  try:
    name = os.confstr("CS_GNU_LIBC_VERSION")      # e.g. "glibc 2.36"
  except (AttributeError, ValueError, OSError):
    return None
  found = re.fullmatch(r"glibc (\d+)\.(\d+).*", name or "")
  return (int(found.group(1)), int(found.group(2))) if found else None


def environ_with(environ: Mapping[str, str], *, mode: Optional[str],
                 glibc: Optional[tuple]) -> Optional[dict]:
  """The environment to re-execute with (`environ` with `glibc.malloc.hugetlb=1` added to
  `GLIBC_TUNABLES`), or None when the process should run as started: switched off, the tunable
  already chosen, no glibc ≥ 2.35, or a kernel `mode` other than `madvise`."""
  switch = environ.get("JAXFUSION_HUGEPAGES", "").strip().lower()
  if switch and switch in OFF:
    return None
  tunables = environ.get("GLIBC_TUNABLES", "")
  if TUNABLE in tunables:
    return None      # the user's choice, or this process is the re-executed one
  if mode != "madvise" or glibc is None or tuple(glibc) < _MIN_GLIBC:
    return None
  env = dict(environ)
  env["GLIBC_TUNABLES"] = f"{tunables}:{TUNABLE}=1" if tunables else f"{TUNABLE}=1"
  return env


def reexec(*, environ: Optional[Mapping[str, str]] = None,
           execve: Callable = os.execve) -> bool:
  """Re-executes this process (`sys.orig_argv`, the same interpreter and arguments) with huge
  pages when `environ_with` says so; otherwise returns False and the caller goes on. Call it
  first thing in a command's entry point, never from a function that tests call in-process:
  the process is replaced."""
  env = environ_with(os.environ if environ is None else environ, mode=thp_mode(),
                     glibc=glibc_version())
  if env is None or not getattr(sys, "orig_argv", None):
    return False
  sys.stdout.flush()
  sys.stderr.flush()
  execve(sys.executable, list(sys.orig_argv), env)
  return True        # only an `execve` that returns (a test's) gets here


def anon_huge_bytes(path: str = "/proc/self/smaps_rollup") -> Optional[int]:
  """Bytes of this process's memory held in transparent huge pages now, or None (not Linux)."""
  try:
    with open(path, encoding="ascii") as f:
      for line in f:
        if line.startswith("AnonHugePages:"):
          return 1024 * int(line.split()[1])
  except (OSError, ValueError, IndexError):
    return None
  return 0


def status() -> dict:
  """What a results file records: the kernel's mode, whether the tunable is set in this
  process, and the bytes held in huge pages now."""
  return {"thp_mode": thp_mode(), "tunable": TUNABLE in os.environ.get("GLIBC_TUNABLES", ""),
          "anon_huge_bytes": anon_huge_bytes()}
