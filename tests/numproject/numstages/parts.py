"""A stage built from parts (Stage.part): each take's values are computed and stored on their own, so a run with
one more take computes only that take's part. Each part computed logs ``part <file name>`` to NUMSTAGES_LOG, and
holds there with NUMSTAGES_HOLD (numstages.basic.hold_if_asked)."""

from functools import partial

import numpy as np

from msflow import Input, Output, Result, Stage, iter_blocks
from numstages.basic import hold_if_asked, log_execution


def take_values(path, scale, offset, sink):
    """One take's part: the numbers in its file, scaled and offset."""
    log_execution(f"part {path.name}")
    hold_if_asked(f"part {path.name}")
    values = sink("values", dtype=np.float64)
    values.append(np.loadtxt(path, ndmin=1) * scale + offset)
    return Result({"values": values}, meta={"rows": len(values)})


class PerTake(Stage):
    """Every take's values end to end, and the index of the take each row came from."""

    class Params(Stage.Params):
        scale: float = 1.0

    inputs = {"takes": Input.files(), "offset": Input.files(optional=True)}
    outputs = {"values": Output.array("f", shape=("rows",)), "take": Output.array("i", shape=("rows",))}

    def run(self, params, inputs):
        log_execution(self.name)
        offset = float(np.loadtxt(next(iter(inputs["offset"].values())))) if inputs["offset"] else 0.0
        values = self.sink("values", dtype=np.float64)
        takes = []
        for index, (label, path) in enumerate(inputs["takes"].items()):
            make = partial(take_values, path, params.scale, offset)
            part = self.part(label, make, labelled=("takes",), whole=("offset",))
            for block in iter_blocks(part.arrays["values"]):
                values.append(block)
            takes.append(np.full(part.meta["rows"], index, dtype=np.int64))
        return Result({"values": values, "take": np.concatenate(takes)})
