"""What a cluster user meets: the work directory on another filesystem than the store,
and the machine refusing a write (a full disk, a permission, a read-only filesystem, a rename
across filesystems) where `run` and `train` put their files in place. Each refusal is one line
naming the path, what the command needed there and the fix; nothing finished is lost, and the
rerun's store is a clean run's bit for bit (the checkpoint: the clean run's weights)."""
import errno
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

import pytest
import torch

from ga3ce_prep.cli import main
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.pipeline.cache import Cache
from ga3ce_prep.testing.stores import store_digests
from ga3ce_prep.testing.toy_store import ToyKnobs, write_toy_store
from ga3ce_prep.testing.worlds import SMALL

SETS = [*SMALL, "run.shard_size=3"]
OLDER = "stages.view.params.mean_error_deg=30"
ENTRIES = 24  # 4 shards x 6 stages
SAID = {errno.ENOSPC: "no space left", errno.EXDEV: "a rename across two filesystems",
        errno.EACCES: "permission denied", errno.EROFS: "read-only"}


@pytest.fixture(scope="module")
def stores(synth_world, tmp_path_factory):
    """A clean run's store and an older store (another parameter's), with their digests."""
    base = tmp_path_factory.mktemp("clean")
    run_pipeline("synthetic", synth_world, base / "clean.zarr", overrides=SETS, progress=False)
    run_pipeline("synthetic", synth_world, base / "older.zarr", overrides=[*SETS, OLDER], progress=False)
    return {k: (base / f"{k}.zarr", store_digests(base / f"{k}.zarr")) for k in ("clean", "older")}


@pytest.fixture
def ga3ce(monkeypatch, capsys):
    """`ga3ce-prep ARGS` through the entry point's error handling, in this process: (exit code,
    stderr)."""
    monkeypatch.delenv("GA3CE_DEBUG", raising=False)

    def call(*args) -> tuple[int, str]:
        monkeypatch.setattr(sys, "argv", ["ga3ce-prep", *map(str, args)])
        try:
            main()
            code = 0
        except SystemExit as e:
            code = e.code
        return code, capsys.readouterr().err

    return call


def refuse(monkeypatch, code: int, hit, after: int = 0, times: int = 1 << 30) -> None:
    """os.replace and os.rename (every file put in place: cache entries, the Zarr writer's chunks,
    the store's rename, checkpoints) raise OSError(code) for a destination `hit` accepts, `times`
    times once `after` such calls went through: ENOSPC as write(2) reports it (no path), the others
    naming both paths as rename(2) does."""
    real = {"replace": os.replace, "rename": os.rename}
    seen = [0]

    def fake(name):
        def put(src, dst, *a, **k):
            if hit(str(dst)):
                seen[0] += 1
                if after < seen[0] <= after + times:
                    if code == errno.ENOSPC:
                        raise OSError(code, os.strerror(code))
                    raise OSError(code, os.strerror(code), str(src), None, str(dst))
            return real[name](src, dst, *a, **k)
        return put

    for name in real:
        monkeypatch.setattr(os, name, fake(name))


def one_line(code: int, err: str, *fragments: str) -> str:
    """The one `error:` line (exit 2, not a bug) holding every fragment."""
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), (code, err)
    assert "a bug" not in lines[0], lines[0]
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def _run_args(data, out, work):
    return ["run", "-p", "synthetic", "-d", data, "-o", out, "--work", work, "-q",
            *[a for s in SETS for a in ("--set", s)]]


POINTS = {  # where the run puts a file in place -> (destination test, calls let through, calls refused)
    "cache entry": (lambda d: d.endswith(".npz"), 4, 1 << 30),
    "store arrays": (lambda d: "partial.zarr/" in d and "/c/" in d, 3, 1 << 30),
    "store commit": (lambda d: d.endswith("/run.zarr"), 0, 1),  # partial.zarr renamed over --out (once)
}


