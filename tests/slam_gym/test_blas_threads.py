"""One BLAS thread wherever the env runs (issue 40 item 1): under a plain ``gym.make`` in a user's
process and in the workers of ``slam_gym.evaluation.benchmark``, with no BLAS variable set.

Each case runs in a fresh interpreter whose environment has no ``*_NUM_THREADS`` variable. There
the BLAS libraries are first given two threads (what OpenBLAS starts with on a machine of two
cores or more; set explicitly so that the test means the same on one core), then a hook around
the optimiser's Gauss-Newton (``filters.submap_optimise.gauss_newton``, which runs the
factorisations) records the thread count of every BLAS library inside each solve.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from filters.blas import blas_thread_counts, limited_blas_threads

ROOT = Path(__file__).resolve().parents[2]
BLAS_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

HOOK = textwrap.dedent("""
    import json, os
    from threadpoolctl import threadpool_limits
    import filters.submap_optimise as submap_optimise
    from filters.blas import blas_thread_counts

    threadpool_limits(max(2, *blas_thread_counts()), user_api="blas")  # the user's process
    OUTSIDE = blas_thread_counts()
    _solve = submap_optimise.gauss_newton

    def _recording_solve(*args, **kwargs):
        with open(os.environ["BLAS_RECORD"], "a") as f:
            f.write(json.dumps({"pid": os.getpid(), "outside": OUTSIDE,
                                "inside": blas_thread_counts()}) + "\\n")
        return _solve(*args, **kwargs)

    submap_optimise.gauss_newton = _recording_solve

    def fixed_optimise():
        import policies
        return policies.make("fixed-10s-optimise")
""")


def _run(code: str, tmp_path) -> list[dict]:
    (tmp_path / "blas_hook.py").write_text(HOOK)
    record = tmp_path / "record.jsonl"
    env = {k: v for k, v in os.environ.items() if k not in BLAS_VARIABLES}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(ROOT)])
    env["BLAS_RECORD"] = str(record)
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return [json.loads(line) for line in record.read_text().splitlines()]


def test_a_plain_gym_make_episode_optimises_with_one_blas_thread(tmp_path):
    rows = _run("""
        import blas_hook  # the user's process: two BLAS threads, the hook installed
        import gymnasium as gym
        import numpy as np
        from filters.blas import blas_thread_counts

        env = gym.make("slam_gym:SlamGym/HybridSLAM-v1", n_particles=10, n_steps=300)
        env.reset(seed=0)
        done = False
        while not done:  # fuse and optimise at every decision
            _, _, terminated, truncated, _ = env.step(np.array([1, 1]))
            done = terminated or truncated
        # the user's own numpy work after the episode: the process's setting, untouched
        assert blas_thread_counts() == blas_hook.OUTSIDE, blas_thread_counts()
    """, tmp_path)
    assert len(rows) >= 20  # every decision optimised a grown graph
    assert all(min(r["outside"]) >= 2 for r in rows)
    assert all(r["inside"] == [1] * len(r["inside"]) for r in rows), rows[:3]


def test_the_benchmark_workers_optimise_with_one_blas_thread(tmp_path):
    rows = _run("""
        from slam_gym.evaluation import benchmark
        from blas_hook import fixed_optimise

        if __name__ == "__main__":
            import os
            with open("main.pid", "w") as f:
                f.write(str(os.getpid()))
            benchmark({"fixed-optimise": fixed_optimise}, clutter_levels=[2], seeds=[0, 1],
                      env_kwargs={"n_particles": 100, "n_steps": 600}, baselines=[], workers=2,
                      figures=False, out="out")
    """, tmp_path)
    # the solves ran in the workers, not in the process that called benchmark
    main_pid = int((tmp_path / "main.pid").read_text())
    assert len(rows) >= 4 and main_pid not in {r["pid"] for r in rows}
    assert all(min(r["outside"]) >= 2 for r in rows)
    assert all(r["inside"] == [1] * len(r["inside"]) for r in rows), rows[:3]


def test_the_limit_is_restored_and_none_leaves_the_setting():
    from threadpoolctl import threadpool_limits

    with threadpool_limits(2, user_api="blas"):
        assert set(blas_thread_counts()) == {2}
        with limited_blas_threads(1):
            assert set(blas_thread_counts()) == {1}
            with limited_blas_threads(3):
                assert set(blas_thread_counts()) == {3}
            assert set(blas_thread_counts()) == {1}
        assert set(blas_thread_counts()) == {2}
        with limited_blas_threads(None):
            assert set(blas_thread_counts()) == {2}


@pytest.mark.parametrize("bad", [0, -1, 2.0, True, "1", 10**6])
def test_a_bad_thread_count_names_the_field(bad):
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    with pytest.raises(ValueError, match="blas_threads"):
        HybridSLAMEnv(n_particles=5, blas_threads=bad)
    with pytest.raises(ValueError, match="blas_threads"):
        with limited_blas_threads(bad):
            pass


def test_blas_threads_option_reaches_the_optimiser():
    """``blas_threads=2`` in the env: the optimiser runs with two threads, not the default."""
    import filters.submap_optimise as submap_optimise
    from slam_gym.envs.hybrid_slam import HybridSLAMEnv

    seen = []
    solve = submap_optimise.gauss_newton

    def recording(*args, **kwargs):
        seen.append(blas_thread_counts())
        return solve(*args, **kwargs)

    for threads in (2, 1):
        seen.clear()
        env = HybridSLAMEnv(n_particles=50, n_steps=120, blas_threads=threads)
        env.reset(seed=0)
        submap_optimise.gauss_newton = recording
        try:
            for _ in range(5):
                env.step(np.array([1, 1]))
        finally:
            submap_optimise.gauss_newton = solve
        assert seen and all(set(c) == {threads} for c in seen), (threads, seen)
