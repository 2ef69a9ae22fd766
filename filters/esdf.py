"""Exactly Sparse Delayed-state Filter (Eustice, Singh & Leonard 2006; CM section II).

The state is the stack of *delayed poses* -- the robot pose at every observation epoch -- and the
landmarks in global coordinates (CM (3)), held in information form ``(eta, Lambda)`` with
``eta = Lambda mu`` (CM section II). Between epochs :meth:`ESDF.predict` only compounds the
odometry into one increment ``Delta`` (in the frame of the last delayed pose) with covariance
``Q`` (:class:`OdometryAccumulator`); at an epoch the new delayed pose enters the state through the
relative-pose constraint ``relative(x_{k-1}, x_k) = Delta + w``, ``w ~ N(0, Q)``. Because the new
pose has no prior information, adding that constraint with the EIF update CM (4)-(5) *is* the
ESDF state augmentation of Eustice et al. (2006): it touches the blocks of ``x_{k-1}`` and
``x_k`` only. New landmarks enter the same way through their first observation, and
re-observations are the EIF update CM (4)-(5). Every one of these edits touches a fixed number of
blocks of ``Lambda`` -- constant time in the state size -- which :class:`SparseInformation` keeps
as a dict of dense blocks and converts to ``scipy.sparse`` CSC only when a global solve is needed.

Mean recovery (CM Assumption 2). CM (5) needs the current mean ``mu_bar`` of the entities an
observation touches. Two recoveries are offered:

* ``"full"``: after every update the whole mean is solved from ``Lambda mu = eta`` with a sparse
  LU factorisation (exact; cost grows with the state).
* ``"window"`` (default): a block Gauss-Seidel step restricted to the *active window* -- the last
  ``recovery_window`` delayed poses and the landmarks they observed. The window's means are the
  exact solution of ``Lambda_AA mu_A = eta_A - Lambda_AB mu_B`` with every entity ``B`` outside the
  window held at its last recovered mean. Only the window's blocks and their neighbours are read,
  so the cost does not grow with the state. The approximation: entities outside the window keep
  stale means, and later observations are linearised at them. Without a loop closure they move
  little, since they are tied to the window only through a few shared landmarks (on the test loop
  the estimates differ from those of full recovery by a few mm, against errors of tens of cm).
  When an update re-observes a landmark not seen for more than ``loop_gap_epochs`` epochs (a loop
  closure: the correction spreads over the whole trajectory) a full solve refreshes every mean,
  as Eustice et al. (2006) do at loop closures.

Reported estimates (:meth:`ESDF.pose`, :meth:`ESDF.landmarks`, :meth:`ESDF.trajectory`) always use
the exact solve (cached until the information changes); they never alter the filter's internal
linearisation points, so what a caller queries does not change what the filter does next.
Marginal covariances come from solving ``Lambda X = E`` for the needed columns only.

Angles inside the state are not wrapped: each entity's heading stays on the 2-pi branch it was
created on, so all the linear constraints ``H x ~ z - h(mu_bar) + H mu_bar`` stay consistent;
residuals and reported headings are wrapped.
"""

from __future__ import annotations

import logging

import numpy as np

from filters.geometry import compose, compose_jacobians, relative, relative_jacobians, wrap_angle
from filters.information import SparseInformation, symmetrise
from filters.models import (
    innovation,
    inverse_observe,
    motion,
    motion_jacobians,
    observe,
    observe_jacobians,
)
from filters.types import FeatureIds, LandmarkEstimate
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

RECOVERY_MODES = ("window", "full")


# --------------------------------------------------------------------------- odometry
class OdometryAccumulator:
    """Odometry compounded between epochs: increment ``Delta`` and its covariance ``Q``.

    ``Delta`` is the pose reached from the origin by the motion model (CM (8)), i.e. the robot's
    displacement in the frame of the last delayed pose; ``Q`` propagates the odometry covariance
    ``Sigma_u`` with the motion Jacobians, ``Q <- F Q F^T + G Sigma_u G^T``.
    """

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.delta = np.zeros(3)
        self.cov = np.zeros((3, 3))
        self.steps = 0
        self.time_s = 0.0
        self.distance_m = 0.0

    def add(self, u, dt: float, sigma_u) -> None:
        J_pose, J_u = motion_jacobians(self.delta, u, dt)
        self.delta = motion(self.delta, u, dt)
        self.cov = symmetrise(J_pose @ self.cov @ J_pose.T + J_u @ np.asarray(sigma_u) @ J_u.T)
        self.steps += 1
        self.time_s += dt
        self.distance_m += abs(float(u[0])) * dt

    def information(self, min_var: float) -> np.ndarray:
        """``Q^-1`` with ``Q``'s eigenvalues floored at ``min_var`` (``Q`` is singular at rest)."""
        w, V = np.linalg.eigh(self.cov)
        return symmetrise((V / np.maximum(w, min_var)) @ V.T)


