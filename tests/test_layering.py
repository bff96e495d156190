"""The layers: library (`jaxfusion`) ← networks (`jaxfusion_models`) ← application
(`jaxfusion.lab`). Dependencies point one way, the networks' modules import one another without
a circle, and `import jaxfusion` stays light."""

import ast
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
LIBRARY = ROOT / "jaxfusion"
LAB = LIBRARY / "lab"
MODELS = ROOT / "models"
# What `import jaxfusion` must not load: the application, the networks, and the heavy or
# optional dependencies that only commands, figures, files or the viewer use.
HEAVY = ("jaxfusion.lab", "jaxfusion_models", "matplotlib", "cv2", "viser", "trimesh")


def _imports(path: pathlib.Path, package: str = None) -> set:
  """Every module an import statement in `path` names, at any depth (function-level imports
  included), resolved to absolute names (relative ones against `path`'s package)."""
  tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
  if package is None:
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
  names = set()
  for node in ast.walk(tree):
    if isinstance(node, ast.Import):
      names.update(alias.name for alias in node.names)
    elif isinstance(node, ast.ImportFrom):
      base = node.module or ""
      if node.level:
        parent = package.split(".")[:len(package.split(".")) - node.level + 1]
        base = ".".join(parent + ([base] if base else []))
      names.add(base)
      names.update(f"{base}.{alias.name}" for alias in node.names)
  return names


def _library_modules():
  for path in sorted(LIBRARY.rglob("*.py")):
    if LAB in path.parents or path.name == "__main__.py":   # the application; entry points
      continue
    yield path


def _names(prefix: str, imports: set) -> list:
  return sorted(n for n in imports if n == prefix or n.startswith(prefix + "."))


@pytest.mark.parametrize("path", list(_library_modules()),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_library_imports_neither_the_application_nor_the_networks(path):
  imports = _imports(path)
  assert not _names("jaxfusion.lab", imports), _names("jaxfusion.lab", imports)
  # `jaxfusion_models` is mapped onto the `models/` folder; either name would be a cycle.
  assert not _names("jaxfusion_models", imports) and not _names("models", imports)


@pytest.mark.parametrize("path", sorted(MODELS.glob("*.py")), ids=lambda p: p.name)
def test_networks_import_the_library_only(path):
  imports = _imports(path)
  assert not _names("jaxfusion.lab", imports), _names("jaxfusion.lab", imports)


def _cycle(graph: dict) -> list:
  """One cycle of a directed graph `{node: set of nodes}` as a path `[a, …, a]`, or []."""
  done, path = set(), []

  def visit(node):
    if node in path:
      return path[path.index(node):] + [node]
    if node in done:
      return []
    path.append(node)
    for succ in sorted(graph.get(node, ())):
      found = visit(succ)
      if found:
        return found
    path.pop()
    done.add(node)
    return []

  for node in sorted(graph):
    found = visit(node)
    if found:
      return found
  return []


def test_the_networks_modules_import_one_another_without_a_circle():
  # Each module of `models/` does one thing, and a circle would tie two of them together (train
  # and evaluate once imported each other for the data helpers that now live in `data`). The
  # package's `__init__` re-exports the modules and is left out.
  modules = {p.stem: p for p in MODELS.glob("*.py") if p.stem != "__init__"}
  graph = {name: {other for other in modules if f"models.{other}" in _imports(path)} - {name}
           for name, path in modules.items()}
  assert graph["train"] and "evaluate" in graph["train"]   # the scan sees relative imports
  assert _cycle(graph) == [], " → ".join(_cycle(graph))


def test_the_cycle_finder_finds_a_circle():
  assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
  assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_the_scan_sees_function_level_and_relative_imports(tmp_path):
  # The guard above must catch an import hidden in a function, or it could not fail.
  probe = tmp_path / "probe.py"
  probe.write_text("def f():\n  from jaxfusion.lab import cli\n  from . import tune\n")
  imports = _imports(probe, package="jaxfusion")
  assert "jaxfusion.lab" in imports and "jaxfusion.tune" in imports


def _modules_after(code: str) -> list:
  code += "\nimport sys\nprint('\\n'.join(sorted(m for m in sys.modules)))"
  return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                        check=True, timeout=300, cwd=ROOT).stdout.split()


def test_the_library_loads_no_command_line_nor_heavy_module():
  # Every public name loaded (the package loads them lazily).
  out = _modules_after("import jaxfusion\nfor name in jaxfusion.__all__: getattr(jaxfusion, name)")
  loaded = [m for m in out if any(m == h or m.startswith(h + ".") for h in HEAVY)]
  assert not loaded, loaded
  assert "jaxfusion.datasets" in out and "jaxfusion.tune" in out   # the library itself is there
  assert "jax" in out


def test_import_jaxfusion_loads_no_jax_until_a_name_is_used():
  # So that a command re-executes itself (huge pages) before JAX is loaded, not after.
  out = _modules_after("import jaxfusion\nfrom jaxfusion.lab import cli, hugepages\n"
                       "import sys\nprint('\\n'.join(sorted(sys.modules)))\nprint('--')\n"
                       "jaxfusion.Mapper")
  light, used = out[:out.index("--")], out[out.index("--") + 1:]
  assert "jaxfusion.lab.hugepages" in light
  assert "jax" not in light and "numpy" not in light, [m for m in light if "jax" in m]
  assert "jax" in used and "jaxfusion.mapper" in used and "jaxfusion.datasets" not in used


def test_lazy_names_are_the_modules_own():
  import jaxfusion                                   # pylint: disable=import-outside-toplevel
  from jaxfusion import fusion, tsdf                 # pylint: disable=import-outside-toplevel
  assert jaxfusion.fuse_frame is fusion.fuse_frame and jaxfusion.tsdf is tsdf
  assert jaxfusion.hashing.EMPTY == jaxfusion.EMPTY  # a submodule not re-exported
  assert set(jaxfusion.__all__) <= set(dir(jaxfusion))
  with pytest.raises(AttributeError, match="no attribute 'fuse_frames'"):
    jaxfusion.fuse_frames                            # pylint: disable=pointless-statement


def test_the_lazy_tables_the_type_checking_imports_and_all_agree():
  # `jaxfusion/__init__.py` names each export three times (the lazy table, `__all__`, and the
  # imports type checkers read); they must not drift apart.
  import jaxfusion                                   # pylint: disable=import-outside-toplevel
  tree = ast.parse((ROOT / "jaxfusion" / "__init__.py").read_text())
  checked = next(n for n in tree.body if isinstance(n, ast.If)
                 and getattr(n.test, "id", None) == "TYPE_CHECKING")
  typed_names, typed_modules = {}, set()
  for node in checked.body:
    if node.module == "jaxfusion":
      typed_modules |= {a.name for a in node.names}
    else:
      typed_names |= {a.name: node.module.split(".", 1)[1] for a in node.names}
  assert typed_names == jaxfusion._EXPORTS           # pylint: disable=protected-access
  assert typed_modules == set(jaxfusion._SUBMODULES)  # pylint: disable=protected-access
  assert set(jaxfusion.__all__) <= set(typed_names) | typed_modules
  assert set(typed_names) <= set(jaxfusion.__all__)
