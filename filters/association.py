"""Data association: chi-square gating, nearest neighbour and JCBB (Neira & Tardos 2001).

One small core serves both uses of the system:

* **observations vs map** (EKF-SLAM update): the innovation of observation ``i`` paired with
  feature ``j`` is ``nu_ij = z_i - h(x_v, m_j)`` (bearing wrapped), linearised as
  ``nu_ij ~ -H_ij dx + w_i`` with ``H_ij = [H_pose | H_m]`` acting on the state columns of the pose
  and of feature ``j``, and ``w_i ~ N(0, R)`` the noise of observation ``i``;
* **feature vs feature** (sub-map fusion, BB section 4): the innovation of local feature ``i``
  paired with global feature ``j`` is the Cartesian difference ``nu_ij = l_i - m_j`` of two blocks
  of one joint state, i.e. ``H_ij = [I | -I]`` on their columns and no noise.

In both cases a pairing ``c = (i, j)`` is described by its innovation ``nu_c`` (m,), the state
columns it touches ``cols_c`` (q,), its Jacobian on those columns ``J_c`` (m, q), and optional
noise ``R_c`` shared by every pairing of the same observation. The covariance of two pairings'
innovations is then ``J_c P[cols_c, cols_c'] J_c'^T + [i = i'] R`` (:func:`joint_covariance`), and
everything below -- individual gates, nearest neighbour, JCBB -- works on innovations and these
covariances only.

Individual compatibility: ``d2_ij = nu_ij^T S_ij^-1 nu_ij <= chi2_m(p)``, vectorised over all
observations x features.

JCBB (Neira & Tardos 2001) searches the interpretation tree observation by observation; each node
either pairs the observation with a feature not yet used (if individually compatible and the
enlarged hypothesis stays jointly compatible, ``D2_H <= chi2_{m |H|}(p)``) or leaves it unpaired.
The joint test is incremental: with the current hypothesis' joint innovation ``nu_H``, the inverse
``S_H^-1`` of its covariance and its distance ``D2_H``, adding pairing ``c`` with cross-covariance
``C = cov(nu_H, nu_c)`` and ``S_c = cov(nu_c)`` uses the Schur complement
``T = S_c - C^T S_H^-1 C`` and the conditional innovation ``e = nu_c - C^T S_H^-1 nu_H``::

    D2_{H+c} = D2_H + e^T T^-1 e
    S_{H+c}^-1 = [[S_H^-1 + K T^-1 K^T, -K T^-1], [-T^-1 K^T, T^-1]],   K = S_H^-1 C

so one node costs O((m |H|)^2) instead of a fresh O((m |H|)^3) factorisation. Branch and bound
maximises the number of pairings, ties broken by the lower joint distance ``D2``: a branch is
explored only if the pairings it already has plus the observations still to come (with at least
one candidate) can beat the best hypothesis found, or equal its count with a smaller ``D2`` (``D2``
only grows along a branch, so it is a valid bound).

Node budget: every joint-compatibility test counts as one node. The full tree has
``prod_i (c_i + 1)`` leaves for ``c_i`` candidates of observation ``i``, which explodes when many
observations fall in many gates (heavy clutter, large uncertainty). When ``node_budget`` tests have
been made the search stops and returns the best hypothesis found so far (``exhausted=True``); the
depth-first order (candidates before the "unpaired" branch, each observation's candidates in
increasing individual distance) makes that first hypothesis a greedy nearest-neighbour-like
jointly compatible one, refined as far as the budget allows. The default of 5000 nodes costs at most
a few tenths of a second in Python and is far more than ordinary scans need (tens of nodes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaincinv

from filters.models import innovation, observe, observe_jacobians
from filters.validation import check_range, require

DEFAULT_NODE_BUDGET = 5000


def validate_gate_probability(value, field="gate_probability"):
    """A gate probability must lie in (0, 1)."""
    check_range(field, value, 0.0, 1.0, low_open=True, high_open=True)


def validate_node_budget(value, field="node_budget"):
    require(
        isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1,
        field,
        value,
        "an integer >= 1",
    )


def chi_square_quantile(probability, dof):
    """``scipy.stats.chi2.ppf(probability, dof)`` for ``dof > 0`` and ``probability`` in [0, 1],
    to the bit: the same ``2 gammaincinv(dof / 2, probability)`` without scipy.stats, whose
    import costs a process 0.3-0.9 s of CPU (docs/PERFORMANCE.md; the env imports this module and
    :mod:`slam_gym.metrics`, the only two that needed it)."""
    return 2 * gammaincinv(np.asarray(dof) / 2, probability)


class ChiSquareTable:
    """Chi-square gate thresholds ``chi2.ppf(p, m k)`` for k = 1, 2, ... (extended on demand)."""

    def __init__(self, probability: float, dim: int):
        validate_gate_probability(probability)
        self.probability = float(probability)
        self.dim = int(dim)
        self._table = chi_square_quantile(self.probability, self.dim * np.arange(1, 17))

    def __call__(self, k: int) -> float:
        """Threshold for a hypothesis of ``k`` pairings (k >= 1)."""
        if k > len(self._table):
            size = max(k, 2 * len(self._table))
            self._table = chi_square_quantile(self.probability,
                                              self.dim * np.arange(1, size + 1))
        return float(self._table[k - 1])

    def table(self, k_max: int) -> np.ndarray:
        self(max(k_max, 1))
        return self._table[:k_max]


# --------------------------------------------------------------------------- covariances
def innovation_covariances(P, cols, J, noise=None):
    """Innovation covariances ``S_c = J_c P[cols_c, cols_c] J_c^T + noise`` (..., m, m).

    ``cols`` (..., q) integer state columns of each pairing, ``J`` (..., m, q) its Jacobian on
    those columns (leading axes broadcast), ``noise`` (m, m) or None.
    """
    cols = np.asarray(cols)
    P_sub = P[cols[..., :, None], cols[..., None, :]]
    S = np.einsum("...ij,...jk,...lk->...il", J, P_sub, J)
    if noise is not None:
        S = S + noise
    return 0.5 * (S + np.swapaxes(S, -1, -2))


def joint_covariance(P, cols, J, noise=None, groups=None):
    """Joint covariance (n m, n m) of the innovations of ``n`` pairings.

    Block ``(c, c')`` is ``J_c P[cols_c, cols_c'] J_c'^T``, plus ``noise`` where
    ``groups[c] == groups[c']`` (pairings of the same observation share its noise).
    ``cols`` (n, q), ``J`` (n, m, q).
    """
    cols = np.asarray(cols)
    n, m = J.shape[0], J.shape[1]
    P_sub = P[cols[:, :, None, None], cols[None, None, :, :]]  # (n, q, n, q)
    M = np.einsum("amq,aqbr,bkr->ambk", J, P_sub, J)
    if noise is not None and groups is not None:
        same = np.asarray(groups)[:, None] == np.asarray(groups)[None, :]
        M = M + same[:, None, :, None] * noise[None, :, None, :]
    M = M.reshape(n * m, n * m)
    return 0.5 * (M + M.T)


# --------------------------------------------------------------------------- gating
def mahalanobis_squared(nu, S):
    """``nu^T S^-1 nu`` for nu (..., m) and S (..., m, m) (broadcast)."""
    nu = np.asarray(nu, dtype=float)
    S = np.asarray(S, dtype=float)
    if nu.shape[-1] == 2:  # range-bearing and point pairings: the 2x2 inverse in closed form
        a, b, c = S[..., 0, 0], 0.5 * (S[..., 0, 1] + S[..., 1, 0]), S[..., 1, 1]
        n0, n1 = nu[..., 0], nu[..., 1]
        return (c * n0 * n0 - 2.0 * b * n0 * n1 + a * n1 * n1) / (a * c - b * b)
    S = np.broadcast_to(S, nu.shape[:-1] + S.shape[-2:])
    sol = np.linalg.solve(S, nu[..., None])[..., 0]
    return np.einsum("...i,...i->...", nu, sol)


def _gate_threshold(gate, dim):
    """The individual gate: ``gate`` is a gate probability or a :class:`ChiSquareTable`."""
    if isinstance(gate, ChiSquareTable):
        require(gate.dim == dim, "gate.dim", gate.dim, f"equal to {dim}")
        return gate(1)
    validate_gate_probability(gate)
    return float(chi_square_quantile(gate, dim))


def individual_compatibility(nu, S, gate):
    """Chi-square gate on every pairing: returns ``(d2, mask)`` of shape nu.shape[:-1].

    ``gate`` is the gate probability or a :class:`ChiSquareTable`.
    """
    d2 = mahalanobis_squared(nu, S)
    return d2, d2 <= _gate_threshold(gate, nu.shape[-1])


@dataclass
class Candidates:
    """Individually compatible pairings and the joint covariance of their innovations.

    ``obs`` (n,) observation index, ``feat`` (n,) feature index, ``nu`` (n, m) innovations, ``d2``
    (n,) individual distances, ``M`` (n m, n m) joint covariance, ``n_obs`` observations in all.
    """

    obs: np.ndarray
    feat: np.ndarray
    nu: np.ndarray
    d2: np.ndarray
    M: np.ndarray
    n_obs: int

    @property
    def dim(self) -> int:
        return self.nu.shape[1]

    def __len__(self) -> int:
        return len(self.obs)


def build_candidates(nu, d2, mask, P, cols, J, noise=None) -> Candidates:
    """Collect the gated pairings of ``mask`` (K, N) with their joint covariance.

    ``nu`` (K, N, m), ``d2`` (K, N); ``cols`` (K|1, N, q) and ``J`` (K|1, N, m, q) describe each
    pairing's linearisation (see the module docstring); ``noise`` (m, m) is the per-observation
    noise shared by pairings of the same observation (None for noise-free differences).
    """
    K, N, m = nu.shape
    obs, feat = np.nonzero(mask)
    q = np.shape(cols)[-1]
    cols_c = np.broadcast_to(cols, (K, N, q))[obs, feat]
    J_c = np.broadcast_to(J, (K, N, m, q))[obs, feat]
    M = joint_covariance(P, cols_c, J_c, noise, obs) if len(obs) else np.zeros((0, 0))
    return Candidates(
        obs=obs.astype(np.int64),
        feat=feat.astype(np.int64),
        nu=nu[obs, feat],
        d2=d2[obs, feat],
        M=M,
        n_obs=K,
    )


# --------------------------------------------------------------------------- nearest neighbour
def nearest_neighbour(d2, mask):
    """Greedy nearest neighbour: pairings taken in increasing ``d2``, each feature at most once.

    Returns (K,) int64: the feature index paired with each observation, or -1. No joint test: this
    is the baseline JCBB improves on.
    """
    K = d2.shape[0]
    pairing = np.full(K, -1, dtype=np.int64)
    obs, feat = np.nonzero(mask)
    order = np.argsort(d2[obs, feat], kind="stable")
    used = set()
    for o, f in zip(obs[order], feat[order], strict=True):
        if pairing[o] < 0 and f not in used:
            pairing[o] = f
            used.add(int(f))
    return pairing


# --------------------------------------------------------------------------- JCBB
@dataclass
class Hypothesis:
    """A jointly compatible association: ``pairing`` (K,) feature index per observation or -1."""

    pairing: np.ndarray
    n_pairs: int
    d2: float
    n_nodes: int
    exhausted: bool


def joint_distance(cands: Candidates, chosen) -> float:
    """Joint Mahalanobis distance of a set of candidates, computed from scratch (for tests)."""
    chosen = np.asarray(chosen, dtype=np.int64)
    if len(chosen) == 0:
        return 0.0
    m = cands.dim
    rows = (chosen[:, None] * m + np.arange(m)).ravel()
    nu = cands.nu[chosen].ravel()
    return float(nu @ np.linalg.solve(cands.M[np.ix_(rows, rows)], nu))


def jcbb(cands: Candidates, thresholds: ChiSquareTable, node_budget: int = DEFAULT_NODE_BUDGET):
    """Joint compatibility branch and bound (Neira & Tardos 2001) over ``cands``.

    ``thresholds`` gives the joint gate for k pairings (a :class:`ChiSquareTable` built with the
    gate probability and the innovation dimension). See the module docstring for the incremental
    test, the bound and the node budget.
    """
    validate_node_budget(node_budget)
    K = cands.n_obs
    m = cands.dim
    pairing_best = np.full(K, -1, dtype=np.int64)
    if len(cands) == 0:
        return Hypothesis(pairing_best, 0, 0.0, 0, False)
    require(thresholds.dim == m, "thresholds.dim", thresholds.dim, f"equal to {m}")

    # observations that have candidates, in order; each one's candidates by increasing d2
    order = np.unique(cands.obs)
    per_obs = []
    for o in order:
        idx = np.flatnonzero(cands.obs == o)
        per_obs.append(idx[np.argsort(cands.d2[idx], kind="stable")])
    L = len(order)
    gates = thresholds.table(L)
    M = cands.M
    nu_all = cands.nu
    feat = cands.feat
    rows_of = np.arange(len(cands))[:, None] * m + np.arange(m)

    best = {"n": 0, "d2": 0.0, "chosen": ()}
    state = {"nodes": 0, "exhausted": False}

    def promising(n_possible, d2):
        return n_possible > best["n"] or (n_possible == best["n"] and d2 < best["d2"])

    def record(chosen, d2):
        n = len(chosen)
        if n > best["n"] or (n == best["n"] and d2 < best["d2"]):
            best.update(n=n, d2=d2, chosen=tuple(chosen))

    def search(level, chosen, used, rows, nu_H, S_inv, d2):
        if level == L or state["exhausted"]:
            return
        n = len(chosen)
        remaining_after = L - level - 1
        if promising(n + 1 + remaining_after, d2):
            for c in per_obs[level]:
                if feat[c] in used:
                    continue
                if state["nodes"] >= node_budget:
                    state["exhausted"] = True
                    return
                state["nodes"] += 1
                r = rows_of[c]
                S_c = M[r[:, None], r[None, :]]
                if n == 0:
                    T = S_c
                    e = nu_all[c]
                else:
                    C = M[rows[:, None], r[None, :]]
                    Kg = S_inv @ C
                    T = S_c - C.T @ Kg
                    e = nu_all[c] - Kg.T @ nu_H
                try:
                    T_inv = np.linalg.inv(0.5 * (T + T.T))
                except np.linalg.LinAlgError:
                    continue
                d2_new = d2 + float(e @ T_inv @ e)
                if not (d2_new <= gates[n]) or not promising(n + 1 + remaining_after, d2_new):
                    continue
                if n == 0:
                    S_inv_new = T_inv
                else:
                    KT = Kg @ T_inv
                    k_rows = len(rows)
                    S_inv_new = np.empty((k_rows + m, k_rows + m))
                    S_inv_new[:k_rows, :k_rows] = S_inv + KT @ Kg.T
                    S_inv_new[:k_rows, k_rows:] = -KT
                    S_inv_new[k_rows:, :k_rows] = -KT.T
                    S_inv_new[k_rows:, k_rows:] = T_inv
                chosen.append(c)
                used.add(feat[c])
                record(chosen, d2_new)
                search(
                    level + 1,
                    chosen,
                    used,
                    np.concatenate([rows, r]),
                    np.concatenate([nu_H, nu_all[c]]),
                    S_inv_new,
                    d2_new,
                )
                chosen.pop()
                used.discard(feat[c])
                if state["exhausted"]:
                    return
        if promising(n + remaining_after, d2):
            search(level + 1, chosen, used, rows, nu_H, S_inv, d2)

    search(0, [], set(), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 0)), 0.0)
    for c in best["chosen"]:
        pairing_best[cands.obs[c]] = feat[c]
    return Hypothesis(
        pairing=pairing_best,
        n_pairs=best["n"],
        d2=float(best["d2"]),
        n_nodes=state["nodes"],
        exhausted=state["exhausted"],
    )


# --------------------------------------------------------------------------- the two uses
@dataclass
class RangeBearingPrediction:
    """Predicted observations of N features from the pose: ``zhat`` (N, 2), Jacobians, ``S``."""

    zhat: np.ndarray
    H_pose: np.ndarray
    H_m: np.ndarray
    cols: np.ndarray
    J: np.ndarray
    S: np.ndarray


def predict_range_bearing(x, P, pose_cols, feature_cols, R) -> RangeBearingPrediction:
    """Predicted range-bearing observations of the features of a joint state.

    ``pose_cols`` (3,) and ``feature_cols`` (N, 2) index the pose and feature blocks in ``x``;
    ``S`` (N, 2, 2) is the individual innovation covariance ``H P H^T + R``, independent of the
    observation it is paired with.
    """
    pose_cols = np.asarray(pose_cols, dtype=np.int64)
    feature_cols = np.asarray(feature_cols, dtype=np.int64).reshape(-1, 2)
    N = len(feature_cols)
    pose = x[pose_cols]
    m = x[feature_cols]
    zhat = observe(pose, m)
    H_pose, H_m = observe_jacobians(pose, m)
    cols = np.concatenate([np.broadcast_to(pose_cols, (N, 3)), feature_cols], axis=1)
    J = np.concatenate([H_pose, H_m], axis=2)
    S = innovation_covariances(P, cols, J, R)
    return RangeBearingPrediction(zhat, H_pose, H_m, cols, J, S)


def range_bearing_candidates(z, x, P, pred: RangeBearingPrediction, R, gate):
    """Gate observations ``z`` (K, 2) against predicted features and collect the candidates.

    Returns ``(candidates, d2 (K, N), mask (K, N))``; bearings are wrapped in the innovation, so
    an observation at +pi - eps and a prediction at -pi + eps differ by 2 eps. ``gate``: the gate
    probability or a :class:`ChiSquareTable` of dimension 2.
    """
    z = np.asarray(z, dtype=float).reshape(-1, 2)
    nu = innovation(z[:, None, :], pred.zhat[None, :, :])
    d2, mask = individual_compatibility(nu, pred.S[None], gate)
    cands = build_candidates(nu, d2, mask, P, pred.cols[None], pred.J[None], noise=R)
    return cands, d2, mask


def point_difference_candidates(x, P, cols_a, cols_b, gate):
    """Gate Cartesian differences ``a_i - b_j`` of 2-D points in one joint Gaussian.

    ``cols_a`` (K, 2), ``cols_b`` (N, 2) index the points in ``x``/``P`` (for sub-map fusion: the
    local features carried into the global frame and the global features). The innovation
    covariance includes the cross-covariances of the two points. ``gate``: the gate probability or
    a :class:`ChiSquareTable` of dimension 2. Returns
    ``(candidates, d2 (K, N), mask (K, N))``.
    """
    cols_a = np.asarray(cols_a, dtype=np.int64).reshape(-1, 2)
    cols_b = np.asarray(cols_b, dtype=np.int64).reshape(-1, 2)
    K, N = len(cols_a), len(cols_b)
    nu = x[cols_a][:, None, :] - x[cols_b][None, :, :]
    cols = np.concatenate(
        [np.broadcast_to(cols_a[:, None, :], (K, N, 2)), np.broadcast_to(cols_b[None], (K, N, 2))],
        axis=2,
    )
    J = np.broadcast_to(np.hstack([np.eye(2), -np.eye(2)]), (K, N, 2, 4))
    S = innovation_covariances(P, cols, J)
    d2, mask = individual_compatibility(nu, S, gate)
    cands = build_candidates(nu, d2, mask, P, cols, J)
    return cands, d2, mask
