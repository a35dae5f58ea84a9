"""View-prior estimators for the view stage (docs/models/view.md): MediaPipe's face mesh
(facemesh.py), GFIE's head-image network and its crop (gfie_head.py, head_crop.py, on resnet.py),
GFIE's whole gaze-following network (gfie_net.py, for train/gfm.py), any head-crop network exported
to ONNX (head_onnx.py), and GAFA's 7-frame head-and-body network (gafa.py)."""
