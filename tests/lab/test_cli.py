"""The `jaxfusion` command line: every command the README shows parses as written, the shared
flags mean one thing everywhere, and the old spellings still work."""

import pathlib
import re
import shlex

import pytest

from jaxfusion.lab import cli

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _fenced_commands(text: str) -> list:
  """`jaxfusion …` command lines in the shell blocks of a Markdown text (continuations joined,
  comments dropped, `&&` chains split, `$NAME` expanded where the block sets `NAME=…`)."""
  commands, block, lang = [], None, None
  for line in text.splitlines():
    if line.startswith("```"):
      if block is None:
        block, lang = [], line[3:].strip()
      else:
        if lang in ("", "bash", "sh"):
          names = {}
          expand = lambda s: re.sub(r"\$\{?(\w+)\}?",
                                    lambda m: names.get(m.group(1), m.group(0)), s)
          for cmd in "\n".join(block).replace("\\\n", " ").splitlines():
            assignment = re.fullmatch(r"\s*([A-Za-z_]\w*)=(.*)", cmd)
            if assignment:
              words = shlex.split(expand(assignment.group(2)))   # `$NAME` unquoted: split again
              names[assignment.group(1)] = " ".join(w for word in words for w in word.split())
              continue
            for part in cmd.split("#")[0].split("&&"):
              if part.strip().startswith("jaxfusion "):
                commands.append(expand(part.strip()))
        block = None
    elif block is not None:
      block.append(line)
  return commands


def test_the_scan_finds_commands():
  text = ("```bash\njaxfusion demo --quick  # x\nls && jaxfusion list\n```\n"
          "```python\njaxfusion x\n```")
  assert _fenced_commands(text) == ["jaxfusion demo --quick", "jaxfusion list"]
  text = '```bash\nF="--frames 3 \\\n  --seed 1"\njaxfusion run $F --out x  # y\n```'
  assert _fenced_commands(text) == ["jaxfusion run --frames 3 --seed 1 --out x"]


@pytest.mark.parametrize("page", ["README.md"] + sorted(
    str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md")))
def test_every_command_in_the_docs_parses(page):
  parser = cli.build_parser()
  for command in _fenced_commands((ROOT / page).read_text(encoding="utf-8")):
    argv = shlex.split(command)[1:]
    if any(re.search(r"[A-Z]{2,}|[\[|]", a) for a in argv):   # placeholders: MAP.npz, [--x], a|b
      continue
    try:
      parser.parse_args(argv)
    except SystemExit as e:
      assert e.code == 0, f"{page}: {command}"


@pytest.mark.parametrize("argv,dest,value", [
    (["study", "--seeds", "4", "5"], "layout_seeds", [4, 5]),
    (["study", "--layout-seeds", "4"], "layout_seeds", [4]),
    (["simulate-sweep", "--scene-seed", "3"], "layout_seeds", [3]),
    (["simulate-sweep", "--seed", "7"], "mc_seed", 7),
    (["sweep", "--seed", "2"], "layout_seeds", [2]),
    (["sweep", "--cache-dir", "c"], "cache", "c"),
    (["tune-protocol", "--cache", "c"], "cache", "c"),
    (["run", "--data", "office:0", "--seed", "9"], "mc_seed", 9),
    (["render", "--seed", "5"], "layout_seeds", [5]),
    (["demo", "--mc-seed", "1"], "mc_seed", 1),
])
def test_shared_flags_and_their_old_spellings(argv, dest, value):
  assert getattr(cli.build_parser().parse_args(argv), dest) == value


def test_every_command_module_offers_add_parser_and_main():
  import importlib  # pylint: disable=import-outside-toplevel
  for name in cli.COMMAND_MODULES:
    module = importlib.import_module(f"jaxfusion.lab.{name}")
    assert callable(module.add_parser) and callable(module.main), name


def test_a_bad_value_is_one_line_and_exit_2(capsys):
  assert cli.main(["render", "--layout-seeds", "1", "2"]) == 2
  err = capsys.readouterr().err
  assert "one --layout-seeds value" in err and "Traceback" not in err
