"""The recipe of a model: :class:`TrainConfig` (sizes, network, evaluation), the shipped recipes per spec
(:data:`SPEC_RECIPES`), the recipe of a spec of one's own (:func:`recipe_for`), the training prior of a
recipe (:func:`default_prior`) and the shifted-prior test set (:data:`SHIFTED_PRIOR`).

:func:`classifier.train.train` runs a recipe; ``classifier.train`` re-exports every name here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from .features import FeatureSpec, load_spec
from .prior import CLASSES, Prior
from .simulation import DEFAULT_TRUNCATION

__all__ = [
    "TrainConfig",
    "SPEC_RECIPES",
    "OWN_SIGNATURE_RECIPE",
    "recipe_for",
    "SCALED_PRIOR_SPECS",
    "default_prior",
    "SHIFTED_PRIOR",
    "SHIFTED_TARGETS",
    "shifted_prior",
]


@dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """Recipe of a model. The defaults are the shipped model's (``doct-train`` without options).

    ``draws_*``: parameter draws per split; ``trials_per_draw``: trials simulated per draw;
    ``truncation_tolerance``: the simulator's PSF truncation (relative amplitude).
    """

    spec: str = "single-acquisition"
    seed: int = 0
    draws_train: int = 270
    draws_validation: int = 45
    draws_test: int = 90
    trials_per_draw: int = 64
    replicates: int = 8
    truncation_tolerance: float = 1e-2
    #: the PSF truncation mode of the training data: ``"taper"`` (scatterers enter the PSF continuously;
    #: unbiased on every model feature against the reference simulator, at the cost of the hard cut at the
    #: same tolerance) or ``"hard"`` (the mode of the models trained before the taper existed)
    truncation: str = DEFAULT_TRUNCATION
    #: law of the flow's polar angle in the training prior when no prior is given
    #: (:attr:`classifier.prior.Prior.flow_polar_law`)
    flow_polar_law: str = "isotropic"
    #: residual bulk-phase step SD range (rad) of the training prior when no prior is given
    #: (:attr:`classifier.prior.Prior.bulk_residual_step_rad`; for models that read the phase)
    bulk_residual_step_rad: tuple[float, float] = (0.0, 0.0)
    #: share of the training draws with detection noise when no prior is given
    #: (:attr:`classifier.prior.Prior.noise_probability`; the noise-free rest is a limit no measurement reaches)
    noise_probability: float = 0.5
    #: share of the training replicates near a static edge when no prior is given
    #: (:attr:`classifier.prior.Prior.static_edge_probability`: each configuration its own static share)
    static_edge_probability: float = 0.0
    hidden: tuple[int, ...] = (64, 64)
    max_epochs: int = 200
    patience: int = 20
    batch_size: int = 512
    learning_rate: float = 3e-3
    weight_decay: float = 1e-4
    singles_per_group: int = 32
    pooled_per_group: int = 16
    max_pool_pixels: int = 48
    min_probability: float = 0.5
    eval_pools: tuple[int, ...] = (1, 4, 9, 25)
    baselines: bool = True
    #: magnitude head (log10 D or v with a Gaussian predictive SD); None = for signature specs
    magnitude: bool | None = None
    magnitude_weight: float = 1.0
    #: also evaluate on a test split with a random bulk phase per frame; None = for specs that use the phase
    bulk_phase_test: bool | None = None
    #: also evaluate on a test split from :data:`SHIFTED_PRIOR`; None = for signature specs
    shifted_test: bool | None = None

    @classmethod
    def for_spec(cls, spec: str | FeatureSpec = "single-acquisition", **overrides: Any) -> TrainConfig:
        """The recipe of ``spec`` with ``overrides``: a shipped spec's (:data:`SPEC_RECIPES`), else, for a spec
        of one's own (a TOML file, ``doct-train --like``), :func:`recipe_for` by its features."""
        if isinstance(spec, FeatureSpec):
            return cls(**{**recipe_for(spec), **overrides, "spec": spec.name})
        if str(spec) in SPEC_RECIPES or str(spec) in _SHIPPED_DEFAULT_RECIPE:
            return cls(**{"spec": spec, **SPEC_RECIPES.get(str(spec), {}), **overrides})
        try:
            recipe = recipe_for(load_spec(spec))
        except (OSError, TypeError, ValueError):  # the spec's own error comes when it is loaded
            recipe = {}
        return cls(**{"spec": spec, **recipe, **overrides})

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        object.__setattr__(self, "eval_pools", tuple(int(n) for n in self.eval_pools))
        object.__setattr__(self, "bulk_residual_step_rad", tuple(float(v) for v in self.bulk_residual_step_rad))
        for key in (
            "draws_train",
            "draws_validation",
            "draws_test",
            "trials_per_draw",
            "max_epochs",
            "batch_size",
            "singles_per_group",
            "pooled_per_group",
            "max_pool_pixels",
            "replicates",
        ):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"TrainConfig.{key} must be a positive integer; got {v!r}")
        for key in ("draws_train", "draws_validation", "draws_test"):
            if getattr(self, key) < len(CLASSES):
                raise ValueError(
                    f"TrainConfig.{key} must be >= {len(CLASSES)} (one draw per motion type); got {getattr(self, key)}"
                )
        if self.max_pool_pixels > self.trials_per_draw:
            raise ValueError(
                f"TrainConfig.max_pool_pixels ({self.max_pool_pixels}) must not exceed "
                f"trials_per_draw ({self.trials_per_draw})"
            )
        if any(n < 1 or n > self.trials_per_draw for n in self.eval_pools) or 1 not in self.eval_pools:
            raise ValueError(
                f"TrainConfig.eval_pools must include 1 and lie in [1, trials_per_draw]; got {self.eval_pools}"
            )
        if (
            isinstance(self.noise_probability, bool)
            or not isinstance(self.noise_probability, (int, float))
            or not 0.0 <= float(self.noise_probability) <= 1.0
        ):
            raise ValueError(
                f"TrainConfig.noise_probability must be a probability in [0, 1]; got {self.noise_probability!r}"
            )
        if (
            isinstance(self.static_edge_probability, bool)
            or not isinstance(self.static_edge_probability, (int, float))
            or not 0.0 <= float(self.static_edge_probability) <= 1.0
        ):
            raise ValueError(
                f"TrainConfig.static_edge_probability must be a probability in [0, 1]; "
                f"got {self.static_edge_probability!r}"
            )
        if not 0.0 <= self.min_probability < 1.0:
            raise ValueError(f"TrainConfig.min_probability must be in [0, 1); got {self.min_probability!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"TrainConfig.seed must be a non-negative integer; got {self.seed!r}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        if d["static_edge_probability"] == 0:  # recipes without edges keep the dicts recorded before the field
            del d["static_edge_probability"]
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


#: Shipped recipes that differ from the :class:`TrainConfig` defaults (``doct-train --spec NAME``).
#: Why each choice, with the measurements behind it in the research reports (``research/results/``, each
#: written by the command ``research/README.md`` gives; the history is in ``research/classifier-history.md``):
#:
#: - The signature spec has several times more features than LIV/OCDS: more draws, a network trained
#:   more slowly and more regularised (the LIV/OCDS recipe stops it after a few epochs), a test split twice
#:   as large, and the random-bulk-phase test split. Wider networks did not score differently within one
#:   SE on the same test draws and cost more per pixel in ``doct-classify``; training longer reached the
#:   same accuracy–coverage curve. What helped is the input scale: the correlation coefficients read as log
#:   decorrelation (:mod:`classifier.model`). With that input the learning curve keeps rising to the
#:   recipe's training draws (``research/results/signature-learning-curve.md``).
#: - Detection noise is in every training draw (``noise_probability = 1``, SNR U[10, 40] dB relative to the
#:   mean intensity). Every measurement holds noise, and at 40 dB it is nearly absent, so noise-free draws
#:   teach only a limit no data reach: a model that saw them reads the tiny decorrelation of slow motion at
#:   the first lags exactly, which any noise floor (``1 − ρ ≈ 2/SNR`` at every lag) hides
#:   (``research/results/independent-prior-ablation.md``, on the independent reference simulator).
#: - The static scatterers stay (a static fraction U[0, 0.8] in half the draws: tissue has them), although
#:   the independent prior has none and training without them scores higher there (the same report): that
#:   gain is the test prior's, not the physics'.
#: - The flow's polar angle is drawn uniform in angle (``flow_polar_law = "uniform-angle"``), not
#:   isotropically: near-axial flow, the direction an intensity signature tells least well from
#:   random-ballistic motion (it decorrelates by axial transit, which only the axial-reduced
#:   configuration slows), gets more of the flow draws than an isotropic law gives it.
SPEC_RECIPES: dict[str, dict[str, Any]] = {
    "signature": {
        "draws_train": 1920,
        "draws_validation": 90,
        "draws_test": 180,
        "replicates": 8,
        "hidden": (64, 64),
        "learning_rate": 1e-3,
        "weight_decay": 1e-3,
        "patience": 15,
        "max_epochs": 60,
        "bulk_phase_test": True,
        "flow_polar_law": "uniform-angle",
        "noise_probability": 1.0,
    },
}
#: The two-wavelength signature spec (the signature's 24 intensity features at 840 and 1310 nm) and the
#: B-scan signature spec (the lateral reduction along x only) take it too (noise in every draw, the prior
#: scaled to the system: :data:`SCALED_PRIOR_SPECS`).
SPEC_RECIPES["two-wavelength-signature"] = dict(SPEC_RECIPES["signature"])
SPEC_RECIPES["signature-bscan"] = dict(SPEC_RECIPES["signature"])
#: The B-scan signature with the field group (|g1| at the first lags) for bulk-phase-corrected maps: the
#: same recipe, with the residual of the correction in the prior (a random walk of step SD up to 0.05 rad:
#: the residual ``torchdoct maps --bulk-phase weighted-mean`` leaves on dynamic tissue,
#: docs/physics.md §12), and the random-bulk-phase test split showing what an uncorrected phase costs.
SPEC_RECIPES["signature-bscan-field"] = {**SPEC_RECIPES["signature-bscan"], "bulk_residual_step_rad": (0.0, 0.05)}
#: The A-line signature (no lateral reduction: one A-line's time series) takes the signature recipe too.
SPEC_RECIPES["signature-aline"] = dict(SPEC_RECIPES["signature"])


#: Shipped specs trained with the :class:`TrainConfig` defaults (LIV/OCDS).
_SHIPPED_DEFAULT_RECIPE = ("single-acquisition", "two-wavelength", "single-acquisition-bscan")
#: Recipe of a signature spec of one's own (``doct-train --like``, a spec TOML): the shipped signature
#: recipe (without the random-bulk-phase test split, which only the models that read the phase need; with a
#: static edge in a quarter of the replicates). Its cost is mostly the network's fit, on one thread so that
#: the model does not depend on the cores (the training time is in each model's report).
OWN_SIGNATURE_RECIPE: dict[str, Any] = {
    **SPEC_RECIPES["signature"],
    "bulk_phase_test": False,
    "static_edge_probability": 0.25,
}


def recipe_for(spec: FeatureSpec) -> dict[str, Any]:
    """The recipe (:class:`TrainConfig` fields) of a spec of one's own: :data:`OWN_SIGNATURE_RECIPE` for
    a signature spec (with the random-bulk-phase test split and a residual bulk phase in the prior when it
    reads the field's phase, as :data:`SPEC_RECIPES` ``"signature-bscan-field"``), the defaults for
    LIV/OCDS."""
    if not spec.is_signature:
        return {}
    recipe = dict(OWN_SIGNATURE_RECIPE)
    if spec.needs_field:
        recipe.update(
            bulk_phase_test=True, bulk_residual_step_rad=SPEC_RECIPES["signature-bscan-field"]["bulk_residual_step_rad"]
        )
    return recipe


#: Shipped specs whose default prior is scaled to their system (:func:`default_prior`,
#: :func:`classifier.own_system.prior_for_spec`: each motion type's identifiable range ± half a decade, flow its
#: own range, speeds capped at what the simulator holds; the B-scan models keep their PSF's y width). A fixed
#: prior spends many draws on motion that is static or decorrelated at the spec's system and never shows slow
#: flow that is identifiable; the scaled prior scored higher on the independent reference simulator, overall
#: and for flow in every polar band (research/results/independent-ceiling.md, parts d and e, and each model's
#: ``research/results/SPEC-independent.md``).
SCALED_PRIOR_SPECS = (
    "signature",
    "signature-bscan",
    "signature-bscan-field",
    "signature-aline",
    "two-wavelength-signature",
)


def default_prior(cfg: TrainConfig) -> Prior:
    """The prior of a recipe when none is given: :class:`Prior` with the recipe's flow polar law and
    residual bulk phase, scaled to the spec's system (:func:`classifier.own_system.prior_for_spec`) for the
    shipped specs of :data:`SCALED_PRIOR_SPECS`."""
    prior = Prior(
        flow_polar_law=cfg.flow_polar_law,
        bulk_residual_step_rad=cfg.bulk_residual_step_rad,
        noise_probability=cfg.noise_probability,
        static_edge_probability=cfg.static_edge_probability,
    )
    if str(cfg.spec) in SCALED_PRIOR_SPECS:
        from .own_system import prior_for_spec

        prior = prior_for_spec(load_spec(cfg.spec), prior)[0]
    return prior


#: Prior of the shifted-prior test set: nuisances the training prior (:class:`~classifier.prior.Prior`)
#: does not draw, or draws elsewhere. Flow at 10-80° from the depth axis (isotropic within that
#: cone: cos of the polar angle ~ U[cos 80°, cos 10°]; training: the whole sphere), the density of the
#: moving scatterers fixed at 0.05 µm⁻³ (training: U[0.02, 0.1]), no static fraction (training: with
#: probability 1/2), noise always on at SNR U[15, 25] dB (training: with probability 1/2 at
#: U[10, 40] dB; before the noise prior was widened, 15-20 dB lay outside it), both random-ballistic
#: direction laws, the training prior's magnitude ranges (:func:`shifted_prior` takes them, and ε,
#: from the prior trained on). Its split is the test split of the same seed (its draws have the test
#: draws' motion types, magnitudes and simulator seeds; the nuisances above are its own) and is cached
#: apart (the cache key holds the prior).
SHIFTED_PRIOR = Prior(
    ballistic_directions="both",
    flow_polar_angle_deg=(10.0, 80.0),
    density_per_um3=(0.05, 0.05),
    static_probability=0.0,
    noise_probability=1.0,
    snr_db=(15.0, 25.0),
)
#: What must hold on the shifted-prior test set, per pixel (pool 1): balanced accuracy over the
#: decided identifiable samples at least, expected calibration error at most.
SHIFTED_TARGETS = {"pool": "1", "balanced_accuracy_identifiable": 0.85, "ece": 0.05}


def shifted_prior(prior: Prior | None = None) -> Prior:
    """:data:`SHIFTED_PRIOR` with the magnitude ranges and ε of ``prior`` (the prior trained on), its fixed
    density scaled as ``prior``'s lower end is from :class:`Prior`'s (a prior scaled to another system's
    resolution volume, :func:`classifier.own_system.prior_for_spec`)."""
    prior = prior or Prior()
    scale = prior.density_per_um3[0] / Prior().density_per_um3[0]  # a prior scaled to another system (N_eff)
    density = tuple(float(f"{d * scale:.3g}") for d in SHIFTED_PRIOR.density_per_um3) if scale != 1.0 else None
    return dataclasses.replace(
        SHIFTED_PRIOR,
        diffusion_um2_per_s=prior.diffusion_um2_per_s,
        speed_um_per_s=prior.speed_um_per_s,
        flow_speed_um_per_s=prior.flow_speed_um_per_s,
        identifiability_epsilon=prior.identifiability_epsilon,
        **({} if density is None else {"density_per_um3": density}),
    )
