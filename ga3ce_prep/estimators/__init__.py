"""Estimators run through ONNX Runtime or LiteRT: MobileSAM segment-everything (mobilesam.py, amg.py,
fast_decoder.py), FastDepth monocular depth (fastdepth.py), the face-mesh head direction
(facemesh.py, on MediaPipe's detector head in ssd.py and the square crops in crops.py), and the
session/interpreter helpers shared by every estimator (onnx_runtime.py, litert.py)."""
