"""Correspondence voting and conversion of a FastSLAM posterior to one Gaussian (BB 3.1, 3.2).

A FastSLAM particle set is a Gaussian mixture (BB 2.1): particle ``p`` carries a weight ``w^p``, a
pose ``v^p`` with zero covariance and independent Gaussian features ``(mu_i^p, Sigma_i^p)``. With
unknown associations the particles' feature lists differ, so every feature also carries a
*correspondence id* ``gamma_i^p`` naming the *common feature* it is a hypothesis about (BB (8)).

Voting (BB 3.1)
---------------
For one observation each particle votes, with its weight, for *clutter*, for the common id of the
existing feature it associated the observation with, or for *new feature*. The heaviest option
wins and every feature modified or created by that observation takes the winning id
(:func:`correspondence_vote` computes the winner; the filter writes the ids). A feature a particle
holds that has never received an id (``gamma = -1``: it was created by an observation whose vote
went to clutter) is not yet a common feature, so a vote for it counts as a vote for *new feature*.
The vote margin (winner share minus runner-up share) measures association ambiguity.

**Ids stay unique within a particle** (:func:`assign_correspondence_ids`). Taken literally, the
rule above can give one particle two features with the same id: a particle that associated the
observation with its feature ``f`` (id ``c``), or created a new feature ``f`` for it, while it
already holds another feature ``g`` with the winning id ``W``, would end with ``f`` and ``g``
both called ``W``. The common map keeps one feature per id and particle (BB 3.2), so the other
is lost from it, and the ids of a landmark cluster collapse into one (measured on MRCLAM
Dataset 7: about 5 common features where known association gives 12-15). We therefore give
``W`` to ``f`` only if its particle holds no other feature with ``W``; otherwise ``f`` keeps its
id (``c``, or -1 for a feature just created: not yet a common feature, as when clutter wins).
The particle thereby keeps its own, minority, hypothesis that ``f`` and ``g`` are two landmarks.

Conversion (BB 3.2, (6), (7), (9))
----------------------------------
``delta(n, p)`` (BB 3.2) maps common feature ``n`` to the slot of particle ``p`` that represents it
(:func:`common_features`). Two corner cases, as BB 3.2 prescribes and with our choices:

* **Several features of one particle with the same id.** BB picks one at random. We pick the one
  with the highest existence probability, ties broken by the smallest covariance trace, then the
  lowest slot: a particle's best-supported hypothesis. The choice is deterministic, so converting
  (or reporting landmarks, which uses the same selection) never draws random numbers and calling it
  for diagnostics cannot change the filter's random stream.
* **A particle without the feature** is ignored for that feature's moments: the weights are
  renormalised over the particles that hold it (mean, BB (6)), and each cross-covariance term of
  BB (7) is summed over the particles that hold *both* entries, with weights renormalised over that
  subset and deviations taken from the means of (6). Two features that no particle holds together
  get a zero cross-covariance.

The existence probability of a common feature is the weighted sum of its particles' existence
probabilities with the *full* weights (a particle lacking the feature contributes 0), as BB 3.2
suggests ("weighted sums analogous to Equation 6"), so features the particles do not agree upon
have a low probability of existence and are not converted.

Pose heading: the mean heading is the weighted circular mean ``atan2(sum w sin, sum w cos)`` and
heading deviations are wrapped around it; the covariance is ``sum w d d^T`` with those deviations
(no re-centring).

Positive definiteness: the pose block from a set of identical poses is zero (right after a
restart), and the subset-wise cross terms can make the matrix indefinite. The result is therefore
projected onto the symmetric matrices with eigenvalues ``>= eig_floor`` (default
:data:`EIGENVALUE_FLOOR` = 1e-10, i.e. a std of 1e-5 m or rad, far below any real uncertainty):
the nearest such matrix in the Frobenius norm (Higham 1988) clips the eigenvalues at the floor.
This happens only when the smallest eigenvalue is below the floor; it is logged at debug level.

A cloud with shared ancestry (issue #14): BB (7) reads the particles as independent draws. After
resampling they are not, and a local map's pose and features relative to its start are carried
by the few lineages (ancestors at the restart) that survive. :func:`moment_match` and
:func:`pose_moments` take the particles' ``lineages`` and add :func:`lineage_covariance`: the
Monte Carlo variance of the weighted mean (Chan & Lai 2013) and the small-sample bias of the
spread between few weighted lineages. The means are unchanged; the covariance only grows.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numba import njit

from filters.existence import CONFIRMED_PROBABILITY
from filters.geometry import wrap_angle, wrap_angle_one
from filters.types import GaussianMap
from filters.validation import check_range, require

logger = logging.getLogger(__name__)

CLUTTER_VOTE = -1
"""Vote (and winner) code: the observation is a false alarm."""
NEW_VOTE = -2
"""Vote code: the observation starts a new common feature."""
EIGENVALUE_FLOOR = 1e-10
"""Smallest eigenvalue of a converted covariance (see module docstring)."""


# --------------------------------------------------------------------------- voting (BB 3.1)
@dataclass(frozen=True)
class VoteResult:
    """Outcome of one weighted vote: ``winner`` is a common id, CLUTTER_VOTE or NEW_VOTE.

    ``options`` (sorted) and ``shares`` give every option that got a vote and its weight share;
    ``margin`` is the winner's share minus the runner-up's (the winner's share if unanimous).
    """

    winner: int
    margin: float
    options: np.ndarray
    shares: np.ndarray

    def share_of(self, option: int) -> float:
        hit = np.flatnonzero(self.options == option)
        return float(self.shares[hit[0]]) if len(hit) else 0.0


def correspondence_vote(weights, votes) -> VoteResult:
    """BB 3.1: weighted majority vote of the particles for one observation.

    ``weights`` (P,) non-negative (normalised here); ``votes`` (P,) int: a common id (>= 0),
    :data:`CLUTTER_VOTE` or :data:`NEW_VOTE`. Ties go to the smallest option code (NEW_VOTE, then
    CLUTTER_VOTE, then the lowest id), so the result is deterministic.
    """
    weights = np.asarray(weights, dtype=float)
    votes = np.asarray(votes, dtype=np.int64)
    require(weights.ndim == 1 and len(weights) > 0, "weights", weights.shape, "a non-empty (P,)")
    require(votes.shape == weights.shape, "votes", votes.shape, f"shape {weights.shape}")
    require(bool(np.all(votes >= NEW_VOTE)), "votes", votes.min(), ">= NEW_VOTE (-2)")
    require(bool(weights.min() >= 0.0), "weights", weights.min(), "non-negative")
    total = weights.sum()
    require(bool(np.isfinite(total) and total > 0.0), "weights", total, "a positive finite sum")
    options = np.empty(len(votes), dtype=np.int64)
    shares = np.empty(len(votes))
    n = tally_votes(weights, votes, options, shares)
    top, margin = heaviest_option(shares, n)
    return VoteResult(int(options[top]), float(margin), options[:n].copy(), shares[:n].copy())


@njit(cache=True)
def tally_votes(weights, votes, options, shares):
    """Distinct options in ascending order and their weight shares; returns their number."""
    total = weights.sum()
    first, last = votes.min(), votes.max()
    if first == last:  # unanimous (the common case): no sorting needed
        options[0] = first
        shares[0] = 1.0
        return 1
    # the options in order of first appearance, each share summed in particle order (as a
    # stable sort by vote would sum it; a scan has a handful of options, so no sort of P votes)
    n = 0
    for p in range(len(votes)):
        j = 0
        while j < n and options[j] != votes[p]:
            j += 1
        if j == n:
            options[n] = votes[p]
            shares[n] = 0.0
            n += 1
        shares[j] += weights[p]
    for i in range(1, n):  # ascending options (insertion sort of the few), shares alongside
        option, share = options[i], shares[i]
        j = i - 1
        while j >= 0 and options[j] > option:
            options[j + 1], shares[j + 1] = options[j], shares[j]
            j -= 1
        options[j + 1], shares[j + 1] = option, share
    for i in range(n):
        shares[i] /= total
    return n


@njit(cache=True)
def heaviest_option(shares, n):
    """The heaviest option (the first on ties) and its margin over the runner-up."""
    top = 0
    for i in range(1, n):
        if shares[i] > shares[top]:
            top = i
    runner_up = 0.0
    for i in range(n):
        if i != top and shares[i] > runner_up:
            runner_up = shares[i]
    return top, shares[top] - runner_up


@njit(cache=True)
def vote_one_observation(log_weights, votes, weights, options, shares):
    """BB 3.1 for one observation from its (P,) log weights: fills ``weights`` with
    ``exp(log_weights - max)`` and ``options``/``shares`` as :func:`tally_votes` does; returns the
    winner, its margin and the number of options (scratch arrays of length P, reused by the
    caller across the observations of a scan)."""
    top_log = log_weights.max()
    for p in range(len(weights)):
        weights[p] = np.exp(log_weights[p] - top_log)
    n = tally_votes(weights, votes, options, shares)
    top, margin = heaviest_option(shares, n)
    return options[top], margin, n


@njit(cache=True)
def vote_scan(log_weights, votes, clutter_prob):
    """BB 3.1 for the K observations of a scan: the one vote loop of the filters.

    ``log_weights`` (K, P): each particle's log weight after observation k; ``votes`` (K, P) as
    in :func:`correspondence_vote`; ``clutter_prob`` (K, P): the probability, under each
    particle's hypothesis, that observation k is a false alarm. Returns per observation the
    winner and its margin (as :func:`correspondence_vote` with the weights ``exp(log_weights[k]
    - max)``) and the weighted probability that it is a false alarm, ``sum_p w_k^p c_k^p``."""
    K, P = votes.shape
    winners = np.empty(K, dtype=np.int64)
    margins = np.empty(K)
    clutter_shares = np.empty(K)
    options = np.empty(P, dtype=np.int64)
    shares = np.empty(P)
    weights = np.empty(P)
    for k in range(K):
        winners[k], margins[k], _ = vote_one_observation(log_weights[k], votes[k], weights,
                                                         options, shares)
        weighted, total = 0.0, 0.0
        for p in range(P):
            weighted += weights[p] * clutter_prob[k, p]
            total += weights[p]
        clutter_shares[k] = weighted / total
    return winners, margins, clutter_shares


def assign_correspondence_ids(cids, active, slots, winners) -> int:
    """Write the voted ids of one scan into ``cids`` (P, C) in place, unique within a particle.

    ``slots`` (K, P): the slot that observation k modified or created in particle p (-1: none),
    so a particle has at most one feature per observation; a feature belongs to at most one
    observation (as in :class:`filters.fastslam.FastSLAM2`, where a feature taken by an
    observation of the scan is excluded for the others). ``winners`` (K,): the winning id of
    each observation (< 0: clutter won, its features keep their ids). ``active`` (P, C) must
    already include created features, whose ``cids`` entry must be -1. Each particle's changes
    are applied in observation order, so later observations see the ids written by earlier ones.
    A feature takes the winning id unless its particle holds another active feature with that
    id; then it keeps its id (module docstring). Returns the number of features that kept their
    id for that reason.
    """
    require(isinstance(cids, np.ndarray), "cids", type(cids).__name__,
            "a numpy array (written in place)")
    active = np.asarray(active, dtype=bool)
    slots = np.asarray(slots, dtype=np.int64)
    winners = np.asarray(winners, dtype=np.int64).reshape(-1)
    require(slots.ndim == 2, "slots", slots.shape, "a (K, P) array")
    require(winners.shape == (slots.shape[0],), "winners", winners.shape,
            f"({slots.shape[0]},): one id per observation of slots")
    require(cids.shape == active.shape and cids.shape[0] == slots.shape[1], "cids", cids.shape,
            f"(P, C) like active {active.shape}, P = {slots.shape[1]} as in slots")
    return assign_correspondence_ids_unchecked(cids, active, slots, winners)


@njit(cache=True)
def assign_correspondence_ids_unchecked(cids, active, slots, winners) -> int:
    """The loop of :func:`assign_correspondence_ids` (integer work only), without its
    validation: for the filter's own arrays (``cids`` int64, ``active`` bool (P, C), ``slots``
    int64 (K, P), ``winners`` int64 (K,))."""
    K, P = slots.shape
    C = cids.shape[1]
    kept = 0
    for p in range(P):
        for k in range(K):
            s, w = slots[k, p], winners[k]
            if s < 0 or w < 0 or cids[p, s] == w:
                continue
            clash = False
            for c in range(C):
                if c != s and active[p, c] and cids[p, c] == w:
                    clash = True
                    break
            if clash:
                kept += 1
            else:
                cids[p, s] = w
    return kept


# --------------------------------------------------------------------------- common set (BB 3.2)
@dataclass(frozen=True)
class CommonFeatures:
    """The common feature set: ``ids`` (N,), ``slots`` (P, N) = delta(n, p) (BB 3.2) or -1 where
    particle p lacks feature n, and the weighted ``existence`` (N,) of each common feature.

    Only features held by at least one particle of positive weight belong to the set."""

    ids: np.ndarray
    slots: np.ndarray
    existence: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def _normalised(weights) -> np.ndarray:
    weights = np.asarray(weights, dtype=float)
    total = weights.sum()
    require(bool(np.isfinite(total) and total > 0.0), "weights", total, "a positive finite sum")
    return weights / total


def common_features(
    weights, correspondence_ids, active, existence, tie_break=None
) -> CommonFeatures:
    """Build delta (BB 3.2) and the weighted existence of every common feature.

    ``correspondence_ids``, ``active``, ``existence``: (P, C); ``tie_break`` (P, C) optional, used
    to break existence ties between duplicates (smallest wins: the covariance trace, module
    docstring).
    """
    w = _normalised(weights)
    cids = np.asarray(correspondence_ids)
    active = np.asarray(active, dtype=bool)
    existence = np.asarray(existence, dtype=float)
    P = len(w)
    require(
        cids.shape == active.shape == existence.shape and cids.shape[:1] == (P,),
        "correspondence_ids",
        cids.shape,
        "(P, C) like active and existence",
    )
    cids = cids.astype(np.int64, copy=False)
    if tie_break is None:
        trace = np.zeros(cids.shape)
    else:
        trace = np.asarray(tie_break, dtype=float)
    if not (active & (cids >= 0)).any():
        return CommonFeatures(np.zeros(0, np.int64), np.zeros((P, 0), np.int64), np.zeros(0))
    # the products in numpy: numba may fuse a product and a sum into one (differently rounded) FMA
    shares = w[:, None] * existence
    ids, slots, weighted = _common_set(w, cids, active, existence, shares, trace, int(cids.max()))
    return CommonFeatures(ids, slots, np.minimum(weighted, 1.0))


@njit(cache=True, inline="always")
def _key_order(a, b) -> int:
    """-1 if sort key ``a`` comes before ``b`` in numpy's ascending order (NaN last), 1 if after,
    0 if they tie."""
    if np.isnan(a):
        return 0 if np.isnan(b) else 1
    if np.isnan(b) or a < b:
        return -1
    return 1 if a > b else 0


@njit(cache=True)
def _common_set(w, cids, active, existence, shares, trace, max_id):
    """The common set of :func:`common_features`, compiled.

    Each particle's representative of an id is the first of its slots holding it in the order
    highest existence, smallest ``trace``, lowest slot (NaN keys last, as numpy sorts them);
    representatives of particles of zero weight are dropped. Returns the ids in ascending order,
    the slots (P, N) and the sum of the representatives' ``shares`` (P, C) = weight x existence
    over the particles in ascending order (the order of the lexsort-and-bincount it replaces, so
    the sums are the same to the bit).
    """
    P, C = cids.shape
    rep = np.zeros((P, C), dtype=np.bool_)
    owner = np.full(max_id + 1, -1, dtype=np.int64)  # the particle whose slot is in best_slot
    best_slot = np.empty(max_id + 1, dtype=np.int64)
    used = np.zeros(max_id + 1, dtype=np.bool_)
    for p in range(P):
        if not w[p] > 0.0:
            continue
        for s in range(C):
            c = cids[p, s]
            if not active[p, s] or c < 0:
                continue
            if owner[c] != p:
                owner[c], best_slot[c] = p, s
                rep[p, s] = True
                used[c] = True
                continue
            t = best_slot[c]
            order = _key_order(-existence[p, s], -existence[p, t])
            if order == 0:
                order = _key_order(trace[p, s], trace[p, t])
            if order < 0:  # s before t (on a tie the lower slot, t, stays)
                rep[p, t], rep[p, s] = False, True
                best_slot[c] = s
    column = np.cumsum(used) - 1
    ids = np.flatnonzero(used).astype(np.int64)
    slots = np.full((P, len(ids)), -1, dtype=np.int64)
    weighted = np.zeros(len(ids))
    for p in range(P):
        for s in range(C):
            if rep[p, s]:
                n = column[cids[p, s]]
                slots[p, n] = s
                weighted[n] += shares[p, s]
    return ids, slots, weighted


# --------------------------------------------------------------------------- moments (BB (6), (7))
def pose_moments(poses, weights, pose_covs=None, lineages=None, small_sample=False):
    """Weighted mean (circular mean heading) and covariance of particle poses (P, 3).

    ``pose_covs`` (P, 3, 3), if given, is each particle's own pose covariance (zero in FastSLAM,
    BB 2.1; the FastSLAM 2.0 proposal between prediction and update), added as in BB (7).
    ``lineages`` (P,), if given, adds :func:`lineage_covariance`, and with ``small_sample`` the
    result is scaled by :func:`small_sample_factor` (the pose block of :func:`moment_match` with
    the same arguments).

    One compiled pass (:func:`pose_moments_unchecked`): the filters ask for the pose at every
    step, and the numpy version of these few 3 x 3 sums cost ~0.4 ms a call at 500 particles
    (issue 27).
    """
    w = _normalised(weights)
    poses = np.asarray(poses, dtype=float)
    P = len(w)
    require(poses.shape == (P, 3), "poses", poses.shape, f"({P}, 3)")
    if pose_covs is None:
        covs = np.zeros((0, 3, 3))
    else:
        covs = np.asarray(pose_covs, dtype=float)
        require(covs.shape == (P, 3, 3), "pose_covs", covs.shape, f"({P}, 3, 3)")
    if lineages is None:
        group, n_groups = np.zeros(0, dtype=np.int64), 0
    else:
        group, n_groups = _lineage_groups(lineages, P)
    return pose_moments_unchecked(poses, w, covs, group, n_groups, bool(small_sample))


@njit(cache=True)
def pose_moments_unchecked(poses, w, covs, group, n_groups, small_sample):
    """:func:`pose_moments` without its validation, for callers whose arrays are the filter's own
    (normalised weights, lineage groups in range): ``covs`` (P, 3, 3) or empty (no particle
    covariances), ``group`` (P,) lineage groups in ``[0, n_groups)`` or empty (no lineage
    term)."""
    P = poses.shape[0]
    mean = np.zeros(3)
    sin_sum, cos_sum = 0.0, 0.0
    for p in range(P):
        mean[0] += w[p] * poses[p, 0]
        mean[1] += w[p] * poses[p, 1]
        sin_sum += w[p] * np.sin(poses[p, 2])
        cos_sum += w[p] * np.cos(poses[p, 2])
    mean[2] = wrap_angle_one(np.arctan2(sin_sum, cos_sum))
    wd = np.empty((P, 3))  # w_p (x_p - mean), heading wrapped
    cov = np.zeros((3, 3))
    for p in range(P):
        d0, d1 = poses[p, 0] - mean[0], poses[p, 1] - mean[1]
        d2 = wrap_angle_one(poses[p, 2] - mean[2])
        wd[p, 0], wd[p, 1], wd[p, 2] = w[p] * d0, w[p] * d1, w[p] * d2
        for i in range(3):
            cov[i, 0] += wd[p, i] * d0
            cov[i, 1] += wd[p, i] * d1
            cov[i, 2] += wd[p, i] * d2
    if covs.shape[0] > 0:  # each symmetrised (the proposal's round-off)
        for p in range(P):
            for i in range(3):
                for j in range(3):
                    cov[i, j] += w[p] * (0.5 * (covs[p, i, j] + covs[p, j, i]))
    if n_groups > 0:
        added, between, s = _lineage_sums(wd, w, group, n_groups)
        cov += added
        if small_sample:
            cov *= _small_sample_factor(cov, between, s)
    return mean, 0.5 * (cov + cov.T)


def _gather(means, covs, slots):
    """Features (P, N, 2) and covariances (P, N, 2, 2) at ``slots`` (P, N); missing -> zeros."""
    has, safe = _gather_index(slots)
    mu = np.where(has[..., None], _take_slots(means, safe), 0.0)
    sig = np.where(has[..., None, None], _take_slots(covs, safe), 0.0)
    return has, mu, sig


def _gather_index(slots):
    """Which particles hold each feature (P, N), and the slot to gather each entry from (slot 0
    where the particle lacks the feature; masked by the caller), for :func:`_take_slots`."""
    has = slots >= 0
    return has, np.where(has, slots, 0)


def _take_slots(values, safe):
    """``values[p, safe[p, n]]`` for every particle p and feature n: (P, N, ...) from per-slot
    values (P, C, ...). One ``np.take`` over the flattened slots: the same copies as the fancy
    index ``values[arange(P)[:, None], safe]``, at a third of its cost (issue 27)."""
    P, C = values.shape[:2]
    flat = (np.arange(P)[:, None] * C + safe).ravel()
    taken = np.take(values.reshape((P * C,) + values.shape[2:]), flat, axis=0)
    return taken.reshape(safe.shape + values.shape[2:])


def _feature_mass(w, has):
    """Each common feature's mass ``w @ has`` (N,): the weight of the particles holding it, which
    must be positive for every feature (``ValueError`` naming ``slots``)."""
    mass = w @ has
    require(
        bool(np.all(mass > 0.0)),
        "slots",
        "a feature held by no weighted particle",
        "every common feature held by a particle of positive weight",
    )
    return mass


def _feature_weights(w, has):
    """Each particle's share (P, N) of each feature's moments: its weight over the feature's
    mass among the particles holding it."""
    return w[:, None] * has / _feature_mass(w, has)


def feature_moments(weights, means, covs, slots):
    """Per-feature moment matching (BB (6), (7) for one feature) over the particles holding it.

    ``slots`` (P, N) from :func:`common_features`. Returns means (N, 2) and covs (N, 2, 2).
    Every feature must be held by a particle of positive weight.
    """
    w = _normalised(weights)
    slots = np.asarray(slots, dtype=np.int64)
    has, mu, sig = _gather(np.asarray(means, float), np.asarray(covs, float), slots)
    wc = _feature_weights(w, has)
    m = np.einsum("pn,pnk->nk", wc, mu)
    d = np.where(has[..., None], mu - m, 0.0)
    cov = np.einsum("pn,pnij->nij", wc, sig) + np.einsum("pn,pni,pnj->nij", wc, d, d)
    return m, 0.5 * (cov + np.swapaxes(cov, -1, -2))


def feature_means(weights, means, slots):
    """The means of :func:`feature_moments` alone (the same numbers, bit for bit), without
    gathering or summing any covariance: for callers that need no uncertainty (map scoring)."""
    means = np.asarray(means, float)
    return feature_means_xy(weights, means[..., 0], means[..., 1], slots)


def feature_means_xy(weights, mx, my, slots):
    """:func:`feature_means` of the feature means given as their x and y (P, C) (a particle
    filter's own arrays, without stacking them): BB (6) for each common feature, ``m_n =
    sum_p w_pn mu_pn`` with ``w_pn`` each holder's share of the feature (:func:`_feature_weights`,
    its mass ``w @ has`` as :func:`feature_moments` forms it) and the sum over the particles in
    their order, one product and one addition rounded at a time: the numbers of
    :func:`feature_moments`' ``einsum``, to the bit (tests/filters/test_conversion.py)."""
    w = _normalised(weights)
    slots = np.asarray(slots, dtype=np.int64)
    mass = _feature_mass(w, slots >= 0)
    return _feature_means_sums(w, np.asarray(mx, float), np.asarray(my, float), slots, mass)


