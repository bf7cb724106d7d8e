"""Where the physics cannot tell random-ballistic motion from flow: a ``ballistic`` decision becomes the
set ``ballistic-or-flow``, unless the speckle pattern moved coherently, which only flow does: then every
decision but ``indeterminate`` is ``flow`` (numpy only: the classify path). The rules are applied in the order
0, 5, 10, 1, 11, 2, 3, 4, 7, 9, then 6 and 8 together, then 12. The derivation is in docs/abstention.md
("What the data cannot tell") and docs/concepts/speckle-motion.md §3, §7.

Kept whole (over 800 lines): this docstring is the rules' specification in the order they run, and every rule
shares the channel readers (``_read`` and the channel patterns) and the box sums (``_box_count``,
``_box_total``, ``_window_share``); split, one ordered decision would be specified across files.

A network that reads one pixel's intensity (pooled or not) decides ``ballistic`` wherever the decay looks
like random-ballistic motion. Two kinds of flow give that same evidence, and the network's calibration
(split-conformal, marginal over the training prior's directions and speeds) does not cover them pixel by
pixel:

1. **Flow along an axis the maps cannot see** (``bscan_plane`` in the counts). In a B-scan (maps of axes
   ``ZX``) the speckle of a flow along ``y`` stays centred and only decays (speckle-motion §7): the same
   centred, decaying correlation as random ballistic motion, diffusion aside. Neither the pixel's frames nor
   its in-plane neighbours can exclude it. A volume sees such a flow only through neighbours that share its
   speckle: along an axis whose pitch ``p_c`` leaves the speckle correlation of neighbouring pixels
   ``exp(−p_c²/(2s_c²))`` (speckle-motion §3 (a) at ``τ = 0``, at the speckle channels' resolution) below
   :data:`NEIGHBOUR_CORRELATION_MIN`, a move of the pattern by less than a pitch changes no neighbour's
   correlation, and along an axis of a single pixel (one A-line's time series) there is no neighbour: rules
   0, 4 and 5 cannot see it; a volume with such an axis (an undersampled slow axis
   ``y`` is the common one), or without the speckle channels, is a stack of B-scans for this rule
   (:func:`unseen_axes`). So in B-scan maps, and in maps with an unseen axis, every ``ballistic`` decision
   is ``ballistic-or-flow``. Flow decisions stay: a coherent in-plane shift or a transit decay the network
   reads as flow is not what random directions give. On maps with fewer than two axes of more than one
   pixel (:func:`line_windows`: one A-line's time series) the speckle window is a line of a few axial grains
   and the Doppler box a few pixels, unlike the windows and boxes over which rules 0, 5 and 10 had their
   false detections recorded: those rules are not applied there, and a flow decision stands on the
   network's reading of the decay and on rules 6-9.
11. **A sheared flow without a phase reference** (``sheared_flow`` in the counts; right after rule 1). A
   laminar flow's speed changes across it (a Poiseuille profile falls to zero at a vessel's wall): inside one
   PSF its scatterers move with a spread of axial speeds ``n_z·G·u`` (``G`` the speed's change per µm along
   ``ĝ``, ``u`` a scatterer's offset along ``ĝ``), and ``|g1(τ)|² = exp(−(2kn·n_z·G·s_g·τ)²/2)``, the Doppler
   decay of random-ballistic motion with a Maxwell velocity of per-axis spread ``n_z·G·s_g/√2``
   (speckle-motion §3 (e)). The pattern moves only with the local mean speed, zero at the wall: where the
   shear decorrelates the window first, no intensity statistic separates the two, in a volume as in a B-scan.
   The mean axial speed shows in the Doppler phase against a static reference (``−2kn·n_z·v̄·τ``); a flow
   across the beam (``n_z = 0``) has no spread to decorrelate with. So a ``ballistic`` decision is
   ``ballistic-or-flow`` at every pixel without a finite ``doppler_phase_m@…`` (:func:`phase_reference`; no
   Doppler channel: every pixel).
2. **Flow too slow to decorrelate by transit** (any geometry). A flow decorrelates the intensity only by
   transit through the PSF, ``ρ(τ) = exp(−Σ_c v_c²τ²/(2s_c²))``; random-ballistic motion mostly by the
   Doppler phase of random directions, about ``2kn·s`` (≈ 30 at 840 nm) times faster at one speed. The two
   decay shapes (Gaussian against the phase average) differ only once the pixel has decorrelated. While the
   window's correlation at the longest lag of the speckle features (``xc_centre_m``, half the acquisition
   by default) stays at or above :data:`DECORRELATED_BELOW`, the shapes have not separated and a
   ``ballistic`` decision is ``ballistic-or-flow``. Without the speckle channels the pooled intensity
   correlation the model reads at the nearest lag (``rho_lin_m`` of the first configuration) stands in.

0. **Coherent motion seen** (any geometry; applied first). A flow carries the speckle pattern along: the
   window's lag-``m`` cross-correlation keeps its value but moves off the centre offset (speckle-motion
   §3), while random-ballistic motion and diffusion, symmetric in direction, keep the peak at the centre
   and only let it decay. Where, at a lag ``m ≤ n_frames / 4`` (at least a quarter of the acquisition's
   frame pairs, and short enough that a few low-density scatterers moving alone do not fake a
   translation), the peak ``xc_peak_m`` is at least :data:`COHERENT_PEAK_MIN` and at least
   :data:`COHERENT_MOVED_MIN` of it has moved off the centre, ``(xc_peak_m − xc_centre_m) / xc_peak_m``,
   a decision for a direction-symmetric motion (``ballistic``, ``diffusion``) or a set of them and flow
   (:data:`COHERENT_TO_FLOW`) is ``flow``. A flow too slow to move the pattern
   by about a pixel within those lags is not seen this way and rule 2 applies to it; the grid benchmark
   (``python -m classifier.bench.grid``) reports what each rule leaves, the ballistic and diffusion wrong
   shares being the false-detection check.

   **Inside static tissue** the static population's pattern neither moves nor decays, and it holds the
   window's peak at the centre (speckle-motion §3 (d)): a flow sharing the PSF with static tissue moves only a
   small share of the peak. Maps written with ``--speckle-dynamic`` also hold the channels of the dynamic field
   (``xcd_…``: the complex field less its temporal mean, which is the static population's field), in which the
   flow's offset shows alone (speckle-motion §3 (f)). Rules 0 and 5 read both families
   (:data:`SPECKLE_FAMILIES`) with the same bounds, and a pixel counts where either shows the motion. Removing
   a per-pixel mean is the same at ``r`` and ``r + Δ``, so a direction-symmetric motion keeps its centred
   expectation in the dynamic field too: the premise of both rules holds there unchanged.
5. **A held pattern that moved** (any geometry; applied right after rule 0). A flow too slow for rule 0
   still carries its pattern along: over the whole span of the speckle features' lags the window's peak keeps
   its height while its offset moves by ``v⊥(τ_L − τ₁)``, linearly in the lag (speckle-motion §3 (a), §5). A
   direction-symmetric motion can move the peak of a window's pattern only by changing the pattern: while the
   pattern holds (``xc_peak_m ≥`` :data:`TRANSLATION_HOLD_MIN` at every lag from the shortest on, through
   at least three lags: a fast flow's pattern leaves the offset grid at the longer lags) its offset stays
   where the window's own grains put it, whatever the lag. Where the signed offset vector
   (``xc_shift_{c}_m@…`` per axis, in pitches of that axis) moved between the shortest and the last held lag
   by at least :data:`TRANSLATION_GROWTH_MIN` pitches, along a straight line in the lag (the residual of a
   per-axis line through the lags at most :data:`TRANSLATION_LINEAR_MAX` pitches, root mean square per degree
   of freedom), a ``ballistic`` decision or a ``ballistic-or-flow`` set is ``flow``
   (:data:`TRANSLATED_TO_FLOW`), provided that on the maps at least :data:`TRANSLATION_SUPPORT_MIN` of the
   valid windows centred within the pixel's speckle window moved so too. At the lowest densities two or
   three scatterers can dominate a window, and their beat moves its pattern steadily while the scatterers
   barely move (a relative axial step ``δ`` turns their relative phase by ``2kn·δ`` and slides the intensity
   maximum between them by a share of their separation): such a window is alone, or nearly, among its
   neighbours, while a flow translates every window that lies in it. It is applied at speckle windows of
   :data:`TRANSLATION_WINDOW_MIN` pixels or more (the window its rates were recorded at). A ``diffusion``
   decision stays: a slowly diffusing pattern under noise
   moves its offset more often than a random-ballistic one (docs/abstention.md gives the measured
   false-detection rates of the null motions and how they are recorded).
10. **A Doppler phase that drifts against static tissue** (complex data whose maps hold ``doppler_phase_m@…``;
   right after rule 5). Where static tissue gives a phase reference in the A-line or B-scan
   (:mod:`torchdoct.measured.doppler`), a pixel's lag-``m`` product has the expectation ``I_s + I_m·g1(τ)``,
   ``g1 = ⟨exp(−i·2kn·d_z)⟩`` over the scatterers' axial displacements. Direction-symmetric motions displace
   up and down alike: ``g1`` is real and the phase symmetric about 0 (or π), the imaginary part of ``exp(iφ)``
   zero in expectation. A flow gives every scatterer ``d_z = v_z·τ``: the phase keeps the sign of
   ``−2kn·v_z·τ`` (wrapped) over its pixels, a static share only dilutes it. Where the imaginary part of the
   mean of ``exp(iφ)`` at the shortest Doppler lag over the pixel's box (``max(pool,``
   :data:`DOPPLER_WINDOW_MIN` ``)`` pixels per axis; :func:`doppler_imaginary`) is at least
   :data:`DOPPLER_IM_MIN` in magnitude, the outcomes of :data:`DOPPLER_TO_FLOW` become ``flow``
   (:func:`doppler_drift`). Flow across the beam, a phase wrapped near 0 or ±π at that lag, and samples
   without a reference (no channel) are left to the other rules; a flow decision it founds is the pixel's own
   evidence, which rules 7 and 9 leave. The grid benchmark records its statistic on each motion.
3. **Decorrelated before the first lag** (any geometry; after rules 1 and 2). Where the moving part of a
   pixel decorrelates within the shortest lag of the speckle features, no lag sees its pattern: a flow that
   leaves the PSF (or the offset grid) within ``m₁·Δt`` keeps no moving peak for rule 0, and with static
   tissue in the PSF only the centred, static part of the correlation stays (speckle-motion §3 (d):
   ``C(0, τ) = |f_s + f_m g1_m(0, τ)|² + …`` falls to the constant ``f_s²(1 + 1/N_s)`` once ``g1_m`` is gone). Random
   ballistic motion fast enough to decorrelate within ``m₁·Δt`` gives the same flat correlation, and one
   pixel's frames at the shorter lags cannot tell the two apart (speckle-motion §6). Where
   the decay left after the shortest lag, ``ρ(m₁) − ρ(m_last)``, is below :data:`FAST_REMAINING_MAX` of the
   whole decay ``1 − ρ(m_last)`` (``xc_centre_m`` at the shortest and longest lags), a ``ballistic`` decision
   is ``ballistic-or-flow``. The grid's static-background cells with fast flow are these pixels.
4. **The offset moved** (any geometry; last). With static tissue sharing the PSF (speckle-motion §3 (d)) a
   flow's heterodyne term beats at its Doppler frequency, so the centred correlation falls by the phase (as
   random motion's does) while the pattern has moved less than a pixel, and rules 0 and 2 see neither a
   moved peak nor a slow decay. The peak *offset* still tells: a direction-symmetric motion keeps the
   peak at the centre until transit (speckle-motion §3 (b), (c)), while a flow's offset is ``v⊥τ`` (the
   heterodyne peak's ``v⊥τ/2``) and grows with the lag. Over the lags ``m ≤ n_frames / 4``:

   * where the offset ``xc_shift_m`` at the shortest lag is at least :data:`OFFSET_FIRST_MIN` of the pixel
     pitch (off the centre: a fast flow's heterodyne peak), a ``ballistic`` or ``diffusion`` decision becomes
     its set with flow (``ballistic-or-flow``, ``diffusion-or-flow``);
   * where the pattern held at the shortest lag (``xc_peak_m₁ ≥`` :data:`OFFSET_HOLD_MIN`) and the offset
     grew at every lag and by at least :data:`OFFSET_GROWTH_MIN` of the pitch in all (a slow flow beating
     against static tissue), a ``ballistic`` decision becomes ``ballistic-or-flow``. While a pattern holds,
     the offset estimate's error is the window's own grain structure, common to every lag; but it grows as
     the pattern decays in place, and a diffusing pattern with noise decays enough to grow it. A beat
     decays as ``cos(2kn·v_z τ)``, quadratic at short lags as random-ballistic motion's phase decay is,
     not as diffusion's exponential (physics.md §5.3), so the network reads such a flow as ballistic and
     diffusion decisions are left to the first clause.

   It only abstains: a random motion that reached transit within the shortest lag, or whose decaying
   pattern let the offset wander, loses coverage, never a right decision.
7. **A flow decision only the coarse configurations hold** (maps of any geometry; after rules 0–5, before
   rule 6). Where a pixel's own data shows no flow (neither rule 0, 5 nor 10 fired), nothing in its own
   frames shows a translation or a Doppler drift: a ``flow`` decision there rests on how the decay changes
   across the configurations the model reads, and the coarsest of them reads the whole footprint (rule 6's box,
   :func:`consensus_window`). Inside a region of one motion that is the region's own evidence. Where the
   footprint reaches into another region, the wide PSF mixes the neighbour's flow in: a random motion whose
   own decay is fast at every resolution then decays slower at the coarse one, the signature of flow (not
   decorrelated, rule 2's case; or decorrelated, as random-ballistic motion beside a vessel is), and the
   network decides flow over a strip as wide as the reach. So such a decision stands only where at least
   :data:`FOOTPRINT_FLOW_MIN` of the classified pixels of its box are ``flow`` after rules 0–5 (the
   footprint is one flow region). The box reaches :data:`FOOTPRINT_REACH` times as far as the footprint: a
   random motion that decays by a few percent by itself reads as flow even where only the far tail of the
   coarse PSF (``exp(−2d²/r²)``, 14 % at the footprint's edge ``d = r``) holds a decorrelating flow.
   Elsewhere it becomes ``indeterminate`` (the exclusion of diffusion rests on the same mixed evidence).
   ``indeterminate`` pixels of the box (static tissue; a motion too slow or too fast to identify) hold no
   other motion's evidence and are not counted: a vessel narrower than the footprint in static tissue keeps
   its decisions, a random-motion strip beside it (its pixels a motion or a set) does not. It only abstains.
9. **A flow decision a coarser configuration's faster decay founds** (maps of any geometry; right after rule 7,
   on its labels). Reducing the resolution never speeds a region's decorrelation: a flow's transit decay
   ``exp(−Σ_c v_c²τ²/(2s_c²))`` slows as the PSF widens, the Doppler-phase decay of diffusion and
   random-ballistic motion depends on the PSF only through terms of order ``Dτ/s²`` and ``v²τ²/s²`` that shrink
   as it widens, and a static share spread evenly through a region is the same at every resolution (physics.md
   §5.3; near a static border it is not, §14, and the grid's static-edge cells measure the cost). So inside one
   motion's region the pooled intensity correlation of every coarser configuration the model reads lies at or
   above the finest configuration's, lag by lag, up to the estimator's scatter. Where a coarser configuration's
   correlation lies below the finest's, its wider PSF reaches a region that decorrelates faster, and the decay
   the network read as flow is that neighbour's. Rule 7 sees this only through the box's labels, and a slow
   random motion next to a flow is often left ``indeterminate`` (a full prediction set, as static tissue is),
   which rule 7 does not count; rule 9 reads the evidence itself. Where, for some coarser configuration, the
   mean over the lags both read of ``rho_lin_m@finest − rho_lin_m@coarser`` exceeds :data:`MIXED_DECAY_MIN`, a
   ``flow`` decision its own data does not found (neither rule 0, 5 nor 10) becomes ``indeterminate``. A
   flow next to a slower region keeps its decisions: there the coarser configuration decays slower, not faster.
   It only abstains.
6. **A decision its neighbours do not share** (maps of any geometry; after rules 7 and 9, with rule 8, before
   rule 12). A region of one motion is at least a resolution cell wide, and the evidence of neighbouring pixels
   overlaps (the pooling window, and the PSF of every configuration the model reads), so a motion's decisions
   come in patches; a single-class decision that fewer than :data:`CONSENSUS_MIN` of the classified pixels of
   its box share is a stray one: where a few scatterers dominate a pixel (the PSF half outside the sample at
   its surface, a slab's border), a pooled estimate fell in its tail, or the coarsest configuration's PSF
   reaches into a region of another motion and its features mix the two. The box (:func:`consensus_window`) is,
   per axis, the footprint of a pooled decision: the coarsest configuration's footprint (the full width over
   which its intensity PSF stays above ``1/e²`` of its peak: the lateral resolution itself; ``1.70×`` the axial
   FWHM, physics.md §5.1) widened by the pooling window, at least :data:`CONSENSUS_WINDOW_MIN` pixels. It
   becomes ``indeterminate``. It only abstains.
8. **A decision its finest footprint contradicts** (maps of any geometry; beside rule 6, on the same labels;
   a pixel both flag counts for rule 6). Every configuration the model reads, the finest included, reads
   the pixel's whole pooling window, so a pooled decision rests at least on the finest configuration's
   footprint widened by the pooling window (:func:`consensus_window` with the finest resolutions). Where a
   border between two motions crosses that box, the decision averages both: beside a faster neighbour a
   slow motion's few percent of decay is outweighed, and the network decides the neighbour's motion a few
   pixels into it. The pixels on the other side of the border say so: their outcomes exclude the decision
   (another motion, or a set that does not name it: ``ballistic-or-flow`` excludes diffusion). A
   single-class decision where at least :data:`CONTRADICTED_MIN` of the classified pixels of that box hold
   such an outcome becomes ``indeterminate``. A few scattered sets inside one motion's region stay under
   it; ``indeterminate`` pixels and sets that name the decided motion never contradict it. It only abstains.
12. **A diffusion decision whose finest footprint decays faster at a coarser configuration** (maps of any
   geometry, pooled over :data:`MIXED_SHAPE_POOL_MIN` pixels or more; last, on the labels of rules 6 and 8).
   Rule 9's premise read on the decay's shape: a slow region (slow flow, slow random-ballistic motion, a small
   vessel) beside or inside faster diffusion is decided ``diffusion`` at its border or over all of it, because
   the coarse configurations' PSFs reach the diffusion and decay as it does (docs/benchmarks/random.md). Rule 9's
   raw excess misses it under noise: noise independent from frame to frame lowers each configuration's
   correlations at every lag of a frame or more by one factor ``(⟨I⟩/(⟨I⟩+N₀))²`` set by its own SNR
   (physics.md §8), and a coarser configuration averages more noise away and sits higher by exactly the amount
   that hides the slow region's decay. Its shape, ``ρ(m)/ρ(m₁)`` at the shortest common lag ``m₁``, is free of
   that factor (:func:`shape_excess`; undefined below :data:`SHAPE_FLOOR` at ``m₁``). Inside a diffusion region
   rule 9's derivation puts the coarser shapes at or above the finest's, up to the scatter and bias of the
   32-frame estimates, which the threshold has to clear; averaged over the decision's finest footprint (rule
   8's box, :func:`footprint_mean`), a mean excess above :data:`MIXED_SHAPE_MIN` turns a ``diffusion``
   decision ``indeterminate``. That threshold is the smallest at which at most 1 % of the
   interior pixels of the phantom grid's diffusion bands, rendered at another seed than the grid benchmark's,
   exceed it in B-scans and in volumes (``python -m research.spill --null``; docs/abstention.md gives the
   recorded table). Unpooled, one pixel's 32-frame scatter fires it inside a region as often as at a border,
   so it is not applied. ``ballistic`` decisions are not set aside: inside the grid's random-ballistic bands
   the statistic exceeds any threshold that keeps diffusion's rate far more often (the same table; measured,
   not derived), so the premise does not hold there. It only abstains.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from torchdoct.conventions import amplitude_sigma_axial_um, amplitude_sigma_lateral_um
from torchdoct.optics import _number as positive_number

__all__ = [
    "COHERENT_MOVED_MIN",
    "COHERENT_TO_FLOW",
    "COHERENT_PEAK_MIN",
    "DOPPLER_IM_MIN",
    "DOPPLER_TO_FLOW",
    "DOPPLER_WINDOW_MIN",
    "DECORRELATED_BELOW",
    "FAST_REMAINING_MAX",
    "OFFSET_FIRST_MIN",
    "OFFSET_GREW_TO_SET",
    "OFFSET_GROWTH_MIN",
    "OFFSET_HOLD_MIN",
    "OFFSET_TO_SET",
    "OffsetMotion",
    "SET_LABEL",
    "TRANSLATED_TO_FLOW",
    "TRANSLATION_GROWTH_MIN",
    "TRANSLATION_HOLD_MIN",
    "TRANSLATION_LINEAR_MAX",
    "TRANSLATION_SUPPORT_MIN",
    "TRANSLATION_WINDOW_MIN",
    "CONSENSUS_MIN",
    "CONSENSUS_WINDOW_MIN",
    "FOOTPRINT_FLOW_MIN",
    "FOOTPRINT_REACH",
    "CONTRADICTED_MIN",
    "MIXED_DECAY_MIN",
    "MIXED_SHAPE_FLAGS",
    "MIXED_SHAPE_MIN",
    "MIXED_SHAPE_POOL_MIN",
    "SHAPE_FLOOR",
    "NEIGHBOUR_CORRELATION_MIN",
    "abstain_where_ambiguous",
    "borrowed_flow",
    "consensus_window",
    "unshared",
    "contradicted",
    "coherent_motion",
    "doppler_drift",
    "doppler_imaginary",
    "mixed_footprint",
    "mixed_shape",
    "footprint_mean",
    "shape_excess",
    "fast_decorrelation",
    "offset_moved",
    "slow_decorrelation",
    "phase_reference",
    "translated",
    "neighbour_correlation",
    "single_pixel_axes",
    "line_windows",
    "unseen_axes",
]

#: Rule 12 (module docstring): a configuration's pooled intensity correlation at the shortest common lag under
#: which its decay's shape is not compared (decorrelated, or under the noise, within the first lag).
SHAPE_FLOOR = 0.2
#: Rule 12: how far the mean over a decision's finest footprint of the shape excess (:func:`shape_excess`) may
#: go before a ``diffusion`` decision counts as mixed; set at a stated false-detection rate inside one region
#: (module docstring; ``python -m research.spill --null``).
MIXED_SHAPE_MIN = 0.25
#: Rule 12: the smallest pooling window (pixels per axis) at which it is applied, the window its
#: false-detection rate was recorded at: unpooled, one pixel's scatter fires it inside a region as often as at
#: a border.
MIXED_SHAPE_POOL_MIN = 5
#: Rule 12: the decisions it may set aside (rule 9 covers ``flow``; inside a random-ballistic region its premise
#: fails, docs/abstention.md, rule 12).
MIXED_SHAPE_FLAGS = ("diffusion",)
#: Rule 9 (module docstring): how far (averaged over the lags the model reads) a coarser configuration's pooled
#: intensity correlation may lie below the finest configuration's before a flow decision counts as mixed.
MIXED_DECAY_MIN = 0.3

#: The window's intensity correlation at the longest lag below which a pixel counts as decorrelated
#: (rule 2 of the module docstring): half of the correlation is gone.
DECORRELATED_BELOW = 0.5
#: Rule 0: the smallest window peak correlation that counts as a pattern still there (half of it kept).
COHERENT_PEAK_MIN = 0.5
#: Rule 0: the smallest share of that peak moved off the centre offset that counts as coherent motion.
COHERENT_MOVED_MIN = 0.5
#: Rules 0 and 5: the speckle channel families they read, the field's (``xc_…``) and the dynamic field's
#: (``xcd_…``, :mod:`torchdoct.sim.speckle`; in maps written with ``--speckle-dynamic``).
SPECKLE_FAMILIES = ("xc", "xcd")
#: Rule 3: the largest share of the window's whole decay ``1 − ρ(m_last)`` still left after the shortest lag
#: ``ρ(m₁) − ρ(m_last)`` that counts as decorrelated before the first lag (a fifth: most of the decay is over).
FAST_REMAINING_MAX = 0.2
#: Rule 0: the decisions and sets a coherent motion turns into ``flow`` (every outcome but ``flow`` and
#: ``indeterminate``: each names only direction-symmetric motions besides flow).
COHERENT_TO_FLOW = ("ballistic", "diffusion", "ballistic-or-flow", "diffusion-or-flow", "diffusion-or-ballistic")
#: Rule 4: the offset at the shortest lag, in pixel pitches, from which flow cannot be excluded (the
#: sub-pixel fit lands nearer a neighbouring offset than the centre).
OFFSET_FIRST_MIN = 0.5
#: Rule 4: the growth of the offset over the lags, in pixel pitches, from which flow cannot be excluded.
OFFSET_GROWTH_MIN = 0.25
#: Rule 4: the window's peak correlation at the shortest lag from which its pattern counts as held.
OFFSET_HOLD_MIN = 0.8
#: Rule 4: the decisions for a direction-symmetric motion that an offset off the centre at the shortest lag
#: turns into a set with flow, and the decisions that a growing offset does.
OFFSET_TO_SET = {"ballistic": "ballistic-or-flow", "diffusion": "diffusion-or-flow"}
OFFSET_GREW_TO_SET = {"ballistic": "ballistic-or-flow"}
#: Rule 5: the window's peak correlation from which its pattern counts as held at a lag.
TRANSLATION_HOLD_MIN = 0.8
#: Rule 5: the smallest move of the signed peak offset between the shortest and the last held lag, in pitches
#: (with the neighbours' vote, the direction-symmetric motions of the patch record, docs/abstention.md, stay
#: at or near no false detection; a larger move loses slow oblique flow).
TRANSLATION_GROWTH_MIN = 0.3
#: Rule 5: the largest residual of the offset's straight line in the lag, in pitches (RMS per degree of freedom).
TRANSLATION_LINEAR_MAX = 0.1
#: Rule 5: the narrowest speckle window (pixels per axis) it is applied at: the window its rates were
#: recorded at (the maps' default). The offset's noise falls as the window's independent grains grow
#: (speckle-motion §6): a narrower window moves a held pattern's offset by chance more often.
TRANSLATION_WINDOW_MIN = 9
#: Rule 5: the outcomes a held pattern that moved turns into ``flow``.
TRANSLATED_TO_FLOW = ("ballistic", "ballistic-or-flow")
#: Rule 5 on maps: the least share of the valid pixels of the speckle window around a pixel whose own window
#: moved as a translation (a majority: the flow's region, not one window's few scatterers).
TRANSLATION_SUPPORT_MIN = 0.5
#: Rule 10: the least magnitude of the imaginary part of the circular mean of ``exp(i·doppler_phase_m)`` over a
#: pixel's box that counts as a directed axial motion. Direction-symmetric motions give it zero in expectation
#: (a real ``g1``, its phase 0 or π); their measured null over the phantom grid's static-background and
#: static-edge cells at the prior's lowest density is recorded and rendered in docs/abstention.md (rule 10).
DOPPLER_IM_MIN = 0.5
#: Rule 10: the narrowest box (pixels per axis) the Doppler phasor is averaged over (the pooling window where
#: it is wider): a single pixel's phase can be set by the one scatterer that dominates it.
DOPPLER_WINDOW_MIN = 5
#: Rule 10: the outcomes a Doppler drift turns into ``flow`` (those of rule 0).
DOPPLER_TO_FLOW = COHERENT_TO_FLOW
#: Rule 1: the least speckle intensity correlation of neighbouring pixels along an axis,
#: ``exp(−p²/(2s²))``, from which the speckle channels see the pattern move along it: ``e⁻¹``, a pitch of at
#: most ``√2·s`` (half the intensity PSF's 1/e² width laterally, 0.85 of its FWHM axially; the sampling the
#: maps' resolution reduction requires, two pixels per 1/e² width).
NEIGHBOUR_CORRELATION_MIN = math.exp(-1.0)
#: The set label a ballistic decision becomes.
SET_LABEL = "ballistic-or-flow"
#: Rule 6: the share of the classified pixels of a pixel's window that must hold its single-class decision.
CONSENSUS_MIN = 0.5
#: Rule 6: the narrowest window (pixels per axis), used where the pooling window and the footprint are narrower.
CONSENSUS_WINDOW_MIN = 3
#: Rule 7: the least share of the classified, not ``indeterminate`` pixels of an unmoved ``flow`` decision's box
#: that must be ``flow`` for it to stand (nine in ten: the footprint is one flow region, a few scattered
#: other outcomes aside).
FOOTPRINT_FLOW_MIN = 0.9
#: Rule 7: the footprint term of its box, a multiple of rule 6's (:func:`consensus_window`, ``reach``). A
#: neighbour at distance ``d`` holds the share ``exp(−2d²/r²)`` of the coarse intensity PSF (``r`` the 1/e² half
#: width, physics.md §5.1): ``e^{−2}`` (14 %) at the footprint's edge, ``e^{−4.5}`` (1 %) at 1.5 of it. A flow that
#: decorrelates fully adds that share to the decay the coarse configuration reads at every lag: beside the few
#: percent a slow random motion decays by itself, 14 % is a flow's signature, 1 % is not.
FOOTPRINT_REACH = 1.5
#: Rule 8: the share of the classified pixels of a decision's finest footprint holding an outcome that excludes
#: its class from which the decision is contradicted (one in ten: a few scattered sets inside a region of one
#: motion stay under it, a neighbouring region's edge inside the footprint does not).
CONTRADICTED_MIN = 0.1
#: The single-class decisions rule 6 checks.
_MOTIONS = ("diffusion", "ballistic", "flow")

_XC_CENTRE = re.compile(r"^xc_centre_(\d+)@")
_RHO_LIN = re.compile(r"^rho_lin_(\d+)$")
_XC_CENTRE_RES = re.compile(r"^xc_centre_(\d+)@(.+)$")
_XC_SHIFT = re.compile(r"^xc_shift_(\d+)@(.+)$")
_DOPPLER = re.compile(r"^doppler_phase_(\d+)@")


def _read(channels: Mapping[str, np.ndarray], name: str, idx: np.ndarray | None) -> np.ndarray:
    """One channel's map as float64, flattened, at the classified pixels ``idx`` (all when ``None``)."""
    v = np.asarray(channels[name], np.float64).reshape(-1)
    return v if idx is None else v[idx]


