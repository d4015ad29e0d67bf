"""A small PLY reader and writer for point clouds (numpy only): the `vertex` element's properties by name.

Reads `ascii`, `binary_little_endian` and `binary_big_endian` files; writes binary little-endian (or
ASCII) atomically. Other elements (faces, ...) are skipped when reading. Every problem with a file raises
PLYError, whose message starts with the file's name.
"""
from __future__ import annotations

import os

import numpy as np

from stg_runtime.atomic import write_atomic

#: PLY scalar type names (both spellings) -> numpy dtype.
TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
#: numpy dtype -> the PLY type name a writer uses.
TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}
FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER = 1 << 20


class PLYError(ValueError):
    """A file that is not a readable PLY point cloud; the message starts with the file's name."""


def require(props: dict, names, path) -> None:
    """Raise PLYError naming `path` and every one of `names` missing from `props`."""
    missing = [n for n in names if n not in props]
    if missing:
        raise PLYError(f"{os.fsdecode(path)}: missing vertex properties: {', '.join(missing)}")


def float32_values(props: dict, names, path) -> dict[str, np.ndarray]:
    """{name: (N,) float64} of properties `names`, every value finite and within float32's range (what a
    model can store); PLYError naming `path` and the property otherwise."""
    limit = float(np.finfo(np.float32).max)
    out = {}
    for name in names:
        with np.errstate(invalid="ignore", over="ignore"):
            values = props[name].astype(np.float64)
        bad = np.count_nonzero(~(np.abs(values) <= limit))  # NaN, inf, and beyond float32
        if bad:
            raise PLYError(f"{os.fsdecode(path)}: property {name!r} has values that are not finite float32 "
                           f"numbers ({bad} of {values.size})")
        out[name] = values
    return out


def _parse_header(f, name: str) -> tuple[str, list]:
    """-> (format, [(element name, count, [(property, dtype) or (property, None) for lists])])."""
    first = f.readline(16)
    if first.rstrip(b"\r\n") != b"ply":
        raise PLYError(f"{name}: not a PLY file (it does not start with 'ply')")
    fmt, elements, size = None, [], len(first)
    while True:
        line = f.readline(MAX_HEADER)
        size += len(line)
        if not line:
            raise PLYError(f"{name}: truncated header (no 'end_header' line)")
        if size > MAX_HEADER:
            raise PLYError(f"{name}: header longer than {MAX_HEADER} bytes")
        try:
            words = line.decode("ascii").split()
        except UnicodeDecodeError:
            raise PLYError(f"{name}: header line {line[:40]!r} is not ASCII") from None
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            if len(words) != 3 or words[1] not in FORMATS:
                raise PLYError(f"{name}: unsupported format line {' '.join(words)!r} "
                               f"(expected one of {', '.join(FORMATS)})")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PLYError(f"{name}: bad element line {' '.join(words)!r} (expected 'element NAME COUNT')")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PLYError(f"{name}: property {' '.join(words[1:])!r} before any element")
            if len(words) == 5 and words[1] == "list":
                if words[2] not in TYPES or words[3] not in TYPES:
                    raise PLYError(f"{name}: unknown type in list property {words[4]!r}")
                elements[-1][2].append((words[4], None))
            elif len(words) == 3:
                if words[1] not in TYPES:
                    raise PLYError(f"{name}: property {words[2]!r} has unknown type {words[1]!r}")
                elements[-1][2].append((words[2], np.dtype(TYPES[words[1]])))
            else:
                raise PLYError(f"{name}: bad property line {' '.join(words)!r}")
        else:
            raise PLYError(f"{name}: unknown header line {' '.join(words)!r}")
    if fmt is None:
        raise PLYError(f"{name}: the header has no 'format' line")
    return fmt, elements


def read_ply(path) -> tuple[dict[str, np.ndarray], int]:
    """The vertex element of a PLY file: ({property name: (N,) array in its stored type}, N).

    Properties keep the file's order and type (float32, float64, uint8, int32, ...), in native byte
    order. Raises PLYError (naming the file) for a file that is not a PLY, has no vertex element, a
    list property in the vertex element, unknown types, duplicate names, or too little data for the
    declared count; OSError if it cannot be opened.
    """
    name = os.fsdecode(path)
    with open(path, "rb") as f:
        fmt, elements = _parse_header(f, name)
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise PLYError(f"{name}: no 'vertex' element (elements: {', '.join(names) or 'none'})")
        index = names.index("vertex")
        _, count, props = elements[index]
        lists = [p for p, dt in props if dt is None]
        if lists:
            raise PLYError(f"{name}: the vertex element has list properties ({', '.join(lists)}), "
                           "which a point cloud cannot hold")
        seen = [p for p, _ in props]
        if len(set(seen)) != len(seen):
            raise PLYError(f"{name}: duplicate vertex property names")
        if fmt == "ascii":
            columns = _read_ascii(f, name, elements[:index], count, props)
        else:
            columns = _read_binary(f, name, FORMATS[fmt], elements[:index], count, props)
    return columns, count


