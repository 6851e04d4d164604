"""What the learned global descriptors share: their weights and their vector distances.

OverlapTransformer and BEVPlace++ differ in their input image and their
network, and in nothing else a user sees: both run on deterministic random
weights unless ``weights=PATH`` names a checkpoint (read without torch by
:mod:`lidar_iris_eval.descriptors.checkpoint`), both put the weights' SHA-256
in the cache key and the run's metadata, and both compare unit vectors by the
squared L2 distance of the authors' faiss index. This base holds that part
once, so a bad checkpoint reads the same way for every learned method.

A subclass sets ``network`` (a module with ``random_weights(seed)`` and
``shapes()``, the name and shape of every tensor the forward pass reads) and
``model_name`` (how the error names the model), and its parameters carry
``weights``, ``seed`` and ``metric``.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from lidar_iris_eval.descriptors import checkpoint
from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.vector_common import gram_pairwise
from lidar_iris_eval.errors import LirisError, warn

#: ``weights`` value of the shipped deterministic random weights (not a trained model)
RANDOM_INIT = "random-init"
#: distances of unit vectors: the authors' squared L2, its root, or ``1 - cos`` (same ranking)
METRICS = ("l2sq", "l2", "cosine")


def weights_digest(weights: dict[str, np.ndarray], shapes: dict[str, tuple]) -> str:
    """SHA-256 of the weights a forward pass reads (names, shapes, float32 bytes): the
    cache token of generated weights, which have no file to hash."""
    h = hashlib.sha256()
    for name in sorted(shapes):
        arr = np.ascontiguousarray(weights[name], dtype=np.float32)
        h.update(name.encode())
        h.update(str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def resolve_shipped(name: str | Path, folder: Path | None) -> Path:
    """The file a ``weights`` value means: a bare file name shipped in ``folder`` (the
    method's own folder) wins over a file of that name in the working directory, as
    ``esm.weights`` does; anything else is a path (``~`` expanded)."""
    if folder is not None and Path(name).name == str(name) and (folder / str(name)).is_file():
        return folder / str(name)
    return Path(name).expanduser()


def check_weights(weights: dict[str, np.ndarray], shapes: dict[str, tuple]) -> list[str]:
    """Problems that stop the forward pass (missing names, wrong shapes); empty if none."""
    problems = []
    for name, shape in shapes.items():
        if name not in weights:
            problems.append(f"no tensor {name!r}")
        elif tuple(np.shape(weights[name])) != shape:
            problems.append(f"{name!r} has shape {tuple(np.shape(weights[name]))}, "
                            f"expected {shape}")
    return problems


class LearnedVectorDescriptor(Descriptor):
    """A global descriptor computed by a network whose weights the user may give."""

    network: ModuleType
    model_name: str = ""
    #: the folder whose files ``weights=NAME`` finds by bare name (the method's folder)
    shipped_dir: Path | None = None

    def __init__(self, params=None, preset: str = "custom"):
        super().__init__(params, preset)
        if self.params.metric not in METRICS:
            raise LirisError(f"{self.name} preset {preset}", f"metric must be one of "
                             f"{', '.join(METRICS)}, got {self.params.metric!r}")
        self._weights: dict | None = None
        self._digest: str | None = None

    def __getstate__(self) -> dict:
        """Picklable (worker processes) without the weights: reloaded on use."""
        state = dict(self.__dict__)
        state["_weights"] = None
        return state

    # ------------------------------------------------------------------ weights

    @property
    def trained(self) -> bool:
        """False for the shipped random weights."""
        return self.params.weights != RANDOM_INIT

    def _error(self, problem: str) -> LirisError:
        return LirisError(f"{self.name}.weights={self.params.weights}", problem)

    def weights(self) -> dict[str, np.ndarray]:
        """The network's float32 weights by name (loaded once, checked against the model)."""
        if self._weights is None:
            if not self.trained:
                warn(f"{self.name}.weights={RANDOM_INIT}",
                     "deterministic random weights, NOT a trained model (scores are not "
                     f"{self.model_name}'s); give a checkpoint with "
                     f"--param {self.name}.weights=PATH")
                w = self.network.random_weights(self.params.seed)
                self._digest = weights_digest(w, self.network.shapes())
            else:
                w, self._digest = self._read_file(
                    resolve_shipped(self.params.weights, self.shipped_dir))
            problems = check_weights(w, self.network.shapes())
            if problems:
                shown = "; ".join(problems[:3]) + (f" (+{len(problems) - 3} more)"
                                                   if len(problems) > 3 else "")
                raise self._error(f"not {self.model_article} {self.model_name} model: {shown}")
            self._weights = {k: np.ascontiguousarray(w[k], dtype=np.float32)
                             for k in self.network.shapes()}
        return self._weights

    @property
    def model_article(self) -> str:
        """"an" before a vowel sound of the model's name, else "a" (error messages)."""
        return "an" if self.model_name[:1].upper() in "AEIOU" else "a"

    def _read_file(self, path: Path) -> tuple[dict, str]:
        try:
            return checkpoint.read_weights_file(path)
        except OSError as err:
            raise self._error(f"cannot read {path} ({err.strerror or err})") from None
        except checkpoint.CheckpointError as err:
            raise self._error(f"{path}: {err}") from None

    def cache_token(self) -> str:
        """SHA-256 (16 hex) of the weights: the file's bytes, or the random arrays."""
        self.weights()
        return str(self._digest)[:16]

    def run_info(self) -> dict[str, Any]:
        return {"weights": Path(self.params.weights).name if self.trained else RANDOM_INIT,
                "weights_sha256": self.cache_token(), "weights_trained": self.trained}

    # ------------------------------------------------------------------ distances

    # All three routes are one :func:`gram_pairwise` call (a BLAS product on padded
    # blocks), so a pair's distance is the same bits whichever route computed it.

    def distance(self, query: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        d = gram_pairwise(np.asarray(query)[None, :], np.asarray(candidate)[None, :],
                          self.params.metric)
        return float(d[0, 0]), float("nan")

    def distances(self, query: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        database = np.asarray(database)
        d = gram_pairwise(np.asarray(query)[None, :], database, self.params.metric)
        return d.reshape(len(database)), np.full(len(database), np.nan)

    def pairwise(self, queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = gram_pairwise(queries, database, self.params.metric)
        return d, np.full(d.shape, np.nan)
