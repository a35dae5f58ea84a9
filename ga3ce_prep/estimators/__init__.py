"""Estimators run through ONNX Runtime: MobileSAM segment-everything (mobilesam.py, amg.py,
fast_decoder.py) and the session/contract helpers shared by every ONNX estimator (onnx_runtime.py)."""
