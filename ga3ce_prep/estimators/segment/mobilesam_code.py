"""MobileSAM's official model code (`mobile_sam` from the `mobilesam-mirror` distribution, with timm),
for the torch runtime (mobilesam_torch.py) and the random-weight test models
(testing/mobilesam_random.py). None of that code is part of ga3ce-prep.

`import_mobile_sam` takes it from this environment when it imports there (`pip install timm
mobilesam-mirror`), else from a private folder (`site_dir`) into which `install` puts the pinned
wheels (`REQUIREMENTS`, version and SHA-256) without their dependencies: a few MB, nothing added to
the environment. `mobile_sam` and timm import torchvision at package import for image utilities and
ops the model never calls, and PyPI's torchvision does not load beside torch's CPU build; where
torchvision does not load, an empty stand-in serves its modules while MobileSAM's import
(`absent_torchvision`), and is removed afterwards.

    python -m ga3ce_prep.estimators.segment.mobilesam_code     # install into site_dir(), once
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import os
import subprocess
import sys
import tempfile
import types
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

# pip requirements of the private folder: version and SHA-256 of each wheel.
REQUIREMENTS = (
    "timm==1.0.31 --hash=sha256:5bd50f7d0fe6d09bf9285ac2523234a1b7e6bf075c0be3e7aed09139fcb617c7",
    "mobilesam-mirror==1.0.0 --hash=sha256:7cbfd414f16a5cfb6d5fa87af24bc23ee01686e76b72d5925b51a645ef9ac788",
)
INSTALL_COMMAND = "python -m ga3ce_prep.estimators.segment.mobilesam_code"
FIX = (f"`{INSTALL_COMMAND}` (the pinned timm and mobilesam-mirror, without dependencies, into a private "
       "folder), or `pip install timm mobilesam-mirror`")


def site_dir() -> Path:
    """The private folder: $GA3CE_MOBILESAM_CODE, else ~/.cache/ga3ce-prep/mobilesam-code."""
    env = os.environ.get("GA3CE_MOBILESAM_CODE")
    return Path(env) if env else Path.home() / ".cache" / "ga3ce-prep" / "mobilesam-code"


def installed(site: Path | None = None) -> bool:
    """Whether `site` (default site_dir()) holds MobileSAM's code."""
    return ((site or site_dir()) / "mobile_sam").is_dir()


def install(site: Path | None = None) -> Path:
    """Install REQUIREMENTS (no dependencies, hashes required) into `site` (default site_dir()),
    unless it holds them already. Returns the folder."""
    site = site or site_dir()
    if installed(site):
        return site
    print(f"[mobilesam-code] installing {', '.join(r.split()[0] for r in REQUIREMENTS)} into {site}")
    with tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False) as f:
        f.write("\n".join(REQUIREMENTS) + "\n")
    try:
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--require-hashes",
                        "--target", str(site), "-r", f.name], check=True)
    finally:
        os.unlink(f.name)
    return site


class _Absent(type):
    """A stand-in class: any attribute is another empty class."""

    def __getattr__(cls, name: str) -> type:
        if name.startswith("__"):
            raise AttributeError(name)
        return _Absent(name, (), {})


class _AbsentModule(types.ModuleType):
    def __getattr__(self, name: str) -> type:
        if name.startswith("__"):
            raise AttributeError(name)
        return _Absent(name, (), {})


class _AbsentFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Serves an `_AbsentModule` for `torchvision` and every `torchvision.*` module."""

    def find_spec(self, name, path=None, target=None):
        if name == "torchvision" or name.startswith("torchvision."):
            return importlib.machinery.ModuleSpec(name, self, is_package=True)
        return None

    def create_module(self, spec):
        module = _AbsentModule(spec.name)
        module.__path__ = []
        return module

    def exec_module(self, module):
        pass


def _torchvision_modules() -> list[str]:
    return [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]


def torchvision_loads() -> bool:
    """Whether this environment's torchvision imports (a failed import's leftovers are removed)."""
    if importlib.util.find_spec("torchvision") is None:
        return False
    try:
        importlib.import_module("torchvision")
        return True
    except Exception:   # PyPI's torchvision beside torch's CPU build raises RuntimeError
        for m in _torchvision_modules():
            del sys.modules[m]
        return False


@contextmanager
def absent_torchvision() -> Iterator[None]:
    """Within the block, `import torchvision...` gives empty stand-ins (any attribute is an empty
    class); afterwards the finder and the stand-in modules are gone (modules imported meanwhile keep
    the names they took, which MobileSAM's model never calls)."""
    finder = _AbsentFinder()
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)
        for m in _torchvision_modules():
            if isinstance(sys.modules[m], _AbsentModule):
                del sys.modules[m]


def import_mobile_sam(site: Path | None = None) -> types.ModuleType:
    """The `mobile_sam` package: this environment's, else the one in `site` (default site_dir()),
    with torchvision stood in for where it does not load. ImportError naming the fix when neither
    has it."""
    if sys.modules.get("mobile_sam") is not None:
        return sys.modules["mobile_sam"]
    site = site or site_dir()
    if importlib.util.find_spec("mobile_sam") is None:
        if not installed(site):
            raise ImportError(f"MobileSAM's model code (the `mobile_sam` package, with timm) is neither installed in "
                              f"this environment nor in {site}: {FIX}")
        sys.path.append(str(site))
    with warnings.catch_warnings():   # timm's deprecated paths and model registry, which MobileSAM imports
        warnings.filterwarnings("ignore", category=FutureWarning, module="timm")
        warnings.filterwarnings("ignore", message="Overwriting tiny_vit", category=UserWarning)
        if torchvision_loads():
            return importlib.import_module("mobile_sam")
        with absent_torchvision():
            return importlib.import_module("mobile_sam")


if __name__ == "__main__":
    print(f"[mobilesam-code] ok: {install()}")
