"""Coil calibration files: each channel's field per ampere relative to the field model.

A real coil's field per ampere is a few percent off its model's (winding count, geometry, the
amplifier's current scale). ``magrun identify --gains FILE`` fits these gains to recordings;
a protocol's ``controller.coil_gains: FILE`` makes the controllers' field models use them
(:class:`magrun.field.model.CalibratedFieldModel`). The file::

    # comments: how and from what the gains were identified
    model: reference          # the field model the gains were fitted against (informative)
    coil_gains:               # one positive factor per channel of the coil system
      stack0_a: 1.0123
      ...

Gains are relative: ``magrun identify`` normalises them to a geometric mean of 1 and puts the
common scale into the robot's moment (its robots file), because recordings cannot tell a
stronger moment from uniformly stronger coils.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from magrun.yamlio import load_yaml_model


class CoilGainsFile(BaseModel):
    """The calibration file's schema."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    model: str | None = Field(None, description="The field model the gains were fitted against.")
    coil_gains: Annotated[dict[str, PositiveFloat], Field(min_length=1)] = Field(
        description="Each channel's field per ampere relative to the model."
    )


def load_coil_gains(path: str | Path) -> dict[str, float]:
    """A calibration file's gains by channel name (raises
    :class:`~magrun.yamlio.YamlModelError` naming the file, line and field)."""
    return dict(load_yaml_model(path, CoilGainsFile).coil_gains)


def gains_in_order(
    gains: dict[str, float], channel_names: Sequence[str], source: str
) -> NDArray[np.float64]:
    """``gains`` as an array in ``channel_names``' order; a :class:`ValueError` naming
    ``source`` when the file's channels are not exactly the coil system's."""
    missing = [c for c in channel_names if c not in gains]
    extra = [c for c in gains if c not in channel_names]
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"no gain for {', '.join(missing)}")
        if extra:
            parts.append(f"unknown channel(s) {', '.join(extra)}")
        raise ValueError(
            f"{source}: {'; '.join(parts)} (the coil system's channels: {', '.join(channel_names)})"
        )
    return np.array([gains[c] for c in channel_names], dtype=np.float64)


def gains_file_text(gains: dict[str, float], model: str, header: Sequence[str] = ()) -> str:
    """A calibration file's text: ``header`` lines as comments, then the model and gains."""
    import yaml

    lines = [f"# {h}" for h in header]
    body = {"model": model, "coil_gains": {k: float(f"{v:.6g}") for k, v in gains.items()}}
    return "".join(f"{line}\n" for line in lines) + yaml.safe_dump(body, sort_keys=False)
