"""Feature specifications: which DOCT metrics, at which system configurations, make a feature vector.

A feature vector is the LIV (dB²) and OCDS (1/s) (or the decorrelation-signature features of
:mod:`torchdoct.sim.signature`, e.g. ``rho_db_3``, ``g1_1``; spec ``signature``) of one pixel at several system configurations
(wavelength, lateral 1/e² resolution, axial FWHM resolution; :mod:`torchdoct.conventions`), all
computed from the *same* scatterers: in simulation, the systems of one scene; in measured data,
one complex dataset and its computational resolution reductions (reference paper §2.1.3), or a
co-registered dual-band acquisition. The reference paper (§3.3, §4) finds that the way LIV and
OCDS change with wavelength and resolution differs between diffusion, random-ballistic motion and
mono-directional flow (physics.md §5.3-5.7, §11): that difference is what the classifier learns.

Specifications are declared once, as TOML files in ``classifier/specs/`` (four ship:
``single-acquisition``, ``two-wavelength`` and their signature twins ``signature``,
``two-wavelength-signature``), and stored in every model's metadata. Feature
``i`` is ``f"{metric}@{configuration.name}"``, ordered metric-major within each configuration::

    liv@original, ocds@original, liv@axial=14, ocds@axial=14, ...

Consumers match a maps channel to a feature by its metric and its optics
(:class:`torchdoct.optics.ChannelOptics`: wavelength, lateral and axial resolution within 1e-6
relative, the one match of the project), never by name. A configuration is isotropic unless it gives
``lateral_resolution_y_um`` (the 1/e² width along y; default: as along x).

This module imports no torch (the classify path uses it); from torchdoct only torch-free modules.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchdoct.files import shipped_files
from torchdoct.optics import REL_TOL, ChannelOptics, same_value
from torchdoct.sim import signature as _signature_module

__all__ = [
    "METRIC_UNITS",
    "physical_range",
    "REL_TOL",
    "metric_unit",
    "Configuration",
    "FeatureSpec",
    "load_spec",
    "shipped_specs",
    "spec_from_dict",
    "toml_text",
    "same_value",
]

#: Metrics a feature may use, with the unit strings of the maps format.
METRIC_UNITS = {"liv": "dB^2", "ocds": "1/s"}


def _signature():
    """:mod:`torchdoct.sim.signature` (names and units of the signature features; no torch at import)."""
    return _signature_module


def metric_unit(metric: str) -> str:
    """Unit of a metric: :data:`METRIC_UNITS`, or a signature feature of :mod:`torchdoct.sim.signature`
    (``rho_db_M``, ``rho_lin_M``, ``g1_M``, ``g1_phase_M``, ``phase_ramp``, ``lin_contrast``, ``db_variance``)."""
    if metric in METRIC_UNITS:
        return METRIC_UNITS[metric]
    return _signature().feature_unit(metric)


#: Largest LIV / dB variance a pixel can have and still be a DOCT measurement (dB²): fully developed
#: speckle gives 31 dB² (physics.md §5.6); a value beyond this is corrupt input, not a sample.
MAX_DB_VARIANCE_DB2 = 1e4


def physical_range(metric: str, n_frames: int) -> tuple[float, float]:
    """The values a feature can take from a real sequence of ``n_frames`` frames, ``(low, high)``.

    Correlation coefficients (``rho_lin_M``, ``rho_db_M``) lie in [−1, 1], ``g1_M`` in [0, 1], a phase in
    [−π, π], ``phase_ramp`` (a cosine) in [−1, 1]; the temporal contrast ``Var I/⟨I⟩²`` (ddof 0) in
    [0, T − 1]; LIV and the dB variance in [0, :data:`MAX_DB_VARIANCE_DB2`]; OCDS (1/s) is any finite
    number. ``doct-classify`` masks a pixel with a feature outside its range (and counts it): the
    network was never shown such a value and would extrapolate (torchdoct.sim.signature for the
    definitions)."""
    tol = 1e-3  # float32 round-off of a coefficient computed from near-constant sequences
    if metric == "ocds":
        return -math.inf, math.inf
    if metric == "liv":
        return 0.0, MAX_DB_VARIANCE_DB2
    kind, _ = _signature().parse_feature(metric)
    if kind in ("rho_lin", "rho_db", "phase_ramp"):
        return -1.0 - tol, 1.0 + tol
    if kind == "g1":
        return 0.0, 1.0 + tol
    if kind == "g1_phase":
        return -math.pi - tol, math.pi + tol
    if kind == "lin_contrast":
        return 0.0, float(max(n_frames - 1, 1)) * (1.0 + tol)
    return 0.0, MAX_DB_VARIANCE_DB2  # db_variance


def _num(path: str, value: Any, *, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{path} must be a number; got {type(value).__name__} {value!r}")
    v = float(value)
    if not math.isfinite(v) or (positive and v <= 0):
        raise ValueError(f"{path} must be a finite number > 0; got {value!r}")
    return v


@dataclass(frozen=True, kw_only=True)
class Configuration:
    """One system configuration of a feature vector.

    ``wavelength_um``: vacuum centre wavelength (µm). ``lateral_resolution_um``: 1/e² full width of
    the intensity PSF along x (µm). ``axial_resolution_um``: intensity FWHM in the medium (µm).
    ``lateral_resolution_y_um``: the 1/e² width along y (µm; ``None``, the default: as along x). ``name``
    is a short label used in feature names (``"original"``, ``"axial=14"``, ``"840nm"``).
    """

    name: str
    wavelength_um: float
    lateral_resolution_um: float
    axial_resolution_um: float
    lateral_resolution_y_um: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise TypeError(f"configuration.name must be a non-empty string; got {self.name!r}")
        p = f"configuration[{self.name!r}]"
        wl = _num(f"{p}.wavelength_um", self.wavelength_um)
        if not 0.1 <= wl <= 20.0:
            raise ValueError(f"{p}.wavelength_um = {wl} is outside 0.1-20 µm (fix: micrometres, 840 nm is 0.84)")
        _num(f"{p}.lateral_resolution_um", self.lateral_resolution_um)
        _num(f"{p}.axial_resolution_um", self.axial_resolution_um)
        if self.lateral_resolution_y_um is not None:
            _num(f"{p}.lateral_resolution_y_um", self.lateral_resolution_y_um)

    @property
    def optics(self) -> ChannelOptics:
        """The configuration's optics as the project's one value (:class:`torchdoct.optics.ChannelOptics`)."""
        return ChannelOptics(
            self.wavelength_um, self.lateral_resolution_um, self.axial_resolution_um, self.lateral_resolution_y_um
        )

    def matches(
        self,
        optics: ChannelOptics | float,
        lateral_resolution_um: float | None = None,
        axial_resolution_um: float | None = None,
        *,
        lateral_y: bool = True,
    ) -> bool:
        """:meth:`ChannelOptics.matches` of :attr:`optics` and ``optics`` (a :class:`ChannelOptics`, or
        wavelength, lateral and axial resolution of an isotropic system)."""
        if not isinstance(optics, ChannelOptics):
            if lateral_resolution_um is None or axial_resolution_um is None:
                raise TypeError(
                    "matches(wavelength_um, lateral_resolution_um, axial_resolution_um): give all three "
                    "resolutions with a wavelength, or one ChannelOptics"
                )
            optics = ChannelOptics(float(optics), float(lateral_resolution_um), float(axial_resolution_um))
        return self.optics.matches(optics, lateral_y=lateral_y)

    def describe(self) -> str:
        return self.optics.describe()

    def to_dict(self) -> dict[str, Any]:
        """The spec-file table of this configuration (``lateral_resolution_y_um`` only when given)."""
        d = dataclasses.asdict(self)
        if d["lateral_resolution_y_um"] is None:
            del d["lateral_resolution_y_um"]
        return d


@dataclass(frozen=True, kw_only=True)
class FeatureSpec:
    """Metrics × configurations, the frame protocol and the OCDS analysis they are computed with.

    ``n_frames`` frames ``frame_interval_s`` apart (s); OCDS per physics.md §2.4 over
    ``ocds_delay_range_s`` (s) on the ``ocds_scale`` intensity with the ``ocds_estimator``
    correlation; ``refractive_index`` is the medium's phase index used in simulation (the paper's
    n = 1).
    """

    name: str
    configurations: tuple[Configuration, ...]
    metrics: tuple[str, ...] = ("liv", "ocds")
    description: str = ""
    n_frames: int = 32
    frame_interval_s: float = 0.2048
    ocds_delay_range_s: tuple[float, float] = (0.2048, 1.2288)
    ocds_scale: str = "db"
    ocds_estimator: str = "pearson"
    refractive_index: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "configurations", tuple(self.configurations))
        object.__setattr__(self, "metrics", tuple(self.metrics))
        object.__setattr__(self, "ocds_delay_range_s", tuple(float(x) for x in self.ocds_delay_range_s))
        if not isinstance(self.name, str) or not self.name:
            raise TypeError(f"spec name must be a non-empty string; got {self.name!r}")
        if not self.configurations:
            raise ValueError(f"spec {self.name!r}: needs at least one [[configuration]]")
        for c in self.configurations:
            if not isinstance(c, Configuration):
                raise TypeError(f"spec {self.name!r}: configurations must be Configuration; got {c!r}")
        names = [c.name for c in self.configurations]
        if len(set(names)) != len(names):
            raise ValueError(f"spec {self.name!r}: duplicate configuration names {names}")
        for i, a in enumerate(self.configurations):
            for b in self.configurations[i + 1 :]:
                if a.optics.matches(b.optics):
                    raise ValueError(
                        f"spec {self.name!r}: configurations {a.name!r} and {b.name!r} are the same system"
                    )
        if not self.metrics:
            raise ValueError(f"spec {self.name!r}: metrics must not be empty")
        for m in self.metrics:
            try:
                metric_unit(m)
            except ValueError:
                raise ValueError(
                    f"spec {self.name!r}: metric {m!r} is not supported; use {sorted(METRIC_UNITS)} "
                    "or signature features (rho_db_M, rho_lin_M, g1_M, g1_phase_M, phase_ramp, "
                    "lin_contrast, db_variance; torchdoct.sim.signature)"
                ) from None
        if len(set(self.metrics)) != len(self.metrics):
            raise ValueError(f"spec {self.name!r}: a metric is listed twice: {list(self.metrics)}")
        if isinstance(self.n_frames, bool) or not isinstance(self.n_frames, int) or self.n_frames < 3:
            raise ValueError(f"spec {self.name!r}: n_frames must be an integer >= 3; got {self.n_frames!r}")
        _num("protocol.frame_interval_s", self.frame_interval_s)
        rng = self.ocds_delay_range_s
        if len(rng) != 2 or _num("analysis.ocds_delay_range_s[1]", rng[1]) <= _num(
            "analysis.ocds_delay_range_s[0]", rng[0]
        ):
            raise ValueError(
                f"analysis.ocds_delay_range_s must be [min_s, max_s] with max > min; "
                f"got {list(self.ocds_delay_range_s)}"
            )
        if self.ocds_scale not in ("db", "linear"):
            raise ValueError(f"analysis.ocds_scale must be 'db' or 'linear'; got {self.ocds_scale!r}")
        if self.ocds_estimator not in ("pearson", "biased"):
            raise ValueError(f"analysis.ocds_estimator must be 'pearson' or 'biased'; got {self.ocds_estimator!r}")
        n = _num("refractive_index", self.refractive_index)
        if not 1.0 <= n <= 5.0:
            raise ValueError(f"refractive_index must be in [1, 5]; got {n}")

    # ------------------------------------------------------------------------------------------
    @property
    def features(self) -> tuple[tuple[str, Configuration], ...]:
        """(metric, configuration) of every feature, in feature order."""
        return tuple((m, c) for c in self.configurations for m in self.metrics)

    @property
    def feature_names(self) -> tuple[str, ...]:
        return tuple(f"{m}@{c.name}" for m, c in self.features)

    @property
    def feature_units(self) -> tuple[str, ...]:
        return tuple(metric_unit(m) for m, _ in self.features)

    @property
    def is_signature(self) -> bool:
        """True when the features are decorrelation-signature features (:mod:`torchdoct.sim.signature`)."""
        return any(m not in METRIC_UNITS for m in self.metrics)

    @property
    def needs_field(self) -> bool:
        """True when some feature needs the complex field (phase), not only the intensity."""
        return any(m not in METRIC_UNITS and _signature().needs_field(m) for m in self.metrics)

    @property
    def n_features(self) -> int:
        return len(self.configurations) * len(self.metrics)

    @property
    def frame_times_s(self) -> tuple[float, ...]:
        return tuple(i * self.frame_interval_s for i in range(self.n_frames))

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the spec-file schema (round-trips through :func:`spec_from_dict`)."""
        return {
            "name": self.name,
            "description": self.description,
            "metrics": list(self.metrics),
            "refractive_index": self.refractive_index,
            "protocol": {"n_frames": self.n_frames, "frame_interval_s": self.frame_interval_s},
            "analysis": {
                "ocds_delay_range_s": list(self.ocds_delay_range_s),
                "ocds_scale": self.ocds_scale,
                "ocds_estimator": self.ocds_estimator,
            },
            "configuration": [c.to_dict() for c in self.configurations],
        }


