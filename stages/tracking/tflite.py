"""Loading TFLite models through OpenCV's DNN module, asking for several outputs in one forward pass."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msflow import UserError


class TfliteNet:
    """A TFLite model run by ``cv2.dnn`` returning the named outputs of one forward pass.

    OpenCV 5's new engine lists only one unconnected output for these models and refuses to return several
    at once, so asking for each name would run the network once per output; the classic engine returns all
    of them from one pass (same numbers). When it is unavailable, fall back to one pass per output.
    """

    def __init__(self, path: str | Path, outputs: tuple[str, ...]):
        import cv2

        path = Path(path)
        if not path.is_file():
            raise UserError("model file not found", file=str(path))
        self.outputs = tuple(outputs)
        self.path = path
        self.single_pass = True
        try:
            self.net = cv2.dnn.readNetFromTFLite(str(path), engine=cv2.dnn.ENGINE_CLASSIC)
        except (cv2.error, AttributeError, TypeError):
            self.net = None
        if self.net is None or self.net.empty():
            try:
                self.net = cv2.dnn.readNetFromTFLite(str(path))
            except cv2.error as exc:
                raise UserError(f"cannot load TFLite model ({exc})", file=str(path)) from None
            self.single_pass = False

    def forward(self, blob: np.ndarray) -> list[np.ndarray]:
        import cv2

        self.net.setInput(blob)
        if self.single_pass:
            try:
                return list(self.net.forward(list(self.outputs)))
            except cv2.error:
                self.single_pass = False
        result = []
        for name in self.outputs:
            self.net.setInput(blob)
            result.append(self.net.forward(name))
        return result
