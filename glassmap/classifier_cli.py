"""``glassmap glass train`` and ``glassmap glass eval``: train the glass classifiers and score them without
retraining (on the benchmark's test worlds, on world files, or on labelled recordings)."""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

from glassmap.cli_args import add_no_progress, add_out, add_seed, parse_seeds


def _models(text: str) -> list[str]:
    from .glass_features import MODELS

    out = [m for m in text.split(",") if m]
    bad = [m for m in out if m not in MODELS]
    if bad or not out:
        raise argparse.ArgumentTypeError(f"unknown model(s) {bad}; models: {', '.join(MODELS)}")
    return out


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", type=_models, default=["context", "baseline"],
                   help="model(s) to train, comma separated: context, baseline (default: both)")
    p.add_argument("--train-seeds", type=parse_seeds, default="10000-10079",
                   help="generated training worlds (seeds 10000-99999; test seeds 0-99 are refused) "
                   "(default: %(default)s)")
    p.add_argument("--val-seeds", type=parse_seeds, default="1000-1019",
                   help="generated validation worlds for early stopping and calibration (default: %(default)s)")
    p.add_argument("--scans", type=int, default=40, help="labelled scans per world (default: %(default)s)")
    p.add_argument("--labelled", nargs="+", default=[], metavar="LABELS",
                   help="train on labelled recordings (.npz from `glassmap glass label`) instead of generated "
                   "worlds; the last 20 %% of each one's scans are kept for early stopping and calibration")
    p.add_argument("--heldout", default=None, metavar="LABELS",
                   help="a labelled recording not trained on: the trained and the shipped model are scored on it")
    p.add_argument("--fine-tune", action="store_true",
                   help="with --labelled: start from the shipped model (or --init) instead of from scratch")
    p.add_argument("--init", default=None, help="weights stem to fine-tune from (default: the shipped model)")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: 20; 15 with --labelled)")
    p.add_argument("--max-beams", type=int, default=1_500_000,
                   help="training beams kept at most (glass first; 0 = all) (default: %(default)s)")
    p.add_argument("--angle-method", default="split-merge", choices=["split-merge", "hough"],
                   help="incidence-angle method (default: %(default)s)")
    add_out(p, "out/classifier", "output directory: glass_<model>.npz/.pt/.json")
    p.add_argument("--replace-shipped", action="store_true",
                   help="write the weights into the package (glassmap/models/), replacing the shipped ones that "
                   "the runtime and the demo load")
    p.add_argument("--beams-cache", default=None,
                   help="directory to keep the simulated beams in (reused when the seeds and scans match)")
    add_seed(p)
    add_no_progress(p)


def cmd_train(args) -> int:
    from .classifier import GlassClassifier, shipped_stem
    from .sim.seeds import TestSeedError, check_not_test
    from .train import BeamSet, TrainConfig, run_training, simulate_worlds

    try:
        train_seeds = tuple(check_not_test(args.train_seeds, "training"))
        val_seeds = tuple(check_not_test(args.val_seeds, "validation (early stopping and calibration)"))
    except TestSeedError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.fine_tune and not args.labelled:
        print("error: --fine-tune needs --labelled recordings", file=sys.stderr)
        return 2
    out_dir = Path(args.out)
    progress = not args.no_progress
    heldout = _load_labels(args.heldout, -1) if args.heldout else None
    if args.labelled:
        parts = [_split_recording(_load_labels(p, i)) for i, p in enumerate(args.labelled)]
        tr = BeamSet.concat([a for a, _ in parts])
        va = BeamSet.concat([b for _, b in parts])
        data_note = f"labelled recordings {', '.join(args.labelled)}"
    else:
        tr, va = _simulated(args, train_seeds, val_seeds, progress, simulate_worlds, BeamSet)
        data_note = f"generated worlds {len(train_seeds)} training + {len(val_seeds)} validation"
    epochs = args.epochs if args.epochs is not None else (15 if args.labelled else 20)
    results = {}
    for model in args.model:
        cfg = TrainConfig(model=model, train_seeds=train_seeds, val_seeds=val_seeds, scans_per_world=args.scans,
                          angle_method=args.angle_method, epochs=epochs, max_beams=args.max_beams, seed=args.seed)
        stem = shipped_stem(model) if args.replace_shipped else out_dir / f"glass_{model}"
        init = None
        if args.fine_tune:
            init = GlassClassifier.load(args.init) if args.init else GlassClassifier.load_default(model)
        print(f"== {model}: {data_note}{' (fine-tuning ' + init.meta.model + ')' if init else ''}")
        shipped = GlassClassifier.load_default(model) if heldout is not None else None  # before any replacing
        rep = run_training(cfg, out_stem=stem, progress=progress, data=(tr, va), init=init,
                           log=(print if progress else (lambda *_: None)))
        v = rep["train"]["validation"]
        what = "validation scans of the recordings" if args.labelled else "validation worlds"
        print(f"{model} on the {what}: balanced accuracy {v['balanced_accuracy']:.4f}, precision "
              f"{v['precision']:.4f}, recall {v['recall']:.4f}, ECE (balanced) {v['ece_balanced']:.4f}, "
              f"temperature {rep['train']['temperature']:.3f}")
        if heldout is not None:
            from .eval.metrics import binary_report

            trained = GlassClassifier.load(stem)
            rep["heldout"] = {"file": args.heldout,
                              "trained": binary_report(heldout.y, trained.predict_beams(heldout.x)).as_dict(),
                              "shipped": binary_report(heldout.y, shipped.predict_beams(heldout.x)).as_dict()}
            for k in ("trained", "shipped"):
                h = rep["heldout"][k]
                print(f"   held-out recording, {k:7s} {model}: balanced accuracy {h['balanced_accuracy']:.4f}, "
                      f"precision {h['precision']:.4f}, recall {h['recall']:.4f}, ECE (balanced) "
                      f"{h['ece_balanced']:.4f}")
        print(f"   wrote {', '.join(rep['files'])} in {rep['seconds']:.0f} s")
        results[model] = rep
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "train_report.json").write_text(json.dumps(_strict(results), indent=2) + "\n")
    if not args.replace_shipped:
        print("the shipped weights are unchanged (use --replace-shipped to replace them)")
    return 0


