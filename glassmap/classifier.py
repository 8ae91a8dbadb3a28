"""Per-beam glass classifier (docs/method.md section 2): f(intensity, distance, incidence) -> p(glass).

A torch MLP with 4 fully connected layers and a softmax over {not glass, glass} (class 1 = glass).
Inputs are normalised: features (log1p(intensity), distance in metres, incidence in radians) are
standardised with the training set's mean and standard deviation. A temperature (fitted on held-out data)
divides the logits before the softmax so that outputs behave as probabilities for the Bayesian update.

The trained weights ship in ``glassmap/models/glass_mlp.pt`` (state dict) with ``glass_mlp.json``
(normalisation, temperature, architecture and the training report); :meth:`GlassClassifier.load_default`
loads them from the package, without network.
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
DEFAULT_STEM = "glass_mlp"


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
    feature_names: tuple[str, str, str] = ("log1p(intensity)", "distance_m", "incidence_rad")
    report: dict = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "ClassifierMeta":
        d = json.loads(text)
        return cls(hidden=tuple(d["hidden"]), mean=list(d["mean"]), std=list(d["std"]),
                   temperature=float(d.get("temperature", 1.0)),
                   feature_names=tuple(d.get("feature_names", cls.feature_names)), report=d.get("report", {}))


def build_mlp(hidden: tuple[int, int, int] = (32, 32, 16)):
    """The network: 4 linear layers (3 -> h1 -> h2 -> h3 -> 2) with ReLU; outputs logits over
    {not glass, glass}."""
    import torch.nn as nn

    h1, h2, h3 = hidden
    return nn.Sequential(nn.Linear(3, h1), nn.ReLU(), nn.Linear(h1, h2), nn.ReLU(), nn.Linear(h2, h3), nn.ReLU(),
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
        model = build_mlp(meta.hidden)
        try:
            model.load_state_dict(torch.load(pt, map_location="cpu", weights_only=True))
        except (RuntimeError, KeyError) as e:
            raise ClassifierError(f"weights {pt} do not match the architecture in {js}: {e}") from e
        return cls(model, meta)

    @classmethod
    def load_default(cls) -> "GlassClassifier":
        """The weights shipped inside the package (glassmap/models/glass_mlp.pt)."""
        ref = resources.files("glassmap") / "models" / DEFAULT_STEM
        return cls.load(Path(str(ref)))

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
        """p(glass) (n,) float64 for beams with intensity (sensor units), distance (m), incidence (rad).

        Inputs must be finite; the caller selects the beams that have an incidence angle.
        """
        x = features(intensity, distance, incidence)
        if x.shape[0] == 0:
            return np.zeros(0)
        if not np.isfinite(x).all():
            raise ValueError("classifier inputs must be finite (select beams with a range and an angle first)")
        lg = self.logits(x).astype(np.float64)
        # softmax over 2 classes: p(glass) = sigmoid(l1 - l0)
        return 1.0 / (1.0 + np.exp(-(lg[:, 1] - lg[:, 0])))
