"""FastSLAM 2.0 with Data Association Sampling: the FASTSLAM baseline and the HYBRID front-end.

References: Montemerlo, Thrun, Koller, Wegbreit, "FastSLAM 2.0" (IJCAI 2003) and Thrun,
Montemerlo et al., "FastSLAM: ... with unknown data association" (JMLR 2004), called FS2 below;
Brooks & Bailey 2008 (BB) for correspondence voting, existence and the Gaussian conversion.

State: one :class:`filters.fastslam_kernel.ParticleState` (issue 47), padded arrays over P
particles and a feature capacity C that doubles when needed: ``poses`` (P, 3), log weights (P,),
each feature component (mean x, y; covariance xx, xy, yy; existence; active; correspondence id,
BB (8), -1 = not yet a common feature) one (P, C) array. Each particle's active features are
packed in slots ``0 .. count_p - 1``. No Python loop runs over particles: the motion prediction
and a scan's whole work (the per-particle sequence in which each observation refines the proposal
the next one is associated with, then the votes, ids, clutter rate, culling, the weights, the
resampling test and the resampling) run compiled, the scan in one call
(:func:`filters.fastslam_kernel.update_iteration`; the reasons and the measured gains are given
there and in docs/PERFORMANCE.md); the random draws come from the generator of each purpose
(:mod:`filters.draws`) and are handed over in blocks. :meth:`FastSLAM2.run_iteration` runs a
whole iteration (prediction, compass, scan, pose moments and, given the frame the local map sits
in, the innovation ratio, the global pose and its NEES) in one compiled call
(:func:`filters.fastslam_kernel.iteration`, issue 47): what the env steps through.

One filter iteration
--------------------
``predict(u, dt)`` moves each particle's pose through the unicycle model and attaches the FS2
Gaussian proposal prior ``N(f(v^p, u), J_u Q J_u^T)`` (Q = ``odometry_noise.covariance(u, dt)``;
rank 2 at most, which the Kalman form below tolerates). ``update_heading`` (compass) and
``update(z)`` then refine that proposal; ``update`` finally samples the pose.

The scan likelihood is that of the usual detection model: each feature ``j`` is detected with
probability ``alpha e_j p_vis,j`` (``e_j`` its existence, ``p_vis,j`` the probability that it lies
inside the sensor's range, soft at the limit: :meth:`FastSLAM2._visibility`), an observation
comes from a detected feature, a not-yet-mapped landmark or clutter. Written in likelihood-ratio
form (as in multiple-hypothesis tracking), the weight of a particle is multiplied first by the
missed-detection product ``prod_j (1 - alpha e_j p_vis,j)`` over its features, and then, for
each observation ``z`` in turn, with the particle's current proposal ``N(x, P)``:

* gated features ``j`` (chi-square gate ``gate_chi2`` on ``S_j``) have the FS2 marginal
  likelihood ``N(nu_j; 0, S_j)``, ``S_j = G P G^T + H_m Sigma_j H_m^T + R`` (``G``, ``H_m`` the
  Jacobians of h w.r.t. pose and feature), times the ratio ``alpha e_j p_vis,j / (1 - alpha e_j
  p_vis,j)`` (detected rather than missed): ``L_j``;
* a *new feature* has ``L_new = alpha rho r`` (``rho`` = ``new_landmark_density_per_m2``, the
  expected density of not-yet-mapped landmarks; ``r`` converts an area density into one over
  range x bearing, since dx dy = r dr db);
* *clutter* has ``L_clutter = beta n_vis / (r_max fov)``: beta false alarms per visible landmark,
  uniform over range x bearing (BB 5.1). ``n_vis`` is the larger of the particle's expected
  number of visible features ``sum_j e_j p_vis,j`` and the scan's own estimate
  ``K / (alpha + beta)``;
* the association is sampled (DAS, FS2) among the gated features and one *unexplained*
  hypothesis of value ``L_new + L_clutter``, a feature already taken by an earlier observation of
  the same scan being excluded (one observation per landmark per scan). An unexplained
  observation always starts a new feature, whose existence ``L_new / (L_new + L_clutter)``
  (below) is the probability that it is not clutter: clutter is marginalised by the feature's
  existence, not sampled (next paragraph);
* the weight is multiplied by the FS2 importance factor ``sum_j L_j + L_new + L_clutter`` (the
  predictive likelihood of ``z``; the association and the pose are both drawn from their
  posteriors, so with the missed-detection product this is the exact importance ratio up to
  linearisation);
* if an existing feature was chosen, the proposal is refined in Kalman form
  ``x += P G^T S^-1 nu``, ``P -= P G^T S^-1 G P`` (FS2 proposal; well defined for singular P).

Why clutter is not a hypothesis of its own (issue #14): the new feature's existence already
carries the clutter probability, and its later misses cost ``1 - alpha e p_vis``, the marginal
over existence. Sampling *clutter* apart from *new feature* (the earlier rule, still available as
``sample_clutter=True``) counts that probability twice and makes the weights depend on the draw:
the few particles that drew *clutter* for a false alarm escape the miss factor (about 0.3 per
scan at BB's level 1) that all others pay, and take over the cloud within a few scans. At 500
particles this left a median of 6-7 ancestors (since the restart) per local map at levels 1-2
and made the local pose over-confident at fusion in 22 % of local maps (11 % with this rule, as
with known association; measured with the 0.999 clip,
docs/results/history.md, "Local maps at fusion with FastSLAM's 0.999 existence clip").

Why the missed-detection terms matter: without them a particle holding two features for one
landmark (created when it sampled *new feature* for a poorly predicted observation) collects the
likelihood of both and is systematically favoured by resampling, which in our tests made the
local maps markedly over-confident; with them such a particle pays for the feature it fails to
detect, and DAS is as consistent as known association.

*Deviation (documented):* FS2 with several observations per scan refines the proposal
observation by observation and samples the pose once from the refined proposal; we do the same,
so the pose is drawn after the scan's last association rather than after every observation
(drawing after each observation would freeze the pose for the later ones and waste their
information). Features are then updated by a standard EKF at the sampled pose and new features
initialised with :func:`filters.models.inverse_observe` and its Jacobian, exactly as FS2 does.

Existence (BB (11), :mod:`filters.existence`) per feature per particle: detection update for the
feature a particle associated (false-alarm probability of its gate), miss update with detection
probability ``alpha p_vis,j`` for every feature not associated by that particle (false-alarm
probability of the smallest gate, the one of R alone: P_fa is < 1e-3 there, so this changes
``1 - P_fa`` by < 0.1 %). A new feature starts at ``L_new / (L_new + L_clutter)``, the
probability that an observation not explained by the map came from a landmark. Existence is
clipped to ``max_existence`` and the detection probability to ``max_detection_probability`` so
that a feature can always be un-confirmed (with alpha = 1 a single miss would otherwise set it to
exactly 0, and a feature at p = 1 could never decay; it also keeps ``1 - alpha e p_vis`` >= 0.011).
Every ``cull_interval_steps`` updates, features with existence below ``cull_threshold`` are removed.

The clip is also a memory limit: at ``max_existence = 0.999`` (log-odds 6.9) the evidence of any
number of detections is forgotten after the misses that take log-odds 6.9 to 2.9 (p = 0.95). With a
small per-step detection probability that is short: on Victoria Park (alpha = 0.107 per 40 Hz step)
36 steps, 0.9 s, without a detection un-confirm any tree, and 1168 of 2004 local features, many
seen ten times or more, were below 0.95 at fusion and not fused (docs/results/real_data.md,
"Victoria Park"). The default 0.999 is kept for a long-lived map (FASTSLAM), where forgetting lets
a feature be un-confirmed when the evidence changes; a front-end whose map restarts every local map
has nothing to forget within BB's 10 s, and HYBRID builds it with :data:`LOCAL_MAP_MAX_EXISTENCE`
(1 - 1e-9, the float guard; BB gives no clip, and the EKF front-end of EKF sub-mapping has none).

Correspondences (BB 3.1) are voted per observation, with the weights after that observation
(:func:`filters.conversion.vote_scan`); all features modified or created by the
observation get the winner's id (a new id from the shared :class:`filters.types.FeatureIds` when
*new feature* wins), except where the particle already holds another feature with that id: ids
stay unique within a particle (:func:`filters.conversion.assign_correspondence_ids`). When
clutter wins (a known false alarm, or ``sample_clutter=True``), modified features keep their id
and created ones get -1 (no common feature yet).
``last_associations[k]`` is the winning id (-1 = clutter).

Systematic resampling runs when ``N_eff < resample_threshold * P``. Every particle remembers
its *lineage*, the index of its ancestor at the last restart (or start).

Conversion of a degenerate cloud (issue #14). BB (7) treats the particles as independent draws
from the posterior. Within a local map they are not: after about 25 resamplings in BB's 10 s the
500 particles descend from a median of 15 ancestors at the restart, and the pose and map errors
relative to the local map's start (fixed early in the local map, by the few surviving paths) are
represented by those few lineages only. Their spread then underestimates the posterior's and the
weighted mean carries a Monte Carlo error of its own: with known association, converted local
poses were over-confident at 11 % of fusions at 500 particles (6 % at 2000), with an empirical
mean square error 1.4-1.7 times the reported variance (measured with the 0.999 clip,
docs/results/history.md, "Local maps at fusion with FastSLAM's 0.999 existence clip").
:meth:`to_gaussian` and :meth:`pose` therefore add the lineage term of
:func:`filters.conversion.lineage_covariance` (the Chan & Lai 2013 estimate of the variance of
the particle mean, with the small-sample correction of a weighted variance from few lineages).
For the FASTSLAM baseline the lineages are those of the start: they coalesce into one within the
first minute, after which the term is zero (a single lineage says nothing about its own error).

That covariance is itself estimated from few lineages (a median of 7 effective ones at fusion),
so its inverse, the information the back-end fuses, is biased high, and the local-pose NEES is
heavy-tailed: local maps whose pose covariance has fewer than 10 effective degrees of freedom
were over the 95 % band at 10.5 % of fusions (nominal 2.5 %; scripts/archive/lineage_diagnosis.py).
With ``small_sample_correction`` (the default) the pose block is also scaled by
:func:`filters.conversion.small_sample_factor`, ``nu / (nu - 4)`` for ``nu`` effective degrees
of freedom, which makes that information unbiased (docs/RESULTS.md).

Use the methods in the order predict, [update_heading], update: a compass reading that arrives
after ``update`` (pose already sampled) can only reweight the particles.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit

from filters.conversion import (
    common_features,
    feature_means_xy,
    feature_moments,
    moment_match,
    pose_moments,
)
from filters.draws import as_draws
from filters.existence import CONFIRMED_PROBABILITY, validate_existence_model
from filters.fastslam_kernel import (
    FilterModel,
    GlobalFrame,
    IterationDraws,
    IterationInput,
    IterationResult,
    ParticleState,
    ScanDraws,
    call_draw_poses,
    call_heading_update,
    call_iteration,
    call_local_pose,
    call_propagate,
    call_systematic_resample,
    call_update_iteration,
    grow_state,
    new_outputs,
    new_state,
    normalise_weights,
)
from filters.models import ClutterModel, RangeBearingSensor
from filters.types import FeatureIds, GaussianMap, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

GATE_CHI2_999 = 13.815510557964274
"""chi2.ppf(0.999, 2): default validation gate (2-dof, 99.9 %)."""
LOCAL_MAP_MAX_EXISTENCE = 0.999999999
"""``max_existence`` of a front-end whose map restarts with every local map (HYBRID, via
:func:`slam_gym.systems.make_system`): the clip is then only the guard that keeps a feature
un-confirmable in floating point, not a memory limit (module doc, "Existence")."""
BB_LANDMARK_DENSITY = 35.0 / (120.0 * 120.0)
"""BB 5.2: 35 landmarks over 120 m x 120 m; the default density of not-yet-mapped landmarks."""
_TWO_PI = 2.0 * np.pi


_NO_KNOWN_IDS = np.zeros(0, dtype=np.int64)  # DAS (writable: one compiled signature for both)
_NO_SCAN = np.zeros((0, 2))
_NO_SCAN.flags.writeable = False  # as a stream's scans (read_only): one compiled signature
_NO_NORMALS = np.zeros((0, 3))
_NO_TRUTH = np.full(3, np.nan)
_NO_COLUMNS = np.zeros((0, 2), dtype=np.int64)
_NO_COLUMNS.flags.writeable = False  # as a back-end's feature_cols(): one compiled signature
_ZERO_Q = np.zeros((2, 2))


def read_only(a: np.ndarray) -> np.ndarray:
    """``a`` as a read-only array (a read-only view of a writable one): numba compiles a
    function once per argument type, and a read-only array is a type of its own, so the arrays
    that reach the compiled iteration read-only from some callers (a stream's scans, a
    back-end's feature columns) are made so for all (a copied env's are writable)."""
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


def own_frame() -> GlobalFrame:
    """The frame of a front-end alone: its origin at zero, known exactly, no global features."""
    return GlobalFrame(np.zeros(3), np.zeros((3, 3)), np.zeros(0), np.zeros((0, 0)),
                       _NO_COLUMNS, 0.0)


_NOT_FINITE, _NEGATIVE_RANGE = 1, 2


@njit(cache=True)
def _scan_problem(z):
    """0 for a valid scan (K, 2); ``_NOT_FINITE`` if an entry is not finite, else
    ``_NEGATIVE_RANGE`` if a range is negative (one compiled pass: the check runs every step)."""
    for k in range(z.shape[0]):
        for i in range(2):
            if not np.isfinite(z[k, i]):
                return _NOT_FINITE
    for k in range(z.shape[0]):
        if not z[k, 0] >= 0.0:
            return _NEGATIVE_RANGE
    return 0


def _checked_motion(u, dt):
    """``(u, dt)`` as a finite ``(v, omega)`` array and a float in [0, 1e6]; ``ValueError``
    naming the argument otherwise."""
    u = np.asarray(u, dtype=float)
    require(u.shape == (2,) and math.isfinite(u[0]) and math.isfinite(u[1]), "u", u,
            "a finite (v, omega)")
    if not (type(dt) is float and 0.0 <= dt <= 1e6):  # a stream's dt passes in one test
        check_range("dt", dt, 0.0, 1e6)
    return u, float(dt)


def _checked_heading(theta, std_rad):
    """A compass reading ``(theta, std_rad)`` as ``(theta, variance)``, validated."""
    theta, std_rad = float(theta), float(std_rad)
    check_range("theta", theta, -1e3, 1e3)
    check_range("std_rad", std_rad, 0.0, 10.0, low_open=True)
    return theta, std_rad**2


class FastSLAM2:
    """FastSLAM 2.0 with Data Association Sampling, existence and correspondence voting.

    Parameters (keyword options are validated; a bad value raises ``ValueError``):
    sensor, clutter, odometry_noise: the models (docs/ARCHITECTURE.md, "Filter interface"). rng:
    where every random number comes from: a ``numpy.random.Generator`` (one stream in order of
    use) or a :class:`filters.draws.SynchronisedDraws` (numbers keyed by iteration and purpose:
    common random numbers across policies), held as :attr:`draws`. ids: shared
    :class:`FeatureIds` (new if None).
    n_particles: P. initial_pose: the pose of every particle at start (zero uncertainty).
    resample_threshold: resample when N_eff < threshold * P. gate_chi2: association gate.
    new_landmark_density_per_m2: rho of ``L_new``. max_detection_probability, max_existence,
    cull_threshold, cull_interval_steps: existence bookkeeping (module doc).
    feature_budget: the front-end's feature budget (``local_map_budget_ratio``).
    clutter_rate_memory: observations over which ``clutter_rate`` is averaged (exponential).
    initial_capacity: initial feature slots per particle (doubles when full; back to this at
        every restart).
    existence_model: ``"gate"`` or ``"bb"``, the reading of BB (11) (:mod:`filters.existence`).
    sample_clutter: draw *clutter* and *new feature* as two DAS hypotheses (the earlier rule,
    kept for comparison; over-confident local maps, docs/RESULTS.md) instead of one new feature
    whose existence carries the clutter probability (module doc; the default).
    lineage_correction: add the lineage term of :func:`filters.conversion.lineage_covariance`
    to the Gaussians of :meth:`pose` and :meth:`to_gaussian` (module doc; the default; False
    gives BB (7) alone).
    small_sample_correction: with ``lineage_correction``, scale the pose block by
    :func:`filters.conversion.small_sample_factor` (module doc; the default).

    Storage is structure-of-arrays: each feature component (mean x, y; covariance xx, xy, yy;
    existence; active; correspondence id) is one (P, C) array, so gathers and scatters by flat
    index ``p * C + slot`` are cheap; the properties ``means`` (P, C, 2), ``covs`` (P, C, 2, 2),
    ``existence``, ``active`` and ``correspondence_ids`` (P, C) assemble the padded arrays.
    """

    def __init__(
        self,
        sensor: RangeBearingSensor,
        clutter: ClutterModel,
        odometry_noise,
        rng: np.random.Generator,
        ids: FeatureIds | None = None,
        *,
        n_particles: int = 500,
        initial_pose=(0.0, 0.0, 0.0),
        resample_threshold: float = 0.5,
        gate_chi2: float = GATE_CHI2_999,
        new_landmark_density_per_m2: float = BB_LANDMARK_DENSITY,
        max_detection_probability: float = 0.99,
        max_existence: float = 0.999,
        cull_threshold: float = 0.01,
        cull_interval_steps: int = 10,
        feature_budget: int = 100,
        clutter_rate_memory: float = 100.0,
        initial_capacity: int = 16,
        existence_model: str = "gate",
        sample_clutter: bool = False,
        lineage_correction: bool = True,
        small_sample_correction: bool = True,
    ):
        require(isinstance(sensor, RangeBearingSensor), "sensor", sensor, "a RangeBearingSensor")
        require(isinstance(clutter, ClutterModel), "clutter", clutter, "a ClutterModel")
        require(
            hasattr(odometry_noise, "covariance"),
            "odometry_noise",
            odometry_noise,
            "an object with .covariance(u, dt)",
        )
        draws = as_draws(rng)  # ValueError naming rng for anything else
        require(ids is None or isinstance(ids, FeatureIds), "ids", ids, "a FeatureIds or None")
        require(
            isinstance(n_particles, (int, np.integer)) and 1 <= n_particles <= 1_000_000,
            "n_particles",
            n_particles,
            "an integer in [1, 1000000]",
        )
        pose0 = np.asarray(initial_pose, dtype=float)
        require(
            pose0.shape == (3,) and bool(np.all(np.isfinite(pose0))),
            "initial_pose",
            initial_pose,
            "a finite (x, y, theta)",
        )
        check_range("resample_threshold", resample_threshold, 0.0, 1.0)
        check_range("gate_chi2", gate_chi2, 0.0, 1000.0, low_open=True)
        check_range(
            "new_landmark_density_per_m2", new_landmark_density_per_m2, 0.0, 100.0, low_open=True
        )
        check_range("max_detection_probability", max_detection_probability, 0.0, 1.0, low_open=True)
        check_range("max_existence", max_existence, 0.5, 1.0)
        check_range("cull_threshold", cull_threshold, 0.0, 0.5)
        require(
            isinstance(cull_interval_steps, (int, np.integer)) and cull_interval_steps >= 1,
            "cull_interval_steps",
            cull_interval_steps,
            "a positive integer",
        )
        require(
            isinstance(feature_budget, (int, np.integer)) and feature_budget >= 1,
            "feature_budget",
            feature_budget,
            "a positive integer",
        )
        check_range("clutter_rate_memory", clutter_rate_memory, 1.0, 1e9)
        require(
            isinstance(sample_clutter, (bool, np.bool_)),
            "sample_clutter",
            sample_clutter,
            "a bool",
        )
        for name, flag in (("lineage_correction", lineage_correction),
                           ("small_sample_correction", small_sample_correction)):
            require(isinstance(flag, (bool, np.bool_)), name, flag, "a bool")
        require(
            isinstance(initial_capacity, (int, np.integer)) and 1 <= initial_capacity <= 1e6,
            "initial_capacity",
            initial_capacity,
            "an integer in [1, 1000000]",
        )

        self.sensor = sensor
        self.clutter = clutter
        self.odometry_noise = odometry_noise
        self.draws = draws
        self.ids = ids if ids is not None else FeatureIds()
        self.n_particles = int(n_particles)
        self.resample_threshold = float(resample_threshold)
        self.gate_chi2 = float(gate_chi2)
        self.new_landmark_density = float(new_landmark_density_per_m2)
        self.detection_probability = min(clutter.alpha, float(max_detection_probability))
        self.max_existence = float(max_existence)
        self.cull_threshold = float(cull_threshold)
        self.cull_interval_steps = int(cull_interval_steps)
        self.feature_budget = int(feature_budget)
        self.clutter_rate_memory = float(clutter_rate_memory)
        R = np.asarray(sensor.R, dtype=float)
        require(R[0, 1] == 0.0 and R[1, 0] == 0.0, "sensor", sensor, "a diagonal R")
        self._model = FilterModel(
            r_var=float(R[0, 0]),
            b_var=float(R[1, 1]),
            detection_probability=float(self.detection_probability),
            beta=float(clutter.beta),
            gate_chi2=self.gate_chi2,
            max_range_m=float(sensor.max_range_m),
            fov_rad=float(sensor.fov_rad),
            range_std_m=float(sensor.range_std_m),
            bearing_std_rad=float(sensor.bearing_std_rad),
            new_landmark_density=self.new_landmark_density,
            max_existence=self.max_existence,
            literal_beta=validate_existence_model(existence_model) == "bb",
            sample_clutter=bool(sample_clutter),
            clutter_decay=1.0 - 1.0 / self.clutter_rate_memory,
            cull_threshold=self.cull_threshold,
            resample_threshold=self.resample_threshold,
        )
        self.existence_model = existence_model
        self._initial_capacity = int(initial_capacity)
        self._capacity = self._initial_capacity
        self._state = None
        self._spare = None
        self.lineage_correction = bool(lineage_correction)
        self.small_sample_correction = bool(small_sample_correction)
        self._reset(pose0)

    # ------------------------------------------------------------------ state
    def _reset(self, pose0):
        self._outputs = {}
        P = self.n_particles
        # the clutter rate's sums belong to the filter and outlive the local maps
        sums = np.zeros(2) if self._state is None else self._state.clutter_sums
        self._state = new_state(P, self._capacity, pose0)._replace(clutter_sums=sums)
        self._pending = False
        self._count_bound = None  # an upper bound of the feature counts (run_iteration)
        self._steps = 0
        self._age_s = 0.0
        self._distance_m = 0.0
        self._ess_ratio = 1.0
        self._vote_margins = np.zeros(0)
        self._label_cid: dict[int, int] = {}
        self.last_associations = np.zeros(0, dtype=np.int64)
        self.last_votes = np.zeros((0, P), dtype=np.int64)
        """Per observation of the last update, each particle's vote (common id, CLUTTER_VOTE or
        NEW_VOTE; a vote for a feature without id counts as NEW_VOTE), shape (K, P)."""

    def _grow(self, needed):
        """Double the feature capacity until ``needed`` slots fit."""
        C = self._capacity
        while C < needed:
            C *= 2
        if C == self._capacity:
            return
        logger.debug("FastSLAM2: feature capacity %d -> %d", self._capacity, C)
        self._state = grow_state(self._state, C)
        self._capacity = C

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def poses(self) -> np.ndarray:
        """Particle poses (P, 3) (proposal means between ``predict`` and ``update``)."""
        return self._state.poses.copy()

    @property
    def weights(self) -> np.ndarray:
        """Normalised particle weights (P,)."""
        return self._weights().copy()

    def _weights(self) -> np.ndarray:
        """The normalised weights of the current state, computed once per state (read-only)."""
        if "weights" not in self._outputs:
            w = np.empty(self.n_particles)
            normalise_weights(self._state.logw, w, 0.0)
            self._outputs["weights"] = w
        return self._outputs["weights"]

    @property
    def means(self) -> np.ndarray:
        """Feature means (P, C, 2)."""
        return np.stack([self._state.mx, self._state.my], axis=-1)

    @property
    def covs(self) -> np.ndarray:
        """Feature covariances (P, C, 2, 2)."""
        s = self._state
        row0 = np.stack([s.sxx, s.sxy], axis=-1)
        row1 = np.stack([s.sxy, s.syy], axis=-1)
        return np.stack([row0, row1], axis=-2)

    @property
    def existence(self) -> np.ndarray:
        return self._state.ex.copy()

    @property
    def active(self) -> np.ndarray:
        return self._state.active.copy()

    @property
    def correspondence_ids(self) -> np.ndarray:
        return self._state.cid.copy()

    @property
    def lineages(self) -> np.ndarray:
        """Each particle's ancestor at the last restart (or start): the index it had there."""
        return self._state.lineage.copy()

    # ------------------------------------------------------------------ prediction
    def predict(self, u, dt):
        """Motion prediction: proposal prior N(f(v, u), J_u Q J_u^T) for every particle (FS2)."""
        u, dt = _checked_motion(u, dt)
        if dt == 0.0:  # no time elapsed, no motion (e.g. a scan at the start pose)
            return
        if self._pending:
            self._sample_pending()
            self._maybe_resample("resample_after_pending")
        call_propagate(self._state, float(u[0]), float(u[1]), dt, self._motion_noise(u, dt))
        self._pending = True
        self._moved(u, dt)
        # the poses moved, the weights did not: only their normalisation outlives the prediction
        self._outputs = {k: v for k, v in self._outputs.items() if k == "weights"}

    def _motion_noise(self, u, dt) -> np.ndarray:
        """Q = ``odometry_noise.covariance(u, dt)`` (2, 2), contiguous."""
        return np.ascontiguousarray(self.odometry_noise.covariance(u, dt), dtype=float)

    def _moved(self, u, dt) -> None:
        self._age_s += dt
        self._distance_m += abs(float(u[0])) * dt

    def _sample_pending(self):
        """Draw every particle's pose from its proposal N(x, P) (FS2)."""
        normals = self.draws.generator("pending_pose").standard_normal((self.n_particles, 3))
        call_draw_poses(self._state, normals)
        self._pending = False

    def update_heading(self, theta, std_rad):
        """Compass: a direct observation of each particle's heading with std ``std_rad``.

        Before ``update`` (proposal pending) it refines the FS2 proposal with the scalar Kalman
        update ``x += P e3 nu / s``, ``P -= P e3 e3^T P / s``, ``s = P_tt + std^2``, and weights by
        ``N(nu; 0, s)``; after ``update`` it can only weight by ``N(theta - theta^p; 0, std^2)``.
        """
        theta, var = _checked_heading(theta, std_rad)
        self._outputs = {}
        call_heading_update(self._state, theta, var, self._pending)
        if not self._pending:
            self._maybe_resample("resample_after_heading")

    # ------------------------------------------------------------------ observation update
    def update(self, z, associations=None):
        """Process one scan ``z`` (K, 2) of range-bearing observations (module docstring).

        ``associations`` (K,) optional, for comparison and tests: known landmark labels (any
        non-negative integers, e.g. the simulator's truth) or -1 for a known false alarm. Each
        label is then tied to one common id and every particle uses that association (no
        sampling, no vote); the weight factor is the FS2 marginal likelihood ``N(nu; 0, S)``
        times the detection ratio of the feature (``L_new`` for a particle lacking it), after
        the missed-detection product (module docstring).

        The work runs in one compiled call, :func:`filters.fastslam_kernel.update_iteration`;
        the random numbers (one uniform per observation and particle for DAS, three normals per
        particle for the pose draw, the resampling's uniform) come from :attr:`draws`, roles
        ``association``, ``scan_pose`` and ``resample_after_scan`` (drawn whether or not the
        weights call for resampling: the kernel decides).
        """
        z, known_cids = self._checked_scan(z, associations)
        K, P = len(z), self.n_particles
        self._grow(int(self._state.count.max()) + K)
        self._count_bound = None  # (run_iteration's bound: read the counts again)
        state = self._state
        if not self._pending:
            state.prop_cov[:] = 0.0
        if associations is None:
            uniforms = self.draws.generator("association").random((K, P))
        else:
            uniforms = np.zeros((0, P))
        normals = self.draws.generator("scan_pose").standard_normal((P, 3))
        offset = self.draws.generator("resample_after_scan").random()
        weights = np.empty(P)
        out = new_outputs(K, P)
        spare = self._spare_state()
        # one compiled call (filters.fastslam_kernel.update_iteration): the scan, then the
        # correspondence votes (BB 3.1), one per observation with the weights after it, fresh
        # ids in observation order for the observations *new feature* wins, the clutter rate,
        # every feature modified or created by an observation taking its winner's id unless its
        # particle holds another feature with that id (clutter winning leaves modified features
        # their id and created ones without one: filters.conversion.assign_correspondence_ids),
        # culling every cull_interval_steps, the weights and the resampling
        result = call_update_iteration(
            state, z, known_cids, ScanDraws(uniforms, normals, offset), self._model,
            out, self.ids.next_id,
            (self._steps + 1) % self.cull_interval_steps == 0, weights, spare,
        )
        self._pending = False
        self._ess_ratio = float(result.ess_ratio)
        if result.resampled:
            self._take_spare()
        self._scanned(result.winners, result.margins, result.n_new_ids, out)
        self._outputs = {"weights": weights}

    def _scanned(self, winners, margins, n_new_ids, out) -> None:
        """The filter's records of a scan the kernel processed."""
        if n_new_ids:
            self.ids.new(n_new_ids)  # the ids the kernel gave, now taken from the source
        self._steps += 1
        self.last_associations = winners
        self.last_votes = out.votes
        self._vote_margins = margins

    def _checked_scan(self, z, associations):
        """``z`` as a valid (K, 2) array and the common ids of the known ``associations``
        (empty for DAS); ``ValueError`` naming the argument otherwise."""
        if not (type(z) is np.ndarray and z.dtype == np.float64 and z.ndim == 2
                and z.shape[1] == 2):  # a stream's scan is one already
            z = np.asarray(z, dtype=float).reshape(-1, 2) if np.size(z) else np.zeros((0, 2))
        problem = _scan_problem(z) if len(z) else 0
        require(problem != _NOT_FINITE, "z", z, "finite range-bearing pairs (K, 2)")
        require(problem != _NEGATIVE_RANGE, "z", z, "ranges >= 0")
        if associations is None:
            return z, _NO_KNOWN_IDS
        known = np.asarray(associations, dtype=np.int64).reshape(-1)
        require(len(known) == len(z), "associations", associations, f"length {len(z)} like z")
        require(bool(np.all(known >= -1)), "associations", associations, "labels >= -1")
        return z, np.array([self._label_id(int(label)) for label in known], dtype=np.int64)

    # ------------------------------------------------------------------ the whole iteration
    def iterate(self, u, dt, z=None, *, heading=None, truth_pose=None):
        """One filter iteration of the filter alone (:meth:`run_iteration` in its own frame):
        ``(mean, cov, nees, position_error_m)`` of the pose, as
        :meth:`filters.submap.SubmapSLAM.iterate` returns them."""
        result = self.run_iteration(u, dt, z, heading=heading, truth_pose=truth_pose)
        return result.mean.copy(), result.cov.copy(), float(result.nees), float(
            result.position_error_m)

    def run_iteration(self, u, dt, z=None, *, heading=None, associations=None, frame=None,
                      truth_pose=None) -> IterationResult:
        """One filter iteration in one compiled call (:func:`filters.fastslam_kernel.iteration`):
        what ``predict(u, dt)``, ``update_heading(*heading)`` (``heading`` = ``(theta,
        std_rad)`` in the local frame, or None), ``update(z, associations)`` (``z`` None: no
        scan) and :meth:`pose` do, and besides, with the :class:`GlobalFrame` ``frame`` (None:
        :func:`own_frame`) the local map sits in, CM's innovation ratio of the scan against the
        prior and the global pose, and that pose's NEES and position error against
        ``truth_pose`` (None: NaN). Returns the :class:`IterationResult`.

        The random numbers are those of the separate calls, each role's block drawn from its
        generator before the call (:meth:`_iteration_draws`): with a synchronised source the
        same numbers; with one ordered stream another order of the same distribution (every
        resampling uniform the iteration might use is drawn).
        """
        u, dt = _checked_motion(u, dt)
        scanned = z is not None
        z, known_cids = self._checked_scan(z, associations) if scanned else (_NO_SCAN,
                                                                             _NO_KNOWN_IDS)
        theta, var = _checked_heading(*heading) if heading is not None else (np.nan, np.nan)
        pending_draw = self._pending and dt > 0.0
        pending = self._pending or dt > 0.0  # the proposal is pending after the prediction
        K = len(z)
        if K:  # a scan of K observations may create K features in a particle
            # an upper bound of the particles' feature counts (they rise only by a scan's
            # observations): the counts are read only when the bound would not fit
            bound = self.__dict__.get("_count_bound")
            if bound is None or bound + K > self._capacity:
                bound = int(self._state.count.max())
                self._grow(bound + K)
            self._count_bound = bound + K
        draws = self._iteration_draws(K if scanned and associations is None else 0,
                                      pending_draw, heading is not None and not pending, scanned)
        step = IterationInput(float(u[0]), float(u[1]), dt,
                              self._motion_noise(u, dt) if dt > 0.0 else _ZERO_Q, theta, var,
                              scanned, read_only(z), known_cids)
        truth = _NO_TRUTH if truth_pose is None else np.asarray(truth_pose, dtype=float)
        flags = (self._pending, self.ids.next_id, (self._steps + 1) % self.cull_interval_steps == 0,
                 self.lineage_correction, self.small_sample_correction)
        out = new_outputs(K, self.n_particles)
        weights = np.empty(self.n_particles)
        result = call_iteration(self._state, self._spare_state(), step, draws, self._model,
                                own_frame() if frame is None else frame, truth, flags, out,
                                weights)
        if result.swaps % 2:
            self._take_spare()
        if dt > 0.0:
            self._moved(u, dt)
        if not math.isnan(result.ess_ratio):
            self._ess_ratio = float(result.ess_ratio)
        if scanned:
            self._scanned(result.winners, result.margins, result.n_new_ids, out)
        self._pending = pending and not scanned
        key = ("pose", self.lineage_correction, self.small_sample_correction)
        self._outputs = {"weights": weights, key: (result.local_mean, result.local_cov)}
        return result

    def _iteration_draws(self, n_uniform_rows, pending, heading, scanned) -> IterationDraws:
        """The iteration's random numbers (:class:`filters.fastslam_kernel.IterationDraws`), each
        role's block from its generator (:mod:`filters.draws`), drawn where the iteration may use
        it: the pending pose and its resampling's uniform when a proposal is pending; the heading
        resampling's uniform after a compass reading that comes after the pose draw; the DAS
        uniforms (``n_uniform_rows`` rows: none under known association), the scan's pose draw
        and its resampling uniform with a scan."""
        generator, P = self.draws.generator, self.n_particles
        return IterationDraws(
            pending_normals=(generator("pending_pose").standard_normal((P, 3)) if pending
                             else _NO_NORMALS),
            pending_offset=generator("resample_after_pending").random() if pending else 0.0,
            heading_offset=generator("resample_after_heading").random() if heading else 0.0,
            uniforms=(generator("association").random((n_uniform_rows, P)) if n_uniform_rows
                      else np.zeros((0, P))),
            normals=generator("scan_pose").standard_normal((P, 3)) if scanned else _NO_NORMALS,
            resample_offset=generator("resample_after_scan").random() if scanned else 0.0,
        )

    @property
    def rng(self) -> np.random.Generator:
        """The one generator of an ordered source (:class:`filters.draws.OrderedDraws`);
        a synchronised source has none (``AttributeError``)."""
        return self.draws.rng

    def _label_id(self, label):
        """The common id tied to a known landmark label (-1 for a known false alarm)."""
        if label < 0:
            return -1
        if label not in self._label_cid:
            self._label_cid[label] = int(self.ids.new(1)[0])
        return self._label_cid[label]

    def _spare_state(self) -> ParticleState:
        """A state of the current shapes for the resampling to gather into (it shares the
        clutter sums, which belong to the filter, not to the particles): kept from one
        resampling to the next (:meth:`_take_spare` swaps the two), made anew when the shapes
        changed."""
        state, spare = self._state, self._spare
        if (spare is None or spare.clutter_sums is not state.clutter_sums
                or spare.mx.shape != state.mx.shape):
            spare = ParticleState(*(np.empty_like(a) for a in state))._replace(
                clutter_sums=state.clutter_sums)
            self._spare = spare
        return spare

    def __getstate__(self):
        """What a copy or a pickle keeps: everything but the resampling's spare state (work
        space, made anew when needed), so a copy of the filter costs what it did before."""
        state = self.__dict__.copy()
        state["_spare"] = None
        return state

    def _take_spare(self) -> None:
        """The spare, into which a resampling gathered the particles, becomes the state."""
        self._state, self._spare = self._spare, self._state

    def _maybe_resample(self, role: str):
        """Systematic resampling when N_eff < resample_threshold * P (compiled:
        :func:`filters.fastslam_kernel.normalise_weights` and
        :func:`~filters.fastslam_kernel.systematic_resample`), its uniform drawn from
        :attr:`draws` with ``role`` only when it resamples (a scan's resampling runs inside
        :func:`~filters.fastslam_kernel.update_iteration`)."""
        weights = np.empty(self.n_particles)
        resample, ess_ratio = normalise_weights(self._state.logw, weights,
                                                self.resample_threshold)
        self._ess_ratio = float(ess_ratio)
        if resample:
            offset = self.draws.generator(role).random()
            call_systematic_resample(self._state, weights, offset, self._spare_state())
            self._take_spare()
            self._outputs = {}
        self._outputs["weights"] = weights

    # ------------------------------------------------------------------ outputs
    def _pose_covs(self):
        if not self._pending:
            return None
        prop_cov = self._state.prop_cov
        return 0.5 * (prop_cov + np.swapaxes(prop_cov, 1, 2))

    def _lineages(self):
        return self._state.lineage if self.lineage_correction else None

    def pose(self):
        """Weighted mean (circular mean heading) and covariance of the particle poses (with the
        lineage term and the small-sample factor of the module doc unless
        ``lineage_correction`` / ``small_sample_correction`` is False)."""
        key = ("pose", self.lineage_correction, self.small_sample_correction)  # flags may change
        if key not in self._outputs:
            # the compiled moments straight away: the filter's own arrays need no validation
            # (lineages are ancestor indices in [0, P)); pose_moments checks external input
            self._outputs[key] = call_local_pose(self._state, self._weights(), self._pending,
                                                 self.lineage_correction,
                                                 self.small_sample_correction)
        mean, cov = self._outputs[key]
        return mean.copy(), cov.copy()

    def _common(self):
        if "common" not in self._outputs:
            s = self._state
            self._outputs["common"] = common_features(
                self.weights, s.cid, s.active, s.ex, tie_break=s.sxx + s.syy
            )
        return self._outputs["common"]

    def landmarks(self) -> LandmarkEstimate:
        """The common features (BB 3.2) with per-feature moments and weighted existence."""
        common = self._common()
        if len(common) == 0:
            return LandmarkEstimate.empty()
        means, covs = feature_moments(self.weights, self.means, self.covs, common.slots)
        return LandmarkEstimate(common.ids.copy(), means, covs, common.existence.copy())

    def landmark_count(self) -> int:
        """``len(self.landmarks())``: the number of common features, without their moments."""
        return len(self._common())

    def landmark_means(self):
        """``(ids, means, existence)`` of :meth:`landmarks` without the covariances (the same
        numbers): what map scoring needs, at a fraction of the cost."""
        common = self._common()
        if len(common) == 0:
            empty = LandmarkEstimate.empty()
            return empty.ids, empty.means, empty.existence
        means = feature_means_xy(self._weights(), self._state.mx, self._state.my, common.slots)
        return common.ids.copy(), means, common.existence.copy()

    def to_gaussian(self) -> GaussianMap:
        """BB 3.2: [pose, features with p(exists) > 0.95] as one SPD Gaussian (local frame).

        With ``lineage_correction`` (the default) the covariance also carries the Monte Carlo
        error of a cloud descended from few particles of the restart, as :meth:`pose` does
        (:func:`filters.conversion.lineage_covariance`; module doc), and with
        ``small_sample_correction`` its pose block is scaled as :meth:`pose`'s is."""
        return moment_match(
            self._state.poses,
            self.weights,
            self.means,
            self.covs,
            self._common(),
            min_existence=CONFIRMED_PROBABILITY,
            pose_covs=self._pose_covs(),
            lineages=self._lineages(),
            small_sample=self.small_sample_correction,
        )

    def restart(self):
        """New local map (BB 4): all particles at the origin, zero uncertainty, no features.

        The feature slots shrink back to ``initial_capacity``: the map is empty, and every
        whole-cloud copy (resampling, culling, the common set) scales with the slots held."""
        self._capacity = self._initial_capacity
        self._reset(np.zeros(3))

    def local_statistics(self) -> dict[str, float]:
        """Local interface features of docs/ARCHITECTURE.md.

        ``ess_ratio`` is N_eff / P of the weights before the latest resampling decision (after a
        resampling the weights are uniform, which would always read 1). The particle spreads are
        those of the cloud (BB (7)), without the lineage term of :meth:`pose`.
        """
        common = self._common()
        clutter_num, clutter_den = self._state.clutter_sums
        # the cloud itself
        _, cov = pose_moments(self._state.poses, self._weights(), self._pose_covs())
        n_features = len(common)
        return {
            "local_map_age_s": float(self._age_s),
            "local_map_distance_m": float(self._distance_m),
            "ess_ratio": float(self._ess_ratio),
            "particle_position_spread_m": float(np.sqrt(max(cov[0, 0] + cov[1, 1], 0.0))),
            "particle_heading_spread_rad": float(np.sqrt(max(cov[2, 2], 0.0))),
            "local_feature_count": float(n_features),
            "local_confirmed_count": float(np.sum(common.existence > CONFIRMED_PROBABILITY)),
            "vote_margin": float(self._vote_margins.min()) if len(self._vote_margins) else 1.0,
            "clutter_rate": float(clutter_num / clutter_den)
            if clutter_den > 0.0
            else 0.0,
            "local_map_budget_ratio": float(n_features / self.feature_budget),
        }