def _toml_value(v: Any) -> str:
    import json

    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"TOML has no value for {v!r}")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)  # a JSON string is a TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {type(v).__name__} {v!r}")


def toml_text(data: dict[str, Any], header: str = "") -> str:
    """``data`` as TOML: its plain keys, then its tables (``[name]``) and arrays of tables (``[[name]]``),
    one level deep (the spec and prior files); ``None`` values are left out. ``header``: comment lines."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    plain = {
        k: v
        for k, v in data.items()
        if v is not None
        and not isinstance(v, dict)
        and not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v))
    }
    lines += [f"{k} = {_toml_value(v)}" for k, v in plain.items()]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items() if vv is not None]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                lines += ["", f"[[{k}]]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in item.items() if vv is not None]
    return "\n".join(lines) + "\n"


_TOP_KEYS = {"name", "description", "metrics", "refractive_index", "protocol", "analysis", "configuration"}


def _keys(path: str, table: Any, allowed: set[str], required: set[str]) -> dict:
    if not isinstance(table, dict):
        raise TypeError(f"{path} must be a table; got {type(table).__name__}")
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {unknown} (allowed: {sorted(allowed)})")
    missing = sorted(required - set(table))
    if missing:
        raise ValueError(f"{path}: missing key(s) {missing}")
    return table


def spec_from_dict(data: dict[str, Any]) -> FeatureSpec:
    """Build a validated :class:`FeatureSpec` from the spec-file schema (see ``classifier/specs/``)."""
    _keys("spec", data, _TOP_KEYS, {"name", "configuration"})
    prot = _keys("spec.protocol", data.get("protocol", {}), {"n_frames", "frame_interval_s"}, set())
    ana = _keys(
        "spec.analysis", data.get("analysis", {}), {"ocds_delay_range_s", "ocds_scale", "ocds_estimator"}, set()
    )
    confs = data["configuration"]
    if not isinstance(confs, list):
        raise TypeError("spec.configuration must be an array of tables ([[configuration]])")
    keys = {"name", "wavelength_um", "lateral_resolution_um", "axial_resolution_um"}
    configurations = tuple(
        Configuration(**_keys(f"spec.configuration[{i}]", c, keys | {"lateral_resolution_y_um"}, keys))
        for i, c in enumerate(confs)
    )
    kw: dict[str, Any] = {
        "name": data["name"],
        "configurations": configurations,
        "description": data.get("description", ""),
    }
    if "metrics" in data:
        if not isinstance(data["metrics"], list):
            raise TypeError(f"spec.metrics must be a list of metric names; got {data['metrics']!r}")
        kw["metrics"] = tuple(data["metrics"])
    if "refractive_index" in data:
        kw["refractive_index"] = data["refractive_index"]
    kw.update(prot)
    if "ocds_delay_range_s" in ana:
        kw["ocds_delay_range_s"] = tuple(ana["ocds_delay_range_s"])
    for k in ("ocds_scale", "ocds_estimator"):
        if k in ana:
            kw[k] = ana[k]
    return FeatureSpec(**kw)


def shipped_specs() -> dict[str, Path]:
    """Names and paths of the specifications shipped in ``classifier/specs/``."""
    return shipped_files("classifier", "specs")


def shipped_or_path(key: str, shipped: dict[str, Path], what: str) -> Path:
    """The shipped file named ``key``, else the file at path ``key``; ``what`` names it in the error."""
    if key in shipped:
        return shipped[key]
    from torchdoct.files import check_regular_file

    try:
        return check_regular_file(key, what)
    except FileNotFoundError:
        raise FileNotFoundError(
            f"{what} {key!r}: no such file and not a shipped {what} (shipped: {', '.join(shipped) or 'none'})"
        ) from None


def load_spec(name_or_path: str | Path | FeatureSpec) -> FeatureSpec:
    """A shipped spec by name (``single-acquisition``, ``two-wavelength``) or a TOML spec file."""
    if isinstance(name_or_path, FeatureSpec):
        return name_or_path
    path = shipped_or_path(str(name_or_path), shipped_specs(), "feature spec")
    from torchdoct.files import check_nesting, read_capped, toml_loads

    try:
        raw = read_capped(path, "feature spec")
        check_nesting(raw, path.name, toml=True)  # before the parser's recursion
        data = toml_loads(raw.decode("utf-8"))
        check_nesting(data, path.name)  # dotted keys nest tables without brackets
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path.name}: not valid TOML: {err}") from None
    except UnicodeDecodeError as err:
        raise ValueError(
            f"{path.name}: not a TOML text file (byte {err.start} is not UTF-8 text); give a feature "
            "spec (TOML, UTF-8) or a shipped spec name, not a data or image file"
        ) from None
    try:
        return spec_from_dict(data)
    except (TypeError, ValueError) as err:
        raise type(err)(f"{path.name}: {err}") from None
