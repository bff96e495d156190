"""The `jaxfusion view` subcommand (imports viser only when it runs)."""

import socket

from jaxfusion.lab.viewer import scene_data as sd


def check_host(host: str) -> None:
  """Raises ValueError (one line) unless this machine can listen on `host`."""
  try:
    family, kind, proto, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
  except (socket.gaierror, UnicodeError) as e:
    raise ValueError(f"--host {host!r} is not an address of this machine ({e})") from None
  with socket.socket(family, kind, proto) as s:
    try:
      s.bind(address)
    except OSError as e:
      raise ValueError(f"--host {host!r}: cannot listen on this address ({e.strerror})"
                       ) from None


def add_parser(subparsers) -> None:
  """Registers `view` on the `jaxfusion` command's subparsers."""
  p = subparsers.add_parser(
      "view", help="interactive 3-D web viewer of saved maps (needs the `viewer` extra)",
      description="Serve saved maps (.npz from `jaxfusion run` / `demo`, or folders holding "
                  "them) in a local web page: voxels coloured by class, entropy, Dirichlet "
                  "confidence, hit count or right/wrong against a saved GT map.")
  p.add_argument("paths", nargs="+", metavar="PATH", help="map .npz files or output folders")
  p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
  p.add_argument("--port", type=int, default=8080,
                 help="port (default 8080; the next free one if taken)")
  p.add_argument("--max-cubes", type=int, default=sd.DEFAULT_MAX_CUBES,
                 help="draw voxels as cubes up to this many, as points beyond")
  p.set_defaults(func=main)


def main(args) -> int:
  """Runs `jaxfusion view`: loads the maps and serves them until Ctrl-C; returns 0.

  Raises:
    ValueError: viser is not installed (the message says what to install), bad options, a
      file that is not a map, maps of different class lists.
    FileNotFoundError: a path that does not exist.
  """
  if not 0 <= args.port <= 65535:
    raise ValueError(f"--port must be in [0, 65535]; got {args.port}")
  if args.max_cubes < 0:
    raise ValueError(f"--max-cubes must be ≥ 0; got {args.max_cubes}")
  check_host(args.host)
  try:
    import viser  # noqa: F401  pylint: disable=import-outside-toplevel,unused-import
  except ImportError:
    raise ValueError(sd.INSTALL_HINT) from None
  from jaxfusion.lab.viewer import server
  server.serve(args.paths, host=args.host, port=args.port, max_cubes=args.max_cubes)
  return 0
