"""A small MLP that maps DOCT feature vectors to motion-type probabilities.

Input ``[N, F + 1]`` float32: the spec's features in spec order (LIV in dB², OCDS in 1/s) and, last,
``pool_pixels``: how many independent pixels were averaged into the feature vector (1 for a single
pixel; ``doct-classify --pool N`` sets it, see :mod:`classifier.infer`). Everything the network
needs to see raw features lives inside it, so the ONNX file is self-contained:

1. fixed transforms: ``log(max(LIV, 0) + 0.01 dB²)`` (LIV spans six decades between a nearly
   static and a fully decorrelated pixel), OCDS unchanged, ``log(pool_pixels)``; for the
   correlation coefficients of the decorrelation signature (``rho_lin_m``, ``rho_db_m``, ``g1_m``,
   :mod:`torchdoct.sim.signature`) the log decorrelation ``log(max(1 − ρ, 0) + 0.001)``. At short
   delays ``1 − ρ_I(τ)`` grows as ``τ`` for diffusion (``|g1|² = exp(−2q²Dτ)``) and as ``τ²`` for
   random-ballistic motion and flow (Gaussian transit and Doppler terms; physics.md §5.3-5.4), and a
   resolution change scales flow's transit time only: on this scale the motion type is a slope
   against ``log m`` and the resolution dependence an offset between configurations, both linear
   in the inputs (measured gain: research/classifier-history.md);
2. standardisation with the training set's mean and SD (buffers);
3. ``Linear → ReLU`` hidden layers, a linear output layer;
4. a temperature (buffer, fitted on the validation split after training) and softmax.

Output ``[N, C]`` class probabilities (float32), classes in the order of the model's metadata.

Magnitude models (``n_magnitude = K`` motion classes, the signature spec) add two linear heads on
the last hidden layer: per motion class ``k`` the predicted ``log10`` magnitude (``D`` in µm²/s for
diffusion, ``v`` in µm/s for ballistic motion and flow) *given that the class is k*, and its
log-variance; trained by the Gaussian negative log-likelihood on identifiable samples of the true
class, the SD then scaled by one factor fitted on the validation split (:meth:`magnitude`).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["MotionClassifier", "LIV_OFFSET_DB2", "DECORRELATION_OFFSET"]

#: Offset (dB²) inside the LIV log transform: below it, LIV differences carry no weight.
LIV_OFFSET_DB2 = 0.01
#: Offset inside the log decorrelation ``log(max(1 − ρ, 0) + offset)`` of correlation features.
DECORRELATION_OFFSET = 1e-3


class MotionClassifier(nn.Module):
    """``features [N, F+1] → probabilities [N, C]`` (module docstring).

    ``log_columns``: indices of the LIV features (log-transformed); ``correlation_columns``: indices
    of the correlation coefficients (log decorrelation); ``n_features`` counts the spec's features
    (the ``pool_pixels`` column comes on top).
    """

    # the buffers (register_buffer in __init__; magnitude_sd_scale only with a magnitude head)
    liv_mask: torch.Tensor
    corr_mask: torch.Tensor
    pool_mask: torch.Tensor
    feature_mean: torch.Tensor
    feature_scale: torch.Tensor
    temperature: torch.Tensor
    magnitude_sd_scale: torch.Tensor

    def __init__(
        self,
        n_features: int,
        n_classes: int,
        log_columns: Sequence[int],
        hidden: Sequence[int] = (64, 64),
        n_magnitude: int = 0,
        correlation_columns: Sequence[int] = (),
    ):
        super().__init__()
        if n_features < 1 or n_classes < 2:
            raise ValueError(f"need n_features >= 1 and n_classes >= 2; got {n_features}, {n_classes}")
        width = n_features + 1
        mask = torch.zeros(width, dtype=torch.bool)
        corr = torch.zeros(width, dtype=torch.bool)
        for m, cols in ((mask, log_columns), (corr, correlation_columns)):
            for c in cols:
                if not 0 <= int(c) < n_features:
                    raise ValueError(f"column {c} is outside the {n_features} features")
                if mask[int(c)] or corr[int(c)]:
                    raise ValueError(f"column {c} is both a LIV and a correlation column")
                m[int(c)] = True
        pool = torch.zeros(width, dtype=torch.bool)
        pool[-1] = True
        self.n_features = int(n_features)
        self.n_classes = int(n_classes)
        self.hidden = tuple(int(h) for h in hidden)
        self.register_buffer("liv_mask", mask)
        self.register_buffer("corr_mask", corr)
        self.register_buffer("pool_mask", pool)
        self.register_buffer("feature_mean", torch.zeros(width))
        self.register_buffer("feature_scale", torch.ones(width))
        self.register_buffer("temperature", torch.ones(()))
        layers: list[nn.Module] = []
        prev = width
        for h in self.hidden:
            layers += [nn.Linear(prev, h), nn.ReLU()]
            prev = h
        layers.append(nn.Linear(prev, n_classes))
        self.net = nn.Sequential(*layers)
        self.n_magnitude = int(n_magnitude)
        if self.n_magnitude:  # created after the classifier layers: their seeded initialisation is unchanged
            self.magnitude_mean = nn.Linear(prev, self.n_magnitude)
            self.magnitude_logvar = nn.Linear(prev, self.n_magnitude)
            self.register_buffer("magnitude_sd_scale", torch.ones(()))

    def transform(self, x: torch.Tensor) -> torch.Tensor:
        """Fixed transforms of step 1 (the last column is ``pool_pixels``)."""
        if x.dim() != 2 or x.shape[1] != self.n_features + 1:
            raise ValueError(
                f"features must be [N, {self.n_features + 1}] (spec features + pool_pixels); got {tuple(x.shape)}"
            )
        liv = torch.log(torch.clamp(x, min=0.0) + LIV_OFFSET_DB2)
        pool = torch.log(torch.clamp(x, min=1.0))
        decorrelation = torch.log(torch.clamp(1.0 - x, min=0.0) + DECORRELATION_OFFSET)
        return torch.where(
            self.liv_mask, liv, torch.where(self.corr_mask, decorrelation, torch.where(self.pool_mask, pool, x))
        )

    def set_normalization(self, x: torch.Tensor) -> None:
        """Store mean and SD of the transformed training features (SD floored at 1e-6)."""
        with torch.no_grad():
            t = self.transform(x)
            self.feature_mean.copy_(t.mean(0))
            self.feature_scale.copy_(t.std(0).clamp(min=1e-6))

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        """Logits before the temperature."""
        z = (self.transform(x) - self.feature_mean) / self.feature_scale
        return self.net(z)

    def heads(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Logits before the temperature ``[N, C]``, magnitude means ``[N, K]`` and log-variances
        ``[N, K]`` before the SD scale (magnitude models only)."""
        z = (self.transform(x) - self.feature_mean) / self.feature_scale
        h = self.net[:-1](z)
        return self.net[-1](h), self.magnitude_mean(h), self.magnitude_logvar(h)

    def magnitude(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Predicted ``log10`` magnitude per motion class ``[N, K]`` and its predictive SD ``[N, K]``
        (``exp(logvar/2)`` times the validation-fitted scale; Gaussian predictive distribution)."""
        _, mean, logvar = self.heads(x)
        return mean, torch.exp(0.5 * logvar) * self.magnitude_sd_scale

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.softmax(self.logits(x) / self.temperature, dim=1)
