"""Training the glass classifier on labelled beams simulated from several worlds and simulator parameter sets.

Data: scans simulated at poses sampled along each world's routes; per beam the measured intensity, the
measured range and the incidence angle ESTIMATED by the same line extractor the mapper uses (so the
network learns the angles it will see at run time); label = the return came from glass (sim truth).
Beams without an estimated angle are not used (the mapper gives them no probability either).

Training: class-balanced cross entropy (so that the logit is a log likelihood ratio and the output is
p(glass) under a 0.5 prior, which is exactly what the log-odds update of the glass map adds), Adam, early
stopping on a validation split of the training worlds, then temperature scaling on that split. The report
is computed on a held-out world simulated with shifted laser parameters.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .angles import AngleMethod, AngleParams, incidence_angles
from .classifier import MODEL_DIR, DEFAULT_STEM, ClassifierMeta, GlassClassifier, build_mlp, features
from .eval.metrics import binary_report


@dataclass(frozen=True)
class TrainConfig:
    """Training settings. Worlds are built-in names or paths; poses_per_world scans per world and parameter
    set; param_sets: how many laser parameter sets per training world (set 0 = defaults)."""

    train_worlds: tuple[str, ...] = ("office", "glass-corridor", "room")
    heldout_world: str = "lobby"
    poses_per_world: int = 300
    heldout_poses: int = 300
    param_sets: int = 3
    angle_method: AngleMethod = "split-merge"
    hidden: tuple[int, int, int] = (32, 32, 16)
    epochs: int = 25
    batch_size: int = 2048
    lr: float = 3e-3
    weight_decay: float = 1e-5
    val_fraction: float = 0.15
    seed: int = 0


def laser_param_sets(k: int) -> list:
    """k laser parameter sets for training: the defaults, then variations of intensity scale, noise, glass
    window and return probability, distance exponent."""
    from .sim.laser import LaserParams

    base = LaserParams()
    variations = [
        {},
        dict(intensity_scale=7000.0, intensity_noise=0.15, glass_window=math.radians(13.0), glass_return_prob=0.8),
        dict(intensity_scale=5000.0, range_exponent=1.15, glass_window=math.radians(17.0), glass_return_prob=0.9,
             range_noise=0.012),
        dict(intensity_scale=6500.0, intensity_noise=0.10, cos_exponent=1.3, glass_window_exponent=0.8),
        dict(intensity_scale=5500.0, intensity_noise=0.18, glass_return_prob=0.7, range_noise=0.015),
    ]
    if k < 1:
        raise ValueError(f"need at least one parameter set, got {k}")
    return [replace(base, **variations[i % len(variations)]) for i in range(k)]


def heldout_laser_params():
    """Shifted parameters for the held-out world (none of the training sets uses these values)."""
    from .sim.laser import LaserParams

    return replace(LaserParams(), intensity_scale=5800.0, intensity_noise=0.16, glass_window=math.radians(14.0),
                   glass_return_prob=0.75, range_noise=0.013, cos_exponent=1.15, range_exponent=1.05)


def sample_poses(world, n: int, rng: np.random.Generator, lateral: float = 0.15) -> np.ndarray:
    """n laser poses (x, y, yaw) along the world's routes: uniform in arc length, lateral offset ~N(0,
    lateral) m (clipped to 2 sigma), yaw along the route +- noise, 30 % of them with a random yaw."""
    legs = []
    for wp in world.routes.values():
        wp = np.asarray(wp, dtype=np.float64)
        legs.extend(zip(wp[:-1], wp[1:]))
    a = np.array([l[0] for l in legs])
    b = np.array([l[1] for l in legs])
    length = np.hypot(*(b - a).T)
    leg = rng.choice(len(legs), size=n, p=length / length.sum())
    t = rng.uniform(0, 1, n)
    d = (b - a)[leg]
    heading = np.arctan2(d[:, 1], d[:, 0])
    pos = a[leg] + t[:, None] * d
    off = np.clip(rng.normal(0, lateral, n), -2 * lateral, 2 * lateral)
    pos += off[:, None] * np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    yaw = heading + rng.normal(0, 0.4, n)
    rnd = rng.uniform(0, 1, n) < 0.3
    yaw[rnd] = rng.uniform(-np.pi, np.pi, rnd.sum())
    return np.column_stack([pos, yaw])


@dataclass
class BeamSet:
    """Labelled beams: raw features (m, 3) (see classifier.features), labels (m,) bool glass, and the true
    and estimated incidence angles (rad) for diagnostics."""

    x: np.ndarray
    y: np.ndarray
    true_incidence: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @staticmethod
    def concat(sets: list["BeamSet"]) -> "BeamSet":
        return BeamSet(np.concatenate([s.x for s in sets]), np.concatenate([s.y for s in sets]),
                       np.concatenate([s.true_incidence for s in sets]))


def simulate_beams(world, poses: np.ndarray, laser_params, rng: np.random.Generator,
                   angle_method: AngleMethod = "split-merge", angle_params: AngleParams = AngleParams(),
                   progress=None) -> BeamSet:
    """Simulate one scan per pose and keep the beams with an estimated incidence angle."""
    from .sim.laser import simulate_scan

    xs, ys, ts = [], [], []
    for pose in poses:
        s = simulate_scan(world, pose, rng, params=laser_params)
        inc = incidence_angles(s.geometry.angles, s.ranges, angle_method, angle_params).incidence
        use = np.isfinite(inc) & np.isfinite(s.intensities) & np.isfinite(s.ranges)
        xs.append(features(s.intensities[use], s.ranges[use], inc[use]))
        ys.append(s.is_glass[use].astype(bool))
        ts.append(s.incidence[use])
        if progress is not None:
            progress.update(1)
    return BeamSet(np.concatenate(xs), np.concatenate(ys), np.concatenate(ts))


def fit_temperature(logit_diff: np.ndarray, y: np.ndarray, weights: np.ndarray) -> float:
    """Temperature T minimising the weighted binary NLL of sigmoid(logit_diff / T) (grid + refinement)."""
    def nll(t: float) -> float:
        z = logit_diff / t
        lp = -np.logaddexp(0.0, -z)  # log sigmoid(z)
        ln = -np.logaddexp(0.0, z)
        return float(-np.sum(weights * np.where(y, lp, ln)) / weights.sum())

    grid = np.exp(np.linspace(np.log(0.25), np.log(8.0), 61))
    best = grid[int(np.argmin([nll(t) for t in grid]))]
    fine = best * np.exp(np.linspace(-0.06, 0.06, 25))
    return float(fine[int(np.argmin([nll(t) for t in fine]))])


def train_classifier(train: BeamSet, cfg: TrainConfig, log=print) -> tuple[GlassClassifier, dict]:
    """Train the MLP with class-balanced cross entropy, early stopping and temperature scaling."""
    import torch
    import torch.nn.functional as F

    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    n = len(train.y)
    perm = rng.permutation(n)
    n_val = int(n * cfg.val_fraction)
    val_idx, tr_idx = perm[:n_val], perm[n_val:]
    mean = train.x[tr_idx].mean(axis=0)
    std = train.x[tr_idx].std(axis=0) + 1e-6
    z = ((train.x - mean) / std).astype(np.float32)
    xt, yt = torch.from_numpy(z[tr_idx]), torch.from_numpy(train.y[tr_idx].astype(np.int64))
    xv, yv = torch.from_numpy(z[val_idx]), train.y[val_idx]
    n_pos = max(int(train.y[tr_idx].sum()), 1)
    n_neg = max(len(tr_idx) - n_pos, 1)
    cw = torch.tensor([0.5 * len(tr_idx) / n_neg, 0.5 * len(tr_idx) / n_pos], dtype=torch.float32)
    wv = np.where(yv, 0.5 / max(yv.sum(), 1), 0.5 / max((~yv).sum(), 1))

    model = build_mlp(cfg.hidden)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.epochs)
    best, best_state, history = np.inf, None, []
    for epoch in range(cfg.epochs):
        model.train()
        order = torch.randperm(len(tr_idx))
        total = 0.0
        for i in range(0, len(order), cfg.batch_size):
            b = order[i:i + cfg.batch_size]
            loss = F.cross_entropy(model(xt[b]), yt[b], weight=cw)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
        sched.step()
        model.eval()
        with torch.inference_mode():
            lv = model(xv).numpy()
        d = (lv[:, 1] - lv[:, 0]).astype(np.float64)
        val_nll = float(np.sum(wv * np.logaddexp(0.0, -np.where(yv, d, -d))))
        history.append({"epoch": epoch, "train_loss": total / len(order), "val_nll_balanced": val_nll})
        if val_nll < best:
            best = val_nll
            best_state = {k: v.clone() for k, v in model.state_dict().items()}
        log(f"epoch {epoch + 1:3d}/{cfg.epochs}: train loss {total / len(order):.4f}, "
            f"balanced val NLL {val_nll:.4f}")
    model.load_state_dict(best_state)
    model.eval()
    with torch.inference_mode():
        lv = model(xv).numpy()
    d = (lv[:, 1] - lv[:, 0]).astype(np.float64)
    temperature = fit_temperature(d, yv, wv)
    meta = ClassifierMeta(hidden=tuple(cfg.hidden), mean=mean.tolist(), std=std.tolist(), temperature=temperature)
    clf = GlassClassifier(model, meta)
    pv = clf.predict(np.expm1(train.x[val_idx, 0]), train.x[val_idx, 1], train.x[val_idx, 2])
    info = {"n_train": int(len(tr_idx)), "n_val": int(n_val), "glass_share_train": float(train.y.mean()),
            "temperature": temperature, "validation": binary_report(yv, pv).as_dict(), "history": history[-3:]}
    return clf, info


def save_classifier(clf: GlassClassifier, stem: str | Path) -> tuple[Path, Path]:
    """Write ``stem.pt`` (state dict) and ``stem.json`` (normalisation, temperature, report)."""
    import torch

    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    pt, js = stem.with_suffix(".pt"), stem.with_suffix(".json")
    torch.save(clf.model.state_dict(), pt)
    js.write_text(clf.meta.to_json() + "\n")
    return pt, js


def run_training(cfg: TrainConfig = TrainConfig(), out_stem: str | Path = MODEL_DIR / DEFAULT_STEM,
                 progress: bool = True, log=print) -> dict:
    """Simulate the data, train, evaluate on the held-out world, write the weights. Returns the report."""
    import torch
    from tqdm import tqdm

    from .sim.world import load_world

    t0 = time.perf_counter()
    torch.set_num_threads(1)
    rng = np.random.default_rng(cfg.seed)
    sets = laser_param_sets(cfg.param_sets)
    total = len(cfg.train_worlds) * len(sets) * cfg.poses_per_world + cfg.heldout_poses
    bar = tqdm(total=total, desc="simulating beams", unit="scan", disable=not progress)
    parts = []
    per_world = {}
    for name in cfg.train_worlds:
        world = load_world(name)
        for params in sets:
            poses = sample_poses(world, cfg.poses_per_world, rng)
            part = simulate_beams(world, poses, params, rng, cfg.angle_method, progress=bar)
            parts.append(part)
            per_world[name] = per_world.get(name, 0) + int(part.y.sum())
    held_world = load_world(cfg.heldout_world)
    held_params = heldout_laser_params()
    held = simulate_beams(held_world, sample_poses(held_world, cfg.heldout_poses, rng), held_params, rng,
                          cfg.angle_method, progress=bar)
    bar.close()
    train = BeamSet.concat(parts)
    log(f"{len(train.y)} training beams ({int(train.y.sum())} glass), {len(held.y)} held-out beams "
        f"({int(held.y.sum())} glass) in {time.perf_counter() - t0:.1f} s")
    clf, info = train_classifier(train, cfg, log=log)
    ph = clf.predict(np.expm1(held.x[:, 0]), held.x[:, 1], held.x[:, 2])
    held_report = binary_report(held.y, ph)
    # the same beams scored without temperature scaling, to show what calibration changed
    raw = GlassClassifier(clf.model, replace(clf.meta, temperature=1.0))
    held_raw = binary_report(held.y, raw.predict(np.expm1(held.x[:, 0]), held.x[:, 1], held.x[:, 2]))
    inc_err = np.degrees(np.abs(held.x[:, 2] - held.true_incidence))
    inc_err = inc_err[np.isfinite(inc_err)]
    report = {
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()},
        "train": info,
        "heldout": {"world": cfg.heldout_world, "laser_params": {k: v for k, v in asdict(held_params).items()},
                    **held_report.as_dict(), "before_temperature": held_raw.as_dict(),
                    "incidence_error_deg_median": float(np.median(inc_err)) if inc_err.size else None},
        "seconds": time.perf_counter() - t0,
    }
    clf.meta.report = report
    pt, js = save_classifier(clf, out_stem)
    report["files"] = [str(pt), str(js)]
    return report
