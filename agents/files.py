"""Files bimp reads and writes whole, safely: a file is read only if it is a regular one and within a bound, JSON
only within a depth, and a file is replaced in one step, never left half-written (``docs/security.md``). The acting
side (RL training) and the evaluation tools share these.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import stat
import tempfile
from pathlib import Path
from typing import Any

from bimp.agents.errors import EvaluationError

MAX_FILE_BYTES = 1 << 30  # episodes.jsonl and arms.json: a results folder is input from anyone
MAX_DEPTH = 16


def shown(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def too_deep(value: object, limit: int = MAX_DEPTH) -> bool:
    """Whether ``value`` nests containers deeper than ``limit`` (walked without recursion: the walk of a crafted
    record must not be what overflows)."""
    stack = [(value, 1)]
    while stack:
        node, depth = stack.pop()
        children = node.values() if isinstance(node, dict) else node if isinstance(node, list) else ()
        for child in children:
            if isinstance(child, (dict, list)):
                if depth + 1 > limit:
                    return True
                stack.append((child, depth + 1))
    return False


# Optional fields a reader uses, by their types: (type, None allowed).


def read_bounded(path: str | Path, limit: int | None = None) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` of them; :class:`EvaluationError` naming the file
    for anything else (a device such as ``/dev/zero`` behind a symlink, a FIFO, a folder, a file over the limit, a
    read that fails); ``FileNotFoundError`` where there is none, for the caller to take as empty. ``limit``:
    :data:`MAX_FILE_BYTES` by default."""
    limit = MAX_FILE_BYTES if limit is None else limit
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a device is refused before it is opened
            raise EvaluationError(f"{path} is not a regular file: bimp reads only regular files")
        # NONBLOCK: opening a FIFO swapped in meanwhile must not wait for a writer; NOCTTY: nor adopt a terminal.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    except FileNotFoundError:
        raise
    except OSError as err:
        raise EvaluationError(f"cannot read {path}: {err.strerror or err}") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # of what was opened, not of what a name pointed to before
            raise EvaluationError(f"{path} is not a regular file: bimp reads only regular files")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(limit + 1)
    except OSError as err:
        raise EvaluationError(f"cannot read {path}: {err.strerror or err}") from None
    finally:
        os.close(fd)
    if len(data) > limit:
        raise EvaluationError(f"{path} is over bimp's limit of {limit} bytes per file (MAX_FILE_BYTES)")
    return data


def read_json(path: str | Path, limit: int | None = None) -> Any:
    """The JSON document in the regular file ``path`` (:func:`read_bounded`), nested at most :data:`MAX_DEPTH`
    deep; :class:`EvaluationError` naming the file for one that is not such a document, ``FileNotFoundError`` where
    there is none."""
    data = read_bounded(path, limit)
    try:
        value = json.loads(data)
    except (ValueError, RecursionError) as err:  # RecursionError: nested past what the parser takes
        raise EvaluationError(f"{path} is not JSON: {type(err).__name__}: {shown(str(err))}") from None
    if too_deep(value):
        raise EvaluationError(f"{path}: nested deeper than {MAX_DEPTH} levels")
    return value


def read_json_or(path: str | Path, default: Any) -> Any:
    """:func:`read_json` of ``path`` where it is a file, else ``default`` (an optional record beside a run)."""
    return read_json(path) if Path(path).is_file() else default


def write_atomic(path: str | Path, text: str | bytes) -> None:
    """``path`` holds ``text``, replaced in one step (fsynced before the rename): a reader, an interruption or a full
    disk leaves the old file or the new one, never part of one. :class:`EvaluationError` in one line naming the file
    when it cannot be written (``ENOSPC`` and every other OS error), the temporary file removed."""
    path = Path(path)
    tmp = None
    try:
        # A fresh name, created exclusively: a file (or a symlink to one) planted at a fixed temporary name in a
        # shared folder is never written through.
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(text.encode() if isinstance(text, str) else text)
            f.flush()
            os.fchmod(f.fileno(), _mode(path))
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
        with contextlib.suppress(OSError):  # the rename itself, on disk
            folder = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(folder)
            finally:
                os.close(folder)
    except OSError as err:
        raise EvaluationError(f"cannot write {path}: {os_reason(err)}") from None
    finally:
        if tmp is not None:  # an error, or an interruption (Ctrl-C): no temporary file left
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def _mode(path: Path) -> int:
    """The permissions ``path`` has (a group-writable file stays so), else those a new file gets under the umask."""
    try:
        return stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def write_figure(fig: Any, path: str | Path, dpi: int) -> Path:
    """A matplotlib figure saved as PNG at ``path`` through :func:`write_atomic`."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    write_atomic(path, buffer.getvalue())
    return Path(path)


def os_reason(err: OSError) -> str:
    """An OS error in a few words: ``No space left on device (ENOSPC)``."""
    code = errno.errorcode.get(err.errno or 0)
    return f"{err.strerror or err}" + (f" ({code})" if code else "")
