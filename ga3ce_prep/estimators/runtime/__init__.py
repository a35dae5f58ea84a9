"""What the estimator families share, below them all: ONNX Runtime sessions and model contracts
(onnx_runtime.py), LiteRT interpreters (litert.py), building ONNX graphs (onnx_graph.py), square and
perspective crops onto a model's input (crops.py), and MediaPipe's single-shot detector heads
(ssd.py)."""
