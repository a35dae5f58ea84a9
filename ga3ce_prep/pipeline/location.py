"""Where a run writes: a local path, or an fsspec URL (s3://bucket/x.zarr, gs://..., any fsspec
filesystem installed: `pip install s3fs` for S3). Credentials and endpoints come from the
filesystem's usual configuration (for S3: AWS_* environment variables, ~/.aws; a custom endpoint
with AWS_ENDPOINT_URL_S3)."""
from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError

Location = str | Path  # a local Path, or a URL string


def is_remote(path: str | Path) -> bool:
    """True for a URL other than file://."""
    return "://" in str(path) and not str(path).startswith("file://")


def absolute(path: str | Path) -> Location:
    """A local path made absolute (file:// URLs included), or the URL without a trailing slash."""
    if is_remote(path):
        return str(path).rstrip("/")
    s = str(path)
    return Path(s[len("file://"):] if s.startswith("file://") else s).resolve()


def join(base: Location, *parts: str) -> Location:
    return "/".join([str(base), *parts]) if is_remote(base) else Path(base).joinpath(*parts)


def filesystem(url: str, what: str = "--out"):
    """The fsspec filesystem of a URL, without its listings cache (other processes write too).
    ConfigError when its package is missing or the URL is malformed."""
    import fsspec

    try:
        return fsspec.core.url_to_fs(url, use_listings_cache=False)[0]
    except ImportError as e:
        raise ConfigError(f"{what} {url}: {e}") from None
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{what} {url}: not a usable fsspec URL ({e})") from None
