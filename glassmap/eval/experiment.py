"""Many trials in a process pool, the CSV, the box plot (like the paper's Fig. 7) and the sigma sweep."""

from __future__ import annotations

import csv
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace

import numpy as np

from .trial import TrialConfig, TrialResult, run_trial


def _init_worker() -> None:
    from ..threads import one_thread

    one_thread()


def _run(args: tuple[TrialConfig, int]) -> TrialResult:
    cfg, seed = args
    return run_trial(cfg, seed)


def run_trials(cfg: TrialConfig, seeds: list[int], workers: int | None = None, progress: bool = True,
               desc: str = "trials") -> list[TrialResult]:
    """Run one trial per seed, in parallel over ``workers`` processes (default: all cores), one BLAS
    thread in each. Results are returned in seed order."""
    from tqdm import tqdm

    workers = workers or os.cpu_count() or 1
    results: dict[int, TrialResult] = {}
    bar = tqdm(total=len(seeds), desc=desc, unit="trial", disable=not progress)
    if workers <= 1:
        _init_worker()
        for s in seeds:
            results[s] = run_trial(cfg, s)
            bar.update(1)
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=_init_worker) as pool:
            futs = {pool.submit(_run, (cfg, s)): s for s in seeds}
            for f in as_completed(futs):
                results[futs[f]] = f.result()
                bar.update(1)
    bar.close()
    return [results[s] for s in seeds]


def rows_of(results: list[TrialResult]) -> list[dict]:
    rows = []
    for i, r in enumerate(results):
        rows.extend(r.rows(i))
    return rows


def write_csv(path: str, rows: list[dict]) -> str:
    if not rows:
        raise ValueError("no rows to write")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path


def summarise(rows: list[dict], key: str = "error") -> dict[str, dict[str, float]]:
    """Per method: mean, worst (max), std, median of ``key`` over trials, plus mean glass recall and
    false-glass rate."""
    out: dict[str, dict[str, float]] = {}
    for m in dict.fromkeys(r["method"] for r in rows):
        v = np.array([r[key] for r in rows if r["method"] == m], dtype=float)
        rec = np.array([r["glass_recall"] for r in rows if r["method"] == m], dtype=float)
        fg = np.array([r["false_glass_rate"] for r in rows if r["method"] == m], dtype=float)
        eo = np.array([r["error_occupied"] for r in rows if r["method"] == m], dtype=float)
        out[m] = dict(n=int(v.size), mean=float(np.nanmean(v)), worst=float(np.nanmax(v)),
                      std=float(np.nanstd(v)), median=float(np.nanmedian(v)), error_occupied=float(np.nanmean(eo)),
                      glass_recall=float(np.nanmean(rec)), false_glass_rate=float(np.nanmean(fg)))
    return out


def format_summary(summary: dict[str, dict[str, float]], title: str = "") -> str:
    lines = [title] if title else []
    lines.append(f"{'method':18s} {'n':>3s} {'mean':>7s} {'worst':>7s} {'std':>7s} {'err|occ':>8s} "
                 f"{'glassrec':>8s} {'falseglass':>10s}")
    for m, s in summary.items():
        lines.append(f"{m:18s} {s['n']:3d} {s['mean']:7.4f} {s['worst']:7.4f} {s['std']:7.4f} "
                     f"{s['error_occupied']:8.4f} {s['glass_recall']:8.4f} {s['false_glass_rate']:10.4f}")
    return "\n".join(lines)


def box_plot(path: str, rows: list[dict], title: str, key: str = "error") -> str:
    """Box plot of ``key`` per method over trials (the paper's Fig. 7 layout)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(dict.fromkeys(r["method"] for r in rows))
    data = [[r[key] for r in rows if r["method"] == m] for m in methods]
    fig, ax = plt.subplots(figsize=(1.3 * len(methods) + 2, 4))
    ax.boxplot(data, showmeans=True)
    ax.set_xticks(range(1, len(methods) + 1), methods, rotation=20)
    ax.set_ylabel("classification error" if key == "error" else key)
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def sweep(cfg: TrialConfig, sigmas_xy: list[float], seeds: list[int], workers: int | None = None,
          progress: bool = True) -> list[dict]:
    """Run the trials for each sigma_xy (m); sigma_theta and tau as in ``cfg``. Returns all rows, each with
    its sigma_xy."""
    rows: list[dict] = []
    for sx in sigmas_xy:
        c = replace(cfg, pose_error=replace(cfg.pose_error, sigma_xy=float(sx)))
        rows.extend(rows_of(run_trials(c, seeds, workers, progress, desc=f"sigma_xy {sx * 100:.0f} cm")))
    return rows


def sweep_plot(path: str, rows: list[dict]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(dict.fromkeys(r["method"] for r in rows))
    sig = sorted({r["sigma_xy"] for r in rows})
    fig, ax = plt.subplots(figsize=(6, 4))
    for m in methods:
        mean = [np.mean([r["error"] for r in rows if r["method"] == m and r["sigma_xy"] == s]) for s in sig]
        ax.plot(np.array(sig) * 100, mean, marker="o", label=m)
    ax.set_xlabel("sigma_xy (cm)")
    ax.set_ylabel("mean classification error")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


__all__ = ["TrialConfig", "run_trials", "write_csv", "summarise", "format_summary", "box_plot",
           "sweep", "sweep_plot", "rows_of"]
