"""What every writing command shares about paths: one rule, checked before any output is touched.

A command declares its inputs (positional paths, options, and the files it will read that are
named inside inputs: a pose file, a mesh, labels, a predictor) and its outputs (each a file or a
folder) to :func:`check_paths`, before it writes anything. The check refuses, with one line:

- an output that is an input, lies inside an input folder, or is a folder that holds an input
  (an input inside an output that will be written into);
- two outputs that are the same path;
- an existing output of the wrong kind (a folder where a file is written, a file where a folder
  is);
- an output whose nearest existing ancestor is not a folder or is not writable (a probe file is
  created and removed there: permissions alone do not tell for root, /sys, a read-only mount);
- an existing, non-empty output folder that is not the command's own earlier output
  (``folder_out(path, replaces=...)``: someone else's files are never merged into or deleted;
  the command's own earlier output is replaced as a whole, so no stale frame survives); an empty
  output path; a symbolic-link loop.

One writer per output: inside a command (:func:`command_locks`, entered for a command's whole
life by the command runner in :mod:`damcap.cli.options`), :func:`check_paths` also locks each
output with ``fcntl.flock`` on a hidden file beside it (``m.dam`` -> ``.m.dam.lock``; a folder
``out`` -> ``.out.lock``), which covers the output and whatever it keeps inside or beside it (a
checkpoint, a work folder). A second run aimed at the same output is refused in one line naming
the first run's process id, before anything is touched. The lock ends with the command (success,
error, Ctrl-C, SIGTERM: the lock file is removed); a killed run's lock is released by the kernel,
and the file it leaves is taken over by the next run.

Folder outputs that a command writes from scratch are staged (:func:`staged_folder`): files are
written into a hidden folder beside the output and moved into place (fsynced) only when the
command succeeds; an error or Ctrl-C removes the staged files. Single files are staged by
:mod:`damcap.common.atomic`.

Exit codes (``damcap.cli.main``): 0 success; 2 a user mistake or an operating-system error
(permission denied, disk full, read-only filesystem: ``error: PATH: <reason>; <what to do>``);
130 Ctrl-C; 143 SIGTERM.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import fcntl
import os
import re
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Callable, Iterable, Iterator, Literal, Optional, Sequence

from damcap.common.atomic import fsync_path, pause_point
from damcap.common.errors import DamcapError

Kind = Literal["file", "folder"]


@dataclass(frozen=True)
class Output:
    """One path a command writes."""

    path: Path
    kind: Kind
    """``"file"``: one file is written at ``path``; ``"folder"``: files are written inside it"""
    replaces: Optional[Callable[[Path], bool]] = None
    """for a folder written from scratch: whether an existing, non-empty folder is this command's
    own earlier output (which it replaces as a whole); any other non-empty folder is refused"""


def _given(path: os.PathLike | str) -> Path:
    if str(path).strip() == "":
        raise DamcapError("an output path is empty (''); give a file or folder path")
    return Path(path)


def file_out(path: Optional[os.PathLike | str]) -> Optional[Output]:
    return None if path is None else Output(_given(path), "file")


def folder_out(path: Optional[os.PathLike | str], replaces: Optional[Callable[[Path], bool]] = None) -> Optional[Output]:
    """A folder output; ``replaces``: see :attr:`Output.replaces` (:func:`holds` builds one)."""
    return None if path is None else Output(_given(path), "folder", replaces)


def never(folder: Path) -> bool:
    """A folder test for :func:`folder_out`: only a new or empty folder (the command replaces
    nothing, not even its own earlier output)."""
    return False


def holds(record: str) -> Callable[[Path], bool]:
    """A folder test for :func:`folder_out`: the folder holds the record file a command writes
    last (``render.json``), so it is that command's earlier output."""
    return lambda folder: (folder / record).is_file()