@njit(cache=True)
def _feature_means_sums(w, mx, my, slots, mass):
    """The sums of :func:`feature_means_xy`, compiled: for each feature, over the particles in
    order, ``(w_p / mass_n) * mu_pn`` (zero for a particle without it), as ``einsum`` adds them."""
    P, N = slots.shape
    out = np.zeros((N, 2))
    for p in range(P):
        for n in range(N):
            slot = slots[p, n]
            if slot >= 0:
                share = w[p] / mass[n]
                out[n, 0] += share * mx[p, slot]
                out[n, 1] += share * my[p, slot]
            else:
                out[n, 0] += 0.0
                out[n, 1] += 0.0
    return out


def lineage_covariance(weighted_deviations, weights, lineages):
    """Covariance to add to BB (7) for a particle cloud whose particles share ancestors.

    ``weighted_deviations`` (P, d): row ``p`` is ``w_p (x_p - mean)`` (the deviations of BB (7)
    times the particle's weight); ``weights`` (P,) normalised; ``lineages`` (P,) each particle's
    ancestor at a reference time (the local map's restart). Grouping the particles by lineage
    ``e`` with weight ``W_e`` and mean ``m_e``, and ``s = sum_e W_e^2``:

    * the Monte Carlo variance of the weighted mean, ``V = sum_e W_e^2 (m_e - m)(m_e - m)^T``
      (Chan & Lai 2013, Ann. Statist. 41(6), the ancestral-group estimator; Lee & Whiteley 2018,
      Biometrika 105(3), show it consistent), and
    * the bias of the between-lineage spread ``B = sum_e W_e (m_e - m)(m_e - m)^T`` as an
      estimate of the posterior's from few weighted lineages (reliability weights: ``B / (1 - s)``
      is unbiased for independent lineages),

    give the predictive covariance of (truth - mean) ``within + (B + V) / (1 - s)``, i.e. BB (7)
    plus ``(s B + V) / (1 - s)``, which is returned (d, d; symmetric PSD). With independent,
    equally weighted particles it is ``2 / (P - 1)`` times BB (7)'s spread, negligible at
    P = 500; a cloud with a single lineage (``s = 1``) carries no information about its own
    Monte Carlo error, and zero is returned.
    """
    return _lineage_parts(weighted_deviations, weights, lineages)[0]


