"""GAFA raw data (kyotovision-public/dynamic-3d-gaze-from-afar): research/gafa.md §1-§2.

    raw_data/<scene>/<session>/<camera>/<frame:06d>.jpg
    raw_data/<scene>/<session>/<camera>.pkl   keypoints2d (N,25,3) BODY_25 px, gaze/head/chest
                                              direction (+ position), R_cam2w, t_cam2w
    raw_data/intrinsics.npz                   cam_mat (3,3), dist_coeffs (1,12)

The split is by session and fixed (eval.py / train.py). GAFA's own validation set is the shuffled
tail of train (unseeded); ours is deterministic: the two sessions in VAL_SESSIONS.
"""
from __future__ import annotations

SCENES: tuple[str, ...] = ("library", "lab", "kitchen", "living_room", "courtyard")
TEST_SESSIONS: tuple[str, ...] = (
    "library/1029_2", "lab/1013_2", "kitchen/1022_2", "living_room/006", "courtyard/002", "courtyard/003",
)
TRAIN_SESSIONS: tuple[str, ...] = (
    "library/1026_3", "library/1028_2", "library/1028_5", "lab/1013_1", "lab/1014_1", "kitchen/1022_4",
    "kitchen/1015_4", "living_room/004", "living_room/005", "courtyard/004", "courtyard/005",
)
VAL_SESSIONS: tuple[str, ...] = ("kitchen/1015_4", "courtyard/005")  # our choice, taken from train
# The 17 sessions in an order whose every prefix of 3+ covers train, val and test (for small
# synthetic datasets).
SESSION_ORDER: tuple[str, ...] = (
    "library/1026_3", "library/1029_2", "kitchen/1015_4", "lab/1013_1", "lab/1013_2", "kitchen/1022_4",
    "kitchen/1022_2", "living_room/004", "living_room/006", "courtyard/004", "courtyard/002",
    "courtyard/005", "library/1028_2", "courtyard/003", "library/1028_5", "lab/1014_1", "living_room/005",
)
WINDOW = 7  # GAFA's temporal window (frames)


def session_split(session: str) -> str:
    """"train", "val" or "test" for a "<scene>/<session>" name; KeyError for an unknown session."""
    if session in TEST_SESSIONS:
        return "test"
    if session in VAL_SESSIONS:
        return "val"
    if session in TRAIN_SESSIONS:
        return "train"
    raise KeyError(session)


def frame_id(session: str, camera: str, frame: int) -> str:
    """Stable frame id, e.g. "library/1029_2/Camera1_0/000123"."""
    return f"{session}/{camera}/{int(frame):06d}"