def check_odometry(u, dt):
    """Validate a predict call: ``u`` finite of shape (2,), ``dt`` in [0, 1e3] s."""
    u = np.asarray(u, dtype=float)
    require(u.shape == (2,) and bool(np.all(np.isfinite(u))), "u", u, "a finite (v, omega) pair")
    if isinstance(dt, np.generic):
        dt = dt.item()
    check_range("dt", dt, 0.0, 1e3)
    return u, float(dt)


def check_observations(z, ids):
    """Validate an update call with known association: ``z`` (K, 2) finite, ``ids`` (K,) int."""
    require(
        ids is not None,
        "ids",
        ids,
        "an integer array (K,) of landmark ids (known data association), -1 for clutter",
    )
    z = np.asarray(z, dtype=float)
    if z.size == 0:
        z = np.zeros((0, 2))
    require(
        z.ndim == 2 and z.shape[1] == 2 and bool(np.all(np.isfinite(z))),
        "z",
        z,
        "an array (K, 2) of finite range-bearing pairs",
    )
    ids_arr = np.asarray(ids)
    require(
        ids_arr.shape == (len(z),)
        and (ids_arr.size == 0 or np.issubdtype(ids_arr.dtype, np.integer)),
        "ids",
        ids,
        f"an integer array of shape ({len(z)},) matching z",
    )
    return z, ids_arr.astype(np.int64)


def check_initial_pose(initial_pose) -> np.ndarray:
    """Validate a start pose (None = origin)."""
    x0 = np.zeros(3) if initial_pose is None else np.asarray(initial_pose, dtype=float)
    require(
        x0.shape == (3,) and bool(np.all(np.isfinite(x0))),
        "initial_pose",
        initial_pose,
        "a finite (x, y, theta)",
    )
    return x0


# --------------------------------------------------------------------------- the filters
class DelayedStateFilter:
    """What the ESDF and the relative-coordinate ESDF (:mod:`filters.relative_esdf`) share.

    The options and models both take (validated here), the information form ``(eta, Lambda)`` in
    :class:`SparseInformation` with one linearisation point per entity (``_mu``), odometry
    compounded between epochs (:class:`OdometryAccumulator`), estimates cached per state version,
    and the current pose as the last delayed pose (+) the pending odometry. A subclass provides
    ``_delayed_pose()`` (mean and covariance of the last delayed pose) and may extend
    ``_cache_stamp()``.
    """

    def __init__(self, sensor, clutter, odometry_noise, ids, recovery_window, min_odometry_var):
        require(hasattr(sensor, "R"), "sensor", sensor, "a RangeBearingSensor")
        require(
            hasattr(odometry_noise, "covariance"),
            "odometry_noise",
            odometry_noise,
            "a noise model with covariance(u, dt)",
        )
        require(
            isinstance(recovery_window, int) and 1 <= recovery_window <= 1000,
            "recovery_window",
            recovery_window,
            "an integer in [1, 1000]",
        )
        check_range("min_odometry_var", min_odometry_var, 0.0, 1.0, low_open=True)
        self.sensor = sensor
        self.clutter = clutter
        self.odometry_noise = odometry_noise
        self.ids = FeatureIds() if ids is None else ids
        self.recovery_window = recovery_window
        self.min_odometry_var = float(min_odometry_var)
        self._R = np.asarray(sensor.R, dtype=float)
        self._R_inv = np.linalg.inv(self._R)
        self.info = SparseInformation()
        self._mu: list[np.ndarray] = []
        self._odo = OdometryAccumulator()
        self.last_associations = np.zeros(0, dtype=np.int64)
        self._est_cache: dict[str, tuple[object, object]] = {}

    @property
    def state_size(self) -> int:
        """Dimension of the state (3 per pose, 2 per landmark coordinates, ...)."""
        return self.info.dim

    def information(self):
        """``(eta, Lambda)``: dense vector and symmetric ``scipy.sparse`` CSC matrix."""
        return self.info.vector(), self.info.matrix()

    def predict(self, u, dt) -> None:
        """Compound odometry ``u`` over ``dt`` into the pending increment (CM (8)); the state
        changes only at the next epoch."""
        u, dt = check_odometry(u, dt)
        if dt == 0.0:
            return
        self._odo.add(u, dt, self.odometry_noise.covariance(u, dt))

    @staticmethod
    def _check_heading(theta, std_rad) -> None:
        check_range("std_rad", std_rad, 0.0, 10.0, low_open=True)
        require(np.isfinite(theta), "theta", theta, "a finite angle in radians")

    def _cache_stamp(self):
        return self.info.version

    def _cached(self, key, fn):
        stamp = self._cache_stamp()
        hit = self._est_cache.get(key)
        if hit is not None and hit[0] == stamp:
            return hit[1]
        val = fn()
        self._est_cache[key] = (stamp, val)
        return val

    def _delayed_pose(self):
        raise NotImplementedError

    def pose(self):
        """Current pose = last delayed pose (+) pending odometry, with covariance (3,), (3, 3)."""
        m, P = self._delayed_pose()
        delta = self._odo.delta
        Ja, Jb = compose_jacobians(m, delta)
        mean = compose(m, delta)
        return mean, symmetrise(Ja @ P @ Ja.T + Jb @ self._odo.cov @ Jb.T)


