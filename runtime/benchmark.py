"""The generalisation benchmark (``glassmap eval``): the pipeline on worlds nobody tuned on.

A driver of existing functions over many worlds, never a second implementation: the classifier's beams
(``glassmap.train.simulate_beams`` + ``GlassClassifier`` + ``glassmap.eval.metrics.binary_report``), the
paper's experiment (``glassmap.eval.trial.run_trial``: with true poses, and direct vs robust 3x3 / 5x5
under pose error), the pose estimator (``glassmap.pose.evaluate.evaluate_run``) and the runtime demo
(``runtime.demo.run_demo``) against emulated devices. Worlds: generated test worlds (seeds from
``glassmap.sim.seeds.TEST_SEEDS``) plus the built-in ones. Work units run in a process pool (or on a Dask
cluster); results go to CSV + JSON + one summary figure.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import csv
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from runtime.parallel import job_executor, local_workers

PARTS = ("classifier", "map", "experiment", "pose", "demo")
BUILTIN = ("office", "glass-corridor", "room", "lobby")
METHODS = ("direct", "robust3", "robust5")


@dataclass(frozen=True)
class BenchmarkConfig:
    """What to run. generated: how many generated test worlds (world seeds 0 .. generated - 1);
    worlds: built-in worlds and world files added; seeds: run seeds (robot, laser and pose-error noise) per world;
    route: route name used where a world has it ("short": the generated worlds' first ~30 m), None = each
    world's default route; classifier_poses: scans of labelled beams per world and seed; trials: trials
    of the paper's experiment per world and seed, with sigma_xy (m) / sigma_theta_deg of pose error;
    demo_speed: the demo's speed-up over real time; demo_duration: emulated seconds after which the demo
    stops even if the route is not done (None: when it is done); demo_loop_closure: run the demo with the
    pose graph (its final estimate is then the one the graph corrected); pose_loop_closure: run the pose graph
    behind the estimator in the pose part as well (its corrected estimate's ATE and consistency are then
    reported beside the front end's); parts: which of PARTS to run."""

    generated: int = 20
    worlds: tuple[str, ...] = BUILTIN
    seeds: tuple[int, ...] = (0, 1, 2)
    route: str | None = None
    classifier_poses: int = 200
    trials: int = 5
    sigma_xy: float = 0.05
    sigma_theta_deg: float = 0.25
    demo_speed: float = 2.0
    demo_duration: float | None = None
    demo_loop_closure: bool = False
    pose_loop_closure: bool = False
    parts: tuple[str, ...] = PARTS
    out_dir: str = "out/eval"

    def __post_init__(self) -> None:
        unknown = [p for p in self.parts if p not in PARTS]
        if unknown:
            raise ValueError(f"unknown part(s) {unknown}; parts: {', '.join(PARTS)}")
        if self.generated < 0 or self.generated > 100:
            raise ValueError(f"generated must be 0-100 (the test seeds), got {self.generated}")
        if not self.seeds:
            raise ValueError("need at least one seed")


QUICK = BenchmarkConfig(generated=4, seeds=(0,), route="short", classifier_poses=60, trials=2, demo_speed=2.0,
                        demo_duration=90.0, out_dir="out/eval-quick")


@dataclass(frozen=True)
class Task:
    world: str  # label
    path: str  # world file or built-in name
    kind: str  # generated kind or "built-in"
    part: str
    seed: int
    trial: int = 0


@dataclass
class TaskResult:
    task: Task
    rows: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    error: str = ""


# ---------------------------------------------------------------------------------------------------------
# worlds and tasks

def prepare_worlds(cfg: BenchmarkConfig) -> list[tuple[str, str, str]]:
    """(label, path or built-in name, kind) of every world; generated ones are written to out_dir/worlds."""
    from glassmap.sim.generate import generate_world
    from glassmap.sim.seeds import TEST_SEEDS
    from glassmap.sim.world import load_world

    out = []
    wdir = Path(cfg.out_dir) / "worlds"
    for s in list(TEST_SEEDS)[: cfg.generated]:
        gw = generate_world(s)
        path = gw.save(wdir / f"gen-{gw.kind}-{s}.toml")
        out.append((f"gen-{gw.kind}-{s}", str(path), gw.kind))
    for w in cfg.worlds:
        load_world(w)  # a bad name or file stops the benchmark here, not once per task
        is_file = w.endswith(".toml") or "/" in w or "\\" in w
        out.append((Path(w).stem if is_file else w, w, "file" if is_file else "built-in"))
    return out


def make_tasks(cfg: BenchmarkConfig, worlds: list[tuple[str, str, str]]) -> list[Task]:
    tasks = []
    # slowest first, so the pool is not left waiting on one long task at the end
    order = {"demo": 0, "pose": 1, "experiment": 2, "map": 3, "classifier": 4}
    for part in sorted(cfg.parts, key=lambda p: order[p]):
        for label, path, kind in worlds:
            for seed in cfg.seeds:
                n = cfg.trials if part == "experiment" else 1
                tasks.extend(Task(label, path, kind, part, seed, i) for i in range(n))
    return tasks


def _route(world, cfg: BenchmarkConfig) -> str | None:
    if cfg.route is not None and cfg.route in world.routes:
        return cfg.route
    return world.default_route


# ---------------------------------------------------------------------------------------------------------
# the parts (each a call of the existing function)

def _classifier(task: Task, cfg: BenchmarkConfig) -> list[dict]:
    from glassmap.classifier import GlassClassifier
    from glassmap.eval.metrics import binary_report
    from glassmap.sim.laser import world_laser_params
    from glassmap.sim.world import load_world
    from glassmap.train import sample_poses, simulate_beams

    world = load_world(task.path)
    rng = np.random.default_rng(np.random.SeedSequence([task.seed, 11]))
    poses = sample_poses(world, cfg.classifier_poses, rng)
    beams = simulate_beams(world, poses, world_laser_params(world), rng)
    clf = GlassClassifier.load_default()
    p = clf.predict_beams(beams.x)
    rep = binary_report(beams.y, p)
    n_other = max(rep.n - rep.n_glass, 1)
    false_glass = float(((p > 0.5) & ~beams.y).sum() / n_other)
    nan = float("nan")
    if rep.n_glass == 0:  # a world without glass: only the false glass rate and the calibration mean something
        return [dict(balanced_accuracy=nan, precision=nan, recall=nan, roc_auc=nan, ece=rep.ece,
                     ece_balanced=nan, false_glass_rate=false_glass, n_beams=rep.n, n_glass=0)]
    return [dict(balanced_accuracy=rep.balanced_accuracy, precision=rep.precision, recall=rep.recall,
                 roc_auc=rep.roc_auc, ece=rep.ece, ece_balanced=rep.ece_balanced, false_glass_rate=false_glass,
                 n_beams=rep.n, n_glass=rep.n_glass)]


def _trial_config(task: Task, cfg: BenchmarkConfig, sigma_xy: float, sigma_theta: float, methods):
    from glassmap.eval.pose_error import PoseErrorModel
    from glassmap.eval.trial import TrialConfig
    from glassmap.sim.world import load_world

    world = load_world(task.path)
    return TrialConfig(world=task.path, route=_route(world, cfg), methods=tuple(methods),
                       pose_error=PoseErrorModel(sigma_xy=sigma_xy, sigma_theta=sigma_theta))


def _map(task: Task, cfg: BenchmarkConfig) -> list[dict]:
    from glassmap.eval.trial import run_trial

    res = run_trial(_trial_config(task, cfg, 0.0, 0.0, ("direct", "robust3")), task.seed)
    return [dict(method=m, **asdict(s)) for m, s in res.scores.items()]


def _experiment(task: Task, cfg: BenchmarkConfig) -> list[dict]:
    from glassmap.eval.trial import run_trial

    tc = _trial_config(task, cfg, cfg.sigma_xy, math.radians(cfg.sigma_theta_deg), METHODS)
    res = run_trial(tc, 1000 * task.seed + task.trial)
    return [dict(method=m, **asdict(s)) for m, s in res.scores.items()]


def _pose(task: Task, cfg: BenchmarkConfig) -> list[dict]:
    from glassmap.pose.evaluate import evaluate_run
    from glassmap.sim.world import load_world

    backend = None
    if cfg.pose_loop_closure:
        from glassmap.pose.backend import BackEndConfig

        backend = BackEndConfig()
    m = evaluate_run(task.path, _route(load_world(task.path), cfg), task.seed, backend_config=backend)
    return [dict(ate_rmse=m.ate_rmse, ate_max=m.ate_max, final_drift=m.final_drift, nees_mean=m.nees_mean,
                 inside_95=m.inside_95, nees_key_mean=m.nees_key_mean, nees_between_mean=m.nees_between_mean,
                 yaw_nees_key_mean=m.yaw_nees_key_mean, yaw_nees_between_mean=m.yaw_nees_between_mean,
                 along_nees_mean=m.along_nees_mean, cross_nees_mean=m.cross_nees_mean, yaw_nees_mean=m.yaw_nees_mean,
                 yaw_rmse_deg=m.yaw_rmse_deg, odom_ate_rmse=m.odom_ate_rmse,
                 length_m=m.length_m, scans=m.scans, lc_ate_rmse=m.lc_ate_rmse, lc_nees_mean=m.lc_nees_mean,
                 lc_inside_95=m.lc_inside_95, lc_closures=m.lc_closures, lc_false_closures=m.lc_false_closures)]


def _demo(task: Task, cfg: BenchmarkConfig) -> list[dict]:
    from glassmap.sim.world import load_world
    from runtime.config import MappingConfig, RuntimeConfig
    from runtime.demo import DemoOptions, final_error, run_demo

    world = load_world(task.path)
    out = Path(cfg.out_dir) / "demo" / f"{task.world}-s{task.seed}"
    config = RuntimeConfig(mapping=MappingConfig(loop_closure=cfg.demo_loop_closure))
    opts = DemoOptions(world=task.path, route=_route(world, cfg), speed=cfg.demo_speed, seed=task.seed,
                       out_dir=str(out), record=False, progress=False, duration=cfg.demo_duration, config=config)
    res = asyncio.run(run_demo(opts))
    ev = res.evaluation
    s = res.summary.stages
    nan = float("nan")
    err = (float(np.hypot(*(res.estimated_final_pose[:2] - res.true_final_pose[:2])))
           if res.estimated_final_pose is not None else nan)
    # the estimate the runtime reports at the end: the pose graph's correction of the front end's, if it ran
    front = final_error(res)
    final = final_error(res, corrected=True) or front
    # the runtime stopped the robot on its pose (a track lost past base.lost_hold, or base.max_sigma): said, not silent
    pose_stop = res.summary.stop_reason.startswith("pose estimate ")
    silent = nan if final is None else float(final[1] > 3.0 and not pose_stop)
    g = res.graph
    cev = res.corrected_evaluation
    return [dict(error=ev.error if ev else nan, glass_recall=ev.glass_recall if ev else nan,
                 corrected_error=cev.error if cev else nan, corrected_glass_recall=cev.glass_recall if cev else nan,
                 false_glass_rate=ev.false_glass_rate if ev else nan,
                 aligned_error=ev.aligned.error if ev is not None and ev.aligned is not None else nan,
                 final_pose_error=err, route_done=bool(res.route_done), scans_received=s.scans_received,
                 scans_processed=s.scans_processed, dropped=s.dropped_overflow + s.dropped_stale,
                 ate=res.trajectory.ate if res.trajectory is not None else nan,
                 frontend_sigma=nan if front is None else front[1], final_error=nan if final is None else final[0],
                 final_sigma=nan if final is None else final[1],
                 stopped_on_pose=pose_stop, lost_holds=res.summary.lost_holds, silent_divergence=silent,
                 closures=res.closures, false_closures=g.false if g is not None else 0,
                 worst_closure_xy=g.worst_xy if g is not None else nan,
                 worst_closure_yaw=g.worst_yaw if g is not None else nan, graph_lag=res.graph_lag)]


_RUNNERS = {"classifier": _classifier, "map": _map, "experiment": _experiment, "pose": _pose, "demo": _demo}


def run_task(task: Task, cfg: BenchmarkConfig) -> TaskResult:
    """Run one work unit; failures are reported in the result, not raised."""
    from glassmap.threads import one_thread

    one_thread()  # the classifier runs in numpy: one BLAS thread per worker process
    t0 = time.perf_counter()
    try:
        rows = _RUNNERS[task.part](task, cfg)
        return TaskResult(task, rows, time.perf_counter() - t0)
    except Exception as exc:  # one failed world must not lose the others' results
        return TaskResult(task, [], time.perf_counter() - t0, error=f"{type(exc).__name__}: {exc}")


def _run_task_args(args: tuple[Task, BenchmarkConfig]) -> TaskResult:
    return run_task(*args)


def run_tasks(tasks: list[Task], cfg: BenchmarkConfig, *, workers: int | None = None,
              dask_address: str | None = None, progress: bool = True) -> list[TaskResult]:
    """All tasks in a process pool (default: one worker per core) or on a Dask cluster; in task order."""
    results: list[TaskResult | None] = [None] * len(tasks)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), desc="benchmark", unit="task")
    try:
        if dask_address is None and local_workers(workers, len(tasks)) <= 1:
            for i, t in enumerate(tasks):
                results[i] = run_task(t, cfg)
                if bar is not None:
                    bar.set_postfix_str(f"{t.world} {t.part}", refresh=False)
                    bar.update(1)
        else:
            with job_executor(len(tasks), workers, dask_address) as executor:
                futs = {executor.submit(_run_task_args, (t, cfg)): i for i, t in enumerate(tasks)}
                for fut in concurrent.futures.as_completed(futs):
                    i = futs[fut]
                    try:
                        results[i] = fut.result()
                    except Exception as exc:  # a crashed worker
                        results[i] = TaskResult(tasks[i], error=f"{type(exc).__name__}: {exc}")
                    if bar is not None:
                        bar.set_postfix_str(f"{tasks[i].world} {tasks[i].part}", refresh=False)
                        bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return results  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------------------------
