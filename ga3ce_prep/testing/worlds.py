"""The small synthetic worlds the tests share, and the pipeline overrides that fit them."""
# 160x120 frames keep the tests fast: 3 scenes x 4 frames.
SMALL_WORLD = dict(scenes=3, frames_per_scene=4, seed=5, width=160)
# 640x480 (the benchmark's resolution), where heads span 15-40 px (at 160x120 a head is 5-8 px
# and its depth window 3x3): 4 scenes x 2 frames.
WORLD_640 = dict(scenes=4, frames_per_scene=2, seed=6, width=640)
# the bundled pipelines with the geometric segmenter's grid scaled to 160x120 frames
SMALL = ["stages.objects.params.stride=1"]

