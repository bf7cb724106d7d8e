"""torchdoct: batched PyTorch simulation of dynamic OCT (DOCT) signals and their metrics.

Units and resolution conventions: :mod:`torchdoct.conventions`.
"""

from .sim.config import (
    Analysis,
    Diffusion,
    Flow,
    Noise,
    OCTSystem,
    Population,
    Protocol,
    RandomBallistic,
    Scene,
    SceneError,
    SimulationSettings,
    load_scene,
    scene_from_dict,
)
from .sim.metrics import complex_variance, lag_correlations, liv, ocds, to_db
from .image.phantom import Phantom, load_phantom, phantom_from_dict
from .sim.plan import Plan, make_plan
from .image.render import RenderResult, render
from .sim.scenes import shipped_scenes
from .sim.simulate import SimulationResult, simulate

__version__ = "0.3.0"

__all__ = [
    "Analysis", "Diffusion", "Flow", "Noise", "OCTSystem", "Population", "Protocol", "RandomBallistic",
    "Scene", "SceneError", "SimulationSettings", "load_scene", "scene_from_dict",
    "complex_variance", "lag_correlations", "liv", "ocds", "to_db",
    "Phantom", "load_phantom", "phantom_from_dict", "RenderResult", "render",
    "Plan", "make_plan", "shipped_scenes", "SimulationResult", "simulate", "__version__",
]
