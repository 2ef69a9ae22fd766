"""A training sweep (issue 29 item 7): seeds x prices of compute as independent resumable jobs.

``slam-gym train --prices 1,10,100`` makes one :class:`~slam_gym.evaluation.Job` of kind
``"training"`` per (price, seed) and runs them through the benchmark's executors
(:func:`slam_gym.evaluation.run_jobs`: ``serial``, a ``process`` pool, or ``ray``, on a local
instance or the cluster at ``--ray-address``), so a sweep runs on a cluster unchanged. Layout::

    OUT/results.jsonl            one row per finished job (the executors' resumable file)
    OUT/price-<p>/seed-<s>/      one training run (slam_gym.training.run), the job's own directory
    OUT/price-<p>/summary.{json,md}, training_curves.png, model.zip (+ .json)
                                 the seeds of one price, as `slam-gym train` writes for its seeds
    OUT/sweep.json, sweep.md     every price: chosen seed, spread over seeds, model

A job trains at ``env_kwargs.w_compute = price`` (and ``compute_clip_s`` when given), so its
training reward and its evaluations are scored at that price. Resuming works at two levels: a
rerun skips the jobs that have a row in ``results.jsonl`` (error rows are run again), and a job
whose run was interrupted continues from its newest checkpoint (``train_run(resume=True)``). A
job's key holds its price, seed, clip and a digest of everything else it trains with
(:meth:`SweepSpec.digest`); the job writes that key into its directory (``sweep-job.json``) and
refuses a directory holding a run of other settings, so a changed configuration never reuses or
continues another's run. With ``--ray-address`` every node must see ``OUT`` at the same path (a
shared file system): the jobs write their runs there; the rows travel back to this process.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slam_gym.evaluation.jobs import Job

logger = logging.getLogger(__name__)

JOB_MARKER = "sweep-job.json"
"""The file in a job's run directory that names the job (its key) the run belongs to."""


def parse_prices(text: str) -> list[float]:
    """``"1,10,100"`` -> ``[1.0, 10.0, 100.0]``: distinct finite numbers in (0, 1e6], in order;
    ``ValueError`` naming ``prices`` otherwise."""
    try:
        prices = [float(v) for v in str(text).split(",") if v.strip() != ""]
    except ValueError as exc:
        raise ValueError(f"prices={text!r} is invalid: must be comma-separated numbers "
                         "(per second of modelled compute)") from exc
    ok = (prices and all(math.isfinite(p) and 0 < p <= 1e6 for p in prices)
          and len(set(prices)) == len(prices))
    if not ok:
        raise ValueError(f"prices={text!r} is invalid: must be distinct numbers in (0, 1e6] "
                         "(per second of modelled compute)")
    return prices


def price_label(price: float) -> str:
    """The directory name of a price: ``price-10``, ``price-0.5``."""
    return f"price-{price:g}"