def neighbour_correlation(pitch_um: float, sigma_um: float) -> float:
    """The speckle intensity correlation of two pixels ``pitch_um`` apart along an axis whose amplitude PSF has
    the standard deviation ``sigma_um`` (µm): ``exp(−p²/(2s²))`` (speckle-motion §3 (a) at ``τ = 0``)."""
    return math.exp(-(pitch_um**2) / (2.0 * sigma_um**2))


def single_pixel_axes(extent_px: Mapping[str, int]) -> list[str]:
    """The axes (lower-case letters) of a map that hold a single pixel (``extent_px``: pixels per axis letter):
    one A-line's time series has one pixel along x (and y)."""
    return [str(c).lower() for c, n in extent_px.items() if int(n) < 2]


def line_windows(extent_px: Mapping[str, int]) -> bool:
    """True where fewer than two axes of a map hold more than one pixel (``extent_px``: pixels per axis letter;
    one A-line's time series): its speckle window is a line of a few axial grains and its Doppler box a few
    pixels, not the two-dimensional windows and boxes over which rules 0, 5 and 10 had their false detections
    recorded, so those rules found no flow on such maps (module docstring, rule 1). A volume of one plane is a
    B-scan for them."""
    return len(extent_px) - len(single_pixel_axes(extent_px)) < 2


