"""The cases: phantoms of the kinds on which a per-pixel model decides flow as random-ballistic motion with
confidence, and of motions and samplings unlike the training prior's, run the way a user runs them
(``torchdoct render`` → ``torchdoct maps --signature`` → ``doct-classify``, the models ``doct-classify``
picks), each scored with the rules of :mod:`classifier.ambiguity` (the default) and without them
(``--decide-ballistic``: the model alone).

Run (from the repository root)::

    python -m classifier.bench.cases --out DIR [--force] [--threads N] [--no-progress]

It writes ``DIR/cases.json`` and ``DIR/cases.md`` (the recorded run: ``docs/benchmarks/cases.*``, rendered
in docs/benchmarks/grid.md). Unlike the phantom grid (:mod:`classifier.bench.grid`), whose phantoms are built
from the model's own system and identifiable speed levels, these are fixed phantoms of one common system:
840 nm, lateral resolution 4.9 µm (the 1/e² width of the intensity PSF), axial 3.8 µm (its FWHM), 2 µm pixels
(not the grid's third of the lateral resolution), 32 frames at 0.2048 s, moving density
:data:`DENSITY` µm⁻³. The cases (:data:`CASES`, :func:`case_dict`):

* ``layers``: a B-scan of 96 × 96 pixels, three slabs stacked in depth without static tissue: diffusion
  (D = 0.03 µm²/s), random-ballistic motion (0.12 µm/s, isotropic directions) and flow (0.3 µm/s, polar angle
  45° from the beam, azimuth 60° from the B-scan's x axis);
* ``layers-slow-25dB``: the same with the flow at 0.1 µm/s and complex Gaussian noise 25 dB below the mean
  intensity;
* ``layers-slow-random-20dB``: the diffusion and the random-ballistic motion slow (D = 0.001 µm²/s,
  0.03 µm/s), noise 20 dB below the mean intensity: the flow is then the steadiest population of the sample,
  and its intensity drift hides under the noise pixel by pixel (the case of the Doppler reference's
  population drift test, docs/concepts/doppler-reference.md §4);
* ``layers-crossing``: the flow nearly across the B-scan plane (polar 80°, azimuth 85°): the flow a B-scan
  cannot tell from random-ballistic motion (docs/abstention.md, rule 1), whose right outcome is a set or
  ``indeterminate``;
* ``layers-static``: the layers inside static tissue: static tissue of the same density under every pixel,
  the field of a second phantom on the same grid added to the layers' (:func:`case_phantoms`, as the phantom
  grid's ``background`` context), so half the mean intensity of a moving pixel is static;
* ``layers-10dB``: ``layers`` under noise 10 dB below the mean intensity: only the brightest speckles are
  steady enough to be a Doppler reference's candidates, a few tens in the B-scan, and the slow flow's
  intensity drift hides under the noise even over all of them (docs/concepts/doppler-reference.md §4, step 7);
* ``layers-volume`` and ``layers-crossing-volume``: ``layers`` and ``layers-crossing`` as volumes of
  :data:`VOLUME_NY` planes along y, whose y neighbours see the flow across the plane;
* ``layers-static-coarse-y-volume``: the layers inside static tissue under 20 dB of noise, as a volume whose
  slow axis y is undersampled (:data:`COARSE_PITCH_Y_UM`: neighbouring planes share no speckle), with the flow
  along y (1 µm/s): the volume cannot see the flow move, and a ``ballistic`` decision there is a set
  (docs/abstention.md, rule 1);
* ``layers-half-static``: ``layers-slow-random-20dB`` with static tissue under the A-lines at x < 0 only: the
  static-free A-lines take the B-scan's Doppler reference (docs/concepts/doppler-reference.md §4);
* ``layers-sheared-static``: ``layers-static`` under 20 dB of noise with a sheared flow: a plane Poiseuille
  profile across the flow layer (:data:`SHEAR_SLABS` sub-slabs, peak 2 µm/s, parallel to the layer at azimuth
  30°), whose speckle decorrelates by the velocity spread within the PSF as well as by transit;
* ``layers-mixed-volume``: a static-free volume under 20 dB of noise whose diffusion layer holds four
  diffusion coefficients and whose random-ballistic layer three speeds over two and three decades
  (:data:`MIXED_RANDOM`), unlike the single value per pixel of the training prior;
* ``layers-sparse-volume``: ``layers-slow-random-20dB``'s motions, noise-free, in a static-free volume at
  :data:`SPARSE_DENSITY` µm⁻³, a few scatterers per resolution volume (non-Gaussian speckle);
* ``layers-jittered-flow``: ``layers`` whose flow scatterers also diffuse (:data:`JITTER_UM2_S`), one
  population with both motions: the renderer labels the layer ``mixed``, and it is scored by
  :func:`classifier.bench.grid.score_mixed` (a decision naming a motion it does not hold is wrong);
* ``layers-maxwell-volume``: ``layers`` as a static-free volume under 20 dB of noise whose random-ballistic
  layer holds :data:`MAXWELL_POPULATIONS` speeds from a Maxwell distribution of mean :data:`BALLISTIC_UM_S`
  (:func:`maxwell_speeds`: an isotropic Gaussian velocity, the other common model of random-ballistic motion);
* ``layers-creeping-half-static-volume``: ``layers-half-static``'s static tissue and slow random motions as a
  volume under 20 dB of noise, with a creeping flow (0.1 µm/s at 30° from the beam): its Doppler phase per frame
  is below rule 10's threshold and its pattern moves less than rule 5's 0.3 pitch over the acquisition, while
  its beat against the static tissue decorrelates it like random motion (docs/abstention.md, rule 2);
* ``vessel-volume``: a static-free volume under 20 dB of noise holding a vessel with a Poiseuille profile
  (:data:`VESSEL`: a cylinder whose axis leaves the B-scan planes at 60° from the beam, the speed falling from
  its axis to zero at its wall; ``flow_profile = "poiseuille"``) beside a diffusing and a random-ballistic
  sphere (``layers-slow-random-20dB``'s motions): the sheared flow whose spread of axial speeds decorrelates as
  random-ballistic motion does (docs/abstention.md, rule 11);
* ``vessel-static-volume``: ``vessel-volume`` with static tissue around the vessel and the spheres (the
  phantom's background), which gives the phase reference;
* ``thin-vessels`` and ``thin-vessels-volume``: a B-scan and a volume of diffusing tissue
  (:data:`THIN_VESSEL_TISSUE_D_UM2_S`) over static tissue under every pixel (as ``layers-static``) under
  20 dB of noise, holding three vessels of radii
  :data:`THIN_VESSEL_RADII_UM` across the B-scan plane and perpendicular to the beam (axes and plug flows along
  y, :data:`THIN_VESSEL_SPEED_UM_S`): vessels narrower than the coarsest configuration's footprint, whose
  coarse features read mostly the tissue around them (docs/abstention.md, "What a class map resolves");
* ``aline``: one A-line's time series (one pixel along x) through ``layers-slow-random-20dB``'s layers, each
  :data:`ALINE_NZ` / 3 pixels deep, classified by ``signature-aline`` (no lateral reduction of one A-line);
* ``motion-types``: the shipped phantom, nine discs in static tissue (flow, diffusion and random-ballistic
  discs of three magnitudes each, 30 dB).

Scores per case, window (``--pool`` 1 and 5) and decision (the rules, the model alone), by
:func:`classifier.bench.grid.score_labels`: per motion the coverage (decided share), the wrong share
(decided as another single class), the set-miss share (a set that leaves the true motion out), the balanced
accuracy on the decided pixels, over every pixel of each motion (``all_pixels``) and over the pixels away
from the other regions (the grid's edge: half the coarsest resolution plus half the window); a ``mixed``
region over its every pixel as ``mixed`` (:func:`classifier.bench.grid.score_mixed`); the cases of
:data:`REGION_CASES` also region by region (``per_region``: each region of one motion over the pixels the
renderer assigns it, :func:`classifier.bench.grid.score_region`).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

SCHEMA_VERSION = 1
#: The cases, in the order they are run and reported (module docstring).
CASES = (
    "layers",
    "layers-slow-25dB",
    "layers-slow-random-20dB",
    "layers-10dB",
    "layers-crossing",
    "layers-static",
    "layers-volume",
    "layers-crossing-volume",
    "layers-static-coarse-y-volume",
    "layers-half-static",
    "layers-sheared-static",
    "layers-mixed-volume",
    "layers-sparse-volume",
    "layers-jittered-flow",
    "layers-maxwell-volume",
    "layers-creeping-half-static-volume",
    "vessel-volume",
    "vessel-static-volume",
    "thin-vessels",
    "thin-vessels-volume",
    "aline",
    "motion-types",
)
#: The system of the built cases: wavelength (µm), lateral (1/e² width) and axial (FWHM) resolution (µm).
SYSTEM = {"name": "840nm", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}
PROTOCOL = {"n_frames": 32, "frame_interval_s": 0.2048}
#: Pixel pitch (µm) and image size (pixels per axis) of the built cases.
PITCH_UM = 2.0
N_PX = 96
#: Planes along y of the volume cases: a field of view (24 µm) that holds the models' coarsest lateral
#: resolution (maps refuse a reduction wider than the field of view).
VOLUME_NY = 12
#: The y pitch (µm) of ``layers-static-coarse-y-volume``: the coarsest the models' coarsest configuration
#: (lateral 18 µm) allows (two pixels per 1/e² width); at the system's 4.9 µm the speckle of neighbouring planes
#: is uncorrelated.
COARSE_PITCH_Y_UM = 9.0
#: Moving (and static) density of the built cases, µm⁻³.
DENSITY = 0.05
#: The layers' motions: D (µm²/s), random-ballistic speed (µm/s), and per case the flow's speed (µm/s),
#: polar and azimuth angle (degrees).
DIFFUSION_UM2_S = 0.03
BALLISTIC_UM_S = 0.12
#: The slow random motions of ``layers-slow-random-20dB``: D (µm²/s) and speed (µm/s).
SLOW_RANDOM = (0.001, 0.03)
#: The mixed random motions of ``layers-mixed-volume``: the diffusion layer holds one population per D
#: (µm²/s) and the random-ballistic layer one per speed (µm/s), each at an equal share of :data:`DENSITY`.
MIXED_RANDOM = ((1e-5, 1e-4, 1e-3, 1e-2), (0.002, 0.02, 0.2))
#: The populations of ``layers-maxwell-volume``'s random-ballistic layer: one per speed at the quantiles
#: ``(k + 1/2)/K`` of a Maxwell distribution (isotropic Gaussian velocity: the speed over its per-axis standard
#: deviation is chi-distributed with three degrees of freedom) whose mean is :data:`BALLISTIC_UM_S`.
MAXWELL_POPULATIONS = 8
#: The diffusion (µm²/s) of ``layers-jittered-flow``'s flow scatterers, added to their flow: over the
#: acquisition it decorrelates the intensity about as much as the flow's transit does, and at the first lags
#: more (diffusion's decay is linear in the lag, transit's quadratic).
JITTER_UM2_S = 1e-4
#: The motions a case's ``mixed`` region combines (scored by :func:`classifier.bench.grid.score_mixed`).
MIXED_HOLDS = {"layers-jittered-flow": ("flow", "diffusion")}
#: The flows: speed (µm/s; for ``sheared`` the peak of the profile), polar angle from the beam and azimuth from
#: the B-scan's x axis (degrees); ``jittered`` is ``oblique`` whose scatterers also diffuse (:data:`JITTER_UM2_S`).
FLOW = {
    "oblique": (0.3, 45.0, 60.0),
    "jittered": (0.3, 45.0, 60.0),
    "slow": (0.1, 45.0, 60.0),
    "crossing": (0.3, 80.0, 85.0),
    "along-y": (1.0, 90.0, 90.0),
    "sheared": (2.0, 90.0, 30.0),
    "creeping": (0.1, 30.0, 30.0),
}
#: Sub-slabs of the ``sheared`` flow: a plane Poiseuille profile across the flow layer, each sub-slab moving at
#: ``v = v_max(1 − (2(z − z_c)/h)²)`` at its centre (``h`` the layer's thickness), the flow parallel to the
#: layer (polar 90°) so that no scatterer leaves its sub-slab.
SHEAR_SLABS = 32
#: The vessel of the ``vessel-*`` cases: peak (centre-line) speed (µm/s), radius (µm), polar and azimuth angle of
#: its axis and flow (degrees), and the centre (µm, x, y, z) its axis passes through; beside it two spheres of
#: radius :data:`SPHERE_RADIUS_UM` centred at :data:`SPHERE_CENTRES_UM` (diffusion, random-ballistic motion).
VESSEL = {
    "speed_um_per_s": 0.6,
    "radius_um": 20.0,
    "polar_deg": 60.0,
    "azimuth_deg": 30.0,
    "center_um": (0.0, 0.0, -35.0),
}
SPHERE_RADIUS_UM = 28.0
SPHERE_CENTRES_UM = ((-50.0, 0.0, 50.0), (50.0, 0.0, 50.0))
#: The vessels of the ``thin-vessels*`` cases: radii (µm), one vessel each, their axes along y (across the
#: B-scan plane, perpendicular to the beam) through (x, z) = :data:`THIN_VESSEL_X_UM`, 0; plug flow along the
#: axis (µm/s); in diffusing tissue of :data:`THIN_VESSEL_TISSUE_D_UM2_S` (µm²/s) over static tissue under every
#: pixel, 20 dB.
THIN_VESSEL_RADII_UM = (4.0, 8.0, 12.0)
THIN_VESSEL_X_UM = (-48.0, 0.0, 48.0)
THIN_VESSEL_SPEED_UM_S = 1.0
THIN_VESSEL_TISSUE_D_UM2_S = 0.001
#: The cases scored region by region as well (``per_region`` of their rows: each region of one motion).
REGION_CASES = ("thin-vessels", "thin-vessels-volume")
#: Depth pixels of the ``aline`` case: one A-line through the three layers, each :data:`N_PX` × 16 pixels
#: deep, so that every layer holds as many pixels as sixteen A-lines of the B-scan cases' layers.
ALINE_NZ = 16 * N_PX
#: The density (µm⁻³) of ``layers-sparse-volume``: a few scatterers per resolution volume.
SPARSE_DENSITY = 0.002


class Layers(NamedTuple):
    """A built case (module docstring): three layers in depth, diffusion, random-ballistic motion and flow."""

    flow: str  #: a key of :data:`FLOW`
    #: ``plain`` (D = 0.03 µm²/s, 0.12 µm/s), ``slow`` (:data:`SLOW_RANDOM`), ``mixed`` (:data:`MIXED_RANDOM`),
    #: ``maxwell`` (``plain`` with Maxwell-distributed random-ballistic speeds, :data:`MAXWELL_POPULATIONS`)
    random: str = "plain"
    #: static tissue under ``all`` pixels (a second phantom, :func:`case_phantoms`), or under the ``half`` of the
    #: A-lines at x < 0 (a static region)
    static: str | None = None
    snr_db: float | None = None  #: noise, dB below the mean intensity (``None``: none)
    #: ``bscan``; ``volume`` (planes at the pitch of x); ``coarse-y-volume``; ``aline`` (one pixel along x,
    #: :data:`ALINE_NZ` deep)
    geometry: str = "bscan"
    density: float = DENSITY  #: moving and static density, µm⁻³


#: The built cases (:class:`Layers`; ``coarse-y-volume``: :data:`VOLUME_NY` planes :data:`COARSE_PITCH_Y_UM`
#: apart).
LAYERS = {
    "layers": Layers("oblique"),
    "layers-slow-25dB": Layers("slow", snr_db=25.0),
    "layers-slow-random-20dB": Layers("oblique", "slow", snr_db=20.0),
    "layers-10dB": Layers("oblique", snr_db=10.0),
    "layers-crossing": Layers("crossing"),
    "layers-static": Layers("oblique", static="all"),
    "layers-volume": Layers("oblique", geometry="volume"),
    "layers-crossing-volume": Layers("crossing", geometry="volume"),
    "layers-static-coarse-y-volume": Layers("along-y", static="all", snr_db=20.0, geometry="coarse-y-volume"),
    "layers-half-static": Layers("oblique", "slow", static="half", snr_db=20.0),
    "layers-sheared-static": Layers("sheared", static="all", snr_db=20.0),
    "layers-mixed-volume": Layers("oblique", "mixed", snr_db=20.0, geometry="volume"),
    "layers-sparse-volume": Layers("oblique", "slow", geometry="volume", density=SPARSE_DENSITY),
    "layers-jittered-flow": Layers("jittered"),
    "layers-maxwell-volume": Layers("oblique", "maxwell", snr_db=20.0, geometry="volume"),
    "layers-creeping-half-static-volume": Layers("creeping", "slow", static="half", snr_db=20.0, geometry="volume"),
    "aline": Layers("oblique", "slow", snr_db=20.0, geometry="aline"),
}
POOLS = (1, 5)
SEED = 0


def case_dict(name: str) -> dict[str, Any]:
    """The phantom of case ``name`` (:data:`CASES`) in the phantom-file schema (module docstring)."""
    if name not in CASES:
        raise ValueError(f"unknown case {name!r}; give one of {', '.join(CASES)}")
    if name == "motion-types":
        from torchdoct.image.phantom import shipped_phantoms
        from torchdoct.sim.config import read_toml

        return read_toml(shipped_phantoms()[name])
    from .grid import layer_regions

    if name in ("vessel-volume", "vessel-static-volume"):
        return _vessel_dict(name, static=name == "vessel-static-volume")
    if name in ("thin-vessels", "thin-vessels-volume"):
        return _thin_vessels_dict(name, volume=name == "thin-vessels-volume")
    case = LAYERS[name]
    speed, polar, azimuth = FLOW[case.flow]
    kind = "volume" if case.geometry.endswith("volume") else "bscan"
    grid: dict[str, Any] = {"kind": kind, "n_x": N_PX, "n_z": N_PX, "pitch_x_um": PITCH_UM, "pitch_z_um": PITCH_UM}
    if case.geometry == "aline":
        grid.update(n_x=1, n_z=ALINE_NZ)
    if kind == "volume":
        grid.update(n_y=VOLUME_NY, pitch_y_um=COARSE_PITCH_Y_UM if case.geometry == "coarse-y-volume" else PITCH_UM)
    else:
        grid["y_um"] = 0.0
    fov = N_PX * PITCH_UM  # along x and z; the grid is centred on the origin: z runs over [-fov/2, fov/2]
    depth = grid["n_z"] * PITCH_UM
    diffusion, ballistic = {
        "plain": ((DIFFUSION_UM2_S,), (BALLISTIC_UM_S,)),
        "slow": ((SLOW_RANDOM[0],), (SLOW_RANDOM[1],)),
        "mixed": MIXED_RANDOM,
        "maxwell": ((DIFFUSION_UM2_S,), maxwell_speeds(BALLISTIC_UM_S)),
    }[case.random]
    flow = {"kind": "flow", "speed_um_per_s": speed, "polar_angle_deg": polar, "azimuth_deg": azimuth}
    layers = layer_regions(
        depth,
        case.density,
        (
            {"kind": "diffusion", "diffusion_um2_per_s": diffusion[0]},
            {"kind": "ballistic", "speed_um_per_s": ballistic[0]},
            flow,
        ),
    )
    regions = (
        _populations(layers[0], "diffusion_um2_per_s", diffusion)
        + _populations(layers[1], "speed_um_per_s", ballistic)
        + (_sheared(layers[2]) if case.flow == "sheared" else [layers[2]])
    )
    if case.flow == "jittered":  # the flow's scatterers diffuse too: the renderer labels the layer "mixed"
        regions[-1]["motion"] = [flow, {"kind": "diffusion", "diffusion_um2_per_s": JITTER_UM2_S}]
    d = _case_phantom(name, grid, regions, static_density=None)  # static="all": a second phantom (case_phantoms)
    if case.static == "half":  # a cylinder along z over the A-lines at x < 0
        d["region"].append(
            {
                "name": "static-tissue",
                "shape": "cylinder",
                "center_um": [-fov / 2, 0.0, 0.0],
                "axis": [0.0, 0.0, 1.0],
                "radius_um": fov / 2,
                "density_per_um3": case.density,
                "motion": [],
            }
        )
    if case.snr_db is not None:
        d["noise"] = {"snr_db": case.snr_db}
    return d


def _case_phantom(
    name: str, grid: dict[str, Any], regions: list[dict[str, Any]], *, static_density: float | None
) -> dict[str, Any]:
    """A case's phantom file: the cases' system, protocol and seed, with static tissue of ``static_density``
    (µm⁻³) around its regions (the phantom's background, wherever no region is) unless ``None``. Static tissue
    under every pixel is a second phantom (:func:`case_phantoms`)."""
    d: dict[str, Any] = {
        "name": f"case-{name}",
        "system": [dict(SYSTEM)],
        "protocol": dict(PROTOCOL),
        "grid": grid,
        "region": regions,
        "simulation": {"seed": SEED},
    }
    if static_density is not None:
        d["background"] = [{"name": "static-tissue", "density_per_um3": static_density}]
    return d


def _vessel_dict(name: str, *, static: bool) -> dict[str, Any]:
    """The ``vessel-*`` cases (module docstring): :data:`VESSEL` with a Poiseuille profile and the two spheres of
    ``layers-slow-random-20dB``'s motions, a volume of :data:`VOLUME_NY` planes, 20 dB of noise."""
    from torchdoct.sim.config import Flow

    flow = {
        "kind": "flow",
        "speed_um_per_s": VESSEL["speed_um_per_s"],
        "polar_angle_deg": VESSEL["polar_deg"],
        "azimuth_deg": VESSEL["azimuth_deg"],
    }
    axis = Flow(speed_um_per_s=1.0, polar_angle_deg=VESSEL["polar_deg"], azimuth_deg=VESSEL["azimuth_deg"])
    random = (
        {"kind": "diffusion", "diffusion_um2_per_s": SLOW_RANDOM[0]},
        {"kind": "ballistic", "speed_um_per_s": SLOW_RANDOM[1]},
    )
    regions: list[dict[str, Any]] = [
        {
            "name": "vessel",
            "shape": "cylinder",
            "center_um": list(VESSEL["center_um"]),
            "axis": list(axis.velocity_um_per_s),
            "radius_um": VESSEL["radius_um"],
            "flow_profile": "poiseuille",
            "density_per_um3": DENSITY,
            "motion": [flow],
        }
    ] + [
        {
            "name": motion["kind"],
            "shape": "sphere",
            "center_um": list(centre),
            "radius_um": SPHERE_RADIUS_UM,
            "density_per_um3": DENSITY,
            "motion": [motion],
        }
        for centre, motion in zip(SPHERE_CENTRES_UM, random)
    ]
    grid = {"kind": "volume", "n_x": N_PX, "n_z": N_PX, "n_y": VOLUME_NY}
    grid.update(pitch_x_um=PITCH_UM, pitch_z_um=PITCH_UM, pitch_y_um=PITCH_UM)
    d = _case_phantom(name, grid, regions, static_density=DENSITY if static else None)
    d["noise"] = {"snr_db": 20.0}
    return d


def _thin_vessels_dict(name: str, *, volume: bool) -> dict[str, Any]:
    """The ``thin-vessels*`` cases (module docstring): diffusing tissue (over static tissue: :func:`case_phantoms`)
    holding one vessel per radius of :data:`THIN_VESSEL_RADII_UM`, their axes and plug flows along y; 20 dB of
    noise."""
    fov = N_PX * PITCH_UM
    flow = {"kind": "flow", "speed_um_per_s": THIN_VESSEL_SPEED_UM_S, "polar_angle_deg": 90.0, "azimuth_deg": 90.0}
    regions: list[dict[str, Any]] = [
        {
            "name": "diffusion",
            "shape": "slab",
            "z_min_um": -fov / 2,
            "z_max_um": fov / 2,
            "density_per_um3": DENSITY,
            "motion": [{"kind": "diffusion", "diffusion_um2_per_s": THIN_VESSEL_TISSUE_D_UM2_S}],
        }
    ] + [
        {
            "name": f"vessel-{radius:g}um",
            "shape": "cylinder",
            "center_um": [x, 0.0, 0.0],
            "axis": [0.0, 1.0, 0.0],
            "radius_um": radius,
            "density_per_um3": DENSITY,
            "motion": [dict(flow)],
        }
        for x, radius in zip(THIN_VESSEL_X_UM, THIN_VESSEL_RADII_UM)
    ]
    grid: dict[str, Any] = {"kind": "volume" if volume else "bscan", "n_x": N_PX, "n_z": N_PX}
    grid.update(pitch_x_um=PITCH_UM, pitch_z_um=PITCH_UM)
    grid.update({"n_y": VOLUME_NY, "pitch_y_um": PITCH_UM} if volume else {"y_um": 0.0})
    d = _case_phantom(name, grid, regions, static_density=None)  # the static tissue: a second phantom (case_phantoms)
    d["noise"] = {"snr_db": 20.0}
    return d


def maxwell_speeds(mean_um_s: float, k: int = MAXWELL_POPULATIONS) -> tuple[float, ...]:
    """Speeds (µm/s) at the quantiles ``(j + 1/2)/k`` of a Maxwell distribution of mean ``mean_um_s``: the speed
    of an isotropic Gaussian velocity of per-axis standard deviation ``σ`` is ``σ·χ₃`` (mean ``2σ√(2/π)``)."""
    from scipy.stats import chi

    sigma = float(mean_um_s) / float(chi(3).mean())
    return tuple(float(sigma * chi(3).ppf((j + 0.5) / k)) for j in range(k))


def _populations(layer: dict[str, Any], key: str, values: Sequence[float]) -> list[dict[str, Any]]:
    """``layer`` (a region of :func:`classifier.bench.grid.layer_regions`) as one region per value of its motion's
    ``key``, each at an equal share of its density (one region, unchanged, for one value)."""
    if len(values) == 1:
        return [layer]
    return [
        {
            **layer,
            "name": f"{layer['name']}-{k}",
            "density_per_um3": layer["density_per_um3"] / len(values),
            "motion": [{**layer["motion"][0], key: v}],
        }
        for k, v in enumerate(values)
    ]


def _sheared(layer: dict[str, Any]) -> list[dict[str, Any]]:
    """The flow ``layer`` as :data:`SHEAR_SLABS` sub-slabs of a plane Poiseuille profile (the peak speed its
    motion's)."""
    z0, z1 = float(layer["z_min_um"]), float(layer["z_max_um"])
    h, peak = z1 - z0, float(layer["motion"][0]["speed_um_per_s"])
    out = []
    for k in range(SHEAR_SLABS):
        a, b = z0 + k * h / SHEAR_SLABS, z0 + (k + 1) * h / SHEAR_SLABS
        speed = peak * (1.0 - (2.0 * ((a + b) / 2 - (z0 + z1) / 2) / h) ** 2)
        out.append(
            {
                **layer,
                "name": f"{layer['name']}-{k}",
                "z_min_um": a,
                "z_max_um": b,
                "motion": [{**layer["motion"][0], "speed_um_per_s": speed}],
            }
        )
    return out


def static_under(name: str) -> bool:
    """Whether case ``name`` holds static tissue under every pixel (module docstring)."""
    return name in ("thin-vessels", "thin-vessels-volume") or (name in LAYERS and LAYERS[name].static == "all")


def case_phantoms(name: str) -> list[dict[str, Any]]:
    """The phantoms whose fields add up to case ``name``: :func:`case_dict`, and for a case with static tissue
    under every pixel (:func:`static_under`) a second phantom of static tissue at :data:`DENSITY` on the same
    grid (as the phantom grid's ``background`` context, :mod:`classifier.bench.grid`)."""
    d = case_dict(name)
    if not static_under(name):
        return [d]
    from .grid import _static_dict

    return [d, _static_dict(d, DENSITY)]


def run_case(name: str, *, threads: int | None = None, pools: Sequence[int] = POOLS) -> list[dict[str, Any]]:
    """Render, map, classify and score case ``name`` at every window of ``pools``, with the rules and with the
    model alone: one row per window and decision."""
    from ..infer import load_model
    from .grid import _classify_rendered

    d = case_dict(name)
    if d["grid"]["n_x"] == 1:  # one A-line: no lateral reduction, the A-line model, no window wider than it
        model = load_model("signature-aline", threads=threads)
        pools = tuple(p for p in pools if int(p) == 1)
    else:
        model = load_model("signature" if d["grid"]["kind"] == "volume" else "signature-bscan", threads=threads)
    scored = _classify_rendered(
        case_phantoms(name),
        model,
        f"case-{name}",
        SEED,
        pools=pools,
        decision=None,
        threads=threads,
        abstain_ambiguous=(True, False),
        mixed_holds=MIXED_HOLDS.get(name),
        per_region=name in REGION_CASES,
    )
    return [
        {
            "case": name,
            "geometry": d["grid"]["kind"],
            "model": model.spec.name,
            "pool": r["pool"],
            "rules": r["abstain_ambiguous"],
            **{k: r[k] for k in ("per_class", "pixels", "coverage", "balanced_accuracy", "wrong_share_max")},
            "all_pixels": r["all_pixels"],
            "rules_changed": r["rules_changed"],
            **({"mixed": r["mixed"]} if "mixed" in r else {}),
            **({"per_region": r["per_region"]} if "per_region" in r else {}),
            "seconds": r["seconds"]["total"],
        }
        for r in scored
    ]


def run_cases(names: Sequence[str] = CASES, *, threads: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Every case of ``names`` (:func:`run_case`) and the results file's header."""
    from tqdm.auto import tqdm

    from torchdoct.runtime.machine import machine_info

    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    for name in tqdm(names, desc="cases", unit="case", disable=not progress):
        rows += run_case(name, threads=threads)

    return {
        "schema_version": SCHEMA_VERSION,
        "benchmark": "classifier.bench.cases",
        "system": SYSTEM,
        "protocol": PROTOCOL,
        "pitch_um": PITCH_UM,
        "density_per_um3": DENSITY,
        "phantoms": {n: case_phantoms(n) if static_under(n) else case_dict(n) for n in names},
        "rows": rows,
        "seconds": time.perf_counter() - t0,
        "machine": machine_info(),
    }


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def format_table(res: dict[str, Any]) -> str:
    """The cases as a Markdown table: per case, window and decision, over every pixel of each motion; and the
    cases of :data:`REGION_CASES` region by region."""
    lines = [
        "| case | window | decision | coverage | balanced accuracy | diffusion: coverage / wrong | "
        "ballistic: coverage / wrong | flow: coverage / wrong | mixture: coverage / wrong | worst wrong share |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        a = r["all_pixels"]
        pc = a["per_class"]
        per = [
            f"{_fmt(pc[m]['coverage'])} / {_fmt(pc[m]['wrong_share'])}" if pc[m]["pixels"] else "–"
            for m in ("diffusion", "ballistic", "flow")
        ]
        mx = r.get("mixed")
        per.append(f"{_fmt(mx['coverage'])} / {_fmt(mx['wrong_share'])}" if mx and mx["pixels"] else "–")
        decision = "rules (default)" if r["rules"] else "model alone"
        cells = [r["case"], str(r["pool"]), decision, _fmt(a["coverage"]), _fmt(a["balanced_accuracy"]), *per]
        lines.append("| " + " | ".join(cells + [_fmt(a["wrong_share_max"])]) + " |")
    regions = [(r, g) for r in res["rows"] for g in r.get("per_region", [])]
    if regions:
        lines += [
            "",
            "| case | region | motion | pixels | window | decision | coverage | wrong share |",
            "|---" * 8 + "|",
        ]
        for r, g in regions:
            decision = "rules (default)" if r["rules"] else "model alone"
            cells = [r["case"], g["region"], g["motion"], str(g["pixels"]), str(r["pool"]), decision]
            lines.append("| " + " | ".join(cells + [_fmt(g["coverage"]), _fmt(g["wrong_share"])]) + " |")
    lines += ["", f"Written by `{res.get('command', 'python -m classifier.bench.cases --out DIR')}`."]
    return "\n".join(lines) + "\n"


def write_cases(res: dict[str, Any], out_dir: str | Path, *, force: bool = False) -> list[Path]:
    """Write ``cases.json`` and ``cases.md`` into ``out_dir`` together (both or none)."""
    from torchdoct.files import output_set

    from .grid import _json_default

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "cases.json", out / "cases.md"]
    with output_set(paths, force, "--out") as stage:
        stage(paths[0]).write_text(json.dumps(res, separators=(",", ":"), default=_json_default), encoding="utf-8")
        stage(paths[1]).write_text(format_table(res), encoding="utf-8")
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    import argparse
    import sys

    from .grid import check_output_dir

    p = argparse.ArgumentParser(
        prog="python -m classifier.bench.cases",
        description="Fixed phantoms on which a per-pixel model decides flow as random-ballistic motion, "
        "classified with and without the rules; writes cases.json and cases.md into --out.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--case", action="append", choices=CASES, help="only this case (repeatable; default: all)")
    p.add_argument("--threads", type=int, default=None, metavar="N")
    p.add_argument("--force", action="store_true", help="overwrite existing results")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    try:
        out = check_output_dir(args.out, "cases", (".json", ".md"), args.force)
        names = tuple(args.case) if args.case else CASES
        res = run_cases(names, threads=args.threads, progress=not args.no_progress)
        res["command"] = "python -m classifier.bench.cases" + "".join(f" --case {n}" for n in args.case or ())
        res["command"] += " --out DIR"
        for path in write_cases(res, out, force=args.force):
            print(f"wrote {path}")
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
