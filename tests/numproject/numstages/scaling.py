"""Scaling: the only stage module importing numstages.helpers."""

from msflow import Input, Output, Result, Stage
from numstages.basic import log_execution
from numstages.helpers import double


class Scale(Stage):
    class Params(Stage.Params):
        factor: float = 2.0

    inputs = {"x": Input.array("f")}
    outputs = {"y": Output.array("f", ndim=1)}

    def run(self, params, inputs):
        log_execution(self.name)
        return Result({"y": double(inputs["x"]) * params.factor / 2})
