"""What the benchmark's episode figures draw, recorded by the runs that the table counts.

The figures of one world (the uncertainty and NEES traces, the decision timeline, the map) used
to come from playing every policy again after the runs, outside the runs' error handling and time
limit: a policy that raised or hung there crashed or hung the benchmark after its runs had been
recorded as error rows. Now the run itself records what those figures need while it is played
(:class:`EpisodeRecorder`, passed to :func:`slam_gym.evaluation.core.run_job` by the worker's run
function), in a small compressed file beside the results, ``OUT/episodes/<digest>.npz``
(:func:`episode_path`: the first 16 hex digits of the SHA-256 of the run's job key, so a file
belongs to exactly one row). The figures read those files (:func:`read_episode`) after the runs:
no policy is called outside the executors, and each figure shows the run its row reports.

A file holds, per iteration, ``t_s``, ``nees``, ``cov_trace`` (trace of the pose covariance),
``est_poses`` and ``true_poses`` (T, 3); per decision, the timeline of
:class:`~slam_gym.evaluation.timeline.TimelineRecorder` (``decision_t_s``, ``fused``,
``optimised``, ``closure_flag``, ``compute_s``); the final map (``landmarks_true``,
``landmark_means``, ``landmark_covs`` of the confirmed features); and ``dt_s``, ``end_s``,
``failed``, ``failure_t_s`` and ``failure_position`` (NaN when it did not fail; the true position
at BB's failure), ``true_loop_closure_s`` (NaN: none), ``n_fusions``, ``n_optimisations``.

The worker writes the file (atomically: a partial file never carries the final name). With Ray
on a cluster the worker's node must see ``OUT`` at the same path (as for training sweeps); a
recording that cannot be written is logged and left out, never turning the run into an error.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)

EPISODES_DIRNAME = "episodes"
FORMAT_VERSION = 1


def true_loop_closure_s(stream, start_fraction: float = 0.1) -> float | None:
    """Time of the first scan after half the path that sees a landmark of the path's first
    ``start_fraction`` (None if the path never closes its loop)."""
    scans = [(s.t_s, s.truth.visible_ids) for s in stream if s.truth.visible_ids is not None]
    if not scans:
        return None
    head = {int(i) for _, ids in scans[:max(1, int(start_fraction * len(scans)))] for i in ids}
    for t, ids in scans[len(scans) // 2:]:
        if head & {int(i) for i in ids}:
            return float(t)
    return None


class TimelineRecorder:
    """Records one episode's decisions (see the module docstring) as it is played: pass
    :meth:`on_step` as ``run_policy_object``'s ``on_step`` and call :meth:`finish` with the
    finished episode and env. ``rate_hz``: the scenario's filter rate (iteration -> time)."""

    def __init__(self, rate_hz: float):
        self.rate_hz = float(rate_hz)
        self.records: dict[str, list] = {"t_s": [], "fused": [], "optimised": [],
                                         "closure_flag": [], "compute_s": []}
        self._counts = {"n_fusions": 0, "n_optimisations": 0}

    def on_step(self, action, info) -> None:
        records, counts = self.records, self._counts
        records["t_s"].append(info["iteration"] / self.rate_hz)
        records["fused"].append(info["n_fusions"] > counts["n_fusions"])
        records["optimised"].append(info["n_optimisations"] > counts["n_optimisations"])
        records["closure_flag"].append(bool(info["features"]["loop_closure_flag"]))
        records["compute_s"].append(float(info["reward_components"]["compute_s"]))
        counts.update(n_fusions=info["n_fusions"], n_optimisations=info["n_optimisations"])

    def finish(self, episode, env) -> dict[str, Any]:
        """The timeline: the per-decision arrays and the episode's ``true_loop_closure_s``,
        ``end_s``, ``failed``, ``n_fusions`` and ``n_optimisations``."""
        out: dict[str, Any] = {k: np.asarray(v) for k, v in self.records.items()}
        out["fused"] = out["fused"].astype(bool)
        out["optimised"] = out["optimised"].astype(bool)
        out["closure_flag"] = out["closure_flag"].astype(bool)
        out.update(
            true_loop_closure_s=true_loop_closure_s(env.stream),
            end_s=float(episode.t_s),
            failed=bool(episode.failure.failed),
            n_fusions=episode.n_fusions,
            n_optimisations=episode.n_optimisations,
        )
        return out


def episode_path(out_dir: str | os.PathLike, job_key: str) -> Path:
    """Where the recording of the run with key ``job_key`` is kept under ``out_dir``."""
    digest = hashlib.sha256(job_key.encode("utf-8")).hexdigest()[:16]
    return Path(out_dir) / EPISODES_DIRNAME / f"{digest}.npz"


@dataclass(frozen=True)
class EpisodeRecorder:
    """Which runs record their episode (``keys``: job keys) and under which output folder
    (``out_dir``). Picklable, so it travels with the run function to worker processes."""

    out_dir: str
    keys: frozenset[str]

    def start(self, job) -> EpisodeRecording | None:
        """A recording for ``job`` if it is one of :attr:`keys`, else None."""
        if job.kind != "policy" or job.key not in self.keys:
            return None
        from slam_gym.scenarios import get_scenario

        return EpisodeRecording(episode_path(self.out_dir, job.key),
                                get_scenario(job.scenario).filter_rate_hz)


