"""Test worlds and scripted models for the test suite and the benchmarks; never imported by the
product path.

- `worlds`: the small synthetic worlds the tests share (sizes, seeds) and the pipeline overrides
  that fit them.
- `toy_store`: a toy 3D-context world written straight into the store format, for the trainer.
- `scripted`: tiny ONNX models with MobileSAM's official interfaces whose outputs are known.
- `photos`: scikit-image's photos as frames (RGB, an assumed K) for the real-model tests.
- `amg_reference`: the automatic mask generator in the official order of operations (slow on
  purpose), what the fast generator is checked and timed against.
- `cluster`: a dask cluster from the standard CLIs and moto's S3 server, on loopback.
- `stores`: stores compared array for array and bit for bit.
- `crash`: the crash campaign (kill -9 at random moments, resume, compare bit for bit).
- `mobilesam_random`: the official MobileSAM architecture with random weights, exported to ONNX
  and verified, built once from registry packages for the MobileSAM tests and benchmarks.
"""
