"""Whether the fast lookahead chooses what the full one chooses (issue 57 item 1): both planners
on the same planning states, captured along an episode of a zoned task.

Supports docs/RESULTS.md, "A planner at a quarter of the cost (issue 57)". Command (one process;
resumable: a rerun with the same ``--out`` skips the worlds already in it)::

    python scripts/results/lookahead_agreement.py --task SlamGym/HybridSLAM-Zones-v1 \\
        --worlds 4810:0,4811:1,4812:2,4813:3,4814:0,4815:1,4816:2,4817:3,4818:0,4819:1 \\
        --out out/agreement57-zones

Each world (``seed:level``) is played by ``--follow`` (default ``lookahead``, the fast planner:
the states it meets); at each of its planning points (a decision where the base rule fuses; with
``--every K`` the first and every K-th after it, for CPU: the others are the fast planner's own)
the fast planner (``lookahead``) and the full one (``lookahead-full``) plan from the same state,
each on its own copies, and the script records both choices, both planners' CPU
(``process_time``) and simulated decisions, and the full planner's rollouts decision by
decision (``rewards``: alternative -> one list per future), from which cheaper planners can be
emulated offline (:func:`emulate`: a subset of the futures and a shorter horizon; the fast
planner's one future is the full planner's first). One line per planning point in
``OUT/states.jsonl``, one per finished world in ``OUT/worlds.jsonl``.

``--report`` prints the agreement: the fraction of planning points where the two choose the
same, pooled, and the mean over worlds of each world's fraction with its 95 % interval (the
cluster bootstrap of :mod:`slam_gym.evaluation.paired`, the seed the cluster and the clutter
levels the strata, with its small-sample correction: a world's planning points are not
independent), the same restricted to the points where the full planner leaves the rule, the
CPU of the two planners on the same states, and the emulated planners' agreement and cost.
Writes ``OUT/agreement.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

logger = logging.getLogger("lookahead_agreement")

FAST, FULL = "lookahead", "lookahead-full"


def _key(action) -> str:
    return f"{int(action[0])}{int(action[1])}"


def _recording_full():
    """``lookahead-full`` that keeps each rollout's rewards, decision by decision."""
    from slam_gym.lookahead import FullLookahead

    class Recording(FullLookahead):
        def _rollouts(self, env, first_action, seeds, base_returns):
            self._current = _key(first_action)
            return super()._rollouts(env, first_action, seeds, base_returns)

        def _simulate(self, sim, action):
            out = sim.step(action)
            per_sim = self.rewards.setdefault(self._current, {})
            per_sim.setdefault(id(sim), []).append(float(out[1]))
            return out

    return Recording()


def plan_both(env, base_action, fast, full) -> dict:
    """Both planners' choices from ``env``'s current state (each plans on its own copies)."""
    out = {"n_decisions": int(env.n_decisions), "base": _key(base_action)}
    base = tuple(int(v) for v in base_action)
    for label, planner in (("fast", fast), ("full", full)):
        planner.bind_env(env)
        if label == "full":
            planner.rewards = {}
        before = planner.simulated_decisions
        start = time.process_time()
        returns = planner.action_returns(base_action)
        out[f"{label}_cpu_s"] = time.process_time() - start
        out[f"{label}_simulated"] = planner.simulated_decisions - before
        out[label] = _key(planner.choose(returns, base))
    out["rewards"] = {a: list(per_sim.values()) for a, per_sim in full.rewards.items()}
    return out