def unseen_axes(
    axes: str,
    pitch_um: Mapping[str, Any] | None,
    lateral_um: float | None,
    axial_um: float | None,
    lateral_y_um: float | None = None,
    extent_px: Mapping[str, int] | None = None,
) -> list[str]:
    """Rule 1 (module docstring): the axes (lower-case letters of ``x, y, z``) along which the speckle
    channels of maps of spatial axes ``axes`` (``ZX``, ``YZX``) cannot see the pattern move: ``y`` of a
    B-scan, every axis of a single pixel (``extent_px``, pixels per axis letter: one A-line's time series has
    no neighbour along x), and every axis whose pitch (``pitch_um``, µm per axis letter) leaves the speckle correlation of
    neighbouring pixels below :data:`NEIGHBOUR_CORRELATION_MIN` at the speckle channels' resolution (lateral:
    1/e² width along x, ``lateral_y_um`` along y when it differs; axial: FWHM; µm). An axis without a positive
    finite pitch or resolution is unseen: nothing says its neighbours share the speckle (maps without the
    speckle channels give ``None`` resolutions and see no axis)."""
    pitch = {str(k).lower(): v for k, v in (pitch_um or {}).items()} if isinstance(pitch_um, Mapping) else {}
    res = {"x": lateral_um, "y": lateral_um if lateral_y_um is None else lateral_y_um, "z": axial_um}

    out = []
    extent = {str(k).lower(): v for k, v in (extent_px or {}).items()} if isinstance(extent_px, Mapping) else {}
    for c in "xyz":
        p, r = positive_number(pitch.get(c)), positive_number(res[c])
        n = extent.get(c)
        if c.upper() not in axes.upper() or p is None or r is None or (n is not None and int(n) < 2):
            out.append(c)
            continue
        s = amplitude_sigma_axial_um(r) if c == "z" else amplitude_sigma_lateral_um(r)
        if neighbour_correlation(p, s) < NEIGHBOUR_CORRELATION_MIN * (1.0 - 1e-9):
            out.append(c)
    return out


