"""Running the keypoint UNet for tracking: ONNX Runtime by default, torch as the reference.

The tracker calls the network once per camera frame on a 64 px window, one image at a time,
in the control loop. At that size torch's eager mode spends as much time dispatching the ~30
operators as computing them: the BN-fused UNet took 2.2 ms per window on one core here, and
ONNX Runtime, which runs the same graph with fused convolution + ReLU kernels and no
per-operator Python, 1.2 ms (BENCHMARKS.md, "Tracking"). Both compute the same function; their
heat maps agree to ~1e-5 (tests/test_tracking.py).

The ONNX graph is exported from the fused torch model in memory (``torch.onnx.export``, sides
and batch dynamic, so whole-frame searches run on the same graph) once per set of weights and
process; nothing is written to disk and no file is ever loaded as code.

    >>> net = heatmap_net(fuse_batch_norm(model), backend="onnx")          # doctest: +SKIP
    >>> net(to_array(window)).shape  # a (64, 64, 3) window                # doctest: +SKIP
    (1, 3, 64, 64)
"""

from __future__ import annotations

import hashlib
import io
import warnings
from collections.abc import Callable
from typing import Literal

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from magrun.tracking.unet import MEAN, SCALE

F32 = NDArray[np.float32]
HeatmapNet = Callable[[F32], F32]
Backend = Literal["onnx", "torch"]
BACKENDS: tuple[Backend, ...] = ("onnx", "torch")


def to_array(images: NDArray[np.uint8]) -> F32:
    """uint8 RGB images (B, H, W, 3) or one (H, W, 3) → normalised float32 (B, 3, H, W)."""
    a = images[None] if images.ndim == 3 else images
    out: F32 = np.ascontiguousarray(a.transpose(0, 3, 1, 2), dtype=np.float32)
    out -= MEAN
    out *= SCALE
    return out


def heatmap_net(
    model: nn.Module, backend: Backend = "onnx", threads: int | None = None
) -> HeatmapNet:
    """``model`` (in eval mode) as a function of float32 arrays (B, 3, H, W) → (B, K, H, W).

    ``threads``: intra-op threads of ONNX Runtime (default: torch's current setting, which
    the runner sets to one per trial).
    """
    if backend == "torch":
        return _torch_net(model)
    if backend == "onnx":
        return _onnx_net(model, torch.get_num_threads() if threads is None else threads)
    raise ValueError(f"unknown backend {backend!r}; one of {', '.join(BACKENDS)}")


def _torch_net(model: nn.Module) -> HeatmapNet:
    def run(x: F32) -> F32:
        with torch.inference_mode():
            t = torch.from_numpy(x).contiguous(memory_format=torch.channels_last)
            out: F32 = model(t).numpy()
        return out

    return run


_ONNX_CACHE: dict[str, bytes] = {}


def onnx_bytes(model: nn.Module) -> bytes:
    """The ONNX graph of ``model`` (opset 17, batch and sides dynamic), cached by its weights."""
    digest = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().numpy().tobytes())
    key = digest.hexdigest()
    if key not in _ONNX_CACHE:
        buf = io.BytesIO()
        axes = {0: "batch", 2: "height", 3: "width"}
        with warnings.catch_warnings():  # the TorchScript exporter announces its successor
            warnings.simplefilter("ignore")
            torch.onnx.export(
                model,
                (torch.zeros(1, 3, 64, 64),),
                buf,  # type: ignore[arg-type]  # any binary file object works
                input_names=["image"],
                output_names=["heatmaps"],
                dynamic_axes={"image": axes, "heatmaps": axes},
                opset_version=17,
                dynamo=False,
            )
        _ONNX_CACHE[key] = buf.getvalue()
    return _ONNX_CACHE[key]


def _onnx_net(model: nn.Module, threads: int) -> HeatmapNet:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = max(threads, 1)
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(onnx_bytes(model), options, providers=["CPUExecutionProvider"])

    def run(x: F32) -> F32:
        out: F32 = session.run(None, {"image": x})[0]
        return out

    return run
