"""``lookahead``: an interface policy that plans on copies of the env (Bertsekas' rollout).

At a decision where the base rule would fuse (by default ``fixed-10s-optimise``: BB's 10 s
interval, CM's optimiser after every fusion), the policy tries each alternative

* fuse, then optimise;
* fuse without optimising;
* wait (neither: the base rule then fuses at the next decision, one second later);

on copies of the env (:meth:`~slam_gym.envs.hybrid_slam.HybridSLAMEnv.clone`), continues each
copy with the base rule for ``horizon_decisions`` decisions (the alternative's own decision
included) and compares the alternatives' returns over ``n_futures`` futures. Every other
decision is the base rule's. Rollout with a base policy is no worse than the base policy itself
when the values are exact (Bertsekas, *Rollout algorithms*: the cost-improvement property).
They are estimated here from a few sampled futures over a truncated horizon, and choosing the
largest of noisy estimates favours whichever alternative drew lucky futures; so the policy
leaves the base rule only for a *clear* gain: the best alternative's mean gain over the base
action, paired future by future, must exceed both ``min_gain`` (return points) and
``z_gain`` standard errors of the paired gains (with one future, ``min_gain`` alone). A failure
within the horizon costs thousands of points (the env's failure charge), the filtering's noise
over 20 decisions tens, so a prevented failure passes and a noisy difference does not.

Two planners (issue 57): ``lookahead`` plans on **one future over 14 decisions** and stops
the rollouts that can no longer change its choice; ``lookahead-full`` is issue 39's planner,
**four futures over 20 decisions**, every rollout played to its horizon, kept for reference.
The fast one simulates under a fifth of the full one's decisions (14 x 1 against 20 x 4, less
what it prunes). Why one future suffices, measured on planning states of the zoned tasks: the
outcome that decides a planning point, a failure within a few seconds of a fusion, depends on
the filter's state far more than on which future is drawn, so the full planner's futures
mostly agree with one another (docs/RESULTS.md, "A planner at a quarter of the cost (issue
57)", gives the agreement of the two planners and their headroom).

Stopping a rollout early (``prune``): the base action's rollouts are played first, then each
alternative's futures side by side; the env's rewards are never positive (every term is a
cost), so an alternative's partial return bounds its return from above, and once the mean of
its partial returns less the base action's is at most ``min_gain`` it cannot pass the gate and
is stopped, reported at that bound. The choice is then the one the unpruned planner makes on
the same futures (:meth:`LookaheadPolicy.choose`: the stopped alternative cannot be the chosen
one, and if it was the best by mean, none passes), only cheaper.

The futures are not the episode's own: each copy's remaining measurement noise and the filter's
random draws are redrawn (:meth:`~slam_gym.envs.hybrid_slam.HybridSLAMEnv.reseed_future`), so
the policy never sees what its episode will observe. Future ``m`` has the same seed for every
alternative (common random numbers: the alternatives are compared on the same draws) and
different seeds at every decision and in every world; future ``m``'s seed does not depend on
``n_futures``, so the fast planner's one future is the full planner's first. ``privileged=True``
is the exception, reported as an upper bound and never as a policy: one future, the episode's
own (its scans and the filter's draws as they will come, as far as the alternative leaves them
unchanged); ``lookahead-privileged`` plans it over the full planner's 20 decisions, unpruned,
as in issue 48.

Fusing where the rule would not (issue 48 item 3): with ``early_fusion_from_s`` set, a decision
where the base rule waits but the local map is at least that old is planned too, with the
alternatives fuse+optimise and fuse against the rule's wait. The planner can then fuse at any
decision from that age on, not only at the rule's clock; it still cannot optimise without
fusing. Off by default (None): the planner of issue 39, and every row measured with it, are
unchanged. Its cost: at BB's 10 s clock and 1 s decisions, ``early_fusion_from_s = 5`` plans
six decisions a cycle instead of one, so about three times the planning.

Cost: at a planned decision, at most ``3 x n_futures`` copies each run ``horizon_decisions``
decisions; ``planning_cpu_s`` and ``simulated_decisions`` say what an episode spent, and the
evaluation records them in each row (:meth:`episode_fields`).

The policy needs the env it acts in: the evaluation calls :meth:`bind_env` before an episode,
and so must a user's own loop (``policy.bind_env(env)`` after ``gym.make``).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

import policies
from filters.validation import check_range, require
from policies.base import Policy, make_action

ALTERNATIVES: tuple[tuple[int, int], ...] = ((1, 1), (1, 0), (0, 0))
"""The (fuse, optimise) actions tried where the base rule fuses (module docstring)."""

FULL_HORIZON_DECISIONS = 20
"""The full planner's horizon (issue 39): two of BB's fusion intervals at 1 s decisions, long
enough for a fusion's effect on the filter's consistency, and on BB's failure criterion (2 s
beyond 10 sigma), to show."""

FULL_N_FUTURES = 4
"""The full planner's futures (issue 39)."""

