"""The artifact contract: frozen dataclasses with declared arrays (dtype, dims, units), validated, stored as zarr v3
groups. The types themselves are in :mod:`eventcap.artifacts` (with the library's own, :class:`eventcap.camera.Camera`
and :class:`eventcap.body.template.Template`, which derive from :class:`Artifact` here: this module sits below them
and imports nothing of eventcap but :mod:`eventcap.memo`).

An artifact type is declared once::

    @dataclass(frozen=True)
    class FrameStack(Artifact):
        schema_version: ClassVar[int] = 1
        images: np.ndarray = array("uint8", ("n", "height", "width"), units="DN")
        t_us: np.ndarray = array("int64", ("n",), units="us")
        height: int = attr(units="px")
        width: int = attr(units="px")

Dimension names are checked for consistency across all arrays of the instance, and a dimension named after an int
attribute (``height`` above) must equal it. Arrays are made read-only. Fields whose annotation is another Artifact
type are stored as sub-groups. Errors show the artifact, the field, what was expected and what was given.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from eventcap.memo import ProcessCache
from eventcap.processes import available_memory_bytes


class ArtifactError(ValueError):
    """An artifact does not match its declared schema."""


@dataclass(frozen=True)
class ArraySpec:
    """What an array field must look like."""

    dtype: np.dtype
    dims: tuple[str | int, ...]
    units: str = ""
    doc: str = ""
    optional: bool = False

    def describe(self) -> str:
        dims = ", ".join(str(d) for d in self.dims)
        return f"{_dtype_str(self.dtype)}[{dims}]" + (f" ({self.units})" if self.units else "")


@dataclass(frozen=True)
class AttrSpec:
    """A scalar or JSON-like field stored in the group's attributes."""

    units: str = ""
    doc: str = ""


def array(dtype, dims, *, units: str = "", doc: str = "", optional: bool = False, default_factory=None):
    """Declare an array field: numpy dtype, dimension names (str) or fixed sizes (int), units."""
    spec = ArraySpec(np.dtype(dtype), tuple(dims), units, doc, optional)
    if optional:
        return field(default=None, metadata={"array": spec})
    if default_factory is not None:
        return field(default_factory=default_factory, metadata={"array": spec})
    return field(metadata={"array": spec})


def attr(default: Any = dataclasses.MISSING, *, units: str = "", doc: str = "", default_factory: Any = None):
    """Declare a scalar/JSON attribute field (int, float, str, bool, list, dict)."""
    if default_factory is not None:
        return field(default_factory=default_factory, metadata={"attr": AttrSpec(units, doc)})
    return field(default=default, metadata={"attr": AttrSpec(units, doc)})


def _dtype_str(dt: np.dtype) -> str:
    if dt.names:
        return "{" + ", ".join(f"{n}: {dt.fields[n][0].str}" for n in dt.names) + "}"
    return dt.str


#: the resolved type hints of each artifact class
_TYPE_HINTS = ProcessCache("artifact.type_hints")


def _hints(cls) -> dict[str, Any]:
    return _TYPE_HINTS.get(cls, lambda: typing.get_type_hints(cls))[0]


def _child_type(hint) -> type[Artifact] | None:
    """The Artifact class of a field annotated ``SomeArtifact`` or ``SomeArtifact | None``."""
    candidates = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, _UnionType) else (hint,)
    for c in candidates:
        if isinstance(c, type) and issubclass(c, Artifact):
            return c
    return None


_UnionType = type(int | None)


