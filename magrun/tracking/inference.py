"""Running the keypoint UNet for tracking: its ONNX graph in ONNX Runtime, no torch.

The tracker calls the network once per camera frame on a 64 px window, one image at a time,
in the control loop. At that size torch's eager mode spends as much time dispatching the ~30
operators as computing them: the BN-fused UNet took 2.2 ms per window on one core here, and
ONNX Runtime, which runs the same graph with fused convolution + ReLU kernels and no
per-operator Python, 1.2 ms (BENCHMARKS.md, "Tracking"). Both compute the same function; their
heat maps agree to ~1e-5 (tests/test_tracking.py).

The graph lies beside its weights (``unet.npz`` → ``unet.onnx``), exported from the fused
torch model by ``magrun tracker train`` or ``magrun tracker export`` (:mod:`magrun.tracking.export`,
which checks the two agree) and stamped with the weights' digest
(:meth:`~magrun.tracking.weights.WeightsFile.digest`): running, tracking and analysing need no
torch. Weights without their graph are exported in memory where torch is installed (the
``train`` extra), and refused with a message saying how to export them where it is not.

    >>> net = graph_net(read_weights("unet.npz"))                           # doctest: +SKIP
    >>> net.run(to_array(window)).shape  # a (64, 64, 3) window             # doctest: +SKIP
    (1, 3, 64, 64)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

from magrun.tracking.heatmaps import MEAN, SCALE
from magrun.tracking.weights import WeightsFile

F32 = NDArray[np.float32]
HeatmapNet = Callable[[F32], F32]
Backend = Literal["onnx", "torch"]
#: the ONNX graph's metadata key holding the digest of the weights it was exported from
DIGEST_KEY = "magrun_weights_sha256"
#: the largest graph file read (the shipped one is 0.5 MB): a bound on what a hostile file
#: can make magrun load
MAX_GRAPH_BYTES = 256 * 1024 * 1024
#: what to install for torch (training, exporting, the torch backend)
TRAIN_EXTRA = "pip install -c constraints.txt -e '.[train]'"


def check_backend(backend: str) -> None:
    """``ValueError`` for a backend that is not one of :data:`Backend`'s."""
    if backend not in get_args(Backend):
        raise ValueError(f"unknown backend {backend!r}; one of {', '.join(get_args(Backend))}")


_threads: int | None = None


@contextmanager
def inference_threads(n: int) -> Iterator[None]:
    """Networks made inside this block run on ``n`` intra-op threads (the runner: one per
    trial, so results do not depend on the thread count); outside it, ONNX Runtime's
    default (one per physical core)."""
    global _threads
    before, _threads = _threads, n
    try:
        yield
    finally:
        _threads = before


@dataclass(frozen=True)
class UNetNet:
    """A runnable heat-map network: ``run`` maps float32 (B, 3, H, W) → (B, K, H, W), with H
    and W multiples of ``stride``."""

    run: HeatmapNet
    stride: int
    backend: Backend


class MissingGraph(ValueError):
    """Weights with no ONNX graph of their own beside them, and no torch to export one."""


def to_array(images: NDArray[np.uint8]) -> F32:
    """uint8 RGB images (B, H, W, 3) or one (H, W, 3) → normalised float32 (B, 3, H, W)."""
    a = images[None] if images.ndim == 3 else images
    out: F32 = np.ascontiguousarray(a.transpose(0, 3, 1, 2), dtype=np.float32)
    out -= MEAN
    out *= SCALE
    return out


def onnx_net(graph: bytes | Path) -> tuple[HeatmapNet, dict[str, str]]:
    """An ONNX Runtime session of ``graph`` (bytes, or a file) as a function, and the graph's
    metadata. Raises ``ValueError`` for a file ONNX Runtime cannot load."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = max(_threads, 1) if _threads is not None else 0
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    model = str(graph) if isinstance(graph, Path) else graph
    try:
        session = ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # ONNX Runtime's own exception types, one per kind of fault
        raise ValueError(f"not a readable ONNX graph: {exc}") from exc
    inputs = [i.name for i in session.get_inputs()]
    if len(inputs) != 1:
        raise ValueError(f"the graph takes {len(inputs)} inputs, not one image batch")

    def run(x: F32) -> F32:
        out: F32 = session.run(None, {inputs[0]: x})[0]
        return out

    return run, dict(session.get_modelmeta().custom_metadata_map)


def graph_net(weights: WeightsFile) -> UNetNet:
    """The network of ``weights``: their ONNX graph beside them, checked to be theirs (its
    digest), in ONNX Runtime.

    Raises :class:`MissingGraph` where no graph of theirs lies beside them
    (:func:`magrun.tracking.tracker.load_net` then exports one in memory where torch is
    installed), ``ValueError`` for a graph that cannot be read."""
    path = weights.graph_path
    if not path.is_file():
        raise MissingGraph(f"{weights.path}: it has no ONNX graph beside it ({path.name})")
    size = path.stat().st_size
    if size > MAX_GRAPH_BYTES:
        raise ValueError(f"{path}: {size:,} bytes, more than the graph limit")
    try:
        run, meta = onnx_net(path)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    if meta.get(DIGEST_KEY) != weights.digest():
        raise MissingGraph(f"{weights.path}: {path.name} beside it was exported from other weights")
    return UNetNet(run, weights.stride, "onnx")
