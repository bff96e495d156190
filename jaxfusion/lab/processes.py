"""`--processes N` on one machine: start N local processes of a command, joined by JAX's runtime.

`launch` starts N copies of a program with a coordinator on the loopback address, telling each
its place through `jaxfusion.distributed`'s environment variables (`initialize()` reads them).
Process 0 keeps the terminal; the others write to log files in a temporary folder. The launcher
watches them all: when every process has exited 0 it returns 0; as soon as one exits with
another status (or, after `join_timeout_s`, one is still silent before joining — `initialize`
itself fails then), it stops the others and reports that process in one line. It never waits
on a dead process.

On a cluster no launcher is needed: the scheduler starts the processes (e.g.
`srun -n 4 jaxfusion study --distributed …`) and JAX reads its environment.
"""

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from typing import Optional, Sequence

from jaxfusion import distributed

POLL_S = 0.1


def free_port() -> int:
  """A TCP port on the loopback address that nothing listens on now."""
  with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def is_worker() -> bool:
  """True in a process a launcher started (it must not launch again)."""
  return os.environ.get(distributed.PROCESS_ID_ENV) is not None


def _last_line(path: str) -> str:
  try:
    with open(path, errors="replace") as f:
      lines = [ln.strip() for ln in f.read().splitlines() if ln.strip()]
  except OSError:
    return ""
  # The distributed runtime's own log lines (absl: "E1205 …", "F1205 …") say less than the
  # program's last words; prefer a line of the program's.
  own = [ln for ln in lines if not (len(ln) > 5 and ln[0] in "IWEF" and ln[1:5].isdigit())]
  return (own or lines or [""])[-1][:300]


def _stop(procs) -> None:
  for p in procs:
    if p.poll() is None:
      try:
        os.killpg(p.pid, signal.SIGTERM)
      except (ProcessLookupError, PermissionError):
        pass
  deadline = time.monotonic() + 5.0
  for p in procs:
    try:
      p.wait(timeout=max(0.0, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
      try:
        os.killpg(p.pid, signal.SIGKILL)
      except (ProcessLookupError, PermissionError):
        pass
      p.wait()


def launch(argv: Sequence[str], num_processes: int, *, program: Optional[Sequence[str]] = None,
           name: str = "jaxfusion", timeout_s: int = distributed.DEFAULT_TIMEOUT_S,
           log_dir: Optional[str] = None) -> int:
  """Runs `program + argv` as `num_processes` joined local processes; returns the exit status.

  Args:
    argv: the arguments every process gets (the same command line).
    num_processes: N ≥ 1.
    program: the program (default: this Python running `jaxfusion.lab.cli`).
    name: the command's name in the one-line report of a failure.
    timeout_s: the join timeout each process gets (`distributed.initialize`).
    log_dir: where processes 1…N−1 write their output (default: a temporary folder, kept
      only when a process failed).

  Returns:
    0 when every process exited 0; otherwise 2, after one line on stderr naming the first
    process that failed, its status and its last line of output.
  """
  num_processes = int(num_processes)
  if num_processes < 1:
    raise ValueError(f"--processes must be ≥ 1; got {num_processes}")
  program = list(program) if program is not None else [sys.executable, "-m", "jaxfusion.lab.cli"]
  coordinator = f"127.0.0.1:{free_port()}"
  own_logs = log_dir is None
  log_dir = log_dir or tempfile.mkdtemp(prefix="jaxfusion-processes-")
  os.makedirs(log_dir, exist_ok=True)
  procs, logs = [], []
  try:
    for pid in range(num_processes):
      env = dict(os.environ)
      env.update({distributed.COORDINATOR_ENV: coordinator,
                  distributed.NUM_PROCESSES_ENV: str(num_processes),
                  distributed.PROCESS_ID_ENV: str(pid),
                  distributed.TIMEOUT_ENV: str(int(timeout_s))})
      log = os.path.join(log_dir, f"process_{pid}.log")
      logs.append(log)
      out = None if pid == 0 else open(log, "w")   # pylint: disable=consider-using-with
      procs.append(subprocess.Popen(program + list(argv), env=env, stdout=out,
                                    stderr=None if pid == 0 else subprocess.STDOUT,
                                    start_new_session=True))
      if out is not None:
        out.close()
    while True:
      codes = [p.poll() for p in procs]
      failed = [(pid, c) for pid, c in enumerate(codes) if c not in (None, 0)]
      if failed:
        pid, code = failed[0]
        _stop(procs)
        why = f"signal {-code}" if code < 0 else f"status {code}"
        last = _last_line(logs[pid]) if pid else ""
        print(f"{name}: error: process {pid} of {num_processes} exited with {why}"
              + (f" ({last})" if last else "") + "; the other processes were stopped"
              + (f" (logs in {log_dir})" if num_processes > 1 else ""), file=sys.stderr)
        own_logs = False
        return 2
      if all(c == 0 for c in codes):
        return 0
      time.sleep(POLL_S)
  except KeyboardInterrupt:
    _stop(procs)
    raise
  finally:
    _stop(procs)
    if own_logs:
      for log in logs:
        try:
          os.remove(log)
        except OSError:
          pass
      try:
        os.rmdir(log_dir)
      except OSError:
        pass
