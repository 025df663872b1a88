""".npz archives and JSON texts from elsewhere, checked before anything is allocated.

Records, checkpoints, trajectories, predictions and datasets arrive from other people
(pull requests, `--with-results`, `lgnn rollout --model`). Loading one must never run
code and never exhaust the machine, whatever its bytes say:

- `npz_problem(path)` reads only the archive's directory and each member's `.npy`
  header, and says what is wrong (None if nothing): more than `MAX_MEMBERS` members; a
  member that inflates past `MAX_ARRAY_BYTES`, or members past `MAX_ARCHIVE_BYTES`
  together (sizes as the directory declares them: Python's zip reader never inflates a
  member past its declared size, so a deflate bomb stops there); a member that is not an
  `.npy` array; an array of Python objects (pickled: unpickling runs code, so it is never
  loaded); an array whose header claims more bytes than the member holds (a header of
  terabytes over a few bytes of data: NumPy allocates what the header says before it
  reads). Readers call it before `np.load`, which they call with `allow_pickle=False`.
- `json_depth_problem(value)` refuses a parsed JSON value nested deeper than
  `MAX_JSON_DEPTH` (a meta is a few levels deep; deeper nesting is an attack on every
  recursive reader after it). Python's parser itself stops far deeper, with
  RecursionError, which readers also turn into one line.

The limits sit far above what lgnn writes: the largest file it keeps is a ground-truth
cache of chain100-3d, about 1.2 GB in members of at most 250 MB.
"""

from __future__ import annotations

import math
import os
import zipfile
import zlib

# An archive's members at most, each member's inflated bytes at most, and all of them.
MAX_MEMBERS = 4096
MAX_ARRAY_BYTES = 2 * 2**30
MAX_ARCHIVE_BYTES = 8 * 2**30
# JSON (metas, manifests, metadata) nested at most this deep.
MAX_JSON_DEPTH = 64


def _gib(n: int) -> str:
    return f"{n / 2**30:.3g} GiB"


def npz_problem(path: str | os.PathLike) -> str | None:
    """What makes the `.npz` at `path` unsafe or impossible to load (module docstring), or
    None; the archive's directory and array headers only are read."""
    import numpy as np

    try:
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
            if len(members) > MAX_MEMBERS:
                return f"{len(members)} members, more than the {MAX_MEMBERS} an lgnn archive may hold"
            total = sum(member.file_size for member in members)
            if total > MAX_ARCHIVE_BYTES:
                return f"its members inflate to {_gib(total)}, over the {_gib(MAX_ARCHIVE_BYTES)} limit"
            for member in members:
                name = member.filename
                if member.file_size > MAX_ARRAY_BYTES:
                    return f"member {name!r} inflates to {_gib(member.file_size)}, over the {_gib(MAX_ARRAY_BYTES)} limit for one array"
                if not name.endswith(".npy"):
                    return f"member {name!r} is not an array (.npy)"
                with archive.open(member) as stream:
                    version = np.lib.format.read_magic(stream)
                    if version not in ((1, 0), (2, 0)):
                        return f"member {name!r} is a .npy of format {version[0]}.{version[1]} (lgnn reads 1.0 and 2.0)"
                    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                    shape, _, dtype = read_header(stream)
                    header = stream.tell()
                if dtype.hasobject:
                    return f"member {name!r} holds Python objects (pickled), which lgnn never loads"
                claimed = math.prod(shape) * dtype.itemsize
                if header + claimed != member.file_size:
                    return (f"member {name!r} claims an array of shape {tuple(shape)} ({claimed} bytes) but holds "
                            f"{member.file_size - header} bytes")
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError) as err:
        return f"not a readable .npz archive ({type(err).__name__}: {err})"
    return None


def json_depth_problem(value, limit: int = MAX_JSON_DEPTH) -> str | None:
    """None if the parsed JSON `value` is nested at most `limit` deep, else the line that
    says it is not (counted without recursion)."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            if depth > limit:
                return f"JSON nested deeper than {limit} levels"
            stack.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return None
