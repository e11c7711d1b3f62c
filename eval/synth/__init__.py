"""The survey simulator: seafloor scenes with a colour board, lawnmower trajectories, ray-cast
rendering, underwater image formation with visible and hidden effects, and the truth to test
against. Entry point: ``simulate_survey(out_dir, make_config("demo", hidden=[...], seed=0))``."""

from .config import FormationConfig, SimulationConfig, config_from_dict, config_to_dict
from .presets import HIDDEN_DEFAULTS, PRESETS, make_config, with_frames
from .survey import SimulationError, SimulationResult, simulate_survey
from .truth import BoardTruth, Truth, load_truth

__all__ = [
    "simulate_survey", "make_config", "with_frames", "SimulationError", "SimulationResult", "SimulationConfig",
    "FormationConfig", "PRESETS", "HIDDEN_DEFAULTS", "load_truth", "Truth", "BoardTruth",
    "config_to_dict", "config_from_dict",
]
