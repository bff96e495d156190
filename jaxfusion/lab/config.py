"""The run configuration the demo, the study and the tuning protocols share.

A *run* renders embedded sequences (environments × trajectories × layout seeds × shifts), runs
a front end on each once, and fuses each with some rules. `RunConfig` holds everything that
decides the numbers of such a run; `jaxfusion demo` runs one (`demo_config`), `jaxfusion study`
composes one with its statistics (`study.StudyConfig`).
"""

import dataclasses
from typing import Optional

from jaxfusion import rules as rules_lib
from jaxfusion.datasets import synthetic

# The paper's setting: robust rules read the MC-dropout moments, baselines one dropout-off pass.
ROBUST_RULES = ("robust_r", "robust_d", "robust_dr")


def uses_moments(rule_name: str) -> bool:
  """Whether a rule is fused on the MC moments (the robust rules and the fitted ones: learned,
  GLFS, the rule family) rather than on the dropout-off pass (the baselines), the paper's
  setting and the study's."""
  return rule_name in ROBUST_RULES or rule_name in ("learned", "glfs", "family")


@dataclasses.dataclass(frozen=True)
class RunConfig:
  """What a run renders, predicts and fuses. The defaults are the demo's full run.

  Attributes:
    envs: environments ("office", "house").
    trajectories: trajectory indices (0, 1, 2).
    layout_seeds: layout seeds of the embedded world.
    shifts: test-domain shifts in [0, 1].
    domain: appearance domain, "test" (shifted by `shifts`) or "train".
    rules: rule names (`rules.PAPER_RULES` keys).
    num_frames: frames per sequence T.
    height: image rows H.
    width: image columns W.
    num_samples: MC-dropout samples M.
    mc_seed: seed of the MC-dropout keys.
    voxel_size: voxel edge in metres.
    capacity: map capacity (a power of two).
    beta: β of the R and D+R rules.
    aggregate: pixel aggregation of every rule ("sum" or "mean").
  """
  envs: tuple = ("office", "house")
  trajectories: tuple = (0, 1, 2)
  layout_seeds: tuple = (0,)
  shifts: tuple = (1.0,)
  domain: str = "test"
  rules: tuple = tuple(rules_lib.PAPER_RULES)
  num_frames: int = 40
  height: int = 120
  width: int = 160
  num_samples: int = 32
  mc_seed: int = 0
  voxel_size: float = 0.1
  capacity: int = 2**17
  beta: float = 0.3
  aggregate: str = "sum"

  def make_rule(self, name: str) -> rules_lib.FusionRule:
    """The rule `name` with this run's β (robust rules) and aggregation."""
    kwargs = {"aggregate": self.aggregate}
    if name in ROBUST_RULES:
      kwargs["beta"] = self.beta
    return rules_lib.by_name(name, **kwargs)

  @property
  def units(self) -> list:
    """The rendered layouts: `[(layout_seed, env, trajectory)]`."""
    return [(s, e, t) for s in self.layout_seeds for e in self.envs for t in self.trajectories]

  @property
  def grid(self) -> list:
    """Every sequence of the run: `[((layout_seed, env, trajectory), shift)]`."""
    return [(u, float(s)) for u in self.units for s in self.shifts]

  def validate(self, *, min_samples: int = 1) -> "RunConfig":
    """Raises ValueError for an unusable configuration; returns self."""
    for name in ("layout_seeds", "shifts", "envs", "trajectories", "rules"):
      values = getattr(self, name)
      if not values:
        raise ValueError(f"{name} must not be empty")
      if len(set(values)) != len(values):
        raise ValueError(f"{name} must be distinct; got {values}")
    if any(int(s) != s or s < 0 for s in self.layout_seeds):
      raise ValueError(f"layout seeds must be non-negative integers; got {self.layout_seeds}")
    if any(not 0.0 <= float(s) <= 1.0 for s in self.shifts):
      raise ValueError(f"shifts must lie in [0, 1]; got {self.shifts}")
    if any(e not in synthetic.ENVIRONMENTS for e in self.envs):
      raise ValueError(f"envs must be among {synthetic.ENVIRONMENTS}; got {self.envs}")
    if any(t not in range(synthetic.NUM_TRAJECTORIES) for t in self.trajectories):
      raise ValueError(f"trajectories must be among 0, 1, 2; got {self.trajectories}")
    if self.domain not in ("test", "train"):
      raise ValueError(f"domain must be 'test' or 'train'; got {self.domain!r}")
    unknown = [r for r in self.rules if r not in rules_lib.PAPER_RULES]
    if unknown:
      raise ValueError(f"rules must be names among {list(rules_lib.PAPER_RULES)}; got {unknown}")
    for name, low in (("num_frames", 1), ("height", 2), ("width", 2),
                      ("num_samples", min_samples)):
      if int(getattr(self, name)) < low:
        raise ValueError(f"{name} must be at least {low}; got {getattr(self, name)}")
    if not 0.0 <= self.beta <= 1.0:
      raise ValueError(f"beta must lie in [0, 1]; got {self.beta}")
    if self.aggregate not in ("sum", "mean"):
      raise ValueError(f"aggregate must be 'sum' or 'mean'; got {self.aggregate!r}")
    return self


def demo_config(quick: bool = False, **overrides) -> RunConfig:
  """The demo's run: 2 environments × 3 trajectories of layout seed 0 at full shift, 40 frames
  at 120×160, M = 32; `quick`: one 20-frame office sequence at 90×120, M = 8."""
  base = dict(envs=("office",), trajectories=(0,), num_frames=20, height=90, width=120,
              num_samples=8) if quick else {}
  base.update({k: v for k, v in overrides.items() if v is not None})
  return RunConfig(**base)


def replace(config: RunConfig, **changes: Optional[object]) -> RunConfig:
  """`dataclasses.replace` that ignores None values (unset command-line flags)."""
  return dataclasses.replace(config, **{k: v for k, v in changes.items() if v is not None})
