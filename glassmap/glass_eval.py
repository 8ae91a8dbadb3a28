"""Evaluation of glass classifiers without retraining: on simulated worlds or on labelled beams.

Worlds: the generalisation benchmark's test worlds (generated worlds of the first ``generated`` test seeds,
``glassmap.sim.seeds.TEST_SEEDS``, plus the built-in worlds) or any world files. Per world and run seed,
labelled scans are simulated at poses along the routes exactly as the benchmark's classifier part does
(same random streams: ``SeedSequence([seed, 11])``, the world's own laser parameters), and every model is
scored on the same beams. Figures per world, their mean, and the worst world.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .eval.metrics import binary_report

BUILTIN = ("office", "glass-corridor", "room", "lobby")
SUMMARY_KEYS = ("balanced_accuracy", "precision", "recall", "roc_auc", "ece", "ece_balanced")
# keys where larger is worse (the worst world has the largest value)
_LOWER_IS_BETTER = ("ece", "ece_balanced")


@dataclass(frozen=True)
class EvalConfig:
    """generated: test worlds of test seeds 0 .. generated - 1; builtin / worlds: built-in names and world
    files added; seeds: run seeds per world; scans: labelled scans per world and seed."""

    generated: int = 20
    builtin: tuple[str, ...] = BUILTIN
    worlds: tuple[str, ...] = ()
    seeds: tuple[int, ...] = (0,)
    scans: int = 200
    angle_method: str = "split-merge"


def benchmark_worlds(cfg: EvalConfig) -> list[tuple[str, object]]:
    """(label, World) of every world of ``cfg``: generated test worlds first."""
    from .sim.generate import generate_world
    from .sim.seeds import TEST_SEEDS
    from .sim.world import load_world, parse_world

    if not 0 <= cfg.generated <= len(TEST_SEEDS):
        raise ValueError(f"generated must be 0-{len(TEST_SEEDS)} (the test seeds), got {cfg.generated}")
    out = []
    for s in list(TEST_SEEDS)[: cfg.generated]:
        gw = generate_world(s)
        label = f"gen-{gw.kind}-{s}"
        out.append((label, parse_world(gw.text, file=f"<generated {label}>", default_name=label)))
    out.extend((name, load_world(name)) for name in cfg.builtin)
    out.extend((Path(p).stem, load_world(p)) for p in cfg.worlds)
    return out


def world_beams(world, seed: int, scans: int, angle_method: str = "split-merge"):
    """The labelled beams of one world and run seed (the benchmark's classifier part's random streams)."""
    from .sim.laser import world_laser_params
    from .train import sample_poses, simulate_beams

    rng = np.random.default_rng(np.random.SeedSequence([seed, 11]))
    poses = sample_poses(world, scans, rng)
    return simulate_beams(world, poses, world_laser_params(world), rng, angle_method)


def score(y: np.ndarray, p: np.ndarray) -> dict:
    """binary_report figures plus the false glass rate (share of non-glass beams given p > 0.5). Balanced
    accuracy, precision and recall are NaN where the beams hold no glass (they are undefined there)."""
    rep = binary_report(y, p).as_dict()
    neg = ~np.asarray(y, dtype=bool)
    rep["false_glass_rate"] = float((np.asarray(p)[neg] > 0.5).mean()) if neg.any() else float("nan")
    if rep["n_glass"] == 0:
        for k in ("balanced_accuracy", "precision", "recall", "roc_auc"):
            rep[k] = float("nan")
    return rep


def per_world(rows: list[dict]) -> list[dict]:
    """Rows of the same world (several run seeds) averaged into one row per world."""
    out: dict[str, list[dict]] = {}
    for r in rows:
        out.setdefault(r["world"], []).append(r)
    keys = SUMMARY_KEYS + ("false_glass_rate",)
    return [{"world": w, "seeds": len(rs), "n": sum(r["n"] for r in rs), "n_glass": sum(r["n_glass"] for r in rs),
             **{k: float(np.mean([r[k] for r in rs])) for k in keys}} for w, rs in out.items()]


def summarise(rows: list[dict]) -> dict:
    """Mean over worlds (rows from :func:`per_world`) of SUMMARY_KEYS and the worst world's value; worlds
    without glass count only for the calibration error and the false glass rate."""
    if not rows:
        return {}
    out: dict = {"n_worlds": len(rows), "n_worlds_with_glass": sum(1 for r in rows if r["n_glass"] > 0)}
    for k in SUMMARY_KEYS + ("false_glass_rate",):
        v = np.array([r[k] for r in rows], dtype=np.float64)
        if np.isnan(v).all():
            out[f"{k}_mean"] = out[f"{k}_worst"] = float("nan")
            continue
        out[f"{k}_mean"] = float(np.nanmean(v))
        out[f"{k}_worst"] = float(np.nanmax(v) if k in _LOWER_IS_BETTER + ("false_glass_rate",) else np.nanmin(v))
    with_glass = [r for r in rows if r["n_glass"] > 0]
    if with_glass:
        out["worst_world"] = min(with_glass, key=lambda r: r["balanced_accuracy"])["world"]
    return out


def evaluate_worlds(classifiers: dict, cfg: EvalConfig = EvalConfig(), progress: bool = True, log=print) -> dict:
    """Score every classifier (name -> GlassClassifier) on the same beams of every world of ``cfg``.
    Returns {"config", "models": {name: {"summary", "worlds": [row per world and seed]}}, "seconds"}."""
    from tqdm import tqdm

    t0 = time.perf_counter()
    worlds = benchmark_worlds(cfg)
    rows: dict[str, list[dict]] = {name: [] for name in classifiers}
    bar = tqdm(total=len(worlds) * len(cfg.seeds), desc="worlds", unit="world", disable=not progress)
    for label, world in worlds:
        for seed in cfg.seeds:
            beams = world_beams(world, seed, cfg.scans, cfg.angle_method)
            for name, clf in classifiers.items():
                rows[name].append({"world": label, "seed": seed, **score(beams.y, clf.predict_beams(beams.x))})
            bar.update(1)
    bar.close()
    out = {"config": {"generated_test_worlds": cfg.generated, "builtin": list(cfg.builtin),
                      "worlds": list(cfg.worlds), "seeds": list(cfg.seeds), "scans": cfg.scans,
                      "angle_method": cfg.angle_method},
           "models": {name: {"summary": summarise(per_world(r)), "worlds": per_world(r), "runs": r}
                      for name, r in rows.items()},
           "seconds": time.perf_counter() - t0}
    return out


def evaluate_beams(classifiers: dict, beams, label: str = "beams") -> dict:
    """Score every classifier on labelled beams (a glassmap.train.BeamSet, e.g. from a labelled recording)."""
    return {"models": {name: {"summary": {**score(beams.y, clf.predict_beams(beams.x)), "data": label}}
                       for name, clf in classifiers.items()}}


def format_table(result: dict) -> str:
    """Text table: one line per model (mean and worst world, or the figures on labelled beams)."""
    rows = list(result["models"].items())
    if rows and "balanced_accuracy_mean" not in rows[0][1]["summary"]:
        lines = [f"{'model':14s} {'bal.acc':>8s} {'precision':>9s} {'recall':>7s} {'ECE(bal)':>8s} {'ECE':>7s}  data"]
        for name, m in rows:
            s = m["summary"]
            lines.append(f"{name:14s} {s['balanced_accuracy']:8.4f} {s['precision']:9.4f} {s['recall']:7.4f} "
                         f"{s['ece_balanced']:8.4f} {s['ece']:7.4f}  {s.get('data', '')} ({s['n']} beams, "
                         f"{s['n_glass']} glass)")
        return "\n".join(lines)
    lines = [f"{'model':10s} {'bal.acc mean/worst':>19s} {'precision mean/worst':>21s} {'recall mean/worst':>18s} "
             f"{'ECE(bal) mean/worst':>20s} {'ECE mean':>9s}  worst world"]
    for name, m in rows:
        s = m["summary"]
        lines.append(f"{name:10s} {s['balanced_accuracy_mean']:9.4f}/{s['balanced_accuracy_worst']:.4f} "
                     f"{s['precision_mean']:11.4f}/{s['precision_worst']:.4f} "
                     f"{s['recall_mean']:8.4f}/{s['recall_worst']:.4f} "
                     f"{s['ece_balanced_mean']:10.4f}/{s['ece_balanced_worst']:.4f} {s['ece_mean']:9.4f}  "
                     f"{s.get('worst_world', '')}")
    return "\n".join(lines)