@dataclass(frozen=True)
class SweepSpec:
    """Everything the jobs of one sweep share (pickled to the workers with the run function)."""

    algo: str
    env_id: str
    hyperparams: dict[str, Any]
    out: str
    clutter_levels: tuple[int, ...] = (0, 1, 2, 3)
    eval_seeds: tuple[int, ...] = ()
    eval_every: int = 25_000
    eval_workers: int = 1
    checkpoint_every: int = 25_000
    compute_clip_s: float | None = None
    command: str = ""

    def __post_init__(self):
        if self.hyperparams.get("compute_price_range") is not None:
            raise ValueError(
                "prices is invalid with compute_price_range (a policy conditioned on the price "
                "learns every price in one run): give one or the other")
        if self.compute_clip_s is not None and not (
                math.isfinite(self.compute_clip_s) and 0 < self.compute_clip_s <= 1e6):
            raise ValueError(f"compute_clip_s={self.compute_clip_s!r} is invalid: must be a "
                             "number in (0, 1e6] (seconds)")

    def setup(self, price: float, seed: int):
        """The :class:`~slam_gym.training.run.TrainingSetup` of one job."""
        from slam_gym.training.hyperparams import validate_hyperparams
        from slam_gym.training.run import TrainingSetup

        params = json.loads(json.dumps(self.hyperparams))  # a deep copy
        env_kwargs = {**params.get("env_kwargs", {}), "w_compute": float(price)}
        if self.compute_clip_s is not None:
            env_kwargs["compute_clip_s"] = float(self.compute_clip_s)
        params["env_kwargs"] = env_kwargs
        params = validate_hyperparams(self.algo, params, where=f"sweep {price_label(price)}")
        return TrainingSetup(
            algo=self.algo, env_id=self.env_id, seed=int(seed), hyperparams=params,
            clutter_levels=tuple(self.clutter_levels), eval_seeds=tuple(self.eval_seeds),
            eval_every=self.eval_every, eval_workers=self.eval_workers,
            checkpoint_every=self.checkpoint_every, command=self.command)

    def digest(self) -> str:
        """What a job trains with besides its price, seed and clip: 16 hex digits of the
        SHA-256 of the algorithm, env id, hyper-parameters and evaluation settings."""
        doc = {k: v for k, v in dataclasses.asdict(self).items()
               if k not in ("out", "command", "compute_clip_s", "eval_workers")}
        text = json.dumps(doc, sort_keys=True, default=list)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def jobs(self, prices, seeds) -> list[Job]:
        """One job per (price, seed), price-major (a price's seeds finish together)."""
        digest = self.digest()
        return [
            Job("training", self.algo, self.env_id, None, int(seed), {
                "w_compute": float(price), "compute_clip_s": self.compute_clip_s,
                "setup_sha256": digest, "run_dir": f"{price_label(price)}/seed-{int(seed)}"})
            for price in prices for seed in seeds
        ]


def run_training_job(job: Job, *, spec: SweepSpec) -> dict[str, Any]:
    """Train (or resume, or find finished) the job's run; its final evaluation as a results row
    (the executors' :data:`~slam_gym.evaluation.results.RESULT_KEYS`, with ``success`` the
    success rate, plus the return, interface CPU and where the model is)."""
    from slam_gym.training.run import chosen_mode, mode_record, train_run

    options = job.options_dict()
    run_dir = Path(spec.out) / options["run_dir"]
    marker = run_dir / JOB_MARKER
    if marker.is_file():
        found = json.loads(marker.read_text()).get("key")
        if found != job.key:
            raise ValueError(
                f"out={spec.out!r} is invalid for this sweep: {options['run_dir']} holds a run "
                f"of other settings (its job: {found}); choose another --out or delete it")
    run_dir.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"key": job.key}) + "\n")
    setup = spec.setup(options["w_compute"], job.seed)
    config = train_run(setup, run_dir, resume=True, progress=False)
    final = config["final_evaluation"]
    mode = chosen_mode(final)
    record = mode_record(final, mode)
    return {
        "alpha": None, "beta": None,
        "success": record["success_rate"],
        "failure_iteration": None,
        "anees": record["anees"],
        "nees_in_band_fraction": None,
        "map_error_m": record["map_error_m"],
        "final_pose_error_m": None,
        "n_fusions": record["n_fusions"],
        "n_optimisations": record["n_optimisations"],
        "mean_return": record["mean_return"],
        "interface_cpu_s": record["interface_cpu_s"],
        "mode": mode,
        "timesteps": config["timesteps"],
        "train_time_s": config.get("train_time_s"),
        "model": str(Path(options["run_dir"]) / "model.zip"),
    }


