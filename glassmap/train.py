"""Training the glass classifiers on labelled beams simulated from generated worlds.

Data: scans simulated at poses sampled along each world's routes, each world with its own laser and
material parameters (``glassmap.sim.generate``: training worlds from the training seed range, early stopping
and calibration on validation worlds; test worlds are refused by ``glassmap.sim.seeds.check_not_test``).
Per beam the features of ``glassmap.glass_features`` with the incidence angle ESTIMATED by the same line
extractor the mapper uses; label = the first echo came from glass (sim truth). Beams without an estimated
angle are not used (the mapper gives them no probability either). The baseline's features are the first
three columns of the context model's, so one data set serves both models.

Training: class-balanced cross entropy (so that the logit is a log likelihood ratio and the output is
p(glass) under a 0.5 prior, which is exactly what the log-odds update of the glass map adds), Adam, early
stopping on the validation worlds, then temperature scaling on them.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .angles import AngleMethod, AngleParams, incidence_angles
from .classifier import ClassifierMeta, GlassClassifier, build_mlp
from .eval.metrics import binary_report
from .glass_features import FEATURES, scan_features


@dataclass(frozen=True)
class TrainConfig:
    """Training settings. model: ``context`` or ``baseline``; train_seeds / val_seeds: generated world seeds
    (training and validation ranges of glassmap.sim.seeds); scans_per_world: labelled scans per world;
    max_beams: training beams kept at most (all glass beams up to a fifth, non-glass for the rest; 0 = all)."""

    model: str = "context"
    train_seeds: tuple[int, ...] = tuple(range(10_000, 10_080))
    val_seeds: tuple[int, ...] = tuple(range(1000, 1020))
    scans_per_world: int = 40
    angle_method: AngleMethod = "split-merge"
    hidden: tuple[int, int, int] = (32, 32, 16)
    epochs: int = 10
    batch_size: int = 2048
    lr: float = 3e-3
    weight_decay: float = 1e-5
    max_beams: int = 400_000
    val_fraction: float = 0.15  # only when no validation beams are given
    seed: int = 0


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
    """Labelled beams: raw features (m, k) (glassmap.glass_features; the context model's columns, of which
    the baseline reads the first three), labels (m,) bool glass, the true incidence angles (rad, for
    diagnostics) and the index of the world (or recording) each beam came from."""

    x: np.ndarray
    y: np.ndarray
    true_incidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    group: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self) -> None:
        if self.group.shape[0] != self.y.shape[0]:
            self.group = np.zeros(self.y.shape[0], dtype=np.int64)
        if self.true_incidence.shape[0] != self.y.shape[0]:
            self.true_incidence = np.full(self.y.shape[0], np.nan)

    def __len__(self) -> int:
        return int(self.y.shape[0])

    def subset(self, idx: np.ndarray) -> "BeamSet":
        return BeamSet(self.x[idx], self.y[idx], self.true_incidence[idx], self.group[idx])

    @staticmethod
    def concat(sets: list["BeamSet"]) -> "BeamSet":
        return BeamSet(np.concatenate([s.x for s in sets]), np.concatenate([s.y for s in sets]),
                       np.concatenate([s.true_incidence for s in sets]), np.concatenate([s.group for s in sets]))

    def save(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(p, x=self.x, y=self.y, true_incidence=self.true_incidence, group=self.group)
        return p

    @staticmethod
    def load(path: str | Path) -> "BeamSet":
        with np.load(path) as d:
            return BeamSet(d["x"], d["y"].astype(bool), d["true_incidence"], d["group"])


def simulate_beams(world, poses: np.ndarray, laser_params, rng: np.random.Generator,
                   angle_method: AngleMethod = "split-merge", angle_params: AngleParams = AngleParams(),
                   progress=None, group: int = 0) -> BeamSet:
    """Simulate one scan per pose and keep the beams with an estimated incidence angle (context features)."""
    from .sim.laser import simulate_scan

    xs, ys, ts = [], [], []
    for pose in poses:
        s = simulate_scan(world, pose, rng, params=laser_params)
        inc = incidence_angles(s.geometry.angles, s.ranges, angle_method, angle_params)
        use = np.isfinite(inc.incidence) & np.isfinite(s.intensities) & np.isfinite(s.ranges)
        x = scan_features("context", s.geometry.angles, s.ranges, s.intensities, inc, s.echo_ranges,
                          s.echo_intensities)
        xs.append(x[use])
        ys.append(s.is_glass[use].astype(bool))
        ts.append(s.incidence[use])
        if progress is not None:
            progress.update(1)
    y = np.concatenate(ys)
    return BeamSet(np.concatenate(xs), y, np.concatenate(ts), np.full(y.shape[0], group, dtype=np.int64))


def generated_world(seed: int):
    """The generated world of ``seed`` (glassmap.sim.generate), parsed."""
    from .sim.generate import generate_world
    from .sim.world import parse_world

    gw = generate_world(seed)
    return parse_world(gw.text, file=f"<generated {gw.kind} {seed}>", default_name=f"gen-{gw.kind}-{seed}")


def simulate_worlds(seeds, scans_per_world: int, rng_seed: int, angle_method: AngleMethod = "split-merge",
                    progress=None, purpose: str = "training") -> BeamSet:
    """Labelled beams from generated worlds (each with its own laser parameters). Refuses test seeds."""
    from .sim.laser import world_laser_params
    from .sim.seeds import check_not_test

    seeds = check_not_test(seeds, purpose)
    parts = []
    for gi, seed in enumerate(seeds):
        world = generated_world(seed)
        rng = np.random.default_rng(np.random.SeedSequence([rng_seed, seed]))
        poses = sample_poses(world, scans_per_world, rng)
        parts.append(simulate_beams(world, poses, world_laser_params(world), rng, angle_method, progress=progress,
                                    group=gi))
    return BeamSet.concat(parts)


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


def _stratified(y: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of at most n beams: every glass beam up to a fifth of n, non-glass beams for the rest (the
    loss is class-balanced, so the share of each class does not change what is learnt)."""
    pos, neg = np.flatnonzero(y), np.flatnonzero(~y)
    n_pos = min(pos.size, n // 5)
    n_neg = min(neg.size, n - n_pos)
    return np.sort(np.concatenate([rng.choice(pos, n_pos, replace=False), rng.choice(neg, n_neg, replace=False)]))


def _balanced_weights(y: np.ndarray) -> np.ndarray:
    return np.where(y, 0.5 / max(int(y.sum()), 1), 0.5 / max(int((~y).sum()), 1))


def train_classifier(train: BeamSet, cfg: TrainConfig, val: BeamSet | None = None, init: GlassClassifier | None = None,
                     log=print) -> tuple[GlassClassifier, dict]:
    """Train the MLP of ``cfg.model`` with class-balanced cross entropy, early stopping and temperature
    scaling on ``val`` (default: a random ``val_fraction`` of ``train``). ``init``: fine-tune this
    classifier (same model; its normalisation is kept) instead of starting from scratch."""
    import torch
    import torch.nn.functional as F

    if cfg.model not in FEATURES:
        raise ValueError(f"unknown model {cfg.model!r}; models: {', '.join(FEATURES)}")
    k = len(FEATURES[cfg.model])
    if train.x.shape[1] < k:
        raise ValueError(f"model {cfg.model!r} needs {k} feature columns, the beams have {train.x.shape[1]}")
    if init is not None and init.meta.model != cfg.model:
        raise ValueError(f"cannot fine-tune a {init.meta.model!r} classifier as {cfg.model!r}")
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    if val is None:
        perm = rng.permutation(len(train))
        n_val = int(len(train) * cfg.val_fraction)
        val, train = train.subset(perm[:n_val]), train.subset(perm[n_val:])
    if cfg.max_beams and len(train) > cfg.max_beams:
        train = train.subset(_stratified(train.y, cfg.max_beams, rng))
    if not train.y.any() or train.y.all():
        raise ValueError("the training beams need both glass and non-glass examples")
    xtr = train.x[:, :k]
    if init is not None:
        mean, std = np.asarray(init.meta.mean), np.asarray(init.meta.std)
        model = init.model
    else:
        mean = xtr.mean(axis=0)
        std = xtr.std(axis=0) + 1e-6
        model = build_mlp(cfg.hidden, k)
    xt = torch.from_numpy(((xtr - mean) / std).astype(np.float32))
    yt = torch.from_numpy(train.y.astype(np.int64))
    xv = torch.from_numpy(((val.x[:, :k] - mean) / std).astype(np.float32))
    yv = val.y
    n_pos = int(train.y.sum())
    n_neg = len(train) - n_pos
    cw = torch.tensor([0.5 * len(train) / n_neg, 0.5 * len(train) / n_pos], dtype=torch.float32)
    wv = _balanced_weights(yv)

    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(cfg.epochs, 1))
    best, best_state, history = np.inf, None, []
    for epoch in range(cfg.epochs):
        model.train()
        order = torch.randperm(len(train))
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
            best_state = {kk: v.clone() for kk, v in model.state_dict().items()}
        log(f"epoch {epoch + 1:3d}/{cfg.epochs}: train loss {total / len(order):.4f}, "
            f"balanced validation NLL {val_nll:.4f}")
    if best_state is not None:
        model.load_state_dict(best_state)
    model.eval()
    with torch.inference_mode():
        lv = model(xv).numpy()
    d = (lv[:, 1] - lv[:, 0]).astype(np.float64)
    temperature = fit_temperature(d, yv, wv) if yv.any() and not yv.all() else 1.0
    meta = ClassifierMeta(hidden=tuple(cfg.hidden), mean=np.asarray(mean).tolist(), std=np.asarray(std).tolist(),
                          temperature=temperature, feature_names=FEATURES[cfg.model], model=cfg.model)
    if init is not None:
        meta = replace(meta, hidden=tuple(init.meta.hidden))
    clf = GlassClassifier.from_torch(model, meta)
    pv = clf.predict_beams(val.x)
    info = {"model": cfg.model, "fine_tuned": init is not None, "n_train": len(train), "n_val": len(val),
            "glass_share_train": float(train.y.mean()), "temperature": temperature,
            "validation": binary_report(yv, pv).as_dict(), "history": history[-3:]}
    return clf, info