def _lineage_parts(weighted_deviations, weights, lineages):
    """``(added, between, s)``: the :func:`lineage_covariance` term ``(s B + V) / (1 - s)``, the
    between-lineage part of the predictive covariance ``(B + V) / (1 - s)`` and ``s`` (zeros and
    ``s = 1`` for a single lineage)."""
    weighted_deviations = np.asarray(weighted_deviations, dtype=float)
    weights = np.asarray(weights, dtype=float)
    P, d = weighted_deviations.shape
    require(weights.shape == (P,), "weights", weights.shape, f"({P},)")
    group, n_groups = _lineage_groups(lineages, P)
    return _lineage_sums(np.ascontiguousarray(weighted_deviations), weights, group, n_groups)


def _lineage_groups(lineages, P):
    """``(group, n_groups)``: each particle's lineage as an index in ``[0, n_groups)``. The
    filters' lineages (ancestor indices, ``0 <= lineage < P``) serve as they are."""
    lineages = np.asarray(lineages)
    require(lineages.shape == (P,), "lineages", lineages.shape, f"({P},)")
    if P and lineages.dtype.kind in "iu" and lineages.min() >= 0 and lineages.max() < P:
        return lineages.astype(np.int64, copy=False), P
    _, group = np.unique(lineages, return_inverse=True)
    return group.astype(np.int64).reshape(-1), int(group.max()) + 1 if P else 0


