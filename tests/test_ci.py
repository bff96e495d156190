"""CI runs what the README says: its test command verbatim, then the slow tier, each timed
against a budget (.ci/run)."""

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _readme_test_command():
  text = (ROOT / "README.md").read_text(encoding="utf-8")
  (line,) = [l for l in text.splitlines() if "pip install -e '.[dev]'" in l and "pytest" in l]
  return line[line.index("python -m pytest"):].strip()


def test_ci_runs_the_readme_test_command_then_the_slow_tier():
  ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
  command = _readme_test_command()
  assert '-m "not slow"' in command and "--durations=25" in command
  tiers = re.findall(r"^tier (\w+) (\d+) (\d+) (.+)$", ci, flags=re.M)
  assert [t[0] for t in tiers] == ["main", "slow"]
  (_, budget, hard, main), (_, _, _, slow) = tiers
  assert main == command
  assert int(budget) == 8 * 60                  # the README's budget: 8 min on 2 cores
  assert int(hard) >= 15 * 60                   # a hard limit far above machine noise
  assert "-m slow" in slow
  # A worker that dies (a segfault in a compile) fails the tier at once: xdist's replacement
  # workers otherwise sat idle until CI's 90-minute limit (12-06).
  assert "--max-worker-restart=0" in main and "--max-worker-restart=0" in slow


def test_the_slow_marker_is_registered():
  text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
  assert re.search(r'^\s*"slow: ', text, flags=re.M)
