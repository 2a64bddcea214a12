"""Finding CMU clips on disk, or downloading them from the CMU database into a cache.

A clip is named ``subject_trial`` (``"02_01"``, ``"131_03"``); its skeleton is the ASF of the
subject, the part of the name before the first underscore (``02.asf``). A clip is looked for,
in order, in each local folder (flat, ``<folder>/<subject>/`` and ``<folder>/subjects/<subject>/``,
the layouts of a flat copy and of CMU's own archive), then in the cache folder; its ASF beside
the AMC first, then in any of those folders and layouts. When it is in none of them and
downloading is allowed, its AMC and ASF are fetched from the CMU database's public URLs
(``http://mocap.cs.cmu.edu/subjects/<subject>/<file>``) into the cache.

`ClipNotFoundError` lists every place looked, and every URL tried with the reason it failed.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import tempfile
import urllib.error
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

CMU_URL_TEMPLATE = "http://mocap.cs.cmu.edu/subjects/{subject}/{file}"
_NAME = re.compile(r"^[A-Za-z0-9]+_[A-Za-z0-9_\-]+$")


class ClipNotFoundError(FileNotFoundError):
    """A clip is in none of the folders looked in and could not be downloaded."""


@dataclass(frozen=True)
class ClipFiles:
    """Where a clip's files are, and where they came from."""

    name: str  # "02_01"
    amc: Path
    asf: Path
    source: str  # "local", "cache" or the URL the AMC was downloaded from

    def sha256(self) -> dict[str, str]:
        """Content hashes of the two files, for provenance."""
        return {
            "amc": hashlib.sha256(self.amc.read_bytes()).hexdigest(),
            "asf": hashlib.sha256(self.asf.read_bytes()).hexdigest(),
        }


def clip_subject(name: str) -> str:
    """The subject part of a clip name: ``"02_01" -> "02"``, ``"acro_backflip" -> "acro"``."""
    if not _NAME.match(name):
        raise ValueError(
            f"clip name {name!r} is not of the form subject_trial (e.g. '02_01', '131_03')"
        )
    return name.split("_", 1)[0]


def default_cache_dir() -> Path:
    """``$MBRL_DELAN_CACHE/cmu_mocap``, else ``$XDG_CACHE_HOME`` or ``~/.cache``."""
    root = os.environ.get("MBRL_DELAN_CACHE")
    if root:
        return Path(root).expanduser() / "cmu_mocap"
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg).expanduser() / "mbrl_delan" / "cmu_mocap"


def _candidates(folder: Path, subject: str, filename: str) -> list[Path]:
    return [
        folder / filename,
        folder / subject / filename,
        folder / "subjects" / subject / filename,
    ]


def _first_file(paths: Sequence[Path], looked: list[Path]) -> Path | None:
    """The first of `paths` that is a file; every path tried is added to `looked`."""
    for path in paths:
        if path not in looked:
            looked.append(path)
        if path.is_file():
            return path
    return None


def _download(url: str, dest: Path, timeout: float) -> None:
    """Fetch url into dest atomically (a temp file in the same folder, then a rename)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    with urllib.request.urlopen(url, timeout=timeout) as response:  # noqa: S310 (http by design)
        fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".part")
        try:
            with os.fdopen(fd, "wb") as out:
                shutil.copyfileobj(response, out)
            head = Path(tmp).read_bytes()[:512].lstrip().lower()
            if head.startswith((b"<!doctype", b"<html")):
                raise ValueError(f"{url} returned an HTML page, not a mocap file")
            os.replace(tmp, dest)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)


def download_clip(
    name: str,
    cache_dir: str | Path,
    url_template: str = CMU_URL_TEMPLATE,
    timeout: float = 30.0,
) -> ClipFiles:
    """Download a clip's AMC (and its subject's ASF unless cached) into cache_dir.

    ``url_template`` is formatted with ``subject`` and ``file`` (e.g. ``"02_01.amc"``).
    Raises `ClipNotFoundError` with the URL and the reason when a download fails.
    """
    subject = clip_subject(name)
    cache = Path(cache_dir)
    amc, asf = cache / f"{name}.amc", cache / f"{subject}.asf"
    todo = [(url_template.format(subject=subject, file=p.name), p) for p in (asf, amc)]
    for url, dest in todo:
        if dest.is_file():
            continue
        log.info("downloading %s -> %s", url, dest)
        try:
            _download(url, dest, timeout)
        except (urllib.error.URLError, OSError, ValueError) as err:
            if isinstance(err, urllib.error.HTTPError):
                reason = f"HTTP {err.code} {err.reason}"
            else:
                reason = str(getattr(err, "reason", err))
            raise ClipNotFoundError(
                f"could not download clip {name!r}: {url} failed ({reason}); offline? "
                f"Put {amc.name} and {asf.name} in a local folder or in {cache}"
            ) from err
    return ClipFiles(name=name, amc=amc, asf=asf, source=todo[1][0])


def find_clip(
    name: str,
    folders: Sequence[str | Path] = (),
    cache_dir: str | Path | None = None,
    download: bool = True,
    url_template: str = CMU_URL_TEMPLATE,
    timeout: float = 30.0,
) -> ClipFiles:
    """Locate clip ``name`` (subject_trial) locally, in the cache, or by downloading it.

    Args:
        name: clip name, e.g. ``"02_01"``.
        folders: local folders searched first, in order.
        cache_dir: download cache (searched after the folders); `default_cache_dir()` if None.
        download: fetch missing clips from ``url_template`` into the cache.
        url_template: download URL with ``{subject}`` and ``{file}`` fields.
        timeout: seconds per HTTP request.

    Raises:
        ClipNotFoundError: listing every path looked at and, when downloading, the URL tried.
    """
    subject = clip_subject(name)
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    places = [Path(folder).expanduser() for folder in folders] + [cache]
    looked: list[Path] = []
    for place in places:
        amc = _first_file(_candidates(place, subject, f"{name}.amc"), looked)
        if amc is None:
            continue
        # the subject's skeleton: beside the AMC, else in any folder's layouts or the cache
        beside = [amc.parent / f"{subject}.asf"]
        anywhere = [p for d in places for p in _candidates(d, subject, f"{subject}.asf")]
        asf = _first_file(beside + anywhere, looked)
        if asf is not None:
            source = "cache" if place == cache else "local"
            return ClipFiles(name=name, amc=amc, asf=asf, source=source)
    where = "\n  ".join(str(p) for p in looked)
    if not download:
        raise ClipNotFoundError(
            f"clip {name!r} not found (downloading is off); looked in:\n  {where}"
        )
    try:
        return download_clip(name, cache, url_template=url_template, timeout=timeout)
    except ClipNotFoundError as err:
        raise ClipNotFoundError(
            f"clip {name!r} not found; looked in:\n  {where}\nand {err}"
        ) from err