def coherent_motion(
    channels: Mapping[str, np.ndarray], idx: np.ndarray | None = None, n_frames: int = 32, family: str = "xc"
) -> tuple[np.ndarray | None, list[str]]:
    """Rule 0 per classified pixel (module docstring): True where the speckle pattern moved coherently at a
    lag ``m ≤ n_frames // 4``; and the lags' channel names read. ``channels``: name -> map holding
    ``xc_peak_m@…`` and ``xc_centre_m@…`` of one resolution, read at ``idx``; ``family="xcd"``: those of the
    dynamic field (``xcd_…``, :data:`SPECKLE_FAMILIES`). ``(None, [])`` without them. NaN counts as not seen."""
    found = None
    used: list[str] = []
    limit = max(1, int(n_frames) // 4)
    peak_pattern = re.compile(rf"^{family}_peak_(\d+)@(.+)$")
    for name in sorted(channels):
        m = peak_pattern.match(name)
        if not m or int(m.group(1)) > limit:
            continue
        centre = f"{family}_centre_{m.group(1)}@{m.group(2)}"
        if centre not in channels:
            continue
        peak, cen = _read(channels, name, idx), _read(channels, centre, idx)
        with np.errstate(invalid="ignore", divide="ignore"):
            seen = (peak >= COHERENT_PEAK_MIN) & ((peak - cen) >= COHERENT_MOVED_MIN * peak)
        found = seen if found is None else (found | seen)
        used += [name, centre]
    return found, used


def _widths(window: int | Sequence[int], ndim: int) -> list[int]:
    """One box width per axis: ``window`` along every one of ``ndim`` axes, or the given widths."""
    if isinstance(window, Sequence):
        return [int(w) for w in window]
    return [int(window)] * ndim


def _box_total(values: np.ndarray, window: int | Sequence[int]) -> np.ndarray:
    """Per pixel of a map: the sum of ``values`` (in their own dtype) over the box centred on it (``window``
    pixels along every axis, or one width per axis; cut at the map's edges)."""
    from .pooling import _box_sum

    out = np.asarray(values)
    for ax, w in enumerate(_widths(window, out.ndim)):
        out = _box_sum(out, w, ax)
    return out


def _box_count(mask: np.ndarray, window: int | Sequence[int]) -> np.ndarray:
    """Per pixel of a map: how many pixels of the box centred on it (as :func:`_box_total`) hold ``mask``
    (int32)."""
    return _box_total(np.asarray(mask).astype(np.int32), window)


def doppler_imaginary(
    channels: Mapping[str, np.ndarray], window: int = DOPPLER_WINDOW_MIN
) -> tuple[np.ndarray | None, str | None]:
    """Rule 10's statistic on the whole map: per pixel the imaginary part of the circular mean of ``exp(i·φ)``,
    ``φ`` the Doppler phase against a static reference at the shortest lag the maps hold (``doppler_phase_m@…``,
    rad, :mod:`torchdoct.measured.doppler`), over the box of ``max(window, DOPPLER_WINDOW_MIN)`` pixels per axis
    centred on the pixel (cut at the map's edges); 0 where less than half of the box holds a phase (NaN: no
    reference). Returns the map and the channel read; ``(None, None)`` without a Doppler channel."""
    best: tuple[int, str] | None = None
    for name in channels:
        m = _DOPPLER.match(name)
        if m and (best is None or int(m.group(1)) < best[0]):
            best = (int(m.group(1)), name)
    if best is None:
        return None, None
    phase = np.asarray(channels[best[1]], np.float64)
    ok = np.isfinite(phase)
    width = max(int(window), DOPPLER_WINDOW_MIN)
    im = _box_total(np.where(ok, np.sin(np.where(ok, phase, 0.0)), 0.0), width)  # float64, as ``phase``
    n_ok = _box_count(ok, width)
    n_all = _box_count(np.ones(phase.shape, bool), width)
    return np.where(2 * n_ok >= n_all, im / np.maximum(n_ok, 1), 0.0), best[1]


def doppler_drift(
    channels: Mapping[str, np.ndarray], idx: np.ndarray | None = None, window: int = DOPPLER_WINDOW_MIN
) -> tuple[np.ndarray | None, list[str]]:
    """Rule 10 per classified pixel (module docstring): True where :func:`doppler_imaginary` (the circular mean
    of the Doppler phasor over the pixel's box of ``max(window, DOPPLER_WINDOW_MIN)`` pixels per axis) has an
    imaginary part of magnitude at least :data:`DOPPLER_IM_MIN`; and the channel read, at the flat positions
    ``idx`` (all when ``None``). ``(None, [])`` without a Doppler channel."""
    im, name = doppler_imaginary(channels, window)
    if im is None or name is None:
        return None, []
    seen = (np.abs(im) >= DOPPLER_IM_MIN).reshape(-1)
    return (seen if idx is None else seen[idx]), [name]


def phase_reference(channels: Mapping[str, np.ndarray], idx: np.ndarray | None = None) -> tuple[np.ndarray, list[str]]:
    """Rule 11 per classified pixel (module docstring): True where some Doppler channel (``doppler_phase_m@…``)
    holds a finite phase, i.e. a static-tissue reference in the pixel's A-line or B-scan measures its mean
    axial motion; and the channels read. All False without a Doppler channel (intensity-only data, or no
    static reference anywhere)."""
    names = sorted(c for c in channels if _DOPPLER.match(c))
    if not names:
        return np.zeros(0 if idx is None else len(idx), bool), []
    seen = np.zeros(int(np.asarray(channels[names[0]]).size), bool)
    for c in names:
        seen |= np.isfinite(np.asarray(channels[c], np.float64).reshape(-1))
    return (seen if idx is None else seen[idx]), names


def _window_share(hit: np.ndarray, valid: np.ndarray, window: int) -> np.ndarray:
    """Per pixel of a map: the share of the valid pixels of the ``window``-wide box centred on it (cut at the
    map's edges) where ``hit`` holds; NaN where the box holds no valid pixel."""
    num, den = _box_count(hit & valid, window), _box_count(valid, window)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1), np.nan)


