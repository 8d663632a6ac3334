"""Output folders: checked before anything runs, written atomically, replaced only when they
hold a previous casmag result.

Every result folder casmag writes carries the marker file :data:`MARKER`. An output path is
refused (:class:`OutputError`, one line, exit 2 on the command line) when it is empty, the
current folder or one of its parents, the home folder, a file, a folder under a file, a
folder that cannot be written, or an existing folder holding files casmag did not write (the
marker lists what it wrote).

:func:`save_atomic` writes into a hidden folder beside the output (``.NAME.tmp-*``, the
marker written first), then swaps it in: the previous result is renamed aside
(``.NAME.old-*``), the new one renamed in, the old one removed. An interrupt or a kill at
any moment leaves either the previous result or the new one in place; the next save of the
same output cleans what a killed run left (and puts a previous result back if a kill came
between the two renames).

Several processes may save into the same output at once (two runs given the same --out):
each writes its own hidden folder, held with an advisory lock (``flock``) so that no other
save takes it for a leftover, and the swaps take turns under a lock on the parent folder,
where the output is checked again. The last swap wins; the output is never half written,
and a save that cannot be made raises OutputError (one line), never a bare OSError.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX: saves are not serialised
    fcntl = None  # type: ignore[assignment]

from casmag.errors import CasmagError, one_line

#: The file that marks a folder as a casmag result (safe to replace).
MARKER = ".casmag-result"
_TMP, _OLD = ".tmp-", ".old-"


class OutputError(CasmagError):
    """An output path casmag will not write to; names the path and the reason."""

    def __init__(self, path: Any, reason: str):
        self.path, self.reason = path, reason
        super().__init__(one_line(f"--out {str(path)!r}: {reason}"))


def is_result_folder(path: Path) -> bool:
    """A folder that casmag wrote (it holds the marker)."""
    return (path / MARKER).is_file()


def check_output_dir(out: Any, kind: str = "result") -> Path:
    """The output path, checked (module docstring); raises OutputError.

    kind ``result``: a folder casmag replaces as a whole (an existing one must hold the
    marker or be empty). kind ``tree``: a folder casmag adds results under (a sweep's), which
    may hold anything, but is still never the current folder, an ancestor of it, home or
    root."""
    return _check(out, kind, lock=True)


def _check(out: Any, kind: str, lock: bool) -> Path:
    """check_output_dir; ``lock``: look into the folder under its parent's lock (off where
    the caller holds it), so that a concurrent save's swap is never seen half done."""
    raw = "" if out is None else str(out)
    if not raw.strip():
        raise OutputError(raw, "an empty path is not an output folder; name a new folder")
    path = Path(raw).expanduser()
    full = path.resolve()
    cwd = Path.cwd().resolve()
    if full == cwd or full in cwd.parents:
        where = "the current folder" if full == cwd else "a parent of the current folder"
        raise OutputError(raw, f"is {where}, which casmag would replace; name a new folder")
    if full == Path.home().resolve() or full == Path(full.anchor):
        raise OutputError(raw, "is the home or root folder; name a new folder")
    held = _locked(full.parent) if lock and full.parent.is_dir() else contextlib.nullcontext()
    with held:
        try:
            mode: int | None = full.stat().st_mode
        except FileNotFoundError:
            mode = None
        except OSError as exc:
            raise OutputError(raw, f"cannot be read ({exc.strerror or exc})") from None
        others: list[str] = []
        if kind == "result" and mode is not None and stat.S_ISDIR(mode):
            written = _written(full)
            others = [p.name for p in full.iterdir() if p.name not in written]
    if mode is not None and not stat.S_ISDIR(mode):
        raise OutputError(raw, "exists and is not a folder")
    if others:
        raise OutputError(
            raw,
            f"holds files casmag did not write ({_names(others)}), which replacing it "
            "would delete; name a new or empty folder",
        )
    parent = full.parent  # where the hidden folders are made and the output renamed
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(raw, f"{parent} is a file, so no folder can be made under it")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(raw, f"{parent} cannot be written")
    return path


#: What a result folder of casmag before the marker held (``casmag run``, ``imu``, ``slam``
#: and a report written into it): such a folder with result.json and nothing else is
#: replaced too.
LEGACY_NAMES = frozenset(
    {
        "result.json", "trajectory.csv", "trajectory.png", "cost.png", "map.png",
        "sessions.png", "biases.md", "table.md", "table.csv", "table.tex", "figures",
    }
)  # fmt: skip