def _load_labels(path: str, recording: int):
    """The labelled beams of a recording; ``group`` = scan index (for the validation split)."""
    from .labeling import load_labels

    lab = load_labels(path)
    beams = lab.beams()
    beams.group = lab.scan_index.astype("int64")
    return beams


def _strict(obj):
    """``obj`` with NaN / inf floats as null and numpy scalars as Python numbers (strict JSON)."""
    import math

    if isinstance(obj, dict):
        return {k: _strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_strict(v) for v in obj]
    if hasattr(obj, "item") and not isinstance(obj, (str, bytes)):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _split_recording(beams, share: float = 0.2):
    """(training, validation) beams of one recording: validation = the beams of the last ``share`` of its
    scans (a contiguous stretch, so that neighbouring scans do not leak into it)."""
    import numpy as np

    cut = np.quantile(beams.group, 1.0 - share) if len(beams) else 0
    val = beams.group >= cut
    return beams.subset(np.flatnonzero(~val)), beams.subset(np.flatnonzero(val))


def _simulated(args, train_seeds, val_seeds, progress, simulate_worlds, BeamSet):
    from tqdm import tqdm

    from .train import _ranges

    cache = None
    if args.beams_cache:
        key = f"{_ranges(train_seeds)}_{_ranges(val_seeds)}_{args.scans}_{args.angle_method}_{args.seed}"
        cache = Path(args.beams_cache) / f"beams_{hashlib.sha1(key.encode()).hexdigest()[:12]}"
        cache.parent.mkdir(parents=True, exist_ok=True)
        tp, vp, kp = cache.with_suffix(".train.npz"), cache.with_suffix(".val.npz"), cache.with_suffix(".key")
        if tp.is_file() and vp.is_file() and kp.is_file() and kp.read_text() == key:
            print(f"reusing the simulated beams in {tp} and {vp}")
            return BeamSet.load(tp), BeamSet.load(vp)
    bar = tqdm(total=(len(train_seeds) + len(val_seeds)) * args.scans, desc="simulating scans", unit="scan",
               disable=not progress)
    tr = simulate_worlds(train_seeds, args.scans, args.seed, args.angle_method, bar, "training")
    va = simulate_worlds(val_seeds, args.scans, args.seed + 1, args.angle_method, bar,
                         "validation (early stopping and calibration)")
    bar.close()
    if cache is not None:
        tr.save(tp)
        va.save(vp)
        kp.write_text(key)
    return tr, va


def add_eval_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", default="context,baseline",
                   help="classifiers to score, comma separated: shipped model names (context, baseline) or "
                   "weights stems (path without .pt/.json) (default: %(default)s)")
    p.add_argument("--generated", type=int, default=20,
                   help="generated test worlds (test seeds 0 .. N-1, as the benchmark) (default: %(default)s)")
    p.add_argument("--builtin", default="office,glass-corridor,room,lobby",
                   help="built-in worlds added ('' for none) (default: %(default)s)")
    p.add_argument("--world", action="append", default=[], help="a world file to add (repeatable)")
    p.add_argument("--seeds", type=parse_seeds, default="0", help="run seeds per world (default: %(default)s)")
    p.add_argument("--scans", type=int, default=200, help="labelled scans per world and seed (default: %(default)s)")
    p.add_argument("--labelled", default=None, metavar="LABELS",
                   help="score on a labelled recording (.npz from `glassmap glass label`) instead of worlds")
    add_out(p, "out/classifier-eval", "output directory: eval.json")
    add_no_progress(p)


def load_classifiers(spec: str) -> dict:
    """name -> GlassClassifier for shipped model names or weights stems."""
    from .classifier import GlassClassifier
    from .glass_features import MODELS

    out = {}
    for item in (s for s in spec.split(",") if s):
        out[item] = (GlassClassifier.load_default(item) if item in MODELS
                                                            else GlassClassifier.load(item))
    return out


def cmd_eval(args) -> int:
    from .classifier import ClassifierError
    from .glass_eval import EvalConfig, evaluate_beams, evaluate_worlds, format_table
    from .threads import one_thread

    one_thread()
    try:
        classifiers = load_classifiers(args.models)
    except ClassifierError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.labelled:
        from .labeling import load_labels

        result = evaluate_beams(classifiers, load_labels(args.labelled).beams(), label=args.labelled)
    else:
        cfg = EvalConfig(generated=args.generated, builtin=tuple(w for w in args.builtin.split(",") if w),
                         worlds=tuple(args.world), seeds=tuple(args.seeds), scans=args.scans)
        result = evaluate_worlds(classifiers, cfg, progress=not args.no_progress)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "eval.json").write_text(json.dumps(_strict(result), indent=2) + "\n")
    print(format_table(result))
    print(f"wrote {out / 'eval.json'}")
    return 0