@pytest.mark.parametrize("code", list(SAID), ids=errno.errorcode.get)
@pytest.mark.parametrize("point", list(POINTS))
def test_a_refused_write_is_one_line_keeps_what_is_finished_and_the_rerun_gives_the_clean_store(
        point, code, synth_world, stores, ga3ce, monkeypatch, tmp_path):
    out, work = tmp_path / "run.zarr", tmp_path / "work"
    shutil.copytree(stores["older"][0], out)
    hit, after, times = POINTS[point]
    with monkeypatch.context() as m:
        refuse(m, code, hit, after, times)
        line = one_line(*ga3ce(*_run_args(synth_world, out, work)), SAID[code], "rerun the same command")
    kept = len(Cache(work / "cache").entries())
    if point == "cache entry":
        one_line(2, line, f"{work}/cache", "the stage cache in --work", "give --work on another filesystem",
                 f" of {ENTRIES} cache entries are finished and kept")
        # the count is the cache's when the error is reported; a worker thread may still place an
        # entry of a kind the test does not refuse (not .npz) before the run has stopped
        said = int(re.search(rf"(\d+) of {ENTRIES} cache entries are finished and kept", line).group(1))
        assert after <= said <= kept
    else:
        one_line(2, line, f"all {ENTRIES} cache entries are finished and kept")
        assert kept == ENTRIES
        if code != errno.ENOSPC:  # rename(2) names the paths; a full disk's write(2) does not
            assert str(out if point == "store commit" else work) in line
    if code == errno.ENOSPC:
        assert "B more" in line and "free now" in line, line
    assert store_digests(out) == stores["older"][1]  # the older store is still there, whole

    s = run_pipeline("synthetic", synth_world, out, overrides=SETS, progress=False, work_dir=work)
    computed = sum(s.computed_shards.values())
    assert computed <= ENTRIES - after if point == "cache entry" else computed == 0  # only what was not finished
    assert store_digests(out) == stores["clean"][1]
    assert not list(tmp_path.glob("run.zarr.*finalize*")) and not (work / "partial.zarr").exists()


def _other_filesystem(than: Path) -> Path | None:
    """A fresh directory on tmpfs (/dev/shm) when it is another filesystem than `than`'s, else None."""
    shm = Path("/dev/shm")
    if not shm.is_dir() or not os.access(shm, os.W_OK) or shm.stat().st_dev == than.stat().st_dev:
        return None
    return Path(tempfile.mkdtemp(prefix="ga3ce-work-", dir=shm))


def test_the_work_directory_on_another_filesystem_gives_the_clean_store(synth_world, stores, ga3ce, monkeypatch,
                                                                        tmp_path):
    out = tmp_path / "run.zarr"
    work = _other_filesystem(tmp_path)
    if work is None:  # no second filesystem here: the rename between them refused as the kernel would
        work = tmp_path / "work"
        refuse(monkeypatch, errno.EXDEV, lambda d: d.endswith(".rename-probe"))
    try:
        shutil.copytree(stores["older"][0], out)
        code, err = ga3ce(*_run_args(synth_world, out, work))
        assert code == 0, err
        assert store_digests(out) == stores["clean"][1]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["run.zarr", "run.zarr.lock"]  # no scratch left
        assert sorted(p.name for p in work.iterdir()) == ["cache", "lock"]

        # the output's disk fills while the store is built beside it: its line names --out
        shutil.rmtree(out)
        shutil.copytree(stores["older"][0], out)
        with monkeypatch.context() as m:
            refuse(m, errno.ENOSPC, lambda d: "run.zarr.finalize/partial.zarr/" in d and "/c/" in d, 2)
            one_line(*ga3ce(*_run_args(synth_world, out, work)), f"{out}.finalize", "no space left",
                     "finalize writes the new store for --out", "choose another --out", "B more",
                     f"all {ENTRIES} cache entries are finished and kept")
        assert store_digests(out) == stores["older"][1]
        code, err = ga3ce(*_run_args(synth_world, out, work))
        assert code == 0, err
        assert store_digests(out) == stores["clean"][1]
        assert not Path(f"{out}.finalize").exists()
    finally:
        if str(work).startswith("/dev/shm/"):
            shutil.rmtree(work)


