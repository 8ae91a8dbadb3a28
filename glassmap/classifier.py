"""Per-beam glass classifiers (docs/method.md section 2): features of a beam -> p(glass).

A torch MLP with 4 fully connected layers and a softmax over {not glass, glass} (class 1 = glass). Two
named models differ only in their inputs (``glassmap.glass_features``): ``baseline`` is the paper's
f(intensity, distance, incidence); ``context`` adds the beam's echoes, its neighbours along the scan and
its place on its line segment. Inputs are standardised with the training set's mean and standard
deviation. A temperature (fitted on validation worlds) divides the logits before the softmax so that
outputs behave as probabilities for the Bayesian update.

The trained weights ship in ``glassmap/models/glass_<model>.pt`` (state dict) with ``glass_<model>.json``
(model name, normalisation, temperature, architecture and the training report);
:meth:`GlassClassifier.load_default` loads them from the package, without network.
"""

from __future__ import annotations

import json
import threading
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

MODEL_DIR = Path(__file__).resolve().parent / "models"
_THREADS_SET = threading.local()  # per thread: torch already set to one intra-op thread
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
    """Trained glass classifier. ``predict`` runs one batched torch call per scan."""

    def __init__(self, model, meta: ClassifierMeta) -> None:
        import torch

        self.torch = torch
        self.model = model.eval()
        with torch.no_grad():
            # weight decay leaves some dead weights at denormal magnitudes (~1e-40), which makes a
            # 1081 x 32 x 32 matmul 10-20x slower on x86; they contribute nothing, so zero them
            for prm in self.model.parameters():
                prm[prm.abs() < 1e-30] = 0.0
        self.meta = meta
        self._mean = np.asarray(meta.mean, dtype=np.float32)
        self._inv_std = (1.0 / np.asarray(meta.std, dtype=np.float32)).astype(np.float32)
        self._inv_t = float(1.0 / meta.temperature)

    @classmethod
    def load(cls, stem: str | Path) -> "GlassClassifier":
        """Load ``stem.pt`` (state dict) and ``stem.json`` (metadata)."""
        import torch

        stem = Path(stem)
        pt, js = stem.with_suffix(".pt"), stem.with_suffix(".json")
        for p in (pt, js):
            if not p.is_file():
                raise ClassifierError(f"classifier file {p} not found; run `glassmap glass train` to create it")
        meta = ClassifierMeta.from_json(js.read_text())
        from .glass_features import FEATURES

        if tuple(FEATURES.get(meta.model, ())) != tuple(meta.feature_names):
            raise ClassifierError(f"{js}: model {meta.model!r} with features {list(meta.feature_names)} is not "
                                  f"a known model of this version (models: {', '.join(FEATURES)})")
        model = build_mlp(meta.hidden, len(meta.feature_names))
        try:
            model.load_state_dict(torch.load(pt, map_location="cpu", weights_only=True))
        except (RuntimeError, KeyError) as e:
            raise ClassifierError(f"weights {pt} do not match the architecture in {js}: {e}") from e
        return cls(model, meta)

    @classmethod
    def load_default(cls, model: str = DEFAULT_MODEL) -> "GlassClassifier":
        """The weights shipped inside the package for ``model`` (glassmap/models/glass_<model>.pt)."""
        shipped_stem(model)  # validates the name
        ref = resources.files("glassmap") / "models" / f"glass_{model}"
        return cls.load(Path(str(ref)))

    @property
    def model_name(self) -> str:
        return self.meta.model

    @property
    def uses_echoes(self) -> bool:
        """The model reads the beams' further echoes (multi-echo scans)."""
        return "echo_count" in self.meta.feature_names

    def _one_thread_here(self) -> None:
        """Run torch on one intra-op thread in the calling thread. ``torch.set_num_threads`` reaches only the
        OpenMP team of the thread that calls it: from any other thread (the runtime's processing executor)
        a 1081-beam batch would run on a team of one thread per core, which is ~80x slower for a matrix
        this small (8.6 ms instead of 0.1 ms per scan on the 2-core development machine, worse when the
        other core is busy). Done once per thread."""
        if not getattr(_THREADS_SET, "done", False):
            self.torch.set_num_threads(1)
            _THREADS_SET.done = True

    def logits(self, x: np.ndarray) -> np.ndarray:
        """Temperature-scaled logits (n, 2) for raw features ``x`` (n, 3) from :func:`features`."""
        torch = self.torch
        self._one_thread_here()
        z = (x - self._mean) * self._inv_std
        with torch.inference_mode():
            out = self.model(torch.from_numpy(np.ascontiguousarray(z, dtype=np.float32)))
        return out.numpy() * self._inv_t

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
            raise ValueError("classifier inputs must be finite (select beams with a range and an angle first)")
        lg = self.logits(x).astype(np.float64)
        # softmax over 2 classes: p(glass) = sigmoid(l1 - l0)
        return 1.0 / (1.0 + np.exp(-(lg[:, 1] - lg[:, 0])))

    def predict_beams(self, x: np.ndarray) -> np.ndarray:
        """p(glass) for rows of the context model's features (the baseline reads their first columns)."""
        return self.predict_features(np.ascontiguousarray(x[:, :len(self.meta.feature_names)]))

    def predict_scan(self, scan, inc, use: np.ndarray) -> np.ndarray:
        """p(glass) (m,) for the beams ``use`` (n,) bool of ``scan`` (glassmap.types.Scan), given the
        incidence result ``inc`` of its ranges. A model that reads echoes sees a single-echo scan as one
        whose beams all had one echo (the runtime falls back to the baseline model instead)."""
        from .glass_features import scan_features

        x = scan_features(self.meta.model, scan.angles, scan.ranges, scan.intensities, inc, scan.echoes,
                          scan.echo_intensities)
        return self.predict_features(x[use])