#: Pixels per slab of rule 5's per-window criterion (bounds its float64 temporaries).
_CHUNK = 1 << 20


def _moved_along_a_line(d: np.ndarray, peaks: np.ndarray, lags: Sequence[int]) -> np.ndarray:
    """Rule 5's per-window criterion (:func:`translated`): ``d`` the signed offsets ``[axes, lags, pixels]`` in
    pitches, ``peaks`` ``xc_peak`` ``[lags, pixels]``; True where the pattern held through at least three lags
    from the shortest on and its offset moved along a line over them."""
    with np.errstate(invalid="ignore"):
        held = peaks >= TRANSLATION_HOLD_MIN
    run = np.cumprod(held, axis=0).sum(0)  # lags held from the shortest on
    seen = np.zeros(d.shape[-1], bool)
    for k in range(3, len(lags) + 1):  # the pixels whose pattern held through exactly the first k lags
        sel = run == k
        if not sel.any():
            continue
        dk = d[:, :k, :]
        lag = np.asarray(lags[:k], np.float64)
        lc = lag - lag.mean()
        slope = (dk * lc[None, :, None]).sum(1) / (lc**2).sum()  # [axes, pixels], pitches per frame
        resid = dk - dk.mean(1, keepdims=True) - slope[:, None, :] * lc[None, :, None]
        rms = np.sqrt((resid**2).sum((0, 1)) / (d.shape[0] * (k - 2)))
        growth = np.sqrt(((dk[:, -1] - dk[:, 0]) ** 2).sum(0))
        with np.errstate(invalid="ignore"):
            seen |= sel & (growth >= TRANSLATION_GROWTH_MIN) & (rms <= TRANSLATION_LINEAR_MAX)
    return seen


def translated(
    channels: Mapping[str, np.ndarray],
    pitch_um: Mapping[str, float] | None,
    idx: np.ndarray | None = None,
    window_px: int | None = None,
    family: str = "xc",
) -> tuple[np.ndarray | None, list[str]]:
    """Rule 5 per classified pixel (module docstring): True where, over the lags through which the window's
    pattern held (the longest run of lags from the shortest on with ``xc_peak_m@…`` ≥
    :data:`TRANSLATION_HOLD_MIN`, at least three lags), its signed peak offset (``xc_shift_{c}_m@…``, µm,
    divided by the pitch of axis ``c``) moved by at least :data:`TRANSLATION_GROWTH_MIN` pitches from the
    first to the last of them along a straight line in the lag (residual at most
    :data:`TRANSLATION_LINEAR_MAX` pitches); and, where the channels are maps (2-D B-scans, 3-D volumes),
    at least :data:`TRANSLATION_SUPPORT_MIN` of the valid pixels of the speckle window centred on the pixel
    (``window_px`` per axis, :data:`TRANSLATION_WINDOW_MIN` when unknown; cut at the map's edges) met that
    criterion too: a flow translates every window that lies in it, a few scatterers moving alone only the
    windows they dominate. 1-D channels are independent windows, judged one by one. Returns the mask and the
    channel names read. ``pitch_um``: the pixel pitch (µm) per axis letter. ``(None, [])`` without the signed
    offsets of every axis and the peaks at three lags or more, or the pitches, or when the speckle window
    ``window_px`` (pixels per axis, the maps' ``meta["speckle"]["window_px"]``) is known and narrower than
    :data:`TRANSLATION_WINDOW_MIN`. NaN counts as not held and not moved. ``family="xcd"``: the channels of the
    dynamic field (``xcd_…``, :data:`SPECKLE_FAMILIES`)."""
    if not isinstance(pitch_um, Mapping):
        return None, []
    if window_px is not None and int(window_px) < TRANSLATION_WINDOW_MIN:
        return None, []
    found: dict[str, dict[str, set[int]]] = {}
    shift_pattern = re.compile(rf"^{family}_shift_([xyz])_(\d+)@(.+)$")
    for name in channels:
        m = shift_pattern.match(name)
        if m:
            found.setdefault(m.group(3), {}).setdefault(m.group(1), set()).add(int(m.group(2)))
    for res, per_axis in sorted(found.items()):
        axes = sorted(per_axis)
        lags = [m for m in sorted(set.intersection(*per_axis.values())) if f"{family}_peak_{m}@{res}" in channels]
        given = {c: pitch_um.get(c) for c in axes}
        ok_pitch = all(
            isinstance(p, (int, float)) and not isinstance(p, bool) and 0 < p < np.inf for p in given.values()
        )
        if len(lags) < 3 or not ok_pitch:
            continue
        pitch = {c: float(p) for c, p in given.items() if p is not None}

        names = [f"{family}_shift_{c}_{m}@{res}" for c in axes for m in lags] + [
            f"{family}_peak_{m}@{res}" for m in lags
        ]
        shape = np.shape(channels[names[0]])
        n = int(np.prod(shape))
        seen = np.zeros(n, bool)
        flat = {k: np.asarray(channels[k]).reshape(-1) for k in names}
        for lo in range(0, n, _CHUNK):  # every pixel of the map (the neighbours vote), a slab at a time
            part = slice(lo, min(lo + _CHUNK, n))
            seen[part] = _moved_along_a_line(
                np.stack(
                    [
                        np.stack(
                            [flat[f"{family}_shift_{c}_{m}@{res}"][part].astype(np.float64) / pitch[c] for m in lags]
                        )
                        for c in axes
                    ]
                ),
                np.stack([flat[f"{family}_peak_{m}@{res}"][part].astype(np.float64) for m in lags]),
                lags,
            )
        if len(shape) >= 2:
            valid = np.isfinite(np.asarray(channels[f"{family}_peak_{lags[0]}@{res}"])).reshape(shape)
            share = _window_share(seen.reshape(shape), valid, window_px or TRANSLATION_WINDOW_MIN)
            with np.errstate(invalid="ignore"):
                seen = seen & (share >= TRANSLATION_SUPPORT_MIN).reshape(-1)
        return (seen if idx is None else seen[idx]), names
    return None, []