@dataclass(frozen=True, eq=False)
class Artifact:
    """Base of every artifact type. Subclasses are frozen dataclasses declaring fields with array()/attr()."""

    schema_version: ClassVar[int] = 1
    #: Dimensions whose rows follow time (always an array's first axis), each with the array that holds their times
    #: in µs, increasing (``"events.t"``: column ``t`` of the structured array ``events``): a windowed read
    #: (:meth:`from_zarr` with ``window``) keeps only the rows with t0 <= t <= t1 and reads no other rows from disk.
    time_dims: ClassVar[dict[str, str]] = {}
    #: For a windowed read: a child's time dimension whose own time array is absent (an optional array left out)
    #: takes the rows a sibling kept: ``{child: {dim: (sibling, sibling's dim)}}`` (ground truth at the frames).
    window_links: ClassVar[dict[str, dict[str, tuple[str, str]]]] = {}

    # -- schema -----------------------------------------------------------------------------------------------
    @classmethod
    def array_fields(cls) -> dict[str, ArraySpec]:
        return {f.name: f.metadata["array"] for f in dataclasses.fields(cls) if "array" in f.metadata}

    @classmethod
    def attr_fields(cls) -> dict[str, AttrSpec]:
        return {f.name: f.metadata["attr"] for f in dataclasses.fields(cls) if "attr" in f.metadata}

    @classmethod
    def child_fields(cls) -> dict[str, tuple[type[Artifact], bool]]:
        """Sub-artifact fields: name -> (type, optional)."""
        out = {}
        hints = _hints(cls)
        for f in dataclasses.fields(cls):
            if "array" in f.metadata or "attr" in f.metadata:
                continue
            child = _child_type(hints[f.name])
            if child is None:
                raise TypeError(
                    f"{cls.__name__}.{f.name}: every artifact field must be declared with array(), attr() "
                    f"or annotated with an Artifact type"
                )
            out[f.name] = (child, f.default is None)
        return out

    @classmethod
    def type_name(cls) -> str:
        return cls.__name__

    @classmethod
    def schema_signature(cls) -> str:
        """Type and schema version, including those of sub-artifacts: ``Recording:1(camera=Camera:1,...)``."""
        children = ",".join(f"{n}={t.schema_signature()}" for n, (t, _) in sorted(cls.child_fields().items()))
        return f"{cls.type_name()}:{cls.schema_version}" + (f"({children})" if children else "")

    @classmethod
    def describe_schema(cls) -> str:
        lines = [f"{cls.__name__} (schema v{cls.schema_version})"]
        lines += [f"  {n}: {s.describe()}" for n, s in cls.array_fields().items()]
        lines += [f"  {n}: attr" + (f" ({s.units})" if s.units else "") for n, s in cls.attr_fields().items()]
        lines += [f"  {n}: {t.__name__}" + (" | None" if o else "") for n, (t, o) in cls.child_fields().items()]
        return "\n".join(lines)

    # -- validation ---------------------------------------------------------------------------------------------
    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Check every declared field; raise ArtifactError showing expected vs. actual."""
        cls = type(self)
        name = cls.__name__
        sizes: dict[str, tuple[int, str]] = {}
        attrs = cls.attr_fields()
        for fname in attrs:
            v = getattr(self, fname)
            if isinstance(v, (np.integer, np.floating, np.bool_)):
                object.__setattr__(self, fname, v.item())
        for fname, spec in cls.array_fields().items():
            value = getattr(self, fname)
            if value is None:
                if spec.optional:
                    continue
                raise ArtifactError(f"{name}.{fname}: expected {spec.describe()}, got None")
            if not isinstance(value, np.ndarray):
                raise ArtifactError(f"{name}.{fname}: expected a numpy array {spec.describe()}, got {type(value).__name__}")
            if value.dtype != spec.dtype:
                raise ArtifactError(
                    f"{name}.{fname}: expected dtype {_dtype_str(spec.dtype)}, got {_dtype_str(value.dtype)}"
                )
            if value.ndim != len(spec.dims):
                raise ArtifactError(
                    f"{name}.{fname}: expected {len(spec.dims)} dims {spec.dims}, got shape {value.shape}"
                )
            for axis, (dim, size) in enumerate(zip(spec.dims, value.shape)):
                if isinstance(dim, int):
                    if size != dim:
                        raise ArtifactError(
                            f"{name}.{fname}: axis {axis} must have size {dim}, got shape {value.shape}"
                        )
                    continue
                if dim in attrs and isinstance(getattr(self, dim), int) and getattr(self, dim) != size:
                    raise ArtifactError(
                        f"{name}.{fname}: axis {axis} ('{dim}') must equal {name}.{dim} = {getattr(self, dim)}, "
                        f"got shape {value.shape}"
                    )
                if dim in sizes and sizes[dim][0] != size:
                    other_size, other_field = sizes[dim]
                    raise ArtifactError(
                        f"{name}.{fname}: dim '{dim}' is {other_size} in {other_field} but {size} here "
                        f"(shape {value.shape})"
                    )
                sizes.setdefault(dim, (size, fname))
            if spec.dtype.kind == "f" and value.size and not np.isfinite(value).all() and "nan" not in spec.units:
                # NaN/inf are never silently accepted unless a field declares it may hold them (units mention nan).
                bad = np.argwhere(~np.isfinite(value))[0]
                raise ArtifactError(f"{name}.{fname}: non-finite value at index {tuple(int(i) for i in bad)}")
            if value.flags.writeable:
                ro = value.view()
                ro.flags.writeable = False
                object.__setattr__(self, fname, ro)
        for fname, (ctype, optional) in cls.child_fields().items():
            value = getattr(self, fname)
            if value is None and optional:
                continue
            if not isinstance(value, ctype):
                raise ArtifactError(f"{name}.{fname}: expected {ctype.__name__}, got {type(value).__name__}")

    # -- zarr I/O -----------------------------------------------------------------------------------------------
    def to_zarr(self, group) -> None:
        """Write this artifact into an (empty) zarr v3 group; validates first."""
        self.validate()
        group.attrs.update(self._group_attrs())
        self._write_members(group)

    def write_zarr(self, parent, name: str):
        """Write this artifact as the new group ``name`` of a zarr group (its attributes written with the group: one
        metadata write, not two; otherwise :meth:`to_zarr`); validates first. Returns the group."""
        self.validate()
        group = parent.create_group(name, attributes=self._group_attrs())
        self._write_members(group)
        return group

    def _group_attrs(self) -> dict[str, Any]:
        cls = type(self)
        return {"artifact": cls.type_name(), "schema_version": cls.schema_version, "attrs": self._attr_values()}

    def _write_members(self, group) -> None:
        """The arrays and the child artifacts into the artifact's group."""
        cls = type(self)
        for fname, spec in cls.array_fields().items():
            value = getattr(self, fname)
            if value is None:
                continue
            if spec.dtype.names:
                sub = group.create_group(fname, attributes={
                    "structured": [[n, spec.dtype.fields[n][0].str] for n in spec.dtype.names]})
                for n in spec.dtype.names:
                    _write_array(sub, n, np.ascontiguousarray(value[n]), spec.units)
            else:
                _write_array(group, fname, value, spec.units)
        for fname in cls.child_fields():
            value = getattr(self, fname)
            if value is not None:
                value.write_zarr(group, fname)

    def _attr_values(self) -> dict[str, Any]:
        return {n: _jsonable(getattr(self, n)) for n in type(self).attr_fields()}

    @classmethod
    def from_zarr(cls, group, where: str = "", window: tuple[int, int] | None = None, without: tuple[str, ...] = ()):
        """Read and validate an artifact of this type from a zarr group written by to_zarr.

        ``window=(t0_us, t1_us)``: only the rows of its time dimensions (:attr:`time_dims`, its children's too)
        with t0 <= t <= t1, read from disk without the others (the recording of one chunk of a long capture);
        ``without``: optional fields of a windowed read left out (None), not read."""
        where = where or str(getattr(group, "store_path", "zarr group"))
        if window is None and without:
            raise ValueError(f"{where}: without={without!r} applies to a windowed read only")
        if window is not None:  # many windows of one entry: its groups and arrays opened once
            group = _OPENED.get(where, lambda: _OpenedGroup(group))[0]
        return cls._read(group, where, window, {}, frozenset(without))[0]

    @classmethod
    def has_time_dims(cls) -> bool:
        """Whether a windowed read can leave rows of this type (or of a child) out: its arrays grow with the
        capture."""
        return bool(cls.time_dims) or any(t.has_time_dims() for t, _ in cls.child_fields().values())

    @classmethod
    def _read(cls, group, where: str, window, given: dict[str, slice], without: frozenset[str] = frozenset()):
        """(the artifact, the rows kept of each time dimension). ``given``: rows of dimensions whose own time array
        is absent, from the parent (:attr:`window_links`); ``without``: optional fields left out."""
        meta = dict(group.attrs)
        if meta.get("artifact") != cls.type_name():
            raise ArtifactError(f"{where}: expected a {cls.type_name()} artifact, found {meta.get('artifact')!r}")
        if meta.get("schema_version") != cls.schema_version:
            raise ArtifactError(
                f"{where}: {cls.type_name()} schema version {meta.get('schema_version')} on disk, "
                f"this code reads version {cls.schema_version}"
            )
        kwargs: dict[str, Any] = dict(meta.get("attrs", {}))
        members = set(group.keys())
        rows = cls._window_rows(group, where, window, given) if window is not None else {}
        fields = cls.array_fields()
        for fname, spec in fields.items():
            if fname not in members or fname in without:
                if spec.optional:
                    kwargs[fname] = None
                    continue
                raise ArtifactError(f"{where}: array '{fname}' missing (expected {spec.describe()})")
            sel = rows.get(spec.dims[0]) if spec.dims else None
            if spec.dtype.names:
                sub = group[fname]
                n = None
                cols = {}
                for col in spec.dtype.names:
                    if col not in sub:
                        raise ArtifactError(f"{where}/{fname}: column '{col}' missing")
                    cols[col] = read_array(sub[col], f"{where}/{fname}/{col}", sel)
                    n = cols[col].shape[0]
                out = np.empty(n or 0, dtype=spec.dtype)
                for col, values in cols.items():
                    out[col] = values
                kwargs[fname] = out
            else:
                kwargs[fname] = read_array(group[fname], f"{where}/{fname}", sel)
        kept: dict[str, dict[str, slice]] = {}
        for fname, (ctype, _optional) in cls.child_fields().items():
            if fname not in members or fname in without:
                kwargs[fname] = None
                continue
            at = f"{where}/{fname}"
            if window is not None and not ctype.has_time_dims():  # the same in every window: read once
                kwargs[fname], kept[fname] = _WINDOW_STATIC.get((at, ctype), lambda c=ctype, f=fname, a=at: c._read(
                    group[f], a, None, {})[0])[0], {}
                continue
            links = {d: kept[s][sd] for d, (s, sd) in cls.window_links.get(fname, {}).items()
                     if sd in kept.get(s, {})}
            kwargs[fname], kept[fname] = ctype._read(group[fname], at, window, links)
        for fname, value in list(kwargs.items()):
            if isinstance(value, list):
                kwargs[fname] = _tuplify(value)
        try:
            return cls(**kwargs), rows
        except TypeError as exc:
            raise ArtifactError(f"{where}: cannot build {cls.type_name()}: {exc}") from exc
        except ArtifactError as exc:  # a value check: say which group on disk holds the bad value
            raise ArtifactError(f"{where}: {exc}") from exc

    @classmethod
    def _window_rows(cls, group, where: str, window: tuple[int, int], given: dict[str, slice]) -> dict[str, slice]:
        """The rows of each time dimension with t0 <= t <= t1 (``given`` for a dimension without its own times)."""
        t0, t1 = int(window[0]), int(window[1])
        rows = {}
        for dim, field_name in cls.time_dims.items():
            name, _, col = field_name.partition(".")
            if name in group and (not col or col in group[name]):
                arr = group[name][col] if col else group[name]
                rows[dim] = rows_between(arr, f"{where}/{field_name.replace('.', '/')}", t0, t1)
            elif dim in given:
                rows[dim] = given[dim]
        return rows

    # -- comparison helpers -------------------------------------------------------------------------------------
    def equals(self, other: Artifact) -> bool:
        """Exact equality of every field (arrays compared element-wise, NaNs equal)."""
        if type(self) is not type(other):
            return False
        for fname in type(self).array_fields():
            a, b = getattr(self, fname), getattr(other, fname)
            if (a is None) != (b is None):
                return False
            if a is not None and not (a.shape == b.shape and _array_equal(a, b)):
                return False
        if self._attr_values() != other._attr_values():
            return False
        for fname in type(self).child_fields():
            a, b = getattr(self, fname), getattr(other, fname)
            if (a is None) != (b is None) or (a is not None and not a.equals(b)):
                return False
        return True


