"""A small builder of ONNX graphs from numpy-like calls, for the graphs this package writes itself
(the restructured MobileSAM decoder, test models). Every call adds one node and returns the name of
its output; constants become initializers.
"""
from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17


class GraphBuilder:
    """Accumulates nodes, initializers, inputs and outputs; `model()` returns the ModelProto (ONNX Runtime
    validates it when a session loads it)."""

    def __init__(self, name: str):
        self.name = name
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.inputs: list[onnx.ValueInfoProto] = []
        self.outputs: list[onnx.ValueInfoProto] = []
        self._renamed: dict[str, str] = {}   # values exposed as graph outputs under another name
        self._n = 0

    def _fresh(self, stem: str) -> str:
        self._n += 1
        return f"{stem}_{self._n}"

    def const(self, value, name: str | None = None, dtype=np.float32) -> str:
        """An initializer holding `value` (cast to dtype); returns its name."""
        arr = np.asarray(value, dtype=dtype)
        name = name or self._fresh("c")
        self.initializers.append(numpy_helper.from_array(np.ascontiguousarray(arr), name))
        return name

    def input(self, name: str, shape: list, elem_type: int = TensorProto.FLOAT) -> str:
        """A graph input; shape entries are ints or symbolic names."""
        self.inputs.append(helper.make_tensor_value_info(name, elem_type, shape))
        return name

    def output(self, value: str, name: str, elem_type: int = TensorProto.FLOAT) -> str:
        """Expose `value` as graph output `name`. The node that computes it writes `name` directly (an
        Identity node would copy the tensor: 3.7 MB per call for the fast decoder's A0cT); a graph
        input, an initializer or a value exposed already goes through an Identity. Later calls may
        still name `value`."""
        value = self._renamed.get(value, value)
        producer = next((n for n in reversed(self.nodes) if value in n.output), None)
        if producer is None or any(o.name == value for o in self.outputs):
            self.nodes.append(helper.make_node("Identity", [value], [name]))
        else:
            for n in self.nodes:
                for i, x in enumerate(n.input):
                    if x == value:
                        n.input[i] = name
            producer.output[list(producer.output).index(value)] = name
            self._renamed[value] = name
        self.outputs.append(helper.make_tensor_value_info(name, elem_type, None))
        return name

    def op(self, op_type: str, *inputs: str, **attrs) -> str:
        out = self._fresh(op_type)
        names = [self._renamed.get(x, x) for x in inputs]
        self.nodes.append(helper.make_node(op_type, names, [out], name=out, **attrs))
        return out

    # numpy-like helpers ---------------------------------------------------------------------
    def mm(self, a: str, b: str) -> str:
        return self.op("MatMul", a, b)

    def add(self, a: str, b: str) -> str:
        return self.op("Add", a, b)

    def sub(self, a: str, b: str) -> str:
        return self.op("Sub", a, b)

    def mul(self, a: str, b: str) -> str:
        return self.op("Mul", a, b)

    def div(self, a: str, b: str) -> str:
        return self.op("Div", a, b)

    def reshape(self, x: str, shape: list[int] | str) -> str:
        """Reshape to `shape` (0 copies the input's dim, -1 is inferred), a list or an int64 tensor name."""
        return self.op("Reshape", x, shape if isinstance(shape, str) else self.const(shape, dtype=np.int64))

    def transpose(self, x: str, perm: list[int]) -> str:
        return self.op("Transpose", x, perm=perm)

    def softmax(self, x: str, axis: int = -1) -> str:
        return self.op("Softmax", x, axis=axis)

    def reduce_sum(self, x: str, axes: list[int], keepdims: bool = True) -> str:
        return self.op("ReduceSum", x, self.const(axes, dtype=np.int64), keepdims=int(keepdims))

    def slice(self, x: str, starts: list[int], ends: list[int], axes: list[int]) -> str:
        return self.op("Slice", x, self.const(starts, dtype=np.int64), self.const(ends, dtype=np.int64),
                       self.const(axes, dtype=np.int64))

    def concat(self, xs: list[str], axis: int) -> str:
        return self.op("Concat", *xs, axis=axis)

    def relu(self, x: str) -> str:
        return self.op("Relu", x)

    def gelu(self, x: str) -> str:
        """Exact GELU, x * 0.5 * (1 + erf(x / sqrt 2)), the way torch's nn.GELU() exports."""
        e = self.op("Erf", self.div(x, self.const(np.sqrt(2.0))))
        return self.mul(self.mul(x, self.add(e, self.const(1.0))), self.const(0.5))

    def layer_norm(self, x: str, weight, bias, eps: float, axis: int = -1) -> str:
        return self.op("LayerNormalization", x, self.const(weight), self.const(bias), axis=axis, epsilon=float(eps))

    def linear(self, x: str, w_in_out: np.ndarray, b: np.ndarray | None = None) -> str:
        """x @ W (+ b), W stored (in, out)."""
        y = self.mm(x, self.const(w_in_out))
        return y if b is None else self.add(y, self.const(b))

    def model(self) -> onnx.ModelProto:
        graph = helper.make_graph(self.nodes, self.name, self.inputs, self.outputs, self.initializers)
        m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="ga3ce-prep")
        m.ir_version = 8
        return m