def slow_decorrelation(
    channels: Mapping[str, np.ndarray],
    columns: Sequence[Mapping[str, Any]] | None = None,
    pooled: np.ndarray | None = None,
    idx: np.ndarray | None = None,
    n_frames: int = 32,
) -> tuple[np.ndarray | None, str | None]:
    """The correlation that decides rule 2 per classified pixel, and where it came from.

    ``channels``: name -> map of the maps files (the speckle channel ``xc_centre_m@…`` at the largest ``m``,
    read at the classified pixels ``idx``); else ``pooled`` (the model's input rows) at the column of the
    first configuration's ``rho_lin_m`` whose lag is nearest ``n_frames // 2``. ``(None, None)`` when
    neither exists (rule 2 is then not applied; the classification's info says so)."""
    best = None
    for name in channels:
        m = _XC_CENTRE.match(name)
        if m and (best is None or int(m.group(1)) > best[0]):
            best = (int(m.group(1)), name)
    if best is not None:
        return _read(channels, best[1], idx), best[1]
    if columns is None or pooled is None:
        return None, None
    target = max(1, int(n_frames) // 2)
    first = columns[0].get("configuration") if columns else None
    cands = []
    for j, col in enumerate(columns[:-1]):
        m = _RHO_LIN.match(str(col.get("metric", "")))
        if m and col.get("configuration") == first:
            cands.append((abs(int(m.group(1)) - target), j, str(col.get("name", col.get("metric")))))
    if not cands:
        return None, None
    _, j, name = min(cands)
    return np.asarray(pooled[:, j], np.float64), name


def fast_decorrelation(
    channels: Mapping[str, np.ndarray], idx: np.ndarray | None = None
) -> tuple[np.ndarray | None, list[str]]:
    """Rule 3 per classified pixel (module docstring): True where the window's correlation left after the
    shortest lag is below :data:`FAST_REMAINING_MAX` of its whole decay, ``ρ(m₁) − ρ(m_last) <
    FAST_REMAINING_MAX·(1 − ρ(m_last))`` with ``ρ(m) = xc_centre_m@…`` of one resolution (the first one
    found), read at ``idx``; and the two channel names. ``(None, [])`` without two lags. NaN counts as not
    decorrelated."""
    by_res: dict[str, list[tuple[int, str]]] = {}
    for name in channels:
        m = _XC_CENTRE_RES.match(name)
        if m:
            by_res.setdefault(m.group(2), []).append((int(m.group(1)), name))
    lags = next((sorted(v) for v in by_res.values() if len(v) >= 2), None)
    if lags is None:
        return None, []
    first, last = lags[0][1], lags[-1][1]
    a, b = _read(channels, first, idx), _read(channels, last, idx)
    with np.errstate(invalid="ignore"):
        fast = (a - b) < FAST_REMAINING_MAX * (1.0 - b)
    return fast, [first, last]


class OffsetMotion(NamedTuple):
    """Rule 4's two clauses per classified pixel (module docstring)."""

    off_centre: np.ndarray  #: the offset at the shortest lag is off the centre
    grew: np.ndarray  #: the pattern held at the shortest lag and its offset grew with the lag


def offset_moved(
    channels: Mapping[str, np.ndarray], pitch_um: float | None, idx: np.ndarray | None = None, n_frames: int = 32
) -> tuple[OffsetMotion | None, list[str]]:
    """Rule 4 per classified pixel (module docstring): where the peak offset ``xc_shift_m@…`` (µm) of one
    resolution, over its lags ``m ≤ n_frames // 4``, starts at least :data:`OFFSET_FIRST_MIN` pitches off the
    centre (``off_centre``), and where it grows at every lag by at least :data:`OFFSET_GROWTH_MIN` pitches in
    all while the pattern held at the shortest lag (``xc_peak_m₁@…`` ≥ :data:`OFFSET_HOLD_MIN`; ``grew``);
    and the channel names read. ``pitch_um``: the finest pixel pitch (µm). ``(None, [])`` without two lags,
    their peaks or a pitch. NaN counts as not moved."""
    if not pitch_um or not np.isfinite(pitch_um) or pitch_um <= 0:
        return None, []
    limit = max(1, int(n_frames) // 4)
    by_res: dict[str, list[int]] = {}
    for name in channels:
        m = _XC_SHIFT.match(name)
        if m and int(m.group(1)) <= limit and f"xc_peak_{m.group(1)}@{m.group(2)}" in channels:
            by_res.setdefault(m.group(2), []).append(int(m.group(1)))
    res = next((r for r, lags in sorted(by_res.items()) if len(lags) >= 2), None)
    if res is None:
        return None, []
    lags = sorted(by_res[res])
    names = [f"xc_shift_{m}@{res}" for m in lags]
    shift = [_read(channels, n, idx) for n in names]
    held_name = f"xc_peak_{lags[0]}@{res}"
    with np.errstate(invalid="ignore"):
        grew = _read(channels, held_name, idx) >= OFFSET_HOLD_MIN
        for a, b in zip(shift[:-1], shift[1:]):
            grew &= b > a
        grew &= (shift[-1] - shift[0]) >= OFFSET_GROWTH_MIN * pitch_um
        off_centre = shift[0] >= OFFSET_FIRST_MIN * pitch_um
    return OffsetMotion(off_centre, grew), names + [held_name]


def abstain_where_ambiguous(
    labels: np.ndarray,
    names: Sequence[str],
    *,
    unseen_axis: bool,
    correlation: np.ndarray | None,
    coherent: np.ndarray | None = None,
    fast: np.ndarray | None = None,
    moved: OffsetMotion | None = None,
    translation: np.ndarray | None = None,
    doppler: np.ndarray | None = None,
    reference: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, int]]:
    """``labels`` (indices into ``names``, one per classified pixel) with, first, the outcomes of
    :data:`COHERENT_TO_FLOW` turned into ``flow`` where ``coherent`` (rule 0, :func:`coherent_motion`) and the
    outcomes of :data:`TRANSLATED_TO_FLOW` where ``translation`` (rule 5, :func:`translated`) and those of
    :data:`DOPPLER_TO_FLOW` where ``doppler`` (rule 10, :func:`doppler_drift`), then the
    remaining ``ballistic`` into :data:`SET_LABEL` where rules 1 (``unseen_axis``: a B-scan, or maps with an axis
    :func:`unseen_axes` names), 11 (``reference`` False: no phase reference, :func:`phase_reference`; not
    applied when ``reference`` is ``None``), 2 (``correlation`` ≥
    :data:`DECORRELATED_BELOW`; NaN counts as not decorrelated) or 3 (``fast``, :func:`fast_decorrelation`)
    apply, and last the remaining ``ballistic`` and ``diffusion`` into their set with flow where
    ``moved.off_centre`` (:data:`OFFSET_TO_SET`) and the remaining ``ballistic`` where ``moved.grew``
    (:data:`OFFSET_GREW_TO_SET`; rule 4, :func:`offset_moved`); and the pixels each rule changed (a pixel
    counts for the first rule that changed it).
    ``names`` must hold ``ballistic`` and :data:`SET_LABEL` (else ``labels`` come back unchanged)."""
    names = list(names)
    counts = {
        "coherent_motion": 0,
        "translation": 0,
        "doppler_drift": 0,
        "bscan_plane": 0,
        "sheared_flow": 0,
        "slow_decorrelation": 0,
        "fast_decorrelation": 0,
        "offset_moved": 0,
    }
    if "ballistic" not in names or SET_LABEL not in names:
        return labels, counts
    out = np.array(labels, copy=True)
    if coherent is not None and "flow" in names:
        to_flow = np.isin(out, [names.index(n) for n in COHERENT_TO_FLOW if n in names]) & np.asarray(coherent, bool)
        counts["coherent_motion"] = int(to_flow.sum())
        out[to_flow] = names.index("flow")
    if translation is not None and "flow" in names:
        to_flow = np.isin(out, [names.index(n) for n in TRANSLATED_TO_FLOW if n in names]) & np.asarray(
            translation, bool
        )
        counts["translation"] = int(to_flow.sum())
        out[to_flow] = names.index("flow")
    if doppler is not None and "flow" in names:
        to_flow = np.isin(out, [names.index(n) for n in DOPPLER_TO_FLOW if n in names]) & np.asarray(doppler, bool)
        counts["doppler_drift"] = int(to_flow.sum())
        out[to_flow] = names.index("flow")
    ball = out == names.index("ballistic")
    if unseen_axis:
        counts["bscan_plane"] = int(ball.sum())
        out[ball] = names.index(SET_LABEL)
        ball[:] = False
    if reference is not None:
        sheared = ball & ~np.asarray(reference, bool)
        counts["sheared_flow"] = int(sheared.sum())
        out[sheared] = names.index(SET_LABEL)
        ball &= ~sheared
    if correlation is not None:
        slow = ball & ~(np.asarray(correlation, np.float64) < DECORRELATED_BELOW)
        counts["slow_decorrelation"] = int(slow.sum())
        out[slow] = names.index(SET_LABEL)
        ball &= ~slow
    if fast is not None:
        gone = ball & np.asarray(fast, bool)
        counts["fast_decorrelation"] = int(gone.sum())
        out[gone] = names.index(SET_LABEL)
    if moved is not None:
        for mask, table in ((moved.off_centre, OFFSET_TO_SET), (moved.grew, OFFSET_GREW_TO_SET)):
            for single, set_name in table.items():
                if single in names and set_name in names:
                    sel = (out == names.index(single)) & np.asarray(mask, bool)
                    counts["offset_moved"] += int(sel.sum())
                    out[sel] = names.index(set_name)
    return out, counts


def consensus_window(
    axes: str,
    pitch_um: Mapping[str, Any] | None,
    pool: int,
    lateral_um: float | None = None,
    axial_um: float | None = None,
    lateral_y_um: float | None = None,
    reach: float = 1.0,
) -> tuple[int, ...]:
    """Rule 6's box (module docstring), pixels per axis of ``axes`` (the maps' spatial axes, e.g. ``"ZX"``,
    ``"YZX"``): per axis the footprint of a decision pooled over ``pool`` pixels, the footprint of the
    coarsest configuration the model reads widened by the pooling window. That footprint is the full width
    over which the configuration's intensity PSF ``exp(−x²/s_x² − z²/s_z²)`` stays above ``1/e²``:
    ``2√2 s_x = lateral_um`` along ``x`` and ``y`` (the 1/e² width; ``lateral_y_um`` along ``y`` when given),
    ``2√2 s_z = √2·axial_um/√ln 2`` along ``z`` (``axial_um`` the FWHM; physics.md §5.1); over the axis's
    pitch, rounded up, plus ``pool − 1`` (the pooled features at a pixel average the footprints of ``pool``
    pixels per axis), rounded up to an odd count; never narrower than ``pool`` or
    :data:`CONSENSUS_WINDOW_MIN`. ``reach`` scales the footprint (rule 7's box: :data:`FOOTPRINT_REACH`).
    An axis without a positive finite pitch or resolution keeps the pooling window."""
    if not (isinstance(reach, (int, float)) and not isinstance(reach, bool) and 0 < reach < np.inf):
        raise ValueError(f"consensus_window: reach must be a positive finite number, got {reach!r}")
    base = max(int(pool), CONSENSUS_WINDOW_MIN)
    pitch = pitch_um if isinstance(pitch_um, Mapping) else {}
    out = []
    for ax in axes.lower():
        res = {"z": axial_um, "y": lateral_um if lateral_y_um is None else lateral_y_um}.get(ax, lateral_um)
        width = res * np.sqrt(2.0 / np.log(2.0)) if (ax == "z" and res is not None) else res
        width = width * float(reach) if isinstance(width, (int, float)) and not isinstance(width, bool) else width
        p = pitch.get(ax)
        ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < np.inf for v in (width, p))
        n = int(np.ceil(float(width) / float(p) - 1e-9)) + int(pool) - 1 if ok else 0  # type: ignore[arg-type]
        out.append(max(base, n + 1 - n % 2))
    return tuple(out)


