"""``--env ID``, ``--env-kwargs KEY:VALUE ...`` and the shorthands for keyword arguments of the
env, shared by every command that runs episodes (issue 55).

The command only parses: every value goes to :func:`slam_gym.envs.spec.resolve_env`, which
checks it and says in one line where it overrides the id's own. A shorthand left out is not
given (its default is the id's), so ``--env SlamGym/HybridSLAM-Light-v1`` runs 100 particles
whatever ``--particles`` would default to.
"""

from __future__ import annotations

SHORTHANDS: dict[str, tuple[str, dict, str]] = {
    "scenario": ("--scenario", {"metavar": "NAME"}, "the worlds' scenario (slam_gym/scenarios.py)"),
    "n_particles": ("--particles", {"type": int, "metavar": "P"},
                    "FastSLAM particles of the front-end"),
    "decision_interval": ("--decision-interval", {"type": int, "metavar": "K"},
                          "simulation steps between decisions"),
    "front_end": ("--front-end", {"choices": ["fastslam", "ekf"]}, "the front-end"),
    "back_end": ("--back-end", {"choices": ["ekf", "relative"]}, "the back-end"),
    "n_steps": ("--n-steps", {"type": int, "metavar": "N"},
                "cut every path to N simulation steps (quick looks, tests)"),
    "w_compute": ("--w-compute", {"type": float, "metavar": "W"},
                  "the reward's price of compute (/s)"),
    "compute_clip_s": ("--compute-clip-s", {"type": float, "metavar": "S"},
                       "the reward's compute clip (s)"),
}
"""Keyword argument -> (flag, argparse options, help): each a shorthand for ``--env-kwargs
KEY:VALUE`` (default: the id's own)."""


def add_env_options(parser, shorthands=tuple(SHORTHANDS), *, levels: bool = True) -> None:
    """``--env``, ``--env-kwargs``, the named ``shorthands`` and (``levels``)
    ``--clutter-levels``."""
    from slam_gym.envs.spec import DEFAULT_ENV_ID

    parser.add_argument("--env", default=None, metavar="ID",
                        help=f"the registered env id the runs are made in (default "
                        f"{DEFAULT_ENV_ID}); e.g. SlamGym/HybridSLAM-Zones-v1, "
                        "SlamGym/HybridSLAM-ZonesStarved-v1")
    parser.add_argument("--env-kwargs", nargs="+", default=None, metavar="KEY:VALUE",
                        help="keyword arguments of gym.make over the id's own, each KEY:VALUE "
                        "(VALUE read as JSON, else a string): e.g. n_particles:150 "
                        "scenario:brooks-bailey-zones; one overriding the id's says so")
    for name in shorthands:
        flag, kwargs, text = SHORTHANDS[name]
        parser.add_argument(flag, dest=f"env_{name}", default=None, **kwargs,
                            help=f"{text} (env keyword {name}; default the id's own)")
    if levels:
        from slam_gym.commands.runs import Given

        parser.add_argument("--clutter-levels", default=None, action=Given, metavar="L,...",
                            help="comma-separated clutter levels 0-3, distinct (default the "
                            "env's own: the four of BB's Table 1, a task's four, or the one "
                            "its id fixes)")


def env_shorthands(args) -> dict:
    """The shorthands given on the command line, as keyword arguments of the env."""
    return {name: getattr(args, f"env_{name}") for name in SHORTHANDS
            if getattr(args, f"env_{name}", None) is not None}


def env_from_args(args, *, per_decision: bool = True):
    """The :class:`~slam_gym.envs.spec.ResolvedEnv` of the command's options (every check in
    :func:`~slam_gym.envs.spec.resolve_env`)."""
    from slam_gym.commands.runs import int_list
    from slam_gym.envs.spec import parse_env_kwargs, resolve_env

    levels = getattr(args, "clutter_levels", None)
    return resolve_env(
        args.env, parse_env_kwargs(args.env_kwargs), shorthands=env_shorthands(args),
        clutter_levels=None if levels is None else int_list(levels, "clutter_levels"),
        per_decision=per_decision)


def policies_help(intro: str) -> str:
    """``intro`` and every policy name a command accepts (:func:`policies.available`: the
    project's, installed plug-ins', this process's), with the forms names take."""
    import policies

    return (f"{intro}: {', '.join(policies.available())}; a threshold rule by its printed "
            "name, threshold-optimise[FEATURE>=THRESHOLD] (e.g. "
            "threshold-optimise[global_position_std_m>=2]); or a package.module:attribute "
            "reference to a policy class, factory or object")