def run_sweep(spec: SweepSpec, prices, seeds, *, executor: str = "process",
              workers: int = 1, ray_address: str | None = None,
              progress: bool = False) -> dict[str, Any]:
    """Run every job of ``prices`` x ``seeds`` not yet done, then summarise each price (its
    seeds' spread, the chosen seed's model copied to ``OUT/price-<p>/model.zip``) and the sweep
    (``sweep.json``, ``sweep.md``). Returns the ``sweep.json`` document."""
    from slam_gym.evaluation import run_jobs
    from slam_gym.training.report import summarise_runs

    out = Path(spec.out)
    jobs = spec.jobs(prices, seeds)
    rows = run_jobs(jobs, functools.partial(run_training_job, spec=spec), out,
                    workers=workers, executor=executor, ray_address=ray_address,
                    progress=progress, retry_errors=True)
    per_price, errors = {}, []
    for price in prices:
        label = price_label(price)
        runs = {}
        for row in rows:
            if row["options"]["w_compute"] != float(price):
                continue
            if row["status"] == "ok":
                runs[row["seed"]] = out / row["options"]["run_dir"]
            else:
                errors.append({"price": price, "seed": row["seed"], "error": row["error"]})
        if not runs:
            logger.warning("%s: no finished run to summarise", label)
            continue
        title = f"{spec.algo.upper()} on {spec.env_id} at {price:g} /s, seeds {sorted(runs)}"
        doc = summarise_runs(out / label, spec.algo, runs, title)
        per_price[label] = {"price": price, "seeds": sorted(runs),
                            "chosen_seed": doc["chosen_seed"], "spread": doc["spread"],
                            "final_evaluation": doc["final_evaluation"],
                            "model": f"{label}/model.zip"}
    sweep = {
        "algo": spec.algo, "env_id": spec.env_id, "prices": list(prices), "seeds": list(seeds),
        "compute_clip_s": spec.compute_clip_s, "setup_sha256": spec.digest(),
        "n_jobs": len(jobs), "n_errors": len(errors), "errors": errors, "per_price": per_price,
        "chosen_by": "per price, the seed with the highest mean return of its final evaluation "
                     "on the training-time evaluation worlds (success rate breaks ties)",
        "command": spec.command,
    }
    (out / "sweep.json").write_text(json.dumps(sweep, indent=2) + "\n")
    (out / "sweep.md").write_text(sweep_markdown(sweep))
    return sweep


def sweep_markdown(sweep: dict[str, Any]) -> str:
    """One line per price: the chosen seed and the spread over seeds of the final evaluation."""
    def spread(s, key, fmt):
        v = s.get(key)
        return "–" if v is None else f"{v['mean']:{fmt}} ± {v['std']:{fmt}}"

    clip = sweep["compute_clip_s"]
    lines = [f"# {sweep['algo'].upper()} sweep on {sweep['env_id']}: prices x seeds", "",
             f"{sweep['n_jobs']} jobs (prices {sweep['prices']}, seeds {sweep['seeds']}, "
             f"compute clip {'the default' if clip is None else f'{clip:g} s'}), "
             f"{sweep['n_errors']} errored. Final evaluation on the training-time evaluation "
             "worlds, mean ± std over seeds; the chosen seed's model is the price's model.", "",
             "| price (/s) | seeds | chosen seed | success | mean return | map error (m) | "
             "optimisations | interface CPU (s) | model |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for entry in sweep["per_price"].values():
        s = entry["spread"]
        lines.append(
            f"| {entry['price']:g} | {','.join(map(str, entry['seeds']))} | "
            f"{entry['chosen_seed']} | {spread(s, 'success_rate', '.2f')} | "
            f"{spread(s, 'mean_return', '.0f')} | {spread(s, 'map_error_m', '.2f')} | "
            f"{spread(s, 'n_optimisations', '.1f')} | {spread(s, 'interface_cpu_s', '.2f')} | "
            f"{entry['model']} |")
    for e in sweep["errors"]:
        lines.append(f"\nerror at price {e['price']:g}, seed {e['seed']}: {e['error']}")
    lines.append(f"\nchosen by: {sweep['chosen_by']}\n")
    return "\n".join(lines)