def _label_map(
    labels: np.ndarray, idx: np.ndarray, shape: tuple[int, ...], window: int | Sequence[int]
) -> tuple[np.ndarray, list[int]]:
    """Rules 6 and 7: the labels as a map of ``shape`` (−1 where not classified) and the box width per axis
    (``window``, at least :data:`CONSENSUS_WINDOW_MIN`); ``ValueError`` when ``window`` gives another number
    of axes than the map has."""
    grid = np.full(int(np.prod(shape)), -1, np.int16)
    grid[idx] = labels
    given = _widths(window, len(shape))
    if len(given) != len(shape):
        raise ValueError(f"rule 6: {len(given)} window widths for a map of {len(shape)} axes {tuple(shape)}")
    return grid.reshape(shape), [max(w, CONSENSUS_WINDOW_MIN) for w in given]


def _unmoved_flow(
    labels: np.ndarray,
    names: list[str],
    coherent: np.ndarray | None,
    translation: np.ndarray | None,
    doppler: np.ndarray | None = None,
) -> np.ndarray:
    """Rules 7 and 9: the ``flow`` decisions that the pixel's own data does not found (neither ``coherent``,
    rule 0, nor ``translation``, rule 5, nor ``doppler``, rule 10, seen; a rule without its channels sees
    nothing). All False without a ``flow`` label."""
    if "flow" not in names:
        return np.zeros(labels.shape, bool)
    cand = labels == names.index("flow")
    for seen in (coherent, translation, doppler):
        if seen is not None:
            cand &= ~np.asarray(seen, bool)
    return cand


def borrowed_flow(
    labels: np.ndarray,
    names: Sequence[str],
    idx: np.ndarray,
    shape: tuple[int, ...],
    window: int | Sequence[int],
    coherent: np.ndarray | None = None,
    translation: np.ndarray | None = None,
    doppler: np.ndarray | None = None,
) -> np.ndarray:
    """Rule 7 (module docstring): per classified pixel (``labels`` after rules 0–5, indices into ``names``, at
    the flat positions ``idx`` of a map of ``shape``), whether it holds a ``flow`` decision that the pixel's
    own data does not found (neither ``coherent``, rule 0, nor ``translation``, rule 5, nor ``doppler``, rule
    10, seen; a rule without its channels sees nothing) and that fewer than :data:`FOOTPRINT_FLOW_MIN` of the
    classified pixels of its box (``window`` as in :func:`unshared`) that are not ``indeterminate`` share. All
    False without a ``flow`` label."""
    labels = np.asarray(labels)
    names = list(names)
    cand = _unmoved_flow(labels, names, coherent, translation, doppler)
    if not cand.any():
        return cand
    grid, width = _label_map(labels, idx, shape, window)
    flow = _box_count(grid == names.index("flow"), width).reshape(-1)[idx]
    motion = grid >= 0
    if "indeterminate" in names:  # static tissue, or a motion the data cannot identify: no other motion's evidence
        motion &= grid != names.index("indeterminate")
    return cand & (flow < FOOTPRINT_FLOW_MIN * _box_count(motion, width).reshape(-1)[idx])


def unshared(
    labels: np.ndarray, names: Sequence[str], idx: np.ndarray, shape: tuple[int, ...], window: int | Sequence[int]
) -> np.ndarray:
    """Rule 6 (module docstring): per classified pixel (``labels``, indices into ``names``, at the flat
    positions ``idx`` of a map of ``shape``), whether it holds a decision for one motion that fewer than
    :data:`CONSENSUS_MIN` of the classified pixels of the box centred on it share (``window`` pixels along
    every axis, or one width per axis as :func:`consensus_window` gives; at least
    :data:`CONSENSUS_WINDOW_MIN`; cut at the map's edges)."""
    return _flag_single_class(
        labels, names, idx, shape, window, lambda k, name: [k], lambda n, c: n < CONSENSUS_MIN * c
    )


