"""The models the stages run, by family, as segment-anything separates `modeling/` from `utils/`:

    segment/  objects: segment-everything (MobileSAM's runners, the generator's grid and filters,
              the restructured fast decoder, reuse across a sequence) and the geometric segmenter
    pose/     pose: BlazePose (+ its smpl+head_30 mapping), the MeTRAbs family's crop models, and
              the placement of a metric pose in the camera frame (the head stage's fallback too)
    view/     view: the face mesh, GFIE's head and whole networks, GAFA's window network, any
              head-crop ONNX network, and their crops
    depth/    depth: sensor depth completion and metric monocular depth (ONNX, FastDepth)
    runtime/  what the families share, below them all: ONNX Runtime sessions, LiteRT interpreters,
              ONNX graph building, square and perspective crops, MediaPipe's SSD decoding

A family imports from itself, from runtime/ and from outside estimators/ (geometry, frames, errors,
...), never from another family; tests/test_imports.py checks it and that the package has no import
cycle. cli.py holds the export commands (`export-mobilesam`, `export-gfie-view`)."""
