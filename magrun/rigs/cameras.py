"""Camera sources of the hardware rig: OpenCV (device, GStreamer pipeline, video file) or the
rig's own connection (``magrun rig-emulator`` serves its rendered camera there).

A source's :meth:`CameraSource.read` returns ``(t, frame)`` (its clock, s; an RGB uint8
frame) or ``None`` when the frame was dropped; the rig counts drops.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from magrun.rigs.drivers import CoilDriver

U8 = NDArray[np.uint8]


class CameraError(RuntimeError):
    """The camera source cannot be opened."""


class CameraSource(ABC):
    def open(self) -> None:  # noqa: B027 - optional hook
        """Start the stream."""

    @abstractmethod
    def read(self) -> tuple[float, U8] | None:
        """The next frame with its time, or ``None`` (dropped)."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the device."""


class OpenCVCamera(CameraSource):
    """``cv2.VideoCapture`` on ``source``: a device index ("0"), a video file, a URL, or a
    GStreamer pipeline (a string containing ``!``, opened with ``cv2.CAP_GSTREAMER``)."""

    def __init__(self, source: str) -> None:
        self.source = source
        self._cap: Any = None
        self._t0 = 0.0

    def open(self) -> None:
        src: Any = int(self.source) if self.source.isdigit() else self.source
        if isinstance(src, str) and "!" in src:
            self._cap = cv2.VideoCapture(src, cv2.CAP_GSTREAMER)
        else:
            self._cap = cv2.VideoCapture(src)
        if not self._cap.isOpened():
            raise CameraError(f"OpenCV cannot open the camera source {self.source!r}")
        self._t0 = time.perf_counter()

    def read(self) -> tuple[float, U8] | None:
        ok, bgr = self._cap.read()
        t = time.perf_counter() - self._t0
        if not ok or bgr is None:
            return None
        return t, np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class DriverCamera(CameraSource):
    """Frames fetched through the coil driver's connection (``GRAB``: the emulator)."""

    def __init__(self, driver: CoilDriver) -> None:
        self.driver = driver

    def read(self) -> tuple[float, U8] | None:
        return self.driver.grab()


def camera_source(spec: str, driver: CoilDriver) -> CameraSource:
    """``driver``: the rig's connection; anything else: OpenCV."""
    return DriverCamera(driver) if spec == "driver" else OpenCVCamera(spec)
