"""The small synthetic worlds the tests share, and the pipeline overrides that fit them."""
# 160x120 frames keep the tests fast: 3 scenes x 4 frames.
SMALL_WORLD = dict(scenes=3, frames_per_scene=4, seed=5, width=160)
# 640x480 (the benchmark's resolution), where heads span 15-40 px (at 160x120 a head is 5-8 px
# and its depth window 3x3): 4 scenes x 2 frames.
WORLD_640 = dict(scenes=4, frames_per_scene=2, seed=6, width=640)
# GAFA format for the temporal windows: 2 scenes x 10 frames (6 camera sequences of raw frames
# 0-9; tests/conftest.py removes GAFA_GAP (camera sequence, raw frame) to make a gap).
GAFA_WORLD = dict(scenes=2, frames_per_scene=10, seed=5, width=160)
GAFA_GAP = ("library/1029_2/Camera2_0", 1)
# the bundled pipelines with the geometric segmenter's grid scaled to 160x120 frames
SMALL = ["stages.objects.params.stride=1"]