DEFAULT_HORIZON_DECISIONS = 14
"""The fast planner's horizon (issue 57): the next fusion of the base rule (10 or 11 decisions
on) and the 2 s of BB's failure criterion after it, with a decision to spare."""

DEFAULT_N_FUTURES = 1
"""The fast planner's futures (issue 57): one, the full planner's first."""

DEFAULT_MIN_GAIN = 10.0
"""Return points an alternative must gain over the base action (module docstring): a few
decisions' worth of the env's per-decision cost (2-5 points on BB's world)."""

DEFAULT_Z_GAIN = 2.0


class LookaheadPolicy(Policy):
    """Rollout of a base rule on re-seeded copies of the env (module docstring): the fast
    planner (one future, 14 decisions, hopeless rollouts stopped) unless told otherwise.

    Options: ``base`` (a policy name, default ``fixed-10s-optimise``), ``horizon_decisions``
    (H >= 1), ``n_futures`` (M >= 1; 1 when ``privileged``), ``min_gain`` and ``z_gain`` (the
    gain that makes it leave the base rule), ``prune`` (stop the rollouts of an alternative that
    can no longer pass that gate: the same choice, less work), ``privileged`` (the episode's own
    future: an upper bound, not a policy), ``seed`` (the futures' seeds, with the world's seed
    and the decision's index) and ``early_fusion_from_s`` (None, or the local-map age from which
    the decisions where the rule waits are planned too: fusing where the rule would not).
    """

    name = "lookahead"

    def __init__(self, *, base: str = "fixed-10s-optimise",
                 horizon_decisions: int = DEFAULT_HORIZON_DECISIONS,
                 n_futures: int = DEFAULT_N_FUTURES, min_gain: float = DEFAULT_MIN_GAIN,
                 z_gain: float = DEFAULT_Z_GAIN, prune: bool = True, privileged: bool = False,
                 seed: int = 0, early_fusion_from_s: float | None = None) -> None:
        super().__init__()
        require(isinstance(base, str), "base", base, "a policy name")
        try:
            self.base = policies.make(base)
        except ValueError as exc:
            raise ValueError(f"base={base!r} is invalid: {exc}") from exc
        for field, value in (("horizon_decisions", horizon_decisions), ("n_futures", n_futures),
                             ("seed", seed)):
            require(isinstance(value, (int, np.integer)) and not isinstance(value, bool)
                    and value >= (0 if field == "seed" else 1), field, value,
                    "a non-negative integer" if field == "seed" else "a positive integer")
        require(isinstance(privileged, bool), "privileged", privileged, "True or False")
        require(isinstance(prune, bool), "prune", prune, "True or False")
        require(not privileged or n_futures == 1, "n_futures", n_futures,
                "1 when privileged (there is one own future)")
        self.early_fusion_from_s = (None if early_fusion_from_s is None else check_range(
            "early_fusion_from_s", early_fusion_from_s, 0.0, 1e6))
        self.min_gain = check_range("min_gain", min_gain, 0.0, 1e9)
        self.z_gain = check_range("z_gain", z_gain, 0.0, 1e3)
        self.horizon_decisions = int(horizon_decisions)
        self.n_futures = int(n_futures)
        self.prune = prune
        self.privileged = privileged
        self.seed = int(seed)
        self.required_features = self.base.required_features
        self.options = {"base": base, "horizon_decisions": self.horizon_decisions,
                        "n_futures": self.n_futures, "min_gain": self.min_gain,
                        "z_gain": self.z_gain, "prune": prune, "privileged": privileged,
                        "seed": self.seed}
        if self.early_fusion_from_s is not None:  # absent when off: issue 39's rows match
            self.options["early_fusion_from_s"] = self.early_fusion_from_s
        self._env = None
        self.reset()

    def bind_env(self, env) -> None:
        """The env this policy acts in (a ``gym.make`` env or its unwrapped one): it plans on
        copies of it. Call before the episode's first decision."""
        env = getattr(env, "unwrapped", env)
        require(callable(getattr(env, "clone", None))
                and callable(getattr(env, "reseed_future", None)), "env", env,
                "an env with clone() and reseed_future() (slam_gym's HybridSLAMEnv)")
        self._env = env

    def reset(self) -> None:
        self.base.reset()
        self.planning_cpu_s = 0.0
        self.simulated_decisions = 0
        self.planned_decisions = 0
        self.deviations = 0

    def episode_fields(self) -> dict[str, Any]:
        """What the episode's planning cost, for the evaluation's rows."""
        return {"planning_cpu_s": self.planning_cpu_s,
                "simulated_decisions": self.simulated_decisions,
                "planned_decisions": self.planned_decisions,
                "deviations_from_base": self.deviations}

    def act(self, obs: Any, info: Mapping[str, Any]) -> np.ndarray:
        base_action = np.asarray(self.base.act(obs, info), dtype=np.int64)
        if not base_action[0] and not self._plans_early(info):
            return base_action
        if self._env is None:
            raise RuntimeError("lookahead needs the env it acts in: call policy.bind_env(env) "
                               "before the episode")
        start = time.process_time()
        returns = self.action_returns(base_action)
        self.planning_cpu_s += time.process_time() - start
        self.planned_decisions += 1
        choice = self.choose(returns, tuple(int(v) for v in base_action))
        if choice != tuple(base_action):
            self.deviations += 1
        return make_action(*choice)

    def _plans_early(self, info: Mapping[str, Any]) -> bool:
        """Whether a decision where the base rule does not fuse is planned (module docstring:
        ``early_fusion_from_s``)."""
        if self.early_fusion_from_s is None:
            return False
        age = float(info["features"]["local_map_age_s"])
        return age + 1e-4 >= self.early_fusion_from_s

    def action_returns(self, base_action: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
        """The horizon's return of each alternative in each future (the base action's first),
        from the env's current state. With ``prune``, an alternative stopped early has its
        partial returns instead, an upper bound that cannot pass :meth:`choose`'s gate."""
        env = self._env
        base = tuple(int(v) for v in base_action)
        seeds = self._future_seeds(env)
        alternatives = ALTERNATIVES if base[0] else ALTERNATIVES[:2]  # waiting is the base's
        returns = {base: self._rollouts(env, base, seeds, None)}
        for alternative in alternatives:
            if alternative != base:
                returns[alternative] = self._rollouts(
                    env, alternative, seeds, returns[base] if self.prune else None)
        return returns

    def choose(self, returns: Mapping[tuple[int, int], np.ndarray],
               base: tuple[int, int]) -> tuple[int, int]:
        """The alternative with the largest mean return if its gain over ``base``, paired by
        future, is clear (``> min_gain`` and ``> z_gain`` standard errors); else ``base``."""
        best = max(returns, key=lambda a: (float(np.mean(returns[a])), a == base))
        if best == base:
            return base
        gains = returns[best] - returns[base]
        mean_gain = float(np.mean(gains))
        stderr = float(np.std(gains, ddof=1) / np.sqrt(len(gains))) if len(gains) > 1 else 0.0
        return best if mean_gain > self.min_gain and mean_gain > self.z_gain * stderr else base

    def _future_seeds(self, env) -> list[int | None]:
        if self.privileged:
            return [None]
        sequence = np.random.SeedSequence([self.seed, int(env.world_seed), int(env.n_decisions)])
        return [int(s.generate_state(1, np.uint64)[0] >> np.uint64(1))
                for s in sequence.spawn(self.n_futures)]

    def _rollouts(self, env, first_action: tuple[int, int], seeds: list[int | None],
                  base_returns: np.ndarray | None) -> np.ndarray:
        """The returns of ``first_action`` then the base rule over the horizon, one per future
        (``seeds``), the futures played side by side. With ``base_returns`` (the base action's
        returns in the same futures), stopped once the alternative cannot pass the gate: its
        partial returns are then returned (module docstring, ``prune``)."""
        sims, rules, steps = [], [], []
        for seed in seeds:
            sim = env.clone()
            if seed is not None:
                sim.reseed_future(seed)
            sims.append(sim)
            rules.append(copy.deepcopy(self.base))
            steps.append((None, {}))
        totals = np.zeros(len(seeds))
        live = [True] * len(seeds)
        rewards_bounded = True  # a positive reward would void the partial return's bound
        for played in range(self.horizon_decisions):
            for m, sim in enumerate(sims):
                if not live[m]:
                    continue
                obs, info = steps[m]
                action = (make_action(*first_action) if played == 0
                          else rules[m].act(obs, info))
                obs, reward, terminated, truncated, info = self._simulate(sim, action)
                steps[m] = (obs, info)
                totals[m] += reward
                rewards_bounded = rewards_bounded and reward <= 0.0
                self.simulated_decisions += 1
                live[m] = not (terminated or truncated)
            if not any(live):
                break
            if (base_returns is not None and rewards_bounded
                    and float(np.mean(totals - base_returns)) <= self.min_gain):
                break  # hopeless: even with no cost from here on it cannot pass the gate
        return totals

    def _simulate(self, sim, action: np.ndarray):
        """One decision of a copy (a seam for instruments that record the rollouts)."""
        return sim.step(action)


class FullLookahead(LookaheadPolicy):
    """The full planner of issue 39 (module docstring), for reference: four futures over 20
    decisions, every rollout played to its horizon."""

    name = "lookahead-full"

    def __init__(self, *, base: str = "fixed-10s-optimise",
                 horizon_decisions: int = FULL_HORIZON_DECISIONS,
                 n_futures: int = FULL_N_FUTURES, min_gain: float = DEFAULT_MIN_GAIN,
                 z_gain: float = DEFAULT_Z_GAIN, prune: bool = False, seed: int = 0,
                 early_fusion_from_s: float | None = None) -> None:
        super().__init__(base=base, horizon_decisions=horizon_decisions, n_futures=n_futures,
                         min_gain=min_gain, z_gain=z_gain, prune=prune, seed=seed,
                         early_fusion_from_s=early_fusion_from_s)


class PrivilegedLookahead(LookaheadPolicy):
    """:class:`LookaheadPolicy` on the episode's own future: an upper bound, not a policy. It
    plans over the full planner's horizon, unpruned (issue 48's bound)."""

    name = "lookahead-privileged"

    def __init__(self, *, base: str = "fixed-10s-optimise",
                 horizon_decisions: int = FULL_HORIZON_DECISIONS,
                 min_gain: float = DEFAULT_MIN_GAIN, prune: bool = False, seed: int = 0,
                 early_fusion_from_s: float | None = None) -> None:
        super().__init__(base=base, horizon_decisions=horizon_decisions, n_futures=1,
                         min_gain=min_gain, prune=prune, privileged=True, seed=seed,
                         early_fusion_from_s=early_fusion_from_s)