# aggregation

# per-world metric -> (part, selector, row field, True if higher is better)
METRICS: dict[str, tuple[str, str | None, str, bool]] = {
    "clf_balanced_accuracy": ("classifier", None, "balanced_accuracy", True),
    "clf_glass_precision": ("classifier", None, "precision", True),
    "clf_glass_recall": ("classifier", None, "recall", True),
    "clf_calibration_error": ("classifier", None, "ece", False),
    "clf_false_glass_rate": ("classifier", None, "false_glass_rate", False),
    "map_error_true_poses": ("map", "robust3", "error", False),
    "map_error_true_poses_direct": ("map", "direct", "error", False),
    "exp_direct_mean": ("experiment", "direct", "error", False),
    "exp_robust3_mean": ("experiment", "robust3", "error", False),
    "exp_robust5_mean": ("experiment", "robust5", "error", False),
    "pose_ate_rmse": ("pose", None, "ate_rmse", False),
    "pose_final_drift": ("pose", None, "final_drift", False),
    "pose_nees_mean": ("pose", None, "nees_mean", False),
    "pose_inside_95": ("pose", None, "inside_95", True),
    "pose_nees_key_mean": ("pose", None, "nees_key_mean", False),
    "pose_nees_between_mean": ("pose", None, "nees_between_mean", False),
    "pose_along_nees_mean": ("pose", None, "along_nees_mean", False),
    "pose_cross_nees_mean": ("pose", None, "cross_nees_mean", False),
    "pose_yaw_nees_mean": ("pose", None, "yaw_nees_mean", False),
    "pose_lc_nees_mean": ("pose", None, "lc_nees_mean", False),
    "pose_lc_inside_95": ("pose", None, "lc_inside_95", True),
    "demo_error": ("demo", None, "error", False),
    "demo_glass_recall": ("demo", None, "glass_recall", True),
    "demo_corrected_error": ("demo", None, "corrected_error", False),
    "demo_corrected_glass_recall": ("demo", None, "corrected_glass_recall", True),
    "demo_final_sigma": ("demo", None, "final_sigma", False),
    "demo_silent_divergence": ("demo", None, "silent_divergence", False),
}


