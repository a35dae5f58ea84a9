"""The crash campaign, short: kill -9 `ga3ce-prep run` at random moments across stages, cache
writes and finalize, resuming each time; the final store equals an uninterrupted run's bit for bit
(`make bench-crash` runs the long one)."""
from ga3ce_prep.testing.crash import crash_campaign
from ga3ce_prep.testing.worlds import SMALL

KILLS = 8


def test_kill_9_at_random_moments_then_resume_gives_the_same_store(synth_world, tmp_path):
    report = crash_campaign(synth_world, tmp_path, kills=KILLS, sets=[*SMALL, "run.shard_size=3"], seed=15)
    assert report.kills == KILLS
    assert report.cycles >= 1
    assert len(report.by_moment) >= 3  # timers and failpoints of several kinds