@njit(cache=True)
def _lineage_sums(wd, w, group, n_groups):
    """:func:`_lineage_parts` after validation, compiled. Lineage ``e`` (a ``group`` index) has
    the mass ``W_e`` and the sum ``W_e (m_e - m)`` of its rows of ``wd``, accumulated in particle
    order; lineages without mass contribute nothing."""
    P, d = wd.shape
    sums = np.zeros((n_groups, d))
    mass = np.zeros(n_groups)
    for p in range(P):
        e = group[p]
        mass[e] += w[p]
        for i in range(d):
            sums[e, i] += wd[p, i]
    s = 0.0
    for e in range(n_groups):
        s += mass[e] * mass[e]
    if s >= 1.0 - 1e-9:
        return np.zeros((d, d)), np.zeros((d, d)), 1.0
    between = np.zeros((d, d))  # B = sum_e W_e (m_e - m)(m_e - m)^T
    spread_of_mean = np.zeros((d, d))  # V = sum_e W_e^2 (m_e - m)(m_e - m)^T
    for e in range(n_groups):
        if mass[e] > 0.0:
            for i in range(d):
                scaled = sums[e, i] / mass[e]
                for j in range(d):
                    between[i, j] += scaled * sums[e, j]
                    spread_of_mean[i, j] += sums[e, i] * sums[e, j]
    added = (s * between + spread_of_mean) / (1.0 - s)
    total_between = (between + spread_of_mean) / (1.0 - s)
    return 0.5 * (added + added.T), 0.5 * (total_between + total_between.T), s