def contradicted(
    labels: np.ndarray, names: Sequence[str], idx: np.ndarray, shape: tuple[int, ...], window: int | Sequence[int]
) -> np.ndarray:
    """Rule 8 (module docstring): per classified pixel (``labels``, indices into ``names``, at the flat
    positions ``idx`` of a map of ``shape``), whether it holds a decision for one motion while at least
    :data:`CONTRADICTED_MIN` of the classified pixels of the box centred on it (``window`` pixels per axis, the
    finest configuration's footprint widened by the pooling window, :func:`consensus_window`; cut at the map's
    edges) hold an outcome that excludes that motion: another motion, or a set that does not name it."""
    names = list(names)

    def excluding(k: int, name: str) -> list[int]:
        return [j for j, n in enumerate(names) if j != k and n != "indeterminate" and name not in n.split("-or-")]

    return _flag_single_class(labels, names, idx, shape, window, excluding, lambda n, c: n >= CONTRADICTED_MIN * c)


def _flag_single_class(
    labels: np.ndarray,
    names: Sequence[str],
    idx: np.ndarray,
    shape: tuple[int, ...],
    window: int | Sequence[int],
    held_by: Callable[[int, str], list[int]],
    flag: Callable[[np.ndarray, np.ndarray], np.ndarray],
) -> np.ndarray:
    """Rules 6 and 8: per classified pixel holding a single-class decision ``k`` (``name``), ``flag(n, c)`` where
    ``n`` counts the pixels of its box whose label is one of ``held_by(k, name)`` and ``c`` the classified
    pixels of the box (≥ 1: itself); False for every other pixel."""
    labels = np.asarray(labels)
    names = list(names)
    grid, width = _label_map(labels, idx, shape, window)
    out = np.zeros(labels.shape, bool)
    classified = None
    for k, name in enumerate(names):
        mine = labels == k
        if name not in _MOTIONS or not mine.any():
            continue
        if classified is None:
            classified = _box_count(grid >= 0, width).reshape(-1)[idx]
        held = _box_count(np.isin(grid, held_by(k, name)), width).reshape(-1)[idx]
        out |= mine & flag(held, classified)
    return out


def mixed_footprint(
    labels: np.ndarray,
    names: Sequence[str],
    columns: Sequence[Mapping[str, Any]],
    pooled: np.ndarray,
    finest: str | None,
    coherent: np.ndarray | None = None,
    translation: np.ndarray | None = None,
    doppler: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Rule 9 (module docstring): per classified pixel (``labels`` after rule 7, indices into ``names``), whether
    it holds a ``flow`` decision that its own pattern does not found (as in :func:`borrowed_flow`) and that a
    coarser configuration founds by a faster decay than the finest one's; and that excess per pixel.

    ``columns``: the model's input columns (``metric``, ``configuration``), the last one the pool size;
    ``pooled``: the model's input rows; ``finest``: the name of the configuration with the smallest footprint.
    The excess is, over the configurations other than ``finest``, the largest mean over the lags both read of
    ``rho_lin_m@finest − rho_lin_m@coarser``; a decision is flagged where it exceeds :data:`MIXED_DECAY_MIN`.
    All False, and the excess ``None``, when the model reads no ``rho_lin_m`` of ``finest`` and of another
    configuration at a common lag."""
    labels = np.asarray(labels)
    names = list(names)
    lags = _rho_lin_columns(columns)
    fine = lags.get(str(finest), {})
    pairs = [(fine, cols, sorted(set(cols) & set(fine))) for conf, cols in lags.items() if conf != finest]
    pairs = [p for p in pairs if p[2]]
    if not pairs:
        return np.zeros(labels.shape, bool), None
    pooled = np.asarray(pooled)
    excess = np.max(
        [
            np.mean([pooled[:, f[m]].astype(np.float64) - pooled[:, c[m]] for m in common], axis=0)
            for f, c, common in pairs
        ],
        axis=0,
    )
    return _unmoved_flow(labels, names, coherent, translation, doppler) & (excess > MIXED_DECAY_MIN), excess


def _rho_lin_columns(columns: Sequence[Mapping[str, Any]]) -> dict[str, dict[int, int]]:
    """Rules 9 and 12: per configuration, the input column of its pooled ``rho_lin_m`` at each lag ``m``."""
    lags: dict[str, dict[int, int]] = {}
    for j, col in enumerate(columns[:-1]):
        m = _RHO_LIN.match(str(col.get("metric", "")))
        if m and col.get("configuration") is not None:
            lags.setdefault(str(col["configuration"]), {})[int(m.group(1))] = j
    return lags


def shape_excess(
    columns: Sequence[Mapping[str, Any]],
    pooled: np.ndarray,
    finest: str | None,
) -> np.ndarray | None:
    """Rule 12's statistic per input row (module docstring): over the configurations other than ``finest`` that
    read at least two lags in common with it, the largest mean over the lags after the shortest common one
    ``m₁`` of ``ρ_f(m)/ρ_f(m₁) − ρ_c(m)/ρ_c(m₁)`` (``ρ`` the pooled ``rho_lin_m``, ``f`` the finest, ``c`` the
    coarser configuration): rule 9's excess on the decay's shape. Noise independent from frame to frame lowers
    every correlation at a lag of a frame or more by one factor ``(⟨I⟩/(⟨I⟩+N₀))²`` set by the configuration's
    own SNR (physics.md §8); a coarser configuration averages more noise away and sits higher by it, which biases
    rule 9's raw excess low by the very noise that hides a slow region's decay; the ratio is free of it. NaN for
    a pair where either correlation at ``m₁`` is below :data:`SHAPE_FLOOR` (no decay shape to compare), and
    where every pair is; ``None`` when the model reads no such pair. ``columns`` and ``pooled`` as in
    :func:`mixed_footprint`."""
    lags = _rho_lin_columns(columns)
    fine = lags.get(str(finest), {})
    x = np.asarray(pooled, np.float64)
    per_pair = []
    for conf, cols in lags.items():
        common = sorted(set(cols) & set(fine))
        if conf == finest or len(common) < 2:
            continue
        f1, c1 = x[:, fine[common[0]]], x[:, cols[common[0]]]
        ok = (f1 >= SHAPE_FLOOR) & (c1 >= SHAPE_FLOOR)
        f1, c1 = np.where(ok, f1, 1.0), np.where(ok, c1, 1.0)
        shape = np.mean([x[:, fine[m]] / f1 - x[:, cols[m]] / c1 for m in common[1:]], axis=0)
        per_pair.append(np.where(ok, shape, np.nan))
    if not per_pair:
        return None
    stacked = np.array(per_pair)
    out = np.full(stacked.shape[1], np.nan)
    some = np.isfinite(stacked).any(axis=0)
    out[some] = np.nanmax(stacked[:, some], axis=0)
    return out


def footprint_mean(
    values: np.ndarray, idx: np.ndarray, shape: tuple[int, ...], window: int | Sequence[int]
) -> np.ndarray:
    """Rule 12: per classified pixel (``values`` one per pixel at the flat positions ``idx`` of a map of
    ``shape``), the mean of the finite ``values`` over the box centred on it (``window`` pixels per axis, or one
    width per axis; cut at the map's edges); NaN where the box holds none."""
    grid = np.full(int(np.prod(shape)), np.nan)
    grid[idx] = values
    grid = grid.reshape(shape)
    ok = np.isfinite(grid)
    width = _widths(window, len(shape))
    if len(width) != len(shape):
        raise ValueError(f"rule 12: {len(width)} window widths for a map of {len(shape)} axes {tuple(shape)}")
    total = _box_total(np.where(ok, grid, 0.0), width).reshape(-1)[idx]
    count = _box_count(ok, width).reshape(-1)[idx]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def mixed_shape(
    labels: np.ndarray,
    names: Sequence[str],
    idx: np.ndarray,
    shape: tuple[int, ...],
    window: int | Sequence[int],
    excess: np.ndarray | None,
    pool: int,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Rule 12 (module docstring): per classified pixel (``labels``, indices into ``names``, at the flat positions
    ``idx`` of a map of ``shape``), whether it holds a decision of :data:`MIXED_SHAPE_FLAGS` where the mean of
    ``excess`` (:func:`shape_excess`, one per classified pixel) over its finest footprint (``window``, rule 8's
    box: :func:`consensus_window` with the finest resolutions) exceeds :data:`MIXED_SHAPE_MIN`; and that mean.
    All False, and the mean ``None``, without ``excess`` or below a pooling window of
    :data:`MIXED_SHAPE_POOL_MIN`."""
    labels = np.asarray(labels)
    if excess is None or int(pool) < MIXED_SHAPE_POOL_MIN:
        return np.zeros(labels.shape, bool), None
    names = list(names)
    mean = footprint_mean(excess, idx, shape, window)
    flaggable = np.isin(labels, [names.index(m) for m in MIXED_SHAPE_FLAGS if m in names])
    return flaggable & (np.nan_to_num(mean, nan=-np.inf) > MIXED_SHAPE_MIN), mean
