"""EKF-SLAM with unknown data association (JCBB), clutter and existence probabilities.

This is both BB's EKF baseline and the EKF front-end of EKF sub-mapping (BB 5.1, filter 2).

State ``[x, y, theta, m_1x, m_1y, ..., m_Nx, m_Ny]`` with covariance ``P``, kept in preallocated
arrays whose capacity doubles when features are added, so adding a feature costs O(n^2) copying
only when the capacity is exceeded (amortised O(n) per feature), not a reallocation every step.

One iteration:

* ``predict(u, dt)``: unicycle mid-point motion (:func:`filters.models.motion`),
  ``P_vv <- F P_vv F^T + G Q G^T``, ``P_vm <- F P_vm`` (O(n)).
* ``update(z)``: predicted observations of every feature with ``S_j = H_j P H_j^T + R``;
  individual chi-square gates over observations x features (bearing wrapped); JCBB over the
  gated pairings (:mod:`filters.association`); one batch Kalman update with the matched pairs;
  existence probabilities (:mod:`filters.existence`): BB (11) for detected features, with the
  probability ``P_fa`` that a false alarm lands in the feature's gate (area ``pi gamma sqrt|S_j|``,
  expected number of visible landmarks = sum of the existence probabilities of the features
  predicted in view, at least 1), and the complementary miss update for features predicted in
  view (with a margin of ``in_view_margin_sigma`` innovation standard deviations inside the
  sensor's range and field) but not detected; an observation that JCBB leaves unpaired starts a
  new feature with ``initial_existence`` unless it lies in some feature's individual gate (then it
  is ambiguous and taken for clutter, ``last_associations = -1``); features whose existence falls
  below ``cull_probability`` are removed with their rows and columns. A feature is confirmed when
  ``p > 0.95`` (:data:`filters.existence.CONFIRMED_PROBABILITY`).
* ``update_heading(theta, std)``: a scalar update of the heading (compass, BB 5.5).

Numerics: every update uses the Cholesky form ``S = L L^T``, ``W1 = P H^T L^-T``,
``x += W1 L^-1 nu``, ``P -= W1 W1^T`` (the form of Bailey's EKF-SLAM code; algebraically the
Joseph form with the optimal gain, O(n^2 r) for r measurement rows), followed by an explicit
symmetrisation; ``S`` itself is symmetrised and factorised with a jitter fallback.

The detection probability used in the existence updates is ``min(alpha, max_detection_probability)``
(default cap 0.99): with ``alpha = 1`` a single miss (an association failure, a landmark just
outside the range) would otherwise set a feature's existence to exactly 0.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from filters.association import (
    DEFAULT_NODE_BUDGET,
    ChiSquareTable,
    jcbb,
    predict_range_bearing,
    range_bearing_candidates,
    validate_gate_probability,
    validate_node_budget,
)
from filters.existence import (
    CONFIRMED_PROBABILITY,
    detection_update,
    false_alarm_in_gate_probability,
    gate_area,
    miss_update,
    validate_existence_model,
)
from filters.geometry import wrap_angle
from filters.models import inverse_observe, inverse_observe_jacobians, motion, motion_jacobians
from filters.types import FeatureIds, GaussianMap, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------- shared numerics
def safe_cholesky(S):
    """Lower Cholesky factor of a symmetric ``S``, adding a growing jitter if it is not PD."""
    S = 0.5 * (S + S.T)
    try:
        return np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        pass
    scale = max(float(np.max(np.abs(np.diag(S)))), 1e-300)
    jitter = 1e-12 * scale
    eye = np.eye(len(S))
    for _ in range(12):
        try:
            L = np.linalg.cholesky(S + jitter * eye)
            logger.debug("innovation covariance needed a jitter of %.3g", jitter)
            return L
        except np.linalg.LinAlgError:
            jitter *= 10.0
    raise np.linalg.LinAlgError("innovation covariance is not positive definite")


def kalman_update(x, P, cols, H, nu, R):
    """In-place linear(ised) Kalman update of ``x`` (n,) and ``P`` (n, n).

    ``H`` (r, q) is the measurement Jacobian on the state columns ``cols`` (q,) (all other columns
    zero), ``nu`` (r,) the innovation, ``R`` (r, r) its noise (may be zero, e.g. the zero-noise
    fusion observation BB (10), as long as ``H P H^T`` is PD). Cholesky form, see the module
    docstring. ``x`` and ``P`` may be views into larger arrays.
    """
    cols = np.asarray(cols, dtype=np.int64)
    W = P[:, cols] @ H.T  # P H^T, (n, r)
    S = H @ W[cols] + R
    L_inv = np.linalg.inv(safe_cholesky(S))  # r x r, small
    W1 = W @ L_inv.T  # P H^T L^-T
    x += W1 @ (L_inv @ nu)
    P -= W1 @ W1.T
    np.copyto(P, 0.5 * (P + P.T))


# --------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class EKFSLAMConfig:
    """Options of :class:`EKFSLAM` (validated; a bad value raises ValueError naming it).

    gate_probability: chi-square probability of the individual and joint gates.
    initial_existence: existence probability of a feature started from one observation.
    cull_probability: features whose existence falls below this are removed.
    max_detection_probability: cap on alpha in the existence updates (see module docstring).
    in_view_margin_sigma: a feature counts as predicted in view (and its non-detection as a miss)
        only if it is this many innovation stds inside the sensor's range and field of view.
    node_budget: JCBB node budget (:mod:`filters.association`).
    clutter_rate_forgetting: per-update forgetting factor of the running clutter-rate estimate.
    feature_budget: the front-end's feature budget (only reported, ``local_map_budget_ratio``).
    initial_feature_capacity: features preallocated (the arrays double when exceeded).
    existence_model: ``"gate"`` or ``"bb"``, the reading of BB (11) (:mod:`filters.existence`).
    """

    gate_probability: float = 0.999
    initial_existence: float = 0.5
    cull_probability: float = 0.05
    max_detection_probability: float = 0.99
    in_view_margin_sigma: float = 2.0
    node_budget: int = DEFAULT_NODE_BUDGET
    clutter_rate_forgetting: float = 0.99
    feature_budget: int = 100
    initial_feature_capacity: int = 32
    existence_model: str = "gate"

    def __post_init__(self):
        validate_gate_probability(self.gate_probability)
        validate_existence_model(self.existence_model)
        check_range(
            "initial_existence", self.initial_existence, 0.0, 1.0, low_open=True, high_open=True
        )
        check_range(
            "cull_probability", self.cull_probability, 0.0, CONFIRMED_PROBABILITY, high_open=True
        )
        require(
            self.initial_existence > self.cull_probability,
            "initial_existence",
            self.initial_existence,
            f"greater than cull_probability={self.cull_probability}",
        )
        check_range(
            "max_detection_probability",
            self.max_detection_probability,
            0.0,
            1.0,
            low_open=True,
        )
        check_range("in_view_margin_sigma", self.in_view_margin_sigma, 0.0, 10.0)
        validate_node_budget(self.node_budget)
        check_range(
            "clutter_rate_forgetting", self.clutter_rate_forgetting, 0.0, 1.0, low_open=True
        )
        for name in ("feature_budget", "initial_feature_capacity"):
            value = getattr(self, name)
            require(
                isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1,
                name,
                value,
                "an integer >= 1",
            )


def make_config(config_cls, config, options):
    """``config`` (or the defaults) with ``options`` overridden; unknown names -> ValueError."""
    known = {f.name for f in dataclasses.fields(config_cls)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"unknown option(s) {unknown}: must be among {sorted(known)}")
    base = config if config is not None else config_cls()
    require(isinstance(base, config_cls), "config", config, f"a {config_cls.__name__}")
    return dataclasses.replace(base, **options) if options else base


def validate_pose(value, field):
    """A pose option: 3 finite numbers (heading wrapped), or ``ValueError`` naming ``field``;
    the back-ends validate their initial pose with it too."""
    pose = np.asarray(value, dtype=float)
    require(pose.shape == (3,) and np.all(np.isfinite(pose)), field, value, "3 finite numbers")
    out = pose.copy()
    out[2] = wrap_angle(out[2])
    return out


def validate_cov(value, field, dim=3):
    """A covariance option: symmetric positive semi-definite ``dim x dim`` (returned
    symmetrised; None: zeros), or ``ValueError`` naming ``field``."""
    if value is None:
        return np.zeros((dim, dim))
    cov = np.asarray(value, dtype=float)
    ok = cov.shape == (dim, dim) and np.all(np.isfinite(cov)) and np.allclose(cov, cov.T)
    if ok:
        ok = bool(np.min(np.linalg.eigvalsh(0.5 * (cov + cov.T))) >= -1e-12)
    require(ok, field, value, f"a symmetric positive semi-definite {dim}x{dim} matrix")
    return 0.5 * (cov + cov.T)


# --------------------------------------------------------------------------- the filter
class EKFSLAM:
    """EKF-SLAM with JCBB association, clutter and existence probabilities (module docstring).

    Parameters: ``sensor`` (:class:`filters.models.RangeBearingSensor`), ``clutter``
    (:class:`filters.models.ClutterModel`), ``odometry_noise`` (``.covariance(u, dt)``), ``ids``
    (a shared :class:`filters.types.FeatureIds`, or None for a private one), ``initial_pose`` and
    ``initial_pose_cov`` (default: the origin, known exactly), ``config`` and keyword options of
    :class:`EKFSLAMConfig`.
    """

    def __init__(
        self,
        sensor,
        clutter,
        odometry_noise,
        ids: FeatureIds | None = None,
        *,
        initial_pose=None,
        initial_pose_cov=None,
        config: EKFSLAMConfig | None = None,
        **options,
    ):
        self.config = make_config(EKFSLAMConfig, config, options)
        self.sensor = sensor
        self.clutter = clutter
        self.odometry_noise = odometry_noise
        self.ids = ids if ids is not None else FeatureIds()
        self._R = sensor.R
        self._gate = ChiSquareTable(self.config.gate_probability, 2)
        self._alpha = min(float(clutter.alpha), self.config.max_detection_probability)
        self._beta = float(clutter.beta)
        self._initial_pose = (
            np.zeros(3) if initial_pose is None else validate_pose(initial_pose, "initial_pose")
        )
        self._initial_cov = validate_cov(initial_pose_cov, "initial_pose_cov")
        cap_f = int(self.config.initial_feature_capacity)
        self._allocate(3 + 2 * cap_f)
        self._clutter_num = 0.0
        self._clutter_den = 0.0
        self.last_hypothesis = None
        self._reset(self._initial_pose, self._initial_cov)

    # ------------------------------------------------------------------ storage
    def _allocate(self, capacity):
        self._x = np.zeros(capacity)
        self._P = np.zeros((capacity, capacity))
        n_f = (capacity - 3) // 2
        self._fid = np.zeros(n_f, dtype=np.int64)
        self._exist = np.zeros(n_f)

    def _ensure_capacity(self, n_needed):
        cap = len(self._x)
        if n_needed <= cap:
            return
        new_cap = max(2 * cap - 3, n_needed)
        new_cap += (new_cap - 3) % 2
        n, N = self._n, self.n_features
        x, P, fid, ex = self._x, self._P, self._fid, self._exist
        self._allocate(new_cap)
        self._x[:n] = x[:n]
        self._P[:n, :n] = P[:n, :n]
        self._fid[:N] = fid[:N]
        self._exist[:N] = ex[:N]

    def _reset(self, pose, cov):
        self._n = 3
        self._x[:3] = pose
        self._P[:3, :3] = cov
        self._age_s = 0.0
        self._distance_m = 0.0
        self._label_fid: dict[int, int] = {}
        self.last_associations = np.zeros(0, dtype=np.int64)

    @property
    def n_features(self) -> int:
        return (self._n - 3) // 2

    @property
    def state_dim(self) -> int:
        return self._n

    @property
    def x(self) -> np.ndarray:
        """The state mean (a view; do not modify)."""
        return self._x[: self._n]

    @property
    def P(self) -> np.ndarray:
        """The state covariance (a view; do not modify)."""
        return self._P[: self._n, : self._n]

    def _feature_cols(self, idx=None):
        idx = np.arange(self.n_features) if idx is None else np.asarray(idx, dtype=np.int64)
        return 3 + 2 * idx[:, None] + np.arange(2)

    # ------------------------------------------------------------------ filter interface
    def predict(self, u, dt):
        """Odometry prediction of the pose; O(n) (only the pose rows change)."""
        u = np.asarray(u, dtype=float)
        require(u.shape == (2,) and np.all(np.isfinite(u)), "u", u, "2 finite numbers (v, omega)")
        check_range("dt", dt, 0.0, 1e6)
        if dt == 0.0:  # no time elapsed, no motion (e.g. a scan at the start pose)
            return
        n = self._n
        x, P = self._x, self._P
        F, G = motion_jacobians(x[:3], u, dt)
        Q = self.odometry_noise.covariance(u, dt)
        x[:3] = motion(x[:3], u, dt)
        Pvv = F @ P[:3, :3] @ F.T + G @ Q @ G.T
        P[:3, :3] = 0.5 * (Pvv + Pvv.T)
        if n > 3:
            P[:3, 3:n] = F @ P[:3, 3:n]
            P[3:n, :3] = P[:3, 3:n].T
        self._age_s += float(dt)
        self._distance_m += abs(float(u[0])) * float(dt)

    def update_heading(self, theta, std_rad):
        """Scalar Kalman update with a compass measurement of the heading (BB 5.5)."""
        check_range("theta", theta, -1e6, 1e6)
        check_range("std_rad", std_rad, 0.0, 10.0, low_open=True)
        n = self._n
        x, P = self._x[:n], self._P[:n, :n]
        nu = np.array([wrap_angle(theta - x[2])])
        kalman_update(x, P, [2], np.ones((1, 1)), nu, np.array([[std_rad**2]]))
        x[2] = wrap_angle(x[2])

    def update(self, z, associations=None):
        """Associate (gating + JCBB), update, manage existence, add and cull features.

        ``associations`` (K,) optional, for comparison (known data association, e.g. the truth
        labels of a recording): non-negative labels tie each observation to one feature per
        label (a new feature the first time, or again after its feature was culled), -1 is a
        known false alarm (ignored); no gating, no JCBB. Existence and culling are unchanged.
        """
        z = np.asarray(z, dtype=float)
        if z.size == 0:
            z = np.zeros((0, 2))
        require(
            z.ndim == 2 and z.shape[1] == 2 and np.all(np.isfinite(z)),
            "z",
            z.shape,
            "a finite (K, 2) array of (range, bearing)",
        )
        K = len(z)
        known = None
        if associations is not None:
            known = np.asarray(associations, dtype=np.int64).reshape(-1)
            require(len(known) == K, "associations", associations, f"length {K} like z")
            require(bool(np.all(known >= -1)), "associations", associations, "labels >= -1")
        N = self.n_features
        pairing = np.full(K, -1, dtype=np.int64)
        gated_any = np.zeros(K, dtype=bool)
        self.last_hypothesis = None
        if N > 0:
            n = self._n
            x, P = self._x[:n], self._P[:n, :n]
            pred = predict_range_bearing(x, P, np.arange(3), self._feature_cols(), self._R)
            in_view = self._predicted_in_view(pred)
            if K > 0 and known is not None:
                pairing = self._known_pairing(known)
                matched = np.flatnonzero(pairing >= 0)
                if len(matched):
                    self._update_matched(z[matched], pairing[matched], pred)
            elif K > 0:
                cands, _, mask = range_bearing_candidates(z, x, P, pred, self._R, self._gate)
                gated_any = mask.any(axis=1)
                hyp = jcbb(cands, self._gate, self.config.node_budget)
                self.last_hypothesis = hyp
                if hyp.exhausted:
                    logger.debug("JCBB node budget exhausted (%d nodes)", hyp.n_nodes)
                pairing = hyp.pairing
                matched = np.flatnonzero(pairing >= 0)
                if len(matched):
                    self._update_matched(z[matched], pairing[matched], pred)
            self._update_existence(pairing, pred, in_view)
        # ids of associations before features are added or culled
        assoc = np.full(K, -1, dtype=np.int64)
        assoc[pairing >= 0] = self._fid[pairing[pairing >= 0]]
        if known is None:
            new_obs = np.flatnonzero((pairing < 0) & ~gated_any)
        else:  # the first observation of each label not (or no longer) mapped
            present = set(self._fid[: self.n_features].tolist())
            unmapped = np.array(
                [lab >= 0 and self._label_fid.get(lab, -1) not in present
                 for lab in known.tolist()],
                dtype=bool,
            )
            labels = np.where(unmapped, known, -1)
            _, first = np.unique(labels, return_index=True)
            new_obs = np.sort(first[labels[first] >= 0])
        if len(new_obs):
            assoc[new_obs] = self._add_features(z[new_obs])
            if known is not None:
                new_labels = known[new_obs].tolist()
                self._label_fid.update(zip(new_labels, assoc[new_obs].tolist(), strict=True))
        self._cull()
        # running clutter rate: observations not explained by an existing feature
        lam = self.config.clutter_rate_forgetting
        self._clutter_num = lam * self._clutter_num + float(np.count_nonzero(pairing < 0))
        self._clutter_den = lam * self._clutter_den + float(K)
        self.last_associations = assoc

    def _known_pairing(self, known):
        """Feature index per observation from known labels (-1: unmapped label or clutter);
        a label observed twice in one scan pairs its first observation only."""
        fids = self._fid[: self.n_features]
        index = {int(f): i for i, f in enumerate(fids)}
        pairing = np.full(len(known), -1, dtype=np.int64)
        used = set()
        for k, label in enumerate(known.tolist()):
            i = index.get(self._label_fid.get(label, -1), -1) if label >= 0 else -1
            if i >= 0 and i not in used:
                pairing[k] = i
                used.add(i)
        return pairing

    def _predicted_in_view(self, pred):
        k = self.config.in_view_margin_sigma
        r_std = np.sqrt(np.maximum(pred.S[:, 0, 0], 0.0))
        inside = pred.zhat[:, 0] + k * r_std <= self.sensor.max_range_m
        if self.sensor.fov_rad < 2.0 * np.pi:
            b_std = np.sqrt(np.maximum(pred.S[:, 1, 1], 0.0))
            inside &= np.abs(pred.zhat[:, 1]) + k * b_std <= 0.5 * self.sensor.fov_rad
        return inside

    def _update_matched(self, z, feats, pred):
        """Batch update with the matched pairs (observation, feature index)."""
        k = len(feats)
        n = self._n
        x, P = self._x[:n], self._P[:n, :n]
        cols = np.concatenate([np.arange(3), (3 + 2 * feats[:, None] + np.arange(2)).ravel()])
        H = np.zeros((2 * k, 3 + 2 * k))
        rows = np.arange(2 * k).reshape(k, 2)
        H[:, :3] = pred.H_pose[feats].reshape(2 * k, 3)
        blocks = pred.H_m[feats]  # (k, 2, 2)
        for a in range(2):
            for b in range(2):
                H[rows[:, a], 3 + 2 * np.arange(k) + b] = blocks[:, a, b]
        nu = z - pred.zhat[feats]
        nu[:, 1] = wrap_angle(nu[:, 1])
        R = np.kron(np.eye(k), self._R)
        kalman_update(x, P, cols, H, nu.ravel(), R)
        x[2] = wrap_angle(x[2])

    def _existence_false_alarm(self, S, n_visible):
        """``P_fa`` of BB (11) for gates of innovation covariances S (k, 2, 2)."""
        if self.config.existence_model == "bb":
            return np.full(len(S), self._beta)
        area = gate_area(S, self._gate(1))
        return false_alarm_in_gate_probability(
            self._beta, n_visible, area, self.sensor.max_range_m, self.sensor.fov_rad
        )

    def _update_existence(self, pairing, pred, in_view):
        N = self.n_features
        p = self._exist[:N]
        detected = np.zeros(N, dtype=bool)
        detected[pairing[pairing >= 0]] = True
        if detected.any():
            n_visible = max(1.0, float(np.sum(p[in_view])))
            p_fa = self._existence_false_alarm(pred.S[detected], n_visible)
            p[detected] = detection_update(p[detected], self._alpha, p_fa)
        missed = in_view & ~detected
        if missed.any():
            n_visible = max(1.0, float(np.sum(p[in_view])))
            p_fa = self._existence_false_alarm(pred.S[missed], n_visible)
            p[missed] = miss_update(p[missed], self._alpha, p_fa)

    def _add_features(self, z):
        """Initialise features from observations z (k, 2); returns their new ids."""
        k = len(z)
        n = self._n
        self._ensure_capacity(n + 2 * k)
        x, P = self._x, self._P
        pose = x[:3].copy()
        m = inverse_observe(pose, z)  # (k, 2)
        G_pose, G_z = inverse_observe_jacobians(pose, z)  # (k, 2, 3), (k, 2, 2)
        Gp = G_pose.reshape(2 * k, 3)
        cross = Gp @ P[:3, :n]  # (2k, n)
        new_block = Gp @ P[:3, :3] @ Gp.T
        noise = np.einsum("kij,jl,kml->kim", G_z, self._R, G_z)  # (k, 2, 2)
        idx = np.arange(k)
        for a in range(2):
            for b in range(2):
                new_block[2 * idx + a, 2 * idx + b] += noise[:, a, b]
        sl = slice(n, n + 2 * k)
        x[sl] = m.ravel()
        P[sl, :n] = cross
        P[:n, sl] = cross.T
        P[sl, sl] = 0.5 * (new_block + new_block.T)
        N = self.n_features
        new_ids = self.ids.new(k)
        self._fid[N : N + k] = new_ids
        self._exist[N : N + k] = self.config.initial_existence
        self._n = n + 2 * k
        return new_ids

    def _remove_features(self, keep_mask):
        """Keep only the features of ``keep_mask`` (N,), removing the others' rows and columns."""
        N = self.n_features
        keep = np.flatnonzero(keep_mask)
        if len(keep) == N:
            return
        idx = np.concatenate([np.arange(3), self._feature_cols(keep).ravel()])
        n_new = len(idx)
        self._x[:n_new] = self._x[idx]
        self._P[:n_new, :n_new] = self._P[np.ix_(idx, idx)]
        self._fid[: len(keep)] = self._fid[keep]
        self._exist[: len(keep)] = self._exist[keep]
        self._n = n_new

    def _cull(self):
        N = self.n_features
        if N:
            keep = self._exist[:N] >= self.config.cull_probability
            if not keep.all():
                self._remove_features(keep)

    # ------------------------------------------------------------------ outputs
    def pose(self):
        return self._x[:3].copy(), self._P[:3, :3].copy()

    def existence(self) -> np.ndarray:
        return self._exist[: self.n_features].copy()

    def feature_ids(self) -> np.ndarray:
        return self._fid[: self.n_features].copy()

    def landmarks(self) -> LandmarkEstimate:
        """Every feature of the map (tentative ones included) with its existence probability."""
        N = self.n_features
        if N == 0:
            return LandmarkEstimate.empty()
        cols = self._feature_cols()
        return LandmarkEstimate(
            ids=self._fid[:N].copy(),
            means=self._x[cols].copy(),
            covs=self._P[cols[:, :, None], cols[:, None, :]].copy(),
            existence=self._exist[:N].copy(),
        )

    def confirmed_mask(self) -> np.ndarray:
        return self._exist[: self.n_features] > CONFIRMED_PROBABILITY

    # ------------------------------------------------------------------ front-end interface
    def to_gaussian(self) -> GaussianMap:
        """Pose and confirmed features (p > 0.95) in the local frame, with their joint covariance.

        ``P`` is symmetric and positive semi-definite; it is positive definite except for the pose
        block right after :meth:`restart` (zero uncertainty at the local origin).
        """
        keep = np.flatnonzero(self.confirmed_mask())
        idx = np.concatenate([np.arange(3), self._feature_cols(keep).ravel()])
        P = self._P[np.ix_(idx, idx)]
        return GaussianMap(
            x=self._x[idx].copy(),
            P=0.5 * (P + P.T),
            ids=self._fid[keep].copy(),
            existence=self._exist[keep].copy(),
        )

    def restart(self):
        """A new local map: pose at the origin with zero uncertainty, no features (BB section 4).

        The running clutter-rate estimate (a property of the sensor) is kept.
        """
        self._reset(np.zeros(3), np.zeros((3, 3)))

    def clutter_rate(self) -> float:
        return self._clutter_num / self._clutter_den if self._clutter_den > 0 else 0.0

    def local_statistics(self) -> dict[str, float]:
        """The local part of the interface features (docs/ARCHITECTURE.md), EKF values."""
        P = self._P
        N = self.n_features
        return {
            "local_map_age_s": float(self._age_s),
            "local_map_distance_m": float(self._distance_m),
            "ess_ratio": 1.0,
            "particle_position_spread_m": float(np.sqrt(max(P[0, 0] + P[1, 1], 0.0))),
            "particle_heading_spread_rad": float(np.sqrt(max(P[2, 2], 0.0))),
            "local_feature_count": float(N),
            "local_confirmed_count": float(np.count_nonzero(self.confirmed_mask())),
            "vote_margin": 1.0,
            "clutter_rate": float(self.clutter_rate()),
            "local_map_budget_ratio": float(N) / float(self.config.feature_budget),
        }