def small_sample_factor(cov, between, s) -> float:
    """Scale for a covariance whose between-lineage part is estimated from few lineages.

    ``cov`` (p, p) is the predictive covariance (BB (7) plus :func:`lineage_covariance`),
    ``between`` (p, p) its part estimated from the spread between lineages, ``(B + V) / (1 - s)``,
    and ``s = sum_e W_e^2`` (so ``1 / s`` is the effective number of lineages). That part has
    ``nu_b = 1 / s - 1`` degrees of freedom; the within-lineage part is taken as exact. Matching
    the variance of ``tr(cov^-1 C_hat)`` to a Wishart's (Satterthwaite 1946) gives the effective
    degrees of freedom of ``cov``,

        nu = p nu_b / tr((cov^-1 between)^2)        (>= nu_b, as ``between <= cov``),

    and a covariance estimated with ``nu`` degrees of freedom overstates the information:
    ``E[S^-1] = nu / (nu - p - 1) Sigma^-1`` for ``S ~ Wishart(Sigma / nu, nu)`` (the mean of
    the inverse Wishart distribution). The returned factor ``nu / (nu - p - 1)`` makes the
    information the back-end fuses unbiased (and the mean NEES ``p``). It is infinite at
    ``nu <= p + 1``; ``nu`` is clipped below at ``p + 2`` (the factor is at most ``p + 2``).
    ``p`` is the rank of ``cov`` (its size unless the cloud is degenerate, e.g. one step after a
    restart, when the poses lie on a curve) and ``cov^-1`` its pseudo-inverse. A single lineage
    (``s = 1``, no between part) returns 1: its cloud says nothing about its own error.
    """
    cov = np.asarray(cov, dtype=float)
    between = np.asarray(between, dtype=float)
    p = cov.shape[0]
    require(cov.shape == (p, p), "cov", cov.shape, "(p, p)")
    require(between.shape == (p, p), "between", between.shape, f"({p}, {p})")
    check_range("s", s, 0.0, 1.0)
    return float(_small_sample_factor(np.ascontiguousarray(cov), np.ascontiguousarray(between),
                                      float(s)))


