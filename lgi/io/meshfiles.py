"""Checks of PLY, STL and OFF mesh files before a library reads them.

pymeshlab, which reads these formats for ``lgi compare``, drops vertices whose coordinates are not finite (with
their faces) without a word, and allocates what a header declares before it reads a byte of the body (a PLY
header declaring 2^31 - 1 vertices ends in ``std::bad_alloc``). :func:`check_mesh_file` reads the file in bounded
blocks first and refuses, naming the file and the vertex, what would be dropped or cannot be there.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from lgi.errors import InputError, cell_text

#: Bytes read at a time: the checks' memory, whatever the file's size.
CHUNK = 1 << 24
#: The longest header read (a PLY or OFF header is a few lines).
HEADER_BYTES = 1 << 16

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
# What a finite number in a text mesh is written with; a letter other than an exponent's (nan, inf, 1.#IND) is not.
_NOT_NUMERIC = re.compile(rb"[^0-9.eE+\-\s]")


def check_mesh_file(path: str | os.PathLike[str]) -> None:
    """Refuse a PLY, STL or OFF file whose vertex coordinates are not all finite numbers, or whose header
    declares more than its body can hold.

    Parameters
    ----------
    path : path of a ``.ply``, ``.stl`` or ``.off`` file (other suffixes are not checked)

    Raises
    ------
    InputError
        Naming the file, and the line (text formats) or the vertex (binary ones) at fault.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        _check_ply(path)
    elif suffix == ".stl":
        _check_stl(path)
    elif suffix == ".off":
        _check_off(path)


def _header_lines(path: Path, end: bytes) -> tuple[list[str], int]:
    """The lines of a text header up to and including the line ``end`` and the body's offset."""
    with open(path, "rb") as f:
        head = f.read(HEADER_BYTES)
    lines, pos = [], 0
    while True:
        nl = head.find(b"\n", pos)
        if nl < 0:
            raise InputError(f"no {end.decode()!r} line in the first {HEADER_BYTES} bytes: not a complete header",
                             path=path)
        line = head[pos:nl].rstrip(b"\r")
        lines.append(line.decode("latin-1"))
        pos = nl + 1
        if line.strip() == end:
            return lines, pos


def _check_ply(path: Path) -> None:
    lines, body = _header_lines(path, b"end_header")
    if not lines or lines[0].strip() != "ply":
        raise InputError("not a PLY file (its first line is not 'ply')", path=path, line=1)
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str | None, str]], int]] = []  # name, count, props, line
    for i, line in enumerate(lines[1:-1], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                count = int(words[2])
            except ValueError:
                count = -1
            if count < 0:
                raise InputError(f"element {words[1]!r} has no valid count ({words[2]!r})", path=path, line=i)
            elements.append((words[1], count, [], i))
        elif words[0] == "property" and elements:
            if len(words) == 5 and words[1] == "list":
                kind = (_PLY_TYPES.get(words[2]), _PLY_TYPES.get(words[3]))
                if None in kind:
                    raise InputError(f"unknown property type in {line.strip()!r}", path=path, line=i)
                elements[-1][2].append(("list", kind[0], kind[1]))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], None, _PLY_TYPES[words[1]]))
            else:
                raise InputError(f"unknown property {line.strip()!r}", path=path, line=i)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format {fmt!r}", path=path)
    size = path.stat().st_size - body
    # The least each element's rows take: text, a character and a separator per value; binary, their bytes.
    least = 0
    for _, count, props, _ in elements:
        per = sum(2 if fmt == "ascii" else np.dtype(p[1] if p[0] == "list" else p[2]).itemsize for p in props)
        least += count * per
    if least > size:
        name, count, _, line = max(elements, key=lambda e: e[1])
        raise InputError(f"the header declares {count:,} {name} rows (at least {least:,} bytes), but the body has "
                         f"{size:,} bytes", path=path, line=line)
    offset = body
    for name, count, props, _ in elements:
        if name == "vertex":
            axes = [p[0] for p in props if p[0] in ("x", "y", "z")]
            if fmt == "ascii":
                _check_text_rows(path, offset, count, len(lines) + 1)
            elif any(p[0] == "list" for p in props):
                return  # vertices with list properties: rows of varying size (never seen in a scan)
            else:
                order = "<" if fmt == "binary_little_endian" else ">"
                dtype = np.dtype([(p[0], order + p[2]) for p in props])
                _check_binary_rows(path, offset, count, dtype, axes)
            return
        if fmt == "ascii" or any(p[0] == "list" for p in props):
            return  # the vertices come after rows of unknown size: pymeshlab's own reading is the check
        offset += count * sum(np.dtype(p[2]).itemsize for p in props)


