"""Write ``tests/data/pose_reference.npz``: HYBRID's poses on a seeded run, as a regression
reference for the front-end's pose (``FastSLAM2.pose()``: BB (6), (7), the lineage term and the
small-sample factor), the composed global pose (``SubmapSLAM.pose()``) and the local map at
every fusion (``FastSLAM2.to_gaussian()``, BB 3.2).

The committed file was re-recorded for issue 47 (the filter's state structure and compiled
iteration: the weights' exponential is the compiled one, and the scan draws its resampling
uniform every scan, so the run's numbers changed; f658fba wrote the one before), by

    python scripts/tools/make_pose_reference.py tests/data/pose_reference.npz

``tests/filters/test_conversion.py`` replays the same run and compares to float rounding.
"""

from __future__ import annotations

import argparse

import numpy as np

# the run the test replays (kept here and imported by the test so the two cannot drift apart)
REFERENCE_RUN = {"scenario": "brooks-bailey", "seed": 3, "clutter_level": 2, "n_steps": 350,
                 "n_particles": 200, "rng_seed": 7, "fusion_every_steps": 100}


def reference_run(observe=None):
    """Replay :data:`REFERENCE_RUN`; returns the arrays the reference file holds. ``observe``, if
    given, is called as ``observe("prior" | "post", front_end)`` right after each front-end pose
    is recorded (the test computes its own reference from the same particle cloud there)."""
    from slam_gym.systems import make_system
    from slam_gym.world import make_stream

    run = REFERENCE_RUN
    stream = make_stream(run["scenario"], seed=run["seed"], clutter_level=run["clutter_level"],
                         n_steps=run["n_steps"])
    system = make_system("hybrid", stream, np.random.default_rng(run["rng_seed"]),
                         n_particles=run["n_particles"]).estimator
    rows = {k: [] for k in ("prior_mean", "prior_cov", "post_mean", "post_cov", "global_mean",
                            "global_cov")}
    out = {}
    for i, step in enumerate(stream):
        system.predict(step.odometry, step.dt_s)
        for when in ("prior", "post"):
            if when == "post":
                system.update(step.z)
            mean, cov = system.front_end.pose()
            rows[f"{when}_mean"].append(mean)
            rows[f"{when}_cov"].append(cov)
            if observe is not None:
                observe(when, system.front_end)
        for name, value in zip(("global_mean", "global_cov"), system.pose(), strict=True):
            rows[name].append(value)
        if (i + 1) % run["fusion_every_steps"] == 0:
            local = system.front_end.to_gaussian()
            out[f"fusion{i + 1}_x"], out[f"fusion{i + 1}_P"] = local.x, local.P
            system.fuse()
    out.update({k: np.array(v) for k, v in rows.items()})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("path")
    args = parser.parse_args()
    np.savez_compressed(args.path, **reference_run())


if __name__ == "__main__":
    main()