def test_an_unreachable_directory_and_a_bug_are_told_apart(ga3ce, monkeypatch, tmp_path):
    import ga3ce_prep.pipeline.run as run_module
    from ga3ce_prep.errors import environment_problem

    gone = tmp_path / "mnt" / "share" / "x.zarr"  # its directory is missing: a lost mount
    assert "does not exist (an unmounted filesystem" in str(environment_problem(
        FileNotFoundError(errno.ENOENT, "No such file or directory", str(gone))))
    assert environment_problem(FileNotFoundError(errno.ENOENT, "No such file", str(tmp_path / "x"))) is None
    assert "too long" in str(environment_problem(OSError(errno.ENAMETOOLONG, "File name too long", "x" * 300)))

    def boom(*a, **k):
        raise OSError(errno.EBADF, "Bad file descriptor")  # ours to get right: still a bug

    monkeypatch.setattr(run_module, "run_pipeline", boom)
    code, err = ga3ce("run", "-p", "synthetic", "-d", tmp_path, "-o", tmp_path / "s.zarr")
    assert code == 1 and "a bug in ga3ce-prep" in err


TRAIN = ["--epochs", str(len(SAID) + 1), "--train-frames", "16", "--val-frames", "8", "--batch-size", "8",
         "--warmup-epochs", "1", "--no-progress", "--model-set", "num_encoder_layers=1", "--model-set",
         "num_decoder_layers=1", "--model-set", "dim_feedforward=128", "--model-set", "head_hidden=128"]


@pytest.mark.slow
def test_a_refused_checkpoint_keeps_the_finished_epochs_and_resume_gives_the_clean_weights(ga3ce, monkeypatch,
                                                                                          tmp_path):
    """Each refusal in turn stops a run at the second epoch's last.pt; --resume goes on from the
    first, and the last run's weights are a clean run's."""
    from ga3ce_prep.train.checkpoint import load_checkpoint

    store = write_toy_store(tmp_path / "toy.zarr", 160, seed=5, frames_per_scene=20, knobs=ToyKnobs())
    code, err = ga3ce("train", "--store", store, "--out", tmp_path / "clean", *TRAIN)
    assert code == 0, err
    run = tmp_path / "run"
    for epoch, code in enumerate(SAID):
        args = ["train", "--store", store, "--out", run, *TRAIN, *(["--resume"] if epoch else [])]
        with monkeypatch.context() as m:
            refuse(m, code, lambda d: d.endswith("last.pt"), after=1)  # the second epoch this run trains
            line = one_line(*ga3ce(*args), SAID[code], str(run), "rerun with --resume")
        if code != errno.ENOSPC:  # rename(2) names the file; a full disk's write(2) does not: the run folder then
            assert str(run / "last.pt") in line
        assert load_checkpoint(run / "last.pt")["epoch"] == epoch  # the epochs before are kept
    code, err = ga3ce("train", "--store", store, "--out", run, *TRAIN, "--resume")
    assert code == 0, err
    got, clean = (load_checkpoint(r / "last.pt")["model"] for r in (run, tmp_path / "clean"))
    assert all(torch.equal(got[k], clean[k]) for k in clean)


@pytest.mark.parametrize("args, place", [
    (["eval", "--store", "s.zarr", "--checkpoint", "b.pt", "--json", "/share/eval.json"], "/share/eval.json"),
    (["report", "runs/a", "--out=/share/page"], "/share/page"),
    (["export", "s.zarr", "/share/s.h5"], "/share/s.h5"),
    (["predict", "-i", "p.jpg", "-o", "/share/p.png"], "/share/p.png"),
])
def test_every_command_names_the_place_it_writes_when_the_disk_is_full(args, place):
    from ga3ce_prep.cli import _refused

    line = str(_refused(OSError(errno.ENOSPC, "No space left on device"), args))
    assert line.startswith(f"{place}: no space left") and "rerun the command" in line, line
