"""jaxfusion_models: the Bayesian segmentation front end (MC-dropout DeepLab-v3-style net).

Installed as `jaxfusion_models` (the repo folder is `models/`). Depends on `jaxfusion`; the
engine never imports it.

    model = jaxfusion_models.load_pretrained()          # shipped weights, class list checked
    samples = jaxfusion_models.mc_samples(model.graphdef, model.params, key, rgb, num_samples=32)
    mean, var = jaxfusion.mc_moments(samples)           # (H, W, K) each
    source = jaxfusion_models.mc_dropout_source(model.graphdef, model.params, num_samples=32)
    rule = jaxfusion_models.load_learned_rule()          # the learned fusion rule, fitted on it
    best = jaxfusion_models.load_family_rule()           # the rule family's fit (spatial term)

Commands: `python -m models.train`, `python -m models.evaluate`, `python -m models.figure`.
"""

from .checkpoint import CheckpointError
from .checkpoint import LoadedModel
from .checkpoint import PRETRAINED_PATH
from .checkpoint import load
from .checkpoint import load_pretrained
from .checkpoint import save
from .learned_rule import FAMILY_RULE_PATH
from .learned_rule import FAMILY_RULE_RECORD
from .learned_rule import GLFS_PATH
from .learned_rule import GLFS_RECORD
from .learned_rule import LEARNED_RULE_PATH
from .learned_rule import LEARNED_RULE_RECORD
from .learned_rule import load_family_rule
from .learned_rule import load_glfs
from .learned_rule import load_learned_rule
from .net import DEFAULT_CLASS_NAMES
from .net import SegNet
from .net import SegNetConfig
from .net import apply
from .net import count_params
from .net import init
from .net import resnet18_config
from .net import tiny_config
from .sampling import deterministic_apply_fn
from .sampling import deterministic_probs
from .sampling import deterministic_source
from .sampling import ensemble_source
from .sampling import mc_dropout_source
from .sampling import mc_samples
from .sampling import mc_samples_batch
from .sampling import prepare_images
from .sampling import stochastic_apply_fn

__all__ = sorted([
    "CheckpointError", "DEFAULT_CLASS_NAMES", "FAMILY_RULE_PATH", "FAMILY_RULE_RECORD",
    "GLFS_PATH", "GLFS_RECORD", "LEARNED_RULE_PATH",
    "LEARNED_RULE_RECORD", "load_family_rule", "load_glfs",
    "LoadedModel", "PRETRAINED_PATH", "SegNet",
    "SegNetConfig", "apply", "count_params", "deterministic_apply_fn", "deterministic_probs",
    "deterministic_source", "ensemble_source", "init", "load", "load_learned_rule",
    "load_pretrained",
    "mc_dropout_source", "mc_samples", "mc_samples_batch", "prepare_images", "resnet18_config",
    "save",
    "stochastic_apply_fn", "tiny_config",
])
