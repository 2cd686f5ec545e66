"""The normalised frame: the cloud centred on its bounding box, largest extent 1."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Frame:
    """Maps input coordinates to the unit frame (``(p - center) / scale``) and back."""

    center: np.ndarray
    scale: float

    @classmethod
    def of(cls, points: np.ndarray) -> Frame:
        """The frame of a cloud: its bounding-box centre and largest extent."""
        low, high = points.min(axis=0), points.max(axis=0)
        return cls(center=(low + high) / 2, scale=float((high - low).max()))

    def to_unit(self, points: np.ndarray) -> np.ndarray:
        return (points - self.center) / self.scale

    def from_unit(self, points: np.ndarray) -> np.ndarray:
        return points * self.scale + self.center