def _nanmean(v: list[float]) -> float:
    a = np.asarray(v, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


def per_world(results: list[TaskResult]) -> list[dict]:
    """One row per world: the metrics of METRICS (means over seeds / trials), plus the experiment's worst
    trial and standard deviation per method."""
    worlds: dict[str, dict] = {}
    for r in results:
        w = worlds.setdefault(r.task.world, {"world": r.task.world, "kind": r.task.kind, "_rows": []})
        w["_rows"].extend((r.task, row) for row in r.rows)
    out = []
    for w in worlds.values():
        row = {"world": w["world"], "kind": w["kind"]}
        for name, (part, sel, fld, _) in METRICS.items():
            vals = [x[fld] for t, x in w["_rows"] if t.part == part and (sel is None or x.get("method") == sel)]
            row[name] = _nanmean(vals)
        for m in METHODS:
            vals = np.array([x["error"] for t, x in w["_rows"] if t.part == "experiment" and x.get("method") == m])
            row[f"exp_{m}_worst"] = float(vals.max()) if vals.size else float("nan")
            row[f"exp_{m}_std"] = float(vals.std()) if vals.size else float("nan")
        out.append(row)
    return out


def aggregate(world_rows: list[dict]) -> dict:
    """Per group (generated, built-in, all): mean over worlds and the worst world of every metric."""
    groups = {"generated": [r for r in world_rows if r["kind"] not in ("built-in", "file")],
              "built-in": [r for r in world_rows if r["kind"] == "built-in"],
              "files": [r for r in world_rows if r["kind"] == "file"], "all": world_rows}
    better = {k: v[3] for k, v in METRICS.items()}
    for m in METHODS:
        better[f"exp_{m}_worst"] = False
        better[f"exp_{m}_std"] = False
    out: dict = {}
    for g, rows in groups.items():
        if not rows:
            continue
        gd = {}
        for k, hb in better.items():
            vals = [(r[k], r["world"]) for r in rows if np.isfinite(r.get(k, float("nan")))]
            if not vals:
                continue
            v = np.array([x for x, _ in vals])
            i = int(np.argmin(v) if hb else np.argmax(v))
            gd[k] = {"mean": float(v.mean()), "worst": float(v[i]), "worst_world": vals[i][1], "worlds": len(v)}
        out[g] = gd
    return out


def write_csv(path: Path, rows: list[dict]) -> Path:
    keys: list[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    return path


def summary_figure(path: Path, world_rows: list[dict]) -> Path:
    """Four panels over worlds: classifier precision / recall, glass-map error (true poses; direct vs robust
    3x3 under pose error), pose ATE, demo per-cell error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["world"] for r in world_rows]
    x = np.arange(len(names))
    fig, axes = plt.subplots(4, 1, figsize=(max(10, 0.45 * len(names) + 5), 12), sharex=True)
    panels = [
        ("classifier (shipped weights)", [("clf_glass_precision", "glass precision"),
                                          ("clf_glass_recall", "glass recall"),
                                          ("clf_balanced_accuracy", "balanced accuracy")]),
        ("glass-map error", [("map_error_true_poses", "true poses, robust 3x3"),
                             ("exp_direct_mean", "sigma 5 cm, direct"), ("exp_robust3_mean", "sigma 5 cm, robust 3x3")]),
        ("pose", [("pose_ate_rmse", "ATE RMSE (m)"), ("pose_final_drift", "final drift (m)")]),
        ("runtime demo", [("demo_error", "per-cell error"), ("demo_glass_recall", "glass recall"),
                          ("demo_corrected_error", "per-cell error, graph-corrected maps")]),
    ]
    for ax, (title, series) in zip(axes, panels):
        wdt = 0.8 / len(series)
        for j, (k, label) in enumerate(series):
            ax.bar(x + (j - (len(series) - 1) / 2) * wdt, [r.get(k, np.nan) for r in world_rows], wdt, label=label)
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        ax.grid(axis="y", alpha=0.3)
    axes[-1].set_xticks(x)
    axes[-1].set_xticklabels(names, rotation=60, ha="right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


@dataclass
class BenchmarkReport:
    config: BenchmarkConfig
    worlds: list[dict]
    summary: dict
    failures: list[dict]
    seconds: float
    files: dict[str, str]


def run_benchmark(cfg: BenchmarkConfig, *, workers: int | None = None, dask_address: str | None = None,
                  progress: bool = True, figure: bool = True) -> BenchmarkReport:
    """Prepare the worlds, run every task, write per_run.csv, per_world.csv, summary.json (and
    summary.png) to ``cfg.out_dir``."""
    t0 = time.perf_counter()
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    worlds = prepare_worlds(cfg)
    tasks = make_tasks(cfg, worlds)
    results = run_tasks(tasks, cfg, workers=workers, dask_address=dask_address, progress=progress)
    raw = []
    for r in results:
        for row in r.rows:
            raw.append(dict(world=r.task.world, kind=r.task.kind, part=r.task.part, seed=r.task.seed,
                            trial=r.task.trial, seconds=round(r.seconds, 2), **row))
    failures = [dict(world=r.task.world, part=r.task.part, seed=r.task.seed, trial=r.task.trial, error=r.error)
                for r in results if r.error]
    wrows = per_world(results)
    summ = aggregate(wrows)
    files = {"per_run": str(write_csv(out / "per_run.csv", raw)),
             "per_world": str(write_csv(out / "per_world.csv", wrows))}
    if figure and wrows:
        files["figure"] = str(summary_figure(out / "summary.png", wrows))
    seconds = time.perf_counter() - t0
    part_seconds: dict[str, float] = {}
    for r in results:
        part_seconds[r.task.part] = part_seconds.get(r.task.part, 0.0) + r.seconds
    doc = {"config": asdict(cfg), "workers": workers or (os.cpu_count() or 1), "dask": dask_address,
           "seconds": seconds, "task_seconds_by_part": part_seconds, "summary": summ, "worlds": wrows,
           "failures": failures}
    (out / "summary.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    files["summary"] = str(out / "summary.json")
    (out / "summary.md").write_text(summary_markdown(doc))
    files["markdown"] = str(out / "summary.md")
    return BenchmarkReport(cfg, wrows, summ, failures, seconds, files)


_LABELS = {
    "clf_balanced_accuracy": "classifier balanced accuracy",
    "clf_glass_precision": "classifier glass precision",
    "clf_glass_recall": "classifier glass recall",
    "clf_calibration_error": "classifier calibration error",
    "clf_false_glass_rate": "classifier: other beams called glass",
    "map_error_true_poses": "glass-map error, true poses (robust 3x3)",
    "exp_direct_mean": "experiment sigma 5 cm: direct, mean error",
    "exp_robust3_mean": "experiment sigma 5 cm: robust 3x3, mean error",
    "exp_robust5_mean": "experiment sigma 5 cm: robust 5x5, mean error",
    "exp_direct_worst": "experiment: direct, worst trial",
    "exp_robust3_worst": "experiment: robust 3x3, worst trial",
    "pose_ate_rmse": "pose ATE RMSE (m)",
    "pose_final_drift": "pose final drift (m)",
    "pose_nees_mean": "pose mean NEES (ideal 3)",
    "pose_inside_95": "pose share inside the 95 % bound",
    "pose_nees_key_mean": "pose mean NEES of the key scans (ideal 3)",
    "pose_nees_between_mean": "pose mean NEES of the scans between key scans (ideal 3)",
    "pose_along_nees_mean": "pose mean NEES of the position along the track alone (ideal 1)",
    "pose_cross_nees_mean": "pose mean NEES of the position across the track alone (ideal 1)",
    "pose_yaw_nees_mean": "pose mean NEES of the heading alone (ideal 1)",
    "pose_lc_nees_mean": "pose with the pose graph: corrected estimate's mean NEES",
    "pose_lc_inside_95": "pose with the pose graph: share inside the 95 % bound",
    "demo_error": "demo per-cell error",
    "demo_glass_recall": "demo glass recall",
    "demo_corrected_error": "demo per-cell error, maps corrected by the pose graph",
    "demo_corrected_glass_recall": "demo glass recall, maps corrected by the pose graph",
    "demo_final_sigma": "demo final position error (sigma)",
    "demo_silent_divergence": "demo runs ending > 3 sigma off, not stopped",
}


_WORLD_COLUMNS = [("clf_glass_precision", "clf prec."), ("clf_glass_recall", "clf recall"),
                  ("clf_calibration_error", "clf ECE"), ("map_error_true_poses", "map err. true poses"),
                  ("exp_direct_mean", "direct"), ("exp_robust3_mean", "robust 3x3"), ("exp_robust5_mean", "robust 5x5"),
                  ("pose_ate_rmse", "ATE (m)"), ("pose_nees_mean", "NEES"), ("pose_inside_95", "in 95 %"),
                  ("pose_lc_nees_mean", "NEES (graph)"), ("pose_lc_inside_95", "in 95 % (graph)"),
                  ("demo_error", "demo err."), ("demo_glass_recall", "demo glass recall"),
                  ("demo_corrected_error", "demo err. (graph)"), ("demo_corrected_glass_recall", "demo recall (graph)"),
                  ("demo_final_sigma", "demo final sigma"), ("demo_silent_divergence", "demo diverged")]


def summary_markdown(doc: dict) -> str:
    """Markdown tables of a summary.json document: mean and worst world per group, then every world."""
    def f(v) -> str:
        return "-" if v is None or not np.isfinite(v) else f"{v:.3f}"

    groups = [g for g in ("generated", "built-in", "files") if g in doc["summary"]]
    lines = ["| metric | " + " | ".join(f"{g}: mean | {g}: worst (world)" for g in groups) + " |",
             "|---|" + "---|---|" * len(groups)]
    for k, label in _LABELS.items():
        cells = []
        for g in groups:
            d = doc["summary"][g].get(k)
            cells += ["-", "-"] if d is None else [f(d["mean"]), f"{f(d['worst'])} ({d['worst_world']})"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "| world | kind | " + " | ".join(h for _, h in _WORLD_COLUMNS) + " |",
              "|---|---|" + "---|" * len(_WORLD_COLUMNS)]
    for r in doc["worlds"]:
        lines.append(f"| {r['world']} | {r['kind']} | " + " | ".join(f(r.get(k)) for k, _ in _WORLD_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def format_report(rep: BenchmarkReport) -> str:
    lines = []
    groups = [g for g in ("generated", "built-in", "files") if g in rep.summary][:2]
    head = f"{'metric':<48}" + "".join(f"{g + ' mean':>16}{g + ' worst':>16}  worst world" for g in groups[:1])
    if len(groups) > 1:
        head += f"  |{groups[1] + ' mean':>16}{groups[1] + ' worst':>16}"
    lines.append(head)
    for k, label in _LABELS.items():
        parts = []
        for gi, g in enumerate(groups):
            d = rep.summary[g].get(k)
            if d is None:
                parts.append(f"{'-':>16}{'-':>16}" + ("  " + " " * 18 if gi == 0 else ""))
                continue
            cell = f"{d['mean']:>16.3f}{d['worst']:>16.3f}"
            if gi == 0:
                cell += f"  {d['worst_world']:<18}"
            else:
                cell = "|" + cell
            parts.append(cell)
        lines.append(f"{label:<48}" + "".join(parts))
    lines.append(f"{len(rep.worlds)} worlds, {rep.seconds:.0f} s; files: " + ", ".join(rep.files.values()))
    for f in rep.failures:
        lines.append(f"FAILED {f['world']} {f['part']} seed {f['seed']} trial {f['trial']}: {f['error']}")
    return "\n".join(lines)


def config_from_args(args) -> BenchmarkConfig:
    base = QUICK if args.quick else BenchmarkConfig()
    changes: dict = {"worlds": tuple(w.strip() for w in args.worlds.split(",") if w.strip())}
    if args.generated is not None:
        changes["generated"] = args.generated
    if not (args.quick and list(args.seeds) == list(SEEDS_DEFAULT)):
        changes["seeds"] = tuple(args.seeds)
    if args.route is not None:
        changes["route"] = None if args.route == "default" else args.route
    if args.trials is not None:
        changes["trials"] = args.trials
    if args.parts is not None:
        changes["parts"] = tuple(p for p in args.parts.split(",") if p)
    if args.demo_speed is not None:
        changes["demo_speed"] = args.demo_speed
    if args.demo_loop_closure:
        changes["demo_loop_closure"] = True
    if args.pose_loop_closure:
        changes["pose_loop_closure"] = True
    if args.classifier_poses is not None:
        changes["classifier_poses"] = args.classifier_poses
    if args.out is not None:
        changes["out_dir"] = args.out
    return replace(base, **changes)


SEEDS_DEFAULT = (0, 1, 2)


def add_arguments(p) -> None:
    from glassmap.cli_args import add_no_progress, add_out, add_seeds, add_workers, add_worlds

    p.add_argument("--quick", action="store_true", help="4 generated + the 4 built-in worlds, seed 0, short "
                   "routes, 2 trials (within 10 minutes on 2 cores)")
    p.add_argument("--generated", type=int, default=None, help="generated test worlds: world seeds 0..N-1 "
                   "(default 20, --quick 4)")
    add_worlds(p, ",".join(BUILTIN))
    add_seeds(p, "0-2")
    p.add_argument("--route", default=None, help="route used where a world has it, e.g. short; 'default' = each "
                   "world's default route (default: the default route; --quick: short)")
    p.add_argument("--trials", type=int, default=None, help="paper-experiment trials per world and seed (default 5, "
                   "--quick 2)")
    p.add_argument("--parts", default=None, help=f"comma-separated parts (default all: {','.join(PARTS)})")
    p.add_argument("--demo-speed", type=float, default=None, help="demo speed-up over real time (default 2)")
    p.add_argument("--demo-loop-closure", action="store_true", help="run the demo with the pose graph and loop "
                   "closure (--mapping.loop_closure); the final estimate scored is then the graph's correction of "
                   "the front end's. Every demo run reports that estimate's error in sigma of its covariance and "
                   "whether it ended more than 3 sigma off without the runtime having stopped on a lost track "
                   "(issue 20, item 0), and the maps the graph rebuilt at its final poses are scored beside the "
                   "online ones. Demos run in real time (times --demo-speed): use --workers 1")
    p.add_argument("--pose-loop-closure", action="store_true", help="the pose part also runs the pose graph behind "
                   "the estimator and reports the corrected estimate's ATE, mean NEES and share inside the 95 %% "
                   "bound beside the front end's (per_run.csv: lc_*; issue 20, item 1)")
    p.add_argument("--classifier-poses", type=int, default=None, help="scans of labelled beams per world and seed "
                   "(default 200, --quick 60)")
    add_out(p, None, "output directory; None = out/eval (--quick: out/eval-quick)")
    add_workers(p)
    p.add_argument("--dask", metavar="ADDRESS", default=None, help="run on a Dask cluster (scheduler address, e.g. "
                   "tcp://10.0.0.2:8786; needs pip install 'glassmap[dask]')")
    add_no_progress(p)


def cmd(args) -> int:
    import sys

    try:
        cfg = config_from_args(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rep = run_benchmark(cfg, workers=args.workers or None, dask_address=args.dask, progress=not args.no_progress)
    print(format_report(rep))
    return 1 if rep.failures else 0
