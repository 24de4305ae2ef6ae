"""Read-only proof: every file the audit reads is hashed before it is first read and again at the end.

`ReadLedger.track(path)` records a file's SHA-256, size and modification time before anything reads it and
returns the path for a read-only reader (polars/pyarrow readers, `open(..., "rb")`). `ReadLedger.verify()`
hashes every tracked file again and lists those that changed or vanished. While `ReadLedger.guard()` is
active, any Python-level attempt to open a file under the audited roots for writing (`open` in a write or
append mode, `os.open` with a write flag) raises `ReadOnlyViolation`; native readers (polars, pyarrow) are
covered by the before/after hashes.
"""
from __future__ import annotations

import builtins
import contextlib
import io
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from prep.rawio import sha256_file  # reads in binary, read-only mode

_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_APPEND | os.O_CREAT | os.O_TRUNC


class ReadOnlyViolation(PermissionError):
    """Something tried to open an audited file for writing."""


@dataclass(frozen=True, kw_only=True)
class Fingerprint:
    """What identifies a file's content and write time."""

    sha256: str
    bytes: int
    mtime_ns: int

    @classmethod
    def of(cls, path: Path) -> "Fingerprint":
        st = path.stat()
        return cls(sha256=sha256_file(path), bytes=st.st_size, mtime_ns=st.st_mtime_ns)


class ReadLedger:
    """The set of files the audit read, with their fingerprints before the first read.

    Args:
        root: repository root; paths are reported relative to it where possible.
        guarded: directories under which write-mode opens are refused while `guard()` is active.
    """

    def __init__(self, *, root: Path, guarded: list[Path]):
        self.root = Path(root).resolve()
        self.guarded = [Path(g).resolve() for g in guarded]
        self.before: dict[Path, Fingerprint] = {}
        self.violations: list[str] = []

    def rel(self, path: Path | str) -> str:
        """Path relative to the root (absolute if outside it)."""
        p = Path(path).resolve()
        try:
            return str(p.relative_to(self.root))
        except ValueError:
            return str(p)

    def track(self, path: Path | str) -> Path:
        """Fingerprints `path` on its first use and returns it (resolved) for a read-only reader.

        Raises:
            FileNotFoundError: the file does not exist (the message names it).
        """
        p = Path(path).resolve()
        if p not in self.before:
            if not p.is_file():
                raise FileNotFoundError(f"{self.rel(p)}: no such file")
            self.before[p] = Fingerprint.of(p)
        return p

    def sha256(self, path: Path | str) -> str:
        """The file's SHA-256 as fingerprinted before its first read (tracks it; hashed once per audit).

        Raises:
            FileNotFoundError: the file does not exist (the message names it).
        """
        return self.before[self.track(path)].sha256

    def read_bytes(self, path: Path | str) -> bytes:
        """The file's bytes (opened "rb")."""
        with open(self.track(path), "rb") as fh:
            return fh.read()

    def read_json(self, path: Path | str) -> Any:
        """A JSON file's content (opened "r")."""
        with open(self.track(path), "r", encoding="utf-8") as fh:
            return json.load(fh)

    def verify(self) -> dict:
        """Hashes every tracked file again.

        Returns:
            {"files": [{path, sha256_before, sha256_after, bytes, mtime_unchanged, unchanged}], "changed":
            [paths], "write_attempts": [messages], "unchanged": bool}.
        """
        rows, changed = [], []
        for p, fp in sorted(self.before.items()):
            after = Fingerprint.of(p) if p.is_file() else None
            same = after is not None and after.sha256 == fp.sha256 and after.bytes == fp.bytes
            rows.append({"path": self.rel(p), "sha256_before": fp.sha256,
                         "sha256_after": after.sha256 if after else None, "bytes": fp.bytes,
                         "mtime_unchanged": bool(after and after.mtime_ns == fp.mtime_ns), "unchanged": same})
            if not same or not (after and after.mtime_ns == fp.mtime_ns):
                changed.append(self.rel(p))
        return {"files": rows, "changed": changed, "write_attempts": list(self.violations),
                "unchanged": not changed and not self.violations}

    def _guarded(self, target: Any) -> bool:
        if isinstance(target, int):
            return False
        try:
            p = Path(os.fsdecode(target)).resolve()
        except (TypeError, ValueError):
            return False
        return any(p == g or g in p.parents for g in self.guarded)

    @contextlib.contextmanager
    def guard(self) -> Iterator[None]:
        """Refuses write-mode opens of guarded paths (builtins.open, io.open, os.open) inside the block."""
        real_open, real_io_open, real_os_open = builtins.open, io.open, os.open
        ledger = self

        def refuse(target: Any, how: str) -> None:
            msg = f"write-mode open of {ledger.rel(os.fsdecode(target))} ({how}) refused during the audit"
            ledger.violations.append(msg)
            raise ReadOnlyViolation(msg)

        def checked_open(file, mode="r", *args, **kwargs):
            if any(c in str(mode) for c in "wax+") and ledger._guarded(file):
                refuse(file, f"mode {mode!r}")
            return real_open(file, mode, *args, **kwargs)

        def checked_os_open(path, flags, *args, **kwargs):
            if flags & _WRITE_FLAGS and ledger._guarded(path):
                refuse(path, f"flags {flags:#o}")
            return real_os_open(path, flags, *args, **kwargs)

        builtins.open, io.open, os.open = checked_open, checked_open, checked_os_open
        try:
            yield
        finally:
            builtins.open, io.open, os.open = real_open, real_io_open, real_os_open