@njit(cache=True)
def _small_sample_factor(cov, between, s):
    """:func:`small_sample_factor` after validation, from one eigen-decomposition of ``cov``:
    its rank with numpy's ``matrix_rank`` tolerance (``p eps`` times the largest eigenvalue's
    magnitude) and its pseudo-inverse with ``pinv``'s cutoff (``1e-15`` times it)."""
    if s >= 1.0 - 1e-9 or not np.any(between != 0.0):
        return 1.0
    p = cov.shape[0]
    lam, vectors = np.linalg.eigh(cov)
    top = np.abs(lam).max()
    rank = 0
    inverse = np.zeros((p, p))
    for k in range(p):
        if abs(lam[k]) > top * p * np.finfo(np.float64).eps:
            rank += 1
        if abs(lam[k]) > 1e-15 * top:
            v = vectors[:, k]
            inverse += np.outer(v, v) / lam[k]
    ratio = inverse @ between
    spread = np.trace(ratio @ ratio)
    if rank == 0 or spread <= 0.0:
        return 1.0
    nu = max(rank * (1.0 / s - 1.0) / spread, rank + 2.0)
    return nu / (nu - rank - 1.0)


def nearest_spd(P, eig_floor: float = EIGENVALUE_FLOOR):
    """The symmetric matrix nearest to ``P`` (Frobenius) whose eigenvalues are ``>= eig_floor``.

    Returns ``(matrix, projected)``; ``projected`` is False when ``P`` (symmetrised) already
    satisfied the floor and is returned unchanged.
    """
    P = 0.5 * (np.asarray(P, dtype=float) + np.asarray(P, dtype=float).T)
    if P.size == 0:
        return P, False
    lam, V = np.linalg.eigh(P)
    if lam[0] >= eig_floor:
        return P, False
    out = (V * np.maximum(lam, eig_floor)) @ V.T
    return 0.5 * (out + out.T), True


