"""The UNet's ONNX graph, exported from torch and checked against it (needs the ``train`` extra).

Tracking runs the network's ONNX graph in ONNX Runtime (:mod:`magrun.tracking.inference`).
The graph is exported here from the trained weights with every BatchNorm folded into its
convolution (:func:`fuse_batch_norm`), opset 17, batch and sides dynamic (whole-frame searches
run on the same graph), and stamped with the digest of the weights it came from. Before a
graph is written, it and torch's model are run on the same fixed windows and must agree
(:data:`AGREEMENT`): ``magrun tracker train`` and ``magrun tracker export`` both do.

    $ magrun tracker export magrun/tracking/data/unet.npz --overwrite   # the shipped graph
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from magrun import __version__
from magrun.atomic import write_bytes
from magrun.tracking.inference import (
    DIGEST_KEY,
    F32,
    Backend,
    HeatmapNet,
    UNetNet,
    check_backend,
    onnx_net,
    to_array,
)
from magrun.tracking.unet import KeypointUNet, model_of
from magrun.tracking.weights import WeightsFile, read_weights

#: the largest difference allowed between the graph's heat maps and torch's (peaks are 1)
AGREEMENT = 1e-4


def fuse_batch_norm(model: KeypointUNet) -> nn.Module:
    """An inference copy of ``model`` with every BatchNorm folded into its convolution."""
    fused = KeypointUNet(model.widths, model.head.out_channels)
    fused.load_state_dict(model.state_dict())
    fused.eval()
    for block in (*fused.encoders, *fused.decoders):
        assert isinstance(block, nn.Sequential)
        layers = list(block)
        out: list[nn.Module] = []
        i = 0
        while i < len(layers):
            layer = layers[i]
            nxt = layers[i + 1] if i + 1 < len(layers) else None
            if isinstance(layer, nn.Conv2d) and isinstance(nxt, nn.BatchNorm2d):
                out.append(nn.utils.fusion.fuse_conv_bn_eval(layer, nxt))
                i += 2
            else:
                out.append(layer)
                i += 1
        block._modules.clear()
        for k, m in enumerate(out):
            block.add_module(str(k), m)
    return fused.to(memory_format=torch.channels_last)


def torch_net(model: nn.Module) -> HeatmapNet:
    """``model`` (eval mode) as a function of float32 arrays (B, 3, H, W) → (B, K, H, W)."""

    def run(x: F32) -> F32:
        with torch.inference_mode():
            t = torch.from_numpy(x).contiguous(memory_format=torch.channels_last)
            out: F32 = model(t).numpy()
        return out

    return run


def onnx_bytes(model: nn.Module, digest: str | None = None) -> bytes:
    """The ONNX graph of ``model`` (opset 17, batch and sides dynamic); with ``digest``, its
    metadata names the weights' digest and the magrun version that exported it (that needs
    the ``onnx`` package, part of the ``train`` extra)."""
    buf = io.BytesIO()
    axes = {0: "batch", 2: "height", 3: "width"}
    with warnings.catch_warnings():  # the TorchScript exporter announces its successor
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            (torch.zeros(1, 3, 64, 64),),
            buf,  # any binary file object works
            input_names=["image"],
            output_names=["heatmaps"],
            dynamic_axes={"image": axes, "heatmaps": axes},
            opset_version=17,
            dynamo=False,
        )
    if digest is None:
        return buf.getvalue()
    import onnx

    graph = onnx.load_from_string(buf.getvalue())
    onnx.helper.set_model_props(graph, {DIGEST_KEY: digest, "magrun": __version__})
    return bytes(graph.SerializeToString())


def check_windows(seed: int = 0) -> F32:
    """The fixed inputs a graph is checked on: four random 64 px windows (the tracking
    window's size), normalised (:func:`~magrun.tracking.inference.to_array`)."""
    rng = np.random.default_rng(seed)
    return to_array(rng.integers(0, 256, (4, 64, 64, 3), dtype=np.uint8))


def disagreement(graph: HeatmapNet, model: nn.Module) -> float:
    """The largest difference between ``graph``'s heat maps and ``model``'s (torch) on
    :func:`check_windows` and on a random 96×128 frame (a whole-frame search's shape)."""
    reference = torch_net(model)
    rng = np.random.default_rng(1)
    frame = to_array(rng.integers(0, 256, (1, 96, 128, 3), dtype=np.uint8))
    return max(float(np.max(np.abs(graph(x) - reference(x)))) for x in (check_windows(), frame))


def model_net(model: KeypointUNet, backend: Backend = "onnx") -> UNetNet:
    """A torch ``model`` as a runnable network: fused, run by torch or (``"onnx"``) by its
    graph exported in memory (unstamped: it is never written)."""
    check_backend(backend)
    fused = fuse_batch_norm(model)
    if backend == "torch":
        return UNetNet(torch_net(fused), model.stride, "torch")
    run, _ = onnx_net(onnx_bytes(fused))
    return UNetNet(run, model.stride, "onnx")


def weights_net(weights: WeightsFile, backend: Backend = "onnx") -> UNetNet:
    """The network of ``weights`` built in torch: torch itself, or its ONNX graph exported
    in memory (:func:`magrun.tracking.tracker.load_net` comes here when no graph of theirs
    lies beside them)."""
    return model_net(model_of(weights), backend)


def export_graph(weights_path: str | Path, out: str | Path | None = None) -> tuple[Path, float]:
    """Write the ONNX graph of the weights at ``weights_path`` (default: beside them, suffix
    ``.onnx``), after checking it against torch; returns the path and the largest
    difference of their heat maps. Raises ``ValueError`` where they differ by more than
    :data:`AGREEMENT` (nothing is written)."""
    weights = read_weights(weights_path)
    fused = fuse_batch_norm(model_of(weights))
    graph = onnx_bytes(fused, weights.digest())
    run, _ = onnx_net(graph)
    worst = disagreement(run, fused)
    if not worst <= AGREEMENT:
        raise ValueError(
            f"the exported graph's heat maps differ from torch's by {worst:.2e} "
            f"(at most {AGREEMENT:.0e} allowed); nothing written"
        )
    target = Path(out) if out is not None else weights.graph_path
    write_bytes(target, graph)
    return target, worst