def _array_equal(a: np.ndarray, b: np.ndarray) -> bool:
    if a.dtype.names:
        return all(_array_equal(a[n], b[n]) for n in a.dtype.names)
    return bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))


def _tuplify(v):
    return tuple(_tuplify(x) for x in v) if isinstance(v, list) else v


def _jsonable(v):
    if isinstance(v, (tuple, list)):
        return [_jsonable(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (np.integer, np.floating, np.bool_)):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return repr(v)
    return v


#: Target size of one chunk; small enough that a batch's arrays are a handful of files.
_CHUNK_BYTES = 4 << 20


def read_array(arr, where: str, rows: slice | None = None) -> np.ndarray:
    """All of zarr array ``arr`` (``where`` names it in messages), or the ``rows`` of its first axis. A chunk that
    cannot be decoded (damaged compressed data) or whose file is missing raises an ArtifactError naming the chunk's
    file, the array and the rows it holds, instead of the codec's bare message or, for a missing chunk, fill values
    read back silently (:meth:`Artifact.to_zarr` writes every chunk, so a missing one is damage)."""
    _check_declared(arr, where)
    try:
        values = np.asarray(arr[...] if rows is None else arr[rows])
    except Exception as exc:  # noqa: BLE001 - numcodecs raises RuntimeError/ValueError/...; named below
        raise ArtifactError(_bad_chunk_message(arr, where, exc)) from exc
    if rows is None and arr.nchunks_initialized < arr.nchunks:  # rows: _check_declared counted the chunk files
        raise ArtifactError(_bad_chunk_message(arr, where, None))
    return values


#: The children without time dimensions of artifacts read by windows (a recording's camera and template), by their
#: group's path: the same in every window of a committed entry, read once per process.
_WINDOW_STATIC = ProcessCache("artifact.window_static", maxsize=8)

#: The first value of each chunk of the time arrays read by windows, by the array's folder and shape: a window finds
#: its rows by reading the one or two chunks that hold its ends, never the whole array.
_CHUNK_STARTS = ProcessCache("artifact.chunk_starts", maxsize=64)


class _OpenedGroup:
    """A zarr group as windowed reads see it: its attributes, member names and members (arrays, groups) read once,
    when first asked for. Every open of a zarr node is a round trip through zarr's event loop; a window of a
    recording reads about twenty arrays."""

    def __init__(self, group):
        self._group = group
        self.attrs = dict(group.attrs)
        self._names = set(group.keys())
        self._members: dict[str, Any] = {}

    def keys(self):
        return self._names

    def __contains__(self, name: str) -> bool:
        return name in self._names

    def __getitem__(self, name: str):
        if name not in self._members:
            m = self._group[name]
            self._members[name] = m if hasattr(m, "dtype") else _OpenedGroup(m)
        return self._members[name]


#: The zarr groups read by windows, opened, by their path (:class:`_OpenedGroup`).
_OPENED = ProcessCache("artifact.window_groups", maxsize=16)


def forget_windows() -> None:
    """Forget what windowed reads keep per process (the groups opened, the chunks' first values, the children read
    once): files on disk may have changed between runs."""
    _OPENED.clear()
    _WINDOW_STATIC.clear()
    _CHUNK_STARTS.clear()


def rows_between(arr, where: str, t0: int, t1: int) -> slice:
    """The rows of zarr array ``arr`` (1-D, increasing times) with t0 <= t <= t1, as a slice. A short array is read
    whole; a long one reads the first value of each chunk once per process, then only the chunks at the ends."""
    n = int(arr.shape[0]) if arr.shape else 0
    if arr.ndim != 1:
        raise ArtifactError(f"{where}: a time array must have one axis, got shape {tuple(arr.shape)}")
    if n == 0:
        return slice(0, 0)
    c = int(arr.chunks[0])
    if n <= c:
        t = read_array(arr, where)
        return slice(int(np.searchsorted(t, t0, side="left")), int(np.searchsorted(t, t1, side="right")))
    folder = _array_folder(arr)
    key = (str(folder) if folder is not None else where, n, c)
    def first_values() -> np.ndarray:
        _check_declared(arr, where)  # once: every chunk file is there (a missing one would read as fill values)
        try:
            return np.array([arr[i] for i in range(0, n, c)])
        except Exception as exc:  # noqa: BLE001 - named as read_array does
            raise ArtifactError(_bad_chunk_message(arr, where, exc)) from exc

    starts = _CHUNK_STARTS.get(key, first_values)[0]

    def find(t: int, side: str) -> int:
        k = max(int(np.searchsorted(starts, t, side=side)) - 1, 0)  # the chunk whose values may hold t
        part = read_array(arr, where, slice(k * c, min((k + 1) * c, n)))
        return k * c + int(np.searchsorted(part, t, side=side))

    a, b = find(t0, "left"), find(t1, "right")
    return slice(a, max(a, b))


def _array_folder(arr):
    """The folder of a zarr array on a local disk (None for other stores)."""
    from pathlib import Path

    store_path = getattr(arr, "store_path", None)
    root = getattr(getattr(store_path, "store", None), "root", None)
    if root is None:
        return None
    return Path(str(root)) / str(store_path.path)


def _check_declared(arr, where: str) -> None:
    """Refuse, before anything is allocated, an array whose metadata declares more than its chunk files can hold:
    a chunk layout this tool never writes (chunked along the first axis only, at most about _CHUNK_BYTES a chunk),
    fewer chunk files than its shape needs, or more bytes than half the available memory. A corrupted
    ``zarr.json`` can declare a shape of 1e15 (issue 57: a MemoryError traceback)."""
    shape, chunks, itemsize = tuple(arr.shape), tuple(arr.chunks), int(arr.dtype.itemsize)
    folder = _array_folder(arr)
    at = where if folder is None else f"{where} ({folder / 'zarr.json'})"
    if not shape:
        return
    row = max(1, itemsize * math.prod(shape[1:]))
    if tuple(chunks[1:]) != shape[1:] or not 1 <= chunks[0] <= max(1, _CHUNK_BYTES // row):
        raise ArtifactError(f"{at}: declares chunks {chunks} for shape {shape} ({arr.dtype}): not a layout eventcap "
                            f"writes (chunks along the first axis of at most {_CHUNK_BYTES >> 20} MiB): a corrupted "
                            f"or foreign zarr.json")
    nchunks = math.prod(-(-n // c) for n, c in zip(shape, chunks)) if all(shape) else 0
    nbytes = math.prod(shape) * itemsize
    if folder is not None and nchunks:
        files = sum(len([f for f in names if f != "zarr.json"]) for _, _, names in _walk(folder, nchunks + 1))
        if files < nchunks <= 1_000_000:  # a few missing: say which chunk, and the rows it holds
            raise ArtifactError(_bad_chunk_message(arr, where, None))
        if files < nchunks:
            raise ArtifactError(f"{at}: declares shape {shape} of {arr.dtype} ({nbytes:,} bytes) in {nchunks:,} chunk "
                                f"files, and the folder holds {files:,}: a corrupted shape, or chunk files missing "
                                f"(they would read back as fill values)")
    avail = available_memory_bytes()
    if avail is not None and nbytes > avail // 2:
        raise ArtifactError(f"{at}: declares shape {shape} of {arr.dtype}: {nbytes / 1e9:.3g} GB, more than half the "
                            f"available memory ({avail / 1e9:.3g} GB): refused before reading")


def _walk(folder, limit: int):
    """os.walk of ``folder``, stopping once more than ``limit`` files were seen (a damaged array can have many)."""
    import os

    seen = 0
    for entry in os.walk(folder):
        yield entry
        seen += len(entry[2])
        if seen > limit:
            return


def _chunk_file(arr, coords: tuple[int, ...], where: str) -> str:
    key = arr.metadata.encode_chunk_key(coords)
    root = getattr(arr.store_path.store, "root", None)
    return f"{root}/{arr.store_path.path}/{key}" if root is not None else f"{where}/{key}"


def _bad_chunk_message(arr, where: str, exc: BaseException | None) -> str:
    """Find the first chunk of ``arr`` that is missing (``exc`` None) or cannot be read, and say where it is."""
    import itertools

    grid = [range(math.ceil(n / c)) for n, c in zip(arr.shape, arr.chunks)]
    rows_total = arr.shape[0] if arr.shape else 1
    for coords in itertools.product(*grid):
        sel = tuple(slice(i * c, min((i + 1) * c, n)) for i, c, n in zip(coords, arr.chunks, arr.shape))
        rows = f"rows {sel[0].start}..{sel[0].stop - 1} of {rows_total}" if sel else "the only chunk"
        path = _chunk_file(arr, coords, where)
        if exc is None:
            import os

            if not os.path.exists(path) and "://" not in path:
                return (f"{path}: chunk file missing: array {where} ({arr.dtype}, shape {arr.shape}), chunk "
                        f"{coords} holding {rows}; the recording or entry is incomplete (copied in part?)")
            continue
        try:
            arr[sel]
        except Exception as chunk_exc:  # noqa: BLE001
            return (f"{path}: cannot decode chunk {coords} of array {where} ({arr.dtype}, shape {arr.shape}), "
                    f"{rows}: {type(chunk_exc).__name__}: {chunk_exc}; the file is damaged (copy or convert it "
                    f"again)")
    if exc is None:
        return f"{where}: {arr.nchunks - arr.nchunks_initialized} of {arr.nchunks} chunk files are missing"
    return f"{where}: cannot read array ({arr.dtype}, shape {arr.shape}): {type(exc).__name__}: {exc}"


def _chunks_for(shape: tuple[int, ...], itemsize: int) -> tuple[int, ...]:
    if not shape:
        return ()
    row = max(1, itemsize * math.prod(shape[1:]))
    first = max(1, min(shape[0], _CHUNK_BYTES // row))
    return (first, *shape[1:]) if shape[0] else (1, *shape[1:])


def _write_array(group, name: str, value: np.ndarray, units: str) -> None:
    value = np.ascontiguousarray(value)
    # One call writes the metadata, the attribute and the data (creating, then filling, then adding the attribute took
    # three metadata round trips: ~10 ms of CPU per array against ~6, and a run writes hundreds of small arrays).
    group.create_array(
        name,
        data=value,
        chunks=_chunks_for(value.shape, value.dtype.itemsize),
        attributes={"units": units},
        # Every chunk is written, so a chunk file missing on disk is corruption, never "all fill values".
        config={"write_empty_chunks": True},
    )


class ArrayAppender:
    """Writes one array of an artifact's zarr group in pieces along its first axis, with the layout
    :meth:`Artifact.to_zarr` gives the whole array (same chunks, empty chunks written, ``units`` attribute).

    For streams too large to hold in memory (a converted recording's event columns). The chunk length of the
    whole-array layout is ``min(rows, full)``: rows are held back until ``full`` of them have arrived (or
    :meth:`close` writes a shorter array exactly as ``to_zarr`` would); after that, only whole chunks are appended,
    so each chunk file is written once and memory stays below about two chunks (4 MiB each) plus one piece.
    """

    def __init__(self, group, name: str, dtype, row_shape: tuple[int, ...] = (), units: str = ""):
        self.group, self.name, self.units = group, name, units
        self.dtype = np.dtype(dtype)
        self.row_shape = tuple(int(s) for s in row_shape)
        # The chunk length of an array longer than one chunk (any longer array gets the same one).
        self.full = _chunks_for((1 << 62, *self.row_shape), self.dtype.itemsize)[0]
        self.rows = 0
        self._pending: list[np.ndarray] = []
        self._pending_rows = 0
        self._array = None

    def append(self, values: np.ndarray) -> None:
        """Add rows: an array of this dtype shaped ``(n, *row_shape)``."""
        values = np.asarray(values)
        if values.dtype != self.dtype or values.shape[1:] != self.row_shape:
            raise ValueError(f"{self.name}: expected rows of dtype {self.dtype} and shape {self.row_shape}, got "
                             f"{values.dtype} {values.shape}")
        if not len(values):
            return
        self._pending.append(values)
        self._pending_rows += len(values)
        self.rows += len(values)
        if self._pending_rows >= self.full:
            self._flush(whole_chunks_only=True)

    def close(self) -> int:
        """Write what is held back; returns the array's length."""
        if self._array is None:
            _write_array(self.group, self.name, self._take(self._pending_rows), self.units)
        else:
            self._flush(whole_chunks_only=False)
        return self.rows

    def _take(self, n: int) -> np.ndarray:
        if not self._pending:
            data = np.empty((0, *self.row_shape), self.dtype)
        else:
            data = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
        head, rest = data[:n], data[n:]
        self._pending = [rest] if len(rest) else []
        self._pending_rows = len(rest)
        return np.ascontiguousarray(head)

    def _flush(self, whole_chunks_only: bool) -> None:
        n = self._pending_rows - self._pending_rows % self.full if whole_chunks_only else self._pending_rows
        if self._array is None:
            self._array = self.group.create_array(
                self.name, shape=(0, *self.row_shape), dtype=self.dtype, chunks=(self.full, *self.row_shape),
                config={"write_empty_chunks": True},
            )
            self._array.attrs["units"] = self.units
        if n:
            self._array.append(self._take(n))
