"""The camera mission's components (``configs/camera.yaml``): a camera on a
device node and an image controller on the control node, joined by a bulk
channel (:mod:`zplatform.runtime.bulk`) outside the 2 ms sync.

* :class:`SimCamera` (DN sensor): fills its bulk channel's array with a test
  pattern (a fixed gradient shifted by the frame number) every run and counts
  frames in a Data Vector element. The runtime publishes the array.
* :class:`ImageStats` (CN controller): the mean brightness of the newest
  frame, from a strided sample (a 4 MB mean costs about 2 ms here; the loop
  has 10).
"""

from __future__ import annotations

from typing import Any

import msgspec
import numpy as np

from zplatform.control.controllers import Controller
from zplatform.control.devices import Sensor
from zplatform.core.datavector import DataVector
from zplatform.errors import ControlError

__all__ = ["ImageStats", "SimCamera"]


def _channel(component: Any, name: str) -> Any:
    try:
        return component.bulk[name]
    except KeyError:
        raise ControlError(
            f"{component.name}: no bulk channel {name!r} on node {component.node} "
            f"(channels here: {sorted(component.bulk)})"
        ) from None


class SimCamera(Sensor):
    """A simulated camera writing one frame per run into a bulk channel."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        channel: str
        frames: str  # an integer element: frames taken

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._frames = self.output(self.config.frames, "frames", kinds=("int",))
        self._n = 0
        self._base: Any = None

    def run(self, t_ns: int) -> None:
        frame = _channel(self, self.config.channel)
        if self._base is None:  # once: the loop itself allocates nothing
            flat = np.arange(frame.size, dtype=np.uint32) % 251
            self._base = flat.astype(frame.dtype).reshape(frame.shape)
        np.add(self._base, frame.dtype.type(self._n & 0xFF), out=frame)
        self._n += 1
        self._frames.set(self._n)


class ImageStats(Controller):
    """Mean brightness of the newest frame of a bulk channel."""

    class Config(msgspec.Struct, forbid_unknown_fields=True):
        channel: str
        mean: str  # a float element
        stride: int = 4096

    config: Config

    def bind(self, dv: DataVector) -> None:
        self._mean = self.output(self.config.mean, "mean", kinds=("float",))

    def run_enabled(self, t_ns: int) -> None:
        frame = _channel(self, self.config.channel)
        self._mean.set(float(frame.reshape(-1)[:: self.config.stride].mean()))

    def run_safed(self, t_ns: int) -> None:
        pass