class ESDF(DelayedStateFilter):
    """Exactly Sparse Delayed-state Filter with known data association (CM section II).

    Parameters
    ----------
    sensor : RangeBearingSensor (its ``R`` is the observation noise).
    clutter : ClutterModel or None; unused -- with known association, observations whose id is
        -1 (false alarms) are simply dropped.
    odometry_noise : any model with ``covariance(u, dt) -> (2, 2)`` (e.g. ``ChongKleemanNoise``).
    ids : FeatureIds shared with other maps (a fresh counter if None).
    initial_pose : (3,) start pose; ``initial_pose_std`` its prior std (x, y, theta), > 0.
    recovery : ``"window"`` (constant-time partial recovery) or ``"full"`` (sparse solve every
        update); see the module docstring.
    recovery_window : delayed poses in the active window (1..1000).
    loop_gap_epochs : a re-observation after more than this many epochs triggers a full solve.
    min_odometry_var : floor on the eigenvalues of the compounded odometry covariance.
    """

    def __init__(
        self,
        sensor,
        clutter=None,
        odometry_noise=None,
        ids: FeatureIds | None = None,
        *,
        initial_pose=None,
        initial_pose_std=(1e-3, 1e-3, 1e-4),
        recovery: str = "window",
        recovery_window: int = 4,
        loop_gap_epochs: int = 10,
        min_odometry_var: float = 1e-10,
    ):
        super().__init__(sensor, clutter, odometry_noise, ids, recovery_window, min_odometry_var)
        require(recovery in RECOVERY_MODES, "recovery", recovery, f"one of {RECOVERY_MODES}")
        require(
            isinstance(loop_gap_epochs, int) and 1 <= loop_gap_epochs <= 10**6,
            "loop_gap_epochs",
            loop_gap_epochs,
            "an integer in [1, 1000000]",
        )
        std0 = np.asarray(initial_pose_std, dtype=float)
        require(
            std0.shape == (3,) and bool(np.all(np.isfinite(std0) & (std0 > 0))),
            "initial_pose_std",
            initial_pose_std,
            "three positive finite stds (x, y, theta)",
        )
        x0 = check_initial_pose(initial_pose)
        self.recovery = recovery
        self.loop_gap_epochs = loop_gap_epochs
        self._poses: list[int] = []
        self._pose_landmarks: list[list[int]] = []
        self._lm_entity: dict[int, int] = {}
        self._lm_fid: dict[int, int] = {}
        self._lm_last_epoch: dict[int, int] = {}
        self.n_full_recoveries = 0
        self.last_update_full_recovery = False

        e0 = self._new_entity(3, x0)
        self.info.add_information([e0], [np.eye(3)], np.diag(1.0 / std0**2), x0)
        self._poses.append(e0)
        self._pose_landmarks.append([])

    # ----------------------------------------------------------------- bookkeeping
    def _new_entity(self, size, mean) -> int:
        e = self.info.add_entity(size)
        self._mu.append(np.asarray(mean, dtype=float).copy())
        return e

    @property
    def n_delayed_poses(self) -> int:
        return len(self._poses)

    @property
    def n_landmarks(self) -> int:
        return len(self._lm_entity)

    # ----------------------------------------------------------------- filter steps
    def _epoch_pose(self) -> int:
        """The delayed pose of the current epoch: augment with the pending odometry if any."""
        if self._odo.steps == 0:
            return self._poses[-1]
        prev = self._poses[-1]
        mu_prev = self._mu[prev]
        delta = self._odo.delta
        mu_new = compose(mu_prev, delta)
        mu_new[2] = mu_prev[2] + wrap_angle(delta[2])  # keep the heading on a continuous branch
        e = self._new_entity(3, mu_new)
        Ja, Jb = relative_jacobians(mu_prev, mu_new)
        res = delta - relative(mu_prev, mu_new)
        res[2] = wrap_angle(res[2])
        # State augmentation (Eustice et al. 2006) as a relative-pose constraint, CM (4)-(5).
        self.info.add_information(
            [prev, e],
            [Ja, Jb],
            self._odo.information(self.min_odometry_var),
            res + Ja @ mu_prev + Jb @ mu_new,
        )
        self._poses.append(e)
        self._pose_landmarks.append([])
        self._odo.reset()
        return e

    def update(self, z, ids=None) -> None:
        """Integrate range-bearing observations ``z`` (K, 2) of landmarks ``ids`` (K,).

        ``ids`` are known associations (CM IV.A): any integer labels, -1 for a false alarm. A new
        delayed pose is added at this epoch (if the robot moved), new landmarks are initialised
        from their first observation, and re-observations are integrated with CM (4)-(5), all
        linearised at the means before this update. Nothing happens for K = 0.
        """
        z, ids = check_observations(z, ids)
        self.last_associations = np.full(len(z), -1, dtype=np.int64)
        self.last_update_full_recovery = False
        valid = np.flatnonzero(ids >= 0)
        if valid.size == 0:
            return
        k = self._epoch_pose()
        epoch = len(self._poses) - 1
        mu_k = self._mu[k]
        known, new_obs = [], []
        loop = False
        for i in valid:
            j = int(ids[i])
            if j in self._lm_entity:
                known.append(i)
                loop |= epoch - self._lm_last_epoch.get(j, epoch) > self.loop_gap_epochs
            else:
                self._lm_entity[j] = self._new_entity(2, inverse_observe(mu_k, z[i]))
                self._lm_fid[j] = int(self.ids.new(1)[0])
                new_obs.append(i)
            self.last_associations[i] = self._lm_fid[j]
        obs = np.asarray(new_obs + known, dtype=int)
        ents = [self._lm_entity[int(ids[i])] for i in obs]
        m = np.array([self._mu[e] for e in ents])
        H_pose, H_m = observe_jacobians(mu_k, m)
        nu = innovation(z[obs], observe(mu_k, m))
        for n, e in enumerate(ents):
            rhs = nu[n] + H_pose[n] @ mu_k + H_m[n] @ self._mu[e]
            self.info.add_information([k, e], [H_pose[n], H_m[n]], self._R_inv, rhs)
        for i, e in zip(obs, ents, strict=True):
            self._lm_last_epoch[int(ids[i])] = epoch
            if e not in self._pose_landmarks[-1]:
                self._pose_landmarks[-1].append(e)
        self._recover(full=loop)

    def update_heading(self, theta, std_rad) -> None:
        """A compass measurement of the current heading (BB 5.5) on this epoch's delayed pose."""
        self._check_heading(theta, std_rad)
        k = self._epoch_pose()
        mu_k = self._mu[k]
        H = np.array([[0.0, 0.0, 1.0]])
        rhs = np.array([wrap_angle(theta - mu_k[2]) + mu_k[2]])
        self.info.add_information([k], [H], np.array([[1.0 / std_rad**2]]), rhs)
        self._recover(full=False)

    # ----------------------------------------------------------------- recovery
    def _recover(self, full: bool) -> None:
        if full or self.recovery == "full":
            self.recover_means()
            self.last_update_full_recovery = True
            return
        window = self._poses[-self.recovery_window :]
        active = list(window)
        for lms in self._pose_landmarks[-self.recovery_window :]:
            active.extend(lms)
        for e, m in self.info.solve_window(active, self._mu).items():
            self._mu[e] = m

    def recover_means(self) -> None:
        """Full recovery: refresh every linearisation point with the exact sparse solve."""
        mu = self.info.mean()
        for e in range(self.info.n_entities):
            self._mu[e] = self.info.mean_of(e, mu).copy()
        self.n_full_recoveries += 1

    # ----------------------------------------------------------------- estimates
    def _delayed_pose(self):
        def fn():
            e = self._poses[-1]
            return self.info.mean_of(e).copy(), self.info.marginals([e])[0]

        return self._cached("last_pose", fn)

    def trajectory(self) -> np.ndarray:
        """Means of all delayed poses (K, 3), headings wrapped (exact solve)."""
        mu = self.info.mean()
        out = np.array([self.info.mean_of(e, mu) for e in self._poses])
        out[:, 2] = wrap_angle(out[:, 2])
        return out

    def landmarks(self) -> LandmarkEstimate:
        """All landmarks: feature ids, exact means and marginal covariances, existence 1."""

        def fn():
            if not self._lm_entity:
                return LandmarkEstimate.empty()
            ext = list(self._lm_entity)
            ents = [self._lm_entity[j] for j in ext]
            mu = self.info.mean()
            means = np.array([self.info.mean_of(e, mu) for e in ents])
            covs = np.array(self.info.marginals(ents))
            fids = np.array([self._lm_fid[j] for j in ext], dtype=np.int64)
            return LandmarkEstimate(fids, means, covs, np.ones(len(ext)))

        return self._cached("landmarks", fn)

    def landmark_ids(self) -> np.ndarray:
        """The external (association) ids of the landmarks, in :meth:`landmarks` order."""
        return np.array(list(self._lm_entity), dtype=np.int64)
