"""One planning point of the lookahead: what each planner costs from the same state, and where
its time goes (issue 57 item 1).

Supports docs/PERFORMANCE.md, "The fast lookahead (issue 57)". Command::

    python scripts/performance/lookahead_point.py --task SlamGym/HybridSLAM-Zones-v1 \\
        --world 900000:2 --after 150 --repeats 3 --profile lookahead-full

Plays ``fixed-10s-optimise`` on world ``--world`` (``seed:level``, a training-time world by
default) to its first fusion at or after decision ``--after`` (a planning point), then times
each planner of ``--planners`` planning from that state ``--repeats`` times, in turn, in CPU
seconds (``process_time``; the planners only touch copies, so every repeat starts from the same
state), and prints the minimum and median with the simulated decisions and the choice.
``--profile NAME`` adds a pyinstrument profile of one more planning by that planner
(``pip install pyinstrument``).
"""

from __future__ import annotations

import argparse
import statistics
import time


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="SlamGym/HybridSLAM-Zones-v1")
    parser.add_argument("--world", default="900000:2", help="seed:level")
    parser.add_argument("--after", type=int, default=150)
    parser.add_argument("--planners", default="lookahead,lookahead-full")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", default=None, help="a planner to profile once")
    args = parser.parse_args(argv)

    import gymnasium as gym

    import policies
    import slam_gym  # noqa: F401  (registers the ids)

    seed, level = (int(v) for v in args.world.split(":"))
    env = gym.make(args.task, clutter_level=level, w_compute=10.0, compute_clip_s=0.2).unwrapped
    rule = policies.make("fixed-10s-optimise")
    obs, info = env.reset(seed=seed, options={"world_seed": seed})
    while True:
        action = rule.act(obs, info)
        if action[0] and env.n_decisions >= args.after:
            break
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            raise SystemExit(f"the episode ended at decision {env.n_decisions}: no planning "
                             f"point after {args.after}")
    base = tuple(int(v) for v in action)
    names = [n.strip() for n in args.planners.split(",") if n.strip()]
    planners = {n: policies.make(n) for n in names}
    times: dict[str, list[float]] = {n: [] for n in names}
    sims, choices = {}, {}
    for _ in range(args.repeats):
        for name, planner in planners.items():
            planner.bind_env(env)
            before = planner.simulated_decisions
            start = time.process_time()
            returns = planner.action_returns(action)
            times[name].append(time.process_time() - start)
            sims[name] = planner.simulated_decisions - before
            choices[name] = planner.choose(returns, base)
    print(f"{args.task} world {seed} level {level}, planning point at decision "
          f"{env.n_decisions} (rule's action {base}), {args.repeats} repeats")
    for name in names:
        print(f"  {name:22s} CPU min {min(times[name]):.3f} s, median "
              f"{statistics.median(times[name]):.3f} s; {sims[name]} simulated decisions; "
              f"chooses {choices[name]}")
    if len(names) == 2:
        ratios = [a / b for a, b in zip(times[names[0]], times[names[1]], strict=True)]
        print(f"  {names[0]} / {names[1]}: median {statistics.median(ratios):.3f} "
              f"(min {min(ratios):.3f}, max {max(ratios):.3f}) of the paired repeats")
    if args.profile:
        import pyinstrument

        planner = planners.get(args.profile) or policies.make(args.profile)
        planner.bind_env(env)
        profiler = pyinstrument.Profiler(interval=0.001)
        profiler.start()
        planner.action_returns(action)
        profiler.stop()
        print(profiler.output_text(unicode=False, color=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