def beside(path: os.PathLike | str, suffix: str) -> Path:
    """The sidecar of an output file: ``m.dam`` -> ``m.dam.ckpt`` (``suffix=".ckpt"``).

    Raises:
        DamcapError: ``path`` names no file ('', '.', '/').
    """
    p = _given(path)
    if p.name in ("", ".", ".."):
        raise DamcapError(f"{path}: names a folder, not a file; give a file path")
    return p.with_name(p.name + suffix)


def _inside(child: Path, parent: Path) -> bool:
    return parent in child.parents


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _resolve(path: Path) -> Path:
    """``path.resolve()``, with a symbolic-link loop (or another unresolvable path) as one line."""
    try:
        return path.resolve()
    except RuntimeError:  # Python < 3.13: "Symlink loop from ..."
        raise DamcapError(f"{path}: is a symbolic link that loops back on itself; give the real path") from None
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise DamcapError(f"{path}: is a symbolic link that loops back on itself; give the real path") from None
        raise


def _probe_writable(folder: Path, out: Path) -> None:
    """Create and remove a hidden file in ``folder``: permissions alone do not tell (root, /sys, a
    read-only mount)."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".damcap-probe.", dir=folder)
    except OSError as e:
        raise DamcapError(f"{folder}: not writable ({e.strerror or e}), so {out} cannot be written; "
                          f"fix its permissions or choose another output path") from None
    os.close(fd)
    os.unlink(probe)


def check_paths(inputs: Iterable[Optional[os.PathLike | str]], outputs: Iterable[Optional[Output]]) -> None:
    """Refuse, before any output is touched, outputs that collide with inputs or cannot be written;
    inside :func:`command_locks`, lock every output for the rest of the command.

    Args:
        inputs: every path the command reads (None entries are skipped).
        outputs: every path it writes (None entries are skipped).

    Raises:
        DamcapError: one line naming the output (see the module docstring), among them an output
            that another damcap run is writing.
    """
    ins = [Path(i) for i in inputs if i is not None]
    outs = [o for o in outputs if o is not None]
    resolved_in = [(i, _resolve(i)) for i in ins]
    seen: dict[Path, Path] = {}
    for o in outs:
        r = _resolve(o.path)
        if r in seen:
            raise DamcapError(f"{o.path}: given for two outputs (also {seen[r]}); choose different output paths")
        seen[r] = o.path
        for i, ri in resolved_in:
            if r == ri or _inside(r, ri):
                raise DamcapError(f"{o.path}: output would overwrite or write into the input {i}; choose another output path")
            if o.kind == "folder" and _inside(ri, r):
                raise DamcapError(f"{o.path}: output would overwrite or write into the input {i} (it lies inside the output folder); "
                                  f"choose another output folder or move the input")
    # locked before the checks that look at the outputs' contents: a run that is writing them is
    # named as such, not as a folder of someone else's files
    not_locked = [(o, reason) for o in outs if (reason := _lock_output(o.path, _resolve(o.path))) is not None]
    for o in outs:
        if o.kind == "file" and o.path.is_dir():
            raise DamcapError(f"{o.path}: is a folder, but a file is written here; give a file path")
        if o.kind == "folder" and o.path.exists() and not o.path.is_dir():
            raise DamcapError(f"{o.path}: exists and is not a folder; give a folder path")
        base = _nearest_existing(o.path if o.kind == "folder" else o.path.parent)
        if not base.is_dir():
            raise DamcapError(f"{base}: is not a folder, so {o.path} cannot be written; choose another output path")
        if not os.access(base, os.W_OK | os.X_OK):
            raise DamcapError(f"{base}: not writable, so {o.path} cannot be written; fix its permissions or choose another output path")
        _probe_writable(base, o.path)
        if o.kind == "folder" and o.replaces is not None and o.path.is_dir() and any(o.path.iterdir()) and not o.replaces(o.path):
            raise DamcapError(f"{o.path}: exists, is not empty and was not written by this command; choose a new or empty "
                              f"folder (damcap never merges into or deletes other files)")
    for o, reason in not_locked:
        warnings.warn(f"{o.path}: could not be locked ({reason}); another damcap run writing it at the same time would not be stopped")
    held = _LOCKS.get()
    for o in outs:  # only an output this run has locked: what a live run is writing is never touched
        r = _resolve(o.path)
        if held is not None and r.name not in ("", ".", "..") and r.with_name(f".{r.name}.lock") in held:
            remove_leftovers(o)
            pause_point(r.with_name(f".{r.name}.lock"))  # test hook (common/atomic.py): a no-op unless a kill test asks


# --------------------------------------------------------------------------------------------
# One writer per output
# --------------------------------------------------------------------------------------------


def lock_path(out: os.PathLike | str) -> Path:
    """The lock file of an output: ``.NAME.lock`` beside it, by its resolved path (a symbolic link
    or a relative spelling of the same output shares one lock)."""
    r = _resolve(_given(out))
    return r.with_name(f".{r.name}.lock")


@dataclass
class _HeldLock:
    path: Path
    fd: int
    made: list[Path]
    """folders created for the lock file (deepest first): removed again if still empty"""

    def release(self) -> None:
        with contextlib.suppress(OSError):  # removed while still held: a run waiting on this file retries on the new one
            os.unlink(self.path)
        os.close(self.fd)
        _remove_empty(self.made)


_LOCKS: contextvars.ContextVar[Optional[dict[Path, _HeldLock]]] = contextvars.ContextVar("damcap_output_locks", default=None)
"""the locks of the running command, by lock file; None outside a command"""


@contextlib.contextmanager
def command_locks() -> Iterator[None]:
    """The life of one command: outputs that :func:`check_paths` locks inside it stay locked
    until it ends, however it ends (return, error, Ctrl-C, SIGTERM). Nested, it is the outer
    command's. Outside it :func:`check_paths` locks nothing (library use). Under torchrun the
    job is one run of many processes: its rank 0 holds the locks, the other ranks take none."""
    if _LOCKS.get() is not None or _secondary_rank():
        yield
        return
    held: dict[Path, _HeldLock] = {}
    token = _LOCKS.set(held)
    try:
        yield
    finally:
        _LOCKS.reset(token)
        for lock in reversed(list(held.values())):
            lock.release()


def _secondary_rank() -> bool:
    """A process of a torchrun job other than its rank 0 (``WORLD_SIZE`` > 1, ``RANK`` != 0)."""
    return os.environ.get("WORLD_SIZE", "1").strip() not in ("", "0", "1") and os.environ.get("RANK", "0").strip() != "0"


def _holder_pid(fd: int) -> Optional[int]:
    """The process id a lock holder wrote into its lock file (it writes it right after locking)."""
    for _ in range(20):
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        if text.isdigit():
            return int(text)
        time.sleep(0.005)
    return None


def _lock_output(out: Path, resolved: Path) -> Optional[str]:
    """Lock ``out`` for the running command (nothing outside :func:`command_locks`).

    Returns:
        None when locked (or when no command runs), else why the lock file could not be made (the
        checks that follow name a real problem with the path; otherwise a warning says so).

    Raises:
        DamcapError: another process holds the lock.
    """
    held = _LOCKS.get()
    if held is None or resolved.name in ("", ".", ".."):
        return None
    path = resolved.with_name(f".{resolved.name}.lock")
    if path in held:  # checked again by the same command
        return None
    made = [p for p in path.parents if not p.exists()]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(100):
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = _holder_pid(fd)
                os.close(fd)
                _remove_empty(made)
                raise DamcapError(f"{out} is being written by another damcap run ({'pid ' + str(pid) if pid else 'pid unknown'}); "
                                  f"wait for it or choose another -o") from None
            except BaseException:
                os.close(fd)
                raise
            try:  # the holder we waited on may have removed the file it locked: lock the file the path names now
                same = os.path.samestat(os.fstat(fd), os.stat(path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        else:
            raise OSError(errno.EAGAIN, "the lock file kept being replaced", str(path))
        try:
            os.ftruncate(fd, 0)  # a killed run's process id is replaced by ours
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError:
            os.close(fd)
            raise
        held[path] = _HeldLock(path, fd, made)
    except OSError as e:
        _remove_empty(made)
        return e.strerror or str(e)
    return None


def frame_output_names(file_paths: Sequence[str], suffix: Optional[str] = None) -> list[str]:
    """Output names for capture frames, unique by construction.

    When every frame lies in the same folder (``images/0000.exr``, ...) the base name is kept
    (``0000.exr``); otherwise each name is the frame's relative path (``images2/0004.exr``), so
    two frames of the same base name in different folders never collide.

    Args:
        file_paths: the frames' ``file_path`` (relative to the capture root).
        suffix: replace each name's suffix by this (``".exr"``), or keep it (None).

    Raises:
        DamcapError: a path that leaves the capture folder, or two frames with one path.
    """
    parts = []
    for fp in file_paths:
        p = PurePosixPath(str(fp).replace("\\", "/"))
        if p.is_absolute() or ".." in p.parts or not p.parts:
            raise DamcapError(f"frame {fp!r}: its path leaves the capture folder; frames must lie inside it")
        parts.append(p)
    one_folder = len({p.parent for p in parts}) <= 1
    names: dict[str, str] = {}
    out = []
    for fp, p in zip(file_paths, parts):
        q = PurePosixPath(p.name) if one_folder else p
        if suffix is not None:
            q = q.with_suffix(suffix)
        name = str(q)
        if name in names:
            raise DamcapError(f"frames {names[name]!r} and {fp!r} would both be written as {name}; give the frames distinct paths")
        names[name] = fp
        out.append(name)
    return out


# --------------------------------------------------------------------------------------------
# Leftovers of killed runs
# --------------------------------------------------------------------------------------------

_RANDOM = r"[a-z0-9_]{8}"
"""the random part of a name made by :mod:`tempfile` (``mkstemp``, ``mkdtemp``)"""
_ATOMIC_TMP = re.compile(rf"^\.(?P<stem>.+)\.{_RANDOM}\.tmp(?P<suffix>\.[^.]*)?$")
"""a file :func:`damcap.common.atomic.atomic_path` stages: ``.m.k3j_x0ab.tmp.dam`` for ``m.dam``"""
_STAGED_FOLDER = re.compile(rf"^\.(?P<name>.+)\.(staging|replaced)-{_RANDOM}$")
"""a folder :func:`staged_folder` stages or sets aside: ``.out.staging-k3j_x0ab`` for ``out``"""
#: how deep inside a folder output leftovers are looked for (``out/images/.0000.k3j_x0ab.tmp.exr``)
LEFTOVER_DEPTH = 3


def leftovers(out: Output) -> list[Path]:
    """What killed runs writing ``out`` left behind: the staged files and folders of
    :func:`damcap.common.atomic.atomic_path` and :func:`staged_folder` (never the output itself).

    Beside ``out``: its staging and set-aside folders, a staged file of ``out`` or of a sidecar
    named after it (``m.dam.ckpt``), a ``keep_name`` folder holding only ``out``'s name. Inside a
    folder output (down to :data:`LEFTOVER_DEPTH` levels): any staged file or staging folder.
    The names carry :mod:`tempfile`'s 8 random characters, so a user's file is not mistaken for one.
    """
    path = Path(out.path)
    found: list[Path] = []
    parent = path.parent
    try:
        beside_out = list(os.scandir(parent)) if parent.is_dir() else []
    except OSError:
        beside_out = []
    keep_name = re.compile(rf"^\.{re.escape(path.stem)}\.{_RANDOM}$")
    for entry in beside_out:
        name = entry.name
        if (m := _STAGED_FOLDER.match(name)) and m["name"] == path.name and entry.is_dir(follow_symlinks=False):
            found.append(Path(entry.path))
        elif (m := _ATOMIC_TMP.match(name)) and entry.is_file(follow_symlinks=False):
            target = m["stem"] + (m["suffix"] or "")
            if target == path.name or target.startswith(path.name + "."):
                found.append(Path(entry.path))
        elif out.kind == "file" and keep_name.match(name) and entry.is_dir(follow_symlinks=False):
            with contextlib.suppress(OSError):
                if {p.name for p in Path(entry.path).iterdir()} <= {path.name}:
                    found.append(Path(entry.path))
    if out.kind == "folder" and path.is_dir() and not path.is_symlink():
        found += _leftovers_inside(path, LEFTOVER_DEPTH)
    return sorted(found)


def _leftovers_inside(folder: Path, depth: int) -> list[Path]:
    found = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return found
    for entry in entries:
        if entry.is_dir(follow_symlinks=False):
            if _STAGED_FOLDER.match(entry.name):
                found.append(Path(entry.path))
            elif depth > 1:
                found += _leftovers_inside(Path(entry.path), depth - 1)
        elif _ATOMIC_TMP.match(entry.name) and entry.is_file(follow_symlinks=False):
            found.append(Path(entry.path))
    return found


def remove_leftovers(out: Output) -> list[Path]:
    """Remove :func:`leftovers` of ``out`` (call it only while holding ``out``'s lock); one
    warning line names what went. Returns what was removed."""
    gone = []
    for p in leftovers(out):
        try:
            kept = p / out.path.name
            if p.name.startswith(f".{out.path.name}.replaced-") and not out.path.exists() and kept.exists():
                os.rename(kept, out.path)  # killed between setting the earlier output aside and moving the new one in
                warnings.warn(f"{out.path}: put back the earlier output that an interrupted run had set aside")
                p.rmdir()
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
            gone.append(p)
        except OSError:
            continue
    if gone:
        shown = ", ".join(str(p.relative_to(out.path.parent)) for p in gone[:3]) + (f" and {len(gone) - 3} more" if len(gone) > 3 else "")
        warnings.warn(f"{out.path}: removed what an interrupted earlier run left ({shown})")
    return gone


# --------------------------------------------------------------------------------------------
# Staging: folders move into place at the end
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def staged_folder(out: Path, replace: bool = False) -> Iterator[Path]:
    """Yield a hidden folder beside ``out``; on success move its files into ``out`` (fsynced).

    An existing ``out`` keeps its other files (a file of the same name is replaced); with
    ``replace`` it is replaced as a whole (the command's own earlier output, checked by
    :func:`check_paths`: no stale file of the earlier run survives). On an error or an interrupt
    the staged files are removed and ``out`` is as it was.
    """
    out = Path(out)
    made = [p for p in out.parents if not p.exists()]  # deepest first: removed again on an error
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
        os.chmod(stage, 0o777 & ~_umask())  # mkdtemp makes 0700; the output folder gets the usual permissions
    except OSError as e:  # the error names the folder the user gave, not a staging name
        _remove_empty(made)
        raise OSError(e.errno, e.strerror or str(e), str(out)) from None
    done = False
    try:
        try:
            yield stage
        except OSError as e:  # a file being staged is named as the output file it would have become
            name = None if e.filename is None else Path(os.fsdecode(e.filename))
            if name is not None and (name == stage or stage in name.parents):
                raise OSError(e.errno, e.strerror or str(e), str(out / name.relative_to(stage))) from None
            if name is None:  # a write that names no file (torch.save, a library's own writer): the output it was for
                raise OSError(e.errno, e.strerror or str(e), str(out)) from None
            raise
        except DamcapError as e:
            if str(stage) in str(e):  # the line names the output, not the hidden staging folder
                e.args = (str(e).replace(str(stage), str(out)),)
            raise
        files = sorted(p for p in stage.rglob("*") if p.is_file())
        for p in files:
            fsync_path(p)
        pause_point(out)  # test hook (common/atomic.py): a no-op unless a kill test asks
        if replace and out.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.replaced-", dir=out.parent))
            os.rename(out, old / out.name)
            try:
                os.rename(stage, out)
            except OSError:
                os.rename(old / out.name, out)
                shutil.rmtree(old, ignore_errors=True)
                raise
            shutil.rmtree(old, ignore_errors=True)
            for d in {out / p.parent.relative_to(stage) for p in files} | {out}:
                fsync_path(d)
            fsync_path(out.parent)
            done = True
            return
        if not out.exists():
            os.rename(stage, out)
            for d in {out / p.parent.relative_to(stage) for p in files} | {out}:
                fsync_path(d)
            fsync_path(out.parent)
            done = True
            return
        folders = set()
        for p in files:
            dst = out / p.relative_to(stage)
            dst.parent.mkdir(parents=True, exist_ok=True)
            if dst.is_dir():
                raise DamcapError(f"{dst}: is a folder, but a file is written here; remove it or choose another output folder")
            os.replace(p, dst)
            folders.add(dst.parent)
        for d in folders:
            fsync_path(d)
        done = True
    finally:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)
        if not done:
            _remove_empty(made)


def _umask() -> int:
    """The process's umask, read without changing it where Linux says it (``/proc/self/status``)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _remove_empty(folders: Iterable[Path]) -> None:
    for d in folders:
        with contextlib.suppress(OSError):
            d.rmdir()


# --------------------------------------------------------------------------------------------
# Interrupts and operating-system errors
# --------------------------------------------------------------------------------------------


class Terminated(KeyboardInterrupt):
    """Raised by damcap's SIGTERM handler, so that SIGTERM takes Ctrl-C's path."""


class Interrupted(Exception):
    """A command stopped by Ctrl-C or SIGTERM; ``kept`` says what it leaves behind."""

    def __init__(self, kept: str, terminated: bool = False):
        super().__init__(kept)
        self.kept = kept
        self.terminated = terminated

    @property
    def exit_code(self) -> int:
        return 143 if self.terminated else 130


NOTHING_KEPT = "no output was completed (staged files were removed); rerun the command"


@contextlib.contextmanager
def on_interrupt(kept: Callable[[], str]) -> Iterator[None]:
    """Turn Ctrl-C / SIGTERM inside the block into :class:`Interrupted` with ``kept()``'s line."""
    try:
        yield
    except KeyboardInterrupt as e:
        raise Interrupted(kept(), isinstance(e, Terminated)) from None


_ADVICE = {
    errno.EACCES: "fix the permissions or choose another path",
    errno.EPERM: "fix the permissions or choose another path",
    errno.ENOSPC: "free disk space or write to another disk",
    errno.EDQUOT: "free space within your quota or write elsewhere",
    errno.EROFS: "the filesystem is read-only; choose a path on a writable one",
    errno.ENOENT: "check that the path exists",
    errno.ENOTDIR: "a part of the path is a file, not a folder; choose another path",
    errno.EISDIR: "it is a folder; give a file path",
    errno.EEXIST: "remove it or choose another path",
    errno.ENAMETOOLONG: "choose a shorter path",
    errno.EMFILE: "too many open files; raise the limit (ulimit -n)",
    errno.EIO: "the disk reported an I/O error; check it",
}


def os_error_line(e: OSError) -> str:
    """``PATH: <reason>; <what to do>`` for an operating-system error (no traceback)."""
    where = e.filename if e.filename is not None else None
    reason = e.strerror or str(e) or type(e).__name__
    advice = _ADVICE.get(e.errno or -1, "check the path and try again")
    prefix = f"{where}: " if where is not None else ""
    if e.filename2 is not None:
        prefix = f"{e.filename} -> {e.filename2}: "
    return f"{prefix}{' '.join(str(reason).split())}; {advice}"