def _written(folder: Path) -> set[str]:
    """The names casmag wrote into a result folder (listed in its marker), the marker too;
    for a folder without a marker that holds result.json, LEGACY_NAMES; else empty."""
    try:
        lines = (folder / MARKER).read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return set(LEGACY_NAMES) if (folder / "result.json").is_file() else set()
    return {MARKER, *(line for line in lines[1:] if line)}


def record_written(folder: Path, names: list[str]) -> None:
    """Add names to the marker of a result folder (no-op for other folders): files another
    casmag command wrote into it (a report), which a later run may replace with it."""
    marker = folder / MARKER
    if not marker.is_file():
        return
    text = marker.read_text()
    have = set(text.splitlines()[1:])
    new = [n for n in names if n not in have]
    if new:
        marker.write_text(text + "".join(f"{n}\n" for n in new))


def _names(names: list[str]) -> str:
    shown = ", ".join(sorted(names)[:3])
    return shown + (f" and {len(names) - 3} more" if len(names) > 3 else "")


@contextlib.contextmanager
def _locked(folder: Path, blocking: bool = True) -> Iterator[bool]:
    """Hold an exclusive advisory lock on a folder (released on exit, or when the process
    dies); yields False when ``blocking`` is off and another process holds it, or where
    folders cannot be locked."""
    if fcntl is None:
        yield True
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        yield True  # a folder that cannot be opened for reading is not locked
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        except OSError:  # a file system without locks
            yield True
            return
        yield True
    finally:
        os.close(fd)


def clean_leftovers(out: Path) -> None:
    """Remove what an interrupted save of ``out`` left beside it; if ``out`` is missing
    and a complete previous result was set aside, put the newest one back. Hidden folders
    that a running save holds (locked) are left alone. Called under the parent's lock."""
    parent = out.parent
    if not parent.is_dir():
        return
    prefix = f".{out.name}"
    tmps = sorted(parent.glob(f"{prefix}{_TMP}*"))
    olds = []
    for p in parent.glob(f"{prefix}{_OLD}*"):
        with contextlib.suppress(FileNotFoundError):
            olds.append((p.stat().st_mtime, p))
    olds_sorted = [p for _, p in sorted(olds)]
    if not out.exists() and olds_sorted and is_result_folder(olds_sorted[-1]):
        os.replace(olds_sorted.pop(), out)
    for p in tmps + olds_sorted:
        try:
            leftover = p.is_dir() and (is_result_folder(p) or not any(p.iterdir()))
        except FileNotFoundError:
            continue
        if not leftover:
            continue
        with _locked(p, blocking=False) as free:
            if free:
                shutil.rmtree(p, ignore_errors=True)


def write_text_atomic(path: Path, text: str) -> None:
    """Write one text file through a temporary name beside it (its folder made when
    missing), so that a reader sees the old file or the whole new one, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def save_atomic(out_dir: Any, write: Callable[[Path], None]) -> Path:
    """Run ``write(folder)`` on a new hidden folder beside ``out_dir`` and swap it in (module
    docstring). Checks the output first and again just before the swap (OutputError);
    never leaves a half-written output."""
    out = check_output_dir(out_dir)
    try:
        return _save(out, write)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        raise OutputError(out_dir, f"cannot be written: {reason}{where}") from None


def _save(out: Path, write: Callable[[Path], None]) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    with _locked(out.parent):
        # Made and locked under the parent's lock: no other save's clean-up can take it for
        # a leftover in between.
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}{_TMP}", dir=out.parent))
        hold = contextlib.ExitStack()
        hold.enter_context(_locked(tmp))
    with hold:
        try:
            header = "written by casmag, replaced by the next run into it; its files:\n"
            (tmp / MARKER).write_text(header)
            write(tmp)
            names = sorted(p.name for p in tmp.iterdir() if p.name != MARKER)
            (tmp / MARKER).write_text(header + "".join(f"{n}\n" for n in names))
            old = None
            with _locked(out.parent):
                clean_leftovers(out)
                _check(out, "result", lock=False)  # another save or a user may have written
                if out.exists():
                    old = out.parent / f".{out.name}{_OLD}{os.getpid()}-{time.time_ns()}"
                    os.replace(out, old)
                    try:
                        os.replace(tmp, out)
                    except BaseException:
                        os.replace(old, out)
                        raise
                else:
                    os.replace(tmp, out)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return out