def _read_binary(f, name, order, before, count, props) -> dict[str, np.ndarray]:
    left = os.fstat(f.fileno()).st_size - f.tell()  # what the file holds after the header
    for elem, n, eprops in before:
        if any(dt is None for _, dt in eprops):
            raise PLYError(f"{name}: cannot skip element {elem!r} with list properties before 'vertex'")
        size = n * sum(dt.itemsize for _, dt in eprops)
        if size > left:
            raise PLYError(f"{name}: truncated: element {elem!r} declares {n} rows ({size} bytes), the file has "
                           f"{left} bytes after the header")
        f.seek(size, os.SEEK_CUR)
        left -= size
    row = np.dtype([(p, dt.newbyteorder(order)) for p, dt in props])
    want = count * row.itemsize
    if want > left:
        raise PLYError(f"{name}: truncated: {count} vertices need {want} bytes of vertex data, the file has {left}")
    data = f.read(want)
    if len(data) < want:
        raise PLYError(f"{name}: truncated: {count} vertices need {want} bytes of vertex data, "
                       f"the file has {len(data)}")
    table = np.frombuffer(data, row, count)
    return {p: np.ascontiguousarray(table[p], dtype=dt) for p, dt in props}


def _read_ascii(f, name, before, count, props) -> dict[str, np.ndarray]:
    skip = sum(n for _, n, _ in before)
    lines = [line for line in f.read().decode("ascii", "replace").splitlines() if line.strip()]
    rows = lines[skip:skip + count]
    if len(rows) < count:
        raise PLYError(f"{name}: truncated: {count} vertices declared, {len(rows)} vertex lines found")
    table = [r.split() for r in rows]
    for i, r in enumerate(table):
        if len(r) != len(props):
            raise PLYError(f"{name}: vertex {i} has {len(r)} values, the header declares {len(props)} properties")
    text = np.array(table, dtype=str).reshape(count, len(props))
    columns = {}
    for j, (p, dt) in enumerate(props):
        try:
            values = text[:, j].astype(np.float64)
            if dt.kind in "iu" and not np.all(values == np.round(values)):
                raise ValueError("not an integer")
            if dt.kind in "iu" and not np.all((values >= np.iinfo(dt).min) & (values <= np.iinfo(dt).max)):
                raise ValueError("out of range")
        except ValueError as e:
            raise PLYError(f"{name}: property {p!r} has a value that is not a {TYPE_NAMES[dt.str[1:]]} ({e})") from None
        with np.errstate(over="ignore"):  # a float beyond float32 is stored as inf, as a binary file holds it
            columns[p] = values.astype(dt)
    return columns


def write_ply(path, properties: dict[str, np.ndarray], fmt: str = "binary_little_endian",
              comments=()) -> None:
    """Write a PLY point cloud with one `vertex` element, atomically (temp file, fsync, rename).

    properties: name -> (N,) array, in file order. Float arrays are written as float32 unless they are
    float64 (kept); integer arrays of a PLY type (int8..uint32) keep their type; bool is written as
    uchar. fmt: "binary_little_endian" (default), "binary_big_endian" or "ascii". Raises ValueError for
    arrays of different lengths, non-1-D arrays, bad names or unsupported types.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown PLY format {fmt!r} (expected one of {', '.join(FORMATS)})")
    columns = {}
    for p, a in properties.items():
        if not p or any(c.isspace() for c in p) or not p.isascii():
            raise ValueError(f"bad PLY property name {p!r}")
        a = np.asarray(a)
        if a.ndim != 1:
            raise ValueError(f"property {p!r}: expected a 1-D array, got shape {a.shape}")
        if a.dtype == bool:
            a = a.astype(np.uint8)
        elif a.dtype.kind == "f" and a.dtype.itemsize != 8:
            a = a.astype(np.float32)
        if a.dtype.str[1:] not in TYPE_NAMES:
            raise ValueError(f"property {p!r}: dtype {a.dtype} has no PLY type")
        columns[p] = a
    counts = {a.shape[0] for a in columns.values()}
    if len(counts) > 1:
        raise ValueError(f"properties have different lengths: {sorted(counts)}")
    count = counts.pop() if counts else 0
    head = ["ply", f"format {fmt} 1.0", *(f"comment {c}" for c in comments), f"element vertex {count}"]
    head += [f"property {TYPE_NAMES[a.dtype.str[1:]]} {p}" for p, a in columns.items()]
    payload = ("\n".join(head) + "\nend_header\n").encode("ascii")
    if fmt == "ascii":
        rows = zip(*[a.tolist() for a in columns.values()]) if columns else []
        payload += "".join(" ".join(repr(v) if isinstance(v, float) else str(v) for v in r) + "\n"
                           for r in rows).encode("ascii")
    else:
        order = FORMATS[fmt]
        row = np.dtype([(p, a.dtype.newbyteorder(order)) for p, a in columns.items()])
        table = np.empty(count, row)
        for p, a in columns.items():
            table[p] = a
        payload += table.tobytes()
    write_atomic(path, payload)

