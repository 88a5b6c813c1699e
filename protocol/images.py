"""Camera frames <-> NumPy images."""

from __future__ import annotations

import logging

import numpy as np

from protocol.messages import CameraFrame, Header


def frame_image(frame: CameraFrame) -> np.ndarray:
    """The frame's pixels as H x W x 3 uint8 RGB: a read-only view on the payload, no copy.

    Raises ValueError for an unknown encoding or a payload of the wrong size (bad input from the bus).
    """
    if frame.encoding != "rgb8":
        raise ValueError(f"unsupported camera encoding {frame.encoding!r} (expected rgb8)")
    expected = frame.width_px * frame.height_px * 3
    if frame.width_px <= 0 or frame.height_px <= 0 or len(frame.data) != expected:
        raise ValueError(
            f"camera frame of {frame.width_px}x{frame.height_px} rgb8 needs {expected} bytes, got {len(frame.data)}"
        )
    return np.frombuffer(frame.data, dtype=np.uint8).reshape(frame.height_px, frame.width_px, 3)


def image_frame(header: Header, image_rgb: np.ndarray) -> CameraFrame:
    """A CameraFrame holding ``image_rgb`` (H x W x 3 uint8)."""
    height, width = image_rgb.shape[:2]
    return CameraFrame(header=header, width_px=width, height_px=height, data=image_rgb.tobytes())


class FrameReader:
    """:func:`frame_image` for a service loop: a bad frame from the bus is counted, logged once, and read as None."""

    def __init__(self, log: logging.Logger):
        self._log = log
        self.bad_frames = 0

    def image(self, frame: CameraFrame) -> np.ndarray | None:
        try:
            return frame_image(frame)
        except ValueError as error:
            self.bad_frames += 1
            if self.bad_frames == 1:
                self._log.warning("dropped bad camera frame: %s (further ones are only counted)", error)
            return None
