"""Per-beam glass classifiers (docs/method.md section 2): features of a beam -> p(glass).

An MLP (trained with torch, run with numpy) with 4 fully connected layers and a softmax over {not glass, glass} (class 1 = glass). Two
named models differ only in their inputs (``glassmap.glass_features``): ``baseline`` is the paper's
f(intensity, distance, incidence); ``context`` adds the beam's echoes, its neighbours along the scan and
its place on its line segment. Inputs are standardised with the training set's mean and standard
deviation. A temperature (fitted on validation worlds) divides the logits before the softmax so that
outputs behave as probabilities for the Bayesian update.

The trained weights ship in ``glassmap/models/glass_<model>.npz`` (numpy arrays, read at run time) and
``glass_<model>.pt`` (the same as a torch state dict) with ``glass_<model>.json`` (model name, normalisation,
temperature, architecture and the training report);
:meth:`GlassClassifier.load_default` loads them from the package, without network.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from .classifier_jit import add_bias_relu, negative_logit_gaps, standardise, standardise_rows
from .glass_features import scan_features

MODEL_DIR = Path(__file__).resolve().parent / "models"
DEFAULT_MODEL = "context"
FALLBACK_MODEL = "baseline"


def shipped_stem(model: str = DEFAULT_MODEL) -> Path:
    """Path stem of the weights shipped for a named model (``baseline`` or ``context``)."""
    from .glass_features import MODELS

    if model not in MODELS:
        raise ClassifierError(f"unknown classifier model {model!r}; shipped models: {', '.join(MODELS)}")
    return MODEL_DIR / f"glass_{model}"


class ClassifierError(RuntimeError):
    """The classifier weights or their metadata are missing or do not fit together."""


def features(intensity: np.ndarray, distance: np.ndarray, incidence: np.ndarray) -> np.ndarray:
    """Raw feature matrix (n, 3) float32: log1p(intensity clipped at 0), distance (m), incidence (rad)."""
    i = np.asarray(intensity, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    a = np.asarray(incidence, dtype=np.float64)
    if not (i.shape == d.shape == a.shape) or i.ndim != 1:
        raise ValueError(f"intensity {i.shape}, distance {d.shape} and incidence {a.shape} must be equal 1-D shapes")
    x = np.empty((i.shape[0], 3), dtype=np.float32)
    x[:, 0] = np.log1p(np.maximum(i, 0.0))
    x[:, 1] = d
    x[:, 2] = np.abs(a)
    return x


@dataclass
class ClassifierMeta:
    """Everything besides the weights needed to run the classifier."""

    hidden: tuple[int, int, int] = (32, 32, 16)
    mean: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    std: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    temperature: float = 1.0
    feature_names: tuple[str, ...] = ("log1p(intensity)", "distance_m", "incidence_rad")
    model: str = "baseline"
    report: dict = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "ClassifierMeta":
        d = json.loads(text)
        return cls(hidden=tuple(d["hidden"]), mean=list(d["mean"]), std=list(d["std"]),
                   temperature=float(d.get("temperature", 1.0)),
                   feature_names=tuple(d.get("feature_names", cls.feature_names)),
                   model=str(d.get("model", "baseline")), report=d.get("report", {}))


def build_mlp(hidden: tuple[int, int, int] = (32, 32, 16), n_in: int = 3):
    """The network: 4 linear layers (n_in -> h1 -> h2 -> h3 -> 2) with ReLU; outputs logits over
    {not glass, glass}."""
    import torch.nn as nn

    h1, h2, h3 = hidden
    return nn.Sequential(nn.Linear(n_in, h1), nn.ReLU(), nn.Linear(h1, h2), nn.ReLU(), nn.Linear(h2, h3), nn.ReLU(),
                         nn.Linear(h3, 2))


class GlassClassifier:
    """Trained glass classifier. Inference is numpy (one BLAS product per layer for a whole scan), so the
    runtime does not load torch; :attr:`model` gives the torch module for training and fine-tuning.

    layers: per linear layer its weight (out, in) and bias (out,), float32, in the order of
    :func:`build_mlp` (ReLU between layers)."""

    def __init__(self, layers: list[tuple[np.ndarray, np.ndarray]], meta: ClassifierMeta) -> None:
        self.meta = meta
        self._layers: list[tuple[np.ndarray, np.ndarray]] = []
        for w, b in layers:
            w = np.array(w, dtype=np.float32)
            # weight decay leaves some dead weights at denormal magnitudes (~1e-40), which makes the
            # products 10-20x slower on x86; they contribute nothing, so zero them
            w[np.abs(w) < 1e-30] = 0.0
            b = np.array(b, dtype=np.float32)
            b[np.abs(b) < 1e-30] = 0.0
            self._layers.append((np.ascontiguousarray(w.T), b))
        self._mean = np.asarray(meta.mean, dtype=np.float32)
        self._inv_std = (1.0 / np.asarray(meta.std, dtype=np.float32)).astype(np.float32)
        self._inv_t = float(1.0 / meta.temperature)

    @classmethod
    def from_torch(cls, model, meta: ClassifierMeta) -> "GlassClassifier":
        """From a torch module made by :func:`build_mlp` (e.g. just trained)."""
        import torch.nn as nn

        lin = [m for m in model if isinstance(m, nn.Linear)]
        return cls([(m.weight.detach().cpu().numpy(), m.bias.detach().cpu().numpy()) for m in lin], meta)

    @property
    def layers(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Copies of the weights (out, in) and biases (out,) per linear layer."""
        return [(wt.T.copy(), b.copy()) for wt, b in self._layers]

    @property
    def model(self):
        """A torch module (:func:`build_mlp`) holding these weights, in eval mode (imports torch)."""
        import torch

        mlp = build_mlp(self.meta.hidden, len(self.meta.feature_names))
        lin = [m for m in mlp if isinstance(m, torch.nn.Linear)]
        with torch.no_grad():
            for m, (w, b) in zip(lin, self.layers):
                m.weight.copy_(torch.from_numpy(w))
                m.bias.copy_(torch.from_numpy(b))
        return mlp.eval()

    @classmethod
    def load(cls, stem: str | Path) -> "GlassClassifier":
        """Load ``stem.json`` (metadata) and the weights: ``stem.npz`` (numpy, no torch needed) if present,
        else ``stem.pt`` (torch state dict)."""
        stem = Path(stem)
        npz, pt, js = stem.with_suffix(".npz"), stem.with_suffix(".pt"), stem.with_suffix(".json")
        if not js.is_file() or not (npz.is_file() or pt.is_file()):
            missing = js if not js.is_file() else pt
            raise ClassifierError(f"classifier file {missing} not found; run `glassmap glass train` to create it")
        meta = ClassifierMeta.from_json(js.read_text())
        from .glass_features import FEATURES

        if tuple(FEATURES.get(meta.model, ())) != tuple(meta.feature_names):
            raise ClassifierError(f"{js}: model {meta.model!r} with features {list(meta.feature_names)} is not "
                                  f"a known model of this version (models: {', '.join(FEATURES)})")
        sizes = [len(meta.feature_names), *meta.hidden, 2]
        if npz.is_file():
            with np.load(npz) as z:
                layers = [(z[f"w{j}"], z[f"b{j}"]) for j in range(len(sizes) - 1) if f"w{j}" in z and f"b{j}" in z]
            src = npz
        else:
            import torch

            try:
                state = torch.load(pt, map_location="cpu", weights_only=True)
                layers = [(state[f"{2 * j}.weight"].numpy(), state[f"{2 * j}.bias"].numpy())
                          for j in range(len(sizes) - 1)]
            except (RuntimeError, KeyError) as e:
                raise ClassifierError(f"weights {pt} do not match the architecture in {js}: {e}") from e
            src = pt
        want = [((o, i), (o,)) for i, o in zip(sizes[:-1], sizes[1:])]
        if [(w.shape, b.shape) for w, b in layers] != want:
            raise ClassifierError(f"weights {src} do not match the architecture in {js}: layers "
                                  f"{[(w.shape, b.shape) for w, b in layers]}, expected {want}")
        return cls(layers, meta)

    @classmethod
    def load_default(cls, model: str = DEFAULT_MODEL) -> "GlassClassifier":
        """The weights shipped inside the package for ``model`` (glassmap/models/glass_<model>.npz)."""
        shipped_stem(model)  # validates the name
        ref = resources.files("glassmap") / "models" / f"glass_{model}"
        return cls.load(Path(str(ref)))

    def save_weights(self, path: str | Path) -> Path:
        """Write the weights as ``.npz`` (w0, b0, w1, b1, ...: weight (out, in), bias (out,) per layer)."""
        path = Path(path)
        np.savez(path, **{f"{k}{j}": a for j, (w, b) in enumerate(self.layers) for k, a in (("w", w), ("b", b))})
        return path

    @property
    def model_name(self) -> str:
        return self.meta.model

    @property
    def uses_echoes(self) -> bool:
        """The model reads the beams' further echoes (multi-echo scans)."""
        return "echo_count" in self.meta.feature_names

    def logits(self, x: np.ndarray) -> np.ndarray:
        """Temperature-scaled logits (n, 2) float32 for raw features ``x`` (n, k) of this model."""
        return self._logits(standardise(np.ascontiguousarray(x, dtype=np.float32), self._mean, self._inv_std))

    def _logits(self, h: np.ndarray) -> np.ndarray:
        """:meth:`logits` from the standardised features ``h`` (n, k) float32."""
        for wt, b in self._layers[:-1]:
            h = h @ wt
            add_bias_relu(h, b)
        wt, b = self._layers[-1]
        h = h @ wt
        h += b
        h *= np.float32(self._inv_t)
        return h

    def predict(self, intensity: np.ndarray, distance: np.ndarray, incidence: np.ndarray) -> np.ndarray:
        """p(glass) (n,) float64 of the baseline model for beams with intensity (sensor units), distance (m),
        incidence (rad). Inputs must be finite; the caller selects the beams that have an incidence angle.
        """
        if self.meta.model != "baseline":
            raise ClassifierError(f"predict(intensity, distance, incidence) needs the baseline model; this is "
                                  f"{self.meta.model!r}: use predict_scan or predict_features")
        return self.predict_features(features(intensity, distance, incidence))

    def predict_features(self, x: np.ndarray) -> np.ndarray:
        """p(glass) (m,) float64 for raw feature rows ``x`` (m, k) of this model (glassmap.glass_features)."""
        if x.shape[0] == 0:
            return np.zeros(0)
        if not np.isfinite(x).all():
            raise ValueError(_NOT_FINITE)
        return _glass_probability(self.logits(x))

    def predict_beams(self, x: np.ndarray) -> np.ndarray:
        """p(glass) for rows of the context model's features (the baseline reads their first columns)."""
        return self.predict_features(np.ascontiguousarray(x[:, :len(self.meta.feature_names)]))

    def predict_scan(self, scan, inc, use: np.ndarray, *, angles: np.ndarray | None = None) -> np.ndarray:
        """p(glass) (m,) for the beams ``use`` (n,) bool of ``scan`` (glassmap.types.Scan), given the
        incidence result ``inc`` of its ranges (``angles``: ``scan.angles`` if the caller has them already).
        A model that reads echoes sees a single-echo scan as one whose beams all had one echo (the runtime
        falls back to the baseline model instead)."""
        a = scan.angles if angles is None else angles
        x = scan_features(self.meta.model, a, scan.ranges, scan.intensities, inc, scan.echoes, scan.echo_intensities)
        # predict_features(x[use]) without the copy of the rows
        h, finite = standardise_rows(x, use, self._mean, self._inv_std)
        if h.shape[0] == 0:
            return np.zeros(0)
        if not finite:
            raise ValueError(_NOT_FINITE)
        return _glass_probability(self._logits(h))


_NOT_FINITE = "classifier inputs must be finite (select beams with a range and an angle first)"


def _glass_probability(logits: np.ndarray) -> np.ndarray:
    """p(glass) (m,) float64 from the logits (m, 2) float32: the softmax over 2 classes, sigmoid(l1 - l0)."""
    p = np.exp(negative_logit_gaps(logits))
    p += 1.0
    return np.divide(1.0, p, out=p)
