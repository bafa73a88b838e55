"""Atomic file output and protection of input files.

:func:`atomic_write` writes to a temporary file in the destination directory and renames it
over the destination only when the block finishes without an exception, so a reader never
sees a half-written file and a failure leaves the old file (if any) untouched.
:func:`all_or_none` stages several outputs of one run so that either all of them replace
their targets or none does. :func:`check_output` says before any work whether a path can be
written. :func:`ensure_not_input` refuses to write onto one of the inputs (same file, a hard or
soft link to it, or a file inside an input bag directory).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from pipe_nav_core.errors import OutputIsInputError


def _same(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def ensure_not_input(
    output: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str]]
) -> None:
    """Raise OutputIsInputError if ``output`` is one of ``inputs`` (same file by samefile or
    realpath) or lies inside an input directory (a rosbag2 directory)."""
    out = Path(output)
    out_real = Path(os.path.realpath(out))
    for inp in inputs:
        p = Path(inp)
        if p.is_dir():
            in_real = Path(os.path.realpath(p))
            if out_real == in_real or in_real in out_real.parents:
                raise OutputIsInputError(
                    f"{out}: refusing to write inside the input bag directory {p}"
                )
            continue
        same_file = out.exists() and p.exists() and _same(out, p)
        if same_file or out_real == Path(os.path.realpath(p)):
            raise OutputIsInputError(f"{out}: refusing to overwrite the input file {p}")


def _tmp_name(target: Path) -> Path:
    return target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")


_STAGED = re.compile(r"^\.(.+)\.[0-9a-f]{8}\.(?:tmp|part)$")


def target_stem(path: str | os.PathLike[str]) -> str:
    """The file name without its extension of the file ``path`` becomes: its own, or for a
    staging path (:func:`all_or_none`, :func:`atomic_path`) its target's (what a document
    names itself after)."""
    name = os.path.basename(os.fspath(path))
    staged = _STAGED.match(name)
    return os.path.splitext(staged.group(1) if staged else name)[0]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for tools that want a file name; on success it is
    renamed onto ``path``, on an exception it is removed. The file may or may not have been
    created by the caller."""
    target = Path(path)
    tmp = _tmp_name(target)
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException:
        _remove(tmp)
        raise


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike[str],
    mode: str = "w",
    *,
    encoding: str | None = "utf-8",
    newline: str | None = None,
) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing (``mode`` 'w' text or 'wb' binary);
    when the block ends normally the data are flushed to disk and the file replaces ``path``
    (os.replace, atomic on POSIX); on any exception the temporary file is deleted and ``path``
    is left as it was. New files get the usual permissions (0666 minus umask)."""
    if mode not in ("w", "wb"):
        raise ValueError("atomic_write mode must be 'w' or 'wb'")
    target = Path(path)
    tmp = _tmp_name(target)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except FileExistsError:
        raise
    except BaseException:  # SIGINT/SIGTERM handled as os.open returned: the file may be there
        _remove(tmp)
        raise
    try:
        try:
            text = {"encoding": encoding, "newline": newline} if mode == "w" else {}
            f: IO[Any] = os.fdopen(fd, mode, **text)
        except BaseException:
            os.close(fd)
            raise
        with f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        _remove(tmp)
        raise


def _remove(path: Path) -> None:
    with contextlib.suppress(OSError):
        path.unlink()


def check_output(path: str | os.PathLike[str], option: str) -> None:
    """Raise ValueError naming ``option`` unless ``path`` can be written: its folder exists and
    is a writable folder, and the path itself is not a folder."""
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if target.is_dir():
        raise ValueError(f"{option} {target}: is a folder, not a file")
    for up in (parent, *parent.parents):
        if up.exists():
            if not up.is_dir():
                raise ValueError(f"{option} {target}: {up} is a file, not a folder")
            break
    if not parent.is_dir():
        raise ValueError(f"{option} {target}: no such folder {parent}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{option} {target}: the folder {parent} is not writable")


@contextlib.contextmanager
def all_or_none(paths: Iterable[str | os.PathLike[str]]) -> Iterator[dict[str, Path]]:
    """Stage the outputs of one run: yields {target: staging path beside it} for the writers
    to write to; when the block ends normally each staged file replaces its target; on any
    exception (SIGINT, SIGTERM turned into one) every staged file is removed and no target
    is touched. Targets must be distinct."""
    staged = {os.fspath(p): _tmp_name(Path(p)).with_suffix(".part") for p in paths}
    try:
        yield staged
    except BaseException:
        for tmp in staged.values():
            _remove(tmp)
        raise
    try:
        for target, tmp in staged.items():
            if tmp.exists():
                os.replace(tmp, target)
    except BaseException:  # interrupted while committing: the rest too (renames), then stop
        for target, tmp in staged.items():
            if tmp.exists():
                with contextlib.suppress(OSError):
                    os.replace(tmp, target)
        raise
