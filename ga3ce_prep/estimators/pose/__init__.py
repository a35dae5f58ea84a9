"""3D pose estimators for the pose stage (docs/models/pose.md): BlazePose GHUM through LiteRT
(blazepose.py, its smpl+head_30 mapping in blazepose_smpl.py), the MeTRAbs family's crop models
(crop.py, run by stages/pose_crop.py; writing such a model: crop_export.py), and placing a
root-relative metric pose in the camera frame (placement.py, also the head stage's fallback)."""
