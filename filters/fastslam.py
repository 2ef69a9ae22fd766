"""FastSLAM 2.0 with Data Association Sampling: the FASTSLAM baseline and the HYBRID front-end.

References: Montemerlo, Thrun, Koller, Wegbreit, "FastSLAM 2.0" (IJCAI 2003) and Thrun,
Montemerlo et al., "FastSLAM: ... with unknown data association" (JMLR 2004), called FS2 below;
Brooks & Bailey 2008 (BB) for correspondence voting, existence and the Gaussian conversion.

State (padded arrays over P particles and a feature capacity C that doubles when needed):
``poses`` (P, 3), ``weights`` (P,), feature ``means`` (P, C, 2), ``covs`` (P, C, 2, 2),
``existence`` (P, C), ``active`` (P, C) and ``correspondence_ids`` (P, C) (BB (8); -1 = not yet a
common feature). Each particle's active features are packed in slots ``0 .. count_p - 1``. No
Python loop runs over particles; loops run over the few observations of a step.

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
* the association is sampled in proportion to these (DAS, FS2), a feature already taken by an
  earlier observation of the same scan being excluded (one observation per landmark per scan);
* the weight is multiplied by the FS2 importance factor ``sum_j L_j + L_new + L_clutter`` (the
  predictive likelihood of ``z``; the association and the pose are both drawn from their
  posteriors, so with the missed-detection product this is the exact importance ratio up to
  linearisation);
* if an existing feature was chosen, the proposal is refined in Kalman form
  ``x += P G^T S^-1 nu``, ``P -= P G^T S^-1 G P`` (FS2 proposal; well defined for singular P).

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

Correspondences (BB 3.1) are voted per observation with
:func:`filters.conversion.correspondence_vote`; all features modified or created by the
observation get the winner's id (a new id from the shared :class:`filters.types.FeatureIds` when
*new feature* wins). When clutter wins, modified features keep their id and created ones get -1
(no common feature yet). ``last_associations[k]`` is the winning id (-1 = clutter).

Systematic resampling runs when ``N_eff < resample_threshold * P``.

Use the methods in the order predict, [update_heading], update: a compass reading that arrives
after ``update`` (pose already sampled) can only reweight the particles.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.special import ndtr

from filters.conversion import (
    CLUTTER_VOTE,
    NEW_VOTE,
    common_features,
    correspondence_vote,
    feature_moments,
    moment_match,
    pose_moments,
)
from filters.existence import (
    CONFIRMED_PROBABILITY,
    detection_update,
    false_alarm_in_gate_probability,
    gate_area,
    miss_update,
)
from filters.geometry import wrap_angle
from filters.models import (
    ClutterModel,
    RangeBearingSensor,
    inverse_observe,
    inverse_observe_jacobians,
    motion,
    motion_jacobians,
)
from filters.types import FeatureIds, GaussianMap, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

GATE_CHI2_999 = 13.815510557964274
"""chi2.ppf(0.999, 2): default validation gate (2-dof, 99.9 %)."""
BB_LANDMARK_DENSITY = 35.0 / (120.0 * 120.0)
"""BB 5.2: 35 landmarks over 120 m x 120 m; the default density of not-yet-mapped landmarks."""
_TWO_PI = 2.0 * np.pi


def _sample_gaussian3(cov, normals):
    """Samples ``L sqrt(D) n`` (P, 3) for PSD covariances (P, 3, 3) via a guarded LDL^T.

    Works for singular covariances (FS2 proposals from rank-2 motion noise): a pivot that is
    zero up to round-off (relative 1e-12 of the trace) gets a zero column.
    """
    tiny = 1e-12 * np.maximum(np.trace(cov, axis1=1, axis2=2), 1e-300)
    d0 = cov[:, 0, 0]
    ok0 = d0 > tiny
    s0 = np.where(ok0, d0, 1.0)
    l10 = np.where(ok0, cov[:, 1, 0] / s0, 0.0)
    l20 = np.where(ok0, cov[:, 2, 0] / s0, 0.0)
    d1 = cov[:, 1, 1] - l10 * l10 * d0
    ok1 = d1 > tiny
    l21 = np.where(ok1, (cov[:, 2, 1] - l20 * l10 * d0) / np.where(ok1, d1, 1.0), 0.0)
    d2 = cov[:, 2, 2] - l20 * l20 * d0 - l21 * l21 * d1
    y0 = np.sqrt(np.where(ok0, d0, 0.0)) * normals[:, 0]
    y1 = np.sqrt(np.where(ok1, d1, 0.0)) * normals[:, 1]
    y2 = np.sqrt(np.where(d2 > tiny, d2, 0.0)) * normals[:, 2]
    return np.stack([y0, l10 * y0 + y1, l20 * y0 + l21 * y1 + y2], axis=1)


def _motion_noise_cov(poses, u, dt, Q):
    """``J_u Q J_u^T`` (P, 3, 3) for every particle, J_u the control Jacobian of
    :func:`filters.models.motion` (broadcast over the particles' poses)."""
    _, J_u = motion_jacobians(poses, u, dt)
    return J_u @ Q @ np.swapaxes(J_u, -1, -2)


def _feature_ekf(pose, mx, my, sxx, sxy, syy, z, R):
    """EKF update of features (n,) components by observations z (n, 2) from known poses (n, 3),
    elementwise: ``K = Sigma H^T S^-1``, ``m += K nu``, ``Sigma -= K H Sigma`` (the FS2 map
    update at the sampled pose). Returns the updated ``(mx, my, sxx, sxy, syy)``."""
    dx = mx - pose[:, 0]
    dy = my - pose[:, 1]
    q = np.maximum(dx * dx + dy * dy, 1e-12)
    r = np.sqrt(q)
    nu_r = z[:, 0] - r
    nu_b = wrap_angle(z[:, 1] - np.arctan2(dy, dx) + pose[:, 2])
    h00, h01, h10, h11 = dx / r, dy / r, -dy / q, dx / q
    t00 = h00 * sxx + h01 * sxy  # H Sigma
    t01 = h00 * sxy + h01 * syy
    t10 = h10 * sxx + h11 * sxy
    t11 = h10 * sxy + h11 * syy
    S00 = h00 * t00 + h01 * t01 + R[0, 0]
    S01 = h10 * t00 + h11 * t01 + R[0, 1]
    S11 = h10 * t10 + h11 * t11 + R[1, 1]
    inv_det = 1.0 / (S00 * S11 - S01 * S01)
    K00 = (t00 * S11 - t10 * S01) * inv_det
    K01 = (t10 * S00 - t00 * S01) * inv_det
    K10 = (t01 * S11 - t11 * S01) * inv_det
    K11 = (t11 * S00 - t01 * S01) * inv_det
    return (
        mx + K00 * nu_r + K01 * nu_b,
        my + K10 * nu_r + K11 * nu_b,
        sxx - (K00 * t00 + K01 * t10),
        sxy - (K00 * t01 + K01 * t11),
        syy - (K10 * t01 + K11 * t11),
    )


_FEATURE_FIELDS = ("_mx", "_my", "_sxx", "_sxy", "_syy", "_ex", "_active", "_cid")
_FIELD_FILL = {"_active": False, "_cid": -1}


class FastSLAM2:
    """FastSLAM 2.0 with Data Association Sampling, existence and correspondence voting.

    Parameters (keyword options are validated; a bad value raises ``ValueError``):
    sensor, clutter, odometry_noise: the models (DESIGN 3). rng: the owned
    ``numpy.random.Generator`` (every draw). ids: shared :class:`FeatureIds` (new if None).
    n_particles: P. initial_pose: the pose of every particle at start (zero uncertainty).
    resample_threshold: resample when N_eff < threshold * P. gate_chi2: association gate.
    new_landmark_density_per_m2: rho of ``L_new``. max_detection_probability, max_existence,
    cull_threshold, cull_interval_steps: existence bookkeeping (module doc).
    feature_budget: the front-end's feature budget (``local_map_budget_ratio``).
    clutter_rate_memory: observations over which ``clutter_rate`` is averaged (exponential).
    initial_capacity: initial feature slots per particle (doubles when full).

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
    ):
        require(isinstance(sensor, RangeBearingSensor), "sensor", sensor, "a RangeBearingSensor")
        require(isinstance(clutter, ClutterModel), "clutter", clutter, "a ClutterModel")
        require(
            hasattr(odometry_noise, "covariance"),
            "odometry_noise",
            odometry_noise,
            "an object with .covariance(u, dt)",
        )
        require(isinstance(rng, np.random.Generator), "rng", rng, "a numpy.random.Generator")
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
            isinstance(initial_capacity, (int, np.integer)) and 1 <= initial_capacity <= 1e6,
            "initial_capacity",
            initial_capacity,
            "an integer in [1, 1000000]",
        )

        self.sensor = sensor
        self.clutter = clutter
        self.odometry_noise = odometry_noise
        self.rng = rng
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
        self._R = sensor.R
        self._capacity = int(initial_capacity)
        self._clutter_num = 0.0
        self._clutter_den = 0.0
        self._reset(pose0)

    # ------------------------------------------------------------------ state
    def _reset(self, pose0):
        P, C = self.n_particles, self._capacity
        self._poses = np.tile(pose0, (P, 1))
        self._logw = np.zeros(P)
        for name in _FEATURE_FIELDS:
            fill = _FIELD_FILL.get(name, 0.0)
            dtype = bool if name == "_active" else np.int64 if name == "_cid" else float
            setattr(self, name, np.full((P, C), fill, dtype=dtype))
        self._count = np.zeros(P, dtype=np.int64)
        self._prop_cov = np.zeros((P, 3, 3))
        self._pending = False
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
        pad = C - self._capacity
        for name in _FEATURE_FIELDS:
            a = getattr(self, name)
            extra = np.full((self.n_particles, pad), _FIELD_FILL.get(name, 0.0), dtype=a.dtype)
            setattr(self, name, np.concatenate([a, extra], axis=1))
        self._capacity = C

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def poses(self) -> np.ndarray:
        """Particle poses (P, 3) (proposal means between ``predict`` and ``update``)."""
        return self._poses.copy()

    @property
    def weights(self) -> np.ndarray:
        """Normalised particle weights (P,)."""
        w = np.exp(self._logw - self._logw.max())
        return w / w.sum()

    @property
    def means(self) -> np.ndarray:
        """Feature means (P, C, 2)."""
        return np.stack([self._mx, self._my], axis=-1)

    @property
    def covs(self) -> np.ndarray:
        """Feature covariances (P, C, 2, 2)."""
        row0 = np.stack([self._sxx, self._sxy], axis=-1)
        row1 = np.stack([self._sxy, self._syy], axis=-1)
        return np.stack([row0, row1], axis=-2)

    @property
    def existence(self) -> np.ndarray:
        return self._ex.copy()

    @property
    def active(self) -> np.ndarray:
        return self._active.copy()

    @property
    def correspondence_ids(self) -> np.ndarray:
        return self._cid.copy()

    # ------------------------------------------------------------------ prediction
    def predict(self, u, dt):
        """Motion prediction: proposal prior N(f(v, u), J_u Q J_u^T) for every particle (FS2)."""
        u = np.asarray(u, dtype=float)
        require(u.shape == (2,) and bool(np.all(np.isfinite(u))), "u", u, "a finite (v, omega)")
        dt = float(dt)
        check_range("dt", dt, 0.0, 1e6)
        if dt == 0.0:  # no time elapsed, no motion (e.g. a scan at the start pose)
            return
        if self._pending:
            self._sample_pending()
            self._maybe_resample()
        Q = np.asarray(self.odometry_noise.covariance(u, dt), dtype=float)
        self._prop_cov = _motion_noise_cov(self._poses, u, dt, Q)
        self._poses = motion(self._poses, u, dt)
        self._pending = True
        self._age_s += dt
        self._distance_m += abs(float(u[0])) * dt

    def _sample_pending(self):
        """Draw every particle's pose from its proposal N(x, P) (FS2)."""
        normals = self.rng.standard_normal((self.n_particles, 3))
        self._poses = self._poses + _sample_gaussian3(self._prop_cov, normals)
        self._poses[:, 2] = wrap_angle(self._poses[:, 2])
        self._prop_cov = np.zeros((self.n_particles, 3, 3))
        self._pending = False

    def update_heading(self, theta, std_rad):
        """Compass: a direct observation of each particle's heading with std ``std_rad``.

        Before ``update`` (proposal pending) it refines the FS2 proposal with the scalar Kalman
        update ``x += P e3 nu / s``, ``P -= P e3 e3^T P / s``, ``s = P_tt + std^2``, and weights by
        ``N(nu; 0, s)``; after ``update`` it can only weight by ``N(theta - theta^p; 0, std^2)``.
        """
        theta, std_rad = float(theta), float(std_rad)
        check_range("theta", theta, -1e3, 1e3)
        check_range("std_rad", std_rad, 0.0, 10.0, low_open=True)
        var = std_rad**2
        nu = wrap_angle(theta - self._poses[:, 2])
        if self._pending:
            Pc = self._prop_cov
            s = Pc[:, 2, 2] + var
            k = Pc[:, :, 2] / s[:, None]
            self._poses = self._poses + k * nu[:, None]
            self._poses[:, 2] = wrap_angle(self._poses[:, 2])
            Pc = Pc - k[:, :, None] * Pc[:, None, 2, :]
            self._prop_cov = 0.5 * (Pc + np.swapaxes(Pc, 1, 2))
        else:
            s = np.full(self.n_particles, var)
        self._logw += -0.5 * nu * nu / s - 0.5 * np.log(_TWO_PI * s)
        self._logw -= self._logw.max()
        if not self._pending:
            self._maybe_resample()

    # ------------------------------------------------------------------ observation update
    def update(self, z, associations=None):
        """Process one scan ``z`` (K, 2) of range-bearing observations (module docstring).

        ``associations`` (K,) optional, for comparison and tests: known landmark labels (any
        non-negative integers, e.g. the simulator's truth) or -1 for a known false alarm. Each
        label is then tied to one common id and every particle uses that association (no
        sampling, no vote); the weight factor is the FS2 marginal likelihood ``N(nu; 0, S)``
        times the detection ratio of the feature (``L_new`` for a particle lacking it), after
        the missed-detection product (module docstring).
        """
        z = np.asarray(z, dtype=float).reshape(-1, 2) if np.size(z) else np.zeros((0, 2))
        require(bool(np.all(np.isfinite(z))), "z", z, "finite range-bearing pairs (K, 2)")
        require(bool(np.all(z[:, 0] >= 0.0)), "z", z, "ranges >= 0")
        K = len(z)
        known = None
        if associations is not None:
            known = np.asarray(associations, dtype=np.int64).reshape(-1)
            require(len(known) == K, "associations", associations, f"length {K} like z")
            require(bool(np.all(known >= -1)), "associations", associations, "labels >= -1")
        if not self._pending:
            self._prop_cov = np.zeros((self.n_particles, 3, 3))
            self._pending = True

        P, C = self.n_particles, self._capacity
        alpha = self.detection_probability
        beta = self.clutter.beta
        n_hi = int(self._count.max())

        # Visibility of every feature from the proposal (soft at the range limit), the clutter
        # density and the missed-detection terms 1 - alpha e p_vis of the scan likelihood.
        p_vis = self._visibility(n_hi)
        seen = alpha * self._ex[:, :n_hi] * p_vis
        miss_term = 1.0 - seen
        n_vis = np.maximum((self._ex[:, :n_hi] * p_vis).sum(axis=1), K / (alpha + beta))
        clutter_density = beta * n_vis / (self.sensor.max_range_m * self.sensor.fov_rad)
        self._logw += np.log(miss_term).sum(axis=1)

        if known is None and K and n_hi:
            near_all = self._candidates(z, n_hi)
            near_any = near_all.any(axis=1)
        else:
            near_all = np.zeros((K, P, n_hi), dtype=bool)
            near_any = np.zeros((K, n_hi), dtype=bool)
        claimed = np.zeros((P, n_hi), dtype=bool)
        choices = np.full((K, P), CLUTTER_VOTE, dtype=np.int64)  # slot, CLUTTER_ or NEW_VOTE
        gate_areas = np.zeros((K, P))
        new_existence = np.zeros((K, P))
        winners = np.full(K, -1, dtype=np.int64)
        votes = np.full((K, P), CLUTTER_VOTE, dtype=np.int64)
        margins = np.ones(K)
        rows = np.arange(P)
        for k in range(K):
            zk = z[k]
            l_new = alpha * self.new_landmark_density * max(zk[0], self.sensor.range_std_m)
            new_existence[k] = np.minimum(l_new / (l_new + clutter_density), self.max_existence)
            if known is not None:
                label = int(known[k])
                if label < 0:
                    continue
                if label not in self._label_cid:
                    self._label_cid[label] = int(self.ids.new(1)[0])
                cid = self._label_cid[label]
                winners[k] = cid
                votes[k] = cid
                if n_hi == 0:
                    choices[k] = NEW_VOTE
                    continue
                match = self._active[:, :n_hi] & (self._cid[:, :n_hi] == cid) & ~claimed
                has = match.any(axis=1)
                slot = np.argmax(match, axis=1)
                flat = (rows * C + slot)[:, None]
                t = self._terms(zk, *(np.take(getattr(self, f), flat) for f in _FEATURE_FIELDS[:5]))
                lik = np.exp(-0.5 * t["d2"][:, 0]) / (_TWO_PI * np.sqrt(t["det"][:, 0]))
                ratio = np.take(seen, rows * n_hi + slot) / np.take(miss_term, rows * n_hi + slot)
                self._logw += np.log(np.maximum(np.where(has, ratio * lik, l_new), 1e-300))
                self._refine(has, t, np.zeros(P, dtype=np.int64))
                gate_areas[k] = np.pi * self.gate_chi2 * np.sqrt(t["det"][:, 0])
                choices[k] = np.where(has, slot, NEW_VOTE)
                claimed[rows[has], slot[has]] = True
                continue

            # --- Data Association Sampling (FS2 / DAS)
            cols = np.flatnonzero(near_any[k])
            n_c = len(cols)
            hyp = np.empty((P, n_c + 2))
            t = None
            if n_c:
                near = near_all[k][:, cols] & ~claimed[:, cols]
                t = self._terms(zk, *(getattr(self, f)[:, cols] for f in _FEATURE_FIELDS[:5]))
                ratio = seen[:, cols] / miss_term[:, cols]
                like = ratio * np.exp(-0.5 * t["d2"]) / _TWO_PI
                gated = near & (t["d2"] < self.gate_chi2)
                hyp[:, :n_c] = np.where(gated, like / np.sqrt(np.abs(t["det"])), 0.0)
            hyp[:, n_c] = l_new
            hyp[:, n_c + 1] = clutter_density
            cum = np.cumsum(hyp, axis=1)
            total = cum[:, -1]
            pick = np.minimum((cum < (self.rng.random(P) * total)[:, None]).sum(axis=1), n_c + 1)
            # a zero-likelihood hypothesis can only be picked through round-off: step past it
            pick = np.where(hyp.reshape(-1)[rows * (n_c + 2) + pick] > 0.0, pick, n_c)
            self._logw += np.log(np.maximum(total, 1e-300))
            kind = np.where(pick == n_c, NEW_VOTE, CLUTTER_VOTE)
            if n_c:
                chose = pick < n_c
                j = np.minimum(pick, n_c - 1)
                self._refine(chose, t, j)
                det_j = t["det"].reshape(-1)[rows * n_c + j]
                gate_areas[k] = np.pi * self.gate_chi2 * np.sqrt(np.abs(det_j))
                slot = cols[j]
                claimed[rows[chose], slot[chose]] = True
                choices[k] = np.where(chose, slot, kind)
                cid_of = np.take(self._cid, rows * C + slot)
                votes[k] = np.where(chose, np.where(cid_of >= 0, cid_of, NEW_VOTE), kind)
            else:
                choices[k] = kind
                votes[k] = kind

            # --- correspondence vote (BB 3.1)
            result = correspondence_vote(np.exp(self._logw - self._logw.max()), votes[k])
            margins[k] = result.margin
            winners[k] = int(self.ids.new(1)[0]) if result.winner == NEW_VOTE else result.winner
            self._remember_clutter(result.share_of(CLUTTER_VOTE))

        # --- sample the poses, then existence and map updates at the sampled poses (FS2)
        self._sample_pending()
        self._miss_update(p_vis, claimed, n_vis)
        self._apply(z, choices, winners, gate_areas, new_existence, n_vis)
        self._steps += 1
        if self._steps % self.cull_interval_steps == 0:
            self._cull()
        self._logw -= self._logw.max()
        self.last_associations = winners
        self.last_votes = votes
        self._vote_margins = margins
        self._maybe_resample()

    def _visibility(self, n_hi):
        """Probability (P, n_hi) that each active feature lies inside the sensor's range.

        The sensor sees a landmark when its *true* range is below ``max_range``; given the
        particle's estimate this happens with probability ``Phi((r_max - r) / sigma_r)``, with
        ``sigma_r^2 = u^T (Sigma_j + A) u`` the radial variance of the feature (``Sigma_j``) and
        of the proposal position (``A``), ``u`` the unit line of sight. A soft limit keeps
        particles that predict a feature a few centimetres either side of the range limit from
        getting very different weights and existence updates. A limited field of view is applied
        as a hard bearing test on the mean.
        """
        x = self._poses
        Pc = self._prop_cov
        dx = self._mx[:, :n_hi] - x[:, 0:1]
        dy = self._my[:, :n_hi] - x[:, 1:2]
        q = np.maximum(dx * dx + dy * dy, 1e-12)
        r = np.sqrt(q)
        radial = (
            dx * dx * (self._sxx[:, :n_hi] + Pc[:, 0, 0:1])
            + 2.0 * dx * dy * (self._sxy[:, :n_hi] + Pc[:, 0, 1:2])
            + dy * dy * (self._syy[:, :n_hi] + Pc[:, 1, 1:2])
        ) / q
        sigma = np.sqrt(np.maximum(radial, 0.0)) + 1e-9
        p_vis = np.where(self._active[:, :n_hi], ndtr((self.sensor.max_range_m - r) / sigma), 0.0)
        if self.sensor.fov_rad < _TWO_PI:
            bearing = wrap_angle(np.arctan2(dy, dx) - x[:, 2:3])
            p_vis = np.where(np.abs(bearing) <= 0.5 * self.sensor.fov_rad, p_vis, 0.0)
        return p_vis

    def _candidates(self, z, n_hi):
        """Per observation, the features near the point it maps to from each pose mean.

        A cheap Cartesian pre-gate computed once per scan: the radius ``sqrt(gate) * (sum of the
        stds of pose position, heading x range, range noise, bearing noise x range, largest
        feature)`` bounds the chi-square gate (a sum of stds bounds the std of the sum; the
        proposal only shrinks within the scan), plus 0.5 m for the linearisation.
        Returns ``near`` (K, P, n_hi).
        """
        x = self._poses
        Pc = self._prop_cov
        active = self._active[:, :n_hi]
        trace = self._sxx[:, :n_hi] + self._syy[:, :n_hi]
        feat_std = float(np.sqrt(np.max(np.where(active, trace, 0.0))))
        sig_pos = np.sqrt(np.maximum(Pc[:, 0, 0] + Pc[:, 1, 1], 0.0))
        sig_th = np.sqrt(np.maximum(Pc[:, 2, 2], 0.0))
        r = z[:, 0:1]
        radius = (
            np.sqrt(self.gate_chi2)
            * (
                sig_pos
                + r * sig_th
                + self.sensor.range_std_m
                + r * self.sensor.bearing_std_rad
                + feat_std
            )
            + 0.5
        )  # (K, P)
        ang = x[:, 2] + z[:, 1:2]
        dx = self._mx[None, :, :n_hi] - (x[:, 0] + r * np.cos(ang))[..., None]
        dy = self._my[None, :, :n_hi] - (x[:, 1] + r * np.sin(ang))[..., None]
        return (dx * dx + dy * dy < (radius * radius)[..., None]) & active

    def _terms(self, zk, mx, my, sxx, sxy, syy):
        """Innovation and ``S = G P G^T + H_m Sigma H_m^T + R`` for features (P, n) components.

        Elementwise 2x2 algebra on (P, n) arrays (faster than batched matmul for n ~ 1). With
        ``G = [-H_m | e]``, ``e = (0, -1)^T`` and the proposal ``P = [[A, c], [c^T, p]]``:
        ``S = H_m (A + Sigma) H_m^T + [[0, u0], [u0, 2 u1 + p]] + R``, ``u = H_m c``.
        """
        x = self._poses
        Pc = self._prop_cov
        dx = mx - x[:, 0:1]
        dy = my - x[:, 1:2]
        q = np.maximum(dx * dx + dy * dy, 1e-12)
        r = np.sqrt(q)
        nu_r = zk[0] - r
        nu_b = wrap_angle(zk[1] - np.arctan2(dy, dx) + x[:, 2:3])
        h00, h01, h10, h11 = dx / r, dy / r, -dy / q, dx / q
        m00 = sxx + Pc[:, 0, 0:1]
        m01 = sxy + Pc[:, 0, 1:2]
        m11 = syy + Pc[:, 1, 1:2]
        t00 = h00 * m00 + h01 * m01
        t01 = h00 * m01 + h01 * m11
        t10 = h10 * m00 + h11 * m01
        t11 = h10 * m01 + h11 * m11
        c0, c1 = Pc[:, 0, 2:3], Pc[:, 1, 2:3]
        S00 = h00 * t00 + h01 * t01 + self._R[0, 0]
        S01 = h10 * t00 + h11 * t01 + (h00 * c0 + h01 * c1)
        S11 = h10 * t10 + h11 * t11 + 2.0 * (h10 * c0 + h11 * c1) + Pc[:, 2, 2:3] + self._R[1, 1]
        det = S00 * S11 - S01 * S01
        d2 = (S11 * nu_r * nu_r - 2.0 * S01 * nu_r * nu_b + S00 * nu_b * nu_b) / det
        return {
            "nu_r": nu_r,
            "nu_b": nu_b,
            "S00": S00,
            "S01": S01,
            "S11": S11,
            "det": det,
            "d2": d2,
            "h": (h00, h01, h10, h11),
        }

    def _refine(self, chose, t, j):
        """FS2 proposal in Kalman form, ``x += P G^T S^-1 nu``, ``P -= P G^T S^-1 G P``, for the
        particles with ``chose`` (others get zero gain); ``j`` (P,) the column in ``t``."""
        P = self.n_particles
        flat = np.arange(P) * t["d2"].shape[1] + j

        def at(a):
            return a.reshape(-1)[flat]

        S00, S01, S11 = at(t["S00"]), at(t["S01"]), at(t["S11"])
        inv_det = np.divide(chose.astype(float), at(t["det"]), out=np.zeros(P), where=chose)
        h00, h01, h10, h11 = (at(h) for h in t["h"])
        Pc = self._prop_cov
        # P g0 and P g1, the columns of P G^T, with g0 = (-h00, -h01, 0), g1 = (-h10, -h11, -1)
        Pg0 = -(Pc[:, :, 0] * h00[:, None] + Pc[:, :, 1] * h01[:, None])
        Pg1 = -(Pc[:, :, 0] * h10[:, None] + Pc[:, :, 1] * h11[:, None] + Pc[:, :, 2])
        K0 = (Pg0 * S11[:, None] - Pg1 * S01[:, None]) * inv_det[:, None]
        K1 = (Pg1 * S00[:, None] - Pg0 * S01[:, None]) * inv_det[:, None]
        self._poses += K0 * at(t["nu_r"])[:, None] + K1 * at(t["nu_b"])[:, None]
        self._poses[:, 2] = wrap_angle(self._poses[:, 2])
        # symmetric in exact arithmetic; consumers read it symmetrised or by its lower triangle
        self._prop_cov = Pc - (K0[:, :, None] * Pg0[:, None, :] + K1[:, :, None] * Pg1[:, None, :])

    def _miss_update(self, p_vis, claimed, n_vis):
        """Complement of BB (11) for every feature not associated in this scan, with the
        detection probability ``alpha * p_vis`` (soft visibility, :meth:`_visibility`).

        P_fa is that of the smallest gate, the one of R alone (module docstring)."""
        if p_vis.size == 0:
            return
        n_hi = p_vis.shape[1]
        area = gate_area(self._R, self.gate_chi2)
        p_fa = false_alarm_in_gate_probability(
            self.clutter.beta, n_vis, area, self.sensor.max_range_m, self.sensor.fov_rad
        )
        ex = self._ex[:, :n_hi]
        missed = ~claimed & (p_vis > 0.0)
        updated = miss_update(ex, self.detection_probability * p_vis, p_fa[:, None])
        self._ex[:, :n_hi] = np.where(missed, updated, ex)

    def _apply(self, z, choices, winners, gate_areas, new_existence, n_vis):
        """EKF updates and initialisations at the sampled poses, existence and ids, for all the
        observations of a scan at once (a particle updates a feature at most once per scan)."""
        C = self._capacity
        ks, ps = np.nonzero(choices >= 0)
        if len(ks):
            flat = ps * C + choices[ks, ps]
            comps = [np.take(getattr(self, f), flat) for f in _FEATURE_FIELDS[:5]]
            updated = _feature_ekf(self._poses[ps], *comps, z[ks], self._R)
            for name, value in zip(_FEATURE_FIELDS[:5], updated, strict=True):
                np.put(getattr(self, name), flat, value)
            p_fa = false_alarm_in_gate_probability(
                self.clutter.beta,
                n_vis[ps],
                gate_areas[ks, ps],
                self.sensor.max_range_m,
                self.sensor.fov_rad,
            )
            ex = detection_update(np.take(self._ex, flat), self.detection_probability, p_fa)
            np.put(self._ex, flat, np.minimum(ex, self.max_existence))
            won = winners[ks]
            np.put(self._cid, flat, np.where(won >= 0, won, np.take(self._cid, flat)))
        is_new = choices == NEW_VOTE
        if is_new.any():
            rank = np.cumsum(is_new, axis=0) - 1  # several new features of one particle per scan
            kn, pn = np.nonzero(is_new)
            slot = self._count[pn] + rank[kn, pn]
            self._grow(int(slot.max()) + 1)
            flat = pn * self._capacity + slot
            pose, zz = self._poses[pn], z[kn]
            _, Gz = inverse_observe_jacobians(pose, zz)
            m = inverse_observe(pose, zz)
            sig = (Gz * np.diag(self._R)) @ np.swapaxes(Gz, 1, 2)
            values = (
                m[:, 0],
                m[:, 1],
                sig[:, 0, 0],
                sig[:, 0, 1],
                sig[:, 1, 1],
                new_existence[kn, pn],
                True,
                winners[kn],
            )
            for name, value in zip(_FEATURE_FIELDS, values, strict=True):
                np.put(getattr(self, name), flat, value)
            self._count += is_new.sum(axis=0)

    def _cull(self):
        """Remove features with existence below ``cull_threshold`` and re-pack the slots."""
        dead = self._active & (self._ex < self.cull_threshold)
        if not dead.any():
            return
        self._active &= ~dead
        order = np.argsort(~self._active, axis=1, kind="stable")
        for name in _FEATURE_FIELDS:
            setattr(self, name, np.take_along_axis(getattr(self, name), order, axis=1))
        self._count = self._active.sum(axis=1)
        self._ex[~self._active] = 0.0
        self._cid[~self._active] = -1

    def _remember_clutter(self, share):
        decay = 1.0 - 1.0 / self.clutter_rate_memory
        self._clutter_num = decay * self._clutter_num + share
        self._clutter_den = decay * self._clutter_den + 1.0

    def _maybe_resample(self):
        """Systematic resampling when N_eff < resample_threshold * P."""
        w = self.weights
        n_eff = 1.0 / np.sum(w * w)
        self._ess_ratio = float(n_eff / self.n_particles)
        if n_eff >= self.resample_threshold * self.n_particles:
            return
        P = self.n_particles
        positions = (self.rng.random() + np.arange(P)) / P
        cdf = np.cumsum(w)
        cdf[-1] = 1.0
        idx = np.minimum(np.searchsorted(cdf, positions, side="right"), P - 1)
        self._poses = self._poses[idx]
        self._prop_cov = self._prop_cov[idx]
        for name in _FEATURE_FIELDS:
            setattr(self, name, getattr(self, name)[idx])
        self._count = self._count[idx]
        self._logw = np.zeros(P)

    # ------------------------------------------------------------------ outputs
    def _pose_covs(self):
        if not self._pending:
            return None
        return 0.5 * (self._prop_cov + np.swapaxes(self._prop_cov, 1, 2))

    def pose(self):
        """Weighted mean (circular mean heading) and covariance of the particle poses."""
        return pose_moments(self._poses, self.weights, self._pose_covs())

    def _common(self):
        return common_features(
            self.weights, self._cid, self._active, self._ex, tie_break=self._sxx + self._syy
        )

    def landmarks(self) -> LandmarkEstimate:
        """The common features (BB 3.2) with per-feature moments and weighted existence."""
        common = self._common()
        if len(common) == 0:
            return LandmarkEstimate.empty()
        means, covs = feature_moments(self.weights, self.means, self.covs, common.slots)
        return LandmarkEstimate(common.ids.copy(), means, covs, common.existence.copy())

    def to_gaussian(self) -> GaussianMap:
        """BB 3.2: [pose, features with p(exists) > 0.95] as one SPD Gaussian (local frame)."""
        return moment_match(
            self._poses,
            self.weights,
            self.means,
            self.covs,
            self._common(),
            min_existence=CONFIRMED_PROBABILITY,
            pose_covs=self._pose_covs(),
        )

    def restart(self):
        """New local map (BB 4): all particles at the origin, zero uncertainty, no features."""
        self._reset(np.zeros(3))

    def local_statistics(self) -> dict[str, float]:
        """Local interface features of docs/ARCHITECTURE.md.

        ``ess_ratio`` is N_eff / P of the weights before the latest resampling decision (after a
        resampling the weights are uniform, which would always read 1).
        """
        common = self._common()
        _, cov = self.pose()
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
            "clutter_rate": float(self._clutter_num / self._clutter_den)
            if self._clutter_den > 0.0
            else 0.0,
            "local_map_budget_ratio": float(n_features / self.feature_budget),
        }
