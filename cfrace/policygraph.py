"""The ONNX graph of a policy, written by hand with ``onnx.helper`` (opset 17, no torch):

    obs [batch, D] float32
      -> (obs - mean) / std, clipped to +-NORM_CLIP          (the training normaliser, folded in)
      -> Gemm -> ELU -> ... -> Gemm                          (the actor's mean network)
      -> clip(-1, 1)
    action [batch, ACTION_DIM] float32

with the metadata of the policy contract (cfrace.contract) as metadata_props. Used by cfrace.export
(trained actors) and cfrace.rehearsal.hold_policy (hand-made benchmark policies).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from cfrace.contract import ACTION_DIM, NORM_CLIP, SCHEMA_VERSION, encode_meta

OPSET = 17

# A layer of the mean network: ("linear", W (out, in), b (out,)) or ("elu"|"relu"|"tanh", None, None)
Layer = tuple[str, "np.ndarray | None", "np.ndarray | None"]


def build_model(layers: Sequence[Layer], mean: np.ndarray | None, std: np.ndarray | None, meta: dict,
                obs_dim: int, nan_output: bool = False) -> onnx.ModelProto:
    """The ONNX model of a normalised MLP actor. ``std`` = sqrt(var + eps), precomputed in float32.
    ``nan_output`` adds NaN after the final clip (test policies only). The metadata gets this
    cfrace's schema_version unless ``meta`` names one."""
    inits: list[TensorProto] = []
    nodes: list[onnx.NodeProto] = []

    def const(name: str, value) -> str:
        inits.append(numpy_helper.from_array(np.asarray(value, dtype=np.float32), name))
        return name

    x = "obs"
    if mean is not None:
        nodes.append(helper.make_node("Sub", [x, const("norm_mean", mean)], ["obs_centred"]))
        nodes.append(helper.make_node("Div", ["obs_centred", const("norm_std", std)], ["obs_scaled"]))
        nodes.append(helper.make_node("Clip", ["obs_scaled", const("norm_lo", -NORM_CLIP),
                                               const("norm_hi", NORM_CLIP)], ["obs_norm"]))
        x = "obs_norm"
    for i, (kind, w, b) in enumerate(layers):
        y = f"h{i}"
        if kind == "linear":
            nodes.append(helper.make_node("Gemm", [x, const(f"W{i}", w), const(f"b{i}", b)], [y], transB=1))
        elif kind == "elu":
            nodes.append(helper.make_node("Elu", [x], [y], alpha=1.0))
        elif kind == "relu":
            nodes.append(helper.make_node("Relu", [x], [y]))
        elif kind == "tanh":
            nodes.append(helper.make_node("Tanh", [x], [y]))
        else:
            raise ValueError(f"unsupported layer {kind}")
        x = y
    out = "action_nan" if nan_output else "action"
    nodes.append(helper.make_node("Clip", [x, const("act_lo", -1.0), const("act_hi", 1.0)], [out]))
    if nan_output:
        nodes.append(helper.make_node("Add", [out, const("nan", np.full(ACTION_DIM, np.nan))], ["action"]))
    graph = helper.make_graph(
        nodes, "cfrace_actor",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", obs_dim])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", ACTION_DIM])],
        initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="cfrace", doc_string="cfrace racing actor: obs -> action in [-1, 1]")
    model.ir_version = 8  # readable by every onnxruntime >= 1.14
    helper.set_model_props(model, encode_meta({"schema_version": SCHEMA_VERSION, **meta}))
    onnx.checker.check_model(model, full_check=True)
    return model