def save_classifier(clf: GlassClassifier, stem: str | Path) -> tuple[Path, Path]:
    """Write ``stem.pt`` (state dict), ``stem.npz`` (the same weights for numpy inference, what
    :meth:`GlassClassifier.load` reads) and ``stem.json`` (model, normalisation, temperature, report)."""
    import torch

    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    pt, js = stem.with_suffix(".pt"), stem.with_suffix(".json")
    torch.save(clf.model.state_dict(), pt)
    clf.save_weights(stem.with_suffix(".npz"))
    js.write_text(clf.meta.to_json() + "\n")
    return pt, js


def run_training(cfg: TrainConfig = TrainConfig(), out_stem: str | Path | None = None, progress: bool = True,
                 log=print, data: tuple[BeamSet, BeamSet] | None = None,
                 init: GlassClassifier | None = None) -> dict:
    """Simulate the training and validation worlds (or use ``data`` = (train, val)), train ``cfg.model``
    (from scratch, or fine-tuning ``init``), write ``out_stem``.pt/.json (default out/glass_<model>).
    Returns the report."""
    import torch
    from tqdm import tqdm

    t0 = time.perf_counter()
    torch.set_num_threads(1)
    if data is None:
        total = (len(cfg.train_seeds) + len(cfg.val_seeds)) * cfg.scans_per_world
        bar = tqdm(total=total, desc="simulating scans", unit="scan", disable=not progress)
        train = simulate_worlds(cfg.train_seeds, cfg.scans_per_world, cfg.seed, cfg.angle_method, bar, "training")
        val = simulate_worlds(cfg.val_seeds, cfg.scans_per_world, cfg.seed + 1, cfg.angle_method, bar,
                              "validation (early stopping and calibration)")
        bar.close()
    else:
        train, val = data
    log(f"{len(train)} training beams ({int(train.y.sum())} glass), {len(val)} validation beams "
        f"({int(val.y.sum())} glass) in {time.perf_counter() - t0:.1f} s")
    clf, info = train_classifier(train, cfg, val=val, init=init, log=log)
    raw = GlassClassifier(clf.layers, replace(clf.meta, temperature=1.0))
    report = {
        "config": {kk: (list(v) if isinstance(v, tuple) else v) for kk, v in asdict(cfg).items()
                   if kk not in ("train_seeds", "val_seeds")},
        "train_seeds": _ranges(cfg.train_seeds), "val_seeds": _ranges(cfg.val_seeds),
        "train": info, "validation_before_temperature": binary_report(val.y, raw.predict_beams(val.x)).as_dict(),
        "seconds": time.perf_counter() - t0,
    }
    clf.meta.report = report
    pt, js = save_classifier(clf, out_stem if out_stem is not None else Path("out") / f"glass_{cfg.model}")
    report["files"] = [str(pt), str(js)]
    return report


def _ranges(seeds) -> str:
    """'10000-10079' style text of a seed list."""
    s = sorted(int(v) for v in seeds)
    if not s:
        return ""
    parts, a, b = [], s[0], s[0]
    for v in s[1:]:
        if v == b + 1:
            b = v
        else:
            parts.append(f"{a}-{b}" if b > a else f"{a}")
            a = b = v
    parts.append(f"{a}-{b}" if b > a else f"{a}")
    return ",".join(parts)