def _check_binary_rows(path: Path, offset: int, count: int, dtype: np.dtype, axes: list[str]) -> None:
    rows = max(1, CHUNK // max(1, dtype.itemsize))
    with open(path, "rb") as f:
        f.seek(offset)
        for lo in range(0, count, rows):
            n = min(rows, count - lo)
            block = np.frombuffer(f.read(n * dtype.itemsize), dtype, count=n)
            for a in axes:
                bad = np.flatnonzero(~np.isfinite(block[a].astype(np.float64)))
                if bad.size:
                    raise InputError(f"vertex {lo + int(bad[0])} (0-based) has a non-finite {a} "
                                     f"({float(block[a][bad[0]])})", path=path)


def _check_text_rows(path: Path, offset: int, count: int, first_line: int, comments: bool = False) -> None:
    """The ``count`` vertex lines from byte ``offset`` (line ``first_line``) hold numbers only (with
    ``comments``, lines that start with ``#`` aside)."""
    done = 0
    carry = b""
    with open(path, "rb") as f:
        f.seek(offset)
        while done < count:
            chunk = f.read(CHUNK)
            if not chunk and not carry:
                return  # fewer rows than declared: the reader names that
            data = carry + chunk
            cut = data.rfind(b"\n") + 1 if chunk else len(data)
            if cut == 0:
                carry = data
                continue
            part, carry = data[:cut], data[cut:]
            ends = np.flatnonzero(np.frombuffer(part, np.uint8) == 10)
            stop = len(part) if len(ends) < count - done else int(ends[count - done - 1]) + 1
            m = next((m for m in _NOT_NUMERIC.finditer(part, 0, stop)
                      if not (comments and part[part.rfind(b"\n", 0, m.start()) + 1:m.start() + 1].lstrip()
                              .startswith(b"#"))), None)
            if m:
                line = first_line + done + part.count(b"\n", 0, m.start())
                start = part.rfind(b"\n", 0, m.start()) + 1
                end = part.find(b"\n", m.start())
                text = part[start:end if end >= 0 else len(part)].decode("latin-1").strip()
                raise InputError(f"a vertex row holds something that is not a finite number: {cell_text(text)}",
                                 path=path, line=line)
            done += len(ends) if chunk else count


def _check_stl(path: Path) -> None:
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(84)
    n = int.from_bytes(head[80:84], "little") if len(head) == 84 else -1
    if n >= 0 and size == 84 + 50 * n:
        dtype = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attribute", "<u2")])
        rows = CHUNK // dtype.itemsize
        with open(path, "rb") as f:
            f.seek(84)
            for lo in range(0, n, rows):
                k = min(rows, n - lo)
                v = np.frombuffer(f.read(k * dtype.itemsize), dtype, count=k)["v"]
                bad = np.flatnonzero(~np.all(np.isfinite(v), axis=(1, 2)))
                if bad.size:
                    raise InputError(f"triangle {lo + int(bad[0])} (0-based) has a non-finite vertex coordinate",
                                     path=path)
        return
    if not head.lstrip().lower().startswith(b"solid"):
        raise InputError(f"neither a binary STL ({n:,} triangles would be {84 + 50 * max(n, 0):,} bytes; the file "
                         f"has {size:,}) nor an ASCII one (it does not start with 'solid')", path=path)
    _check_stl_text(path)


_STL_VERTEX = re.compile(rb"^[ \t]*vertex[ \t]+([^\r\n]*)", re.M)


def _check_stl_text(path: Path) -> None:
    line0, carry = 1, b""
    with open(path, "rb") as f:
        while True:
            chunk = f.read(CHUNK)
            data = carry + chunk
            cut = data.rfind(b"\n") + 1 if chunk else len(data)
            part, carry = data[:cut], data[cut:]
            for m in _STL_VERTEX.finditer(part):
                if _NOT_NUMERIC.search(m.group(1)):
                    raise InputError(f"a vertex holds something that is not a finite number: "
                                     f"{cell_text(m.group(0).decode('latin-1').strip())}", path=path,
                                     line=line0 + part.count(b"\n", 0, m.start()))
            line0 += part.count(b"\n")
            if not chunk:
                return


def _check_off(path: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(HEADER_BYTES)
    lines = head.split(b"\n")
    # The keyword line (OFF, COFF, NOFF, ...; the counts may follow it on the same line), then the counts.
    words: list[bytes] = []
    line_no, pos = 0, 0
    for line_no, line in enumerate(lines[:-1], start=1):
        pos += len(line) + 1
        text = line.split(b"#")[0].split()
        if line_no == 1:
            if not text or not text[0].upper().endswith(b"OFF"):
                raise InputError("not an OFF file (its first line is not OFF)", path=path, line=1)
            text = text[1:]
        words.extend(text)
        if len(words) >= 3:
            break
    else:
        raise InputError("no vertex and face counts in the header", path=path)
    try:
        nv, nf = int(words[0]), int(words[1])
    except ValueError:
        raise InputError(f"the counts line is not numbers ({b' '.join(words[:3]).decode('latin-1')!r})",
                         path=path, line=line_no) from None
    size = path.stat().st_size - pos
    if nv < 0 or nf < 0 or 6 * nv + 8 * nf > size:
        raise InputError(f"the header declares {nv:,} vertices and {nf:,} faces, but the body has {size:,} bytes",
                         path=path, line=line_no)
    _check_text_rows(path, pos, nv, line_no + 1, comments=True)