def moment_match(
    poses,
    weights,
    means,
    covs,
    common: CommonFeatures,
    *,
    min_existence: float = CONFIRMED_PROBABILITY,
    pose_covs=None,
    lineages=None,
    small_sample: bool = False,
    eig_floor: float = EIGENVALUE_FLOOR,
) -> GaussianMap:
    """BB 3.2: one Gaussian over ``[pose, features with existence > min_existence]``.

    Each particle's mean is BB (9) ``[v^p, mu_delta(1,p)^p, ...]`` with the block-diagonal
    covariance of BB 3.2 (zero pose block unless ``pose_covs`` is given); the moments are BB (6)
    and (7) with the missing-feature rule and the SPD projection of the module docstring. All
    sums over particles are vectorised (einsum / matrix products). ``lineages`` (P,), if given,
    adds :func:`lineage_covariance`: each feature's deviations weighted as in its moments, the
    lineage weights ``W_e`` and ``s`` from the full particle weights (exact for a feature every
    particle holds, an approximation for one held by some). With ``small_sample`` (and
    ``lineages``) the pose block is scaled by :func:`small_sample_factor` of that block, i.e.
    ``(c - 1)`` times it is added to it alone: the covariance only grows (Loewner order), the
    cross-covariances and the features' blocks are unchanged.
    """
    check_range("min_existence", min_existence, 0.0, 1.0)
    check_range("eig_floor", eig_floor, 0.0, 1.0)
    w = _normalised(weights)
    poses = np.asarray(poses, dtype=float)
    P = len(w)
    require(poses.shape == (P, 3), "poses", poses.shape, f"({P}, 3)")
    select = np.flatnonzero(common.existence > min_existence)
    slots = common.slots[:, select]
    n = len(select)
    has, mu, sig = _gather(np.asarray(means, float), np.asarray(covs, float), slots)

    pose_mean, _ = pose_moments(poses, w)
    mass = w @ has
    wc = w[:, None] * has / np.where(mass > 0.0, mass, 1.0)
    feat_mean = np.einsum("pn,pnk->nk", wc, mu)

    # Deviations D (P, 3 + 2n), zero where a particle lacks the entry, and presence mask M.
    dim = 3 + 2 * n
    D = np.empty((P, dim))
    D[:, :3] = poses - pose_mean
    D[:, 2] = wrap_angle(D[:, 2])
    D[:, 3:] = np.where(has[..., None], mu - feat_mean, 0.0).reshape(P, 2 * n)
    M = np.ones((P, dim))
    M[:, 3:] = np.repeat(has, 2, axis=1)
    pair_mass = (M * w[:, None]).T @ M  # weight of the particles holding both entries
    spread = (D * w[:, None]).T @ D  # BB (7) outer products (zero rows for missing entries)
    cov = np.divide(spread, pair_mass, out=np.zeros((dim, dim)), where=pair_mass > 0.0)

    # Block-diagonal part of BB (7): each feature's own covariance, and the pose covariance.
    own = np.einsum("pn,pnij->nij", wc, sig)
    idx = 3 + 2 * np.arange(n)
    for a in range(2):
        for b in range(2):
            cov[idx + a, idx + b] += own[:, a, b]
    if pose_covs is not None:
        cov[:3, :3] += np.einsum("p,pij->ij", w, np.asarray(pose_covs, dtype=float))
    if lineages is not None:
        W = np.empty((P, dim))
        W[:, :3] = w[:, None]
        W[:, 3:] = np.repeat(wc, 2, axis=1)
        added, between, s = _lineage_parts(W * D, w, lineages)
        cov += added
        if small_sample:
            c = small_sample_factor(cov[:3, :3], between[:3, :3], s)
            cov[:3, :3] *= c

    cov, projected = nearest_spd(cov, eig_floor)
    if projected:
        logger.debug("moment_match: covariance projected to eigenvalues >= %g", eig_floor)
    x = np.concatenate([pose_mean, feat_mean.reshape(-1)])
    return GaussianMap(
        x=x, P=cov, ids=common.ids[select].copy(), existence=common.existence[select].copy()
    )
