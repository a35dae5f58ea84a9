"""ga3ce-prep: offline 3D-context preprocessing and a GA3CE trainer for 3D gaze estimation.

Conventions everywhere: metres; camera frame x right, y down, z forward (OpenCV); pixel (u, v)
with u along x; angles in radians inside, degrees only at the edges (reports, CLI).
"""
__version__ = "0.1.0"
