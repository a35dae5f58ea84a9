"""Depth estimators for the depth stage (docs/models/depth.md): classical completion of sensor
depth (completion.py) and metric monocular depth from an ONNX export (monodepth.py; FastDepth, the
registry's, in fastdepth.py)."""