def capture_world(task: str, seed: int, level: int, follow: str, states_path: Path,
                  every: int = 1) -> dict:
    """Play world ``seed`` at ``level`` with ``follow``; plan both planners at every
    ``every``-th of its planning points (the first, then every ``every``); append one line per
    point to ``states_path``; return the world's summary."""
    import gymnasium as gym

    import policies
    import slam_gym  # noqa: F401  (registers the ids)
    from policies.base import make_action

    env = gym.make(task, clutter_level=level, w_compute=10.0, compute_clip_s=0.2).unwrapped
    # following the fast planner, its choice at a planning point is the one just planned (the
    # same futures, so the same choice): it is not planned twice
    follower = None if follow == FAST else policies.make(follow)
    fast, full = policies.make(FAST), _recording_full()
    rule = policies.make(full.options["base"])
    obs, info = env.reset(seed=seed, options={"world_seed": seed})
    if follower is not None:
        follower.reset()
        if callable(getattr(follower, "bind_env", None)):
            follower.bind_env(env)
    n_points, n_captured, done = 0, 0, False
    with states_path.open("a") as f:
        while not done:
            rule_action = rule.act(obs, info)
            action = rule_action
            if rule_action[0] and n_points % every == 0:
                row = plan_both(env, rule_action, fast, full)
                f.write(json.dumps({"seed": seed, "level": level, **row}) + "\n")
                f.flush()
                n_captured += 1
                action = make_action(int(row["fast"][0]), int(row["fast"][1]))
            elif rule_action[0] and follower is None:
                action = fast.act(obs, info)
            n_points += int(bool(rule_action[0]))
            if follower is not None:
                action = follower.act(obs, info)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
    return {"seed": seed, "level": level, "follow": follow, "points": n_points,
            "captured": n_captured,
            "success": not bool(info["failed"]), "return": float(env.episode_return)}


def choose(returns: dict, base: str, min_gain: float = 10.0, z_gain: float = 2.0) -> str:
    """:meth:`slam_gym.lookahead.LookaheadPolicy.choose` on ``{"11": [...], ...}``."""
    best = max(returns, key=lambda a: (float(np.mean(returns[a])), a == base))
    if best == base:
        return base
    gains = np.asarray(returns[best]) - np.asarray(returns[base])
    mean = float(np.mean(gains))
    stderr = float(np.std(gains, ddof=1) / np.sqrt(len(gains))) if len(gains) > 1 else 0.0
    return best if mean > min_gain and mean > z_gain * stderr else base


def emulate(state: dict, n_futures: int, horizon: int) -> tuple[str, int]:
    """The choice of a planner on the full planner's first ``n_futures`` futures over
    ``horizon`` decisions (unpruned), and the decisions it would simulate."""
    rewards = state["rewards"]
    returns = {a: [sum(r[:horizon]) for r in futures[:n_futures]]
               for a, futures in rewards.items()}
    cost = sum(min(len(r), horizon) for futures in rewards.values() for r in futures[:n_futures])
    return choose(returns, state["base"]), cost


def agreement(states: list[dict], chosen: list[str]) -> dict:
    """Pooled and per-world agreement of ``chosen`` with the full planner's choices."""
    from slam_gym.evaluation.paired import cluster_bootstrap_interval

    by_world: dict = defaultdict(list)
    for s, c in zip(states, chosen, strict=True):
        by_world[(s["level"], s["seed"])].append(c == s["full"])
    worlds = sorted(by_world)
    fractions = np.array([np.mean(by_world[w]) for w in worlds])
    out = {"points": len(states), "worlds": len(worlds),
           "pooled": float(np.mean([c == s["full"] for s, c in zip(states, chosen, strict=True)]))}
    if len(worlds) >= 2:
        if np.ptp(fractions) == 0.0:
            out["mean_over_worlds"] = [float(fractions[0])] * 3
        else:
            # the worlds' seeds are the clusters (issue 56): a seed's levels share its world
            iv = cluster_bootstrap_interval(fractions, np.array([w[0] for w in worlds]),
                                            np.array([w[1] for w in worlds]), rng=0)
            out["mean_over_worlds"] = [float(iv.estimate), float(iv.lo), float(iv.hi)]
    return out