class EpisodeRecording:
    """One run being recorded: :meth:`on_step` sees every decision, :meth:`finish` writes the
    file once the episode ended."""

    def __init__(self, path: Path, rate_hz: float):
        self.path = Path(path)
        self.timeline = TimelineRecorder(rate_hz)
        self.on_step = self.timeline.on_step

    def finish(self, episode, env) -> Path | None:
        """Write the recording (module docstring); its path, or None when it could not be
        written (logged: the run's row stands, its figures leave it out and say so)."""
        try:
            arrays = episode_arrays(episode, env, self.timeline.finish(episode, env))
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(f"{self.path.stem}.{os.getpid()}.tmp")
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **arrays)
            os.replace(tmp, self.path)
        except Exception as exc:  # never turn a finished run into an error row
            logger.warning("could not record the episode for the figures in %s: %s: %s",
                           self.path, type(exc).__name__, exc)
            return None
        return self.path


def failure_point(episode) -> tuple[float, float, float] | None:
    """``(t_s, x, y)``: when BB's failure criterion was met in a finished episode (with a
    trace) and the true position then; None if it did not fail."""
    trace = episode.trace
    k = episode.failure.failure_iteration
    if not episode.failure.failed or k is None or trace is None or not trace.t_s:
        return None
    i = min(max(int(k) - 1, 0), len(trace.t_s) - 1)  # iterations count from 1
    pose = np.asarray(trace.true_poses[i], dtype=float)
    return float(trace.t_s[i]), float(pose[0]), float(pose[1])


def episode_arrays(episode, env, timeline: dict[str, Any]) -> dict[str, np.ndarray]:
    """The arrays of a recording (module docstring) of a finished ``episode`` in ``env``."""
    trace = episode.trace
    failure = failure_point(episode)
    failure_t_s = np.nan if failure is None else failure[0]
    failure_position = np.full(2, np.nan) if failure is None else np.array(failure[1:])
    landmarks = episode.confirmed_landmarks()
    closure = timeline["true_loop_closure_s"]
    return {
        "format": np.asarray(FORMAT_VERSION),
        "t_s": np.asarray(trace.t_s, dtype=float),
        "nees": np.asarray(trace.nees, dtype=float),
        "cov_trace": np.asarray(trace.cov_trace, dtype=float),
        "est_poses": np.asarray(trace.est_poses, dtype=float).reshape(-1, 3),
        "true_poses": np.asarray(trace.true_poses, dtype=float).reshape(-1, 3),
        "decision_t_s": np.asarray(timeline["t_s"], dtype=float),
        "fused": np.asarray(timeline["fused"], dtype=bool),
        "optimised": np.asarray(timeline["optimised"], dtype=bool),
        "closure_flag": np.asarray(timeline["closure_flag"], dtype=bool),
        "compute_s": np.asarray(timeline["compute_s"], dtype=float),
        "landmarks_true": np.asarray(episode.stream.landmarks_true, dtype=float).reshape(-1, 2),
        "landmark_means": np.asarray(landmarks.means, dtype=float).reshape(-1, 2),
        "landmark_covs": np.asarray(landmarks.covs, dtype=float).reshape(-1, 2, 2),
        "dt_s": np.asarray(float(env.stream.dt_s)),
        "end_s": np.asarray(float(timeline["end_s"])),
        "failed": np.asarray(bool(timeline["failed"])),
        "failure_t_s": np.asarray(failure_t_s),
        "failure_position": np.asarray(failure_position, dtype=float),
        "true_loop_closure_s": np.asarray(np.nan if closure is None else float(closure)),
        "n_fusions": np.asarray(int(timeline["n_fusions"])),
        "n_optimisations": np.asarray(int(timeline["n_optimisations"])),
    }


_SCALARS = {"dt_s": float, "end_s": float, "failed": bool, "failure_t_s": float,
            "true_loop_closure_s": float, "n_fusions": int, "n_optimisations": int,
            "format": int}


def read_episode(path: str | os.PathLike) -> dict[str, Any]:
    """A recording as a dict: arrays, and the scalars as Python numbers (a NaN
    ``failure_t_s`` or ``true_loop_closure_s`` as None). ``ValueError`` naming the file when it
    is not a recording of this format."""
    try:
        with np.load(path, allow_pickle=False) as data:
            out: dict[str, Any] = {k: data[k] for k in data.files}
    except Exception as exc:  # not a file, not a zip, a damaged member
        raise ValueError(f"episode recording {str(path)!r} is invalid: cannot read it "
                         f"({exc})") from exc
    missing = sorted(set(_SCALARS) - set(out))
    if missing or int(out["format"]) != FORMAT_VERSION:
        raise ValueError(f"episode recording {str(path)!r} is invalid: must be format "
                         f"{FORMAT_VERSION} with {sorted(_SCALARS)} (missing {missing})")
    for key, kind in _SCALARS.items():
        out[key] = kind(out[key])
    for key in ("failure_t_s", "true_loop_closure_s"):
        if not np.isfinite(out[key]):
            out[key] = None
    return out


def timeline_of(recording: dict[str, Any]) -> dict[str, Any]:
    """The decision timeline of a recording, in the form
    :func:`~slam_gym.evaluation.timeline.plot_decision_timelines` draws."""
    return {"t_s": recording["decision_t_s"], "fused": recording["fused"],
            "optimised": recording["optimised"], "closure_flag": recording["closure_flag"],
            "compute_s": recording["compute_s"], "end_s": recording["end_s"],
            "failed": recording["failed"], "n_fusions": recording["n_fusions"],
            "n_optimisations": recording["n_optimisations"],
            "true_loop_closure_s": recording["true_loop_closure_s"]}