def report(states: list[dict]) -> dict:
    left = [s for s in states if s["full"] != s["base"]]
    doc = {
        "all": agreement(states, [s["fast"] for s in states]),
        "where_full_leaves_the_rule": agreement(left, [s["fast"] for s in left]) if left else None,
        "full_leaves_the_rule": len(left),
        "fast_leaves_the_rule": sum(s["fast"] != s["base"] for s in states),
        "cpu_s_per_point": {"fast": float(np.mean([s["fast_cpu_s"] for s in states])),
                            "full": float(np.mean([s["full_cpu_s"] for s in states]))},
        "cpu_ratio_pooled": float(sum(s["fast_cpu_s"] for s in states)
                                  / sum(s["full_cpu_s"] for s in states)),
        "simulated_ratio_pooled": float(sum(s["fast_simulated"] for s in states)
                                        / sum(s["full_simulated"] for s in states)),
        "emulated": {},
    }
    if all(len(f) == 4 for s in states for f in s["rewards"].values()):
        # how far a choice is a draw: a planner like the fast one (one future, 14 decisions) on
        # each of the full planner's futures (the first is the fast planner's own: the same
        # choices as it made), and the full planner's two halves of its futures against each
        # other (two futures each, 20 decisions)
        doc["one_future_on_future_k"] = [
            agreement(states, [choose({a: [sum(f[k][:14])] for a, f in s["rewards"].items()},
                                      s["base"]) for s in states])["pooled"]
            for k in range(4)]
        halves = [[choose({a: [sum(r) for r in f[h:h + 2]] for a, f in s["rewards"].items()},
                          s["base"]) for s in states] for h in (0, 2)]
        doc["halves_agree"] = float(np.mean([a == b for a, b in zip(*halves, strict=True)]))
    full_cost = sum(emulate(s, 4, 10**6)[1] for s in states)
    for m in (1, 2, 4):
        for h in (5, 10, 12, 14, 16, 20):
            chosen = [emulate(s, m, h) for s in states]
            doc["emulated"][f"M={m} H={h}"] = {
                "pooled": float(np.mean([c == s["full"] for s, (c, _) in zip(states, chosen,
                                                                               strict=True)])),
                "simulated_ratio": float(sum(c for _, c in chosen) / full_cost)}
    return doc


def _read(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:  # a line cut by a killed run
            continue
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="SlamGym/HybridSLAM-Zones-v1")
    parser.add_argument("--worlds", default="", help="seed:level,... (comma-separated)")
    parser.add_argument("--follow", default=FAST, help="the policy whose episode is played")
    parser.add_argument("--out", required=True)
    parser.add_argument("--every", type=int, default=1,
                        help="capture every EVERY-th planning point of a world (CPU)")
    parser.add_argument("--report", action="store_true", help="only report the rows in --out")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    states_path, worlds_path = out / "states.jsonl", out / "worlds.jsonl"
    if not args.report:
        done = {(w["seed"], w["level"]) for w in _read(worlds_path)}
        for spec in filter(None, (w.strip() for w in args.worlds.split(","))):
            seed, level = (int(v) for v in spec.split(":"))
            if (seed, level) in done:
                continue
            # a world cut short by a killed run is captured again from its start
            kept = [s for s in _read(states_path) if (s["seed"], s["level"]) != (seed, level)]
            states_path.write_text("".join(json.dumps(s) + "\n" for s in kept))
            start = time.monotonic()
            summary = capture_world(args.task, seed, level, args.follow, states_path,
                                    args.every)
            with worlds_path.open("a") as f:
                f.write(json.dumps({"task": args.task, **summary}) + "\n")
            logger.info("world %d level %d: %d planning points, %d captured, %.0f s", seed,
                        level, summary["points"], summary["captured"], time.monotonic() - start)
    finished = {(w["seed"], w["level"]) for w in _read(worlds_path)}
    states = [s for s in _read(states_path) if (s["seed"], s["level"]) in finished]
    if not states:
        parser.error(f"no finished world in {out}")
    doc = {"task": args.task, "follow": args.follow, **report(states)}
    (out / "agreement.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps({k: v for k, v in doc.items() if k != "emulated"}, indent=2))
    for name, e in doc["emulated"].items():
        print(f"{name:12s} agreement {e['pooled']:.3f}  simulated decisions "
              f"{e['simulated_ratio']:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
